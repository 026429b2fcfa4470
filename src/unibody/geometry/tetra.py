"""Tetrahedral (3D barycentric) correspondence between two mesh topologies.

SOMA §3.3: every target point is expressed in the closest source triangle
``(u1, u2, u3)`` lifted to a tetrahedron by ``u4 = u1 + (u2 - u1) x (u3 - u1)``
(deliberately *not* normalised, so ``u4`` moves with the triangle's area).
The four barycentric weights ``b`` (summing to 1) are solved once, in float64;
at runtime a deformed source mesh is mapped by a gather of the three face
vertices, recomputing ``u4`` and summing ``sum_k b_k u_k``. The cost of that gather
depends only on the number of target points, not on the source vertex count.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from unibody._checks import check_shape, check_tensor

__all__ = [
    "TetCorrespondence",
    "apply_correspondence",
    "build_correspondence",
    "closest_point_on_triangles",
    "closest_triangles",
    "lift_tetrahedra",
    "quads_to_triangles",
    "tet_barycentric",
]

# Cap on (points x candidates) evaluated at once by the exact triangle test.
_PAIR_BUDGET = 1 << 18


def _dot(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    return (x * y).sum(-1)


def closest_point_on_triangles(
    p: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact closest point on triangle ``(a, b, c)`` to ``p``; all ``(..., 3)``, broadcast.

    Region analysis: if the projection of ``p`` onto the triangle's plane lies in
    the face region (all three barycentric numerators >= 0, non-zero area) the
    projection is a candidate; the three edge segments, clamped to their end
    points, cover the three edge and three vertex regions. The answer is the
    nearest candidate, which is exact for every point and also for degenerate
    (zero-area) triangles, where only the segments take part. No NaN is produced,
    neither forward nor backward. Returns ``(q (..., 3), squared distance (...))``.
    """
    p, a, b, c = torch.broadcast_tensors(p, a, b, c)
    ab, ac, ap = b - a, c - a, p - a
    d00, d01, d11 = _dot(ab, ab), _dot(ab, ac), _dot(ac, ac)
    d20, d21 = _dot(ap, ab), _dot(ap, ac)
    den = d00 * d11 - d01 * d01  # |ab x ac|^2
    vn = d11 * d20 - d01 * d21  # barycentric numerators of b and c
    wn = d00 * d21 - d01 * d20
    inside = (den > 0) & (vn >= 0) & (wn >= 0) & (vn + wn <= den)
    safe = torch.where(den > 0, den, torch.ones_like(den))
    q_face = a + (vn / safe).unsqueeze(-1) * ab + (wn / safe).unsqueeze(-1) * ac

    start = torch.stack((a, b, c), dim=-2)
    edge = torch.stack((ab, c - b, a - c), dim=-2)
    ee = _dot(edge, edge)
    t = _dot(p.unsqueeze(-2) - start, edge) / torch.where(ee > 0, ee, torch.ones_like(ee))
    q_edge = start + t.clamp(0.0, 1.0).unsqueeze(-1) * edge

    q_all = torch.cat((q_face.unsqueeze(-2), q_edge), dim=-2)  # (..., 4, 3)
    diff = q_all - p.unsqueeze(-2)
    d2 = _dot(diff, diff)
    outside = torch.stack((~inside, *[torch.zeros_like(inside)] * 3), dim=-1)
    d2 = d2.masked_fill(outside, torch.inf)  # face candidate only in the face region
    sqdist, which = d2.min(dim=-1)
    q = q_all.gather(-2, which[..., None, None].expand(*which.shape, 1, 3)).squeeze(-2)
    return q, sqdist


def _exact_on_candidates(p: torch.Tensor, tri: torch.Tensor, cand: torch.Tensor):
    """Best triangle among ``cand (n, k)`` for each point of ``p (n, 3)``; sliced by rows."""
    n, k = cand.shape
    step = max(1, _PAIR_BUDGET // max(k, 1))
    face = torch.empty(n, dtype=torch.long, device=p.device)
    q = torch.empty(n, 3, dtype=p.dtype, device=p.device)
    d2 = torch.empty(n, dtype=p.dtype, device=p.device)
    for s in range(0, n, step):
        ci = cand[s : s + step]
        t = tri[ci]  # (m, k, 3, 3)
        qq, dd = closest_point_on_triangles(p[s : s + step, None], t[..., 0, :], t[..., 1, :], t[..., 2, :])
        dmin, j = dd.min(dim=1)
        d2[s : s + step] = dmin
        face[s : s + step] = ci.gather(1, j[:, None]).squeeze(1)
        q[s : s + step] = qq.gather(1, j[:, None, None].expand(-1, 1, 3)).squeeze(1)
    return face, q, d2


@torch.no_grad()
def closest_triangles(
    points: torch.Tensor,
    vertices: torch.Tensor,
    faces: torch.Tensor,
    *,
    candidates: int = 32,
    chunk: int = 2048,
    exact_ties: bool = False,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Exact closest triangle of ``faces`` for each of ``points (N, 3)``.

    On the CPU this is libigl's AABB tree (``igl.point_mesh_squared_distance``, in float64;
    ~70x faster than the torch search on the 18,056 canonical vertices). On CUDA a torch
    search runs on the device: bounding spheres prune the triangles to ``candidates`` per
    point, tested exactly in chunks of ``chunk`` points, retried with more candidates until
    the answer is provably the closest (``candidates`` and ``chunk`` only tune that path).
    Where several triangles are equally close (a point nearest to a shared edge or vertex)
    either may be returned. Returns ``(face_index (N,) long, closest point (N, 3),
    distance (N,))`` in the dtype of ``points``, on the device of ``vertices``. Runs without autograd:
    it is a precomputation whose useful output is the index. ``exact_ties`` takes the torch
    search on the CPU too, whose choice among equally close triangles the shipped canonical
    assets were built with (libigl picks another for 11 wrap vertices, moving them up to 0.5 mm).
    """
    sizes: dict[str, int] = {}
    check_shape(points, "N 3", name="points", sizes=sizes)
    check_shape(vertices, "V 3", name="vertices", sizes=sizes)
    check_shape(faces, "F 3", name="faces", sizes=sizes)
    if faces.dtype not in (torch.int32, torch.int64):
        raise ValueError(f"faces: expected an integer tensor, got {faces.dtype}")
    if vertices.dtype != points.dtype:
        raise ValueError(f"vertices: dtype {vertices.dtype} differs from points dtype {points.dtype}")
    if sizes["F"] == 0:
        raise ValueError("faces: expected at least one triangle, got 0")
    if candidates < 1 or chunk < 1:
        raise ValueError(f"candidates/chunk: expected >= 1, got {candidates}/{chunk}")
    if vertices.device.type != "cpu" or exact_ties:
        return _closest_triangles_torch(points, vertices, faces, candidates, chunk)
    import igl  # a compiled extension: loaded on first use only

    # Centred on the mesh (as the torch path) so rounding stays at the scale of the body.
    v = vertices.detach().to(torch.float64)
    origin = v.mean(0)
    sq, face, q = igl.point_mesh_squared_distance(
        np.ascontiguousarray((points.detach().to(device="cpu", dtype=torch.float64) - origin).numpy()),
        np.ascontiguousarray((v - origin).numpy()),
        np.ascontiguousarray(faces.detach().cpu().numpy().astype(np.int64, copy=False)),
    )
    dist = torch.from_numpy(sq).sqrt().to(points.dtype)
    return torch.from_numpy(face), (torch.from_numpy(q) + origin).to(points.dtype), dist


def _closest_triangles_torch(
    points: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor, candidates: int, chunk: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`closest_triangles` in torch (the CUDA path).

    Each triangle gets a bounding sphere (centroid, radius = farthest vertex), so
    ``|p - centroid| - radius`` is a lower bound on its distance to ``p``. For a chunk
    of points, the ``candidates`` triangles with the smallest bound (centroid
    distances via ``torch.cdist``) are tested exactly. The result is accepted when
    no other triangle's bound is below the best exact distance; rows that fail are
    retried with 4x as many candidates, up to all triangles, so the answer is
    always exact.
    """
    faces = faces.to(device=vertices.device, dtype=torch.long)
    points = points.to(vertices.device)
    n_faces = faces.shape[0]
    # Centre everything on the mesh to keep coordinates (and rounding) small.
    origin = vertices.mean(0)
    tri = vertices[faces] - origin  # (F, 3, 3)
    pts = points - origin
    centre = tri.mean(1)
    radius = (tri - centre[:, None]).norm(dim=-1).amax(1)
    # Bounds only prune, so they are computed in float32 (half the memory traffic of
    # float64); a slack covering that rounding keeps the acceptance test conservative.
    lo = torch.float32 if points.dtype == torch.float64 else points.dtype
    scale = float(tri.abs().amax()) + float(pts.abs().amax()) if points.numel() else 1.0
    slack = 64.0 * torch.finfo(lo).eps * max(scale, 1e-30)
    centre_lo, radius_lo, pts_lo = centre.to(lo), radius.to(lo), pts.to(lo)

    n = points.shape[0]
    face = torch.empty(n, dtype=torch.long, device=points.device)
    q = torch.empty(n, 3, dtype=points.dtype, device=points.device)
    dist = torch.empty(n, dtype=points.dtype, device=points.device)
    for s in range(0, n, chunk):
        p = pts[s : s + chunk]
        bound = torch.cdist(pts_lo[s : s + chunk], centre_lo, compute_mode="donot_use_mm_for_euclid_dist")
        bound -= radius_lo
        todo = torch.arange(p.shape[0], device=p.device)
        k = min(candidates, n_faces)
        while todo.numel():
            lb = bound if todo.numel() == bound.shape[0] else bound[todo]
            if k >= n_faces:
                cand, next_lb = torch.arange(n_faces, device=p.device).expand(todo.numel(), -1), None
            else:
                vals, idx = lb.topk(k + 1, dim=1, largest=False, sorted=False)
                # The largest of the k + 1 smallest bounds is a bound for every non-candidate.
                next_lb, far = vals.max(dim=1)
                keep = torch.ones_like(idx, dtype=torch.bool).scatter_(1, far[:, None], False)
                cand = idx[keep].view(-1, k)
            f, qq, d2 = _exact_on_candidates(p[todo], tri, cand)
            d = d2.sqrt()
            ok = torch.ones_like(d, dtype=torch.bool) if next_lb is None else next_lb.to(d) >= d + slack
            rows = todo[ok] + s
            face[rows], q[rows], dist[rows] = f[ok], qq[ok], d[ok]
            todo = todo[~ok]
            k = min(4 * k, n_faces)
    return face, q + origin, dist


def lift_tetrahedra(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Tetrahedra ``(..., F, 4, 3)`` = ``(u1, u2, u3, u1 + (u2 - u1) x (u3 - u1))`` per face."""
    check_shape(faces, "F 3", name="faces")
    u = vertices[..., faces, :]  # (..., F, 3, 3)
    u1, u2, u3 = u.unbind(-2)
    u4 = u1 + torch.linalg.cross(u2 - u1, u3 - u1, dim=-1)
    return torch.cat((u, u4.unsqueeze(-2)), dim=-2)


def tet_barycentric(points: torch.Tensor, tet: torch.Tensor) -> torch.Tensor:
    """Barycentric weights ``(..., 4)`` (summing to 1) of ``points (..., 3)`` in ``tet (..., 4, 3)``.

    Solves ``[u1-u4, u2-u4, u3-u4] x = p - u4`` in the input dtype; ``b = (x, 1 - sum x)``.
    """
    if tet.shape[-2:] != (4, 3):
        raise ValueError(f"tet: expected shape (..., 4, 3), got {tuple(tet.shape)}")
    if points.shape[-1:] != (3,):
        raise ValueError(f"points: expected shape (..., 3), got {tuple(points.shape)}")
    u4 = tet[..., 3, :]
    m = (tet[..., :3, :] - u4.unsqueeze(-2)).transpose(-1, -2)  # columns u_k - u4
    rhs = (points - u4).unsqueeze(-1)
    batch = torch.broadcast_shapes(m.shape[:-2], rhs.shape[:-2])
    x = torch.linalg.solve(m.expand(*batch, 3, 3), rhs.expand(*batch, 3, 1)).squeeze(-1)
    return torch.cat((x, 1.0 - x.sum(-1, keepdim=True)), dim=-1)


def apply_correspondence(vertices: torch.Tensor, face_vertices: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Eq. (1): map source vertices ``(B, Vs, 3)`` or ``(Vs, 3)`` to ``(B, N, 3)`` or ``(N, 3)``.

    Gathers ``u1, u2, u3`` of each point's face, recomputes ``u4`` and returns
    ``sum_k weights[:, k] u_k``, evaluated as ``u1 + sum_{k>1} b_k (u_k - u1)``, which
    equals it for weights summing to 1 (as built) and avoids the cancellation of
    large ``b`` times absolute positions (the un-normalised ``u4`` of small faces
    gives ``|b|`` in the hundreds for points a few mm off the surface), so float32
    stays accurate. ``weights`` must already match the dtype and device of
    ``vertices`` (no silent casts). Differentiable w.r.t. ``vertices`` and ``weights[:, 1:]``.
    """
    sizes: dict[str, int] = {}
    check_shape(vertices, "B V 3", "V 3", name="vertices")
    check_shape(face_vertices, "N 3", name="face_vertices", sizes=sizes)
    check_shape(weights, "N 4", name="weights", sizes=sizes)
    if face_vertices.dtype not in (torch.int32, torch.int64):
        raise ValueError(f"face_vertices: expected an integer tensor, got {face_vertices.dtype}")
    if weights.dtype != vertices.dtype:
        raise ValueError(
            f"weights: dtype {str(weights.dtype).removeprefix('torch.')} does not match vertices dtype "
            f"{str(vertices.dtype).removeprefix('torch.')}; cast it first, e.g. weights.to(vertices)"
        )
    for name, t in (("weights", weights), ("face_vertices", face_vertices)):
        if t.device != vertices.device:
            raise ValueError(f"{name}: on {t.device} but vertices are on {vertices.device}; move it first")
    if _batch_inner_applies(vertices, weights):
        return _apply_batch_inner(vertices, face_vertices, weights)
    n = face_vertices.shape[0]
    u = vertices.index_select(-2, face_vertices.reshape(-1)).unflatten(-2, (n, 3))  # (..., N, 3, 3)
    u1, u2, u3 = u.unbind(-2)
    e2, e3 = u2 - u1, u3 - u1
    e4 = torch.linalg.cross(e2, e3, dim=-1)  # u4 - u1
    return u1 + weights[:, 1:2] * e2 + weights[:, 2:3] * e3 + weights[:, 3:4] * e4


# The batch-inner kernel below pays from B = 4 on (Anny -> canonical, N = 18,056, float32,
# 1 thread, interleaved medians of process_time on a shared 2-core EPYC: 1.5x at B = 4,
# 2.3x at B = 8, 4.5x at B = 32, 2.5x at B = 128) and loses ~20 % at B = 1, which keeps the
# autograd formula.
_BATCH_INNER_MIN_B = 4
# Elements of one chunk per batch item x B: the chunk's gather (9 x this many values) and its
# temporaries stay in L2/L3 instead of streaming (B, N, 3)-sized intermediates through memory.
# Single-threaded only: with more threads every op of every chunk is its own parallel region,
# and on the same shared machine at 2 threads the chunked loop ran 0.2-0.8x the old formula at
# B = 32 and 128 (barrier waits), while one chunk of all N (a dozen large parallel ops) ran
# 1.1-2x it.
_BATCH_INNER_CHUNK = 1 << 16


def _batch_inner_applies(vertices: torch.Tensor, weights: torch.Tensor) -> bool:
    """Whether :func:`_apply_batch_inner` may run: a CPU batch of at least 4 that needs no graph.

    It writes into its own buffers with ``out=`` and in-place ops, so it runs only when autograd
    records nothing (no input requires grad, or grad mode is off), outside ``torch.compile``
    tracing and ``torch.func`` transforms; on CUDA its per-chunk launches would cost more than
    they save.
    """
    return (
        vertices.dim() == 3
        and vertices.shape[0] >= _BATCH_INNER_MIN_B
        and vertices.device.type == "cpu"
        and not (torch.is_grad_enabled() and (vertices.requires_grad or weights.requires_grad))
        and not torch.compiler.is_compiling()
        and not torch._C._are_functorch_transforms_active()
    )


def _apply_batch_inner(vertices: torch.Tensor, face_vertices: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """:func:`apply_correspondence` for ``(B, Vs, 3)``, no autograd, with the batch innermost.

    The same operations as the autograd formula (``u1 + b2 e2 + b3 e3 + b4 (e2 x e3)``, so the
    same cancellation-free float32 accuracy), evaluated on ``(n, 3, B)`` tiles so that every
    elementwise op runs over contiguous runs of ``B`` values (vectorised) instead of an innermost
    dimension of 3, in chunks of canonical vertices whose temporaries stay in cache:

    - one transposing copy of the input to ``(Vs, 3, B)``, whose rows (``3 B`` contiguous values)
      are gathered by ``index_select``;
    - the edges ``e2, e3`` in a ``(n, 2, 5, B)`` buffer whose components run ``x y z x y``, so the
      cross product is two products and a difference of shifted views;
    - the result is accumulated by ``addcmul`` and copied, transposed, into its slice of the
      contiguous ``(B, N, 3)`` output.

    With more than one intra-op thread the whole of ``N`` is one chunk (see ``_BATCH_INNER_CHUNK``).
    """
    b, n = vertices.shape[0], face_vertices.shape[0]
    chunk = min(n, max(64, _BATCH_INNER_CHUNK // b)) if torch.get_num_threads() == 1 else n
    vt = vertices.permute(1, 2, 0).contiguous()  # (Vs, 3, B)
    ids = face_vertices.reshape(-1)
    w = weights[:, :, None, None]  # (N, 4, 1, 1), broadcast over (3, B)
    out = vertices.new_empty(b, n, 3)
    gather = vertices.new_empty(3 * chunk, 3, b)
    edges = vertices.new_empty(chunk, 2, 5, b)
    cross, tmp, acc = (vertices.new_empty(chunk, 3, b) for _ in range(3))
    for n0 in range(0, n, chunk):
        m = min(chunk, n - n0)
        u = torch.index_select(vt, 0, ids[3 * n0 : 3 * (n0 + m)], out=gather[: 3 * m]).view(m, 3, 3, b)
        e = edges[:m]
        torch.sub(u[:, 1:], u[:, :1], out=e[:, :, :3])  # e2, e3: (m, 2, 3, B)
        e[:, :, 3:].copy_(e[:, :, :2])  # components x y z x y
        e2, e3 = e[:, 0], e[:, 1]
        c, t, r = cross[:m], tmp[:m], acc[:m]
        torch.mul(e2[:, 1:4], e3[:, 2:5], out=c)  # (y z x)(z x y) - (z x y)(y z x) = e2 x e3
        torch.mul(e2[:, 2:5], e3[:, 1:4], out=t)
        c.sub_(t)
        wm = w[n0 : n0 + m]
        torch.addcmul(u[:, 0], wm[:, 1], e2[:, :3], out=r)
        r.addcmul_(wm[:, 2], e3[:, :3]).addcmul_(wm[:, 3], c)
        out[:, n0 : n0 + m].copy_(r.permute(2, 0, 1))
    return out


@dataclass(frozen=True, slots=True)
class TetCorrespondence:
    """Fixed buffers of the mapping: ``face_vertices (N, 3) long`` and ``weights (N, 4)``."""

    face_vertices: torch.Tensor
    weights: torch.Tensor

    def __post_init__(self) -> None:
        sizes: dict[str, int] = {}
        check_shape(self.face_vertices, "N 3", name="face_vertices", sizes=sizes)
        check_shape(self.weights, "N 4", name="weights", sizes=sizes)

    def __len__(self) -> int:
        return int(self.face_vertices.shape[0])

    def to(self, *args, **kwargs) -> TetCorrespondence:
        """Move both buffers (``face_vertices`` keeps its integer dtype)."""
        w = self.weights.to(*args, **kwargs)
        return TetCorrespondence(self.face_vertices.to(w.device), w)

    def apply(self, vertices: torch.Tensor) -> torch.Tensor:
        """:func:`apply_correspondence` with the weights cast to ``vertices`` (explicitly)."""
        check_tensor(vertices, "vertices")
        w = self.weights.to(device=vertices.device, dtype=vertices.dtype)
        return apply_correspondence(vertices, self.face_vertices.to(vertices.device), w)


def build_correspondence(
    points: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor, **search
) -> TetCorrespondence:
    """Closest source triangle + tetrahedral weights of ``points (N, 3)``, in float64.

    Zero-area faces are skipped (their tetrahedron would be singular). Extra
    keyword arguments go to :func:`closest_triangles`. The result lives on the
    device of ``vertices``.
    """
    check_shape(faces, "F 3", name="faces")
    v = vertices.detach().to(torch.float64)
    p = points.detach().to(device=v.device, dtype=torch.float64)
    faces = faces.to(device=v.device, dtype=torch.long)
    tri = v[faces]
    area2 = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1).square().sum(-1)
    valid = (area2 > 0).nonzero().squeeze(1)
    if valid.numel() == 0:
        raise ValueError("faces: every triangle has zero area")
    idx, _, _ = closest_triangles(p, v, faces[valid], **search)
    fv = faces[valid[idx]]
    weights = tet_barycentric(p, lift_tetrahedra(v, fv))
    return TetCorrespondence(face_vertices=fv, weights=weights)


def quads_to_triangles(faces: Sequence[Sequence[int]] | np.ndarray | torch.Tensor) -> torch.Tensor:
    """Triangulate polygons (tris, quads, n-gons) by fans: quad ``(a, b, c, d)`` -> ``(a, b, c), (a, c, d)``.

    Accepts a rectangular array/tensor ``(F, 3 or 4)`` or a ragged list; each
    polygon's triangles stay consecutive and in input order. Returns ``(T, 3)`` long.
    """
    if isinstance(faces, torch.Tensor):
        faces = faces.detach().cpu().numpy()
    if isinstance(faces, np.ndarray) and faces.ndim == 2:
        polys = [np.asarray(faces, dtype=np.int64)]
        order = np.arange(len(faces))
    else:  # ragged: group polygons by size, then restore the input order
        faces = [np.asarray(f, dtype=np.int64).reshape(-1) for f in faces]
        sizes = np.array([len(f) for f in faces], dtype=np.int64)
        order = np.argsort(sizes, kind="stable")
        polys = [np.stack([faces[i] for i in order[sizes[order] == k]]) for k in np.unique(sizes)]
    if not polys or polys[0].size == 0:
        return torch.empty(0, 3, dtype=torch.long)
    tris = []
    for poly in polys:
        k = poly.shape[1]
        if k < 3:
            raise ValueError(f"faces: expected polygons with >= 3 vertices, got one with {k}")
        fan = np.stack([np.stack((poly[:, 0], poly[:, i], poly[:, i + 1]), axis=1) for i in range(1, k - 1)], axis=1)
        tris.extend(fan)  # one (k - 2, 3) block per polygon, in `order`
    blocks: list[np.ndarray] = [np.empty(0)] * len(tris)
    for pos, i in enumerate(order):
        blocks[i] = tris[pos]
    return torch.from_numpy(np.concatenate(blocks))
