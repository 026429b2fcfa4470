"""Fit identity parameters of any backend to canonical meshes in the bind A-pose.

The objective is the mean squared per-vertex distance between the backend's identity, run
through the whole unified pipeline and reposed to the rig's bind A-pose,

    fit(p) = repose_to_bind(prepare_identity(p))   (identity -> topology transfer -> skeleton fit -> repose)

and target meshes on the canonical topology, in the same pose (paper 000 §4.4: shapes of
different models compare once they share topology and rest pose). Every stage is
differentiable, so a backend whose shape space is not a linear basis on the canonical mesh
(Anny's phenotypes, SMPL betas through a registration, MHR bone scales, ...) is fitted by
gradient descent: optionally Adam, then L-BFGS. Items of the batch are independent (the
objective is a sum over items).

Parameter ranges are respected by construction: a parameter with two finite limits is
``lo + (hi - lo) sigmoid(z)``, one with a single finite limit ``lo + softplus(z)`` (or
``hi - softplus(z)``), an unbounded one is ``z`` itself; the optimiser works on ``z``.
Limits are the backend's ``param_bounds`` (:class:`~unibody.identity.base.IdentityBackend`):
Anny's phenotypes in [0, 1] and local changes in [-1, 1], the PCA's coefficients within
+-10 sigma_0 / sigma_k, MHR's bone scales within the file's limits; SMPL and
GarmentMeasurements are unbounded. Units: metres.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from .._checks import check_finite, check_grad_mode, check_like, check_shape
from ..body import BodyLayer
from ..identity.base import IdentityBackend

__all__ = ["IdentityFit", "fit_identity", "param_limits"]

# Start points on (or within this fraction of the range from) a finite limit are moved
# inside it: a sigmoid or softplus reaches its limit only at infinity.
_INSIDE = 1e-4
_HISTORY = 30  # L-BFGS memory; measured on Anny + 256 local changes: 0.72 mm mean after 100 iterations vs 1.1 with 10
_MAX_TRIALS = 12  # line-search trials per L-BFGS iteration (t shrinks 2 to 10 times per trial)
SPAN_EXPONENT = 0.5
"""How the parameters' steps grow with their spans (:class:`_Bounded`): 0.5 fits every native-PCA
body of ``benchmarks/identity_fit.py``; 0.85 and 1 stop some in other minima, 0 converges slowly."""


@dataclass(frozen=True, slots=True)
class IdentityFit:
    """Identity parameters fitted to canonical meshes in the bind A-pose.

    Attributes:
        params: (B, K) fitted parameters of the layer's backend, within their limits.
        vertices: (B, V, 3) m, the fitted identities reposed to the bind A-pose.
        per_vertex_error: (B, V) m, distance between ``vertices`` and the targets.
        adam_steps: Adam steps taken.
        lbfgs_steps: L-BFGS iterations taken (each may evaluate the objective several times).
    """

    params: torch.Tensor
    vertices: torch.Tensor
    per_vertex_error: torch.Tensor
    adam_steps: int
    lbfgs_steps: int


def param_limits(identity: IdentityBackend) -> torch.Tensor:
    """(K, 2) [min, max] of each identity parameter (+-inf where unbounded), float64 on CPU.

    Args:
        identity: an identity backend; its ``param_bounds`` (None: all unbounded).

    Raises:
        ValueError: ``param_bounds`` is not None nor a pair of (K,) tensors.
    """
    k = int(identity.num_params)
    bounds = identity.param_bounds
    if bounds is None:
        return torch.tensor([-math.inf, math.inf], dtype=torch.float64).repeat(k, 1)
    shapes = [tuple(b.shape) if isinstance(b, torch.Tensor) else type(b).__name__ for b in bounds]
    if len(shapes) != 2 or any(s != (k,) for s in shapes):
        raise ValueError(f"identity.param_bounds: expected (lower, upper) of shape ({k},) each, got {shapes}")
    return torch.stack([b.detach().to("cpu", torch.float64) for b in bounds], dim=1)


class _Bounded:
    """The map z -> params that keeps each parameter within its limits, and its inverse.

    A parameter with both limits is ``lo + (hi - lo) sigmoid(g z)``, its slope at mid-range
    ``s = (hi - lo) g / 4``. The narrowest span gets ``s = min(1, span / 4)`` (a unit step of z
    moves a [0, 1] phenotype by 0.25, the native PCA's leading coefficient by one sigma) and the
    slopes grow as ``span ** SPAN_EXPONENT`` from there. For the native PCA (``|c_k| <= 10
    sigma_0 / sigma_k``) the exponent picks how far a unit step moves the vertices of component
    k: 0, alike in sigma (the last components barely move the mesh: slow); 1, alike in
    millimetres (fast, but it stops in other minima). ``benchmarks/identity_fit.py`` compares them.
    The slopes of before (the span's own, ``s = span / 4``) sent the first L-BFGS step of the
    native PCA to a 19 m body, which the layer refuses.
    """

    def __init__(self, limits: torch.Tensor, ref: torch.Tensor) -> None:
        lo, hi = limits[:, 0], limits[:, 1]
        if bool((lo >= hi).any()):
            k = int(torch.nonzero(lo >= hi)[0])
            raise ValueError(f"param limits: parameter {k} has min {float(lo[k])} >= max {float(hi[k])}")
        self.both = (lo.isfinite() & hi.isfinite()).to(ref.device)
        self.low_only = (lo.isfinite() & ~hi.isfinite()).to(ref.device)
        self.high_only = (~lo.isfinite() & hi.isfinite()).to(ref.device)
        self.lo = torch.where(lo.isfinite(), lo, 0.0).to(ref)
        self.hi = torch.where(hi.isfinite(), hi, 0.0).to(ref)
        self.lo_raw, self.hi_raw = lo.to(ref), hi.to(ref)
        span = torch.where(self.both, self.hi - self.lo, 1.0)
        narrow = float(span[self.both].min()) if bool(self.both.any()) else 1.0
        slope = min(1.0, narrow / 4) * (span / narrow) ** SPAN_EXPONENT
        self.gain = torch.where(self.both, 4 * slope / span, 1.0)

    def __call__(self, z: torch.Tensor) -> torch.Tensor:
        sig = self.lo + (self.hi - self.lo) * torch.sigmoid(self.gain * z)
        out = torch.where(self.both, sig, z)
        out = torch.where(self.low_only, self.lo + F.softplus(z), out)
        return torch.where(self.high_only, self.hi - F.softplus(z), out)

    def inverse(self, params: torch.Tensor) -> torch.Tensor:
        """z for start parameters; those on a finite limit are first moved just inside it."""
        bad = (params < self.lo_raw) | (params > self.hi_raw)
        if bool(bad.any()):
            b, k = (int(i) for i in torch.nonzero(bad)[0])
            raise ValueError(
                f"init: parameter {k} must lie in [{float(self.lo_raw[k]):g}, {float(self.hi_raw[k]):g}], "
                f"got {float(params[b, k]):.4g} at batch {b}"
            )
        span = torch.where(self.both, self.hi - self.lo, torch.ones_like(self.lo))
        eps = _INSIDE * span
        p = torch.where(self.lo_raw.isfinite(), torch.maximum(params, self.lo + eps), params)
        p = torch.where(self.hi_raw.isfinite(), torch.minimum(p, self.hi - eps), p)
        u = ((p - self.lo) / span).clamp(_INSIDE, 1.0 - _INSIDE)
        z = torch.where(self.both, torch.logit(u) / self.gain, p)
        softplus_inv = lambda y: y + torch.log(-torch.expm1(-y))  # noqa: E731  (y > 0)
        z = torch.where(self.low_only, softplus_inv((p - self.lo).clamp_min(eps)), z)
        return torch.where(self.high_only, softplus_inv((self.hi - p).clamp_min(eps)), z)


def _check_args(layer: BodyLayer, targets: torch.Tensor, steps: int, lbfgs_steps: int, lr: float) -> None:
    if not isinstance(layer, BodyLayer):
        raise TypeError(f"layer: expected a BodyLayer, got {type(layer).__name__}")
    if layer.identity is None:
        raise ValueError("layer: has no identity backend to fit (built for prepare_rest only)")
    check_shape(targets, f"B {layer.num_vertices} 3", name="targets")
    check_like(targets, layer.skeleton.bind_rot, name="targets")
    check_finite(targets, "targets")
    for name, n in (("steps", steps), ("lbfgs_steps", lbfgs_steps)):
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            raise ValueError(f"{name}: expected an int >= 0, got {n!r}")
    if not (isinstance(lr, int | float) and not isinstance(lr, bool) and math.isfinite(lr) and lr > 0):
        raise ValueError(f"lr: expected a finite float > 0, got {lr!r}")


def fit_identity(
    layer: BodyLayer,
    targets: torch.Tensor,
    *,
    steps: int = 0,
    lr: float = 0.05,
    lbfgs_steps: int = 200,
    init: torch.Tensor | None = None,
    progress: Callable[[str], None] | None = None,
) -> IdentityFit:
    """Fit the layer's identity parameters to meshes in the bind A-pose.

    Minimises, for each item b independently, mean_i |fit_b,i - target_b,i|^2 with
    ``fit = layer.repose_to_bind(layer.prepare_identity(params))``: Adam for ``steps`` steps
    with learning rate ``lr`` on the unconstrained variables (cosine-decayed to lr / 100),
    then ``lbfgs_steps`` iterations of a batched L-BFGS in which every item has its own
    curvature memory and its own backtracking (Armijo) line search. One objective evaluation
    runs the whole batch (or the items still searching) through the layer once.

    The defaults skip Adam: on held-out Anny identities (``benchmarks/shape_spaces.py``)
    L-BFGS alone from the default start reached the same residual as 50 Adam steps + L-BFGS
    with 6 phenotypes (9.6 vs 9.7 mm mean, 16 identities) and a much lower one with 262
    parameters (0.48 vs 1.77 mm mean for the same cost, 8 identities): Adam's equal-size
    steps push the many weakly identified parameters around. Adam stays available for
    objectives that are too rough for a line search.

    Args:
        layer: a layer with an identity backend; its dtype and device are used.
        targets: (B, V, 3) m, canonical meshes reposed to the bind A-pose (see
            :meth:`BodyLayer.repose_to_bind`).
        steps: Adam steps (>= 0).
        lr: Adam learning rate, in units of the unconstrained variables (for a parameter
            in [0, 1], ``z`` with ``p = sigmoid(z)``).
        lbfgs_steps: L-BFGS iterations after Adam (>= 0); an item stops once it gains less
            than float precision (10 eps relative), the whole fit once every item stopped.
        init: (B, K) or (1, K) start parameters within their limits; default the backend's
            ``default_params`` (Anny: the average identity; linear bases: zeros).
        progress: called with a one-line report about ten times per run (e.g. ``print``).

    Returns:
        :class:`IdentityFit` (parameters, reposed fits, per-vertex error; detached).

    Raises:
        TypeError / ValueError: bad layer, targets (shape, dtype, device, NaN), counts, lr or init.
    """
    check_grad_mode("fit_identity")
    _check_args(layer, targets, steps, lbfgs_steps, lr)
    b = targets.shape[0]
    ref = layer.skeleton.bind_rot
    if init is None:
        init = layer.identity.default_params(1).to(ref)
    check_shape(init, f"B {layer.identity.num_params}", name="init")
    if init.shape[0] not in (1, b):
        raise ValueError(f"init: expected batch 1 or {b} (the targets' batch), got {init.shape[0]}")
    check_like(init, ref, name="init")
    check_finite(init, "init")
    bounded = _Bounded(param_limits(layer.identity), ref)
    objective = _Objective(layer, bounded, targets.detach())
    z = bounded.inverse(init.detach()).expand(b, -1).clone()
    report = _Reporter(progress, steps + lbfgs_steps, b)
    if steps:
        z = _adam(objective, z, steps, lr, report)
    done = 0
    if lbfgs_steps:
        z, done = _lbfgs(objective, z, lbfgs_steps, report, first=steps)
    with torch.no_grad():
        params = bounded(z)
        fit = layer.repose_to_bind(layer.prepare_identity(params))
        err = (fit - objective.targets).norm(dim=-1)
    check_finite(params, "fitted params")
    return IdentityFit(params, fit, err, steps, done)


class _Objective:
    """Per-item mean squared per-vertex distance, mm^2 (O(1) values for the line search)."""

    def __init__(self, layer: BodyLayer, bounded: _Bounded, targets: torch.Tensor) -> None:
        self.layer, self.bounded, self.targets = layer, bounded, targets

    def __call__(self, z: torch.Tensor, items: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``(f (n,), grad (n, K))`` at z (n, K) for the targets ``items`` (default all)."""
        target = self.targets if items is None else self.targets[items]
        z = z.detach().requires_grad_(True)
        with torch.enable_grad():
            fit = self.layer.repose_to_bind(self.layer.prepare_identity(self.bounded(z)))
            f = 1e6 * (fit - target).square().sum(-1).mean(-1)
            # Items are independent: the gradient of the sum is each item's own gradient. Taken
            # with respect to z only, so no gradient accumulates in the layer's tensors.
            (grad,) = torch.autograd.grad(f.sum(), z)
        return f.detach(), grad


def _adam(objective: _Objective, z: torch.Tensor, steps: int, lr: float, report: _Reporter) -> torch.Tensor:
    z = z.clone().requires_grad_(True)
    opt = torch.optim.Adam([z], lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=steps, eta_min=lr / 100)
    for i in range(steps):
        f, z.grad = objective(z)
        opt.step()
        sched.step()
        report(i + 1, "adam", f)
    return z.detach()


def _direction(g: torch.Tensor, s: torch.Tensor, y: torch.Tensor, rho: torch.Tensor) -> torch.Tensor:
    """-H g by the L-BFGS two-loop recursion, batched; memory (B, m, K), newest last, rho 0 = empty."""
    q, alphas = g.clone(), []
    for i in reversed(range(s.shape[1])):
        a = rho[:, i] * (s[:, i] * q).sum(-1)
        q = q - a[:, None] * y[:, i]
        alphas.append(a)
    sy, yy = (s[:, -1] * y[:, -1]).sum(-1), (y[:, -1] * y[:, -1]).sum(-1)
    # Initial scaling s.y / y.y from the newest pair; without memory a steepest-descent step
    # whose largest entry is 1 (an O(1) change of the unconstrained variables).
    no_memory = rho[:, -1] == 0
    gamma = torch.where(no_memory, 1.0 / g.abs().amax(-1).clamp_min(1e-12), sy / yy.clamp_min(1e-30))
    r = gamma[:, None] * q
    for i, a in zip(range(s.shape[1]), reversed(alphas), strict=True):
        bcoef = rho[:, i] * (y[:, i] * r).sum(-1)
        r = r + s[:, i] * (a - bcoef)[:, None]
    return -r


def _lbfgs(
    objective: _Objective, z: torch.Tensor, iters: int, report: _Reporter, *, first: int, history: int = _HISTORY
) -> tuple[torch.Tensor, int]:
    """Batched L-BFGS with a per-item backtracking line search; returns (z, iterations run).

    Kept instead of ``torch.optim.LBFGS``, which shares one memory and one line search across
    the batch (items would no longer be independent). Measured on the tests' cases (one core,
    same objective, history 30, strong Wolfe): Anny float64, 2 identities: this 14.6 s, 128
    evaluations, max error 5e-14 m; torch 13.7 s, 122 evaluations, stalled at 1.66 mm (0.054
    phenotype error) even with max_iter 400. PCA, 10 components: 1.6 vs 1.2 s, 0.026 vs 0.027 mm.
    """
    b, k = z.shape
    s, y = z.new_zeros(b, history, k), z.new_zeros(b, history, k)
    rho = z.new_zeros(b, history)
    f, g = objective(z)
    active = torch.ones(b, dtype=torch.bool, device=z.device)
    done = 0
    for it in range(iters):
        d = _direction(g, s, y, rho)
        gtd = (g * d).sum(-1)
        bad = gtd >= 0  # not a descent direction: forget the memory, go downhill
        d = torch.where(bad[:, None], -g / g.abs().amax(-1, keepdim=True).clamp_min(1e-12), d)
        rho = torch.where(bad[:, None], 0.0, rho)
        gtd = (g * d).sum(-1)
        t = torch.ones_like(f)
        pending = active.clone()
        f_new, g_new, accepted = f.clone(), g.clone(), torch.zeros_like(active)
        for _ in range(_MAX_TRIALS):
            idx = torch.nonzero(pending).flatten()
            if idx.numel() == 0:
                break
            f_try, g_try = _trial(objective, z[idx] + t[idx, None] * d[idx], idx)
            ti, fi, gi = t[idx], f[idx], gtd[idx]
            ok = f_try <= fi + 1e-4 * ti * gi  # Armijo
            f_new[idx[ok]], g_new[idx[ok]] = f_try[ok], g_try[ok]
            accepted[idx[ok]] = True
            pending[idx[ok]] = False
            # Backtrack to the minimum of the quadratic through f(0), f'(0) and f(t), kept
            # within [t / 10, t / 2] (Nocedal & Wright §3.5); t / 10 where f(t) is not finite.
            t_quad = -gi * ti.square() / (2 * (f_try - fi - gi * ti)).clamp_min(1e-30)
            t_quad = torch.where(t_quad.isfinite(), t_quad, 0.1 * ti)
            t[idx[~ok]] = torch.minimum(torch.maximum(t_quad, 0.1 * ti), 0.5 * ti)[~ok]
        step = t[:, None] * d
        # An item stops once it gains less than float precision: its objective fell by less
        # than 10 eps relative, or its search failed without memory (with memory, it forgets
        # the memory and tries steepest descent next).
        stalled = accepted & (f - f_new <= 10 * torch.finfo(f.dtype).eps * f)
        active = active & (accepted | (rho[:, -1] != 0)) & ~stalled
        step = torch.where(accepted[:, None], step, 0.0)
        z = z + step
        dy = g_new - g
        sy = (step * dy).sum(-1)
        keep = accepted & (sy > 1e-10 * step.norm(dim=-1) * dy.norm(dim=-1))
        roll = lambda m, new: torch.cat([m[:, 1:], new[:, None]], dim=1)  # noqa: E731  (newest last)
        s = torch.where(keep[:, None, None], roll(s, step), s)
        y = torch.where(keep[:, None, None], roll(y, dy), y)
        rho = torch.where(keep[:, None], roll(rho, 1.0 / sy.clamp_min(1e-30)), rho)
        rho = torch.where((active & ~accepted)[:, None], 0.0, rho)
        f, g = torch.where(accepted, f_new, f), torch.where(accepted[:, None], g_new, g)
        done = it + 1
        stop = not bool(active.any())
        report(first + done, "lbfgs" + (" (converged)" if stop else ""), f, force=stop)
        if stop:
            break
    return z, done


def _trial(objective: _Objective, z: torch.Tensor, items: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The objective at a line-search trial; +inf (backtrack) for an item whose body the layer
    refuses (a rest mesh past 10 m: the backend's limits allow larger bodies than the layer)."""
    try:
        return objective(z, items)
    except ValueError:
        if len(items) == 1:
            return z.new_full((1,), math.inf), torch.zeros_like(z)
        parts = [_trial(objective, z[i : i + 1], items[i : i + 1]) for i in range(len(items))]
        return torch.cat([f for f, _ in parts]), torch.cat([g for _, g in parts])


class _Reporter:
    """Calls ``progress`` about ten times per run with the RMS per-vertex distance."""

    def __init__(self, progress: Callable[[str], None] | None, total: int, batch: int) -> None:
        self.progress, self.total, self.batch = progress, total, batch
        self.every = max(1, total // 10)

    def due(self, i: int) -> bool:
        return self.progress is not None and (i % self.every == 0 or i == self.total)

    def __call__(self, i: int, stage: str, per_item: torch.Tensor, *, force: bool = False) -> None:
        """Report step i of the run; per_item (B,) mean squared distances, mm^2."""
        if self.progress is None or not (force or self.due(i)):
            return
        rms = per_item.sqrt()  # per_item in mm^2
        self.progress(
            f"  fit {i:4d}/{self.total} ({stage}): RMS per-vertex distance over {self.batch} items: "
            f"mean {float(rms.mean()):.3f} mm, max {float(rms.max()):.3f} mm"
        )
