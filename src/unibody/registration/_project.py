"""Stage 4: snap the wrap onto the source surface without breaking its triangles.

Every data vertex moves to its exact closest source point. A triangle is *flipped* when its
normal points against the same triangle's normal on the reference (the articulated
template: the canonical mesh's own orientation, posed) and *degenerate* when its area falls
below ``min_area_ratio`` times the reference area. Vertices of bad triangles go back to
their pre-projection positions, repeatedly, until no bad triangle is left; what stays
unprojected is counted. Should the pre-projection mesh itself hold a bad triangle (the ICP
can fold a few tiny triangles in dense regions), :func:`untangle` relaxes the vertices
around it toward their neighbours' mean until none is left.
"""

from __future__ import annotations

import torch

from ..geometry.mesh import face_areas, unique_edges
from ._closest import SurfaceIndex

__all__ = ["bad_triangles", "project_onto_surface", "untangle"]


def bad_triangles(
    x: torch.Tensor, faces: torch.Tensor, ref: torch.Tensor, min_area_ratio: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Masks ``(flipped (F,), degenerate (F,))`` of ``x`` against the reference mesh ``ref``."""
    a, b, c = x[faces].unbind(1)
    ra, rb, rc = ref[faces].unbind(1)
    n = torch.linalg.cross(b - a, c - a, dim=-1)
    rn = torch.linalg.cross(rb - ra, rc - ra, dim=-1)
    flipped = (n * rn).sum(-1) <= 0
    degenerate = face_areas(x, faces) <= min_area_ratio * face_areas(ref, faces)
    return flipped, degenerate


def project_onto_surface(
    x: torch.Tensor,
    faces: torch.Tensor,
    data: torch.Tensor,
    source: SurfaceIndex,
    ref: torch.Tensor,
    *,
    min_area_ratio: float = 0.02,
    max_rounds: int = 50,
) -> tuple[torch.Tensor, int]:
    """Project the ``data`` vertices of ``x (V, 3)`` onto the source where triangles allow.

    Returns ``(projected vertices (V, 3), number of data vertices left unprojected)``.
    """
    _, q, _ = source.query(x[data])
    target = x.clone()
    target[data] = q
    moved = data.clone()
    y = target.clone()
    for _ in range(max_rounds):
        flipped, degenerate = bad_triangles(y, faces, ref, min_area_ratio)
        bad = flipped | degenerate
        if not bool(bad.any()):
            break
        back = torch.zeros_like(moved)
        back[faces[bad].reshape(-1)] = True
        back &= moved
        if not bool(back.any()):
            break  # the bad triangles are not caused by the projection
        moved &= ~back
        y = torch.where(moved[:, None], target, x)
    return y, int((data & ~moved).sum())


def untangle(
    x: torch.Tensor, faces: torch.Tensor, ref: torch.Tensor, min_area_ratio: float, *, max_rounds: int = 200
) -> tuple[torch.Tensor, torch.Tensor]:
    """Relax the vertices of flipped/degenerate triangles of ``x`` toward their neighbours' mean.

    The relaxed region grows by one ring every 10 rounds without success. Returns
    ``(x (V, 3), moved (V,) bool)``.
    """
    edges = unique_edges(faces)
    i, j = edges.unbind(1)
    deg = torch.bincount(torch.cat([i, j]), minlength=x.shape[0]).to(x.dtype).clamp_min(1)
    moved = torch.zeros(x.shape[0], dtype=torch.bool)
    y = x.clone()
    rings = 0
    for r in range(max_rounds):
        flipped, degenerate = bad_triangles(y, faces, ref, min_area_ratio)
        bad = flipped | degenerate
        if not bool(bad.any()):
            break
        if r and r % 10 == 0:
            rings += 1
        region = torch.zeros_like(moved)
        region[faces[bad].reshape(-1)] = True
        for _ in range(rings):
            region[i[region[j]]] = True
            region[j[region[i]]] = True
        mean = torch.zeros_like(y).index_add_(0, i, y[j]).index_add_(0, j, y[i]) / deg[:, None]
        y = torch.where(region[:, None], 0.5 * y + 0.5 * mean, y)
        moved |= region
    return y, moved
