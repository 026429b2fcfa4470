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

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import nn

from ._checks import check_finite, check_like, check_shape, check_tensor
from .geometry.kinematics import pose_transforms
from .geometry.rotations import axis_angle_to_matrix, rot6d_to_matrix
from .geometry.skinning import lbs_sparse, register_skin_layout, registered_skin_layout, skin_layout
from .rig import Rig
from .skeleton import SkeletonTransfer

if TYPE_CHECKING:
    from .procedural import ProceduralDefinition, ProceduralTwist
    from .topology import TopologyTransfer

__all__ = ["BodyLayer", "BodyOutput", "PreparedIdentity"]


@dataclass(frozen=True, slots=True)
class PreparedIdentity:
    """An identity fitted once, posed many times (``Bi`` is 1 or the pose batch).

    Attributes:
        rest_vertices: (Bi, V, 3) m, canonical rest mesh.
        rest_rotations: (Bi, J, 3, 3) world rotations of the fitted joints at rest.
        rest_joints: (Bi, J, 3) m, world positions of the fitted joints at rest.
        offsets: (Bi, J, 3) m, each joint's position in its parent's rest frame.
    """

    rest_vertices: torch.Tensor
    rest_rotations: torch.Tensor
    rest_joints: torch.Tensor
    offsets: torch.Tensor

    @property
    def batch_size(self) -> int:
        return self.rest_vertices.shape[0]


@dataclass(frozen=True, slots=True)
class BodyOutput:
    """A posed batch.

    Attributes:
        vertices: (B, V, 3) m, posed mesh, world frame.
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
        identity: an identity backend (``params (B, K) -> native rest mesh``), or None to
            pose canonical rest meshes given directly (:meth:`prepare_rest`).
        topology: the transfer from the backend's native topology; None when the backend
            already produces canonical meshes.
        procedural: procedural twist joints (paper 001): True for the sidecar shipped with
            unibody (upper arms, forearms, thighs, shins), or a parsed
            :class:`~unibody.procedural.ProceduralDefinition`. The pose stays 77 joints and
            the outputs 78 public joints; the expanded skeleton is internal.
    """

    def __init__(
        self,
        rig: Rig,
        identity: nn.Module | None = None,
        topology: TopologyTransfer | None = None,
        *,
        procedural: bool | ProceduralDefinition = False,
    ) -> None:
        super().__init__()
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
        self.register_buffer("faces", rig.faces, persistent=False)
        self.register_buffer("skin_weight", rig.skin_weight, persistent=False)
        register_skin_layout(self, skin_layout(rig.skin_vertex, rig.skin_joint, rig.num_vertices, rig.num_joints))
        self.num_vertices, self.num_joints = rig.num_vertices, rig.num_joints

    @classmethod
    def from_anny(
        cls,
        *,
        local_changes: str | tuple[str, ...] = "none",
        procedural: bool | ProceduralDefinition = False,
        dtype: torch.dtype = torch.float32,
    ) -> BodyLayer:
        """The canonical rig with Anny as identity backend (offline, from the ``anny`` package)."""
        from .identity.anny import AnnyIdentity
        from .topology import TopologyTransfer

        identity = AnnyIdentity.create(local_changes=local_changes)
        return cls(Rig.canonical(), identity, TopologyTransfer.from_anny(), procedural=procedural).to(dtype)

    @classmethod
    def from_pca(
        cls,
        *,
        num_components: int = 128,
        procedural: bool | ProceduralDefinition = False,
        dtype: torch.dtype = torch.float32,
    ) -> BodyLayer:
        """The canonical rig with unibody's native PCA shape space (canonical meshes, no transfer)."""
        from .identity.pca import PCAIdentity

        identity = PCAIdentity.from_asset(num_components=num_components, dtype=dtype)
        return cls(Rig.canonical(), identity, None, procedural=procedural).to(dtype)

    @classmethod
    def from_identity(
        cls, identity: nn.Module, *, procedural: bool | ProceduralDefinition = False, dtype: torch.dtype = torch.float32
    ) -> BodyLayer:
        """Any identity backend on a foreign topology (SMPL family, MHR, GarmentMeasurements, ...).

        Its template mesh (``identity.template()``, ``identity.faces()``) is registered onto the
        canonical mesh automatically (:mod:`unibody.registration`; cached per template, so only
        the first call for a new template takes minutes).
        """
        from .registration import topology_transfer

        with torch.no_grad():
            template, faces = identity.template().double(), identity.faces()
        topology = topology_transfer(template, faces, name=identity.name)
        return cls(Rig.canonical(), identity, topology, procedural=procedural).to(dtype)

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
        """Fit the skeleton to canonical rest meshes (B, V, 3), metres."""
        rot, pos = self.skeleton(rest_vertices)
        rp_t = rot[:, self.parents].transpose(-1, -2)
        offsets = (rp_t @ (pos - pos[:, self.parents])[..., None]).squeeze(-1)
        return PreparedIdentity(rest_vertices, rot, pos, offsets)

    def prepare_identity(self, params: torch.Tensor) -> PreparedIdentity:
        """Run the identity backend, the topology transfer and the skeleton fit once.

        Args:
            params: (B, K) the backend's identity parameters (for Anny: 6 phenotypes in
                [0, 1], then local changes).
        """
        if self.identity is None:
            raise ValueError("params: this layer has no identity backend; use prepare_rest(vertices)")
        rest = self.identity(params)
        if self.topology is not None:
            rest = self.topology(rest)
        return self.prepare_rest(rest)

    def _local_rotations(self, pose: torch.Tensor, absolute: bool) -> torch.Tensor:
        """(B, P, 3 | 3x3 | 6) -> absolute local rotations (B, J, 3, 3), Root = I."""
        p = self.num_joints - 1
        kind = check_shape(pose, f"B {p} 3", f"B {p} 3 3", f"B {p} 6", name="pose")
        check_like(pose, self.tpose_orient, name="pose")
        check_finite(pose, "pose")
        rot = (axis_angle_to_matrix, lambda r: r, rot6d_to_matrix)[kind](pose)
        if not absolute:
            o = self.tpose_orient  # R_abs,j = O_p(j)^T R_rel,j O_j
            rot = o[self.parents[1:]].transpose(-1, -2) @ rot @ o[1:]
        eye = torch.eye(3, dtype=rot.dtype, device=rot.device).expand(rot.shape[0], 1, 3, 3)
        return torch.cat([eye, rot], dim=1)

    def pose(
        self,
        prepared: PreparedIdentity,
        pose: torch.Tensor,
        *,
        transl: torch.Tensor | None = None,
        absolute: bool = False,
    ) -> BodyOutput:
        """Pose a prepared identity.

        Args:
            prepared: from :meth:`prepare_identity` or :meth:`prepare_rest`; batch 1 or B.
            pose: (B, 77, 3) axis-angle (radians), (B, 77, 3, 3) matrices or (B, 77, 6)
                continuous 6D, local rotations of joints 1..77 (T-pose-relative unless
                ``absolute``).
            transl: (B, 3) m, Hips world position; None puts the Hips at the origin.
            absolute: whether ``pose`` holds absolute local rotations.

        Returns:
            BodyOutput with B meshes.
        """
        if not isinstance(prepared, PreparedIdentity):
            raise TypeError(f"prepared: expected a PreparedIdentity, got {type(prepared).__name__}")
        check_tensor(pose, "pose")
        b = pose.shape[0]
        if prepared.batch_size not in (1, b):
            raise ValueError(f"prepared: identity batch {prepared.batch_size} must be 1 or the pose batch {b}")
        local_r = self._local_rotations(pose, absolute)
        if transl is not None:
            check_shape(transl, "B 3", name="transl", sizes={"B": b})
            check_like(transl, self.tpose_orient, name="transl")
            check_finite(transl, "transl")
        else:
            transl = local_r.new_zeros(b, 3)
        g_rot, g_pos, vertices = self.skin_local(prepared, local_r, transl)
        bottom = g_rot.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(b, self.num_joints, 1, 4)
        transforms = torch.cat([torch.cat([g_rot, g_pos[..., None]], dim=-1), bottom], dim=-2)
        return BodyOutput(vertices, g_pos, transforms, prepared.rest_vertices.expand(b, -1, -1))

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
        if self.twist is not None:
            p = prepared
            return self.twist(p.rest_vertices, p.rest_rotations, p.rest_joints, p.offsets, local_rot, transl)
        g_rot, g_pos, mats = self.skin_transforms(prepared, local_rot, transl)
        return g_rot, g_pos, lbs_sparse(prepared.rest_vertices, mats, self.skin_weight, registered_skin_layout(self))

    def skin_transforms(
        self, prepared: PreparedIdentity, local_rot: torch.Tensor, transl: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """FK and skinning transforms: ``(world_rot, world_pos, mats (B, J, 3, 4))``, mats = G T^-1.

        The public joints only (plain LBS): procedural twist joints are not included.
        """
        p = prepared
        return pose_transforms(self.rig_tree, local_rot, p.offsets, transl, p.rest_rotations, p.rest_joints)

    def to_relative(self, local_rot: torch.Tensor) -> torch.Tensor:
        """Absolute local rotations (B, 77, 3, 3) -> T-pose-relative: O_p R_abs O_j^T (paper 001)."""
        o = self.tpose_orient
        return o[self.parents[1:]] @ local_rot @ o[1:].transpose(-1, -2)

    def forward(
        self, params: torch.Tensor, pose: torch.Tensor, *, transl: torch.Tensor | None = None, absolute: bool = False
    ) -> BodyOutput:
        """Identity parameters (B or 1, K) and pose (B, 77, ...) -> BodyOutput (see :meth:`pose`)."""
        return self.pose(self.prepare_identity(params), pose, transl=transl, absolute=absolute)
