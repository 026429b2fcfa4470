"""Body parts of the canonical mesh for articulated occupancy (paper 002 §4, reference_systems §1.2).

Every vertex goes to the joint that skins it most; small joints are merged into a kinematic
ancestor by name (fingers into the hand, eyes and jaw into the head, toes into the foot, the
shoulders into the chest, ...). That leaves 17 parts, each carried by one joint's posed frame.
A face belongs to the part most of its vertices belong to (*tight* faces); a part's *extended*
faces add those of its parent and children parts, the context its encoder sees.

Self-intersection exclusions are named pairs of parts that touch in ordinary poses (parent and
child, both thighs, the upper arms and the trunk, ...): contact there is anatomy, not a defect.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import torch

from ..rig import Rig

__all__ = ["PART_JOINTS", "MERGED_INTO", "EXCLUDED_PAIRS", "BodyParts"]

# The joints that carry a part, parents before children.
PART_JOINTS: tuple[str, ...] = (
    "Hips", "Spine2", "Chest", "Neck1", "Head",
    "LeftArm", "LeftForeArm", "LeftHand", "RightArm", "RightForeArm", "RightHand",
    "LeftLeg", "LeftShin", "LeftFoot", "RightLeg", "RightShin", "RightFoot",
)  # fmt: skip

# Joints whose vertices join another part (anything under a hand or a foot joins it too).
MERGED_INTO: dict[str, str] = {
    "Root": "Hips", "Spine1": "Hips", "Neck2": "Neck1", "HeadEnd": "Head", "Jaw": "Head",
    "LeftEye": "Head", "RightEye": "Head", "LeftShoulder": "Chest", "RightShoulder": "Chest",
}  # fmt: skip

# Pairs that may touch without it being a self-intersection (besides parent and child parts).
EXCLUDED_PAIRS: tuple[tuple[str, str], ...] = (
    ("LeftLeg", "RightLeg"), ("Hips", "Chest"), ("Spine2", "Neck1"), ("Chest", "Head"),
    ("Hips", "LeftArm"), ("Hips", "RightArm"), ("Spine2", "LeftArm"), ("Spine2", "RightArm"),
    ("Neck1", "LeftArm"), ("Neck1", "RightArm"), ("Spine2", "LeftLeg"), ("Spine2", "RightLeg"),
)  # fmt: skip


def _part_of_joint(rig: Rig) -> list[int]:
    """Part index of every joint of ``rig`` (by name, following parents up to a part joint)."""
    index = {name: k for k, name in enumerate(PART_JOINTS)}
    missing = [name for name in PART_JOINTS if name not in rig.joint_names]
    if missing:
        raise ValueError(f"rig: the part joints {missing} are not in the rig's joint names")
    part = []
    for j, name in enumerate(rig.joint_names):
        walk = j
        while rig.joint_names[walk] not in index and rig.joint_names[walk] not in MERGED_INTO:
            walk = rig.tree.parents[walk]
            if walk < 0:
                raise ValueError(f"rig: joint {name!r} has no part among its ancestors")
        target = rig.joint_names[walk]
        part.append(index[MERGED_INTO.get(target, target)])
    return part


@dataclass(frozen=True, eq=False)
class BodyParts:
    """The part decomposition of the canonical mesh (CPU tensors; modules copy them to buffers).

    Attributes:
        names: K part names (the carrying joint's name).
        joints: (K,) rig index of the joint whose posed transform is the part's frame.
        parents: (K,) parent part, -1 for the Hips.
        vertex_part: (V,) part of every vertex.
        face_part: (F,) part of every face (majority of its vertices; the first vertex's on a tie).
        extended: (K, K) bool, part k's context parts (itself, its parent and its children).
        allowed: (K, K) bool, symmetric: pairs whose overlap counts as a self-intersection.
    """

    names: tuple[str, ...]
    joints: torch.Tensor
    parents: torch.Tensor
    vertex_part: torch.Tensor
    face_part: torch.Tensor
    extended: torch.Tensor
    allowed: torch.Tensor

    @property
    def num_parts(self) -> int:
        return len(self.names)

    @classmethod
    def from_rig(cls, rig: Rig) -> BodyParts:
        """Parts of ``rig``'s mesh from its skinning weights and joint names."""
        joint_part = torch.tensor(_part_of_joint(rig))
        vertex_part = joint_part[rig.dense_skinning_weights().argmax(1)]
        fp = vertex_part[rig.faces.long()]
        face_part = torch.where(fp[:, 1] == fp[:, 2], fp[:, 1], fp[:, 0])
        k = len(PART_JOINTS)
        joints = torch.tensor([rig.joint_names.index(name) for name in PART_JOINTS])
        parents = torch.tensor([-1] + [int(joint_part[rig.tree.parents[int(j)]]) for j in joints[1:]])
        extended = torch.eye(k, dtype=torch.bool)
        extended[torch.arange(1, k), parents[1:]] = True
        extended[parents[1:], torch.arange(1, k)] = True
        allowed = ~extended
        for a, b in EXCLUDED_PAIRS:
            i, j = PART_JOINTS.index(a), PART_JOINTS.index(b)
            allowed[i, j] = allowed[j, i] = False
        counts = torch.bincount(vertex_part, minlength=k)
        if bool((counts == 0).any()):
            raise ValueError(f"rig: parts without vertices: {[PART_JOINTS[i] for i in torch.nonzero(counts == 0)]}")
        return cls(PART_JOINTS, joints, parents, vertex_part, face_part, extended, allowed)

    @staticmethod
    @cache
    def canonical() -> BodyParts:
        """The parts of the canonical rig (cached)."""
        return BodyParts.from_rig(Rig.canonical())
