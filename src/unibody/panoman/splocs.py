"""Sparse localized components of scalar-per-element data on a graph (paper 004 §4.2, §4.4).

The decomposition behind PanoMan's body, face and hand components (one scalar per mesh edge;
two edges are neighbours when they share a face), after Neumann et al. 2013 with an adaptive
support radius per component (Liu et al. 2019). The steps (greedy initialisation, adaptive
support, alternating box-constrained W and ADMM C updates) are in ``docs/panoman.md``.

Notation:
    X (N, D): samples in rows; x̄ (D,) the mean; X_c = X − x̄.
    C (K, D): components, mostly zeros.  W (N, K): weights, held in the box |W_nk| ≤ 1.
    g_k(d): graph (Dijkstra) distance from element d to the centre of component k, metres.
    Λ_kd: locality weight of the support ramp (d_min, d_max) of component k: 0 for
        g_k(d) ≤ d_min, rising linearly to 1 at d_max; beyond d_max the component is zero.
    λ = sparsity · N · rms(X_c): the penalty scale.

Objective (minimised over W and C; E never increases, nothing is random):
    E(W, C) = ½‖X_c − W C‖²_F + λ Σ_kd Λ_kd |C_kd|,   subject to |W_nk| ≤ 1.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import dijkstra
from torch import Tensor

from .._checks import check_finite, check_like, check_shape, check_tensor

__all__ = [
    "DEFAULT_ADAPTIVE_SUPPORTS",
    "SplocsConfig",
    "SplocsResult",
    "element_graph",
    "project",
    "sparse_localized_components",
]

Progress = Callable[[str, int, int], None]
Adjacency = sp.spmatrix | sp.sparray | tuple[Sequence[int] | np.ndarray | Tensor, ...]

#: (d_min, d_max) ramps in metres, doubling from finger joints and facial features (5 cm) to
#: whole limbs (40 cm), in graph distance over the canonical mesh's edge midpoints.
DEFAULT_ADAPTIVE_SUPPORTS: tuple[tuple[float, float], ...] = ((0.02, 0.05), (0.04, 0.1), (0.08, 0.2), (0.16, 0.4))

_SUBSPACE, _SUBSPACE_STEPS = 6, 10  # block size and steps of the subspace iteration for modes
_WEIGHT_STEPS = 300


def _ramp(pair: object, name: str) -> tuple[float, float]:
    try:
        d_min, d_max = (float(v) for v in pair)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a (d_min, d_max) pair of numbers, got {pair!r}") from None
    if not (0.0 <= d_min < d_max < float("inf")):
        raise ValueError(f"{name}: expected 0 <= d_min < d_max < inf, got ({d_min}, {d_max})")
    return d_min, d_max


@dataclass(frozen=True, slots=True)
class SplocsConfig:
    """Options of :func:`sparse_localized_components`.

    Attributes:
        num_components: K ≥ 1.
        sparsity: penalty weight as a fraction of the data RMS (module docstring); 0 gives
            localized but unpenalised components. On the synthetic tests the default shrinks the
            supports 2–3× against 0, to near the true extents, for 0.15 % of explained variance.
        support: one (d_min, d_max) ramp in metres of graph distance for every component, or
            None to choose one per component from ``adaptive_supports``.
        adaptive_supports: candidate ramps (at least one), any order.
        adaptive_threshold: in (0, 1); relative amplitude below which the centre's mode counts
            as died out (step 2 of the module docstring).
        iterations: outer alternations of the W and C steps (≥ 0).
        admm_iterations: ADMM steps per C step (≥ 1).
        seed: kept for interface stability; the algorithm uses no randomness.
    """

    num_components: int
    sparsity: float = 0.25
    support: tuple[float, float] | None = None
    adaptive_supports: tuple[tuple[float, float], ...] = DEFAULT_ADAPTIVE_SUPPORTS
    adaptive_threshold: float = 0.1
    iterations: int = 10
    admm_iterations: int = 10
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("num_components", "iterations", "admm_iterations", "seed"):
            if isinstance(getattr(self, name), bool) or not isinstance(getattr(self, name), int):
                raise ValueError(f"{name}: expected an int, got {getattr(self, name)!r}")
        if self.num_components < 1:
            raise ValueError(f"num_components: expected >= 1, got {self.num_components}")
        if self.iterations < 0:
            raise ValueError(f"iterations: expected >= 0, got {self.iterations}")
        if self.admm_iterations < 1:
            raise ValueError(f"admm_iterations: expected >= 1, got {self.admm_iterations}")
        if not (0.0 <= float(self.sparsity) < float("inf")):
            raise ValueError(f"sparsity: expected a finite value >= 0, got {self.sparsity}")
        if not (0.0 < float(self.adaptive_threshold) < 1.0):
            raise ValueError(f"adaptive_threshold: expected a value in (0, 1), got {self.adaptive_threshold}")
        if self.support is not None:
            object.__setattr__(self, "support", _ramp(self.support, "support"))
        ramps = tuple(_ramp(r, "adaptive_supports") for r in self.adaptive_supports)
        if not ramps:
            raise ValueError("adaptive_supports: expected at least one (d_min, d_max) ramp, got none")
        object.__setattr__(self, "adaptive_supports", ramps)


@dataclass(frozen=True, slots=True)
class SplocsResult:
    """A sparse localized decomposition X ≈ mean + weights @ components.

    Attributes:
        mean: (D,) mean of the training samples.
        components: (K, D) components, zero outside each support.
        weights: (N, K) training weights, |weights| ≤ 1.
        centers: (K,) long, element id of each component's centre.
        supports: (K, 2) the (d_min, d_max) ramp of each component, metres of graph distance.
        objective: (iterations + 1,) float64, E(W, C) after the initialisation and after each
            alternation (non-increasing).
    """

    mean: Tensor
    components: Tensor
    weights: Tensor
    centers: Tensor
    supports: Tensor
    objective: Tensor

    def support_sizes(self) -> Tensor:
        """(K,) long, the number of non-zero elements of each component."""
        return (self.components != 0).sum(1)

    def reconstruct(self, weights: Tensor) -> Tensor:
        """(N, D) samples ``mean + weights @ components`` for (N, K) weights."""
        check_shape(weights, "N K", name="weights", sizes={"K": self.components.shape[0]})
        return self.mean + weights @ self.components


def element_graph(positions: Tensor | np.ndarray, pairs: Tensor | np.ndarray) -> sp.csr_matrix:
    """Build the symmetric (D, D) element graph weighted by Euclidean distance.

    Args:
        positions: (D, 3) element positions, metres (edge midpoints for mesh edges).
        pairs: (P, 2) neighbouring element ids (each pair once or twice).

    Returns:
        A scipy CSR matrix with both (i, j) and (j, i) set to ‖p_i − p_j‖.
    """
    pos = np.asarray(positions.detach().cpu() if isinstance(positions, Tensor) else positions, dtype=np.float64)
    ij = np.asarray(pairs.detach().cpu() if isinstance(pairs, Tensor) else pairs)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(f"positions: expected shape (D, 3), got {pos.shape}")
    if ij.ndim != 2 or ij.shape[1] != 2 or (ij.size and not np.issubdtype(ij.dtype, np.integer)):
        raise ValueError(f"pairs: expected integer shape (P, 2), got {ij.dtype} {ij.shape}")
    if ij.size and (ij.min() < 0 or ij.max() >= len(pos)):
        raise ValueError(f"pairs: ids must lie in [0, {len(pos)}), got [{ij.min()}, {ij.max()}]")
    ij = np.unique(np.sort(ij[ij[:, 0] != ij[:, 1]], axis=1), axis=0)
    # Coincident elements still get an edge: a zero weight would drop it from the sparse graph.
    w = np.maximum(np.linalg.norm(pos[ij[:, 0]] - pos[ij[:, 1]], axis=1), 1e-12)
    rows, cols = np.concatenate([ij[:, 0], ij[:, 1]]), np.concatenate([ij[:, 1], ij[:, 0]])
    return sp.csr_matrix((np.concatenate([w, w]), (rows, cols)), shape=(len(pos), len(pos)))


def _as_graph(adjacency: Adjacency, num_elements: int) -> sp.csr_matrix:
    """Validate ``adjacency`` (scipy sparse or (rows, cols, weights)) as a (D, D) CSR graph."""
    if isinstance(adjacency, tuple):
        if len(adjacency) != 3:
            raise ValueError(f"adjacency: expected (rows, cols, weights), got a tuple of {len(adjacency)}")
        rows, cols, w = (np.asarray(a.detach().cpu() if isinstance(a, Tensor) else a) for a in adjacency)
        if not (rows.shape == cols.shape == w.shape and rows.ndim == 1):
            raise ValueError(
                f"adjacency: rows, cols and weights must be 1-D of one length, got {rows.shape}, "
                f"{cols.shape}, {w.shape}"
            )
        n = num_elements
        if rows.size and (min(rows.min(), cols.min()) < 0 or max(rows.max(), cols.max()) >= n):
            raise ValueError(f"adjacency: element ids must lie in [0, {n})")
        adjacency = sp.coo_matrix((w.astype(np.float64), (rows, cols)), shape=(n, n))
    if not sp.issparse(adjacency):
        raise ValueError(
            f"adjacency: expected a scipy sparse matrix or (rows, cols, weights), got {type(adjacency).__name__}"
        )
    if adjacency.shape != (num_elements, num_elements):
        raise ValueError(f"adjacency: expected shape (D, D) with D={num_elements}, got {adjacency.shape}")
    g = sp.csr_matrix(adjacency, dtype=np.float64)
    if g.nnz and not (np.isfinite(g.data).all() and (g.data >= 0).all()):
        raise ValueError("adjacency: edge weights must be finite and >= 0")
    return g


def _leading_mode(rows: Tensor) -> Tensor:
    """Unit u (N,) maximising ‖rows @ u‖ for rows (m, N): the leading right singular vector."""
    m, n = rows.shape
    if min(m, n) <= _SUBSPACE:
        gram = rows.T @ rows
        u = torch.linalg.eigh(gram.double())[1][:, -1].to(rows.dtype)
    else:  # subspace iteration: converges as (σ_{q+1}/σ_1)^2 per step, two passes over rows each
        q, _ = torch.linalg.qr(rows[torch.linspace(0, m - 1, _SUBSPACE, dtype=torch.long)].T)
        for _ in range(_SUBSPACE_STEPS):
            q, _ = torch.linalg.qr(rows.T @ (rows @ q))
        y = rows @ q
        u = q @ torch.linalg.eigh((y.T @ y).double())[1][:, -1].to(rows.dtype)
    return u / u.norm().clamp_min(torch.finfo(u.dtype).tiny)


def _choose_ramp(residual: Tensor, idx: Tensor, counts: list[int], threshold: float):
    """Step 2 on distance-sorted element ids: the ramp index, the mode u (N,) and, per ring up to
    the chosen ramp, (element ids, residual rows, amplitudes). Rings beyond are never gathered."""
    rows = residual.index_select(0, idx[: counts[0]])
    u = _leading_mode(rows)
    amplitude = rows @ u
    limit = threshold * float(amplitude.abs().max())
    blocks = [(idx[: counts[0]], rows, amplitude)]
    for r in range(len(counts) - 1):
        ring_ids = idx[counts[r] : counts[r + 1]]
        rows = residual.index_select(0, ring_ids)
        amplitude = rows @ u
        if ring_ids.numel() == 0 or float(amplitude.abs().max()) <= limit:
            return r, u, blocks
        blocks.append((ring_ids, rows, amplitude))
    return len(counts) - 1, u, blocks


def _greedy_init(xt: Tensor, energy: Tensor, graph: sp.csr_matrix, cfg: SplocsConfig, progress: Progress | None):
    """Steps 1–2: greedy components on the residual. Returns Wᵀ, C, centres, ramps, Λ, mask."""
    num_elements, n = xt.shape
    k_total = cfg.num_components
    ramps = [cfg.support] if cfg.support is not None else sorted(cfg.adaptive_supports, key=lambda r: r[1])
    residual, energy = xt.clone(), energy.clone()
    wt = xt.new_zeros(k_total, n)
    comps = xt.new_zeros(k_total, num_elements)
    lam = xt.new_zeros(k_total, num_elements)
    mask = torch.zeros(k_total, num_elements, dtype=torch.bool, device=xt.device)
    centres, chosen = [], []
    for k in range(k_total):
        centre = int(torch.argmax(energy))
        dist = dijkstra(graph, directed=False, indices=centre, limit=ramps[-1][1])
        near = np.flatnonzero(dist <= ramps[-1][1])
        near = near[np.argsort(dist[near], kind="stable")]
        counts = [int(np.searchsorted(dist[near], r[1], side="right")) for r in ramps]
        choice, u, blocks = _choose_ramp(
            residual, torch.as_tensor(near, device=xt.device), counts, cfg.adaptive_threshold
        )
        d_min, d_max = ramps[choice]
        sel = torch.cat([b[0] for b in blocks])
        scale = u.abs().max()
        if scale > 0:  # an all-zero residual leaves an empty component
            wt[k] = u / scale  # max |w| = 1: the box of step 3a
            comps[k, sel] = torch.cat([b[2] for b in blocks]) * scale
            for ids, rows, coef in blocks:
                residual.index_copy_(0, ids, torch.addr(rows, coef, u, alpha=-1))
                # ‖r − (r·u)u‖² = ‖r‖² − (r·u)² for unit u: no second pass over the rows
                energy[ids] = (energy[ids] - coef.square()).clamp_min(0.0)
        ramp = torch.as_tensor(dist[near[: counts[choice]]], dtype=xt.dtype, device=xt.device)
        lam[k, sel] = ((ramp - d_min) / (d_max - d_min)).clamp(0.0, 1.0)
        mask[k, sel] = True
        centres.append(centre)
        chosen.append((d_min, d_max))
        if progress is not None:
            progress("init", k + 1, k_total)
    return wt, comps, centres, chosen, lam, mask


def _weights_energy(wt: Tensor, p: Tensor, g: Tensor) -> float:
    """½⟨WᵀW, G⟩ − ⟨W, P⟩ for Wᵀ (K, N), P = C X_cᵀ (K, N), G = CCᵀ, all float64."""
    return float(0.5 * (g * (wt @ wt.T)).sum() - (wt * p).sum())


def _ridge(g: Tensor) -> Tensor:
    """A numerical ridge for the Gram matrix g (K, K): 1e-12 of its largest diagonal entry
    (empty components have a zero row), or the identity when g is zero."""
    top = float(g.diagonal().max())
    return (1e-12 * top if top > 0 else 1.0) * torch.eye(g.shape[0], dtype=g.dtype, device=g.device)


def _column_energies(wt: Tensor, p: Tensor, g: Tensor) -> Tensor:
    """(N,) per-sample ½ wᵀGw − pᵀw: each sample's weights are an independent box QP."""
    return 0.5 * (wt * (g @ wt)).sum(0) - (wt * p).sum(0)


def _box_qp(start: Tensor, p: Tensor, g: Tensor) -> Tensor:
    """min over |w| ≤ 1 of ½ wᵀGw − pᵀw for every column, from a feasible ``start`` (K, M)."""
    # Accelerated projected gradient in the Jacobi metric diag(G): the metric is diagonal, so
    # the projection onto the box is still a clamp, and near-diagonal G (localized, hence
    # nearly orthogonal components) makes the scaled problem well conditioned.
    diag = g.diagonal()
    inv = torch.where(diag > 0, 1.0 / diag.clamp_min(torch.finfo(g.dtype).tiny), 0.0)
    root = inv.sqrt()
    step = inv / float(torch.linalg.eigvalsh(root[:, None] * g * root[None, :])[-1].clamp_min(1e-300))
    x, y, t = start, start, 1.0
    for it in range(_WEIGHT_STEPS):
        grad = g @ y - p
        x_new = (y - step[:, None] * grad).clamp(-1.0, 1.0)
        if float((grad * (x_new - x)).sum()) > 0:  # momentum points uphill: restart it
            t = 1.0
        t_new = 0.5 * (1.0 + (1.0 + 4.0 * t * t) ** 0.5)
        y = x_new + ((t - 1.0) / t_new) * (x_new - x)
        done = it % 10 == 9 and float((x_new - x).abs().max()) <= 1e-7
        x, t = x_new, t_new
        if done:
            break
    return x


def _update_weights(wt: Tensor, p: Tensor, g: Tensor) -> Tensor:
    """Step 3a: min over |W| ≤ 1 of ½‖X_c − WC‖², float64 Wᵀ (K, N) in and out."""
    factor, info = torch.linalg.cholesky_ex(g + _ridge(g))  # the box, not the ridge, bounds W
    out = wt.clone()
    hard = torch.ones(wt.shape[1], dtype=torch.bool, device=wt.device)
    start = wt
    if int(info) == 0:
        free = torch.cholesky_solve(p, factor)
        hard = (free.abs() > 1.0).any(0)  # a feasible unconstrained optimum is that sample's solution
        out = free
        if not bool(hard.any()):
            return out
        clipped, previous = free[:, hard].clamp(-1.0, 1.0), wt[:, hard]
        better = _column_energies(clipped, p[:, hard], g) < _column_energies(previous, p[:, hard], g)
        start = torch.where(better, clipped, previous)
    p_hard = p[:, hard]
    solved = _box_qp(start, p_hard, g)
    keep = _column_energies(solved, p_hard, g) <= _column_energies(start, p_hard, g)
    out[:, hard] = torch.where(keep, solved, start)
    return out


def _components_energy(c: Tensor, b: Tensor, wtw: Tensor, pen: Tensor) -> float:
    """½⟨WᵀW, CCᵀ⟩ − ⟨B, C⟩ + Σ λΛ|C| for B = WᵀX_c (K, D)."""
    f64 = torch.float64
    quadratic = 0.5 * (wtw * (c @ c.T).to(f64)).sum()
    return float(quadratic - (b * c).sum(dtype=f64) + (pen * c.abs()).sum(dtype=f64))


def _update_components(
    c: Tensor, dual: Tensor, b: Tensor, wtw: Tensor, pen: Tensor, mask: Tensor, iterations: int
) -> tuple[Tensor, Tensor]:
    """Step 3b: ADMM on min_C ½‖X_c − WC‖² + Σ λΛ|C|; ``dual`` is the unscaled multiplier."""
    k_total = wtw.shape[0]
    rho = float(wtw.diagonal().mean())
    if rho <= 0:
        return c, dual  # all weights zero: nothing to fit
    system = torch.linalg.inv(wtw + rho * torch.eye(k_total, dtype=wtw.dtype, device=wtw.device)).to(c.dtype)
    # Soft threshold as v − clamp(v, −t, t); t = inf outside the support gives exact zeros there.
    upper = torch.where(mask, pen / rho, torch.inf)
    lower = -upper
    z, u = c, dual / rho
    for _ in range(iterations):
        x = system @ torch.add(b, z - u, alpha=rho)
        v = x + u
        z = v - torch.minimum(torch.maximum(v, lower), upper)
        u = v - z
    if _components_energy(z, b, wtw, pen) <= _components_energy(c, b, wtw, pen):
        return z, u * rho
    return c, u * rho


def _check_inputs(x: Tensor, config: SplocsConfig) -> None:
    check_tensor(x, "X")
    check_shape(x, "N D", name="X")
    if not x.is_floating_point():
        raise ValueError(f"X: expected a floating-point tensor, got {x.dtype}")
    if x.shape[0] < 2 or x.shape[1] < 1:
        raise ValueError(f"X: expected at least 2 samples and 1 element, got shape {tuple(x.shape)}")
    check_finite(x, "X")
    if not isinstance(config, SplocsConfig):
        raise TypeError(f"config: expected a SplocsConfig, got {type(config).__name__}")


def sparse_localized_components(
    X: Tensor, adjacency: Adjacency, config: SplocsConfig, *, progress: Progress | None = None
) -> SplocsResult:
    """Decompose X into sparse localized components (module docstring for the algorithm).

    Args:
        X: (N, D) samples, N ≥ 2, one scalar per element (an RL or RA vector per row).
        adjacency: the element graph, a scipy sparse (D, D) matrix or a (rows, cols, weights)
            triple; weights are graph-edge lengths in metres (see :func:`element_graph`).
        config: the options.
        progress: called as ``progress(stage, i, n)`` with stage "init" (component i of K)
            and "iterate" (alternation i of ``config.iterations``).

    Returns:
        A :class:`SplocsResult` in the dtype and on the device of X.

    Raises:
        ValueError: X not (N, D) floating point with N ≥ 2 or not finite; adjacency not
            (D, D) with finite non-negative weights.
        TypeError: X not a tensor or config not a SplocsConfig.
    """
    _check_inputs(X, config)
    graph = _as_graph(adjacency, X.shape[1])
    mean = X.mean(0)
    xt = X.new_empty(X.shape[1], X.shape[0]).copy_(X.T)  # (D, N), our own copy: rows contiguous for gathers
    xt -= mean[:, None]
    energy0 = xt.square().sum(1)  # (D,) per-element energy: the initial residual
    half_xx = 0.5 * float(energy0.sum(dtype=torch.float64))
    lam_scale = config.sparsity * X.shape[0] * (2.0 * half_xx / xt.numel()) ** 0.5  # λ = sparsity·N·rms
    wt, comps, centres, ramps, lam, mask = _greedy_init(xt, energy0, graph, config, progress)
    pen = lam * lam_scale
    del lam

    def energy(wt64: Tensor, c: Tensor, p: Tensor, g: Tensor) -> float:  # E(W, C) given P = C X_cᵀ, G = CCᵀ
        return half_xx + _weights_energy(wt64, p, g) + float((pen * c.abs()).sum(dtype=torch.float64))

    wt = wt.double()
    p, g = (comps @ xt).double(), (comps @ comps.T).double()
    history = [energy(wt, comps, p, g)]
    dual = torch.zeros_like(comps)
    for it in range(config.iterations):
        wt = _update_weights(wt, p, g)
        b = wt.to(xt.dtype) @ xt.T  # (K, D) = WᵀX_c
        comps, dual = _update_components(comps, dual, b, wt @ wt.T, pen, mask, config.admm_iterations)
        p, g = (comps @ xt).double(), (comps @ comps.T).double()
        history.append(energy(wt, comps, p, g))
        if progress is not None:
            progress("iterate", it + 1, config.iterations)
    wt = _update_weights(wt, p, g)
    history[-1] = energy(wt, comps, p, g)
    centre_ids = torch.as_tensor(centres, dtype=torch.long, device=X.device)
    sign = torch.where(comps[torch.arange(len(centres), device=X.device), centre_ids] < 0, -1.0, 1.0).to(X.dtype)
    return SplocsResult(
        mean=mean,
        components=comps * sign[:, None],
        weights=(wt.to(X.dtype) * sign[:, None]).T.contiguous(),
        centers=centre_ids,
        supports=torch.as_tensor(ramps, dtype=X.dtype, device=X.device),
        objective=torch.as_tensor(history, dtype=torch.float64),
    )


def project(result: SplocsResult, X: Tensor) -> Tensor:
    """Least-squares weights of new samples on the components (no box constraint).

    Args:
        result: a decomposition.
        X: (N, D) samples, same dtype and device as ``result``.

    Returns:
        (N, K) weights minimising ‖X − mean − weights @ components‖².

    Raises:
        ValueError: X not (N, D) or not finite.
        TypeError: X not a tensor, or of another dtype or device than ``result``.
    """
    check_tensor(X, "X")
    check_shape(X, "N D", name="X", sizes={"D": result.components.shape[1]})
    check_like(X, result.components, "X", owner="the decomposition")
    check_finite(X, "X")
    c = result.components
    p = (c @ (X - result.mean).T).double()
    g = (c @ c.T).double()
    return torch.linalg.solve(g + _ridge(g), p).T.to(X.dtype).contiguous()
