"""Canonical vertices with no counterpart on most sources: the inner mouth and eye bags.

They are found once, on the canonical mesh, through Anny's artist-made wrap: a canonical
vertex is *inner* when any vertex of its tetrahedron base triangle on Anny's mesh lies on an
Anny face labelled ``eye_cavity.*``, ``eye_back.*``, ``mouth_cavity`` or ``tongue`` in
Anny's body-part segmentation (the same rule as ``benchmarks/topology.py``). The Anny data
serve only as labels here: nothing of Anny's shape or wrap enters the registration itself.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import torch

__all__ = ["INNER_LABELS", "inner_vertices"]

INNER_LABELS = ("eye_cavity.L", "eye_cavity.R", "eye_back.L", "eye_back.R", "mouth_cavity", "tongue")


@cache
def _inner_numpy() -> np.ndarray:
    from anny.face_segmentation import get_face_segmentation_mask

    from ..assets import canonical_assets
    from ..identity.anny import AnnyIdentity

    model = AnnyIdentity.create().model
    face_mask = get_face_segmentation_mask(model, list(INNER_LABELS)).cpu()
    inner = torch.zeros(int(model.template_vertices.shape[0]), dtype=torch.bool)
    inner[model.faces[face_mask].flatten().cpu()] = True
    base = torch.from_numpy(canonical_assets()["anny_face_vertices"]).long()
    out = inner[base].any(1).numpy()
    out.setflags(write=False)
    return out


def inner_vertices() -> torch.Tensor:
    """(18056,) bool: canonical vertices of the inner mouth and eye bags (814 of them)."""
    return torch.from_numpy(_inner_numpy().copy())
