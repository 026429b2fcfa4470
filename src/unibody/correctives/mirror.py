"""Left/right mirror symmetry of a correctives model.

A body mirrored through its sagittal plane (x -> -x, :mod:`unibody.symmetry`) and posed with the
mirrored pose (:func:`unibody.mocap.synthetic.mirror_pose`) should get the mirrored correctives.
On the canonical rig a right joint's rest-relative rotation in the mirrored pose equals its left
partner's in the pose itself (the rig's frames are mirror images; ``tests/test_correctives_mirror.py``
measures it), so mirroring a model's inputs is a permutation: each needed joint reads its partner,
each limb segment's build input its partner's. Its output is mirrored by ``d'[v] = S d[mirror(v)]``,
``S = diag(-1, 1, 1)``.

:func:`symmetrize` makes a model exactly equivariant, ``f(mirror x) = mirror f(x)``, by giving each
right joint's activations and decoder the mirror image of its left partner's (or the reverse).
Training with every sample and its mirror image in the batch (``train --mirror``) then keeps it so:
the gradients are mirror images too.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..symmetry import canonical_mirror_map, partner_joints
from .model import Correctives

__all__ = ["CorrectivesMirror", "mirror_maps", "symmetrize", "asymmetry"]


@dataclass(frozen=True, slots=True)
class CorrectivesMirror:
    """Index maps of a model's mirror image (all int64).

    Attributes:
        joints: (78,) each joint's partner (itself on the midline), Root first.
        active: (A,) each active joint's partner among the active joints.
        slots: (A, I) per active joint k, for each of its partner's input slots, the slot of k
            that reads the partner of that input (padding to padding).
        needed: (N,) each needed joint's partner, as a slot among :attr:`Correctives.needed`.
        union: (U,) each union vertex's partner, as a position in :attr:`Correctives.union`.
        rows: (R,) for each decoder row (mask vertex, xyz) the row of its mirror image.
        shape: (S + 1,) each identity input's partner (the size is its own); empty for a pose-only model.
        side: (78,) 1 for a left joint, -1 for a right one, 0 on the midline.
    """

    joints: torch.Tensor
    active: torch.Tensor
    slots: torch.Tensor
    needed: torch.Tensor
    union: torch.Tensor
    rows: torch.Tensor
    shape: torch.Tensor
    side: torch.Tensor

    def inputs(self, rel: torch.Tensor, shape: torch.Tensor | None = None) -> tuple:
        """The mirrored samples' inputs: rest-relative rotations (B, 77, 3, 3) of joints 1..77 and
        identity inputs (B, S + 1) or None."""
        rel = rel.index_select(1, self.joints[1:].to(rel.device) - 1)
        return rel, None if shape is None else shape.index_select(1, self.shape.to(shape.device))

    def output(self, d: torch.Tensor) -> torch.Tensor:
        """Mirror union displacements (B, U, 3): ``S d[mirror(v)]`` (an involution)."""
        return d.index_select(1, self.union.to(d.device)) * d.new_tensor([-1.0, 1.0, 1.0])


def mirror_maps(model: Correctives, joint_names: tuple[str, ...]) -> CorrectivesMirror:
    """The maps of ``model``'s mirror image on the canonical mesh; ``joint_names``: the 78 rig joints.

    Raises:
        ValueError: the model is not mirror-closed (a mask, an input list or the union whose mirror
            image is not its partner's).
    """
    names = list(joint_names)
    joints = partner_joints(tuple(names))
    act = [names.index(n) for n in model.joint_names]
    active = torch.tensor([act.index(int(joints[j])) for j in act])
    vmap = canonical_mirror_map().index.to(model.vertex_ids.device)
    masks = model.vertex_ids.split(model.sizes.tolist())
    rows, slots = [], []
    inputs = model.inputs.tolist()
    for k, p in enumerate(active.tolist()):
        mine = [int(joints[j]) if j >= 0 else -1 for j in inputs[p]]  # the partner's inputs, mirrored
        if sorted(mine) != sorted(inputs[k]):
            raise ValueError(
                f"correctives: {model.joint_names[p]}'s inputs are not the mirror of {model.joint_names[k]}'s"
            )
        slots.append([inputs[k].index(j) for j in mine])
        pos = {int(v): i for i, v in enumerate(masks[p].tolist())}
        try:  # joint k's vertex v takes the row of mirror(v) in its partner's block
            at = torch.tensor([pos[int(v)] for v in vmap[masks[k]].tolist()])
        except KeyError:
            raise ValueError(f"correctives: {model.joint_names[k]}'s mask is not the mirror of its partner's") from None
        start = int(model.sizes[:p].sum())
        rows.append((3 * (start + at)[:, None] + torch.arange(3)).flatten())
    where = {int(v): i for i, v in enumerate(model.union.tolist())}
    union = torch.tensor([where[int(v)] for v in vmap[model.union].tolist()])
    needed = model.needed.tolist()
    need = torch.tensor([needed.index(int(joints[j])) for j in needed])
    shape = torch.zeros(0, dtype=torch.int64)
    if model.num_shape:
        pairs = model._shape_joints.tolist()
        part = [pairs.index([int(joints[a]), int(joints[b])]) for a, b in pairs]
        shape = torch.tensor([*part, len(pairs)])
    side = torch.tensor([1 if n.startswith("Left") else -1 if n.startswith("Right") else 0 for n in names])
    return CorrectivesMirror(joints, active, torch.tensor(slots), need, union, torch.cat(rows), shape, side)


@torch.no_grad()
def symmetrize(model: Correctives, maps: CorrectivesMirror, keep: str = "Left") -> Correctives:
    """Give the ``keep`` side's partners the mirror image of its activations and decoders, in place.

    The identity inputs' statistics are first made equal between partners (the mean and std of
    each pair), with the first layer rescaled so the function does not change; the finger inputs
    held by :meth:`Correctives.freeze` take their partner's values. Afterwards
    ``f(mirror x) = mirror f(x)`` to rounding. A model on the CPU (what training uses).
    """
    if keep not in ("Left", "Right"):
        raise ValueError(f"keep: expected 'Left' or 'Right', got {keep!r}")
    w1, b1 = model.w1, model.b1
    if model.num_shape:  # equal statistics per pair, folded into the first layer
        mean, std = model.shape_mean.clone(), model.shape_std.clone()
        new_mean, new_std = (mean + mean[maps.shape]) / 2, (std + std[maps.shape]) / 2
        cols = slice(w1.shape[2] - model.num_shape, None)
        old = w1[:, :, cols].clone()
        b1 += (old * ((new_mean - mean) / std)).sum(-1)
        w1[:, :, cols] = old * (new_std / std)
        model.shape_mean.copy_(new_mean)
        model.shape_std.copy_(new_std)
    src = [k for k, n in enumerate(model.joint_names) if n.startswith(keep)]
    i6 = (maps.slots[:, :, None] * 6 + torch.arange(6)).flatten(1)  # (A, I*6) input columns
    for k in src:
        p = int(maps.active[k])
        cols = i6[k]
        if model.num_shape:
            cols = torch.cat([cols, model.inputs.shape[1] * 6 + maps.shape])
        w1[p] = w1[k][:, cols]
        for name in ("b1", "w2", "b2"):
            getattr(model, name)[p] = getattr(model, name)[k]
    dst = torch.cat([torch.arange(3 * s, 3 * e) for k, (s, e) in enumerate(model._blocks) if k not in src])
    sign = model.decode.new_tensor([-1.0, 1.0, 1.0]).repeat(len(model.decode) // 3)[:, None]
    model.decode[dst] = (model.decode[maps.rows] * sign)[dst]
    other = -1 if keep == "Left" else 1  # the needed joints on the other side take their partner's held inputs
    dst = (maps.side[model.needed] == other).nonzero().flatten()
    model._frozen[dst] = model._frozen[maps.needed[dst]]
    model._frozen_value[dst] = model._frozen_value[maps.needed[dst]]
    return model


def asymmetry(model: Correctives, maps: CorrectivesMirror, rel: torch.Tensor, size: torch.Tensor, shape=None) -> float:
    """m, the largest ``|f(x) - mirror f(mirror x)|`` over the samples (0 for a symmetric model)."""
    with torch.no_grad():
        d = model.union_displacements(rel, size, shape)
        m_rel, m_shape = maps.inputs(rel, shape)
        back = maps.output(model.union_displacements(m_rel, size, m_shape))
    return float((d - back).norm(dim=-1).max())
