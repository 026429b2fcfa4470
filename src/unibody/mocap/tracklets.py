"""Tracklet labeling (paper 003 §4.5, SOMA's runtime): one label per hardware trajectory, or per span of it.

A passive optical system already links points over time into tracklets: columns of a
(T, N) sequence, visible in some frames. Per-frame labels are noisy; the sequence settles them.

:func:`settle_tracklets` (what :func:`~unibody.mocap.pipeline.label_sequence` uses) weighs the
labeler's per-point label probabilities (:func:`~unibody.mocap.labeler.frame_probabilities`):

1. **spans**: a column whose evidence changes over time (a tracker that joined two markers'
   trajectories, or a marker and a ghost) is cut where it changes (:func:`column_spans`: the
   label sequence with the most evidence less ``switch`` per change, by dynamic programming;
   a run of fewer than ``min_span`` visible frames joins its neighbour, and a run between two
   runs of one label joins them);
2. **evidence**: span s has E[s, l], the sum of label l's probability over its visible frames
   (null included: a span that is mostly ghost stays null);
3. **assignment**: in each frame, a minimum-cost matching (Hungarian,
   ``scipy.optimize.linear_sum_assignment``) of the visible spans to the labels, each span
   also free to be null, maximising the summed evidence; frames whose spans' best labels do
   not clash need no matching. Each span takes the label it got in most of its frames; where
   two spans of a frame still share a label, the one with more evidence for it keeps it and
   the other takes the frame's matching label if that is free, else null.

:func:`undecided_frames` says which unsure frames could still overturn a span's label (the
only ones :func:`~unibody.mocap.labeler.sequence_probabilities` orients again).

The body check (:func:`~unibody.mocap.relabel.relabel_tracklets`) adds the labels of a body
solved from these as more evidence, so it decides close calls.

:func:`label_tracklets` is the older **majority vote** per column over hard labels (a column
keeps its most frequent label; clashes go to the larger vote share). :func:`labelled_markers`
turns per-point labels into one column per marker.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment

from .._checks import check_shape

__all__ = [
    "TrackletConfig",
    "TrackletVotes",
    "column_spans",
    "label_tracklets",
    "labelled_markers",
    "settle_tracklets",
    "tracklet_labels",
    "tracklet_votes",
    "undecided_frames",
]


@dataclass(frozen=True, slots=True)
class TrackletVotes:
    """Majority vote of each column.

    Attributes:
        labels: (N,) int64, the winning label of each column (null for never-visible columns).
        share: (N,) float64 in [0, 1], the winner's votes / the column's visible frames (0 if never visible).
    """

    labels: torch.Tensor
    share: torch.Tensor


def check_frame_labels(
    frame_labels: torch.Tensor, visible: torch.Tensor, null: int, name: str = "frame_labels"
) -> None:
    """(T, N) integer labels in [0, null] wherever the (T, N) bool ``visible`` holds a point."""
    sizes: dict[str, int] = {}
    check_shape(frame_labels, "T N", name=name, sizes=sizes)
    check_shape(visible, "T N", name="visible", sizes=sizes)
    if visible.dtype != torch.bool:
        raise TypeError(f"visible: expected a bool tensor, got {visible.dtype}")
    if frame_labels.is_floating_point():
        raise TypeError(f"{name}: expected integer labels, got {frame_labels.dtype}")
    if bool(((frame_labels < 0) | (frame_labels > null))[visible].any()):
        raise ValueError(f"{name}: visible entries need labels in [0, {null}] (the null label is {null})")


def tracklet_votes(frame_labels: torch.Tensor, visible: torch.Tensor, null: int) -> TrackletVotes:
    """Majority label of each column over its visible frames.

    Ties go to the smallest label, so a tie between a marker label and null keeps the marker.

    Args:
        frame_labels: (T, N) int per-frame labels in [0, null] (anything where not visible).
        visible: (T, N) bool, where column n holds a point in frame t.
        null: the null label L.

    Returns:
        :class:`TrackletVotes`.
    """
    check_frame_labels(frame_labels, visible, null)
    n = frame_labels.shape[1]
    lab = torch.where(visible, frame_labels.long(), null + 1)  # invisible -> an extra, discarded class
    col = torch.arange(n, device=lab.device).expand_as(lab)
    counts = torch.zeros(n * (null + 2), dtype=torch.long, device=lab.device)
    counts.scatter_add_(0, (col * (null + 2) + lab).reshape(-1), torch.ones_like(lab).reshape(-1))
    counts = counts.view(n, null + 2)[:, : null + 1]
    best, labels = counts.max(dim=1)  # max returns the first (smallest) label among ties
    seen = visible.sum(dim=0)
    labels = torch.where(seen > 0, labels, null)
    share = torch.where(seen > 0, best.double() / seen.clamp(min=1).double(), 0.0)
    return TrackletVotes(labels, share)


def tracklet_labels(frame_labels: torch.Tensor, visible: torch.Tensor, null: int) -> torch.Tensor:
    """(N,) majority label of each column (null if mostly null or never visible); see :func:`tracklet_votes`."""
    return tracklet_votes(frame_labels, visible, null).labels


def label_tracklets(frame_labels: torch.Tensor, visible: torch.Tensor, null: int) -> torch.Tensor:
    """Per-frame labels after tracklet voting and conflict resolution.

    Each visible entry takes its column's majority label; where two visible columns of a
    frame share a label, the column with the larger vote share keeps it (ties: the lower
    column index) and the others are null in that frame.

    Args:
        frame_labels: (T, N) int per-frame labels in [0, null].
        visible: (T, N) bool.
        null: the null label L.

    Returns:
        (T, N) int64 labels, null where not visible; no label twice in a frame.
    """
    votes = tracklet_votes(frame_labels, visible, null)
    n = votes.labels.shape[0]
    lab = torch.where(visible, votes.labels[None, :], null)  # (T, N)
    idx = torch.arange(n, device=lab.device)
    # column j outranks column i: larger share, or the same share and a lower index
    outranks = (votes.share[None, :] > votes.share[:, None]) | (
        (votes.share[None, :] == votes.share[:, None]) & (idx[None, :] < idx[:, None])
    )  # (N i, N j)
    clash = (lab[:, :, None] == lab[:, None, :]) & (lab[:, :, None] != null)  # (T, i, j)
    lost = (clash & outranks[None]).any(dim=2)
    return torch.where(lost, null, lab)


def labelled_markers(points: torch.Tensor, labels: torch.Tensor, m: int) -> torch.Tensor:
    """(T, M, 3) marker columns from (T, N, 3) points and their (T, N) labels in [0, M] (M = null).

    Marker m of frame t is the point labelled m there, NaN where no point is; null and absent
    (NaN) points are left out. Same dtype as ``points``.
    """
    visible = torch.isfinite(points).all(-1)
    check_frame_labels(labels, visible, m, "labels")
    out = torch.full((points.shape[0], m, 3), math.nan, dtype=points.dtype, device=points.device)
    f, i = (visible & (labels < m)).nonzero(as_tuple=True)
    out[f, labels[f, i]] = points[f, i]
    return out


@dataclass(frozen=True, slots=True)
class TrackletConfig:
    """Settings of :func:`column_spans` and :func:`settle_tracklets`.

    Attributes:
        switch: the cost of a cut in a column, in frames of full confidence: a column is cut where
            the labels its evidence prefers on the two sides gain more than this over one label
            (15: e.g. 30 frames at a mean lead of 0.5, or 17 surely labelled frames; an island
            inside a column needs twice that).
        min_span: a span with fewer visible frames joins its neighbour (10: a twelfth of a second
            at 120 Hz; ``switch`` already asks 15 frames of evidence of a cut).

    The defaults were chosen from three settings ((15, 30), (15, 10), (10, 10)) by the
    benchmark's tracklet and joined-trajectory rows of all evaluation files together.
    """

    switch: float = 15.0
    min_span: int = 10

    def __post_init__(self) -> None:
        if isinstance(self.min_span, bool) or not isinstance(self.min_span, int) or self.min_span < 1:
            raise ValueError(f"min_span: expected an int >= 1, got {self.min_span!r}")
        if not (math.isfinite(self.switch) and self.switch >= 0):
            raise ValueError(f"switch: expected a finite number >= 0, got {self.switch!r}")


def _segment(p: np.ndarray, vis: np.ndarray, switch: float) -> np.ndarray:
    """(T, N) state of each column per frame: the label sequence maximising the summed evidence
    minus ``switch`` per change (dynamic programming over frames, all columns at once)."""
    t, n, c = p.shape
    best = np.zeros((n, c))
    moved = np.zeros((t, n, c), dtype=bool)
    came = np.zeros((t, n), dtype=np.int64)
    rows = np.arange(n)
    e = np.where(vis[..., None], p, 0.0)
    for f in range(t):
        arg = best.argmax(1)
        top = best[rows, arg] - switch
        sw = top[:, None] > best
        best = np.where(sw, top[:, None], best) + e[f]
        moved[f], came[f] = sw, arg
    state = np.empty((t, n), dtype=np.int64)
    s = best.argmax(1)
    for f in range(t - 1, -1, -1):
        state[f] = s
        s = np.where(moved[f, rows, s], came[f], s)
    return state


def column_spans(prob: torch.Tensor, visible: torch.Tensor, config: TrackletConfig | None = None) -> torch.Tensor:
    """(T, N) int64 span of each visible point (-1 where not visible); spans of a column are consecutive ids.

    A column is cut where its evidence changes label for long enough (see :class:`TrackletConfig`).

    Args:
        prob: (T, N, L+1) label probabilities of each point (rows of the labeler's plan).
        visible: (T, N) bool.
        config: :class:`TrackletConfig`.
    """
    cfg = TrackletConfig() if config is None else config
    sizes: dict[str, int] = {}
    check_shape(prob, "T N C", name="prob", sizes=sizes)
    check_shape(visible, "T N", name="visible", sizes=sizes)
    vis = visible.cpu().numpy().astype(bool)
    span = np.full(vis.shape, -1, dtype=np.int64)
    cols = np.flatnonzero(vis.any(0))
    if not len(cols):
        return torch.from_numpy(span).to(visible.device)
    p = prob.detach().cpu().numpy()[:, cols].astype(np.float64)
    state = _segment(p, vis[:, cols], cfg.switch)
    next_id = 0
    for j, n in enumerate(cols):
        f = np.flatnonzero(vis[:, n])
        run = np.concatenate([[0], np.cumsum(state[f[1:], j] != state[f[:-1], j])])
        size = np.bincount(run)
        keep = size >= cfg.min_span
        if not keep.any():
            keep[int(size.argmax())] = True
        # a short run joins the kept run before it (the first kept run, at the start)
        kept = np.flatnonzero(keep)
        owner = kept[np.clip(np.searchsorted(kept, np.arange(len(size)), side="right") - 1, 0, None)]
        # a run between two runs of one label joins them: the labeler wrong or unsure for a while
        # (two wrist markers swapped in some frames, a marker taken for a ghost in floor work) is
        # likelier than a tracker that swapped two trajectories and swapped them back
        first = np.searchsorted(run, kept)  # each kept run's first visible frame
        lab = state[f[first], j]
        for a in range(1, len(kept) - 1):
            if lab[a - 1] == lab[a + 1]:
                owner[np.isin(owner, kept[a : a + 2])] = owner[kept[a - 1]]
        ids = np.unique(owner, return_inverse=True)[1]
        span[f, n] = next_id + ids[run]
        next_id += int(ids.max()) + 1
    return torch.from_numpy(span).to(visible.device)


def _match(score: np.ndarray, null: int) -> np.ndarray:
    """Labels of K spans (score (K, L+1) evidence) maximising the summed evidence, no marker label twice."""
    k = len(score)
    big = 1e18
    cost = np.full((k, null + k), big)
    cost[:, :null] = -score[:, :null]
    cost[np.arange(k), null + np.arange(k)] = -score[:, null]
    rows, cols = linear_sum_assignment(cost)
    out = np.full(k, null, dtype=np.int64)
    out[rows] = np.where(cols < null, cols, null)
    return out


def settle_tracklets(
    prob: torch.Tensor,
    visible: torch.Tensor,
    *,
    config: TrackletConfig | None = None,
    spans: torch.Tensor | None = None,
) -> torch.Tensor:
    """Per-frame labels settled over the sequence: one label per column per span (see the module).

    Args:
        prob: (T, N, L+1) each point's label probabilities (:attr:`~unibody.mocap.labeler.FrameLabels.prob`;
            more evidence may be added, e.g. a body check's labels); entries of missing points are ignored.
        visible: (T, N) bool.
        config: :class:`TrackletConfig`.
        spans: (T, N) spans from :func:`column_spans` (default: found from ``prob``).

    Returns:
        (T, N) int64 labels in [0, L], L = null (also where not visible); no label twice in a frame.
    """
    sizes: dict[str, int] = {}
    check_shape(prob, "T N C", name="prob", sizes=sizes)
    check_shape(visible, "T N", name="visible", sizes=sizes)
    if visible.dtype != torch.bool:
        raise TypeError(f"visible: expected a bool tensor, got {visible.dtype}")
    null = prob.shape[2] - 1
    if spans is None:
        spans = column_spans(prob, visible, config)
    span = spans.cpu().numpy()
    vis = visible.cpu().numpy() & (span >= 0)
    p = prob.detach().cpu().numpy().astype(np.float64)
    t, n = vis.shape
    out = np.full((t, n), null, dtype=np.int64)
    if not vis.any():
        return torch.from_numpy(out).to(visible.device)
    s_count = int(span.max()) + 1
    ev = np.zeros((s_count, null + 1))
    np.add.at(ev, span[vis], p[vis])
    best = ev.argmax(1)
    # per frame: the spans' best labels, matched where two of them clash
    frame = np.where(vis, best[np.maximum(span, 0)], null)
    claimed = np.where(frame < null, frame, null + 1 + np.arange(n))
    srt = np.sort(claimed, axis=1)
    clash = (srt[:, 1:] == srt[:, :-1]).any(1)
    cache: dict[bytes, np.ndarray] = {}
    for f in np.flatnonzero(clash):
        idx = np.flatnonzero(vis[f])
        ids = span[f, idx]
        key = ids.tobytes()
        if key not in cache:
            cache[key] = _match(ev[ids], null)
        frame[f, idx] = cache[key]
    # each span: the label it got in most of its frames (ties: its best label)
    votes = np.zeros((s_count, null + 1))
    np.add.at(votes, (span[vis], frame[vis]), 1.0)
    votes[np.arange(s_count), best] += 0.5
    label = votes.argmax(1)
    out = np.where(vis, label[np.maximum(span, 0)], null)
    # clashes left: more evidence keeps the label; the others take the frame's match if free, else null
    strength = np.where(vis, ev[np.maximum(span, 0), np.minimum(out, null)], 0.0)
    for f in np.flatnonzero(_clashing(out, null)):
        row, fr = out[f], frame[f]
        order = np.argsort(-strength[f], kind="stable")
        taken: set[int] = set()
        for i in order:
            if not vis[f, i] or row[i] == null:
                continue
            if row[i] not in taken:
                taken.add(int(row[i]))
            elif fr[i] != null and int(fr[i]) not in taken and int(fr[i]) not in set(row[vis[f]].tolist()):
                row[i] = fr[i]
                taken.add(int(fr[i]))
            else:
                row[i] = null
        out[f] = row
    return torch.from_numpy(out).to(visible.device)


def undecided_frames(
    prob: torch.Tensor, visible: torch.Tensor, unsure: torch.Tensor, config: TrackletConfig | None = None
) -> torch.Tensor:
    """(T,) bool: the ``unsure`` frames with a point in a span whose label they could overturn.

    Span s's best label leads its runner-up by ``E[s, best] - E[s, second]`` (the evidence of
    :func:`settle_tracklets`). Relabelling one frame moves that lead by at most 2 (a point's
    probabilities sum to 1), so a span with ``u`` unsure frames is undecided while its lead is
    at most ``2 u``; the others keep their label whatever those frames become.

    Args:
        prob: (T, N, L+1) label probabilities; visible: (T, N) bool; unsure: (T,) bool.
    """
    sizes: dict[str, int] = {}
    check_shape(prob, "T N C", name="prob", sizes=sizes)
    check_shape(visible, "T N", name="visible", sizes=sizes)
    check_shape(unsure, "T", name="unsure", sizes=sizes)
    span = column_spans(prob, visible, config).cpu().numpy()
    vis = visible.cpu().numpy() & (span >= 0)
    low = unsure.cpu().numpy().astype(bool)
    if not (vis.any() and low.any()):
        return torch.zeros(vis.shape[0], dtype=torch.bool, device=unsure.device)
    s_count = int(span.max()) + 1
    ev = np.zeros((s_count, prob.shape[2]))
    np.add.at(ev, span[vis], prob.detach().cpu().numpy().astype(np.float64)[vis])
    top = np.sort(ev, axis=1)
    lead = top[:, -1] - top[:, -2]
    in_low = vis & low[:, None]
    count = np.bincount(span[in_low], minlength=s_count)
    open_span = lead <= 2.0 * count
    out = low & (vis & open_span[np.maximum(span, 0)]).any(1)
    return torch.from_numpy(out).to(unsure.device)


def _clashing(labels: np.ndarray, null: int) -> np.ndarray:
    """(T,) bool: frames where a marker label appears twice."""
    n = labels.shape[1]
    claimed = np.where(labels < null, labels, null + 1 + np.arange(n))
    srt = np.sort(claimed, axis=1)
    return (srt[:, 1:] == srt[:, :-1]).any(1)
