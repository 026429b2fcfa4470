"""Stage 1 of the marker solve: shape, latent markers and the poses of a few well-visible frames."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ._marker_body import (
    Identity,
    MarkerBody,
    Weights,
    _block_diag,
    _damped_cholesky,
    frame_cost,
    frame_system,
    lm_frames,
)


@dataclass(frozen=True)
class Stage1Result:
    """Shape, latent markers and the poses of the stage-1 frames."""

    ident: Identity
    anchors: torch.Tensor  # (M,)
    latent: torch.Tensor  # (M, 3) rest positions
    local: torch.Tensor  # (F, J, 3, 3)
    transl: torch.Tensor  # (F, 3)


def pick_frames(vis: torch.Tensor, n: int) -> torch.Tensor:
    """(F <= n,) frames spread over the sequence: the best visible frame of n equal segments.

    In each segment the frame with the most visible markers wins (ties: the one nearest the
    segment's middle), so a sequence with no complete frame still gets its best ones. Frames
    with fewer than 3 visible markers are never picked.
    """
    t = vis.shape[0]
    counts = vis.sum(1)
    bounds = torch.linspace(0, t, min(n, t) + 1).round().long().tolist()
    out = []
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        if hi <= lo:
            continue
        c = counts[lo:hi].double()
        mid = (lo + hi - 1) / 2
        score = c - 1e-3 * (torch.arange(lo, hi, dtype=torch.float64, device=c.device) - mid).abs() / max(1, hi - lo)
        best = lo + int(score.argmax())
        if counts[best] >= 3:
            out.append(best)
    return torch.tensor(out, dtype=torch.long)


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
        wt = Weights(self.w_data, local.new_full((local.shape[0],), w["pose"]), robust=self.cfg.robust)
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
        wt = Weights(self.w_data, local.new_full((f_count,), w["pose"]), robust=self.cfg.robust)
        f_cost, h_ff, g_f, w2 = frame_system(body, x, jac, g_rot, local, self.obs, wt)
        cost = lat_cost + f_cost.sum()
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
    wt = Weights(st.w_data, obs.new_full((obs.shape[0],), w0["pose"]), robust=cfg.robust)
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
