"""Stage 2 of the marker solve: per-frame pose and translation, warm-started, with a temporal prior."""

from __future__ import annotations

from collections.abc import Callable

import torch

from ..geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from ._marker_body import MarkerBody, Weights, frame_cost, lm_frames, lm_iteration


def _temporal_fn(x_hist, frames, w_data, w_prior, w_acc: float, robust: float, temporal_robust: float) -> Callable:
    """Weights with block-Jacobi temporal targets for the frames of the window.

    A frame whose previous and next frames (in time) are both in ``x_hist`` or the window gets
    the target (x_{t-1} + x_{t+1}) / 2 with weight ``w_acc`` = 2 / (s dt^2) (s: acceleration
    std: the residual is -a dt^2 / 2); the newest frame has none until its successor arrives.
    Each frame moves to a weighted mean of its data and its neighbours' average, a contraction,
    so the coupling cannot diverge (a one-sided constant-velocity target 2 x_{t-1} - x_{t-2}
    did, under strong weights: it doubles the neighbours' errors).
    ``x_hist`` (H <= 2, M, 3) are model markers of retired frames; ``frames`` the frame indices
    of the H retired frames and then of the window. ``temporal_robust`` (m): the Cauchy scale of
    that residual (see :class:`~.solve_config.SolveConfig`'s ``acceleration_robust``).
    """
    h = x_hist.shape[0]
    gap = frames[1:] - frames[:-1]
    both = (torch.cat([gap.new_zeros(1), gap]) == 1) & (torch.cat([gap, gap.new_zeros(1)]) == 1)
    w = (both[h:].to(w_data.dtype) * w_acc)[:, None].expand(-1, w_data.shape[1])

    def fn(x: torch.Tensor) -> Weights:
        seq = torch.cat([x_hist, x])
        prev = torch.cat([seq[:1], seq[:-1]])
        nxt = torch.cat([seq[1:], seq[-1:]])
        return Weights(w_data, w_prior, w, ((prev + nxt) / 2)[h:], robust, temporal_robust)

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
        self.solved = cfg.solvable(vis)
        self.body, self.ident, self.anchors, self.p = body, ident, anchors, p
        self.obs, self.vis, self.cfg = obs, vis, cfg
        dt = obs.dtype
        # MoSh++: data weight renormalised by the visible count, pose prior grown with the missing one.
        self.w_data = vis.to(dt) / cfg.marker_std * (m / nvis.clamp_min(1).to(dt)).sqrt()[:, None]
        self.w_prior = cfg.pose_prior_weight * (1 + cfg.missing_prior_gain * (m - nvis).to(dt) / m).sqrt()
        self.w_acc = 2 * fps**2 / cfg.acceleration_std
        self.acc_robust = cfg.acceleration_robust / (2 * fps**2)  # m: that acceleration's residual
        self.local = body.relaxed_local.expand(t_count, -1, -1, -1).clone()  # retired estimates
        self.transl = obs.new_zeros(t_count, 3)
        self.recent: list[float] = []  # costs of the last retired frames
        self.last_try = 0

    def first(self, f: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The first frame: relaxed pose, Kabsch root, LM with the pose prior annealed from 10x (MoSh++)."""
        b, sl = self.body, slice(f, f + 1)
        local, transl = b.root_init(self.ident, self.anchors, self.p, b.relaxed_local, self.obs[sl], self.vis[sl])
        for mult in (10.0, 3.0, 1.0):
            w = Weights(self.w_data[sl], self.w_prior[sl] * mult, robust=self.cfg.robust)
            local, transl, *_ = lm_frames(
                b, self.ident, self.anchors, self.p, local, transl, self.obs[sl], lambda x, w=w: w, self.cfg.window
            )
        return local, transl

    def cost(self, f: int, local: torch.Tensor, transl: torch.Tensor) -> torch.Tensor:
        """(B,) data + prior cost of B candidate states of frame f."""
        b, sl = local.shape[0], slice(f, f + 1)
        x, *_ = self.body.markers(self.ident, self.anchors, self.p, local, transl, jacobian=False)
        w = Weights(self.w_data[sl].expand(b, -1), self.w_prior[sl].expand(b), robust=self.cfg.robust)
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
        w = Weights(self.w_data[fr], self.w_prior[fr], robust=self.cfg.robust)
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
        fn = _temporal_fn(hist_x, frames_t, st.w_data[fr], st.w_prior[fr], st.w_acc, cfg.robust, st.acc_robust)
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
