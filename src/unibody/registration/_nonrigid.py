"""Stage 3: non-rigid ICP of the aligned template onto the source surface.

In the spirit of Amberg et al. 2007 (optimal step non-rigid ICP) with an as-rigid-as-possible
regulariser. The unknowns are the template's vertex positions ``X (V, 3)``; each iteration
fixes correspondences and solves one sparse linear least-squares problem:

    E(X) = sum_i a_i w_i [ (m_i . (x_i - q_i))^2 + beta |x_i - q_i|^2 ]            template -> source
         + sum_s a_s w_s [ (m_s . (B_s X - y_s))^2 + beta |B_s X - y_s|^2 ]       source -> template
         + alpha sum_(i,j) c_ij |(x_i - x_j) - R_ij (x0_i - x0_j)|^2             ARAP on the edges

``q_i`` is the exact closest source point of template vertex ``i`` and ``m_i`` the normal of
its source triangle; ``y_s`` a source surface sample, ``B_s X`` its exact closest point on the
current template (barycentric in the template triangle) and ``m_s`` its source normal.
Pairs farther than a threshold or with normals more than 60 degrees apart get ``w = 0``;
template vertices without a counterpart (inner mouth and eyes) never take part in the
data terms and follow the regulariser. ``a`` are surface areas, so the energy approximates
surface integrals and ``alpha = l^2`` sets a smoothing length ``l`` independent of the mesh
density. ``R_ij = (R_i + R_j) / 2`` with ``R_i`` the best rotation of vertex ``i``'s edge
fan (ARAP local step, recomputed after every solve). The stiffness ``l`` decreases
geometrically. After each solve, triangles that flipped (normal against the template's) or
collapsed below ``min_area_ratio`` of their template area mark their vertices and one ring
around them as unreliable: those vertices leave the data terms for good (the regulariser
carries them, which unfolds the region) and the iteration is solved again; if bad triangles
remain after ``retries`` solves the iteration is dropped, so the result never holds one.
The normal equations ``(alpha L + D + B^T M B) X = rhs`` are solved by conjugate
gradients with a 3x3 block-Jacobi preconditioner, warm-started.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..geometry.mesh import face_normals, unique_edges, vertex_areas, vertex_normals
from ..geometry.procrustes import polar_svd
from ._closest import SurfaceIndex
from ._project import bad_triangles

__all__ = ["IcpSettings", "nonrigid_icp"]


@dataclass(frozen=True, slots=True)
class IcpSettings:
    """Non-rigid ICP schedule and weights (lengths in metres)."""

    iterations: int = 24
    stiffness_start: float = 0.03
    stiffness_end: float = 0.002
    beta: float = 0.1
    max_distance: float = 0.03
    min_cos: float = 0.5
    arap: bool = True
    cg_iterations: int = 200
    cg_tolerance: float = 1e-5
    min_area_ratio: float = 0.02
    retries: int = 4
    cot_clamp: tuple[float, float] = (0.05, 50.0)


def _coo(indices: torch.Tensor, values: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    """A coalesced sparse COO matrix (indices are built in range here: no invariant check)."""
    return torch.sparse_coo_tensor(indices, values, shape, check_invariants=False).coalesce()


class _System:
    """Normal-equation operator of one ICP iteration."""

    def __init__(self, lap: torch.Tensor, degree: torch.Tensor, alpha: float, diag: torch.Tensor,
                 b_rows: torch.Tensor | None, b_mats: torch.Tensor | None):  # fmt: skip
        self.lap, self.alpha, self.diag = lap, alpha, diag
        self.b_rows, self.b_mats = b_rows, b_mats  # B (S, V) sparse; M (S, 3, 3) weighted
        pre = diag + alpha * degree[:, None, None] * torch.eye(3, dtype=diag.dtype)
        if b_rows is not None:
            sq = _coo(b_rows.indices(), b_rows.values().square(), tuple(b_rows.shape))
            pre = pre + (sq.t() @ b_mats.reshape(-1, 9)).view(-1, 3, 3)
        self.pre = torch.linalg.inv(pre)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        y = self.alpha * (self.lap @ x) + (self.diag @ x[..., None]).squeeze(-1)
        if self.b_rows is not None:
            bx = self.b_rows @ x
            y = y + self.b_rows.t() @ (self.b_mats @ bx[..., None]).squeeze(-1)
        return y

    def precondition(self, r: torch.Tensor) -> torch.Tensor:
        return (self.pre @ r[..., None]).squeeze(-1)


def _cg(op: _System, rhs: torch.Tensor, x: torch.Tensor, iters: int, tol: float) -> torch.Tensor:
    """Preconditioned conjugate gradients on (V, 3) unknowns."""
    r = rhs - op(x)
    z = op.precondition(r)
    p = z
    rz = (r * z).sum()
    stop = tol * rhs.norm()
    for _ in range(iters):
        if r.norm() <= stop:
            break
        ap = op(p)
        step = rz / (p * ap).sum()
        x = x + step * p
        r = r - step * ap
        z = op.precondition(r)
        rz_new = (r * z).sum()
        p = z + (rz_new / rz) * p
        rz = rz_new
    return x


def _edge_weights(x0: torch.Tensor, faces: torch.Tensor, edges: torch.Tensor, clamp: tuple[float, float]):
    """Cotangent weights ``(cot a + cot b) / 2`` of the edges on the rest shape, clamped to ``clamp``.

    Unlike uniform weights they are large on short edges opposite small angles, so the
    regulariser resists the displacement gradients that fold the canonical mesh's tiny and
    thin triangles (fingers, toes, ears); the lower clamp keeps obtuse configurations positive.
    """
    n = x0.shape[0]
    tri = x0[faces]
    cots = []
    for k in range(3):  # angle at corner k, opposite edge (k+1, k+2)
        a = tri[:, (k + 1) % 3] - tri[:, k]
        b = tri[:, (k + 2) % 3] - tri[:, k]
        cross = torch.linalg.cross(a, b, dim=-1).norm(dim=-1).clamp_min(torch.finfo(x0.dtype).tiny)
        cots.append((a * b).sum(-1) / cross)
    opp = torch.cat([faces[:, [1, 2]], faces[:, [2, 0]], faces[:, [0, 1]]])
    opp = torch.sort(opp, dim=1).values
    key = opp[:, 0] * n + opp[:, 1]
    ekey = edges[:, 0] * n + edges[:, 1]
    pos = torch.searchsorted(ekey, key)
    w = torch.zeros(edges.shape[0], dtype=x0.dtype).index_add_(0, pos, 0.5 * torch.cat(cots))
    return w.clamp(*clamp)


def _laplacian(edges: torch.Tensor, weight: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Weighted graph Laplacian (V, V) sparse CSR and the weighted vertex degrees."""
    i, j = edges.unbind(1)
    deg = torch.zeros(n, dtype=weight.dtype).index_add_(0, i, weight).index_add_(0, j, weight)
    rows = torch.cat([i, j, torch.arange(n)])
    cols = torch.cat([j, i, torch.arange(n)])
    vals = torch.cat([-weight, -weight, deg])
    lap = _coo(torch.stack([rows, cols]), vals, (n, n)).to_sparse_csr()
    return lap, deg


def _arap_rotations(x: torch.Tensor, x0: torch.Tensor, edges: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """(V, 3, 3) rotation per vertex best mapping its rest edge fan onto the current one."""
    i, j = edges.unbind(1)
    e, e0 = x[i] - x[j], x0[i] - x0[j]
    outer = (weight[:, None, None] * e[:, :, None] * e0[:, None, :]).reshape(-1, 9)
    h = torch.zeros(x.shape[0], 9, dtype=x.dtype).index_add_(0, i, outer).index_add_(0, j, outer)
    return polar_svd(h.view(-1, 3, 3))


def _reg_rhs(x0: torch.Tensor, edges: torch.Tensor, weight: torch.Tensor, rot: torch.Tensor | None) -> torch.Tensor:
    """sum_j w_ij R_ij (x0_i - x0_j) per vertex (the regulariser's right-hand side without alpha)."""
    i, j = edges.unbind(1)
    e0 = weight[:, None] * (x0[i] - x0[j])
    if rot is not None:
        e0 = (0.5 * (rot[i] + rot[j]) @ e0[..., None]).squeeze(-1)
    return torch.zeros_like(x0).index_add_(0, i, e0).index_add_(0, j, -e0)


def _point_plane(m: torch.Tensor, w: torch.Tensor, beta: float) -> torch.Tensor:
    """(N, 3, 3) w (m m^T + beta I)."""
    eye = torch.eye(3, dtype=m.dtype)
    return w[:, None, None] * (m[:, :, None] * m[:, None, :] + beta * eye)


def _reverse_terms(x, faces, face_ok, src_pts, src_nrm, src_area, vert_area, settings, index):
    """Source samples -> closest template points: sparse B (S, V) and weighted 3x3 blocks."""
    index.refit(x)
    f, q, d = index.query(src_pts)
    tri = x[faces[f]]
    nrm = face_normals(x, faces)[f]
    ok = face_ok[f] & (d < settings.max_distance) & ((nrm * src_nrm).sum(-1) > settings.min_cos)
    # barycentric coordinates of q in its triangle (q lies on it)
    a, b, c = tri.unbind(1)
    v0, v1, v2 = b - a, c - a, q - a
    d00, d01, d11 = (v0 * v0).sum(-1), (v0 * v1).sum(-1), (v1 * v1).sum(-1)
    d20, d21 = (v2 * v0).sum(-1), (v2 * v1).sum(-1)
    den = (d00 * d11 - d01 * d01).clamp_min(1e-30)
    bv = (d11 * d20 - d01 * d21) / den
    bw = (d00 * d21 - d01 * d20) / den
    bary = torch.stack([1 - bv - bw, bv, bw], 1).clamp(0, 1)
    bary = bary / bary.sum(1, keepdim=True)
    rows = torch.nonzero(ok).squeeze(1)
    s = rows.numel()
    idx = torch.stack([torch.arange(s).repeat_interleave(3), faces[f[rows]].reshape(-1)])
    b_rows = _coo(idx, bary[rows].reshape(-1), (s, x.shape[0]))
    # A sample stands for src_area of source surface, but where the template is much denser
    # than the samples it would concentrate that weight on one tiny triangle and fold it:
    # cap it at the template area around the triangle hit.
    cap = 3.0 * vert_area[faces[f[rows]]].sum(1)
    mats = _point_plane(src_nrm[rows], cap.clamp_max(src_area), settings.beta)
    return b_rows, mats, src_pts[rows]


def nonrigid_icp(
    x0: torch.Tensor,
    faces: torch.Tensor,
    data: torch.Tensor,
    source: SurfaceIndex,
    src_normals: torch.Tensor,
    src_samples: tuple[torch.Tensor, torch.Tensor] | None,
    settings: IcpSettings,
    *,
    log: list[str] | None = None,
) -> torch.Tensor:
    """Deform ``x0 (V, 3)`` onto the source surface.

    Args:
        x0: (V, 3) m, the articulated fit (also the ARAP rest shape).
        faces: (F, 3) template triangles.
        data: (V,) bool, vertices that take part in the data terms.
        source: index of the source surface (normalised frame).
        src_normals: (Fs, 3) unit normals of the source triangles.
        src_samples: ``(points (S, 3), normals (S, 3))`` source surface samples for the
            source -> template term, or None to skip it.
        settings: schedule and weights.
        log: when given, one progress line per iteration is appended.

    Returns:
        (V, 3) the deformed template.
    """
    n = x0.shape[0]
    edges = unique_edges(faces)
    weight = _edge_weights(x0, faces, edges, settings.cot_clamp)
    lap, deg = _laplacian(edges, weight, n)
    area = vertex_areas(x0, faces)
    face_ok = data[faces].all(1)
    tpl_index = SurfaceIndex(x0, faces) if src_samples is not None else None
    if src_samples is not None:
        src_area = source.area() / src_samples[0].shape[0]
    x = x0.clone()
    rot = None
    reject = torch.zeros(n, dtype=torch.bool)
    k = settings.iterations
    for it in range(k):
        frac = it / max(k - 1, 1)
        ell = settings.stiffness_start * (settings.stiffness_end / settings.stiffness_start) ** frac
        alpha = ell * ell
        f, q, d = source.query(x[data])
        nv = vertex_normals(x, faces)[data]
        m = src_normals[f]
        ok = (d < settings.max_distance) & ((nv * m).sum(-1) > settings.min_cos)
        mq = torch.zeros(n, 3, dtype=x.dtype)
        mn = torch.zeros(n, 3, dtype=x.dtype)
        mq[data], mn[data] = q, m
        wd = torch.zeros(n, dtype=x.dtype)
        wd[data] = area[data] * ok.to(x.dtype)
        reg = alpha * _reg_rhs(x0, edges, weight, rot)
        rev = None
        if src_samples is not None:
            rev = _reverse_terms(x, faces, face_ok, src_samples[0], src_samples[1], src_area, area, settings, tpl_index)
        for _ in range(settings.retries + 1):
            w = torch.where(reject, torch.zeros_like(wd), wd)
            diag = _point_plane(mn, w, settings.beta)
            rhs = (diag @ mq[..., None]).squeeze(-1) + reg
            b_rows = b_mats = None
            if rev is not None:
                b_rows, b_mats, rhs_rev = _drop_rejected(rev, reject)
                rhs = rhs + rhs_rev
            op = _System(lap, deg, alpha, diag, b_rows, b_mats)
            y = _cg(op, rhs, x, settings.cg_iterations, settings.cg_tolerance)
            flipped, degenerate = bad_triangles(y, faces, x0, settings.min_area_ratio)
            bad = flipped | degenerate
            if not bool(bad.any()):
                break
            reject |= _grow(faces, bad, edges)
        if not bool(bad.any()):
            x = y  # else keep the last fold-free iterate (x0 has no bad triangle)
        if settings.arap:
            rot = _arap_rotations(x, x0, edges, weight)
        if log is not None:
            log.append(
                f"icp {it:2d} l={1e3 * ell:5.1f}mm pairs={int(ok.sum())}/{int(data.sum())} "
                f"rejected={int(reject.sum())} bad={int(bad.sum())} "
                f"mean={1e3 * float(d[ok].mean()):.3f}mm p95={1e3 * float(d.quantile(0.95)):.3f}mm"
            )
    return x


def _grow(faces: torch.Tensor, bad: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """(V,) vertices of the ``bad`` triangles and one ring around them."""
    mark = torch.zeros(int(faces.max()) + 1, dtype=torch.bool)
    mark[faces[bad].reshape(-1)] = True
    i, j = edges.unbind(1)
    ring = mark.clone()
    ring[i[mark[j]]] = True
    ring[j[mark[i]]] = True
    return ring


def _drop_rejected(rev, reject: torch.Tensor):
    """The source -> template term without rows touching rejected template vertices."""
    b_rows, mats, pts = rev
    idx, val = b_rows.indices(), b_rows.values()
    hit = torch.zeros(b_rows.shape[0], dtype=torch.bool).index_put_((idx[0],), reject[idx[1]], accumulate=True)
    keep = torch.nonzero(~hit).squeeze(1)
    remap = torch.full((b_rows.shape[0],), -1, dtype=torch.long)
    remap[keep] = torch.arange(keep.numel())
    sel = ~hit[idx[0]]
    sub = _coo(torch.stack([remap[idx[0][sel]], idx[1][sel]]), val[sel], (keep.numel(), b_rows.shape[1]))
    m = mats[keep]
    rhs = sub.t() @ (m @ pts[keep, :, None]).squeeze(-1)
    return sub, m, rhs
