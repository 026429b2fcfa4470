"""Procedural twist joints, compiled once and evaluated batched with no loop over joints.

Evaluation order (paper 001): extract channels -> twist angles -> twist rotations -> twist
translations -> forward kinematics -> skinning. Names are resolved to indices once, at
construction; each extraction mode keeps its own sparse slice of the rotation matrix as
(row, column, value) triplets, so ``theta = sum_m M^(m) c^(m)`` is one gather, one channel
evaluation and one ``index_add`` per mode.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import torch
from torch import nn

from ..geometry.kinematics import pose_transforms
from ..geometry.rotations import axis_angle_to_matrix
from ..geometry.skinning import Skinning, lbs_sparse, register_skin_layout, registered_skin_layout, skin_layout
from ..rig import Rig
from .expand import expand_rig, segment_alignment, translation_matrix
from .extract import twist_channel
from .format import AXES, ROTATION_VALUE_LIMIT, ProceduralDefinition, ProceduralFormatError, load

__all__ = ["ProceduralTwist", "canonical_definition"]

CANONICAL_SIDECAR = "canonical_twist.json"


def canonical_definition() -> ProceduralDefinition:
    """The twist sidecar shipped with unibody (upper arms, forearms, thighs, shins)."""
    with resources.as_file(resources.files("unibody.procedural") / "data" / CANONICAL_SIDECAR) as path:
        return load(Path(path))


class ProceduralTwist(nn.Module):
    """A compiled twist definition for one rig: public local rotations -> posed mesh.

    Args:
        definition: the parsed sidecar.
        rig: the public rig it extends (its joint names must be the definition's main joints).

    Attributes:
        expanded: the expanded rig (public joints, then twist joints).
    """

    def __init__(self, definition: ProceduralDefinition, rig: Rig) -> None:
        super().__init__()
        self.definition = definition
        self.expanded = expand_rig(rig, definition)
        self.num_public = rig.num_joints
        names = rig.joint_names
        col = {n: i for i, n in enumerate(names)}
        row = {n: i for i, n in enumerate(definition.twist_joints)}
        segs = [definition.segment_of(n) for n in definition.twist_joints]
        start = torch.tensor([col[s.start] for s in segs])
        end = torch.tensor([col[s.end] for s in segs])
        axis = torch.tensor([AXES.index(s.source_axis) for s in segs])
        sign = torch.tensor([float(s.sign) for s in segs])
        for name, value in (("start", start), ("end", end), ("axis", axis), ("sign", sign)):
            self.register_buffer(f"_{name}", value, persistent=False)
        self.register_buffer("_trans", translation_matrix(definition), persistent=False)
        self.register_buffer("_parents", torch.tensor([max(p, 0) for p in rig.tree.parents]), persistent=False)
        m = definition.rotation
        for i, v in enumerate(m.values):  # a definition built by hand skips parse()
            if not abs(v) <= ROTATION_VALUE_LIMIT:
                raise ProceduralFormatError(
                    f"parameter_matrices.rotation.values[{i}]",
                    f"expected a twist share in [-{ROTATION_VALUE_LIMIT:g}, {ROTATION_VALUE_LIMIT:g}], got {v!r}",
                )
        self.modes = tuple(sorted({definition.rotation_extraction.mode_of(r) for r in m.rows}))
        for mode in self.modes:
            sel = [i for i, r in enumerate(m.rows) if definition.rotation_extraction.mode_of(r) == mode]
            rows = torch.tensor([row[m.rows[i]] for i in sel])
            self.register_buffer(f"_{mode}_rows", rows, persistent=False)
            self.register_buffer(f"_{mode}_cols", torch.tensor([col[m.columns[i]] for i in sel]), persistent=False)
            self.register_buffer(f"_{mode}_vals", torch.tensor([m.values[i] for i in sel]), persistent=False)
        ex = self.expanded
        self.register_buffer("skin_weight", ex.skin_weight, persistent=False)
        register_skin_layout(self, skin_layout(ex.skin_vertex, ex.skin_joint, ex.num_vertices, ex.num_joints))
        self.tree = ex.tree

    @classmethod
    def canonical(cls, rig: Rig | None = None) -> ProceduralTwist:
        """The shipped sidecar compiled for the canonical rig."""
        return cls(canonical_definition(), rig or Rig.canonical())

    @property
    def skinning(self) -> Skinning:
        """The expanded rig's sparse skinning weights (public joints, then twist joints), read-only."""
        lay = registered_skin_layout(self)
        return Skinning(lay.vertex, lay.joint, self.skin_weight, lay.w_crow, lay.num_vertices, lay.num_joints)

    @property
    def num_twist(self) -> int:
        return self.expanded.num_joints - self.num_public

    def angles(self, local_rot: torch.Tensor, rest_rot: torch.Tensor, rest_pos: torch.Tensor) -> torch.Tensor:
        """Twist angles ``theta`` (B, K), before the segment signs.

        Args:
            local_rot: (B, J, 3, 3) absolute local rotations of the public joints.
            rest_rot: (Bi, J, 3, 3) rest world rotations; rest_pos: (Bi, J, 3) rest positions.
        """
        theta = local_rot.new_zeros(local_rot.shape[0], self.num_twist)
        for mode in self.modes:
            rows, cols, vals = (getattr(self, f"_{mode}_{k}") for k in ("rows", "cols", "vals"))
            rest_c = rest_rot[:, cols]
            bind_local = rest_rot[:, self._parents[cols]].transpose(-1, -2) @ rest_c
            d = bind_local.transpose(-1, -2) @ local_rot[:, cols]
            bone = None
            if mode.startswith("aligned"):
                b = rest_pos[:, self._end[rows]] - rest_pos[:, self._start[rows]]
                bone = (rest_c.transpose(-1, -2) @ b[..., None]).squeeze(-1).expand(d.shape[:-1])
            theta = theta.index_add(1, rows, vals.to(d.dtype) * twist_channel(mode, d, bone))
        return theta

    def forward(
        self,
        rest_vertices: torch.Tensor,
        rest_rot: torch.Tensor,
        rest_pos: torch.Tensor,
        offsets: torch.Tensor,
        local_rot: torch.Tensor,
        transl: torch.Tensor,
        *,
        with_mats: bool = False,
    ) -> tuple[torch.Tensor, ...]:
        """FK + LBS through the expanded rig (a :class:`~unibody.body.PreparedIdentity`'s fields).

        Args:
            rest_vertices: (Bi, V, 3); rest_rot: (Bi, J, 3, 3); rest_pos, offsets: (Bi, J, 3).
            local_rot: (B, J, 3, 3) absolute local rotations of the public joints (Root = I).
            transl: (B, 3) m, Hips world position.
            with_mats: also return the expanded rig's skinning transforms.

        Returns:
            ``(world_rot (B, J, 3, 3), world_pos (B, J, 3), vertices (B, V, 3))``, public joints;
            with ``with_mats``, then the (B, J + K, 3, 4) skinning transforms of every joint.
        """
        start = self._start
        align = segment_alignment(rest_rot, rest_pos, start, self._end, self._axis)  # (Bi, K, 3, 3)
        theta = self.angles(local_rot, rest_rot, rest_pos) * self._sign.to(local_rot.dtype)
        axis = nn.functional.one_hot(self._axis, 3).to(theta.dtype)
        twist_rot = align @ axis_angle_to_matrix(axis * theta[..., None])
        twist_pos = torch.einsum("kj,bjc->bkc", self._trans.to(rest_pos.dtype), rest_pos)
        rest_start = rest_rot[:, start]
        twist_off = (rest_start.transpose(-1, -2) @ (twist_pos - rest_pos[:, start])[..., None]).squeeze(-1)
        g_rot, g_pos, mats = pose_transforms(
            self.tree,
            torch.cat([local_rot, twist_rot], 1),
            torch.cat([offsets, twist_off], 1),
            transl,
            torch.cat([rest_rot, rest_start @ align], 1),
            torch.cat([rest_pos, twist_pos], 1),
        )
        vertices = lbs_sparse(rest_vertices, mats, self.skin_weight, registered_skin_layout(self))
        n = self.num_public
        if with_mats:
            return g_rot[:, :n], g_pos[:, :n], vertices, mats
        return g_rot[:, :n], g_pos[:, :n], vertices
