"""Internals of :mod:`unibody.mocap.solve`: the latent-marker body and its per-frame Gauss-Newton steps.

Notation (all float64 inside the solver, metres):

- ``beta`` (K,) PCA coefficients; ``rest(beta)`` the rest mesh (bind A-pose) and its skeleton.
- Marker m is attached to an *anchor* vertex a_m. Its latent rest position is
  ``p_m = v_a + n_a d_m + delta_m`` (v, n: rest vertex and unit normal, d_m: layout distance,
  delta_m: stage-1 slide, rest-frame metres). It is skinned with the anchor's weights:
  ``x_m = sum_k w_mk (R_k p_m + t_k)`` with [R_k | t_k] = G_k T_k^-1.
- Per frame the unknowns are the Hips translation and, for each solved body joint j, a
  world-frame rotation increment w_j about the joint position g_j (as in
  :mod:`unibody.fitting._gauss_newton`, whose Jacobian and update this module uses): d x_m / d w_j = -[q_mj]_x with
  ``q_mj = sum_{k in subtree(j)} w_mk (R_k p_m + t_k) - (sum_{k in subtree(j)} w_mk) g_j``.
  Increments are applied as L_j <- W_p^T exp(w_j) W_p L_j (W_p: parent world rotation).
- Pose prior on every solved joint but the Hips: ``(theta_j - mu_j) / sigma_j`` with theta_j
  the T-pose-relative axis-angle, mu_j the relaxed standing pose and sigma_j half the joint
  range of :data:`unibody.joint_limits.JOINT_RANGES`. A world increment acts on the relative
  rotation from the left by phi = O_p W_p^T w, so d theta / d w = J_l^-1(theta) O_p W_p^T.

Every residual is divided by its standard deviation, so the cost is a sum of squares in
units of "sigmas" and the weights of :class:`~unibody.mocap.solve.SolveConfig` compare
directly.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import lru_cache

import torch

from ..body import BodyLayer
from ..fitting._gauss_newton import articulated_jacobian, rotate_joints
from ..geometry.kinematics import pose_transforms
from ..geometry.procrustes import kabsch
from ..geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle, skew
from ..joint_limits import JOINT_RANGES
from ..regions import dominant_joints

_LIMBS = ("Shoulder", "Arm", "ForeArm", "Hand", "Leg", "Shin", "Foot", "ToeBase")
BODY_JOINTS: tuple[str, ...] = ("Hips", "Spine1", "Spine2", "Chest", "Neck1", "Neck2", "Head") + tuple(
    f"{side}{part}" for side in ("Left", "Right") for part in _LIMBS
)
_TORSO = ("Hips", "Spine1", "Spine2", "Chest")
_FINGER_CURL = 0.3  # rad, relaxed curl of the fixed finger joints (sign: left -Z, right +Z)
_MIN_PRIOR_STD = 0.05  # rad, floor of the pose prior's per-axis std


# --------------------------------------------------------------------------- small math


def _inv_left_jacobian(theta: torch.Tensor) -> torch.Tensor:
    """J_l^-1(theta) (..., 3, 3): d log(exp(phi) R) / d phi at phi = 0, R = exp(theta)."""
    t = theta.norm(dim=-1)
    small = t < 1e-4
    ts = torch.where(small, torch.ones_like(t), t.clamp_max(3.1))
    coef = torch.where(small, torch.full_like(t, 1.0 / 12.0), 1 / ts**2 - (1 + ts.cos()) / (2 * ts * ts.sin()))
    k = skew(theta)
    eye = torch.eye(3, dtype=theta.dtype, device=theta.device)
    return eye - 0.5 * k + coef[..., None, None] * (k @ k)


def _block_diag(blocks: torch.Tensor) -> torch.Tensor:
    """(B, n, 3, 3) -> (B, 3n, 3n) block-diagonal."""
    b, n = blocks.shape[:2]
    out = blocks.new_zeros(b, n, n, 3, 3)
    ar = torch.arange(n, device=blocks.device)
    out[:, ar, ar] = blocks
    return out.permute(0, 1, 3, 2, 4).reshape(b, 3 * n, 3 * n)


def _damped_cholesky(h: torch.Tensor, lam: torch.Tensor) -> torch.Tensor:
    """Cholesky factor of H + lam diag(H) (Marquardt), with a small floor on the diagonal."""
    d = h.diagonal(dim1=-2, dim2=-1)
    floor = 1e-9 * d.mean(-1, keepdim=True) + 1e-12
    a = h + torch.diag_embed(lam[:, None] * d + floor)
    chol, info = torch.linalg.cholesky_ex(a)
    if bool((info != 0).any()):  # not SPD in rounding: add more diagonal
        chol, _ = torch.linalg.cholesky_ex(a + torch.diag_embed(1e-6 * d.mean(-1, keepdim=True).expand_as(d)))
    return chol


def kabsch_root(model: torch.Tensor, obs: torch.Tensor, weight: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rigid (R, t) with R model + t ~ obs, weighted (B, M); (B, 3, 3) and (B, 3)."""
    w = weight / weight.sum(-1, keepdim=True).clamp_min(1e-12)
    obs = torch.nan_to_num(obs)
    mc = (w[..., None] * model).sum(1)
    oc = (w[..., None] * obs).sum(1)
    r = kabsch(model - mc[:, None], obs - oc[:, None], w)
    return r, oc - (r @ mc[..., None]).squeeze(-1)


# --------------------------------------------------------------------------- the body


@dataclass(frozen=True, eq=False)
class Identity:
    """A fitted (or trial) identity: skeleton and the anchor geometry, batch Bi.

    Attributes:
        beta: (Bi, K); offsets, rest_rot, rest_pos: skeleton (Bi, J, ...);
        rest: (Bi, V, 3) rest mesh.
    """

    beta: torch.Tensor
    offsets: torch.Tensor
    rest_rot: torch.Tensor
    rest_pos: torch.Tensor
    rest: torch.Tensor

    def expand(self, n: int) -> Identity:
        """Each identity repeated for n consecutive frames (skeleton only; batch Bi * n)."""
        rep = lambda x: x.repeat_interleave(n, 0)  # noqa: E731
        return replace(self, offsets=rep(self.offsets), rest_rot=rep(self.rest_rot), rest_pos=rep(self.rest_pos))


@lru_cache(maxsize=2)
def _layer(num_components: int, device: str) -> BodyLayer:
    """The float64 PCA body layer used by the solver (loading takes ~1 s, so it is cached)."""
    return BodyLayer.from_pca(num_components=num_components, dtype=torch.float64).to(device)


class MarkerBody:
    """The PCA body with latent markers: marker positions, Jacobians and the pose prior.

    Args:
        num_components: K, PCA coefficients.
        device: where to compute.
    """

    def __init__(self, num_components: int, device: torch.device) -> None:
        layer = _layer(num_components, str(device))
        self.layer = layer
        self.tree = layer.rig_tree
        names = layer.joint_names
        j_count = layer.num_joints
        dt, dev = torch.float64, layer.tpose_orient.device
        self.num_components = num_components
        self.parents = layer.parents
        self.solved = torch.tensor([names.index(n) for n in BODY_JOINTS], device=dev)
        self.num_solved = len(BODY_JOINTS)
        self.num_params = 3 + 3 * self.num_solved
        # S[s, k] = 1 if joint k is in the subtree of solved joint s.
        sub = torch.zeros(self.num_solved, j_count, dtype=dt)
        for s, j in enumerate(self.solved.tolist()):
            stack = [j]
            while stack:
                k = stack.pop()
                sub[s, k] = 1.0
                stack.extend(self.tree.children[k])
        self.subtree = sub.to(dev)
        skin = layer.skinning
        self.weights = skin.dense().to(dt)  # (V, J)
        dom = dominant_joints(skin.vertex, skin.joint, skin.weight, layer.num_vertices, j_count)
        self.torso_vertex = torch.isin(dom, torch.tensor([names.index(n) for n in _TORSO])).to(dev)
        self._init_pose_tables(names)
        faces = layer.faces.long()
        self.faces_ext = torch.cat([faces, faces.new_zeros(1, 3)])  # row F: degenerate padding
        vid = faces.flatten()
        order = torch.argsort(vid, stable=True)
        counts = torch.bincount(vid, minlength=layer.num_vertices)
        start = torch.cumsum(counts, 0) - counts
        slot = torch.arange(vid.numel(), device=vid.device) - start[vid[order]]
        table = faces.new_full((layer.num_vertices, int(counts.max())), faces.shape[0])
        table[vid[order], slot] = order // 3
        self.vertex_faces = table  # (V, max valence) incident faces, padded with F

    def _init_pose_tables(self, names: tuple[str, ...]) -> None:
        """Fixed relaxed local rotations of the unsolved joints and the prior's mean / std."""
        dev, dt = self.solved.device, torch.float64
        rel = torch.zeros(len(names) - 1, 3, dtype=dt)
        for side, sign in (("Left", -1.0), ("Right", 1.0)):
            for finger in ("Index", "Middle", "Ring", "Pinky"):
                for k in (1, 2, 3):
                    rel[names.index(f"{side}Hand{finger}{k}") - 1, 2] = sign * _FINGER_CURL
        mu = torch.zeros(self.num_solved, 3, dtype=dt)
        std = torch.ones(self.num_solved, 3, dtype=dt)
        mirror = torch.tensor([1.0, -1.0, -1.0], dtype=dt)
        for s, name in enumerate(BODY_JOINTS[1:], start=1):
            base = "Left" + name[5:] if name.startswith("Right") else name
            lo, hi, relaxed = (torch.tensor(v, dtype=dt) for v in JOINT_RANGES[base])
            mu[s] = relaxed * mirror if name.startswith("Right") else relaxed
            std[s] = ((hi - lo) / 2).clamp_min(_MIN_PRIOR_STD)
        rel[self.solved.cpu() - 1] = mu
        self.relaxed_pose = rel.to(dev)  # (77, 3) T-pose-relative
        self.relaxed_local = self._absolute(axis_angle_to_matrix(self.relaxed_pose)[None])  # (1, J, 3, 3)
        self.prior_joint = self.solved[1:]
        self.prior_mu, self.prior_inv_std = mu[1:].to(dev), (1 / std[1:]).to(dev)

    def _absolute(self, rel: torch.Tensor) -> torch.Tensor:
        """T-pose-relative (B, 77, 3, 3) -> absolute local rotations (B, J, 3, 3), Root = I."""
        o, p = self.layer.tpose_orient, self.parents
        loc = o[p[1:]].transpose(-1, -2) @ rel @ o[1:]
        eye = torch.eye(3, dtype=loc.dtype, device=loc.device).expand(loc.shape[0], 1, 3, 3)
        return torch.cat([eye, loc], 1)

    def relative_pose(self, local: torch.Tensor) -> torch.Tensor:
        """Absolute local rotations (B, J, 3, 3) -> T-pose-relative axis-angle (B, 77, 3).

        The unsolved joints get their fixed relaxed values exactly (no conversion round-off).
        """
        rel = matrix_to_axis_angle(self.layer.to_relative(local[:, 1:]))
        pose = self.relaxed_pose.expand_as(rel).clone()
        pose[:, self.solved - 1] = rel[:, self.solved - 1]
        return pose

    # -- identity -------------------------------------------------------------------------
    def identity(self, beta: torch.Tensor) -> Identity:
        """Rest mesh, normals and skeleton of coefficients (Bi, K)."""
        rest = self.layer.identity(beta)
        prep = self.layer.prepare_rest(rest)
        return Identity(beta, prep.offsets, prep.rest_rotations, prep.rest_joints, rest)

    def normals(self, rest: torch.Tensor, ids: torch.Tensor) -> torch.Tensor:
        """Unit area-weighted normals (Bi, n, 3) of the vertices ids (n,) of meshes (Bi, V, 3).

        The same normals as :func:`~unibody.mocap.layout.vertex_normals`, from the incident
        faces of those vertices only (the whole mesh would cost ~25 ms per identity).
        """
        tri = self.faces_ext[self.vertex_faces[ids]]  # (n, valence, 3), padding: a degenerate face
        p0, p1, p2 = (rest[:, tri[..., k]] for k in range(3))
        n = torch.linalg.cross(p1 - p0, p2 - p0).sum(2)
        return n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)

    def latent(self, ident: Identity, anchors: torch.Tensor, distance: torch.Tensor, delta: torch.Tensor):
        """Latent rest positions p (Bi, M, 3) = v_a + n_a d + delta, and n_a (Bi, M, 3)."""
        n = self.normals(ident.rest, anchors)
        return ident.rest[:, anchors] + n * distance[:, None] + delta, n

    # -- posed markers --------------------------------------------------------------------
    def markers(self, ident: Identity, anchors: torch.Tensor, p: torch.Tensor, local, transl, jacobian: bool):
        """Posed markers of B frames.

        Args:
            ident: identity with batch 1 or B (skeleton fields).
            anchors: (M,) anchor vertices; p: (1 | B, M, 3) latent rest positions.
            local: (B, J, 3, 3) absolute local rotations; transl: (B, 3) Hips position.
            jacobian: whether to return the Jacobian and the blended rotations.

        Returns:
            ``(x (B, M, 3), g_rot (B, J, 3, 3), jac (B, M, 3, N) | None, blend (B, M, 3, 3) | None)``.
        """
        g_rot, g_pos, mats = pose_transforms(self.tree, local, ident.offsets, transl, ident.rest_rot, ident.rest_pos)
        w = self.weights[anchors]  # (M, J)
        y = torch.einsum("bkrc,bmc->bmkr", mats[..., :3], p.expand(local.shape[0], -1, -1)) + mats[:, None, :, :, 3]
        x = torch.einsum("mk,bmkr->bmr", w, y)
        if not jacobian:
            return x, g_rot, None, None
        ws = w[:, None, :] * self.subtree[None]  # (M, S, J)
        q = torch.einsum("msk,bmkr->bmsr", ws, y) - ws.sum(-1)[None, :, :, None] * g_pos[:, None, self.solved]
        m, s = q.shape[1:3]
        point = torch.arange(m, device=q.device).repeat_interleave(s)  # every (marker, joint) pair
        slot = torch.arange(s, device=q.device).repeat(m)
        jac = articulated_jacobian(q.reshape(q.shape[0], m * s, 3), point, slot, m, s)
        blend = torch.einsum("mk,bkrc->bmrc", w, mats[..., :3])
        return x, g_rot, jac, blend

    def prior(self, local: torch.Tensor, g_rot: torch.Tensor | None):
        """Pose-prior residuals (B, S-1, 3) and, given world rotations, their Jacobian blocks (B, S-1, 3, 3)."""
        j = self.prior_joint
        o, par = self.layer.tpose_orient, self.parents[j]
        theta = matrix_to_axis_angle(o[par] @ local[:, j] @ o[j].transpose(-1, -2))
        r = (theta - self.prior_mu) * self.prior_inv_std
        if g_rot is None:
            return r, None
        a = o[par] @ g_rot[:, par].transpose(-1, -2)
        return r, self.prior_inv_std[..., None] * (_inv_left_jacobian(theta) @ a)

    def apply(self, local, transl, g_rot, step):
        """Apply parameter steps (B, N) at the linearisation point (world rotations g_rot)."""
        b = step.shape[0]
        new = rotate_joints(local, g_rot, self.solved, self.parents, step[:, 3:].view(b, self.num_solved, 3))
        # One Newton-Schulz step, R (3I - R^T R) / 2: rounding errors would otherwise compound
        # from frame to frame through the warm starts (measured: 1e-3 after 100 frames).
        eye = torch.eye(3, dtype=new.dtype, device=new.device)
        new = 0.5 * new @ (3 * eye - new.transpose(-1, -2) @ new)
        return local.index_copy(1, self.solved, new), transl + step[:, :3]

    def root_init(self, ident, anchors, p, local, obs, vis) -> tuple[torch.Tensor, torch.Tensor]:
        """Hips rotation and position by Kabsch of the torso markers (all markers if < 3 torso)."""
        b = local.shape[0]
        hips = self.solved[0]
        zero = local.index_copy(1, hips[None], torch.eye(3, dtype=local.dtype, device=local.device).expand(b, 1, 3, 3))
        x, *_ = self.markers(ident, anchors, p, zero, local.new_zeros(b, 3), jacobian=False)
        torso = vis & self.torso_vertex[anchors]
        w = torch.where((torso.sum(1, keepdim=True) >= 3), torso, vis).to(x.dtype)
        r, t = kabsch_root(x, obs, w)
        return zero.index_copy(1, hips[None], r[:, None]), t


# --------------------------------------------------------------------------- normal equations


@dataclass
class Weights:
    """Per-frame residual weights (1 / std): data (B, M) (0 where missing), prior (B,), temporal (B, M).

    ``robust`` (m) > 0 makes the data term Cauchy: a marker at distance d from its model marker
    costs ``w^2 c^2 log(1 + d^2 / c^2)`` (about ``w^2 d^2`` below c, growing only
    logarithmically beyond), so a mislabelled point does not drag the body; 0 keeps squares.
    ``temporal_robust`` (m) does the same for the temporal term (a glitch frame does not drag
    its neighbours).
    """

    data: torch.Tensor
    prior: torch.Tensor
    temporal: torch.Tensor | None = None
    target: torch.Tensor | None = None  # (B, M, 3) temporal targets
    robust: float = 0.0
    temporal_robust: float = 0.0


def _row_weights(r: torch.Tensor, w: torch.Tensor, robust: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Costs (B, M) of residuals r (B, M, 3) with weights w (B, M) and their Gauss-Newton row weights.

    Squares (robust 0): ``w^2 d^2`` and ``w^2``. Cauchy (scale c = robust):
    ``w^2 c^2 log(1 + d^2 / c^2)`` and ``w^2 / (1 + d^2 / c^2)`` (IRLS: the cost's gradient is
    that weight times 2 r).
    """
    d2, w2 = r.square().sum(-1), w.square()
    if robust <= 0:
        return w2 * d2, w2
    c2 = robust**2
    return w2 * c2 * torch.log1p(d2 / c2), w2 / (1 + d2 / c2)


def frame_cost(body, x, local, obs, wt: Weights) -> torch.Tensor:
    """(B,) weighted cost: data (squares or Cauchy) + pose prior + temporal."""
    data, _ = _row_weights(torch.nan_to_num(x - obs), wt.data, wt.robust)
    cost = data.sum(1)
    rp, _ = body.prior(local, None)
    cost = cost + wt.prior.square() * rp.square().sum((1, 2))
    if wt.temporal is not None:
        cost = cost + _row_weights(x - wt.target, wt.temporal, wt.temporal_robust)[0].sum(1)
    return cost


def frame_system(body, x, jac, g_rot, local, obs, wt: Weights):
    """:func:`frame_cost` (B,) and the per-frame normal equations at the same point:
    ``(cost, H (B, N, N), g (B, N), row weights^2 (B, M))``; g = J^T W r."""
    b, m = x.shape[:2]
    r = torch.nan_to_num(x - obs)
    data, w2 = _row_weights(r, wt.data, wt.robust)
    r = r * w2[..., None]
    rp, jp = body.prior(local, g_rot)
    cost = data.sum(1) + wt.prior.square() * rp.square().sum((1, 2))
    if wt.temporal is not None:
        rt = x - wt.target
        tc, t2 = _row_weights(rt, wt.temporal, wt.temporal_robust)
        cost = cost + tc.sum(1)
        r = r + rt * t2[..., None]
        w2 = w2 + t2
    jf = jac.reshape(b, 3 * m, -1)
    h = (jf * w2.repeat_interleave(3, 1)[..., None]).transpose(1, 2) @ jf
    g = (jf.transpose(1, 2) @ r.reshape(b, 3 * m, 1)).squeeze(-1)
    p2 = wt.prior.square()[:, None, None, None]
    blocks = torch.cat([jp.new_zeros(b, 2, 3, 3), p2 * jp.transpose(-1, -2) @ jp], 1)  # transl, Hips: no prior
    h = h + _block_diag(blocks)
    gp = (p2[..., 0] * (jp.transpose(-1, -2) @ rp[..., None]).squeeze(-1)).reshape(b, -1)
    g = g + torch.cat([gp.new_zeros(b, 6), gp], 1)
    return cost, h, g, w2


def lm_iteration(body, ident, anchors, p, local, transl, obs, wt: Callable, lam):
    """One Levenberg-Marquardt iteration on independent frames (batch B).

    ``wt(x)`` gives the weights from the current model markers x (B, M, 3), so temporal
    targets follow the neighbours' latest estimates (block-Jacobi coupling). A step that does
    not lower a frame's cost is retried with 10x damping (up to 3 times): costs never increase.

    Returns ``(local, transl, lam, x)`` with x the model markers of the returned state.
    """
    b = local.shape[0]
    x, g_rot, jac, _ = body.markers(ident, anchors, p, local, transl, jacobian=True)
    w = wt(x)
    cost, h, g, _ = frame_system(body, x, jac, g_rot, local, obs, w)
    done = torch.zeros(b, dtype=torch.bool, device=local.device)
    for _ in range(3):
        step = -torch.cholesky_solve(g[..., None], _damped_cholesky(h, lam)).squeeze(-1)
        step = torch.where(torch.isfinite(step), step, 0.0)
        c_local, c_transl = body.apply(local, transl, g_rot, step)
        cx, *_ = body.markers(ident, anchors, p, c_local, c_transl, jacobian=False)
        c_cost = frame_cost(body, cx, c_local, obs, w)
        ok = (c_cost < cost) & ~done
        local = torch.where(ok[:, None, None, None], c_local, local)
        transl = torch.where(ok[:, None], c_transl, transl)
        x = torch.where(ok[:, None, None], cx, x)
        cost = torch.where(ok, c_cost, cost)
        lam = torch.where(ok, lam / 3, torch.where(done, lam, lam * 10)).clamp(1e-7, 1e7)
        done = done | ok
        if bool(done.all()):
            break
    return local, transl, lam, x


def lm_frames(body, ident, anchors, p, local, transl, obs, wt: Callable, iters: int, lam=None):
    """``iters`` :func:`lm_iteration` steps; returns ``(local, transl, lam, x)``."""
    lam = local.new_full((local.shape[0],), 1e-3) if lam is None else lam
    x = None
    for _ in range(iters):
        local, transl, lam, x = lm_iteration(body, ident, anchors, p, local, transl, obs, wt, lam)
    return local, transl, lam, x
