"""Training data of the pose correctives: identities, poses and the teacher's rest-space targets.

The teacher (:mod:`.teacher`) returns posed vertices; the correctives live in the rest pose
(paper 000 eq. 7: ``V_corr = V(beta) + f(theta)``, skinned afterwards). LBS is linear in the rest
vertex, ``LBS(v + d) = LBS(v) + M_v d`` with ``M_v = sum_k w_vk R_k`` the blended rotation, so the
exact rest-space target of a posed correction ``r`` is ``d = M_v^-1 r`` (``M_v`` is invertible
below a 180 deg blend; targets are clamped to :data:`MAX_TARGET_M`).
"""

from __future__ import annotations

import numpy as np
import torch

from .model import size_of
from .teacher import Arap, teacher_region

__all__ = ["MAX_TARGET_M", "draw_identities", "size_of", "teacher_targets", "TeacherSetup"]

MAX_TARGET_M = 0.15
"""Largest rest-space displacement kept as a target (m)."""


def draw_identities(layer, n: int, generator: torch.Generator, *, components: int = 16) -> torch.Tensor:  # noqa: ANN001
    """(n, K) native PCA coefficients: N(0, 1) on the first ``components``, stature uniform 1.0-1.95 m.

    The first coefficient sets the stature (linear in it, as :mod:`unibody.mocap.synthetic` draws
    it), so children and adults are equally represented.
    """
    k = layer.identity.num_params
    coeffs = torch.zeros(n, k)
    coeffs[:, :components] = torch.randn(n, components, generator=generator)
    with torch.no_grad():
        probe = torch.zeros(2, k, dtype=layer.tpose_orient.dtype)
        probe[1, 0] = 1.0
        y = layer.identity(probe)[..., 1].float()
        h = y.amax(1) - y.amin(1)
    tall = 1.0 + 0.95 * torch.rand(n, generator=generator)
    coeffs[:, 0] = (tall - h[0]) / (h[1] - h[0])
    return coeffs


class TeacherSetup:
    """The teacher's fixed tables for one layer: the relaxed region and its per-joint parts.

    Attributes:
        masks: per stressed joint, (V,) bool (:func:`~.teacher.teacher_region`, ``rings`` rings).
        union: (U,) int64 sorted vertex ids of all of them: where correctives are non-zero.
    """

    def __init__(self, layer, *, rings: int = 5, twist_start: bool = True) -> None:  # noqa: ANN001
        self.faces = layer.faces.cpu().numpy().astype(np.int64)
        self.weights = layer.skinning.dense().detach().cpu().double().numpy()
        self.parents = layer.parents.cpu()
        self.masks = teacher_region(
            self.weights, self.parents.numpy(), tuple(layer.joint_names), self.faces, rings=rings
        )
        self.free = np.any(list(self.masks.values()), axis=0)
        self.union = torch.from_numpy(np.flatnonzero(self.free))
        self.twist = None
        if twist_start:
            from ..body import BodyLayer
            from ..rig import Rig

            self.twist = BodyLayer(Rig.canonical(), procedural=True).to(layer.tpose_orient.dtype)


def teacher_targets(
    layer, prepared, pose: torch.Tensor, setup: TeacherSetup, *, iterations: int = 6
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:  # noqa: ANN001
    """Teacher meshes and rest-space targets of one identity (batch 1) in ``pose`` (B, 77, 3).

    Returns:
        ``(lbs (B, V, 3), teacher (B, V, 3), d (B, U, 3))``: LBS and teacher meshes (float64), and
        the rest-space displacements on ``setup.union`` that LBS maps onto the teacher's.
    """
    with torch.no_grad():
        out = layer.pose(prepared, pose)
        lbs = out.vertices.double()
        arap = Arap(prepared.rest_vertices[0].double().numpy(), setup.faces, setup.free, iterations=iterations)
        start = lbs
        if setup.twist is not None:  # start the free vertices from LBS + twist joints: no candy wrapper to undo
            start = lbs.clone()
            free = torch.from_numpy(setup.free)
            start[:, free] = setup.twist.pose(prepared, pose).vertices.double()[:, free]
        teacher = torch.from_numpy(arap(start.numpy()))
        local = layer.local_rotations(pose)
        _, _, mats = layer.skin_transforms(prepared, local, pose.new_zeros(len(pose), 3))  # (B, J, 3, 4)
        u = setup.union
        w = torch.from_numpy(setup.weights[u.numpy()])  # (U, J)
        blended = torch.einsum("uj,bjrc->burc", w, mats[..., :3].double())  # (B, U, 3, 3)
        r = (teacher - lbs)[:, u]
        d = torch.linalg.solve(blended, r[..., None]).squeeze(-1)
        n = d.norm(dim=-1, keepdim=True)
        d = d * (MAX_TARGET_M / n.clamp_min(MAX_TARGET_M))
    return lbs, teacher, d
