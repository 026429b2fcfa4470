"""Lab frames, axes and units of marker points, shared by labelling and solving.

unibody works in metres with Y up; most labs record Z up and many in millimetres.
:func:`lab_to_unibody` / :func:`unibody_to_lab` turn the axes, :func:`check_marker_units`
refuses points that are not in metres, :func:`check_points` checks a solver's input.
"""

from __future__ import annotations

import numpy as np
import torch

from .._checks import check_shape, check_tensor
from ..motion import check_fps  # one rule for frame rates (re-exported: the solve and its result use it)

Points = torch.Tensor | np.ndarray  # lab_to_unibody and unibody_to_lab take and return either

__all__ = [
    "Points",
    "check_fps",
    "check_marker_units",
    "check_points",
    "lab_to_unibody",
    "unibody_to_lab",
    "vertical_note",
]


def _axes(points: Points, up: str) -> None:
    if up not in ("y", "z"):
        raise ValueError(f"up: expected 'y' or 'z', got {up!r}")
    if not isinstance(points, torch.Tensor | np.ndarray):
        raise TypeError(f"points: expected a torch.Tensor or numpy array, got {type(points).__name__}")
    if points.shape[-1:] != (3,):
        raise ValueError(f"points: expected shape (..., 3), got {tuple(points.shape)}")


def lab_to_unibody(points: Points, up: str = "z") -> Points:
    """Lab coordinates (..., 3) -> unibody's Y-up frame; Z-up: (x, y, z) -> (x, z, -y).

    ``up="y"`` returns the points unchanged. Works on tensors and numpy arrays; the units
    are kept (convert millimetres to metres yourself).
    """
    _axes(points, up)
    if up == "y":
        return points
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    stack = torch.stack if isinstance(points, torch.Tensor) else np.stack
    return stack([x, z, -y], -1)


def unibody_to_lab(points: Points, up: str = "z") -> Points:
    """Inverse of :func:`lab_to_unibody`: (x, y, z) -> (x, -z, y) for a Z-up lab."""
    _axes(points, up)
    if up == "y":
        return points
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    stack = torch.stack if isinstance(points, torch.Tensor) else np.stack
    return stack([x, -z, y], -1)


def check_points(points: torch.Tensor, spec: str, m: int | None = None, name: str = "points") -> torch.Tensor:
    """Check solver input: a float tensor of ``spec`` (with M = ``m``), finite or NaN, not all missing,
    in metres (:func:`check_marker_units`: the labeler's rule, so a sequence it labels is one the
    solve takes; how far the subject travels or a stray point lies does not matter)."""
    check_tensor(points, name)
    check_shape(points, spec, name=name, sizes={} if m is None else {"M": m})
    if not points.is_floating_point():
        raise TypeError(f"{name}: expected float32 or float64, got {points.dtype}")
    if bool(torch.isinf(points).any()):
        raise ValueError(f"{name}: expected finite values or NaN for missing markers, got inf")
    if not bool(torch.isfinite(points).any()):
        raise ValueError(f"{name}: every marker is missing (all NaN)")
    check_marker_units(points.detach().reshape(-1, *points.shape[-2:]).cpu().numpy(), name)
    return points


def check_marker_units(points: np.ndarray, name: str = "points", frames: int = 64) -> None:
    """Refuse marker points that are not in metres (one shared check of :mod:`unibody.mocap`).

    The statistic ignores far extra points and absurd values: the 10th percentile, over up to
    ``frames`` frames spread over the sequence (those with 3 or more visible points), of each
    point's distance to its nearest neighbour. A body's markers sit 0.01-0.2 m apart (synthetic
    cmu41/pig39 frames: 10th percentile 0.06 m); the same in centimetres is 1-20, in millimetres
    10-200. Above 1 the points are refused.

    Args:
        points: (T, M, 3) with NaN for missing samples.
        name: the argument named in the message.
    """
    pts = np.asarray(points, dtype=np.float64)
    vis = np.isfinite(pts).all(-1)
    rows = _spread_rows(vis, 3, frames)
    if rows.size == 0:
        return
    nearest = []
    with np.errstate(over="ignore", invalid="ignore"):
        for t in rows:
            p = pts[t, vis[t]]
            d = np.linalg.norm(p[:, None] - p[None], axis=-1)
            np.fill_diagonal(d, np.inf)
            nearest.append(d.min(1))
    typical = float(np.percentile(np.concatenate(nearest), 10))
    if typical > 1.0:
        hint = "millimetres? divide by 1000" if typical > 5.0 else "centimetres? divide by 100"
        raise ValueError(
            f"{name}: the points are not in metres: neighbouring markers are typically {typical:.3g} units "
            f"apart (a body's markers: 0.01-0.2 m); {hint}"
        )


def _spread_rows(vis: np.ndarray, least: int, frames: int) -> np.ndarray:
    """Up to ``frames`` frame indices spread over the sequence, among those with ``least`` visible points."""
    rows = np.flatnonzero(vis.sum(1) >= least)
    if rows.size == 0:
        return rows
    return rows[np.unique(np.linspace(0, rows.size - 1, min(frames, rows.size)).round().astype(int))]


def vertical_note(points: np.ndarray, up: str, frames: int = 64) -> str | None:
    """A one-line note when a take in metres looks recorded with the other vertical axis, else None.

    The statistic: over up to ``frames`` frames spread over the take (6 or more visible points),
    the median extent of the markers (5th to 95th percentile) along each axis. A body standing
    in its lab spans 1.3-1.7 m along its vertical axis (the evaluation files' C3D and TRC takes)
    and 0.2-0.85 m along the other candidate; so ``up``'s extent under 0.9 m with the other
    candidate's 1.5 times larger reads as the wrong axis (OpenSim's TRC files are Y up). A take
    lying on the floor most of the time reads so too: it is a note, not an error.
    """
    pts = np.asarray(points, dtype=np.float64)
    vis = np.isfinite(pts).all(-1)
    rows = _spread_rows(vis, 6, frames)
    if rows.size == 0:
        return None
    spans = [np.percentile(pts[t, vis[t]], 95, axis=0) - np.percentile(pts[t, vis[t]], 5, axis=0) for t in rows]
    extent = np.median(spans, axis=0)
    other = "y" if up == "z" else "z"
    mine, theirs = extent["xyz".index(up)], extent["xyz".index(other)]
    if mine < 0.9 and theirs > 1.5 * mine:
        return (
            f"the markers span {theirs:.2f} m along {other.upper()} but {mine:.2f} m along {up.upper()} (the "
            f"vertical axis, --up {up}) in most frames: if the lab is {other.upper()} up, pass --up {other}"
        )
    return None
