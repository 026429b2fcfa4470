"""Forward kinematics over a joint tree, one batched step per tree level.

Transforms are kept as a rotation (..., 3, 3) and a translation (..., 3) rather than 4x4
matrices: the bottom row is never multiplied. A joint's world transform is its parent's
world transform composed with its local one: R_w = R_w,p R_l, t_w = R_w,p t_l + t_w,p.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache, cached_property

import torch

__all__ = ["KinematicTree", "forward_kinematics", "pose_transforms", "relative_to_parent"]


@dataclass(frozen=True)
class KinematicTree:
    """A joint hierarchy, hashable, with its breadth-first levels precomputed.

    Attributes:
        parents: parent index per joint, -1 for the root; parents precede children.
        levels: joint indices grouped by depth, root level first.
    """

    parents: tuple[int, ...]

    def __post_init__(self) -> None:
        for j, p in enumerate(self.parents):
            if (p < 0) != (j == 0) or p >= j:
                raise ValueError(
                    f"parents: joint {j} has parent {p}; expected a root at 0 "
                    "and every parent listed before its children"
                )

    @cached_property
    def levels(self) -> tuple[tuple[int, ...], ...]:
        depth = [0] * len(self.parents)
        for j in range(1, len(self.parents)):
            depth[j] = depth[self.parents[j]] + 1
        return tuple(tuple(j for j, d in enumerate(depth) if d == k) for k in range(max(depth) + 1))

    @cached_property
    def children(self) -> tuple[tuple[int, ...], ...]:
        kids: list[list[int]] = [[] for _ in self.parents]
        for j, p in enumerate(self.parents[1:], start=1):
            kids[p].append(j)
        return tuple(tuple(k) for k in kids)


@cache
def _schedule(tree: KinematicTree) -> tuple[tuple[tuple[int, ...], tuple[int, ...]], ...]:
    """Per level: (joints, slot of each joint's parent within the previous level)."""
    steps = []
    for depth, level in enumerate(tree.levels[1:], start=1):
        slot = {j: i for i, j in enumerate(tree.levels[depth - 1])}
        steps.append((level, tuple(slot[tree.parents[j]] for j in level)))
    return tuple(steps)


@cache
def _joint_order(tree: KinematicTree) -> tuple[int, ...]:
    """Position of each joint in the level-major concatenation."""
    flat = [j for level in tree.levels for j in level]
    inverse = [0] * len(flat)
    for pos, j in enumerate(flat):
        inverse[j] = pos
    return tuple(inverse)


@cache
def _index_tensors(
    tree: KinematicTree, device: torch.device
) -> tuple[list[tuple[torch.Tensor, torch.Tensor]], torch.Tensor]:
    """The schedule and joint order as index tensors on ``device``, built once per device."""
    steps = [(torch.tensor(j, device=device), torch.tensor(p, device=device)) for j, p in _schedule(tree)]
    return steps, torch.tensor(_joint_order(tree), device=device)


def forward_kinematics(
    tree: KinematicTree, rot: torch.Tensor, trans: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Compose local transforms into world transforms.

    Args:
        tree: the joint hierarchy; joint 0 is the root.
        rot: (B, J, 3, 3) local rotations (the root's is its world rotation).
        trans: (B, J, 3) local translations, in the parent's frame.

    Returns:
        ``(world_rot (B, J, 3, 3), world_trans (B, J, 3))``.
    """
    root = tree.levels[0]
    r_levels = [rot[:, root]]
    t_levels = [trans[:, root]]
    steps, order = _index_tensors(tree, rot.device)
    for idx, pslot in steps:
        rp, tp = r_levels[-1][:, pslot], t_levels[-1][:, pslot]
        r_levels.append(rp @ rot[:, idx])
        t_levels.append((rp @ trans[:, idx, :, None]).squeeze(-1) + tp)
    return torch.cat(r_levels, 1)[:, order], torch.cat(t_levels, 1)[:, order]


def pose_transforms(
    tree: KinematicTree,
    local_rot: torch.Tensor,
    offsets: torch.Tensor,
    transl: torch.Tensor,
    rest_rot: torch.Tensor,
    rest_pos: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """FK of a posed body and its skinning transforms ``G_k T_k^-1``.

    Args:
        tree: the joint hierarchy; joint 0 is a virtual root at the origin, joint 1 the Hips.
        local_rot: (B, J, 3, 3) local rotations.
        offsets: (Bi, J, 3) each joint's rest position in its parent's rest frame (Bi = 1 or B).
        transl: (B, 3) world position of joint 1 (it replaces joint 1's offset).
        rest_rot: (Bi, J, 3, 3) rest world rotations; rest_pos: (Bi, J, 3) rest positions.

    Returns:
        ``(world_rot (B, J, 3, 3), world_pos (B, J, 3), mats (B, J, 3, 4))``.
    """
    local_t = offsets.expand(local_rot.shape[0], -1, -1)
    local_t = torch.cat([local_t[:, :1], transl[:, None], local_t[:, 2:]], dim=1)
    g_rot, g_pos = forward_kinematics(tree, local_rot, local_t)
    skin_rot = g_rot @ rest_rot.transpose(-1, -2)
    skin_t = g_pos - (skin_rot @ rest_pos[..., None]).squeeze(-1)
    return g_rot, g_pos, torch.cat([skin_rot, skin_t[..., None]], dim=-1)


def relative_to_parent(
    tree: KinematicTree, rot: torch.Tensor, trans: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse of :func:`forward_kinematics`: world transforms to local ones.

    Args:
        rot: (B, J, 3, 3) world rotations; trans: (B, J, 3) world positions.

    Returns:
        ``(local_rot, local_trans)``; the root keeps its world transform.
    """
    parents = torch.tensor([max(p, 0) for p in tree.parents], device=rot.device)
    rp_t = rot[:, parents].transpose(-1, -2)
    local_r = rp_t @ rot
    local_t = (rp_t @ (trans - trans[:, parents])[..., None]).squeeze(-1)
    is_root = torch.tensor([p < 0 for p in tree.parents], device=rot.device)
    local_r = torch.where(is_root[:, None, None], rot, local_r)
    local_t = torch.where(is_root[:, None], trans, local_t)
    return local_r, local_t
