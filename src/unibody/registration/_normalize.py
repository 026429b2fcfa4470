"""Stage 1: units and axes of a source body mesh.

The normalised frame is unibody's: metres, Y up, the body faces +Z (its left is +X), the
feet on ``y = 0`` and the surface centroid on the Y axis:

    x_norm = R (unit * x) + t.

Units come from the body height (extent along the up axis): 0.4-2.6 in the file's units
means metres, 40-260 centimetres, 400-2600 millimetres; anything else needs an explicit
unit. The up axis and facing come from the surface's principal axes (area-weighted): for a
standing body in T- or A-pose the smallest principal extent is front-back and the up axis
is one of the other two. That leaves eight proper rotations (up = +-e1 or +-e2, front =
+-e3, left = up x front); :func:`candidate_rotations` lists them and the articulated fit
decides (see ``register``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch

from ..geometry.mesh import face_areas

__all__ = ["UNITS", "Normalization", "candidate_rotations", "detect_unit", "normalization", "principal_axes"]

Unit = Literal["auto", "m", "cm", "mm", "in"]
UNITS: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254}
# Plausible standing-body heights, metres (an infant to a very tall adult).
HEIGHT_RANGE_M = (0.4, 2.6)
# Largest allowed ratio of the front-back extent to the height.
MAX_DEPTH_RATIO = 0.6


@dataclass(frozen=True, slots=True)
class Normalization:
    """The similarity from the source's frame and units to unibody's normalised frame.

    ``x_norm = rotation @ (scale * x) + translation``.

    Attributes:
        unit: "m", "cm", "mm" or "in": the source's length unit.
        scale: metres per source unit.
        rotation: (3, 3) float64 proper rotation, source axes -> unibody axes.
        translation: (3,) float64, m.
    """

    unit: str
    scale: float
    rotation: torch.Tensor
    translation: torch.Tensor

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        """Source points (N, 3) -> normalised frame."""
        return self.scale * x @ self.rotation.T + self.translation

    def invert(self, y: torch.Tensor) -> torch.Tensor:
        """Normalised points (N, 3) -> the source's frame and units."""
        return (y - self.translation) @ self.rotation / self.scale


def principal_axes(v: torch.Tensor, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Area-weighted surface centroid (3,), principal axes (3, 3) as columns (largest variance first), extents (3,).

    The covariance integrates exactly over each triangle:
    ``int x x^T = A/12 (sum_k v_k v_k^T + (sum_k v_k)(sum_k v_k)^T)``.
    """
    tri = v[faces]
    area = face_areas(v, faces)
    total = area.sum()
    if not total > 0:
        raise ValueError("faces: the surface has zero area")
    centroid = (area[:, None] * tri.mean(1)).sum(0) / total
    d = tri - centroid
    s = d.sum(1)
    second = torch.einsum("fki,fkj->fij", d, d) + s[:, :, None] * s[:, None, :]
    cov = (area[:, None, None] * second).sum(0) / (12.0 * total)
    _, vecs = torch.linalg.eigh(cov)
    axes = vecs.flip(1)
    proj = (v - centroid) @ axes
    extents = proj.amax(0) - proj.amin(0)
    return centroid, axes, extents


def detect_unit(height: float, unit: Unit) -> tuple[str, float]:
    """Pick the unit from a height in source units (or check an explicit one)."""
    lo, hi = HEIGHT_RANGE_M
    if unit != "auto":
        if unit not in UNITS:
            raise ValueError(f"unit: expected one of 'auto', {', '.join(map(repr, UNITS))}, got {unit!r}")
        h = height * UNITS[unit]
        if not lo <= h <= hi:
            raise ValueError(
                f"vertices: a body {h:.3g} m tall (in {unit!r}) is outside [{lo}, {hi}] m; "
                "is this a human body mesh, and is the unit right?"
            )
        return unit, UNITS[unit]
    for name in ("m", "cm", "mm"):
        if lo <= height * UNITS[name] <= hi:
            return name, UNITS[name]
    raise ValueError(
        f"vertices: height {height:.4g} (in source units) fits no body size in m, cm or mm "
        f"([{lo}, {hi}] m); not a body-sized object, or pass unit= explicitly"
    )


def candidate_rotations(axes: torch.Tensor) -> list[torch.Tensor]:
    """The eight proper rotations (source -> unibody) with up = +-e1, +-e2 and front = +-e3."""
    e1, e2, e3 = axes.unbind(1)
    out = []
    for up in (e1, -e1, e2, -e2):
        for front in (e3, -e3):
            left = torch.linalg.cross(up, front, dim=0)
            out.append(torch.stack([left, up, front]))  # rows: unibody x, y, z in source coords
    return out


def normalization(
    v: torch.Tensor, faces: torch.Tensor, rotation: torch.Tensor, unit: str, scale: float
) -> Normalization:
    """Feet on y = 0 and the surface centroid on the Y axis, for a chosen rotation and unit."""
    centroid, _, _ = principal_axes(v, faces)
    y = scale * v @ rotation.T
    c = scale * rotation @ centroid
    t = torch.stack([-c[0], -y[:, 1].min(), -c[2]])
    return Normalization(unit, scale, rotation, t)


def check_body_extents(extents_m: torch.Tensor) -> None:
    """Reject shapes that cannot be a standing body: too flat-round, wrong size."""
    big, depth = float(extents_m[0]), float(extents_m[2])
    lo, hi = HEIGHT_RANGE_M
    if not lo <= big <= 1.25 * hi:
        raise ValueError(f"vertices: largest extent {big:.3g} m is not body-sized ([{lo}, {1.25 * hi}] m)")
    if depth > MAX_DEPTH_RATIO * big:
        raise ValueError(
            f"vertices: principal extents {big:.3g} x {float(extents_m[1]):.3g} x {depth:.3g} m do not look like "
            f"a standing human body (front-back extent above {MAX_DEPTH_RATIO:g} x the largest)"
        )
