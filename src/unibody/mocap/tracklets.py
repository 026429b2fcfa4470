"""Tracklet labeling (paper 003 §4.5, SOMA's runtime): one label per hardware trajectory.

A passive optical system already links points over time into tracklets: columns of a
(T, N) sequence, visible in some frames. Per-frame labels are noisy; a column keeps the
**majority vote** of its per-frame labels over the frames where it is visible (the null
label is a candidate, so a column that is mostly ghost stays null). Two columns can win the
same label (a trajectory broken in two, or a wrong vote): in the frames where both are
visible, the column with the larger vote share keeps the label and the others are null
there.

:func:`labelled_markers` turns per-point labels into one column per marker.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .._checks import check_shape

__all__ = ["TrackletVotes", "label_tracklets", "labelled_markers", "tracklet_labels", "tracklet_votes"]


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
