"""Triangle-mesh helpers for registration: input checks, surface sampling, outward winding.

All functions take ``vertices (V, 3)`` float and ``faces (F, 3)`` long tensors and follow
their dtype and device. Normals, areas and edges are in :mod:`unibody.geometry.mesh`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from .._checks import check_finite
from ..geometry.mesh import face_areas
from ..geometry.tetra import quads_to_triangles

__all__ = ["as_triangles", "as_vertices", "outward", "sample_surface"]


def as_vertices(vertices: torch.Tensor | np.ndarray) -> torch.Tensor:
    """Validate ``vertices (V, 3)`` (tensor or array, finite, V >= 4) and return a float64 CPU copy."""
    if isinstance(vertices, np.ndarray):
        if not (np.issubdtype(vertices.dtype, np.floating) or np.issubdtype(vertices.dtype, np.integer)):
            raise TypeError(f"vertices: expected a real-valued array, got dtype {vertices.dtype}")
        vertices = torch.from_numpy(np.ascontiguousarray(vertices))
    if not isinstance(vertices, torch.Tensor):
        raise TypeError(f"vertices: expected a torch.Tensor or numpy array, got {type(vertices).__name__}")
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices: expected shape (V, 3), got {tuple(vertices.shape)}")
    if vertices.shape[0] < 4:
        raise ValueError(f"vertices: expected at least 4 vertices, got {vertices.shape[0]}")
    if vertices.is_complex() or vertices.dtype == torch.bool:
        raise TypeError(f"vertices: expected a real-valued tensor, got {vertices.dtype}")
    v = vertices.detach().to(device="cpu", dtype=torch.float64).clone()
    check_finite(v, "vertices")
    return v


def as_triangles(faces: torch.Tensor | np.ndarray | Sequence[Sequence[int]], num_vertices: int) -> torch.Tensor:
    """Validate polygons (``(F, 3 | 4)`` or ragged, >= 1) and fan-triangulate them to ``(T, 3)`` long.

    Raises ValueError for an empty list, indices outside ``[0, num_vertices)`` or
    non-integer arrays.
    """
    if isinstance(faces, torch.Tensor):
        if faces.is_floating_point() or faces.dtype == torch.bool:
            raise TypeError(f"faces: expected integer vertex ids, got {faces.dtype}")
    elif isinstance(faces, np.ndarray) and faces.dtype != object:
        if not np.issubdtype(faces.dtype, np.integer):
            raise TypeError(f"faces: expected integer vertex ids, got dtype {faces.dtype}")
    if isinstance(faces, (torch.Tensor, np.ndarray)) and faces.ndim == 2 and faces.shape[1] < 3:
        raise ValueError(f"faces: expected polygons with >= 3 vertices, got shape {tuple(faces.shape)}")
    if len(faces) == 0:
        raise ValueError("faces: expected at least one polygon, got 0")
    tri = quads_to_triangles(faces)
    if tri.numel() == 0:
        raise ValueError("faces: expected at least one polygon, got 0")
    lo, hi = int(tri.min()), int(tri.max())
    if lo < 0 or hi >= num_vertices:
        raise ValueError(f"faces: expected vertex ids in [0, {num_vertices}), got range [{lo}, {hi}]")
    return tri.long()


def sample_surface(
    v: torch.Tensor, faces: torch.Tensor, count: int, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """``count`` points uniformly distributed over the surface (area-weighted faces, uniform barycentrics).

    Returns ``(points (count, 3), face index (count,))``.
    """
    area = face_areas(v, faces)
    face = torch.multinomial(area, count, replacement=True, generator=generator)
    r = torch.rand(count, 2, generator=generator, dtype=v.dtype)
    s = r[:, :1].sqrt()
    w = torch.cat([1 - s, s * (1 - r[:, 1:]), s * r[:, 1:]], dim=1)
    pts = (v[faces[face]] * w[..., None]).sum(1)
    return pts, face


def outward(v: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """``faces`` wound so that normals point outward: reversed when the signed volume is negative.

    The signed volume ``sum det(a, b, c) / 6`` of a closed surface is positive for outward
    (counter-clockwise seen from outside) winding; for a nearly closed one its sign still
    tells. Registration compares normals, so an inside-out source is flipped first; the tet
    weights built on either winding reproduce the same points (eq. 1 uses the same order).
    """
    a, b, c = (v[faces[:, k]] - v.mean(0) for k in range(3))
    volume = (a * torch.linalg.cross(b, c, dim=-1)).sum() / 6.0
    return faces if volume >= 0 else faces[:, [0, 2, 1]]
