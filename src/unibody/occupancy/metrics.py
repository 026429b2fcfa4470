"""Exact self-intersection counts of posed meshes, per pair of parts (for benchmarks and tests)."""

from __future__ import annotations

import torch

from ..geometry.intersect import intersecting_pairs
from .parts import BodyParts

__all__ = ["part_intersecting_pairs", "part_intersections"]


def part_intersecting_pairs(vertices: torch.Tensor, faces: torch.Tensor, parts: BodyParts) -> torch.Tensor:
    """(P, 2) face indices of the intersecting triangle pairs of one mesh (V, 3) between parts that
    may not overlap (``parts.allowed``): contact of a part with itself, its parent, its children or
    a named neighbour (which includes skinning artefacts at the joints) is not counted."""
    label = parts.face_part.to(faces.device)
    pairs = intersecting_pairs(vertices.detach(), faces)
    return pairs[parts.allowed.to(faces.device)[label[pairs[:, 0]], label[pairs[:, 1]]]]


def part_intersections(vertices: torch.Tensor, faces: torch.Tensor, parts: BodyParts) -> torch.Tensor:
    """(B,) number of :func:`part_intersecting_pairs` of each mesh (B, V, 3)."""
    return torch.tensor([len(part_intersecting_pairs(v, faces, parts)) for v in vertices])
