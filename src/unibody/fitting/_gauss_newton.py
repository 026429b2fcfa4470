"""Articulated Gauss-Newton: the shared Jacobian of skinned points, and the refinement of
all joint rotations at once used by :mod:`unibody.fitting.inversion`.

Parameters per frame: the Hips translation and, for each solved joint k, a world-frame
rotation increment w_k about the joint's position g_k. Rotating joint k rigidly moves the
part of every point that its subtree skins, so to first order

    p_i(w, d) = p_i + d + sum_k w_k x q_ik,     q_ik = sum_{m in subtree(k)} w_im (M_m v_i - g_k),

and the Jacobian block of point i and joint k is -[q_ik]_x (:func:`articulated_jacobian`);
increments are applied as local rotations R_k <- R_p^T exp(w_k) R_p R_k
(:func:`rotate_joints`). Both are shared with the marker solver (:mod:`unibody.mocap`).
The inversion's refinement forms the normal equations on a fixed seeded sample of vertices
and solves them per frame (Cholesky with a small Levenberg damping).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from ..geometry.rotations import axis_angle_to_matrix, skew

if TYPE_CHECKING:
    from ..body import BodyLayer, PreparedIdentity

__all__ = ["GaussNewtonData", "articulated_jacobian", "gauss_newton", "gauss_newton_data", "rotate_joints"]


def articulated_jacobian(
    q: torch.Tensor, point: torch.Tensor, slot: torch.Tensor, num_points: int, num_joints: int
) -> torch.Tensor:
    """Jacobian of skinned points with respect to the translation and world rotation increments.

    Args:
        q: (B, P, 3) m, moment arms of P (point i, solved joint s) pairs,
            q_is = sum_{m in subtree(s)} w_im (M_m v_i) - (sum_{m in subtree(s)} w_im) g_s.
        point: (P,) i of each pair, in [0, N).
        slot: (P,) s of each pair, in [0, S); a pair that is not listed (the joint's subtree
            does not skin the point) has a zero block.
        num_points: N.
        num_joints: S, the solved joints.

    Returns:
        (B, N, 3, 3 + 3S): d x_i / d (t, w_1, ..., w_S) = [I, -[q_i1]_x, ..., -[q_iS]_x].
    """
    b = q.shape[0]
    jac = q.new_zeros(b, num_points, 3, 1 + num_joints, 3)
    jac[:, :, :, 0] = torch.eye(3, dtype=q.dtype, device=q.device)
    # Advanced indices split by a slice put the pair axis first: (P, B, 3, 3). Filling only the
    # listed pairs keeps sparse incidences cheap (the inversion's 1,500 vertices x 60 joints).
    jac[:, point, :, 1 + slot] = -skew(q).transpose(0, 1)
    return jac.reshape(b, num_points, 3, 3 + 3 * num_joints)


def rotate_joints(
    local: torch.Tensor, world_rot: torch.Tensor, joints: torch.Tensor, parents: torch.Tensor, increments: torch.Tensor
) -> torch.Tensor:
    """Local rotations of ``joints`` after world-frame increments: R_k <- R_p^T exp(w_k) R_p R_k.

    Args:
        local: (B, J, 3, 3) absolute local rotations; world_rot: (B, J, 3, 3) their FK.
        joints: (S,) solved joints; parents: (J,) parent of every joint.
        increments: (B, S, 3) axis-angle w_k, world frame.

    Returns:
        (B, S, 3, 3) the new local rotations of ``joints``.
    """
    gp = world_rot[:, parents[joints]]
    return gp.transpose(-1, -2) @ axis_angle_to_matrix(increments) @ gp @ local[:, joints]


@dataclass(frozen=True, eq=False)
class GaussNewtonData:
    """Index structure over sampled vertices (CPU int64 / float tensors).

    Attributes:
        verts: (N,) sampled vertices.
        joints: (K,) solved (skinned) joints.
        infl_vertex, infl_joint, infl_weight: (E,) influences of the sampled vertices
            (vertex as position in ``verts``).
        pair_vertex, pair_slot: (P,) (vertex position, joint slot in ``joints``) pairs with
            a non-empty subtree part.
        entry_pair, entry_infl: (Q,) which influence contributes to which pair.
        pair_weight: (P,) sum of the pair's influence weights.
        pair_flat: (P,) vertex position * K + slot: the pair's row in a dense (N, K) grid.
    """

    verts: torch.Tensor
    joints: torch.Tensor
    infl_vertex: torch.Tensor
    infl_joint: torch.Tensor
    infl_weight: torch.Tensor
    pair_vertex: torch.Tensor
    pair_slot: torch.Tensor
    entry_pair: torch.Tensor
    entry_infl: torch.Tensor
    pair_weight: torch.Tensor
    pair_flat: torch.Tensor


def gauss_newton_data(layer: BodyLayer, num_samples: int, seed: int = 0) -> GaussNewtonData:
    """Sample vertices and build the (vertex, ancestor joint) incidence once per layer."""
    parents = layer.rig_tree.parents
    skin = layer.skinning
    sv, sj, sw = (x.cpu() for x in (skin.vertex, skin.joint, skin.weight))
    skinned = torch.bincount(sj, minlength=layer.num_joints) > 0
    joints = torch.nonzero(skinned).flatten()
    slot = {int(j): i for i, j in enumerate(joints)}
    gen = torch.Generator().manual_seed(seed)
    verts = torch.randperm(layer.num_vertices, generator=gen)[:num_samples].sort().values
    pos = torch.full((layer.num_vertices,), -1, dtype=torch.long)
    pos[verts] = torch.arange(verts.numel())
    keep = pos[sv] >= 0
    iv, ij, iw = pos[sv[keep]], sj[keep], sw[keep]
    ancestors = []
    for m in range(layer.num_joints):
        chain, a = [], m
        while a > 0:
            if a in slot:
                chain.append(slot[a])
            a = parents[a]
        ancestors.append(chain)
    pair_id: dict[tuple[int, int], int] = {}
    entry_pair, entry_infl = [], []
    for e, (v, m) in enumerate(zip(iv.tolist(), ij.tolist(), strict=True)):
        for k in ancestors[m]:
            p = pair_id.setdefault((v, k), len(pair_id))
            entry_pair.append(p)
            entry_infl.append(e)
    pairs = torch.tensor(list(pair_id.keys()), dtype=torch.long)
    entry_pair_t, entry_infl_t = torch.tensor(entry_pair), torch.tensor(entry_infl)
    pair_weight = torch.zeros(len(pair_id), dtype=iw.dtype).index_add_(0, entry_pair_t, iw[entry_infl_t])
    flat = pairs[:, 0] * joints.numel() + pairs[:, 1]
    return GaussNewtonData(
        verts, joints, iv, ij, iw, pairs[:, 0], pairs[:, 1], entry_pair_t, entry_infl_t, pair_weight, flat
    )


def normal_equations(
    d: dict[str, torch.Tensor], q: torch.Tensor, residual: torch.Tensor, num_joints: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """J^T J (B, 3 + 3S, 3 + 3S) and J^T r (B, 3 + 3S, 1) of :func:`articulated_jacobian`, from its structure.

    With J's blocks I (translation) and -[q_ik]_x (joint k, where its subtree skins vertex i):
    J_t^T J_t = N I, J_k^T J_t = [sum_i q_ik]_x, J_k^T J_l = sum_i (q_ik . q_il) I - q_il q_ik^T,
    J_t^T r = sum_i r_i, J_k^T r = sum_i q_ik x r_i. The joint blocks come from one product
    Q^T Q of the moment arms laid out densely, Q (N, 3S): a third of the rows of J and no
    skew blocks (measured, batch 32, 800 vertices, one thread: 72 ms, where summing over
    couples of pairs on one vertex took 131 ms and the dense J^T J ~3x the product's work).

    Args:
        d: the fields of :class:`GaussNewtonData` on the solve's device.
        q: (B, P, 3) moment arms of the pairs; residual: (B, N, 3) target minus prediction.
        num_joints: S.
    """
    b, n = residual.shape[:2]
    grid = num_joints + 1
    dense = q.new_zeros(b, n * num_joints, 3).index_copy_(1, d["pair_flat"], q).view(b, n, 3 * num_joints)
    # outer[:, k, l] = sum_i q_il q_ik^T: Q^T Q holds sum_i q_ik q_il^T at block (k, l).
    outer = (dense.transpose(1, 2) @ dense).view(b, num_joints, 3, num_joints, 3).permute(0, 1, 3, 4, 2)
    eye = torch.eye(3, dtype=q.dtype, device=q.device)
    moment = q.new_zeros(b, num_joints, 3).index_add_(1, d["pair_slot"], q)
    blocks = q.new_zeros(b, grid, grid, 3, 3)
    blocks[:, 0, 0] = n * eye
    blocks[:, 1:, 0] = skew(moment)
    blocks[:, 0, 1:] = skew(moment).transpose(-1, -2)
    blocks[:, 1:, 1:] = outer.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None] * eye - outer
    jtj = blocks.transpose(2, 3).reshape(b, 3 * grid, 3 * grid)
    r = residual.index_select(1, d["pair_vertex"])
    rhs_joint = q.new_zeros(b, num_joints, 3).index_add_(1, d["pair_slot"], torch.linalg.cross(q, r, dim=-1))
    rhs = torch.cat([residual.sum(1, keepdim=True), rhs_joint], 1).reshape(b, 3 * grid, 1)
    return jtj, rhs


def gauss_newton(
    layer: BodyLayer,
    data: GaussNewtonData,
    prepared: PreparedIdentity,
    target: torch.Tensor,
    local: torch.Tensor,
    transl: torch.Tensor,
    iters: int,
    damping: float = 1e-6,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Refine absolute local rotations (B, J, 3, 3) and translation (B, 3) by ``iters`` steps.

    Levenberg-Marquardt safeguard per frame: a step that does not lower the sampled
    squared error is rejected and that frame's damping grows x10 (shrinks /3 on success), so
    the error never increases and NaNs never enter the state.
    """
    dev, dtype = target.device, target.dtype
    d = {k: getattr(data, k).to(dev) for k in data.__dataclass_fields__}
    n, k_count = d["verts"].numel(), d["joints"].numel()
    rest = prepared.rest_vertices[:, d["verts"]]
    tgt = target[:, d["verts"]]
    weight = d["infl_weight"].to(dtype)
    pair_weight = d["pair_weight"].to(dtype)
    eye = torch.eye(3 + 3 * k_count, dtype=dtype, device=dev)

    def evaluate(local, transl):
        g_rot, g_pos, mats = layer.skin_transforms(prepared, local, transl)
        m = mats[:, d["infl_joint"]]
        vh = rest[:, d["infl_vertex"]]
        contrib = weight[:, None] * ((m[..., :3] @ vh[..., None]).squeeze(-1) + m[..., 3])  # (B, E, 3)
        pred = contrib.new_zeros(mats.shape[0], n, 3).index_add_(1, d["infl_vertex"], contrib)
        err = (tgt - pred).square().sum((1, 2))
        return g_rot, g_pos, contrib, pred, torch.where(torch.isfinite(err), err, torch.inf)

    state = evaluate(local, transl)
    lam = torch.full((target.shape[0],), damping, dtype=dtype, device=dev)
    for _ in range(iters):
        g_rot, g_pos, contrib, pred, _ = state
        b = contrib.shape[0]
        q = contrib.new_zeros(b, d["pair_slot"].numel(), 3).index_add_(1, d["entry_pair"], contrib[:, d["entry_infl"]])
        q = q - pair_weight[:, None] * g_pos[:, d["joints"][d["pair_slot"]]]
        jtj, rhs = normal_equations(d, q, tgt - pred, k_count)
        scale = jtj.diagonal(dim1=1, dim2=2).mean(-1)
        done = torch.zeros_like(state[4], dtype=torch.bool)
        for _ in range(4):  # retries reuse J^T J: only the 3x3-block solve and a sampled LBS repeat
            # Cholesky: J^T J + lambda I is SPD. (Batched LU, torch.linalg.solve, fails on this
            # shape under torch.set_num_threads(2) with MKL: "Pivots given to lu_solve...".)
            chol, info = torch.linalg.cholesky_ex(jtj + (lam * scale)[:, None, None] * eye)
            step = torch.cholesky_solve(rhs, chol).squeeze(-1)
            step = torch.where((info == 0)[:, None] & torch.isfinite(step), step, torch.zeros_like(step))
            new = rotate_joints(local, g_rot, d["joints"], layer.parents, step[:, 3:].view(b, k_count, 3))
            cand_local = local.index_copy(1, d["joints"], new)
            cand_transl = transl + step[:, :3]
            cand = evaluate(cand_local, cand_transl)
            ok = (cand[4] < state[4]) & ~done
            local = torch.where(ok[:, None, None, None], cand_local, local)
            transl = torch.where(ok[:, None], cand_transl, transl)
            state = tuple(
                torch.where(ok.view(-1, *[1] * (c.dim() - 1)), c, s) for c, s in zip(cand, state, strict=True)
            )
            lam = torch.where(ok, lam / 3, torch.where(done, lam, lam * 10))
            done = done | ok
            if bool(done.all()):
                break
    return local, transl
