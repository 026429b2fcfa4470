"""Discrete-shell fitting in the PanoMan subspace (paper 004 §5, eqs. 6–11).

The unknowns are the vertices V of one mesh and the motion weights beta = (beta_L, beta_A).
The energy is

    E = E_S + E_B + E_C
    E_S = sum_e (l_e(V) / l0_e - 1 - rl*_e)^2                       stretching, eq. 7
    E_B = mu sum_e w_e^2 (a_e(V) - a0_e - ra*_e)^2,  w_e ~ l0_e / S0_e  bending, eq. 8
    E_C = lambda / h^2 (sum_k |v_k - v^_k|^2 + sum_j |(W V)_j - J^_j|^2)   handles, eq. 11
          + gamma sum_k (beta_k - beta^_k)^2                            parameters, eq. 10

with ``rl* = mean_L + M_L beta_L (+ R_L)`` and ``ra* = mean_A + M_A beta_A (+ R_A)`` the
subspace targets, ``l0, a0, S0`` the rest shape's edge lengths, dihedral angles and the area
of the two triangles at each edge, ``h`` the mean rest edge length (so handle residuals are
measured in edge lengths), and ``W`` a sparse linear joint regressor. The bending weights are
the paper's ``l0 / S0`` divided by their median, so both shell terms are dimensionless and
``mu`` weighs them against each other.

The solver is block-coordinate descent (§5.3): beta given V is a small linear least squares
per decomposition (exact); V given beta is a Gauss–Newton step on all vertices with a
backtracking line search. The Gauss–Newton matrix J^T J + C^T C is factorised once and
reused for ``refactor_every`` steps (a chord method): the factorisation dominates a step, the
reuse makes a step a pair of triangular solves.
Everything here is float64 numpy/scipy on one mesh.
"""

from __future__ import annotations

import numbers
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import torch

from ._cholesky import cholesky
from .rla import dihedral_angles, edge_lengths, shell_jacobian

__all__ = ["Handles", "ShellConfig", "ShellResult", "ShellSubspace", "fit_shell"]


@dataclass(frozen=True)
class ShellConfig:
    """Weights and schedule of :func:`fit_shell`.

    Attributes:
        bending: mu, weight of E_B against E_S.
        handles: lambda, weight of the vertex and joint handles (residuals in mean edge lengths).
        ridge: weight of |beta|^2 (keeps the weights of unobserved components small).
        parameters: gamma, weight of the parameter targets beta^.
        iterations: outer iterations (one V step and one beta step each).
        refactor_every: factorise J^T J again every this many iterations (1 = plain Gauss–Newton).
        damping: Levenberg damping added to the diagonal, relative to its median (the mean is
            dominated by the few tiny edges at the mouth and eye corners).
        tolerance: stop when the energy decreases by less than this fraction in one iteration.
    """

    bending: float = 1.0
    handles: float = 100.0
    ridge: float = 1e-4
    parameters: float = 1.0
    iterations: int = 12
    refactor_every: int = 4
    damping: float = 1e-6
    tolerance: float = 1e-5

    def __post_init__(self) -> None:
        for name in ("bending", "handles", "ridge", "parameters", "damping", "tolerance"):
            x = getattr(self, name)
            if isinstance(x, bool) or not isinstance(x, numbers.Real) or not (0 <= x < float("inf")):
                raise ValueError(f"config.{name}: expected a finite number >= 0, got {x!r}")
        for name in ("iterations", "refactor_every"):
            x = getattr(self, name)
            if isinstance(x, bool) or not isinstance(x, numbers.Integral) or x < 1:
                raise ValueError(f"config.{name}: expected an int >= 1, got {x!r}")


@dataclass(frozen=True)
class Handles:
    """Positional constraints on one mesh (all optional).

    Attributes:
        vertex_ids: (H,) vertex indices; vertex_targets (H, 3) m.
        regressor: (R, V) scipy sparse rows mapping vertices to points (e.g. joints); regressor_targets (R, 3) m.
    """

    vertex_ids: np.ndarray | None = None
    vertex_targets: np.ndarray | None = None
    regressor: sp.spmatrix | None = None
    regressor_targets: np.ndarray | None = None

    def __post_init__(self) -> None:
        if (self.vertex_ids is None) != (self.vertex_targets is None):
            raise ValueError("handles: give vertex_ids and vertex_targets together")
        if (self.regressor is None) != (self.regressor_targets is None):
            raise ValueError("handles: give regressor and regressor_targets together")
        if self.vertex_ids is not None:
            ids = _array(self.vertex_ids)
            if ids.ndim != 1 or (ids.size and ids.dtype.kind not in "iu"):
                raise ValueError(f"handles.vertex_ids: expected (H,) integer vertex ids, got {ids.shape} {ids.dtype}")
            object.__setattr__(self, "vertex_ids", ids.astype(np.int64))
            object.__setattr__(self, "vertex_targets", _points(self.vertex_targets, len(ids), "vertex_targets"))
        if self.regressor is not None:
            shape = getattr(self.regressor, "shape", ())
            if len(shape) != 2:
                raise ValueError(f"handles.regressor: expected an (R, V) matrix, got shape {shape}")
            object.__setattr__(
                self, "regressor_targets", _points(self.regressor_targets, shape[0], "regressor_targets")
            )

    def matrix(self, num_vertices: int) -> tuple[sp.csr_matrix, np.ndarray]:
        """(C (H+R, V), targets (H+R, 3)): the handles as rows of one linear map of the vertices.

        Raises:
            ValueError: a vertex id outside ``[0, num_vertices)`` or a regressor of another width.
        """
        ids = self.vertex_ids
        if ids is not None and len(ids) and not (0 <= ids.min() and ids.max() < num_vertices):
            bad = ids[(ids < 0) | (ids >= num_vertices)][0]
            raise ValueError(f"handles.vertex_ids: expected vertex ids in [0, {num_vertices}), got {bad}")
        if self.regressor is not None and self.regressor.shape[1] != num_vertices:
            raise ValueError(f"handles.regressor: expected {num_vertices} columns, got {self.regressor.shape[1]}")
        rows, targets = [], []
        if self.vertex_ids is not None and len(self.vertex_ids):
            ids = np.asarray(self.vertex_ids, dtype=np.int64)
            rows.append(sp.csr_matrix((np.ones(len(ids)), (np.arange(len(ids)), ids)), shape=(len(ids), num_vertices)))
            targets.append(np.asarray(self.vertex_targets, dtype=np.float64).reshape(-1, 3))
        if self.regressor is not None:
            rows.append(sp.csr_matrix(self.regressor, dtype=np.float64))
            targets.append(np.asarray(self.regressor_targets, dtype=np.float64).reshape(-1, 3))
        if not rows:
            return sp.csr_matrix((0, num_vertices)), np.zeros((0, 3))
        return sp.vstack(rows).tocsr(), np.concatenate(targets)


def _array(x: object) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def _points(x: object, count: int, name: str) -> np.ndarray:
    """``x`` as a finite (count, 3) float64 array, else ValueError naming ``handles.<name>``."""
    a = _array(x)
    if a.shape != (count, 3) or a.dtype.kind not in "fiu":
        raise ValueError(f"handles.{name}: expected ({count}, 3) numbers, got {a.shape} {a.dtype}")
    a = a.astype(np.float64)
    if not np.isfinite(a).all():
        raise ValueError(f"handles.{name}: expected finite values, got {int((~np.isfinite(a)).sum())} NaN/inf")
    return a


@dataclass(frozen=True)
class ShellSubspace:
    """The PanoMan subspace at one identity: rest quantities and linear components.

    Attributes:
        rest_lengths, rest_angles, rest_areas: (E,) of the rest shape B_S(alpha).
        mean_l, mean_a: (E,) summed subset means of the RL / RA vectors.
        basis_l, basis_a: (E, K_L), (E, K_A) scipy sparse components (columns).
        residual: optional callable beta (K_L + K_A,) -> (R_L (E,), R_A (E,)), the correction MLP.
        beta_targets: optional (mask (K,), values (K,)) parameter constraints (eq. 10).
    """

    rest_lengths: np.ndarray
    rest_angles: np.ndarray
    rest_areas: np.ndarray
    mean_l: np.ndarray
    mean_a: np.ndarray
    basis_l: sp.spmatrix
    basis_a: sp.spmatrix
    residual: object | None = None
    beta_targets: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def num_l(self) -> int:
        return self.basis_l.shape[1]

    def targets(self, beta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rl*, ra*) of weights beta."""
        rl = self.mean_l + self.basis_l @ beta[: self.num_l]
        ra = self.mean_a + self.basis_a @ beta[self.num_l :]
        if self.residual is not None:
            dl, da = self.residual(beta)
            rl, ra = rl + dl, ra + da
        return rl, ra


@dataclass(frozen=True)
class ShellResult:
    """Outcome of :func:`fit_shell`.

    Attributes:
        vertices: (V, 3) m.
        beta: (K_L + K_A,) motion weights.
        energy: per-iteration total energy (first entry: at the initial guess).
        handle_error: (H+R,) m, distance of each handle after the fit.
        seconds: wall time.
    """

    vertices: np.ndarray
    beta: np.ndarray
    energy: list = field(default_factory=list)
    handle_error: np.ndarray | None = None
    seconds: float = 0.0


def _wrap(x: np.ndarray) -> np.ndarray:
    return (x + np.pi) % (2 * np.pi) - np.pi


class _Problem:
    """Residuals and Jacobians of E at fixed targets; numpy float64, one mesh."""

    def __init__(self, topo, sub: ShellSubspace, handles: Handles, config: ShellConfig, num_vertices: int):
        self.topo, self.sub, self.cfg, self.n = topo, sub, config, num_vertices
        ratio = sub.rest_lengths / sub.rest_areas
        self.w_bend = np.sqrt(config.bending) * ratio / np.median(ratio)
        self.h = float(sub.rest_lengths.mean())
        self.c_mat, self.c_targets = handles.matrix(num_vertices)
        self.c_scale = np.sqrt(config.handles) / self.h
        self.c3 = sp.kron(self.c_mat, sp.eye(3), format="csr") * self.c_scale
        # The beta step's normal matrices depend only on the subspace and the weights: factorise
        # them once per fit (one (K, K) Cholesky per half), not once per iteration.
        self.beta_systems = []
        for basis, w, sl in (
            (sub.basis_l, None, slice(0, sub.num_l)),
            (sub.basis_a, self.w_bend, slice(sub.num_l, sub.num_l + sub.basis_a.shape[1])),
        ):
            m = sp.csc_matrix(basis) if w is None else sp.diags(w) @ basis
            lhs = (m.T @ m).toarray() + config.ridge * np.eye(m.shape[1])
            prior = None
            if sub.beta_targets is not None:
                mask, values = sub.beta_targets
                prior = (mask[sl].astype(np.float64) * config.parameters, values[sl])
                lhs[np.diag_indices_from(lhs)] += prior[0]
            self.beta_systems.append((m, w, prior, scipy.linalg.cho_factor(lhs)))
        self._measured: tuple[np.ndarray, tuple[np.ndarray, np.ndarray]] | None = None

    def measures(self, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Edge lengths and bending angles of ``v``; the last mesh's are kept (each step asks twice)."""
        if self._measured is not None and np.array_equal(self._measured[0], v):
            return self._measured[1]
        t = torch.from_numpy(v)[None]
        out = edge_lengths(t, self.topo)[0].numpy(), dihedral_angles(t, self.topo)[0].numpy()
        self._measured = (v.copy(), out)
        return out

    def residuals(self, v: np.ndarray, rl_t: np.ndarray, ra_t: np.ndarray) -> np.ndarray:
        lengths, angles = self.measures(v)
        s = self.sub
        r_s = lengths / s.rest_lengths - 1.0 - rl_t
        r_b = self.w_bend * _wrap(angles - s.rest_angles - ra_t)
        r_c = self.c_scale * (self.c_mat @ v - self.c_targets).ravel()
        return np.concatenate([r_s, r_b, r_c])

    def jacobian(self, v: np.ndarray) -> sp.csr_matrix:
        rows, cols, vals = (np.asarray(x) for x in shell_jacobian(torch.from_numpy(v), self.topo))
        e = len(self.sub.rest_lengths)
        scale = np.concatenate([1.0 / self.sub.rest_lengths, self.w_bend])
        j = sp.csr_matrix((vals * scale[rows], (rows, cols)), shape=(2 * e, 3 * self.n))
        return sp.vstack([j, self.c3]).tocsr()


def _beta_step(prob: _Problem, v: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """Exact minimiser of E over beta at fixed V (the correction MLP held at the current beta)."""
    s = prob.sub
    lengths, angles = prob.measures(v)
    dl = da = 0.0
    if s.residual is not None:
        dl, da = s.residual(beta)
    targets = (lengths / s.rest_lengths - 1.0 - s.mean_l - dl, _wrap(angles - s.rest_angles) - s.mean_a - da)
    out = []
    for (m, w, prior, factor), y in zip(prob.beta_systems, targets, strict=True):
        rhs = m.T @ (y if w is None else w * y)
        if prior is not None:
            rhs = rhs + prior[0] * prior[1]
        out.append(scipy.linalg.cho_solve(factor, rhs))
    return np.concatenate(out)


def _line_search(prob: _Problem, v, step, r, rl_t, ra_t):
    """Backtracking on the V step at fixed targets: the accepted move (V, 3), or None if none descends."""
    e_old, t = float(r @ r), 1.0
    for _ in range(8):
        r_try = prob.residuals(v + t * step, rl_t, ra_t)
        if float(r_try @ r_try) < e_old:
            return t * step
        t *= 0.5
    return None


def _energy(r: np.ndarray, beta: np.ndarray, prob: _Problem) -> float:
    e = float(r @ r) + prob.cfg.ridge * float(beta @ beta)
    if prob.sub.beta_targets is not None:
        mask, values = prob.sub.beta_targets
        e += prob.cfg.parameters * float((mask * (beta - values) ** 2).sum())
    return e


def fit_shell(
    topo,
    subspace: ShellSubspace,
    init_vertices: np.ndarray,
    handles: Handles,
    *,
    config: ShellConfig = ShellConfig(),
    init_beta: np.ndarray | None = None,
) -> ShellResult:
    """Fit one mesh to handles in the PanoMan subspace (block-coordinate Gauss–Newton).

    Args:
        topo: the mesh's :class:`~unibody.panoman.mesh.EdgeTopology`.
        subspace: rest quantities and components at the identity (:class:`ShellSubspace`).
        init_vertices: (V, 3) m, the initial mesh (e.g. a ``BodyLayer`` fit or ``g`` of the subspace).
        handles: vertex and regressor constraints.
        config: weights and schedule.
        init_beta: (K,) initial weights; None computes the best ones for ``init_vertices``.

    Returns:
        ShellResult.
    """
    t0 = time.perf_counter()
    v = np.array(init_vertices, dtype=np.float64)
    n = topo.vertex_count
    if v.shape != (n, 3):
        raise ValueError(f"init_vertices: expected shape ({n}, 3), the mesh's vertices, got {v.shape}")
    if not np.isfinite(v).all():
        raise ValueError("init_vertices: expected finite values")
    prob = _Problem(topo, subspace, handles, config, n)
    k = subspace.basis_l.shape[1] + subspace.basis_a.shape[1]
    beta = np.zeros(k) if init_beta is None else np.asarray(init_beta, dtype=np.float64)
    if init_beta is None:
        beta = _beta_step(prob, v, beta)
    rl_t, ra_t = subspace.targets(beta)
    r = prob.residuals(v, rl_t, ra_t)
    energy = [_energy(r, beta, prob)]
    solve = None
    for it in range(config.iterations):
        jac = prob.jacobian(v)
        if solve is None or it % max(config.refactor_every, 1) == 0:
            h = (jac.T @ jac).tocsc()
            h = h + sp.diags(np.full(3 * n, config.damping * np.median(h.diagonal())), format="csc")
            solve = cholesky(h)
        move = _line_search(prob, v, -solve(jac.T @ r).reshape(-1, 3), r, rl_t, ra_t)
        if move is None:
            break  # no descent along the (possibly stale) Gauss-Newton step: stop here
        v = v + move
        beta = _beta_step(prob, v, beta)
        rl_t, ra_t = subspace.targets(beta)
        r = prob.residuals(v, rl_t, ra_t)
        energy.append(_energy(r, beta, prob))
        if energy[-2] - energy[-1] < config.tolerance * energy[-2]:
            break
    err = np.linalg.norm(prob.c_mat @ v - prob.c_targets, axis=1) if prob.c_mat.shape[0] else None
    return ShellResult(v, beta, energy, err, time.perf_counter() - t0)
