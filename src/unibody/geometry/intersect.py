"""Exact triangle-triangle intersection and mesh self-intersection pairs.

Narrow phase (:func:`triangles_intersect`): two closed, non-coplanar triangles intersect iff an
edge of one meets the other triangle. Everything is decided from the signs of orientation
determinants ``orient3d(a, b, c, d) = det[a - d, b - d, c - d]`` (Shewchuk's convention):

* ``s_a[i] = orient3d(B, a_i)``, ``s_b[j] = orient3d(A, b_j)``: vertex sides of the other plane.
  All three strictly on one side rejects the pair at once.
* ``E[i, k] = orient3d(a_i, a_i+1, b_k, b_k+1)``: the side on which edge ``i`` of A passes edge
  ``k`` of B. Edge ``i`` of A meets B iff its endpoints are on opposite sides of (or on) B's
  plane, not both on it, and ``E[i, 0..2]`` share a sign (zeros allowed: through an edge or a
  vertex). Since ``orient3d(a, b, c, d) = orient3d(c, d, a, b)``, edge ``k`` of B meets A iff
  the same holds for ``s_b`` and ``E[0..2, k]``: 15 determinants decide a pair.

An edge lying in the other triangle's plane is skipped: the intersection is then also found
through a neighbouring edge of either triangle.

The signs are exact: each determinant is evaluated in float64 with Shewchuk's static error
bound, and the rare ones the bound cannot certify are recomputed with Python integers (every
float64 is an integer times a power of two). Inputs of any float dtype are converted to float64
first (exactly), so the predicate has no tolerance: touching counts as intersecting.

Coplanar pairs (every vertex of each triangle exactly on the other's plane) are reported as *not*
intersecting, even where they overlap: no edge then crosses the other plane. For meshes from
float data an exactly coplanar overlap is a measure-zero event; handling it would need a 2D test.
A degenerate (collinear) triangle is handled as the segment it is, unless it lies in the other
triangle's plane, which makes the pair coplanar.

Broad phase (:func:`intersecting_pairs`): triangles are binned by bounding-sphere radius
(powers of two below the largest), a k-d tree per bin gives the pairs of centroids within the
sum of the bins' largest radii, exact AABB overlap filters them, pairs that share a vertex index
are dropped, and the narrow phase runs in chunks of bounded memory.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from unibody._checks import check_finite, check_shape

__all__ = ["intersecting_pairs", "triangles_intersect"]

_CHUNK = 1 << 17  # triangle pairs per narrow-phase chunk (a few hundred MB of temporaries at most)
_ERR_BOUND = 8.0 * 2.0**-53  # above Shewchuk's o3derrboundA = (7 + 56 eps) eps for float64
_SAFE_RANGE = (1e-80, 1e80)  # |differences| inside it cannot under- or overflow a 3x3 determinant
_MAX_BINS = 8  # radius bins of the broad phase
_RADIUS_SLACK = 1.0 + 1e-9  # covers the rounding of centroids, radii and k-d tree distances


def _exact_orient_signs(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Exact signs of ``det[a - d, b - d, c - d]`` with Python integers.

    Args:
        a, b, c, d: (M, 3) float64 points.

    Returns:
        (M,) int8 signs in {-1, 0, 1}.
    """
    pts = np.stack([a, b, c, d], axis=1)  # (M, 4, 3)
    mant, expo = np.frexp(pts)  # pts = mant * 2**expo, 0.5 <= |mant| < 1
    mant = np.ldexp(mant, 53).astype(np.int64)  # exact 53-bit integers
    expo = np.where(mant == 0, expo.max(axis=(1, 2), keepdims=True), expo)
    shift = expo - expo.min(axis=(1, 2), keepdims=True)  # a positive common scale per row keeps the sign
    out = np.empty(len(pts), dtype=np.int8)
    for row, (m_row, s_row) in enumerate(zip(mant.tolist(), shift.tolist(), strict=True)):
        (ax, ay, az), (bx, by, bz), (cx, cy, cz), (dx, dy, dz) = (
            [m << s for m, s in zip(mp, sp, strict=True)] for mp, sp in zip(m_row, s_row, strict=True)
        )
        ax, ay, az, bx, by, bz = ax - dx, ay - dy, az - dz, bx - dx, by - dy, bz - dz
        cx, cy, cz = cx - dx, cy - dy, cz - dz
        det = az * (bx * cy - cx * by) + bz * (cx * ay - ax * cy) + cz * (ax * by - bx * ay)
        out[row] = (det > 0) - (det < 0)
    return out


def _orient_signs(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Exact signs of ``orient3d(a, b, c, d) = det[a - d, b - d, c - d]``, filtered float64.

    Positive when ``d`` lies below the plane through ``a, b, c`` (counter-clockwise seen from
    above); zero when the four points are coplanar.

    Args:
        a, b, c, d: (..., 3) float64 points, broadcast together.

    Returns:
        (...) int8 signs in {-1, 0, 1}.
    """
    a, b, c, d = torch.broadcast_tensors(a, b, c, d)
    ad, bd, cd = a - d, b - d, c - d
    ax, ay, az = ad.unbind(-1)
    bx, by, bz = bd.unbind(-1)
    cx, cy, cz = cd.unbind(-1)
    bxcy, cxby, cxay, axcy, axby, bxay = bx * cy, cx * by, cx * ay, ax * cy, ax * by, bx * ay
    det = az * (bxcy - cxby) + bz * (cxay - axcy) + cz * (axby - bxay)
    perm = (bxcy.abs() + cxby.abs()) * az.abs() + (cxay.abs() + axcy.abs()) * bz.abs()
    perm = perm + (axby.abs() + bxay.abs()) * cz.abs()
    diffs = torch.stack([ad, bd, cd], dim=-1).abs()
    unsafe = ((diffs != 0) & ((diffs < _SAFE_RANGE[0]) | (diffs > _SAFE_RANGE[1]))).flatten(-2).any(-1)
    unsure = (det.abs() <= _ERR_BOUND * perm) & (perm > 0) | unsafe
    signs = torch.sign(det).to(torch.int8)
    if bool(unsure.any()):
        idx = unsure.nonzero(as_tuple=True)
        exact = _exact_orient_signs(*(p[idx].numpy() for p in (a, b, c, d)))
        signs[idx] = torch.from_numpy(exact)
    return signs


def _segments_cross(ends: torch.Tensor, sides: torch.Tensor) -> torch.Tensor:
    """Which edges of one triangle meet the other (closed) triangle.

    Args:
        ends: (N, 3) int8 sides of the three vertices w.r.t. the other triangle's plane.
        sides: (N, 3, 3) int8, ``sides[n, e]`` the three edge-edge orientations of edge ``e``.

    Returns:
        (N, 3) bool per edge ``e`` (vertex ``e`` to vertex ``e + 1``).
    """
    nxt = ends.roll(-1, dims=1)
    straddles = (ends.to(torch.int16) * nxt <= 0) & ((ends != 0) | (nxt != 0))
    through = (sides >= 0).all(-1) | (sides <= 0).all(-1)
    return straddles & through


def _intersect64(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """:func:`triangles_intersect` on validated float64 CPU tensors (N, 3, 3)."""
    s_a = _orient_signs(b[:, None, 0], b[:, None, 1], b[:, None, 2], a)  # (N, 3)
    s_b = _orient_signs(a[:, None, 0], a[:, None, 1], a[:, None, 2], b)
    one_side = (s_a > 0).all(1) | (s_a < 0).all(1) | (s_b > 0).all(1) | (s_b < 0).all(1)
    hit = torch.zeros(a.shape[0], dtype=torch.bool)
    todo = (~one_side).nonzero().squeeze(1)
    if todo.numel() == 0:
        return hit
    a, b, s_a, s_b = a[todo], b[todo], s_a[todo], s_b[todo]
    a0, a1 = a[:, :, None], a.roll(-1, dims=1)[:, :, None]  # edge i of A on dim 1
    b0, b1 = b[:, None, :], b.roll(-1, dims=1)[:, None, :]  # edge k of B on dim 2
    edges = _orient_signs(a0, a1, b0, b1)  # (M, 3, 3) = orient3d(a_i, a_i+1, b_k, b_k+1)
    cross = _segments_cross(s_a, edges).any(1) | _segments_cross(s_b, edges.transpose(1, 2)).any(1)
    hit[todo] = cross
    return hit


def triangles_intersect(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Does triangle ``a[n]`` intersect triangle ``b[n]``? Exact, vectorised over n.

    Triangles are closed: touching at a point counts. Exactly coplanar pairs are reported as not
    intersecting (see the module docstring).

    Args:
        a: (N, 3, 3) triangle vertices (any float dtype and device).
        b: (N, 3, 3) triangle vertices.

    Returns:
        (N,) bool on ``a``'s device.

    Raises:
        ValueError: on wrong shapes or non-finite coordinates.
    """
    sizes: dict[str, int] = {}
    for name, t in (("a", a), ("b", b)):
        check_shape(t, "N 3 3", name=name, sizes=sizes)
        _check_float(t, name)
        check_finite(t, name)
    a64, b64 = _cpu64(a), _cpu64(b)
    hits = [_intersect64(x, y) for x, y in zip(a64.split(_CHUNK), b64.split(_CHUNK), strict=True)]
    return torch.cat(hits).to(a.device) if hits else torch.zeros(0, dtype=torch.bool, device=a.device)


def _candidate_pairs(centres: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Pairs ``i < j`` whose bounding spheres may overlap: ``|c_i - c_j| <= r_i + r_j``.

    Triangles are binned by radius (``(r_max / 2**(k+1), r_max / 2**k]``, the last bin takes the
    rest) so that small triangles are not searched with the largest triangle's radius.

    Args:
        centres: (F, 3) sphere centres.
        radii: (F,) sphere radii.

    Returns:
        (P, 2) int64 pairs, a superset of the overlapping ones.
    """
    r_max = float(radii.max())
    if r_max == 0.0:
        ratio = np.zeros(len(radii))
    else:
        ratio = np.log2(r_max / np.maximum(radii, r_max * 2.0**-_MAX_BINS))
    bins = np.minimum(np.floor(ratio).astype(np.int64), _MAX_BINS - 1)
    groups = [np.flatnonzero(bins == k) for k in range(_MAX_BINS)]
    groups = [g for g in groups if len(g)]
    trees = [cKDTree(centres[g]) for g in groups]
    bounds = [float(radii[g].max()) * _RADIUS_SLACK for g in groups]
    found = [np.empty((0, 2), dtype=np.int64)]
    for i, (g_i, t_i) in enumerate(zip(groups, trees, strict=True)):
        pairs = t_i.query_pairs(2.0 * bounds[i], output_type="ndarray")
        found.append(g_i[pairs])
        for j in range(i + 1, len(groups)):
            near = t_i.sparse_distance_matrix(trees[j], bounds[i] + bounds[j], output_type="ndarray")
            found.append(np.stack([g_i[near["i"]], groups[j][near["j"]]], axis=1))
    pairs = np.concatenate(found).astype(np.int64)
    return np.sort(pairs, axis=1)


def intersecting_pairs(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """The pairs of triangles of one mesh that intersect (exact, see :func:`triangles_intersect`).

    Pairs that share a vertex index are never reported: neighbours touch by construction.

    Args:
        vertices: (V, 3) float vertex positions (any device; a detached CPU copy is used).
        faces: (F, 3) integer vertex indices.

    Returns:
        (P, 2) int64 triangle indices, ``i < j``, sorted lexicographically, on ``vertices``' device.

    Raises:
        ValueError: on wrong shapes, non-finite vertices or out-of-range face indices.
        TypeError: on non-tensors or wrong dtypes.
    """
    check_shape(vertices, "V 3", name="vertices")
    _check_float(vertices, "vertices")
    check_finite(vertices, "vertices")
    check_shape(faces, "F 3", name="faces")
    if faces.is_floating_point() or faces.is_complex() or faces.dtype == torch.bool:
        raise TypeError(f"faces: expected an integer dtype, got {str(faces.dtype).removeprefix('torch.')}")
    f = faces.detach().to("cpu", torch.int64)
    if f.numel() and (int(f.min()) < 0 or int(f.max()) >= vertices.shape[0]):
        raise ValueError(f"faces: expected indices in [0, {vertices.shape[0]}), got [{int(f.min())}, {int(f.max())}]")
    empty = torch.empty(0, 2, dtype=torch.int64, device=vertices.device)
    if f.shape[0] < 2:
        return empty
    tri = _cpu64(vertices)[f]  # (F, 3, 3)
    tri_np, f_np = tri.numpy(), f.numpy()
    centres = tri_np.mean(axis=1)
    radii = np.linalg.norm(tri_np - centres[:, None], axis=2).max(axis=1)
    pairs = _candidate_pairs(centres, radii)
    lo, hi = tri_np.min(axis=1), tri_np.max(axis=1)
    i, j = pairs[:, 0], pairs[:, 1]
    boxes_meet = ((lo[i] <= hi[j]) & (lo[j] <= hi[i])).all(axis=1)
    pairs = pairs[boxes_meet]
    i, j = pairs[:, 0], pairs[:, 1]
    shares = (f_np[i][:, :, None] == f_np[j][:, None, :]).any(axis=(1, 2))
    pairs = torch.from_numpy(pairs[~shares])
    hits = [chunk[_intersect64(tri[chunk[:, 0]], tri[chunk[:, 1]])] for chunk in pairs.split(_CHUNK) if chunk.numel()]
    if not hits:
        return empty
    out = torch.cat(hits)
    order = np.lexsort((out[:, 1].numpy(), out[:, 0].numpy()))
    return out[torch.from_numpy(order)].to(vertices.device)


def _check_float(x: torch.Tensor, name: str) -> None:
    """Raise TypeError unless ``x`` holds real floating-point values."""
    if not x.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point dtype, got {str(x.dtype).removeprefix('torch.')}")


def _cpu64(x: torch.Tensor) -> torch.Tensor:
    """A detached float64 CPU copy of ``x``."""
    return x.detach().to("cpu", torch.float64)
