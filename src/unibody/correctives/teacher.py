"""The teacher of the pose correctives: an elastic (as-rigid-as-possible) relaxation of the LBS
mesh around the joints.

Plain LBS shears and collapses the surface where the skinning weights blend two bones (the
inside of a bent elbow or knee, a raised shoulder, a twisted forearm). The teacher keeps LBS
where one bone dominates and relaxes the joint regions (:func:`teacher_region`) toward the rest
shape's local geometry: the spokes-and-rims as-rigid-as-possible energy (:class:`Arap`) with the
LBS result as start and as boundary. It is measured against LBS by :mod:`.metrics`
(``benchmarks/correctives.py``).
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["Arap", "teacher_region"]


def _memberships(rest: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Spokes-and-rims cells: (M, 2) edges, (M,) cell vertex, (M,) weights.

    Every half of a face's edge (opposite corner o) carries the cotangent weight ``cot(o) / 2``
    into three cells: those of its two ends (spokes) and that of o (a rim, which resists bending).
    """
    edges, cells, vals = [], [], []
    for k in range(3):
        i, j, o = faces[:, k], faces[:, (k + 1) % 3], faces[:, (k + 2) % 3]
        u, v = rest[i] - rest[o], rest[j] - rest[o]
        cot = (u * v).sum(1) / np.maximum(np.linalg.norm(np.cross(u, v), axis=1), 1e-12)
        for c in (i, j, o):
            edges.append(np.stack([i, j], 1))
            cells.append(c)
            vals.append(0.5 * cot)
    w = np.concatenate(vals)
    # Obtuse corners give negative weights, which break the energy's convexity; a floor keeps the
    # Laplacian positive definite at a negligible bias (the canonical mesh is near-Delaunay).
    return np.concatenate(edges), np.concatenate(cells), np.maximum(w, 0.05 * np.median(w))


class Arap:
    """As-rigid-as-possible relaxation of a region of a posed mesh.

    The energy ``sum_c sum_(a,b) in cell c  w_ab |(x_a - x_b) - R_c (x0_a - x0_b)|^2`` over the
    spokes-and-rims cells of Chao et al. 2010 ("A simple geometric model for elastic
    deformations": vertex c's cell holds its spokes and the rims of its faces, so bending costs
    energy too; Sorkine & Alexa 2007 use the spokes only) with cotangent weights of the rest mesh
    x0 and one rotation per cell, is minimised over the ``free`` vertices with the others held
    where they are, by alternating its two exact block minimisations: per-cell rotations (polar
    factor of the cell's edge covariance) and one sparse Cholesky solve of the Laplacian system.

    Args:
        rest: (V, 3) the identity's rest mesh (float64 numpy).
        faces: (F, 3) int faces.
        free: (V,) bool, the vertices to relax (the joint regions).
        iterations: local/global rounds.
    """

    def __init__(self, rest: np.ndarray, faces: np.ndarray, free: np.ndarray, *, iterations: int = 8) -> None:
        import scipy.sparse as sp
        from cholespy import CholeskySolverD, MatrixType

        v = len(rest)
        e, c, w = _memberships(rest, faces)
        touch = free[e].any(1)
        cells = np.unique(c[touch])
        keep = np.isin(c, cells)  # every membership of a cell the free vertices depend on
        self.edges, self.w = e[keep], w[keep]
        self.cells, self.cell = cells, np.searchsorted(cells, c[keep])
        i, j = self.edges.T
        lap = sp.coo_matrix((np.r_[-self.w, -self.w], (np.r_[i, j], np.r_[j, i])), shape=(v, v)).tocsr()
        lap = lap - sp.diags(np.asarray(lap.sum(1)).ravel())
        self.free, self.fixed = np.flatnonzero(free), np.flatnonzero(~free)
        a = lap[self.free][:, self.free].tocsr()
        self.l_fh = lap[self.free][:, self.fixed].tocsr()
        self._solver = CholeskySolverD(
            a.shape[0], a.indptr.astype(np.int32), a.indices.astype(np.int32), a.data, MatrixType.CSR
        )
        self.e0 = rest[i] - rest[j]  # (M, 3)
        self.iterations, self.num_vertices = iterations, v

    def __call__(self, posed: np.ndarray) -> np.ndarray:
        """Relax (B, V, 3) posed meshes (float64 numpy); the fixed vertices are returned unchanged."""
        x = torch.from_numpy(np.array(posed, dtype=np.float64, copy=True))
        b, v = x.shape[:2]
        i, j = (torch.from_numpy(t) for t in self.edges.T)
        cell = torch.from_numpy(self.cell)
        w, e0 = torch.from_numpy(self.w), torch.from_numpy(self.e0)
        nf, nc = len(self.free), len(self.cells)
        for _ in range(self.iterations):
            e = x[:, i] - x[:, j]  # (B, M, 3)
            cov = (w[:, None, None] * e0[:, :, None]) * e[:, :, None, :]
            s = x.new_zeros(b, nc, 3, 3).index_add_(1, cell, cov)
            u, _, vh = torch.linalg.svd(s)
            d = torch.sign(torch.linalg.det(vh.transpose(-1, -2) @ u.transpose(-1, -2)))
            vh = torch.cat([vh[..., :2, :], vh[..., 2:, :] * d[..., None, None]], -2)
            rot = vh.transpose(-1, -2) @ u.transpose(-1, -2)  # R_c maps rest edges to posed ones
            rhs_e = w[:, None] * (rot[:, cell] @ e0[..., None]).squeeze(-1)  # (B, M, 3)
            rhs = x.new_zeros(b, v, 3).index_add_(1, i, rhs_e).index_add_(1, j, -rhs_e)
            rhs_f = rhs[:, self.free].permute(1, 0, 2).reshape(nf, 3 * b).numpy()
            fixed = x[:, self.fixed].permute(1, 0, 2).reshape(len(self.fixed), 3 * b).numpy()
            rhs_f = np.ascontiguousarray(rhs_f - self.l_fh @ fixed)
            out = np.zeros_like(rhs_f)
            self._solver.solve(rhs_f, out)
            x[:, self.free] = torch.from_numpy(out).reshape(nf, b, 3).permute(1, 0, 2)
        return x.numpy()


STRESSED_JOINTS: tuple[str, ...] = tuple(
    s + j for s in ("Left", "Right") for j in ("Arm", "ForeArm", "Hand", "Leg", "Shin", "Foot")
)
"""Joints whose neighbourhood (with their parents) the teacher relaxes and the metrics measure."""


def _grow(mask: np.ndarray, edges: np.ndarray, rings: int) -> np.ndarray:
    for _ in range(rings):
        grow = mask.copy()
        grow[edges[mask[edges[:, 0]], 1]] = True
        grow[edges[mask[edges[:, 1]], 0]] = True
        mask = grow
    return mask


def teacher_region(
    weights: np.ndarray,
    parents: np.ndarray,
    joint_names: tuple[str, ...],
    faces: np.ndarray,
    *,
    rings: int = 2,
    whole_segments: bool = True,
) -> dict[str, np.ndarray]:
    """Per stressed joint: (V,) bool, the vertices skinned by it and its parent (>= 0.05), grown by ``rings``.

    With ``whole_segments``, the wrists and ankles also take the whole forearm or shin (the vertices it dominates): a
    twisted hand or foot turns the segment along its length, which a band at the joint cannot
    relax (LBS's candy wrapper).

    Args:
        weights: (V, J) dense skinning weights; parents: (J,) parent ids; faces: (F, 3).
    """
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    dominant = weights.argmax(1)
    out = {}
    for name in STRESSED_JOINTS:
        k = joint_names.index(name)
        band = (weights[:, k] >= 0.05) & (weights[:, parents[k]] >= 0.05)
        if whole_segments and name.endswith(("Hand", "Foot")):
            band |= dominant == parents[k]
        out[name] = _grow(band, e, rings)
    return out
