"""BodyLayer: identity parameters + 77 joint rotations -> posed mesh on the canonical topology.

Data flows one way (paper 000 Fig. 2):
identity params -> identity backend -> native rest mesh -> TopologyTransfer -> canonical rest
mesh -> SkeletonTransfer -> rest joint transforms T_k; pose -> FK -> G_k; LBS with G_k T_k^-1.

Pose convention (paper 001, compatible with py-soma-x): ``pose`` holds local rotations of
joints 1..77 (Hips first; it carries the global orientation). By default they are
T-pose-relative, R_abs,j = O_p(j)^T R_rel,j O_j with O the T-pose world orientations, so the
zero pose is the T-pose; ``absolute=True`` takes R_abs,j directly. ``transl`` is the Hips
world position (the origin when omitted). Units: metres; Y up; the body faces +Z.

Differences from py-soma-x at the boundary: ``BodyOutput.joints`` includes Root (78 rows,
Root at the origin); drop row 0 for the official (B, 77, 3).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

import torch
from torch import nn

from ._checks import check_finite, check_like, check_shape, check_tensor
from .geometry.kinematics import (
    KinematicTree,
    batch_major,
    chain,
    compose,
    homogeneous,
    joint_major,
    pose_transforms,
    posed_local,
    rest_inverse,
)
from .geometry.rotations import axis_angle_to_matrix, rot6d_to_matrix
from .geometry.skinning import (
    Skinning,
    lbs_joint_major,
    register_skin_layout,
    registered_skin_layout,
    skin_layout,
    skin_values,
)
from .identity.base import IdentityBackend, check_identity_backend
from .rig import Rig
from .skeleton import SkeletonTransfer

if TYPE_CHECKING:
    from .correctives.model import Correctives
    from .procedural import ProceduralDefinition, ProceduralTwist
    from .topology import TopologyTransfer

__all__ = ["BodyLayer", "BodyOutput", "PreparedIdentity"]

ROTATION_TOLERANCE = {torch.float64: 1e-5, torch.float32: 1e-3}
"""Rotation-matrix poses must satisfy ``max |R^T R - I| <= tol`` and ``det R > 0``; 6D poses
need ``sin`` of the angle between their halves ``>= tol``. float64 admits float32 data cast up
(error ~1e-7); float32 admits matrices composed or stored in float32 (~1e-6) with room to spare,
and 1e-3 still bounds the scale error of a skinned vertex by 1 mm per metre. Other dtypes: 1e-3."""
R6D_MIN_NORM = 1e-6
"""Each 3-vector half of a 6D pose needs a norm of at least this (and a finite one)."""
REST_EXTENT_M = (0.1, 10.0)
"""Bounding-box diagonal (m) a rest mesh must have: a newborn's is ~0.6 m and a 3 m giant's
~4 m; below 0.1 m a mesh is collapsed or scaled down, above 10 m it is in cm or mm."""


def _local_math(pose: torch.Tensor, kind: int, absolute: bool, left: torch.Tensor, right: torch.Tensor) -> torch.Tensor:
    """Checked pose (B, 77, ...) of ``kind`` 0 axis-angle, 1 matrices, 2 6D -> joint-major (J, 3, 3, B).

    Absolute local rotations, Root (row 0) = I; T-pose-relative ones are turned absolute with
    the factors ``left`` = O_p(j)^T and ``right`` = O_j, each (77, 3, 3).
    """
    rot = joint_major((axis_angle_to_matrix, lambda r: r, rot6d_to_matrix)[kind](pose))
    if not absolute:
        rot = compose(joint_major(left[None]), compose(rot, joint_major(right[None])))
    eye = torch.eye(3, dtype=rot.dtype, device=rot.device)[None, ..., None].expand(1, 3, 3, rot.shape[3])
    return torch.cat([eye, rot], dim=0)


def _rig_math(
    tree: KinematicTree,
    local: torch.Tensor,
    offsets: torch.Tensor,
    transl: torch.Tensor,
    rest_rot: torch.Tensor,
    rest_pos: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """FK of joint-major local rotations: world transforms (B, J, 4, 4) and skinning ones (J, 4, 3, B)."""
    world = chain(tree, posed_local(local, offsets, transl))
    mats = compose(world, rest_inverse(rest_rot, rest_pos))
    world = world.permute(3, 0, 2, 1)  # (B, J, 3, 4)
    bottom = world.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(*world.shape[:2], 1, 4)
    return torch.cat([world, bottom], dim=-2), mats


def _pose_math(
    tree: KinematicTree,
    pose: torch.Tensor,
    kind: int,
    absolute: bool,
    left: torch.Tensor,
    right: torch.Tensor,
    offsets: torch.Tensor,
    transl: torch.Tensor,
    rest_rot: torch.Tensor,
    rest_pos: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`_local_math` then :func:`_rig_math`: the dense part of posing, one compilable graph."""
    return _rig_math(tree, _local_math(pose, kind, absolute, left, right), offsets, transl, rest_rot, rest_pos)


@functools.cache
def _compiled_pose_math() -> Callable[..., tuple[torch.Tensor, torch.Tensor]]:
    """:func:`_pose_math` through ``torch.compile`` (one graph for every batch size)."""
    return torch.compile(_pose_math, dynamic=True)


def outside_rest_extent(rest: torch.Tensor) -> tuple[int, float] | None:
    """(mesh, bounding-box diagonal in m) of the first of rest meshes (B, V, 3) whose diagonal lies
    outside :data:`REST_EXTENT_M` (no body is that small or large), or None."""
    with torch.no_grad():
        low, high = torch.aminmax(rest, dim=1)  # one pass
        diag = torch.linalg.vector_norm(high - low, dim=-1)
        lo, hi = REST_EXTENT_M
        bad = ~((diag >= lo) & (diag <= hi))
        if not bool(bad.any()):
            return None
        b = int(bad.nonzero()[0, 0])
        return b, float(diag[b])


@dataclass(frozen=True, slots=True)
class PreparedIdentity:
    """An identity fitted once, posed many times (``Bi`` is 1 or the pose batch).

    Attributes:
        rest_vertices: (Bi, V, 3) m, canonical rest mesh.
        rest_rotations: (Bi, J, 3, 3) world rotations of the fitted joints at rest.
        rest_joints: (Bi, J, 3) m, world positions of the fitted joints at rest.
        offsets: (Bi, J, 3) m, each joint's position in its parent's rest frame.
        skin_values: (Bi, 4 nnz) the rest mesh's sparse skinning matrix values
            (:func:`~unibody.geometry.skinning.skin_values`), which :meth:`BodyLayer.prepare_rest`
            keeps for a single identity so that posing it again skips rebuilding them (1 MB in
            float32; 0.3-0.8 ms of a batch-1 pose). None for Bi > 1: those are posed by blending
            the transforms, which needs no per-identity values. Not a constructor argument: an identity
            built or ``dataclasses.replace``-d by hand has None, and posing rebuilds them from
            its own ``rest_vertices``, so they can never belong to another mesh.
    """

    rest_vertices: torch.Tensor
    rest_rotations: torch.Tensor
    rest_joints: torch.Tensor
    offsets: torch.Tensor
    skin_values: torch.Tensor | None = field(default=None, init=False, repr=False, compare=False)

    @property
    def batch_size(self) -> int:
        return self.rest_vertices.shape[0]

    def detach(self) -> PreparedIdentity:
        """The same identity cut from the autograd graph."""
        out = PreparedIdentity(
            *(t.detach() for t in (self.rest_vertices, self.rest_rotations, self.rest_joints, self.offsets))
        )
        return out._keep(None if self.skin_values is None else self.skin_values.detach())

    def _keep(self, skin_values: torch.Tensor | None) -> PreparedIdentity:
        """Attach the skinning values of this identity's own rest mesh (BodyLayer only)."""
        object.__setattr__(self, "skin_values", skin_values)  # frozen: a derived cache, set once
        return self


@dataclass(frozen=True, slots=True)
class BodyOutput:
    """A posed batch.

    Attributes:
        vertices: (B, V, 3) m, posed mesh, world frame; for B > 1 a view of vertex-major
            (V, B, 3) storage, the sparse product's own layout (``.contiguous()`` packs it,
            ``.reshape`` works where ``.view`` does not).
        joints: (B, J, 3) m, posed joint positions, Root included (row 0, at the origin).
        transforms: (B, J, 4, 4) posed world transforms G_k of the joints.
        rest_vertices: (B, V, 3) m, the canonical rest mesh of each item (may be a broadcast view).
    """

    vertices: torch.Tensor
    joints: torch.Tensor
    transforms: torch.Tensor
    rest_vertices: torch.Tensor


class BodyLayer(nn.Module):
    """The unified body: pose any identity with the canonical 78-joint rig.

    Args:
        rig: the canonical rig.
        identity: an identity backend, an ``nn.Module`` implementing
            :class:`~unibody.identity.base.IdentityBackend` (``params (B, K) -> native rest
            mesh``), or None to pose canonical rest meshes given directly (:meth:`prepare_rest`).
        topology: the transfer from the backend's native topology; None when the backend
            already produces canonical meshes.
        procedural: procedural twist joints (paper 001): True for the sidecar shipped with
            unibody (upper arms, forearms, thighs, shins), or a parsed
            :class:`~unibody.procedural.ProceduralDefinition`. The pose stays 77 joints and
            the outputs 78 public joints; the expanded skeleton is internal.
        correctives: pose correctives (paper 000 §3.5.2, :mod:`unibody.correctives`): True for
            the weights shipped with unibody (with ``procedural``, those trained for the twist rig,
            ``correctives_twist.pt``; else ``correctives.pt``), or a loaded
            :class:`~unibody.correctives.model.Correctives`, used as given; applied by
            :meth:`pose` unless it is told ``correctives=False``.

    Raises:
        TypeError: ``identity`` is not an nn.Module implementing IdentityBackend (the message
            names the missing members), or ``procedural`` is neither a bool nor a definition,
            or ``correctives`` neither a bool nor a Correctives.
    """

    def __init__(
        self,
        rig: Rig,
        identity: IdentityBackend | None = None,
        topology: TopologyTransfer | None = None,
        *,
        procedural: bool | ProceduralDefinition = False,
        correctives: bool | Correctives = False,
    ) -> None:
        super().__init__()
        if identity is not None:
            check_identity_backend(identity)
        self.twist: ProceduralTwist | None = None
        if procedural is not False:
            from .procedural import ProceduralDefinition, ProceduralTwist, canonical_definition

            if procedural is True:
                procedural = canonical_definition()
            if not isinstance(procedural, ProceduralDefinition):
                raise TypeError(
                    f"procedural: expected a bool or a ProceduralDefinition, got {type(procedural).__name__}"
                )
            self.twist = ProceduralTwist(procedural, rig)
        self.rig_tree = rig.tree
        self.joint_names = rig.joint_names
        self.identity = identity
        self.topology = topology
        self.skeleton = SkeletonTransfer(rig)
        parents = torch.tensor([max(p, 0) for p in rig.tree.parents])
        self.register_buffer("parents", parents, persistent=False)
        self.register_buffer("tpose_orient", rig.tpose_orient, persistent=False)
        # R_abs,j = O_p(j)^T R_rel,j O_j: both factors per posed joint, gathered once; int32
        # parents for the Warp kernel.
        orient = rig.tpose_orient
        self.register_buffer("_tpose_left", orient[parents[1:]].transpose(-1, -2).contiguous(), persistent=False)
        self.register_buffer("_tpose_right", orient[1:].contiguous(), persistent=False)
        self.register_buffer("_parents32", parents.to(torch.int32), persistent=False)
        self.register_buffer("faces", rig.faces, persistent=False)
        self.register_buffer("skin_weight", rig.skin_weight, persistent=False)
        register_skin_layout(self, skin_layout(rig.skin_vertex, rig.skin_joint, rig.num_vertices, rig.num_joints))
        self.num_vertices, self.num_joints = rig.num_vertices, rig.num_joints
        self._compiled = False
        self.correctives: Correctives | None = None
        if correctives is not False:
            from .correctives.model import Correctives

            if correctives is True:  # the twist rig has its own weights: the twist is not corrected twice
                correctives = Correctives.load(procedural=self.twist is not None)
            if not isinstance(correctives, Correctives):
                raise TypeError(f"correctives: expected a bool or a Correctives, got {type(correctives).__name__}")
            self.correctives = correctives
            # Where its displacements are skinned: the twist rig's weights when there is one.
            skinning = self.skinning if self.twist is None else self.twist.skinning
            for k, v in correctives.skin_binding(skinning).items():
                self.register_buffer(f"_corr_{k}", v, persistent=False)

    @classmethod
    def from_anny(
        cls,
        *,
        local_changes: str | tuple[str, ...] = "none",
        phenotypes: Literal["default", "all"] = "default",
        procedural: bool | ProceduralDefinition = False,
        correctives: bool | Correctives = False,
        dtype: torch.dtype = torch.float32,
    ) -> BodyLayer:
        """The canonical rig with Anny as identity backend (offline, from the ``anny`` package).

        ``phenotypes="all"`` builds Anny with py-soma-x's eleven phenotypes (six given: the other
        five at 0.5, as py-soma-x fills them); the default six-phenotype model gives the same
        bodies at those defaults and is twice as fast (:class:`~unibody.identity.anny.AnnyIdentity`).
        """
        from .identity.anny import AnnyIdentity
        from .topology import TopologyTransfer

        identity = AnnyIdentity.create(local_changes=local_changes, phenotypes=phenotypes)
        layer = cls(
            Rig.canonical(), identity, TopologyTransfer.from_anny(), procedural=procedural, correctives=correctives
        )
        return layer.to(dtype)

    @classmethod
    def from_pca(
        cls,
        space: str = "v1",
        *,
        num_components: int | None = 128,
        procedural: bool | ProceduralDefinition = False,
        correctives: bool | Correctives = False,
        dtype: torch.dtype = torch.float32,
    ) -> BodyLayer:
        """The canonical rig with a native PCA shape space (canonical meshes, no transfer).

        Args:
            space: a shipped space by name, "v1" (the default, Anny's space) or "v2" (broader,
                Hips-placed; docs/shape_spaces.md), or the path (str or ``pathlib.Path``) of a
                ``.npz`` written by ``unibody shape-space build``.
            num_components: K, the leading components kept; None for all of the asset's.
        """
        from .identity.pca import PCAIdentity

        identity = PCAIdentity.from_asset(space, num_components=num_components, dtype=dtype)
        return cls(Rig.canonical(), identity, None, procedural=procedural, correctives=correctives).to(dtype)

    @classmethod
    def from_identity(
        cls,
        identity: IdentityBackend,
        *,
        procedural: bool | ProceduralDefinition = False,
        correctives: bool | Correctives = False,
        dtype: torch.dtype = torch.float32,
    ) -> BodyLayer:
        """Any identity backend on a foreign topology (SMPL family, MHR, GarmentMeasurements, ...).

        Its template mesh (``identity.template()``, ``identity.faces()``) is registered onto the
        canonical mesh automatically (:mod:`unibody.registration`; cached per template, so only
        the first call for a new template takes minutes).
        """
        from .registration import topology_transfer

        check_identity_backend(identity)
        with torch.no_grad():
            template, faces = identity.template().double(), identity.faces()
        topology = topology_transfer(template, faces, name=identity.name)
        return cls(Rig.canonical(), identity, topology, procedural=procedural, correctives=correctives).to(dtype)

    def bind_local_rotations(self) -> torch.Tensor:
        """(1, 77, 3, 3) absolute local rotations of the rig's bind (A-)pose, R_bind,parent^T R_bind,k."""
        rot = self.skeleton.bind_rot
        return (rot[self.parents[1:]].transpose(-1, -2) @ rot[1:])[None]

    def repose_to_bind(self, prepared: PreparedIdentity) -> torch.Tensor:
        """Rest meshes (B, V, 3) of prepared identities reposed to the bind A-pose, m.

        Every joint gets its bind local rotation, the Hips keep the identity's rest position:
        the posed skeleton's world rotations are exactly the bind ones, so shapes of any backend
        become comparable (paper 000 §4.4; the native PCA is built on such meshes).
        """
        b = prepared.rest_joints.shape[0]
        local = self.bind_local_rotations().expand(b, -1, -1, -1)
        return self.pose(prepared, local, transl=prepared.rest_joints[:, 1], absolute=True).vertices

    def prepare_rest(self, rest_vertices: torch.Tensor) -> PreparedIdentity:
        """Fit the skeleton to canonical rest meshes (B, V, 3), metres.

        A single identity also keeps its skinning values (:attr:`PreparedIdentity.skin_values`),
        so that posing it again is cheaper.

        Raises:
            TypeError: ``rest_vertices`` is not a tensor, or not of the layer's dtype and device.
            ValueError: wrong shape, NaN/inf values, or a bounding-box diagonal outside
                :data:`REST_EXTENT_M` (0.1 to 10 m): a collapsed mesh, or one not in metres.
        """
        prepared = self._fit_rest(rest_vertices)
        if rest_vertices.shape[0] != 1:  # many identities are posed by blending (geometry.skinning)
            return prepared
        return prepared._keep(skin_values(rest_vertices, self.skin_weight, registered_skin_layout(self)))

    def _fit_rest(self, rest_vertices: torch.Tensor) -> PreparedIdentity:
        """:meth:`prepare_rest` without the kept skinning values (identities posed once)."""
        check_shape(rest_vertices, f"B {self.num_vertices} 3", name="rest_vertices")
        check_like(rest_vertices, self.tpose_orient, name="rest_vertices")
        check_finite(rest_vertices, "rest_vertices")
        if rest_vertices.shape[0]:
            self._check_extent(rest_vertices)
        rot, pos = self.skeleton.fit(rest_vertices)
        rp_t = rot[:, self.parents].transpose(-1, -2)
        offsets = (rp_t @ (pos - pos[:, self.parents])[..., None]).squeeze(-1)
        return PreparedIdentity(rest_vertices, rot, pos, offsets)

    @staticmethod
    def _check_extent(rest: torch.Tensor) -> None:
        """ValueError unless every mesh's bounding-box diagonal lies in :data:`REST_EXTENT_M`."""
        found = outside_rest_extent(rest)
        if found is None:
            return
        b, d = found
        lo, hi = REST_EXTENT_M
        if d == 0:
            why = "the mesh is collapsed to a point"
        elif d < lo:
            why = "the mesh is collapsed or scaled down (not in metres?)"
        elif d == float("inf"):
            why = "its coordinates are far beyond any body (the extent overflows)"
        else:  # a human body's diagonal is ~2 m: ~200 in centimetres, ~2000 in millimetres
            unit = "millimetres (divide by 1000)" if d > 600 else "centimetres (divide by 100)"
            why = f"the mesh is not in metres: in {unit}?"
        raise ValueError(
            f"rest_vertices: bounding-box diagonal {d:.4g} m at batch {b} is outside [{lo:g}, {hi:g}] m; {why}"
        )

    def prepare_identity(self, params: torch.Tensor) -> PreparedIdentity:
        """Run the identity backend, the topology transfer and the skeleton fit once.

        Args:
            params: (B, K) the backend's identity parameters (for Anny: 6 phenotypes in
                [0, 1], then local changes).
        """
        return self.prepare_rest(self._rest_mesh(params))

    def _rest_mesh(self, params: torch.Tensor) -> torch.Tensor:
        """Canonical rest meshes (B, V, 3) of identity parameters: the backend, then the transfer."""
        if self.identity is None:
            raise ValueError("params: this layer has no identity backend; use prepare_rest(vertices)")
        rest = self.identity(params)
        return rest if self.topology is None else self.topology(rest)

    @property
    def skinning(self) -> Skinning:
        """The sparse skinning weights (vertex, joint, weight, CSR rows), read-only.

        Built from the layer's buffers on each access, so it follows ``.to()``: on the layer's
        device, weights in its dtype. Solvers use this view, never the private buffers.
        """
        return Skinning(
            self._skin_vertex, self._skin_joint, self.skin_weight, self._skin_w_crow, self.num_vertices, self.num_joints
        )

    def local_rotations(self, pose: torch.Tensor, *, absolute: bool = False) -> torch.Tensor:
        """Checked pose -> absolute local rotations (B, J, 3, 3), Root (row 0) = I.

        The first step of :meth:`pose`, for solvers that run FK and skinning themselves
        (:meth:`skin_transforms`, :meth:`skin_local`).

        Args:
            pose: (B, 77, 3) axis-angle, (B, 77, 3, 3) matrices or (B, 77, 6) continuous 6D,
                local rotations of joints 1..77 (T-pose-relative unless ``absolute``).
            absolute: whether ``pose`` holds absolute local rotations.

        Raises:
            TypeError: ``pose`` is not a tensor of the layer's dtype and device.
            ValueError: a wrong shape, NaN/inf, a non-rotation matrix or a degenerate 6D
                vector (validation as in :meth:`pose`).
        """
        kind = self._check_pose(pose)
        return batch_major(_local_math(pose, kind, absolute, self._tpose_left, self._tpose_right))[0]

    def _check_pose(self, pose: torch.Tensor, values: bool = True) -> int:
        """The pose's kind (0 axis-angle, 1 matrices, 2 6D) after its shape, dtype and (``values``) value checks."""
        p = self.num_joints - 1
        kind = check_shape(pose, f"B {p} 3", f"B {p} 3 3", f"B {p} 6", name="pose")
        check_like(pose, self.tpose_orient, name="pose")
        if values:  # matrices and 6D: their rotation checks also catch NaN/inf (then reported as such)
            (check_finite, self._check_matrices, self._check_rot6d)[kind](pose, "pose")
        return kind

    def compile_posing(self, enable: bool = True) -> BodyLayer:
        """Run the dense part of :meth:`pose` (rotations, FK, skinning transforms) through ``torch.compile``.

        One graph serves every batch size (``dynamic=True``); the sparse skinning product stays
        eager. It pays off for small batches, where the eager path is dominated by per-operator
        overhead: see ``benchmarks/forward.py --compile`` for the speed-up and the compile time
        (tens of seconds on the first call, once per process). Needs a C++ compiler on the CPU
        (torch inductor). ``compile_posing(False)`` returns to the eager path. Results agree with it to
        float rounding (tests/test_body_fast.py).

        Returns:
            self.
        """
        self._compiled = enable
        return self

    def _worst(self, bad: torch.Tensor, score: torch.Tensor) -> tuple[int, int, str]:
        """(batch, pose index, description) of the bad entry with the largest ``score``."""
        worst = int(torch.where(bad, score, -1.0).flatten().argmax())
        b, j = divmod(worst, bad.shape[1])
        return b, j, f"joint {self.joint_names[j + 1]!r} (pose index {j}, batch {b})"

    def _check_matrices(self, pose: torch.Tensor, name: str = "pose") -> None:
        """ValueError unless every (3, 3) is finite and a rotation within :data:`ROTATION_TOLERANCE`."""
        if not pose.shape[0]:
            return
        tol = ROTATION_TOLERANCE.get(pose.dtype, 1e-3)
        with torch.no_grad():
            eye = torch.eye(3, dtype=pose.dtype, device=pose.device)
            err = (pose.transpose(-1, -2) @ pose - eye).abs().amax((-1, -2))  # (B, P)
            c = pose.unbind(-1)
            det = (c[0] * torch.linalg.cross(c[1], c[2], dim=-1)).sum(-1)
            # One reduction: within tol of orthonormal, |det - 1| <= ~1.5 tol if det > 0, ~2 if not.
            if bool(torch.maximum(err, (1 - det) / 3).amax() <= tol):  # False for NaN
                return
            check_finite(pose, name)
            bad = ~((err <= tol) & (det > 0))
            score = (err + (det <= 0)).nan_to_num(float("inf"))  # reflections rank above small errors
            b, k, where = self._worst(bad, score)
            e, d = float(err[b, k]), float(det[b, k])
        if not e <= tol:  # inf when the entries overflow
            found = f"max |R^T R - I| = {e:.3g} > {tol:g}"
        else:
            found = f"det = {d:.3g} (a reflection, not a rotation)"
        raise ValueError(
            f"{name}: rotation matrix of {where} is not a rotation: {found} "
            f"(expected orthonormal with det +1 within {tol:g} for {str(pose.dtype).removeprefix('torch.')}; "
            "project approximate ones with unibody.geometry.rotations.orthonormalize)"
        )

    def _check_rot6d(self, pose: torch.Tensor, name: str = "pose") -> None:
        """ValueError unless both halves of every 6D vector are finite, non-zero and not (near-)parallel."""
        if not pose.shape[0]:
            return
        tol = ROTATION_TOLERANCE.get(pose.dtype, 1e-3)
        with torch.no_grad():
            halves = pose.unflatten(-1, (2, 3))
            n = torch.linalg.vector_norm(halves, dim=-1)  # (B, P, 2); inf if it overflows
            u = halves / n.clamp_min(R6D_MIN_NORM)[..., None]  # 0 where n = inf: sin = 0 below
            sin = torch.linalg.vector_norm(torch.linalg.cross(u[..., 0, :], u[..., 1, :], dim=-1), dim=-1)
            # One reduction: ok iff both norms >= R6D_MIN_NORM and sin >= tol (False for NaN).
            score = torch.minimum(n.amin(-1) / R6D_MIN_NORM, sin / tol)
            if bool(score.amin() >= 1):
                return
            check_finite(pose, name)
            ok_n = (n.amin(-1) >= R6D_MIN_NORM) & torch.isfinite(n).all(-1)
            bad = ~(ok_n & (sin >= tol))
            b, k, where = self._worst(bad, torch.where(ok_n, 1 - sin, 2.0))  # zero/huge halves first
            m1, m2, s, norms_ok = float(n[b, k, 0]), float(n[b, k, 1]), float(sin[b, k]), bool(ok_n[b, k])
        if not norms_ok:
            found = f"its 3-vectors have norms {m1:.3g} and {m2:.3g} (expected finite and >= {R6D_MIN_NORM:g})"
        else:
            found = f"its 3-vectors are (near-)parallel, |sin angle| = {s:.3g} < {tol:g}"
        raise ValueError(f"{name}: 6D rotation of {where} is degenerate: {found}")

    def pose(
        self,
        prepared: PreparedIdentity,
        pose: torch.Tensor,
        *,
        transl: torch.Tensor | None = None,
        absolute: bool = False,
        check: bool = True,
        correctives: bool | None = None,
    ) -> BodyOutput:
        """Pose a prepared identity.

        Args:
            prepared: from :meth:`prepare_identity` or :meth:`prepare_rest`; batch 1 or B.
            pose: (B, 77, 3) axis-angle (radians), (B, 77, 3, 3) matrices or (B, 77, 6)
                continuous 6D, local rotations of joints 1..77 (T-pose-relative unless
                ``absolute``).
            transl: (B, 3) m, Hips world position; None puts the Hips at the origin.
            absolute: whether ``pose`` holds absolute local rotations.
            check: validate the values of ``pose`` and ``transl`` and guard the outputs (below).
                False skips only that (shapes, dtypes and devices are always checked), for
                inner loops over data already validated; the result is bit-identical.
            correctives: add the pose correctives to the rest mesh before skinning (paper 000
                eq. 7); None follows the layer (on when it was built with ``correctives``).

        Returns:
            BodyOutput with B meshes (B may be 0: empty outputs of the right shapes).
            ``vertices`` is a (B, V, 3) view of vertex-major storage (the sparse product's
            layout, which saves a transposing copy); ``.contiguous()`` packs it.

        Validation: every entry finite. Axis-angle may have any finite magnitude (the angle is
        reduced modulo 2 pi exactly). Matrices must be rotations: ``max |R^T R - I| <= tol``
        and ``det R > 0``, ``tol`` from :data:`ROTATION_TOLERANCE` (1e-3 float32, 1e-5
        float64); they are not projected (do that explicitly with
        :func:`unibody.geometry.rotations.orthonormalize`). 6D: both 3-vectors finite with norm
        >= :data:`R6D_MIN_NORM` and ``|sin|`` of their angle >= ``tol`` (Gram-Schmidt is then
        well conditioned). The checks run without autograd, one batched reduction each (measured
        on one core: +2 % for a B=1 matrix or 6D pose, +5 % at B=32, output guard included);
        the outputs are checked finite too.

        Raises:
            TypeError: ``prepared`` is not a PreparedIdentity; ``pose``/``transl`` not tensors
                of the layer's dtype and device.
            ValueError: a wrong shape, NaN/inf, a non-rotation matrix or a degenerate 6D
                vector (the message names the joint and the batch item), outputs that
                overflowed the dtype, or ``correctives=True`` on a layer without them.
        """
        corr = self._use_correctives(correctives)
        for name, flag in (("absolute", absolute), ("check", check)):
            if not isinstance(flag, bool):  # a truthy string would pass as True
                raise TypeError(f"{name}: expected True or False, got {flag!r}")
        if not isinstance(prepared, PreparedIdentity):
            raise TypeError(f"prepared: expected a PreparedIdentity, got {type(prepared).__name__}")
        check_tensor(pose, "pose")
        b = pose.shape[0]
        if prepared.batch_size not in (1, b):
            raise ValueError(f"prepared: identity batch {prepared.batch_size} must be 1 or the pose batch {b}")
        kind = self._check_pose(pose, check)
        if transl is not None:
            check_shape(transl, "B 3", name="transl", sizes={"B": b})
            check_like(transl, self.tpose_orient, name="transl")
            if check:
                check_finite(transl, "transl")
        else:
            transl = pose.new_zeros(b, 3)
        p = prepared
        left, right = self._tpose_left, self._tpose_right
        mats = None
        if self.twist is not None:
            local = batch_major(_local_math(pose, kind, absolute, left, right))[0]
            args = (p.rest_vertices, p.rest_rotations, p.rest_joints, p.offsets, local, transl)
            # The transforms also bound the outputs (_check_overflow): without them the output
            # guard scanned every vertex, 40 % of a batch-32 pose on one core.
            g_rot, g_pos, vertices, mats = self.twist(*args, with_mats=True)
            if corr is not None:  # LBS of the shared rest mesh, plus the skinned displacements
                rel = corr.rest_relative(local, p.rest_rotations, self.parents, corr.needed)
                vertices = corr.posed(
                    vertices,
                    rel,
                    mats.permute(1, 3, 2, 0),
                    corr.size_of(p.rest_joints),
                    self._corr_binding(),
                    corr.shape_inputs(p.rest_vertices, p.rest_joints),
                )
            world = homogeneous(g_rot, g_pos)
        else:
            dense = self._warp_pose(pose, kind, absolute, p, transl)
            if dense is None:
                math = _compiled_pose_math() if self._compiled else _pose_math
                dense = math(
                    self.rig_tree, pose, kind, absolute, left, right, p.offsets, transl, p.rest_rotations, p.rest_joints
                )
            world, mats = dense
            vertices = self._skin(p, mats)
            if corr is not None:
                rel = corr.world_relative(world, p.rest_rotations, self.parents)
                shape = corr.shape_inputs(p.rest_vertices, p.rest_joints)
                vertices = corr.posed(vertices, rel, mats, corr.size_of(p.rest_joints), self._corr_binding(), shape)
        if check and b:
            self._check_overflow(world, vertices, mats, p.rest_vertices)
        return BodyOutput(vertices, world[..., :3, 3], world, p.rest_vertices.expand(b, -1, -1))

    def _corr_binding(self) -> dict[str, torch.Tensor]:
        """The correctives' skinning binding (``Correctives.skin_binding``), on the layer's device."""
        return {k: getattr(self, f"_corr_{k}") for k in ("crow", "col", "val", "joints")}

    def _use_correctives(self, correctives: bool | None) -> Correctives | None:
        """The correctives model to apply, or None (``pose``'s switch against the layer's)."""
        if correctives is None or correctives is False:
            return None if correctives is False else self.correctives
        if correctives is not True:
            raise TypeError(f"correctives: expected a bool or None, got {type(correctives).__name__}")
        if self.correctives is None:
            raise ValueError(
                "correctives: True, but this layer has none; build it with correctives=True "
                "(BodyLayer.from_anny(correctives=True), from_pca(...), BodyLayer(..., correctives=True))"
            )
        return self.correctives

    def _warp_pose(
        self, pose: torch.Tensor, kind: int, absolute: bool, p: PreparedIdentity, transl: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The dense part of posing through the Warp kernel (``geometry/_warp/posing.py``), or None.

        None (take the torch path) when gradients may be needed, for dtypes other than float32,
        in compiled mode, for axis-angles beyond its :data:`~unibody.geometry._warp.posing.MAX_ANGLE`,
        and when Warp cannot run here (then once with a warning).
        """
        from .geometry._warp import posing

        if pose.dtype != torch.float32 or self._compiled or pose.device.type not in ("cpu", "cuda"):
            return None
        tensors = (pose, transl, p.offsets, p.rest_rotations, p.rest_joints)
        if torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
            return None
        if kind == 2:
            pose, kind = rot6d_to_matrix(pose), 1
        elif kind == 0 and pose.shape[0] and not bool(pose.abs().amax() <= posing.MAX_ANGLE):
            return None
        if not posing.available():
            return None
        try:
            return posing.pose_transforms(
                self._parents32,
                pose,
                kind == 1,
                not absolute,
                self._tpose_left,
                self._tpose_right,
                p.offsets,
                transl,
                p.rest_rotations,
                p.rest_joints,
            )
        except Exception as exc:  # a Warp that cannot compile or launch here: torch from now on
            posing.disable(f"{type(exc).__name__}: {exc}")
            return None

    def _skin(self, prepared: PreparedIdentity, mats: torch.Tensor) -> torch.Tensor:
        """LBS of the prepared rest mesh by joint-major skinning transforms (J, 4, 3, B)."""
        layout = registered_skin_layout(self)
        return lbs_joint_major(prepared.rest_vertices, mats, self.skin_weight, layout, prepared.skin_values)

    @staticmethod
    def _check_overflow(
        world: torch.Tensor, vertices: torch.Tensor, mats: torch.Tensor | None, rest: torch.Tensor
    ) -> None:
        """ValueError if posing overflowed (checked inputs cannot, but a huge transl or prepared identity can).

        Each vertex coordinate is a convex combination (weights >= 0, sum 1) of ``M_k [v; 1]``,
        so ``|v'| <= 4 max|M| max(|v|, 1)``: when that bound and the joints are finite, so are
        the vertices, and the O(B V) scan of them is skipped (it cost 5-15 % at B = 32).
        """
        with torch.no_grad():
            big = torch.finfo(world.dtype).max
            if mats is not None:
                size = torch.stack([t.abs().amax() for t in (mats, world)] + [x.abs() for x in torch.aminmax(rest)])
                bound = 4 * size[0] * size[2:].amax().clamp_min(1) + size[1]
                if bool(bound < big):  # False for NaN
                    return
            if torch.isfinite(vertices).all() and torch.isfinite(world).all():
                return
        raise ValueError(
            "pose: posing gave non-finite vertices or joints (the floating-point range overflowed); "
            "check the magnitudes of transl and of the prepared identity"
        )

    def skin_local(
        self, prepared: PreparedIdentity, local_rot: torch.Tensor, transl: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """FK + LBS from absolute local rotations, without input checks (for solvers).

        With procedural twist the twist joints are evaluated in between (internally).

        Args:
            prepared: the identity (batch 1 or B).
            local_rot: (B, J, 3, 3) absolute local rotations, Root included (row 0).
            transl: (B, 3) m, Hips world position.

        Returns:
            ``(world_rot (B, J, 3, 3), world_pos (B, J, 3), vertices (B, V, 3))``.
        """
        p = prepared
        if self.twist is not None:
            return self.twist(p.rest_vertices, p.rest_rotations, p.rest_joints, p.offsets, local_rot, transl)
        world, mats = _rig_math(
            self.rig_tree, joint_major(local_rot), p.offsets, transl, p.rest_rotations, p.rest_joints
        )
        return world[..., :3, :3], world[..., :3, 3], self._skin(p, mats)

    def skin_transforms(
        self, prepared: PreparedIdentity, local_rot: torch.Tensor, transl: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """FK and skinning transforms: ``(world_rot, world_pos, mats (B, J, 3, 4))``, mats = G T^-1.

        The public joints only (plain LBS): procedural twist joints are not included.
        """
        p = prepared
        return pose_transforms(self.rig_tree, local_rot, p.offsets, transl, p.rest_rotations, p.rest_joints)

    def to_relative(self, local_rot: torch.Tensor) -> torch.Tensor:
        """Absolute local rotations (..., 77, 3, 3) -> T-pose-relative: O_p R_abs O_j^T (paper 001)."""
        check_tensor(local_rot, "local_rot")
        n = self.num_joints - 1
        if tuple(local_rot.shape[-3:]) != (n, 3, 3):
            raise ValueError(f"local_rot: expected shape (..., {n}, 3, 3), got {tuple(local_rot.shape)}")
        check_like(local_rot, self.tpose_orient, name="local_rot")
        o = self.tpose_orient
        return o[self.parents[1:]] @ local_rot @ o[1:].transpose(-1, -2)

    def forward(
        self, params: torch.Tensor, pose: torch.Tensor, *, transl: torch.Tensor | None = None, absolute: bool = False
    ) -> BodyOutput:
        """Identity parameters (B or 1, K) and pose (B, 77, ...) -> BodyOutput (see :meth:`pose`).

        The identity is used once, so it keeps no skinning values: its meshes are skinned by
        blending (``geometry.skinning``), cheaper than building them for one use.
        """
        return self.pose(self._fit_rest(self._rest_mesh(params)), pose, transl=transl, absolute=absolute)
