"""Exact self-intersection counts of posed meshes, per pair of parts (for benchmarks and tests)."""

from __future__ import annotations

import torch

from ..geometry.intersect import intersecting_pairs
from .parts import BodyParts

__all__ = ["part_intersections"]


def part_intersections(vertices: torch.Tensor, faces: torch.Tensor, parts: BodyParts) -> torch.Tensor:
    """(B,) number of intersecting triangle pairs of each mesh (B, V, 3) between parts that may not
    overlap (``parts.allowed``): contact of a part with itself, its parent, its children or a named
    neighbour (which includes skinning artefacts at the joints) is not counted."""
    label = parts.face_part.to(faces.device)
    allowed = parts.allowed.to(faces.device)
    counts = []
    for v in vertices.detach():
        pairs = intersecting_pairs(v, faces)
        counts.append(int(allowed[label[pairs[:, 0]], label[pairs[:, 1]]].sum()))
    return torch.tensor(counts)
