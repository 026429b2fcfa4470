"""Internals of :mod:`unibody.mocap.solve`: the latent-marker body and its Gauss-Newton solves.

Notation (all float64 inside the solver, metres):

- ``beta`` (K,) PCA coefficients; ``rest(beta)`` the rest mesh (bind A-pose) and its skeleton.
- Marker m is attached to an *anchor* vertex a_m. Its latent rest position is
  ``p_m = v_a + n_a d_m + delta_m`` (v, n: rest vertex and unit normal, d_m: layout distance,
  delta_m: stage-1 slide, rest-frame metres). It is skinned with the anchor's weights:
  ``x_m = sum_k w_mk (R_k p_m + t_k)`` with [R_k | t_k] = G_k T_k^-1.
- Per frame the unknowns are the Hips translation and, for each solved body joint j, a
  world-frame rotation increment w_j about the joint position g_j (as in
  :mod:`unibody._gauss_newton`): d x_m / d w_j = -[q_mj]_x with
  ``q_mj = sum_{k in subtree(j)} w_mk (R_k p_m + t_k) - (sum_{k in subtree(j)} w_mk) g_j``.
  Increments are applied as L_j <- W_p^T exp(w_j) W_p L_j (W_p: parent world rotation).
- Pose prior on every solved joint but the Hips: ``(theta_j - mu_j) / sigma_j`` with theta_j
  the T-pose-relative axis-angle, mu_j the relaxed standing pose and sigma_j half the joint
  range of :data:`unibody.poses.JOINT_RANGES`. A world increment acts on the relative
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
from ..geometry.kinematics import pose_transforms
from ..geometry.procrustes import kabsch
from ..geometry.rotations import _skew, axis_angle_to_matrix, matrix_to_axis_angle
from ..poses import JOINT_RANGES
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
    k = _skew(theta)
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
        self.weights = torch.zeros(layer.num_vertices, j_count, dtype=dt, device=dev)
        self.weights[layer._skin_vertex, layer._skin_joint] = layer.skin_weight
        dom = dominant_joints(layer._skin_vertex, layer._skin_joint, layer.skin_weight, layer.num_vertices, j_count)
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
        b, m = x.shape[:2]
        jr = -_skew(q).permute(0, 1, 3, 2, 4).reshape(b, m, 3, 3 * self.num_solved)
        eye = torch.eye(3, dtype=x.dtype, device=x.device).expand(b, m, 3, 3)
        blend = torch.einsum("mk,bkrc->bmrc", w, mats[..., :3])
        return x, g_rot, torch.cat([eye, jr], -1), blend

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
        inc = axis_angle_to_matrix(step[:, 3:].view(b, self.num_solved, 3))
        gp = g_rot[:, self.parents[self.solved]]
        new = gp.transpose(-1, -2) @ inc @ gp @ local[:, self.solved]
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
    """Per-frame residual weights (1 / std): data (B, M) (0 where missing), prior (B,), temporal (B, M)."""

    data: torch.Tensor
    prior: torch.Tensor
    temporal: torch.Tensor | None = None
    target: torch.Tensor | None = None  # (B, M, 3) temporal targets


def frame_cost(body, x, local, obs, wt: Weights) -> torch.Tensor:
    """(B,) weighted sum of squares: data + pose prior + temporal."""
    r = torch.nan_to_num(x - obs) * wt.data[..., None]
    cost = r.square().sum((1, 2))
    rp, _ = body.prior(local, None)
    cost = cost + wt.prior.square() * rp.square().sum((1, 2))
    if wt.temporal is not None:
        cost = cost + ((x - wt.target) * wt.temporal[..., None]).square().sum((1, 2))
    return cost


def frame_system(body, x, jac, g_rot, local, obs, wt: Weights):
    """Per-frame normal equations ``(H (B, N, N), g (B, N), row weights^2 (B, M))``; g = J^T W r."""
    b, m = x.shape[:2]
    w2 = wt.data.square()
    r = torch.nan_to_num(x - obs) * w2[..., None]
    if wt.temporal is not None:
        t2 = wt.temporal.square()
        r = r + (x - wt.target) * t2[..., None]
        w2 = w2 + t2
    jf = jac.reshape(b, 3 * m, -1)
    h = (jf * w2.repeat_interleave(3, 1)[..., None]).transpose(1, 2) @ jf
    g = (jf.transpose(1, 2) @ r.reshape(b, 3 * m, 1)).squeeze(-1)
    rp, jp = body.prior(local, g_rot)
    p2 = wt.prior.square()[:, None, None, None]
    blocks = torch.cat([jp.new_zeros(b, 2, 3, 3), p2 * jp.transpose(-1, -2) @ jp], 1)  # transl, Hips: no prior
    h = h + _block_diag(blocks)
    gp = (p2[..., 0] * (jp.transpose(-1, -2) @ rp[..., None]).squeeze(-1)).reshape(b, -1)
    g = g + torch.cat([gp.new_zeros(b, 6), gp], 1)
    return h, g, w2


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
    cost = frame_cost(body, x, local, obs, w)
    h, g, _ = frame_system(body, x, jac, g_rot, local, obs, w)
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


# --------------------------------------------------------------------------- stage 1


@dataclass(frozen=True)
class Stage1Result:
    """Shape, latent markers and the poses of the stage-1 frames."""

    ident: Identity
    anchors: torch.Tensor  # (M,)
    latent: torch.Tensor  # (M, 3) rest positions
    local: torch.Tensor  # (F, J, 3, 3)
    transl: torch.Tensor  # (F, 3)


def _take(ident: Identity, sl) -> Identity:
    return Identity(*(getattr(ident, f)[sl] for f in ident.__dataclass_fields__))


def _spread(x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Weighted RMS distance (B,) of points (B, M, 3) from their weighted centroid."""
    x = torch.nan_to_num(x)
    wn = w / w.sum(-1, keepdim=True).clamp_min(1e-12)
    c = (wn[..., None] * x).sum(1, keepdim=True)
    return ((wn * (x - c).square().sum(-1)).sum(-1)).sqrt()


def scale_init(body: MarkerBody, obs, vis, anchors, distance) -> torch.Tensor:
    """(1, K) start coefficients: the first component set so the marker spread matches the data.

    Umeyama's similarity scale of the torso markers (the relaxed pose of the mean body vs
    each frame, median over frames), mapped to the first coefficient through the spread of
    the body at coefficient 0 and 1 (the first component is mostly overall size).
    """
    beta = obs.new_zeros(2, body.num_components)
    beta[1, 0] = 1.0
    ident = body.identity(beta)
    p, _ = body.latent(ident, anchors, distance, 0.0)
    x, *_ = body.markers(ident, anchors, p, body.relaxed_local.expand(2, -1, -1, -1), obs.new_zeros(2, 3), False)
    torso = vis & body.torso_vertex[anchors]
    w = torch.where(torso.sum(1, keepdim=True) >= 3, torso, vis).to(obs.dtype)
    s = (_spread(obs, w) / _spread(x[:1].expand(obs.shape[0], -1, -1), w)).median()
    r1 = _spread(x[1:], vis.any(0, keepdim=True).to(obs.dtype)) / _spread(x[:1], vis.any(0, keepdim=True).to(obs.dtype))
    c0 = ((s - 1) / (r1 - 1).clamp_min(1e-3)).clamp(-3.0, 3.0)
    out = obs.new_zeros(1, body.num_components)
    out[0, 0] = c0[0]
    return out


class _Stage1:
    """Joint LM over per-frame poses, shape and latent marker slides (block-arrow Schur solve)."""

    def __init__(self, body: MarkerBody, obs, vis, anchors, distance, cfg, slide_std, surface_std) -> None:
        self.body, self.obs, self.vis, self.distance, self.cfg = body, obs, vis, distance, cfg
        self.orig = anchors
        self.slide_std, self.surface_std = slide_std, surface_std
        self.w_data = vis.to(obs.dtype) / cfg.marker_std

    def weights(self, a: float) -> dict[str, float]:
        c = self.cfg
        return {"pose": c.pose_prior_weight * a, "shape": c.shape_prior_weight * a, "slide": a / self.slide_std}

    def latent_cost(self, ident, anchors, delta, w) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(cost, p (1, M, 3), anchor normals (1, M, 3), p_init (1, M, 3)) of the shape and latent priors."""
        p, n = self.body.latent(ident, anchors, self.distance, delta)
        p_init, _ = self.body.latent(ident, self.orig, self.distance, 0.0)
        surf = (delta * n).sum(-1) / self.surface_std
        cost = (w["shape"] * ident.beta).square().sum() + (w["slide"] * (p - p_init)).square().sum()
        return cost + surf.square().sum(), p, n, p_init

    def total_cost(self, ident, anchors, delta, local, transl, w) -> tuple[torch.Tensor, torch.Tensor]:
        cost, p, _, _ = self.latent_cost(ident, anchors, delta, w)
        x, *_ = self.body.markers(ident, anchors, p, local, transl, False)
        wt = Weights(self.w_data, local.new_full((local.shape[0],), w["pose"]))
        return cost + frame_cost(self.body, x, local, self.obs, wt).sum(), x

    def linearize(self, beta, anchors, delta, local, transl, w: dict[str, float]):
        """Cost and block-arrow normal equations at the current state.

        Unknowns: per frame f the pose x_f (N,), globally z = (beta (K,), delta (3M,)). Returns
        ``(cost, g_rot, h_ff (F, N, N), g_f (F, N), h_fz (F, N, G), h_zz (G, G), g_z (G,))``. The
        marker Jacobian in beta is a forward difference over K + 1 identities in one batch; in
        delta it is the anchor's blended rotation.
        """
        body, f_count, m = self.body, local.shape[0], anchors.numel()
        k, h = body.num_components, 1e-4
        idall = body.identity(torch.cat([beta, beta + h * torch.eye(k, dtype=beta.dtype, device=beta.device)]))
        ident, fd = _take(idall, slice(0, 1)), _take(idall, slice(1, None))
        lat_cost, p, n, p_init = self.latent_cost(ident, anchors, delta, w)
        x, g_rot, jac, blend = body.markers(ident, anchors, p, local, transl, True)
        p_fd, _ = body.latent(fd, anchors, self.distance, delta)
        rep = (local.repeat(k, 1, 1, 1), transl.repeat(k, 1))
        x_fd, *_ = body.markers(fd.expand(f_count), anchors, p_fd.repeat_interleave(f_count, 0), *rep, False)
        jb = ((x_fd.view(k, f_count, m, 3) - x[None]) / h).permute(1, 2, 3, 0)  # (F, M, 3, K)
        jd = _block_diag(blend).view(f_count, m, 3, 3 * m)  # d x_m / d delta_m = blended rotation
        jz = torch.cat([jb, jd], -1).reshape(f_count, 3 * m, -1)
        wt = Weights(self.w_data, local.new_full((f_count,), w["pose"]))
        cost = lat_cost + frame_cost(body, x, local, self.obs, wt).sum()
        h_ff, g_f, w2 = frame_system(body, x, jac, g_rot, local, self.obs, wt)
        w2r = w2.repeat_interleave(3, 1)[..., None]
        h_fz = (jac.reshape(f_count, 3 * m, -1) * w2r).transpose(1, 2) @ jz
        h_zz = ((jz * w2r).transpose(1, 2) @ jz).sum(0)
        g_z = (jz.transpose(1, 2) @ (torch.nan_to_num(x - self.obs) * w2[..., None]).reshape(f_count, -1, 1)).sum(0)
        g_z = g_z.squeeze(-1)
        # Priors on the global unknowns: shape, slide (toward the initial placement), surface distance.
        ws2, wn2, eye3 = w["slide"] ** 2, self.surface_std**-2, torch.eye(3, dtype=x.dtype, device=x.device)
        h_zz[:k, :k] += w["shape"] ** 2 * torch.eye(k, dtype=x.dtype, device=x.device)
        g_z[:k] += w["shape"] ** 2 * beta[0]
        h_zz[k:, k:] += _block_diag((ws2 * eye3 + wn2 * n[0, :, :, None] * n[0, :, None, :])[None])[0]
        g_z[k:] += (ws2 * (p - p_init)[0] + wn2 * n[0] * (delta * n[0]).sum(-1, keepdim=True)).reshape(-1)
        return cost, g_rot, h_ff, g_f, h_fz, h_zz, g_z

    def step(self, beta, anchors, delta, local, transl, w: dict[str, float], lam: torch.Tensor):
        """One LM iteration (up to 4 damping increases); returns the state, the damping and the cost."""
        cost, g_rot, h_ff, g_f, h_fz, h_zz, g_z = self.linearize(beta, anchors, delta, local, transl, w)
        k, m = beta.shape[1], anchors.numel()
        for _ in range(4):
            # Schur complement on the per-frame blocks: S dz = -(g_z - H_zf H_ff^-1 g_f).
            chol = _damped_cholesky(h_ff, lam.expand(local.shape[0]))
            a_fz = torch.cholesky_solve(h_fz, chol)
            b_f = torch.cholesky_solve(g_f[..., None], chol)
            s = h_zz - (h_fz.transpose(1, 2) @ a_fz).sum(0)
            rhs = (h_fz.transpose(1, 2) @ b_f).sum(0).squeeze(-1) - g_z
            dz = torch.cholesky_solve(rhs[:, None], _damped_cholesky(s[None], lam)[0]).squeeze(-1)
            dx = -(b_f.squeeze(-1) + (a_fz @ dz[:, None]).squeeze(-1))
            c_beta, c_delta = beta + dz[:k], delta + dz[k:].view(m, 3)
            c_local, c_transl = self.body.apply(local, transl, g_rot, dx)
            c_cost, _ = self.total_cost(self.body.identity(c_beta), anchors, c_delta, c_local, c_transl, w)
            if bool(c_cost < cost):
                return (c_beta, c_delta, c_local, c_transl), (lam / 3).clamp_min(1e-7), c_cost
            lam = (lam * 10).clamp_max(1e7)
        return (beta, delta, local, transl), lam, cost

    def reanchor(self, beta, anchors, delta):
        """Attach each latent marker to its nearest rest vertex (its slide stays the same point)."""
        ident = self.body.identity(beta)
        p, _ = self.body.latent(ident, anchors, self.distance, delta)
        new = torch.cdist(p[0], ident.rest[0]).argmin(1)
        base, _ = self.body.latent(ident, new, self.distance, 0.0)
        return new, (p - base)[0]


def stage1(
    body: MarkerBody, obs, vis, anchors, distance, cfg, *, slide_std: float, surface_std: float, progress=None
) -> Stage1Result:
    """Fit shape, latent markers and the poses of F frames (obs (F, M, 3), vis (F, M)).

    Schedule: the scale start (:func:`scale_init`), a Kabsch root per frame, pose-only LM
    iterations at the strongest prior, then for each anneal factor a (prior weights times a)
    ``stage1_iters`` joint LM iterations followed by a re-anchoring of the latent markers.
    """
    st = _Stage1(body, obs, vis, anchors, distance, cfg, slide_std, surface_std)
    beta = scale_init(body, obs, vis, anchors, distance)
    delta = obs.new_zeros(anchors.numel(), 3)
    ident = body.identity(beta)
    p, _ = body.latent(ident, anchors, distance, delta)
    local, transl = body.root_init(ident, anchors, p, body.relaxed_local.expand(obs.shape[0], -1, -1, -1), obs, vis)
    w0 = st.weights(cfg.stage1_anneal[0])
    wt = Weights(st.w_data, obs.new_full((obs.shape[0],), w0["pose"]))
    local, transl, *_ = lm_frames(body, ident, anchors, p, local, transl, obs, lambda x: wt, cfg.stage1_iters)
    lam = obs.new_full((1,), 1e-3)
    for level, a in enumerate(cfg.stage1_anneal):
        w = st.weights(a)
        for _ in range(cfg.stage1_iters):
            (beta, delta, local, transl), lam, cost = st.step(beta, anchors, delta, local, transl, w, lam)
        anchors, delta = st.reanchor(beta, anchors, delta)
        if progress is not None:
            progress(f"stage 1: level {level + 1}/{len(cfg.stage1_anneal)} (prior x{a:g}), cost {float(cost):.1f}")
    ident = body.identity(beta)
    p, _ = body.latent(ident, anchors, distance, delta)
    return Stage1Result(ident, anchors, p[0], local, transl)


# --------------------------------------------------------------------------- stage 2


def _temporal_fn(x_hist, frames, w_data, w_prior, w_acc: float) -> Callable:
    """Weights with block-Jacobi temporal targets for the frames of the window.

    A frame whose previous and next frames (in time) are both in ``x_hist`` or the window gets
    the target (x_{t-1} + x_{t+1}) / 2 with weight ``w_acc`` = 2 / (s dt^2) (s: acceleration
    std: the residual is -a dt^2 / 2); the newest frame has none until its successor arrives.
    Each frame moves to a weighted mean of its data and its neighbours' average, a contraction,
    so the coupling cannot diverge (a one-sided constant-velocity target 2 x_{t-1} - x_{t-2}
    did, under strong weights: it doubles the neighbours' errors).
    ``x_hist`` (H <= 2, M, 3) are model markers of retired frames; ``frames`` the frame indices
    of the H retired frames and then of the window.
    """
    h = x_hist.shape[0]
    gap = frames[1:] - frames[:-1]
    both = (torch.cat([gap.new_zeros(1), gap]) == 1) & (torch.cat([gap, gap.new_zeros(1)]) == 1)
    w = (both[h:].to(w_data.dtype) * w_acc)[:, None].expand(-1, w_data.shape[1])

    def fn(x: torch.Tensor) -> Weights:
        seq = torch.cat([x_hist, x])
        prev = torch.cat([seq[:1], seq[:-1]])
        nxt = torch.cat([seq[1:], seq[-1:]])
        return Weights(w_data, w_prior, w, ((prev + nxt) / 2)[h:])

    return fn


def slerp_local(a: torch.Tensor, b: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Geodesic interpolation of rotations (..., 3, 3) with fractions t (...)."""
    rel = matrix_to_axis_angle(a.transpose(-1, -2) @ b)
    return a @ axis_angle_to_matrix(t[..., None] * rel)


def interpolate(local, transl, solved: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Fill unsolved frames: slerp / lerp between the nearest solved frames, held at the ends."""
    idx = torch.nonzero(solved).flatten()
    missing = torch.nonzero(~solved).flatten()
    if missing.numel() == 0 or idx.numel() == 0:
        return local, transl
    pos = torch.searchsorted(idx, missing)
    lo = idx[(pos - 1).clamp_min(0)]
    hi = idx[pos.clamp_max(idx.numel() - 1)]
    lo = torch.where(pos == 0, hi, lo)
    hi = torch.where(pos == idx.numel(), lo, hi)
    frac = torch.where(hi > lo, (missing - lo).to(transl.dtype) / (hi - lo).clamp_min(1).to(transl.dtype), 0.0)
    local, transl = local.clone(), transl.clone()
    local[missing] = slerp_local(local[lo], local[hi], frac[:, None].expand(-1, local.shape[1]))
    transl[missing] = transl[lo] + frac[:, None] * (transl[hi] - transl[lo])
    return local, transl


class _Stage2:
    """Stage 2 by a sliding window (wavefront) over the solved frames; see :func:`stage2`."""

    def __init__(self, body: MarkerBody, ident, anchors, p, obs, vis, cfg, fps: float) -> None:
        t_count, m = vis.shape
        nvis = vis.sum(1)
        self.solved = nvis >= max(cfg.min_markers, int(cfg.min_visible * m + 0.999))
        self.body, self.ident, self.anchors, self.p = body, ident, anchors, p
        self.obs, self.vis, self.cfg = obs, vis, cfg
        dt = obs.dtype
        # MoSh++: data weight renormalised by the visible count, pose prior grown with the missing one.
        self.w_data = vis.to(dt) / cfg.marker_std * (m / nvis.clamp_min(1).to(dt)).sqrt()[:, None]
        self.w_prior = cfg.pose_prior_weight * (1 + cfg.missing_prior_gain * (m - nvis).to(dt) / m).sqrt()
        self.w_acc = 2 * fps**2 / cfg.acceleration_std
        self.local = body.relaxed_local.expand(t_count, -1, -1, -1).clone()  # retired estimates
        self.transl = obs.new_zeros(t_count, 3)
        self.recent: list[float] = []  # costs of the last retired frames
        self.last_try = 0

    def first(self, f: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The first frame: relaxed pose, Kabsch root, LM with the pose prior annealed from 10x (MoSh++)."""
        b, sl = self.body, slice(f, f + 1)
        local, transl = b.root_init(self.ident, self.anchors, self.p, b.relaxed_local, self.obs[sl], self.vis[sl])
        for mult in (10.0, 3.0, 1.0):
            w = Weights(self.w_data[sl], self.w_prior[sl] * mult)
            local, transl, *_ = lm_frames(
                b, self.ident, self.anchors, self.p, local, transl, self.obs[sl], lambda x, w=w: w, self.cfg.window
            )
        return local, transl

    def cost(self, f: int, local: torch.Tensor, transl: torch.Tensor) -> torch.Tensor:
        """(B,) data + prior cost of B candidate states of frame f."""
        b, sl = local.shape[0], slice(f, f + 1)
        x, *_ = self.body.markers(self.ident, self.anchors, self.p, local, transl, jacobian=False)
        w = Weights(self.w_data[sl].expand(b, -1), self.w_prior[sl].expand(b))
        return torch.nan_to_num(frame_cost(self.body, x, local, self.obs[sl], w), torch.inf)

    def stuck(self, f: int, cost: float) -> bool:
        """Whether to re-solve a retiring frame afresh: its cost jumped over 3x the median of the
        last 60 retired frames (at most every 8 frames), or ``recheck_every`` frames passed.

        On CMU 85_02 (flips, breakdance) fresh solves beat the tracked state in about half of
        the periodic checks (e.g. cost 251 -> 154), and the mean residual fell from 7.9 to 6.5 mm.
        """
        recent = self.recent
        self.recent = (recent + [cost])[-60:]
        periodic = f - self.last_try >= self.cfg.recheck_every
        jump = len(recent) >= 10 and f - self.last_try >= 8 and cost > 3 * sorted(recent)[len(recent) // 2]
        if not (periodic or jump):
            return False
        self.last_try = f
        return True

    def reseed(self, win: list[int], local, transl, l1, t1) -> tuple[torch.Tensor, torch.Tensor]:
        """Offer a recovered state (l1, t1) of the retiring frame (row 0) to the window ``win`` (rows 1..).

        The recovered state is refined on each window frame by ``window`` LM iterations (one
        batch), and each frame keeps whichever of its own and the refined state costs less.
        """
        if not win:
            return local, transl
        fr = torch.tensor(win, device=local.device)
        n = fr.numel()
        w = Weights(self.w_data[fr], self.w_prior[fr])
        cand_l, cand_t, *_ = lm_frames(
            self.body, self.ident, self.anchors, self.p, l1.expand(n, -1, -1, -1), t1.expand(n, -1),
            self.obs[fr], lambda x: w, self.cfg.window,
        )  # fmt: skip
        own = torch.cat([self.cost(g, local[i + 1 : i + 2], transl[i + 1 : i + 2]) for i, g in enumerate(win)])
        new = torch.cat([self.cost(g, cand_l[i : i + 1], cand_t[i : i + 1]) for i, g in enumerate(win)])
        take = torch.cat([torch.zeros(1, dtype=torch.bool, device=local.device), new < own])
        cand_l, cand_t = torch.cat([local[:1], cand_l]), torch.cat([transl[:1], cand_t])
        return torch.where(take[:, None, None, None], cand_l, local), torch.where(take[:, None], cand_t, transl)

    def retire(self, f: int, win: list[int], local, transl, x0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Finish frame f (row 0 of the window states; ``win``: the frames after it).

        When :meth:`stuck` says so, the frame is solved afresh (:meth:`first`): a warm start can
        carry a wrong minimum (a limb turned the wrong way) from frame to frame. A better fresh
        solution replaces it and is offered to the window (:meth:`reseed`). Returns the window's
        states without row 0 and the frame's model markers x0 (1, M, 3).
        """
        cost = float(self.cost(f, local[:1], transl[:1]))
        if self.stuck(f, cost):
            l1, t1 = self.first(f)
            if float(self.cost(f, l1, t1)) < cost:
                local, transl = self.reseed(win, torch.cat([l1, local[1:]]), torch.cat([t1, transl[1:]]), l1, t1)
                x0 = self.body.markers(self.ident, self.anchors, self.p, l1, t1, jacobian=False)[0]
        self.local[f], self.transl[f] = local[0], transl[0]
        return local[1:], transl[1:], x0

    def start(self, f: int, last: int, retired: list[int], win_local, win_transl):
        """Start of frame f from the latest estimate (frame ``last``: the window's newest or retired).

        After a gap the root is re-found by Kabsch. Otherwise the constant-velocity guess
        L_f = L_last L_a^T L_b from the two latest retired, converged frames (a, b) is tried
        as well and kept when it fits frame f better (extrapolating unconverged window
        estimates diverged in tests).
        """
        b, sl = self.body, slice(f, f + 1)
        if win_local.shape[0]:
            l0, t0 = win_local[-1:], win_transl[-1:]
        else:
            l0, t0 = self.local[last][None], self.transl[last][None]
        if f != last + 1:
            return b.root_init(self.ident, self.anchors, self.p, l0, self.obs[sl], self.vis[sl])
        if len(retired) < 2 or retired[1] - retired[0] != 1 or last - retired[1] != win_local.shape[0]:
            return l0, t0
        a, c = retired
        cand_l = torch.cat([l0, l0 @ (self.local[a].transpose(-1, -2) @ self.local[c])[None]])
        cand_t = torch.cat([t0, t0 + self.transl[c] - self.transl[a]])
        best = int(self.cost(f, cand_l, cand_t).argmin())
        return cand_l[best : best + 1], cand_t[best : best + 1]


def stage2(body: MarkerBody, ident, anchors, p, obs, vis, cfg, fps: float, progress=None):
    """Per-frame pose and translation of all frames by a sliding window (wavefront).

    The window holds the ``window`` most recent frames. Each tick adds the next frame (started
    by :meth:`_Stage2.first` / :meth:`_Stage2.start`), runs one batched LM iteration on the
    whole window, with temporal targets from the neighbours' latest estimates, and retires the
    oldest frame (:meth:`_Stage2.retire`, which may re-solve it afresh). Every frame thus gets
    ``window`` iterations, warm-started from a predecessor that already had ``window - 1``: the
    accuracy of a sequential solve for the cost of one batched iteration per frame. Unsolved
    frames are interpolated at the end.

    Returns ``(local (T, J, 3, 3), transl (T, 3), solved (T,) bool)``.
    """
    st = _Stage2(body, ident, anchors, p, obs, vis, cfg, fps)
    frames = torch.nonzero(st.solved).flatten().tolist()
    hist_x, retired, win = obs.new_zeros(0, vis.shape[1], 3), [], []  # model markers of the last 2 retired
    local, transl, lam = obs.new_zeros(0, body.layer.num_joints, 3, 3), obs.new_zeros(0, 3), obs.new_zeros(0)
    added = done = 0
    while added < len(frames) or win:
        if added < len(frames):
            f = frames[added]
            l0, t0 = st.first(f) if added == 0 else st.start(f, (retired + win)[-1], retired, local, transl)
            win.append(f)
            added += 1
            local, transl = torch.cat([local, l0]), torch.cat([transl, t0])
            lam = torch.cat([lam, lam.new_full((1,), 1e-3)])
        fr = torch.tensor(win, device=obs.device)
        frames_t = torch.tensor(retired + win, device=obs.device)
        fn = _temporal_fn(hist_x, frames_t, st.w_data[fr], st.w_prior[fr], st.w_acc)
        local, transl, lam, x = lm_iteration(body, ident, anchors, p, local, transl, obs[fr], fn, lam)
        if len(win) == cfg.window or added == len(frames):
            f = win.pop(0)
            local, transl, x0 = st.retire(f, win, local, transl, x[:1])
            hist_x, retired, lam = torch.cat([hist_x, x0])[-2:], (retired + [f])[-2:], lam[1:]
            done += 1
            if progress is not None and (done % max(1, len(frames) // 10) == 0 or done == len(frames)):
                progress(f"stage 2: {done}/{len(frames)} solved frames")
    local_out, transl_out = interpolate(st.local, st.transl, st.solved)
    return local_out, transl_out, st.solved
