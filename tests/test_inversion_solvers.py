"""Inversion solver internals: the structured Gauss-Newton normal equations, the scaled
Newton-Schulz polar factor, accuracy bounds of the presets on the random protocol (0.3 rad std
on every joint) and vertex-major input."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from unibody.fitting._gauss_newton import articulated_jacobian, gauss_newton_data, normal_equations
from unibody.fitting.inversion import PRESETS, PoseInverter, _newton_schulz_scaled
from unibody.geometry.procrustes import polar_svd
from unibody.geometry.rotations import axis_angle_to_matrix


def test_normal_equations_match_dense_jacobian(anny_layer64):
    data = gauss_newton_data(anny_layer64, 200)
    d = {k: getattr(data, k) for k in data.__dataclass_fields__}
    n, s = d["verts"].numel(), d["joints"].numel()
    gen = torch.Generator().manual_seed(3)
    q = torch.randn(2, d["pair_slot"].numel(), 3, generator=gen, dtype=torch.float64)
    r = torch.randn(2, n, 3, generator=gen, dtype=torch.float64)
    jac = articulated_jacobian(q, d["pair_vertex"], d["pair_slot"], n, s).reshape(2, 3 * n, 3 + 3 * s)
    jtj, rhs = normal_equations(d, q, r, s)
    torch.testing.assert_close(jtj, jac.mT @ jac, rtol=1e-12, atol=1e-10)
    torch.testing.assert_close(rhs, jac.mT @ r.reshape(2, 3 * n, 1), rtol=1e-12, atol=1e-10)


def test_scaled_newton_schulz_is_the_polar_factor():
    """Damped cross-covariances (condition up to ~1/lambda) reach the SVD polar factor in 9 + 2 steps."""
    gen = torch.Generator().manual_seed(4)
    lam = 3e-3
    pts = torch.randn(64, 50, 3, generator=gen, dtype=torch.float64)
    pts = pts * torch.tensor([1.0, 0.3, 1e-4], dtype=torch.float64)  # some nearly flat sets
    cov = pts.mT @ pts
    cov = cov + lam * cov.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None] * torch.eye(3, dtype=torch.float64)
    h = axis_angle_to_matrix(torch.randn(64, 3, generator=gen, dtype=torch.float64)) @ cov
    lower = lam / (3**0.5 * (1 + lam))
    x = _newton_schulz_scaled(_newton_schulz_scaled(h, 9, lower), 2)
    assert (x - polar_svd(h)).abs().max() < 1e-9
    near = x + 1e-4 * torch.randn(64, 3, 3, generator=gen, dtype=torch.float64)
    polished = _newton_schulz_scaled(near, 2)
    assert (polished.mT @ polished - torch.eye(3, dtype=torch.float64)).abs().max() < 1e-12


@pytest.fixture(scope="module")
def random_protocol(anny_layer64):
    layer = anny_layer64
    gen = torch.Generator().manual_seed(0)
    prepared = layer.prepare_identity(torch.rand(1, 6, generator=gen, dtype=torch.float64))
    pose = 0.3 * torch.randn(4, 77, 3, generator=gen, dtype=torch.float64)
    transl = 0.1 * torch.randn(4, 3, generator=gen, dtype=torch.float64)
    with torch.no_grad():
        target = layer.pose(prepared, pose, transl=transl).vertices
    return layer, prepared, target


# Bounds the solvers met before the speed work too (mean mm, these 4 frames: analytic 2.85 / refined
# 0.176 then, 2.85 / 0.175 now).
@pytest.mark.parametrize(("preset", "mean_mm"), [("analytic", 3.0), ("refined", 0.25)])
def test_random_protocol_accuracy(random_protocol, preset, mean_mm):
    layer, prepared, target = random_protocol
    with torch.no_grad():
        result = PoseInverter(layer, PRESETS[preset]).invert(target, prepared)
    assert float(result.per_vertex_error.mean()) * 1e3 < mean_mm


def test_vertex_major_input_gives_the_same_pose(random_protocol):
    """BodyLayer's meshes are (V, B, 3) buffers seen as (B, V, 3): the inverter copies them once."""
    layer, prepared, target = random_protocol
    assert not target.is_contiguous()  # the case this covers; a contiguous output makes it trivial
    inv = PoseInverter(layer, PRESETS["analytic"])
    with torch.no_grad():
        a, b = inv.invert(target, prepared), inv.invert(target.contiguous(), prepared)
    assert torch.equal(a.rotations, b.rotations) and torch.equal(a.transl, b.transl)


def test_block_sums_match_the_per_vertex_sums(random_protocol):
    """Each level sums q r^T over its joints' vertices as one batched product when every joint has
    as many (the canonical rig at any vertices_per_joint cap it reaches), else vertex by vertex:
    both give the same pose."""
    layer, prepared, target = random_protocol
    blocked = PoseInverter(layer, PRESETS["analytic"])
    assert all(lv.block == 128 for scope in blocked._levels.values() for lv in scope)
    per_vertex = PoseInverter(layer, PRESETS["analytic"])
    per_vertex._levels = {k: [lv._replace(block=0) for lv in v] for k, v in per_vertex._levels.items()}
    with torch.no_grad():
        a, b = blocked.invert(target, prepared), per_vertex.invert(target, prepared)
    assert (a.rotations - b.rotations).abs().max() < 1e-10
    assert (a.transl - b.transl).abs().max() < 1e-12
    # A cap no joint reaches leaves the joints' counts unequal: the per-vertex sums serve.
    uncapped = PoseInverter(layer, dataclasses.replace(PRESETS["analytic"], vertices_per_joint=100_000))
    assert any(lv.block == 0 for lv in uncapped._levels["full"])
    with torch.no_grad():
        assert float(uncapped.invert(target, prepared).per_vertex_error.mean()) * 1e3 < 3.0


def test_gather_reads_either_layout():
    """_gather takes rows of a vertex-major mesh and columns of a batch-major one alike."""
    from unibody.fitting.inversion import _gather

    mesh = torch.randn(5, 40, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    index = torch.tensor([7, 0, 39, 7])
    vertex_major = mesh.transpose(0, 1).contiguous().transpose(0, 1)
    assert vertex_major.stride(0) < vertex_major.stride(1)
    for m in (mesh, vertex_major):
        assert torch.equal(_gather(m, index), mesh[:, index])
