"""Triangle-mesh quantities: face and vertex normals, areas, edges.

Pure torch, differentiable, following the dtype and device of ``vertices``. Vertices are
``(..., V, 3)`` with any leading batch dimensions, faces ``(F, 3)`` integer indices shared by
the batch. Normals follow the right-hand rule on the winding; vertex normals are
area-weighted (the sum of the incident faces' cross products) and unit length, zero for
isolated or degenerate vertices.
"""

from __future__ import annotations

import torch

__all__ = ["face_areas", "face_normals", "unique_edges", "vertex_areas", "vertex_normals"]


def _face_cross(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(..., F, 3) ``(b - a) x (c - a)``: twice the area times the unit face normal."""
    f = faces.long()
    a, b, c = (vertices[..., f[:, k], :] for k in range(3))
    return torch.linalg.cross(b - a, c - a, dim=-1)


def _unit(n: torch.Tensor) -> torch.Tensor:
    # Dividing by a norm clamped at the smallest normal float keeps zero vectors at zero.
    return n / n.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(n.dtype).tiny)


def face_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Unit face normals.

    Args:
        vertices: ``(..., V, 3)`` positions.
        faces: ``(F, 3)`` vertex indices.

    Returns:
        ``(..., F, 3)`` unit normals, zero for degenerate faces.
    """
    return _unit(_face_cross(vertices, faces))


def face_areas(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Triangle areas ``(..., F)`` of ``vertices (..., V, 3)`` and ``faces (F, 3)``."""
    return 0.5 * _face_cross(vertices, faces).norm(dim=-1)


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Unit area-weighted vertex normals.

    Each face adds its cross product (twice its area times its unit normal) to its three
    corners, in face order.

    Args:
        vertices: ``(..., V, 3)`` positions.
        faces: ``(F, 3)`` vertex indices.

    Returns:
        ``(..., V, 3)`` unit normals, zero where no face or only cancelling faces touch.
    """
    n = _face_cross(vertices, faces).repeat_interleave(3, dim=-2)
    acc = torch.zeros_like(vertices).index_add_(-2, faces.reshape(-1).long(), n)
    return _unit(acc)


def vertex_areas(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """``(..., V)`` one third of the area of the faces around each vertex (barycentric cells)."""
    a = (face_areas(vertices, faces) / 3.0).repeat_interleave(3, dim=-1)
    return vertices.new_zeros(vertices.shape[:-1]).index_add_(-1, faces.reshape(-1).long(), a)


def unique_edges(faces: torch.Tensor) -> torch.Tensor:
    """``(E, 2)`` undirected edges ``i < j`` of a triangle list ``(F, 3)``, sorted."""
    e = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = torch.sort(e, dim=1).values
    return torch.unique(e, dim=0)
