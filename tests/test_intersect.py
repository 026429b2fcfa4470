"""Exact triangle-triangle intersection and mesh self-intersection pairs."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
import torch

from conftest import icosphere
from unibody.geometry.intersect import _orient_signs, intersecting_pairs, triangles_intersect


def _tri(*points: tuple[float, float, float]) -> torch.Tensor:
    """One triangle as a (1, 3, 3) float64 batch."""
    return torch.tensor([points], dtype=torch.float64)


def sphere(levels: int = 3) -> tuple[torch.Tensor, torch.Tensor]:
    """The unit icosphere (``conftest.icosphere``) as float64 / int64 tensors."""
    v, f = icosphere(levels)
    return torch.from_numpy(v), torch.from_numpy(f)


def two_spheres(distance: float) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Two unit icospheres ``distance`` apart along X, as one mesh; also the first sphere's face count."""
    v, f = sphere()
    shift = torch.tensor([distance, 0.0, 0.0], dtype=v.dtype)
    return torch.cat([v, v + shift]), torch.cat([f, f + v.shape[0]]), f.shape[0]


def test_agrees_with_libigl_on_random_pairs():
    igl = pytest.importorskip("igl")
    gen = np.random.default_rng(0)
    n = 2500
    a = gen.uniform(0, 1, (n, 1, 3)) + gen.normal(0, 0.1, (n, 3, 3))
    # b contains a point of a, then moves: about half the pairs still intersect.
    x = (gen.dirichlet(np.ones(3), n)[:, :, None] * a).sum(1)
    u, w = gen.normal(0, 0.1, (n, 3, 3)), gen.dirichlet(np.ones(3), n)[:, :, None]
    b = x[:, None] + u - (w * u).sum(1, keepdims=True) + gen.normal(0, 0.035, (n, 1, 3))
    ours = triangles_intersect(torch.from_numpy(a), torch.from_numpy(b)).numpy()
    ref = np.empty(n, dtype=bool)
    for k in range(n):
        hit, coplanar, _, _ = igl.tri_tri_intersection_test_3d(*a[k, :, None, :], *b[k, :, None, :])
        assert not coplanar
        ref[k] = hit
    assert 0.35 < ref.mean() < 0.65
    np.testing.assert_array_equal(ours, ref)
    ours32 = triangles_intersect(torch.from_numpy(a).float(), torch.from_numpy(b).float())
    assert ours32.dtype == torch.bool and ours32.shape == (n,)


def test_hand_made_cases():
    ground = _tri((0, 0, 0), (2, 0, 0), (0, 2, 0))
    chain = _tri((0.5, 0.5, -1), (0.5, 0.5, 1), (-1, 0.5, 0))  # hooks through the ground's edge x = 0
    assert triangles_intersect(ground, chain).item()
    lifted = ground + torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64)
    assert not triangles_intersect(ground, lifted).item()  # parallel planes
    spike = _tri((0.5, 0.5, -1), (0.6, 0.5, 1), (0.5, 0.6, 1))  # one vertex below, two above
    assert triangles_intersect(ground, spike).item() and triangles_intersect(spike, ground).item()
    assert not triangles_intersect(ground, spike + torch.tensor([3.0, 0.0, 0.0], dtype=torch.float64)).item()
    batch = triangles_intersect(torch.cat([ground, ground, ground]), torch.cat([chain, lifted, spike]))
    assert batch.tolist() == [True, False, True]


def test_touching_is_exact():
    ground = _tri((0, 0, 0), (2, 0, 0), (0, 2, 0))
    for z, expected in ((0.0, True), (-1e-300, True), (1e-300, False), (2**-40, False)):
        tip = _tri((0.5, 0.5, z), (0.5, 0.6, 1), (0.6, 0.5, 1))  # a vertex touches the ground from above
        assert triangles_intersect(ground, tip).item() is expected, z
    on_edge = _tri((1, 1, 0), (2, 2, 1), (2, 2, -1))  # meets the hypotenuse in a single point
    assert triangles_intersect(ground, on_edge).item()
    assert not triangles_intersect(ground, on_edge + torch.tensor([1e-15, 0, 0], dtype=torch.float64)).item()
    # an edge lying in the ground's plane, on the line x = y: outside the ground, then touching its corner
    assert not triangles_intersect(ground, _tri((1.5, 1.5, 0), (3, 3, 0), (1.5, 1.5, 1))).item()
    assert triangles_intersect(ground, _tri((1, 1, 0), (3, 3, 0), (1, 1, 1))).item()
    needle = _tri((0.5, 0.5, -1), (0.5, 0.5, 0), (0.5, 0.5, 1))  # degenerate: a segment through the ground
    assert triangles_intersect(ground, needle).item() and triangles_intersect(needle, ground).item()
    assert not triangles_intersect(ground, needle + torch.tensor([0.0, 0.0, 1.5], dtype=torch.float64)).item()
    coplanar = _tri((0.5, 0.5, 0), (1.5, 0.5, 0), (0.5, 1.5, 0))  # documented: coplanar is not reported
    assert not triangles_intersect(ground, coplanar).item()


def test_orientation_signs_are_exact_near_degenerate():
    gen = np.random.default_rng(1)
    a, b, c = gen.normal(size=(3, 400, 3))
    s, t = gen.uniform(-1, 1, (2, 400, 1))
    d = a + s * (b - a) + t * (c - a) + gen.normal(size=(400, 3)) * 1e-17  # within rounding of the plane
    tensors = [torch.from_numpy(p) for p in (a, b, c, d)]
    signs = _orient_signs(*tensors).tolist()

    def exact(p: np.ndarray, q: np.ndarray, r: np.ndarray, o: np.ndarray) -> int:
        rows = [[Fraction(float(x)) - Fraction(float(y)) for x, y in zip(v, o, strict=True)] for v in (p, q, r)]
        (ax, ay, az), (bx, by, bz), (cx, cy, cz) = rows
        det = ax * (by * cz - bz * cy) - ay * (bx * cz - bz * cx) + az * (bx * cy - by * cx)
        return (det > 0) - (det < 0)

    expected = [exact(a[k], b[k], c[k], d[k]) for k in range(400)]
    assert signs == expected
    assert len(set(expected)) >= 2  # the data really straddles the plane


def test_shared_vertex_excluded_but_touching_reported():
    v = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [-1, 0, 0.5], [0, -1, 0.5], [0, 0, 0]], dtype=torch.float64)
    shared = torch.tensor([[0, 1, 2], [0, 3, 4]])
    assert intersecting_pairs(v, shared).shape == (0, 2)
    copied = torch.tensor([[0, 1, 2], [5, 3, 4]])  # same geometry, the common corner duplicated
    assert intersecting_pairs(v, copied).tolist() == [[0, 1]]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_icosphere_has_no_self_intersections(dtype):
    v, f = sphere()
    assert f.shape == (1280, 3)
    pairs = intersecting_pairs(v.to(dtype), f)
    assert pairs.shape == (0, 2) and pairs.dtype == torch.int64


def test_two_spheres():
    v, f, n_first = two_spheres(1.5)
    pairs = intersecting_pairs(v, f)
    assert pairs.shape[0] > 0
    assert (pairs[:, 0] < n_first).all() and (pairs[:, 1] >= n_first).all()
    order = np.lexsort((pairs[:, 1].numpy(), pairs[:, 0].numpy()))
    assert (order == np.arange(len(order))).all()
    a, b = v[f[pairs[:, 0]]], v[f[pairs[:, 1]]]
    assert triangles_intersect(a, b).all()
    v, f, _ = two_spheres(2.5)
    assert intersecting_pairs(v, f).shape == (0, 2)


@pytest.fixture(scope="module")
def body():
    from unibody.body import BodyLayer

    layer = BodyLayer.from_pca(num_components=10, dtype=torch.float64)
    return layer, layer.prepare_identity(torch.zeros(1, 10, dtype=torch.float64))


def test_canonical_rest_mesh_has_no_self_intersections(rig):
    assert intersecting_pairs(rig.bind_vertices, rig.faces).shape == (0, 2)


def test_folded_elbow_intersects(body):
    from unibody.rig import joint_index

    layer, identity = body
    elbow = joint_index("LeftForeArm")

    def pairs_near_elbow(flex: float) -> int:
        pose = torch.zeros(1, 77, 3, dtype=torch.float64)
        pose[0, elbow - 1, 1] = flex  # about Y: negative flexes the left forearm
        out = layer.pose(identity, pose)
        vertices = out.vertices[0]
        pairs = intersecting_pairs(vertices, layer.faces)
        centres = vertices[layer.faces].mean(1)[pairs].mean(1)
        return int(((centres - out.joints[0, elbow]).norm(dim=-1) < 0.12).sum())

    assert pairs_near_elbow(0.0) == 0
    assert pairs_near_elbow(-2.6) > 0


def test_bad_inputs():
    v, f = sphere(0)
    with pytest.raises(ValueError, match=r"vertices: expected shape \(V, 3\), got \(5, 2\)"):
        intersecting_pairs(torch.zeros(5, 2), f)
    with pytest.raises(ValueError, match="faces: expected shape"):
        intersecting_pairs(v, f[:, :2])
    with pytest.raises(ValueError, match="faces: expected indices"):
        intersecting_pairs(v, f + 1)
    nan = v.clone()
    nan[3, 1] = float("nan")
    with pytest.raises(ValueError, match="vertices: expected finite"):
        intersecting_pairs(nan, f)
    with pytest.raises(TypeError, match="faces: expected an integer"):
        intersecting_pairs(v, f.double())
    tri = torch.zeros(4, 3, 3)
    with pytest.raises(ValueError, match=r"a: expected shape \(N, 3, 3\)"):
        triangles_intersect(torch.zeros(4, 3, 2), tri)
    with pytest.raises(ValueError, match=r"b: expected shape \(N, 3, 3\) with N=4, got \(5, 3, 3\)"):
        triangles_intersect(tri, torch.zeros(5, 3, 3))
    bad = tri.clone()
    bad[0, 0, 0] = float("inf")
    with pytest.raises(ValueError, match="b: expected finite"):
        triangles_intersect(tri, bad)
