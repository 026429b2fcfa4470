"""Body-checked labels: solve the body from a labeler's labels, then give each point the solved marker it sits on.

A labeler decides every frame alone, from the shape of its point cloud. Its mistakes are
mostly a marker given a neighbour's label (an occluded neighbour's, often) and ghosts taken
for markers; a body solved over the whole sequence knows where every marker of every frame
should be, occluded or not, to a few millimetres. :func:`relabel` runs, ``passes`` times:

1. **solve** (:func:`~unibody.mocap.solve.solve_markers`, whose Cauchy data term keeps a few
   mislabelled points from dragging the body) from the current labels;
2. **drop**: labels whose point lies more than ``drop`` from its model marker are removed
   and the body solved again;
3. **support**: a marker whose labelled points lie within ``drop`` of its model marker in fewer
   than ``support`` of the frames is left out of step 4, and its labels stay the labeler's.
   The labeler rarely finds it (a session that places it elsewhere: pyCGM's thigh, shank and toe
   markers), so the solve has only guessed where it sits, and nearby unlabelled points (a
   session's extra markers) would take it;
4. **assign**, frame by frame: a minimum-cost matching of the frame's points to the model
   markers, each point also free to be null. A point costs ``min(d, reach) / reach`` for a
   marker at distance d and ``null_cost`` for null; its current label is ``keep`` cheaper.
   So a point leaves its label only for a marker ``keep * reach`` nearer (1.25 cm), and a point
   the labeler called null takes a free marker only within ``(null_cost - keep) * reach`` of it
   (3.7 cm). A labelled point turns null only when another point takes its marker: with
   ``null_cost + keep < 1`` it would also when its marker is farther than
   ``(null_cost + keep) * reach``, but on the CMU files that loses more true markers (where
   the solve is a few cm off: hands, floor work) than it frees from ghosts.

The solve uses the sequence (its temporal prior, its shape from a dozen frames), so the
result is a sequence labelling, like tracklet voting, not a per-frame one. Where the body
solve itself goes wrong (floor work with many wrong labels) the labels stay the labeler's:
``keep`` makes them win every close call.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, fields

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment

from .._checks import check_shape
from .layout import MarkerLayout
from .solve import SolveConfig, SolveResult, solve_markers
from .tracklets import TrackletConfig, check_frame_labels, column_spans, labelled_markers, settle_tracklets

__all__ = ["RelabelConfig", "assign_points", "body_stride", "labelled_markers", "relabel", "relabel_tracklets"]

BODY_RATE = 50.0  # Hz: the tracklet body check solves every k-th frame, at this rate or above


@dataclass(frozen=True)
class RelabelConfig:
    """Thresholds of :func:`relabel` (distances in metres; costs in units of ``reach``).

    Attributes:
        passes: solve-and-assign rounds; each solves from the previous round's labels.
        support: a marker takes part in the matching only when, in at least this fraction of
            the frames, a point labelled with it lies within ``drop`` of its model marker; the
            others (a marker the labeler rarely finds, so the solve has only guessed where it
            sits) keep the labeler's labels.
        drop: m, labels farther than this from their model marker are left out of the second solve.
        reach: m, distances are clipped here: beyond it a marker is no better than any other.
        keep: cost discount of a point's current label (null included).
        null_cost: cost of the null label, below 1 so a point beyond ``reach`` of every marker is null.
    """

    passes: int = 2
    support: float = 0.5
    drop: float = 0.03
    reach: float = 0.05
    keep: float = 0.25
    null_cost: float = 0.99

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ValueError(f"{f.name}: expected a finite number, got {v!r}")
        if not isinstance(self.passes, int) or self.passes < 1:
            raise ValueError(f"passes: expected an int >= 1, got {self.passes!r}")
        for name in ("drop", "reach"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name}: expected a distance > 0, got {getattr(self, name)!r}")
        if not 0 <= self.support <= 1:
            raise ValueError(f"support: expected 0 <= support <= 1, got {self.support!r}")
        if not 0 <= self.keep < 1:
            raise ValueError(f"keep: expected 0 <= keep < 1, got {self.keep!r}")
        if not 0 < self.null_cost < 1:
            raise ValueError(f"null_cost: expected 0 < null_cost < 1, got {self.null_cost!r}")


def assign_points(
    points: torch.Tensor,
    markers: torch.Tensor,
    labels: torch.Tensor,
    config: RelabelConfig | None = None,
    checked: torch.Tensor | None = None,
) -> torch.Tensor:
    """Each frame's points matched to model markers (or null), favouring their current labels.

    Args:
        points: (T, N, 3) m, NaN rows are absent points.
        markers: (T, M, 3) m, where each marker should be (e.g. :attr:`SolveResult.markers`).
        labels: (T, N) int current labels in [0, M], M = null.
        config: the costs (see the module); default :class:`RelabelConfig`.
        checked: (M,) bool, the markers that take part (default all); a point labelled with
            another marker keeps its label.

    Returns:
        (T, N) int64 labels in [0, M]; no marker twice in a frame; M for absent points.
    """
    cfg = RelabelConfig() if config is None else config
    sizes: dict[str, int] = {}
    check_shape(points, "T N 3", name="points", sizes=sizes)
    check_shape(markers, "T M 3", name="markers", sizes=sizes)
    check_shape(labels, "T N", name="labels", sizes=sizes)
    m = markers.shape[1]
    visible = torch.isfinite(points).all(-1)
    check_frame_labels(labels, visible, m, "labels")
    if not bool(torch.isfinite(markers).all()):
        raise ValueError("markers: expected finite model markers, got NaN/inf")
    if checked is None:
        checked = torch.ones(m, dtype=torch.bool)
    elif checked.dtype != torch.bool or checked.shape != (m,):
        raise ValueError(f"checked: expected a ({m},) bool tensor, got {tuple(checked.shape)} {checked.dtype}")
    use = np.nonzero(checked.cpu().numpy())[0]  # the matching's marker columns
    k = len(use)
    dist = torch.cdist(torch.nan_to_num(points.double()), markers.double()[:, use])
    cost = (dist.clamp_max(cfg.reach) / cfg.reach).cpu().numpy()
    vis, lab = visible.cpu().numpy(), labels.cpu().numpy()
    column = np.full(m + 1, -1)  # label -> its column (-1: a marker left out)
    column[use] = np.arange(k)
    column[m] = k
    out = np.where(vis & (column[lab] < 0), lab, m).astype(np.int64)
    for f in range(len(lab)):
        idx = np.nonzero(vis[f] & (column[lab[f]] >= 0))[0]
        n = len(idx)
        if n == 0:
            continue
        c = np.concatenate([cost[f, idx], np.full((n, n), cfg.null_cost)], axis=1)  # markers | one null per point
        mine = column[lab[f, idx]]
        c[np.arange(n), np.where(mine < k, mine, k + np.arange(n))] -= cfg.keep
        rows, cols = linear_sum_assignment(c)
        hit = cols < k
        out[f, idx[rows[hit]]] = use[cols[hit]]
    return torch.from_numpy(out).to(labels.device)


def relabel(
    points: torch.Tensor,
    labels: torch.Tensor,
    layout: MarkerLayout,
    *,
    fps: float,
    config: RelabelConfig | None = None,
    solve: SolveConfig | None = None,
    progress: Callable[[str], None] | None = None,
) -> tuple[torch.Tensor, SolveResult | None]:
    """Check a labelling against a body solved from it (see the module).

    Args:
        points: (T, N, 3) m, the sequence's points in unibody's frame (Y up,
            :func:`~unibody.mocap.solve.lab_to_unibody`); NaN rows are absent points.
        labels: (T, N) int labels in [0, M] of ``layout``'s markers, M = null (e.g.
            :func:`~unibody.mocap.labeler.label_frames`).
        layout: the M markers the labels name.
        fps: the frame rate (the solve's temporal prior).
        config: the thresholds; default :class:`RelabelConfig`.
        solve: the solve's settings; default :class:`SolveConfig`.
        progress: called with one-line reports.

    Returns:
        (T, N) int64 labels in [0, M] and the last body solve (from the labels before the last
        assignment); None, and the labels as given, when no frame has the labelled markers a
        solve needs (:meth:`SolveConfig.needed`: nothing to check them against).
    """
    cfg = RelabelConfig() if config is None else config
    check_shape(points, "T N 3", name="points")
    m = len(layout)
    check_frame_labels(labels, torch.isfinite(points).all(-1), m, "labels")
    say = progress or (lambda _: None)
    solve = SolveConfig() if solve is None else solve
    labels = labels.long()
    result = None
    for k in range(cfg.passes):
        observed = labelled_markers(points.double(), labels, m)
        if _unsolvable(observed, solve, say):
            break
        marked = observed.clone()
        result = solve_markers(marked, layout, config=solve, fps=fps)
        far = result.residual.to(marked) > cfg.drop
        if bool(far.any()):
            marked[far] = math.nan
            if _solvable(marked, solve):  # else the solve with them stands
                result = solve_markers(marked, layout, config=solve, fps=fps)
        near = (observed - result.markers.to(observed)).norm(dim=-1) <= cfg.drop
        checked = near.double().mean(0) >= cfg.support
        new = assign_points(points, result.markers, labels, cfg, checked.cpu())
        changed = int(((new != labels) & torch.isfinite(points).all(-1)).sum())
        left = "" if bool(checked.all()) else f", left {int((~checked).sum())} rarely found markers to the labeler"
        say(f"pass {k + 1}: dropped {int(far.sum())} far labels, changed {changed} labels{left}")
        labels = new
    return labels, result


def _solvable(observed: torch.Tensor, solve: SolveConfig) -> bool:
    """Whether some frame of the labelled markers (T, M, 3) has the markers a solve needs."""
    return bool(solve.solvable(torch.isfinite(observed).all(-1)).any())


def _unsolvable(observed: torch.Tensor, solve: SolveConfig, say: Callable[[str], None]) -> bool:
    """Whether no frame of the labelled markers (T, M, 3) can be solved; says so."""
    if _solvable(observed, solve):
        return False
    vis = torch.isfinite(observed).all(-1)
    most = int(vis.sum(1).max()) if vis.numel() else 0
    say(f"body check skipped: no frame has the {solve.needed(vis.shape[1])} labelled markers a body solve "
        f"needs (the most: {most})")  # fmt: skip
    return True


def body_stride(fps: float, rate: float = BODY_RATE) -> int:
    """Frames between the solved frames of :func:`relabel_tracklets`: the largest k with fps / k >= ``rate``.

    At 50 Hz or more a model marker moves smoothly enough between solved frames that the linear
    interpolation is within a few millimetres of a solve (a hand at 100 m/s^2 over 1/50 s:
    a * dt^2 / 8 = 5 mm), well inside the check's 1.25 cm margin.
    """
    return max(1, int(fps // rate))


def _strided(t: int, k: int) -> torch.Tensor:
    """Every k-th of t frames, and the last."""
    picked = torch.arange(0, t, k)
    return picked if t == 0 or int(picked[-1]) == t - 1 else torch.cat([picked, torch.tensor([t - 1])])


def _solve_strided(
    points: torch.Tensor, picked: torch.Tensor, layout: MarkerLayout, fps: float, solve: SolveConfig | None, k: int
):
    """(T, M, 3) model markers (and the solve) from the ``picked`` frames (:func:`_strided`),
    linearly interpolated between them."""
    t = len(points)
    result = solve_markers(points[picked], layout, config=solve, fps=fps / k)
    if k == 1 or t == 1:  # every frame solved (one frame: nothing to interpolate between)
        return result.markers, result
    x = torch.arange(t, dtype=torch.float64)
    hi = torch.searchsorted(picked.double(), x).clamp(1, len(picked) - 1)
    lo = hi - 1
    w = ((x - picked[lo]) / (picked[hi] - picked[lo]).double())[:, None, None]
    mk = result.markers.double()
    return (1 - w) * mk[lo] + w * mk[hi], result


def relabel_tracklets(
    points: torch.Tensor,
    prob: torch.Tensor,
    layout: MarkerLayout,
    *,
    fps: float,
    config: RelabelConfig | None = None,
    tracklets: TrackletConfig | None = None,
    solve: SolveConfig | None = None,
    weight: float = 0.5,
    progress: Callable[[str], None] | None = None,
) -> tuple[torch.Tensor, SolveResult | None]:
    """Tracklet labels checked by a body: the body's labels are more evidence for the spans.

    :func:`~unibody.mocap.tracklets.settle_tracklets` labels the sequence; one body is solved
    from those labels (every :func:`body_stride`-th frame, the model markers interpolated between
    them; its Cauchy data term keeps a few wrong labels from pulling it); each frame's points are
    matched to the solved markers as in :func:`relabel` (:func:`assign_points`, the markers found
    in fewer than ``support`` of the frames left out), and each point's body label adds
    ``weight`` to its label probabilities; the spans are then settled again. With ``weight``
    0.5 the body decides a span only where the labeler's evidence for two labels is within half
    of its frames of each other: close calls. One solve at 50+ Hz, not :func:`relabel`'s four.

    Args:
        points: (T, N, 3) m, unibody frame, NaN rows absent.
        prob: (T, N, M+1) the labeler's label probabilities (:func:`~unibody.mocap.labeler.frame_probabilities`).
        layout: the M markers the labels name.
        fps: the frame rate.
        config: the matching's thresholds (``passes`` is not used: one pass).
        tracklets: the spans' settings.
        solve: the solve's settings.
        weight: evidence of one frame's body label (the labeler's: probabilities summing to 1).
        progress: called with one-line reports.

    Returns:
        (T, N) int64 labels in [0, M] and the body solve (of the solved frames only); the settled
        labels and None when no frame has the labelled markers a solve needs.
    """
    cfg = RelabelConfig() if config is None else config
    check_shape(points, "T N 3", name="points")
    m = len(layout)
    check_shape(prob, f"{points.shape[0]} {points.shape[1]} {m + 1}", name="prob")
    if not (math.isfinite(weight) and weight >= 0):
        raise ValueError(f"weight: expected a finite number >= 0, got {weight!r}")
    vis = torch.isfinite(points).all(-1)
    say = progress or (lambda _: None)
    solve = SolveConfig() if solve is None else solve
    spans = column_spans(prob, vis, tracklets)
    labels = settle_tracklets(prob, vis, spans=spans)
    observed = labelled_markers(points.double(), labels, m)
    k = body_stride(fps)
    picked = _strided(len(observed), k)
    if _unsolvable(observed[picked], solve, say):
        return labels, None
    markers, result = _solve_strided(observed, picked, layout, fps, solve, k)
    near = (observed - markers).norm(dim=-1) <= cfg.drop
    checked = near.double().mean(0) >= cfg.support
    body = assign_points(points, markers, labels, cfg, checked)
    extra = torch.zeros_like(prob)
    extra.scatter_(2, body[..., None], weight)
    prob2 = prob + torch.where(vis[..., None], extra, 0.0)
    new = settle_tracklets(prob2, vis, config=tracklets)
    changed = int(((new != labels) & vis).sum())
    left = "" if bool(checked.all()) else f", left {int((~checked).sum())} rarely found markers to the labeler"
    say(f"body check (every {k} frames solved): the body differs on {int(((body != labels) & vis).sum())} "
        f"labels, changed {changed}{left}")  # fmt: skip
    return new, result
