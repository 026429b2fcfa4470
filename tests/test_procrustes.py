"""Procrustes solvers: the closest rotation, three ways, against a brute-force reference."""

from __future__ import annotations

import pytest
import torch

from unibody.geometry.procrustes import kabsch, newton_schulz, polar, polar_svd
from unibody.geometry.rotations import axis_angle_to_matrix


def _cases(dtype):
    gen = torch.Generator().manual_seed(0)
    h = torch.randn(400, 3, 3, generator=gen, dtype=dtype)  # about half have det < 0
    planar = torch.randn(20, 3, 3, generator=gen, dtype=dtype)
    planar[..., 2] = 0  # rank 2: coplanar point sets
    return torch.cat([h, planar, torch.zeros(1, 3, 3, dtype=dtype)])


def _is_rotation(r, tol):
    eye = torch.eye(3, dtype=r.dtype)
    return ((r.transpose(-1, -2) @ r - eye).abs().amax((-1, -2)) < tol) & ((torch.det(r) - 1).abs() < tol)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_polar_matches_svd_and_is_optimal(dtype):
    h = _cases(dtype)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    fast, ref = polar(h), polar_svd(h)
    assert _is_rotation(fast, 10 * tol).all() and _is_rotation(ref, 10 * tol).all()
    full = torch.linalg.matrix_rank(h.double()) == 3
    assert (fast - ref)[full].abs().max() < 100 * tol
    # Optimality: no nearby rotation gives a larger trace(R^T H) (the Procrustes objective).
    gen = torch.Generator().manual_seed(1)
    for _ in range(5):
        nudge = axis_angle_to_matrix(1e-2 * torch.randn(h.shape[0], 3, generator=gen, dtype=dtype))
        score = lambda r: (r * h).sum((-1, -2))  # noqa: E731
        assert (score(fast @ nudge) <= score(fast) + 10 * tol).all()


def test_polar_gradients():
    h = torch.randn(6, 3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    h = h * torch.det(h).sign()[:, None, None]  # det > 0: the Newton path
    assert torch.autograd.gradcheck(polar, (h.requires_grad_(),))
    (g,) = torch.autograd.grad(polar(-h).sum(), h)  # det < 0: the SVD fallback
    assert torch.isfinite(g).all()


def test_kabsch_recovers_a_rotation_and_newton_schulz_agrees():
    gen = torch.Generator().manual_seed(3)
    a = torch.randn(8, 50, 3, generator=gen, dtype=torch.float64)
    r = axis_angle_to_matrix(torch.randn(8, 3, generator=gen, dtype=torch.float64))
    b = a @ r.transpose(-1, -2)
    assert (kabsch(a, b) - r).abs().max() < 1e-12
    h = b.transpose(-1, -2) @ a
    assert (newton_schulz(h, iters=40) - r).abs().max() < 1e-10
