"""Forward kinematics over a joint tree by pointer jumping: a few batched 4x4 products.

A joint's world transform is its parent's world transform composed with its local one,
G_j = G_p(j) L_j (homogeneous 4x4, column vectors). :func:`chain` evaluates all of them in
ceil(log2(depth + 1)) steps rather than one per tree level; the public functions take and
return rotations (..., 3, 3) and translations (..., 3).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache, cached_property

import torch

__all__ = [
    "KinematicTree",
    "batch_major",
    "chain",
    "compose",
    "forward_kinematics",
    "homogeneous",
    "joint_major",
    "pose_transforms",
    "posed_local",
    "relative_to_parent",
    "rest_inverse",
]


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
def _jumps(tree: KinematicTree, device: torch.device) -> tuple[torch.Tensor, ...]:
    """Ancestor tables for pointer jumping on ``device``, built once per tree and device.

    Slot J (one past the last joint) holds the identity: it is the root's parent and its own.
    """
    n = len(tree.parents)
    anc = [p if p >= 0 else n for p in tree.parents] + [n]
    steps = []
    while any(a != n for a in anc[:n]):
        steps.append(torch.tensor(anc, device=device))
        anc = [anc[a] for a in anc]
    return tuple(steps)


def joint_major(rot: torch.Tensor, trans: torch.Tensor | None = None) -> torch.Tensor:
    """(B, J, 3, 3) rotations [and (B, J, 3) translations] -> joint-major (J, 3 or 4, 3, B).

    Joint-major layout: ``x[j, c, r, b] = M_bj[r, c]``, the batch innermost. Products of many
    3x3/3x4 matrices become a few elementwise passes over contiguous length-B rows
    (:func:`compose`), where a batched ``matmul`` of tiny matrices costs ~0.15 us per product
    (5x slower at B = 32, ``benchmarks/forward.py --profile``).
    """
    cols = rot.permute(1, 3, 2, 0)
    if trans is None:
        return cols.contiguous()
    return torch.cat([cols, trans.permute(1, 2, 0)[:, None]], dim=1)


def batch_major(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Joint-major (J, 3 or 4, 3, B) -> ``(rot (B, J, 3, 3), trans (B, J, 3) or None)``, views."""
    rot = x[:, :3].permute(3, 0, 2, 1)
    return rot, (x[:, 3].permute(2, 0, 1) if x.shape[1] == 4 else None)


def compose(p: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """Products ``P A`` of joint-major matrices (J, C, 3, B), C = 3 (rotations) or 4 (affine).

    ``a`` may have C = 3 or 4 columns (the result has as many); an affine ``p`` adds its
    translation to the result's 4th column. B broadcasts (1 against B).
    """
    c = p[:, None, 0] * a[:, :, 0, None]
    c = torch.addcmul(c, p[:, None, 1], a[:, :, 1, None])
    c = torch.addcmul(c, p[:, None, 2], a[:, :, 2, None])
    if p.shape[1] == 4 and a.shape[1] == 4:
        c = torch.cat([c[:, :3], c[:, 3:] + p[:, 3:]], dim=1)
    return c


def chain(tree: KinematicTree, local: torch.Tensor) -> torch.Tensor:
    """World transforms of local ones, joint-major (J, 4, 3, B); the root's local is its world.

    Pointer jumping (a Hillis-Steele scan over the tree): each step composes every joint with
    the product its current ancestor holds, then doubles the ancestor distance, so
    ceil(log2(depth + 1)) steps of one gather and one :func:`compose` replace one step per
    level (4 instead of 13 for the canonical rig). Joints whose chain is complete compose with
    an identity slot, so no step needs a mask.
    """
    eye = torch.eye(4, 3, dtype=local.dtype, device=local.device)[None, ..., None].expand(1, 4, 3, local.shape[3])
    a = torch.cat([local, eye], dim=0)
    for anc in _jumps(tree, local.device):
        a = compose(a.index_select(0, anc), a)
    return a[:-1]


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
    return batch_major(chain(tree, joint_major(rot, trans)))


def homogeneous(rot: torch.Tensor, trans: torch.Tensor) -> torch.Tensor:
    """``[[R, t], [0, 1]]`` (..., 4, 4) of rotations (..., 3, 3) and translations (..., 3)."""
    top = torch.cat([rot, trans[..., None]], dim=-1)
    bottom = top.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(*top.shape[:-2], 1, 4)
    return torch.cat([top, bottom], dim=-2)


def rest_inverse(rest_rot: torch.Tensor, rest_pos: torch.Tensor) -> torch.Tensor:
    """Joint-major (J, 4, 3, Bi) inverse rest transforms ``T^-1 = [R^T | -R^T p]``."""
    rt = rest_rot.transpose(-1, -2)
    return joint_major(rt, -(rt @ rest_pos[..., None]).squeeze(-1))


def posed_local(local_rot: torch.Tensor, offsets: torch.Tensor, transl: torch.Tensor) -> torch.Tensor:
    """Joint-major local transforms (J, 4, 3, B) of a body whose joint 1 sits at ``transl``.

    Args:
        local_rot: joint-major (J, 3, 3, B) local rotations.
        offsets: (Bi, J, 3) rest offsets in the parent's frame (Bi = 1 or B).
        transl: (B, 3) world position of joint 1 (it replaces joint 1's offset).
    """
    b = local_rot.shape[3]
    t = offsets.permute(1, 2, 0).expand(-1, -1, b)
    t = torch.cat([t[:1], transl.t()[None], t[2:]], dim=0)
    return torch.cat([local_rot, t[:, None]], dim=1)


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
    world = chain(tree, posed_local(joint_major(local_rot), offsets, transl))
    mats = compose(world, rest_inverse(rest_rot, rest_pos))
    g_rot, g_pos = batch_major(world)
    return g_rot, g_pos, mats.permute(3, 0, 2, 1)


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
