"""Training data of the pose correctives: identities, poses and the teacher's rest-space targets.

The teacher (:mod:`.teacher`) returns posed vertices; the correctives live in the rest pose
(paper 000 eq. 7: ``V_corr = V(beta) + f(theta)``, skinned afterwards). LBS is linear in the rest
vertex, ``LBS(v + d) = LBS(v) + M_v d`` with ``M_v = sum_k w_vk R_k`` the blended rotation, so the
exact rest-space target of a posed correction ``r`` is ``d = M_v^-1 r`` (``M_v`` is invertible
below a 180 deg blend; targets are clamped to :data:`MAX_TARGET_M`).

With procedural twist joints the displaced rest mesh is skinned by the twist rig instead, whose
blended rotation ``M_t`` differs; :func:`twist_targets` gives the twist rig's targets
``d_twist = M_t^-1 (teacher - LBS_twist)`` of the same teacher meshes, so the correctives of
that rig do not add the twist correction a second time.
"""

from __future__ import annotations

import numpy as np
import torch

from .metrics import SurfaceMeasures, cone_volume
from .model import size_of
from .teacher import Arap, Contact, bone_anchors, teacher_region

__all__ = [
    "ANCHOR",
    "MAX_TARGET_M",
    "blended_rotations",
    "draw_identities",
    "size_of",
    "teacher_targets",
    "twist_targets",
    "TeacherSetup",
]

MAX_TARGET_M = 0.15
"""Largest rest-space displacement kept as a target (m)."""
ANCHOR = 0.01
"""The teacher's default tie of one-bone flesh to its bone (:func:`~.teacher.bone_anchors`; 0: none,
the teacher of the weights before 2026-11-28's second set)."""


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
        measures: with ``volume``, the :class:`~.metrics.SurfaceMeasures` whose limb segments
            (upper arms, forearms, thighs, shins) keep their rest volume in the teacher.
        contact: with ``contact``, the teacher's :class:`~.teacher.Contact` (self-contact resolved).
        anchor: (V,) each vertex's tie to its skinned position (:func:`~.teacher.bone_anchors`), or None.
    """

    def __init__(  # noqa: D107
        self,
        layer,  # noqa: ANN001 (a BodyLayer; no import cycle)
        *,
        rings: int = 5,
        twist_start: bool = True,
        volume: bool = True,
        contact: bool = True,
        anchor: float = ANCHOR,
    ) -> None:
        self.faces = layer.faces.cpu().numpy().astype(np.int64)
        self.weights = layer.skinning.dense().detach().cpu().double().numpy()
        self.parents = layer.parents.cpu()
        self.masks = teacher_region(
            self.weights, self.parents.numpy(), tuple(layer.joint_names), self.faces, rings=rings
        )
        self.free = np.any(list(self.masks.values()), axis=0)
        self.union = torch.from_numpy(np.flatnonzero(self.free))
        # The limb segments whose volume the teacher keeps (those the metrics measure), or None.
        self.measures = SurfaceMeasures.from_layer(layer) if volume else None
        # Self-contact: penetrating free vertices pulled out (parts: each vertex's dominant joint), or None.
        self.contact = Contact(self.faces, self.weights.argmax(1)) if contact else None
        self.anchor = bone_anchors(self.weights, anchor) if anchor > 0 else None
        self.twist = None
        if twist_start:
            from ..body import BodyLayer
            from ..rig import Rig

            self.twist = BodyLayer(Rig.canonical(), procedural=True).to(layer.tpose_orient.dtype)
        self._twist64 = None

    def twist64(self):  # noqa: ANN201 (a BodyLayer)
        """A float64 copy of :attr:`twist` (made once; :attr:`twist` keeps the layer's dtype)."""
        if self._twist64 is None:
            import copy

            self._twist64 = copy.deepcopy(self.twist).double()
        return self._twist64


def teacher_targets(
    layer, prepared, pose: torch.Tensor, setup: TeacherSetup, *, iterations: int = 6
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:  # noqa: ANN001
    """Teacher meshes and rest-space targets of one identity (batch 1) in ``pose`` (B, 77, 3).

    Returns:
        ``(lbs (B, V, 3), teacher (B, V, 3), d (B, U, 3))``: LBS and teacher meshes (float64), and
        the rest-space displacements on ``setup.union`` that LBS maps onto the teacher's.
    """
    with torch.no_grad():
        out = layer.pose(prepared, pose, correctives=False)  # the targets are relative to plain LBS
        lbs = out.vertices.double()
        rest = prepared.rest_vertices[0].double().numpy()
        volumes, apex, target = (), None, None
        if setup.measures is not None:  # each limb segment keeps its rest volume (cone from its bone midpoint)
            m = setup.measures
            volumes = m.segment_faces
            apex0, apex = m.segment_apexes(prepared.rest_rotations, prepared.rest_joints, out.transforms)
            rest64 = prepared.rest_vertices.double().cpu()
            target = torch.stack(
                [cone_volume(rest64, torch.from_numpy(f), apex0[:, k])[0] for k, f in enumerate(volumes)]
            )
        arap = Arap(rest, setup.faces, setup.free, iterations=iterations, volumes=volumes, anchor=setup.anchor)
        start = lbs
        if setup.twist is not None:  # start the free vertices from LBS + twist joints: no candy wrapper to undo
            start = lbs.clone()
            free = torch.from_numpy(setup.free)
            start[:, free] = setup.twist.pose(prepared, pose).vertices.double()[:, free]
        teacher = torch.from_numpy(arap(start.numpy(), apex, target, setup.contact))
        local = layer.local_rotations(pose)
        _, _, mats = layer.skin_transforms(prepared, local, pose.new_zeros(len(pose), 3))  # (B, J, 3, 4)
        u = setup.union
        w = torch.from_numpy(setup.weights[u.numpy()])  # (U, J)
        blended = torch.einsum("uj,bjrc->burc", w, mats[..., :3].double())  # (B, U, 3, 3)
        d = _rest_space((teacher - lbs)[:, u], blended)
    return lbs, teacher, d


def _rest_space(r: torch.Tensor, blended: torch.Tensor) -> torch.Tensor:
    """(B, U, 3) ``M^-1 r`` of posed corrections r (B, U, 3), blended rotations (B, U, 3, 3); clamped."""
    d = torch.linalg.solve(blended, r[..., None]).squeeze(-1)
    n = d.norm(dim=-1, keepdim=True)
    return d * (MAX_TARGET_M / n.clamp_min(MAX_TARGET_M))


def blended_rotations(
    layer, prepared, pose: torch.Tensor, vertices: torch.Tensor, *, absolute: bool = False
) -> tuple[torch.Tensor, torch.Tensor]:  # noqa: ANN001
    """The posed meshes of ``layer`` (any rig, twist joints included) and its blended rotations.

    Skinning is affine in the rest vertex, ``LBS(v + e) = LBS(v) + M_v e``, whatever joints and
    weights the rig skins with, so the columns of ``M_v`` are the moves of the posed mesh when the
    whole rest mesh is shifted by the unit vectors (exact up to rounding): no rig internals needed.

    Args:
        layer: a BodyLayer (plain or procedural); prepared: the identity (batch 1); pose: (B, 77, 3)
            or any form :meth:`BodyLayer.pose` takes; vertices: (U,) int64, the vertices whose
            ``M_v`` is wanted; absolute: whether ``pose`` holds absolute local rotations.

    Returns:
        ``(posed (B, V, 3), blended (B, U, 3, 3))``, in the layer's dtype.
    """
    from ..body import PreparedIdentity

    p = prepared
    posed = layer.pose(p, pose, absolute=absolute, correctives=False).vertices
    cols = []
    for c in range(3):
        shift = p.rest_vertices.new_zeros(3)
        shift[c] = 1.0
        moved = PreparedIdentity(p.rest_vertices + shift, p.rest_rotations, p.rest_joints, p.offsets)
        cols.append((layer.pose(moved, pose, absolute=absolute, correctives=False).vertices - posed)[:, vertices])
    return posed, torch.stack(cols, -1)


def twist_targets(prepared, pose: torch.Tensor, teacher: torch.Tensor, setup: TeacherSetup) -> torch.Tensor:  # noqa: ANN001
    """(B, U, 3) the twist rig's rest-space targets on ``setup.union``: ``M_t^-1 (teacher - LBS_twist)``.

    ``LBS_twist`` and ``M_t`` are the procedural layer ``setup.twist``'s posed mesh and blended
    rotations (:func:`blended_rotations`, in float64), so that rig maps ``rest + d_twist`` onto the teacher.

    Args:
        prepared: the identity (batch 1); pose: (B, 77, 3); teacher: (B, V, 3) float64, from
            :func:`teacher_targets` of the same identity and pose.
    """
    if setup.twist is None:
        raise ValueError("twist_targets: the TeacherSetup has no twist layer (built with twist_start=False)")
    from ..body import PreparedIdentity

    with torch.no_grad():
        p = PreparedIdentity(*(t.double() for t in (prepared.rest_vertices, prepared.rest_rotations,
                                                    prepared.rest_joints, prepared.offsets)))  # fmt: skip
        twist = setup.twist64()
        posed, blended = blended_rotations(twist, p, pose.double(), setup.union)
        u = setup.union
        return _rest_space((teacher - posed)[:, u], blended)
