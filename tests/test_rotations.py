"""Invariants of unibody.geometry.rotations: rotations are rotations, round trips close,
corner angles (0, tiny, near pi, pi) stay finite and exact, gradients are finite."""

from __future__ import annotations

import math

import pytest
import torch

from unibody.geometry import rotations as rot

DTYPES = [torch.float32, torch.float64]
# Well-conditioned comparisons (entries of unit-scale matrices). float32 gets a few ulps
# of headroom over eps because every conversion chains ~10 rounding steps.
TOL = {torch.float32: 1e-5, torch.float64: 1e-10}
# shortest_arc 1e-3 rad from antiparallel: the axis comes from a cross product of size
# 1e-3, so errors scale like eps / 1e-3 (measured 4e-5 in float32, 6e-14 in float64).
TOL_ILL = {torch.float32: 1e-4, torch.float64: 1e-12}
CORNER_ANGLES = [0.0, 1e-7, math.pi - 1e-6, math.pi]


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def unit(n: int, dtype: torch.dtype, seed: int) -> torch.Tensor:
    v = torch.randn(n, 3, generator=gen(seed), dtype=torch.float64)
    return (v / v.norm(dim=-1, keepdim=True)).to(dtype)


def rand_aa(n: int, dtype: torch.dtype, seed: int, max_angle: float = math.pi) -> torch.Tensor:
    angle = torch.rand(n, 1, generator=gen(seed + 1), dtype=torch.float64) * max_angle
    return (unit(n, torch.float64, seed) * angle).to(dtype)


def rand_quat(n: int, dtype: torch.dtype, seed: int) -> torch.Tensor:
    q = torch.randn(n, 4, generator=gen(seed), dtype=torch.float64)
    return (q / q.norm(dim=-1, keepdim=True)).to(dtype)


def rand_R(n: int, dtype: torch.dtype, seed: int) -> torch.Tensor:
    return rot.quat_xyzw_to_matrix(rand_quat(n, torch.float64, seed)).to(dtype)


def skew(v: torch.Tensor) -> torch.Tensor:
    K = v.new_zeros(*v.shape[:-1], 3, 3)
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    return K - K.transpose(-1, -2)


def expm_aa(aa: torch.Tensor) -> torch.Tensor:
    """Independent reference: exp([aa]_x) in float64."""
    return torch.linalg.matrix_exp(skew(aa.double()))


def geodesic(R1: torch.Tensor, R2: torch.Tensor) -> torch.Tensor:
    """Frobenius distance, robust reference that does not use the module under test."""
    return (R1.double() - R2.double()).flatten(-2).norm(dim=-1)


def assert_rotation(R: torch.Tensor, tol: float) -> None:
    assert torch.isfinite(R).all()
    eye = torch.eye(3, dtype=R.dtype).expand_as(R)
    torch.testing.assert_close(R.transpose(-1, -2) @ R, eye, atol=tol, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(R.shape[:-2], dtype=R.dtype), atol=tol, rtol=0)


def corner_aa(dtype: torch.dtype) -> torch.Tensor:
    axes = torch.cat([torch.eye(3, dtype=torch.float64), unit(5, torch.float64, 7)])
    aa = torch.stack([axes * a for a in CORNER_ANGLES]).reshape(-1, 3)
    return aa.to(dtype)


# ----------------------------------------------------------------- rotations
@pytest.mark.parametrize("dtype", DTYPES)
def test_every_to_matrix_returns_rotations(dtype):
    tol = TOL[dtype]
    g = gen(3)
    assert_rotation(rot.axis_angle_to_matrix(rand_aa(64, dtype, 0, 3 * math.pi)), tol)
    assert_rotation(rot.quat_xyzw_to_matrix(3 * rand_quat(64, dtype, 1)), tol)
    assert_rotation(rot.rot6d_to_matrix(torch.randn(64, 6, generator=g, dtype=dtype)), tol)
    assert_rotation(rot.euler_xyz_to_matrix(4 * torch.randn(64, 3, generator=g, dtype=dtype)), tol)
    a, b = torch.randn(2, 64, 3, generator=g, dtype=dtype)
    assert_rotation(rot.shortest_arc(a, b), tol)
    assert_rotation(rot.orthonormalize(torch.randn(64, 3, 3, generator=g, dtype=dtype)), 10 * tol)
    assert_rotation(rot.swing_twist(rand_R(64, dtype, 4), unit(1, dtype, 5)[0])[0], tol)


@pytest.mark.parametrize("dtype", DTYPES)
def test_batch_dims_dtype_and_no_input_mutation(dtype):
    aa = rand_aa(6, dtype, 2).reshape(2, 3, 3)
    before = aa.clone()
    R = rot.axis_angle_to_matrix(aa)
    assert R.shape == (2, 3, 3, 3) and R.dtype == dtype
    assert rot.matrix_to_axis_angle(R).shape == (2, 3, 3)
    assert rot.matrix_to_quat_xyzw(R).shape == (2, 3, 4)
    assert rot.matrix_to_rot6d(R).shape == (2, 3, 6)
    assert rot.matrix_to_euler_xyz(R).shape == (2, 3, 3)
    assert rot.rotation_angle(R).shape == (2, 3)
    swing, angle = rot.swing_twist(R, torch.tensor([0.0, 1.0, 0.0], dtype=dtype))
    assert swing.shape == (2, 3, 3, 3) and angle.shape == (2, 3) and angle.dtype == dtype
    assert torch.equal(aa, before)


@pytest.mark.parametrize("dtype", DTYPES)
def test_axis_angle_matches_matrix_exp(dtype):
    aa = torch.cat([rand_aa(64, dtype, 10, 3 * math.pi), corner_aa(dtype)])
    torch.testing.assert_close(rot.axis_angle_to_matrix(aa).double(), expm_aa(aa), atol=TOL[dtype], rtol=0)


def test_taylor_branches_are_accurate_to_eps():
    # Just below the series cutoff (t^2 < eps^(1/3) = 6e-6) a truncated series would
    # show up at the 1e-13 level; exact formulas agree with expm to ~1e-16.
    aa = unit(4, torch.float64, 41)[:, None, :] * torch.tensor([1e-4, 1e-3, 2.4e-3], dtype=torch.float64)[:, None]
    aa = aa.reshape(-1, 3)
    torch.testing.assert_close(rot.axis_angle_to_matrix(aa), expm_aa(aa), atol=1e-15, rtol=0)
    q = rot.axis_angle_to_quat_xyzw(aa)
    torch.testing.assert_close(rot.quat_xyzw_to_axis_angle(q), aa, atol=1e-17, rtol=1e-14)
    ref = torch.cat(
        [
            aa / aa.norm(dim=-1, keepdim=True) * torch.sin(aa.norm(dim=-1, keepdim=True) / 2),
            torch.cos(aa.norm(dim=-1, keepdim=True) / 2),
        ],
        -1,
    )
    torch.testing.assert_close(q, ref, atol=4e-16, rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_axis_angle_round_trip(dtype):
    aa = rand_aa(256, dtype, 11)
    R = rot.axis_angle_to_matrix(aa)
    back = rot.matrix_to_axis_angle(R)
    assert (back.norm(dim=-1) <= math.pi + TOL[dtype]).all()
    assert geodesic(rot.axis_angle_to_matrix(back), R).max() < TOL[dtype]
    ok = aa.norm(dim=-1) < math.pi - 1e-3
    torch.testing.assert_close(back[ok], aa[ok], atol=TOL[dtype], rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_axis_angle_corner_angles(dtype):
    aa = corner_aa(dtype)
    R = rot.axis_angle_to_matrix(aa)
    back = rot.matrix_to_axis_angle(R)
    assert torch.isfinite(R).all() and torch.isfinite(back).all()
    assert geodesic(rot.axis_angle_to_matrix(back), R).max() < 2 * TOL[dtype]
    angle = back.norm(dim=-1).double()
    torch.testing.assert_close(angle, aa.double().norm(dim=-1), atol=2 * TOL[dtype], rtol=0)
    # Exactly pi from an exact half-turn matrix 2nn^T - I (skew part is exactly zero).
    n = unit(8, torch.float64, 12)
    half = (2 * n[:, :, None] * n[:, None, :] - torch.eye(3, dtype=torch.float64)).to(dtype)
    back = rot.matrix_to_axis_angle(half)
    torch.testing.assert_close(
        back.norm(dim=-1).double(), torch.full((8,), math.pi, dtype=torch.float64), atol=TOL[dtype], rtol=0
    )
    assert geodesic(rot.axis_angle_to_matrix(back), half).max() < 2 * TOL[dtype]


@pytest.mark.parametrize("dtype", DTYPES)
def test_quat_round_trips(dtype):
    q = rand_quat(256, dtype, 13)
    R = rot.quat_xyzw_to_matrix(q)
    back = rot.matrix_to_quat_xyzw(R)
    assert (back[:, 3] >= 0).all()
    sign = torch.where(q[:, 3:] < 0, -1.0, 1.0).to(dtype)
    torch.testing.assert_close(back, q * sign, atol=TOL[dtype], rtol=0)
    Rs = rand_R(256, dtype, 14)
    torch.testing.assert_close(rot.quat_xyzw_to_matrix(rot.matrix_to_quat_xyzw(Rs)), Rs, atol=TOL[dtype], rtol=0)
    aa = rand_aa(64, dtype, 15)
    torch.testing.assert_close(
        rot.quat_xyzw_to_axis_angle(rot.axis_angle_to_quat_xyzw(aa)), aa, atol=TOL[dtype], rtol=0
    )
    torch.testing.assert_close(
        rot.quat_xyzw_to_matrix(rot.axis_angle_to_quat_xyzw(aa)), rot.axis_angle_to_matrix(aa), atol=TOL[dtype], rtol=0
    )


@pytest.mark.parametrize("dtype", DTYPES)
def test_quat_multiply_and_conjugate(dtype):
    q1, q2 = rand_quat(32, dtype, 16), rand_quat(32, dtype, 17)
    R = rot.quat_xyzw_to_matrix(rot.quat_xyzw_multiply(q1, q2))
    torch.testing.assert_close(R, rot.quat_xyzw_to_matrix(q1) @ rot.quat_xyzw_to_matrix(q2), atol=TOL[dtype], rtol=0)
    ident = rot.quat_xyzw_multiply(q1, rot.quat_xyzw_conjugate(q1))
    torch.testing.assert_close(ident, torch.tensor([0.0, 0, 0, 1], dtype=dtype).expand(32, 4), atol=TOL[dtype], rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_rot6d_round_trips(dtype):
    R = rand_R(64, dtype, 18)
    torch.testing.assert_close(rot.rot6d_to_matrix(rot.matrix_to_rot6d(R)), R, atol=TOL[dtype], rtol=0)
    x = torch.randn(64, 6, generator=gen(19), dtype=dtype)
    once = rot.matrix_to_rot6d(rot.rot6d_to_matrix(x))
    torch.testing.assert_close(rot.matrix_to_rot6d(rot.rot6d_to_matrix(once)), once, atol=TOL[dtype], rtol=0)
    # The first column is the normalized first half: Gram-Schmidt keeps its direction.
    torch.testing.assert_close(once[:, :3], x[:, :3] / x[:, :3].norm(dim=-1, keepdim=True), atol=TOL[dtype], rtol=0)


def elementary(angle: torch.Tensor, i: int) -> torch.Tensor:
    c, s = torch.cos(angle), torch.sin(angle)
    R = torch.eye(3, dtype=angle.dtype).repeat(*angle.shape, 1, 1)
    j, k = [(1, 2), (2, 0), (0, 1)][i]
    R[..., j, j], R[..., j, k], R[..., k, j], R[..., k, k] = c, -s, s, c
    return R


@pytest.mark.parametrize("dtype", DTYPES)
def test_euler_xyz(dtype):
    ang = torch.randn(128, 3, generator=gen(20), dtype=dtype)
    ang[:, 1] = ang[:, 1].clamp(-1.5, 1.5)
    ang[:, [0, 2]] = torch.remainder(ang[:, [0, 2]] + math.pi, 2 * math.pi) - math.pi
    R = rot.euler_xyz_to_matrix(ang)
    ref = elementary(ang[:, 0], 0) @ elementary(ang[:, 1], 1) @ elementary(ang[:, 2], 2)
    torch.testing.assert_close(R, ref, atol=TOL[dtype], rtol=0)
    torch.testing.assert_close(rot.matrix_to_euler_xyz(R), ang, atol=20 * TOL[dtype], rtol=0)
    Rs = rand_R(128, dtype, 21)
    torch.testing.assert_close(rot.euler_xyz_to_matrix(rot.matrix_to_euler_xyz(Rs)), Rs, atol=TOL[dtype], rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("b", [math.pi / 2, -math.pi / 2])
def test_euler_gimbal_lock(dtype, b):
    ang = torch.tensor([[0.3, b, -1.1], [-2.0, b, 0.4]], dtype=dtype)
    R = rot.euler_xyz_to_matrix(ang)
    back = rot.matrix_to_euler_xyz(R)
    assert torch.isfinite(back).all()
    torch.testing.assert_close(back[:, 0], torch.zeros(2, dtype=dtype))
    torch.testing.assert_close(rot.euler_xyz_to_matrix(back), R, atol=TOL[dtype], rtol=0)


# ------------------------------------------------------------ decompositions
def twist_matrix(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    return expm_aa(axis.double() * angle.double()[..., None]).to(angle.dtype)


@pytest.mark.parametrize("dtype", DTYPES)
def test_swing_twist_recomposes_with_perpendicular_swing(dtype):
    R = rand_R(128, dtype, 22)
    axis = unit(1, dtype, 23)[0]
    swing, angle = rot.swing_twist(R, axis)
    assert ((angle > -math.pi) & (angle <= math.pi)).all()
    torch.testing.assert_close(swing @ twist_matrix(axis, angle), R, atol=TOL[dtype], rtol=0)
    swing_axis = rot.matrix_to_axis_angle(swing)
    assert ((swing_axis @ axis).abs() < 10 * TOL[dtype]).all()
    # Per-sample axes broadcast too.
    axes = unit(128, dtype, 24)
    swing, angle = rot.swing_twist(R, axes)
    torch.testing.assert_close(swing @ twist_matrix(axes, angle), R, atol=TOL[dtype], rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_swing_twist_pure_twist_and_degenerate(dtype):
    axis = unit(1, dtype, 25)[0]
    angles = torch.tensor([0.0, 0.5, -2.0, 3.0, math.pi - 1e-3, math.pi], dtype=dtype)
    swing, angle = rot.swing_twist(twist_matrix(axis, angles), axis)
    torch.testing.assert_close(swing, torch.eye(3, dtype=dtype).expand(6, 3, 3), atol=TOL[dtype], rtol=0)
    # Compare modulo 2 pi: float32(pi) exceeds pi, so its canonical twist is near -pi.
    wrapped = torch.remainder(angle.double() - angles.double() + math.pi, 2 * math.pi) - math.pi
    assert wrapped.abs().max() < 20 * TOL[dtype]
    # A half-turn about a perpendicular axis has no defined twist: angle 0, swing = R.
    perp = torch.linalg.cross(axis, unit(1, dtype, 26)[0], dim=-1)
    R = rot.axis_angle_to_matrix(math.pi * perp / perp.norm())
    swing, angle = rot.swing_twist(R, axis)
    assert angle.item() == 0.0 and torch.isfinite(swing).all()
    torch.testing.assert_close(swing, R)
    # An exact half-turn twist (w == 0) is reported as +pi, never -pi, for either axis sign.
    half = 2 * axis[:, None] * axis[None, :] - torch.eye(3, dtype=dtype)
    for sign in (1.0, -1.0):
        swing, angle = rot.swing_twist(half, sign * axis)
        assert angle.item() == pytest.approx(math.pi, abs=TOL[dtype])
        torch.testing.assert_close(swing, torch.eye(3, dtype=dtype), atol=TOL[dtype], rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_shortest_arc(dtype):
    g = gen(27)
    a = torch.randn(64, 3, generator=g, dtype=dtype) * 3
    b = torch.randn(64, 3, generator=g, dtype=dtype) * 0.5
    R = rot.shortest_arc(a, b)
    u, v = a / a.norm(dim=-1, keepdim=True), b / b.norm(dim=-1, keepdim=True)
    torch.testing.assert_close((R @ u[..., None])[..., 0], v, atol=TOL[dtype], rtol=0)
    # Minimal: angle is the angle between the directions, axis along a x b.
    torch.testing.assert_close(rot.rotation_angle(R), torch.acos((u * v).sum(-1).clamp(-1, 1)), atol=1e-3, rtol=0)
    aa = rot.matrix_to_axis_angle(R)
    assert ((aa * u).sum(-1).abs() < 10 * TOL[dtype]).all() and ((aa * v).sum(-1).abs() < 10 * TOL[dtype]).all()
    eye = torch.eye(3, dtype=dtype).expand(64, 3, 3)
    torch.testing.assert_close(rot.shortest_arc(a, 2 * a), eye, atol=TOL[dtype], rtol=0)
    anti = rot.shortest_arc(a, -0.1 * a)
    assert_rotation(anti, TOL[dtype])
    torch.testing.assert_close((anti @ u[..., None])[..., 0], -u, atol=TOL[dtype], rtol=0)
    torch.testing.assert_close(
        rot.rotation_angle(anti), torch.full((64,), math.pi, dtype=dtype), atol=TOL[dtype], rtol=0
    )
    # Deterministic axis for exact antiparallel: e_x x e_y (e_y: first most perpendicular) = e_z.
    ex = torch.tensor([[2.0, 0.0, 0.0]], dtype=dtype)
    torch.testing.assert_close(rot.shortest_arc(ex, -ex)[0], torch.diag(torch.tensor([-1.0, -1.0, 1.0], dtype=dtype)))
    # Nearly antiparallel (1e-3 rad off) still maps u to v on the regular branch.
    perp = torch.linalg.cross(u, unit(64, dtype, 40), dim=-1)
    near = -u + 1e-3 * perp / perp.norm(dim=-1, keepdim=True)
    vn = near / near.norm(dim=-1, keepdim=True)
    torch.testing.assert_close((rot.shortest_arc(a, near) @ u[..., None])[..., 0], vn, atol=TOL_ILL[dtype], rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_rotation_angle(dtype):
    aa = torch.cat([rand_aa(64, dtype, 28), corner_aa(dtype)])
    angle = rot.rotation_angle(rot.axis_angle_to_matrix(aa))
    torch.testing.assert_close(angle, aa.norm(dim=-1), atol=2 * TOL[dtype], rtol=0)
    # atan2 keeps relative accuracy for tiny angles where acos(trace) would return 0.
    tiny = rot.rotation_angle(rot.axis_angle_to_matrix(torch.tensor([[0.0, 1e-7, 0.0]], dtype=dtype)))
    torch.testing.assert_close(tiny, torch.tensor([1e-7], dtype=dtype), atol=0, rtol=1e-6)


@pytest.mark.parametrize("dtype", DTYPES)
def test_orthonormalize(dtype):
    R = rand_R(32, dtype, 29)
    torch.testing.assert_close(rot.orthonormalize(R), R, atol=10 * TOL[dtype], rtol=0)
    noisy = R + 1e-3 * torch.randn(32, 3, 3, generator=gen(30), dtype=dtype)
    assert geodesic(rot.orthonormalize(noisy), R).max() < 1e-2
    reflection = -R  # det -1: the nearest rotation must still have det +1
    assert_rotation(rot.orthonormalize(reflection), 10 * TOL[dtype])
    # One nearest rotation in the package: the public name is procrustes.polar_svd.
    from unibody.geometry.procrustes import polar_svd

    torch.testing.assert_close(rot.orthonormalize(noisy), polar_svd(noisy), atol=0, rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_skew_is_the_cross_product_matrix(dtype):
    g = gen(32)
    v = torch.randn(4, 5, 3, generator=g, dtype=dtype)
    u = torch.randn(4, 5, 3, generator=g, dtype=dtype)
    K = rot.skew(v)
    assert K.shape == (4, 5, 3, 3) and K.dtype == dtype
    torch.testing.assert_close(K, -K.transpose(-1, -2), atol=0, rtol=0)
    torch.testing.assert_close((K @ u[..., None])[..., 0], torch.linalg.cross(v, u))
    torch.testing.assert_close(K, skew(v), atol=0, rtol=0)


# ------------------------------------------------------------------ gradients
def grad_of(fn, x: torch.Tensor) -> torch.Tensor:
    x = x.clone().requires_grad_(True)
    w = torch.randn(fn(x.detach()).shape, generator=gen(31), dtype=x.dtype)
    (fn(x) * w).sum().backward()
    return x.grad


@pytest.mark.parametrize("dtype", DTYPES)
def test_gradients_finite_at_singular_points(dtype):
    zero = torch.zeros(2, 3, dtype=dtype)
    assert torch.isfinite(grad_of(rot.axis_angle_to_matrix, zero)).all()
    assert torch.isfinite(grad_of(rot.axis_angle_to_quat_xyzw, zero)).all()
    eye = torch.eye(3, dtype=dtype).repeat(2, 1, 1)
    assert torch.isfinite(grad_of(rot.matrix_to_axis_angle, eye)).all()
    assert torch.isfinite(grad_of(rot.rotation_angle, eye)).all()
    assert torch.isfinite(grad_of(rot.matrix_to_euler_xyz, eye)).all()
    half = rot.axis_angle_to_matrix(torch.tensor([[0.0, math.pi, 0.0], [0.6, 0.0, 0.8]], dtype=dtype) * math.pi)
    assert torch.isfinite(grad_of(rot.matrix_to_axis_angle, half)).all()
    gimbal = rot.euler_xyz_to_matrix(torch.tensor([[0.3, math.pi / 2, 0.2]], dtype=dtype))
    assert torch.isfinite(grad_of(rot.matrix_to_euler_xyz, gimbal)).all()
    a = torch.tensor([[1.0, 2.0, 3.0]], dtype=dtype)
    assert torch.isfinite(grad_of(lambda x: rot.shortest_arc(x, 2 * a), a)).all()
    assert torch.isfinite(grad_of(lambda x: rot.shortest_arc(x, -a), a)).all()
    R = rot.axis_angle_to_matrix(torch.tensor([[0.0, 0.0, math.pi]], dtype=dtype))
    assert torch.isfinite(grad_of(lambda m: rot.swing_twist(m, torch.tensor([1.0, 0, 0], dtype=dtype))[0], R)).all()


def test_axis_angle_gradient_at_zero_is_the_generator():
    # dR/d(aa_k) at 0 is the skew generator of axis k.
    zero = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    jac = torch.autograd.functional.jacobian(rot.axis_angle_to_matrix, zero)
    torch.testing.assert_close(jac.permute(2, 0, 1), skew(torch.eye(3, dtype=torch.float64)))


def test_gradcheck():
    g = gen(32)
    f64 = {"dtype": torch.float64}

    def leaf(x: torch.Tensor) -> torch.Tensor:
        return x.detach().requires_grad_(True)

    aa = torch.cat([torch.zeros(1, 3, **f64), 1e-5 * torch.ones(1, 3, **f64), rand_aa(3, torch.float64, 33)])
    assert torch.autograd.gradcheck(rot.axis_angle_to_matrix, (leaf(aa),))
    assert torch.autograd.gradcheck(rot.axis_angle_to_quat_xyzw, (leaf(aa),))
    # Generic angles; the input is a free 3x3 matrix, so the check covers off-manifold directions.
    R = rot.axis_angle_to_matrix(torch.cat([rand_aa(3, torch.float64, 34, 2.5), torch.full((1, 3), 1e-3, **f64)]))
    assert torch.autograd.gradcheck(rot.matrix_to_axis_angle, (leaf(R),))
    assert torch.autograd.gradcheck(rot.matrix_to_quat_xyzw, (leaf(R),))
    assert torch.autograd.gradcheck(rot.matrix_to_euler_xyz, (leaf(R),))
    assert torch.autograd.gradcheck(rot.rotation_angle, (leaf(R),))
    axis = unit(1, torch.float64, 37)[0]
    assert torch.autograd.gradcheck(lambda m: rot.swing_twist(m, axis), (leaf(R),))
    assert torch.autograd.gradcheck(rot.quat_xyzw_to_axis_angle, (leaf(rand_quat(3, torch.float64, 35)),))
    assert torch.autograd.gradcheck(rot.rot6d_to_matrix, (leaf(torch.randn(3, 6, generator=g, **f64)),))
    assert torch.autograd.gradcheck(rot.quat_xyzw_to_matrix, (leaf(2 * rand_quat(3, torch.float64, 36)),))
    assert torch.autograd.gradcheck(rot.euler_xyz_to_matrix, (leaf(torch.randn(3, 3, generator=g, **f64)),))
    a, b = torch.randn(2, 3, 3, generator=g, **f64)
    b = torch.cat([b[:2], 3 * a[2:]])  # include a parallel pair
    assert torch.autograd.gradcheck(rot.shortest_arc, (leaf(a), leaf(b)))


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("angle", [1e5, 1e20, 3e38])
def test_huge_axis_angle_is_finite_and_exact(dtype, angle):
    """|aa|^2 overflowed (NaN for 1e20 in float32); sin/cos reduce the angle modulo 2 pi exactly."""
    if angle > torch.finfo(dtype).max:
        pytest.skip("not representable")
    theta = torch.tensor(angle, dtype=dtype)
    c, s = math.cos(float(theta)), math.sin(float(theta))
    for axis in range(3):
        aa = torch.zeros(2, 3, dtype=dtype)
        aa[0, axis], aa[1, axis] = theta, -theta
        R = rot.axis_angle_to_matrix(aa)
        q = rot.axis_angle_to_quat_xyzw(aa)
        assert torch.isfinite(R).all() and torch.isfinite(q).all()
        i, j = (axis + 1) % 3, (axis + 2) % 3  # cyclic: R[j, i] = sin
        ref = torch.eye(3, dtype=torch.float64)
        ref[i, i] = ref[j, j] = c
        ref[j, i], ref[i, j] = s, -s
        assert (R[0].double() - ref).abs().max() < TOL[dtype]
        assert (R[1].double() - ref.T).abs().max() < TOL[dtype]
        assert (rot.quat_xyzw_to_matrix(q).double() - R.double()).abs().max() < 10 * TOL[dtype]
    big = torch.full((4, 3), angle, dtype=dtype) * torch.tensor([[1.0], [-1.0], [0.5], [0.25]], dtype=dtype)
    R = rot.axis_angle_to_matrix(big)
    assert torch.isfinite(R).all()
    eye = torch.eye(3, dtype=dtype)
    assert (R.transpose(-1, -2) @ R - eye).abs().max() < 10 * TOL[dtype]


def test_huge_axis_angle_gradient_is_finite():
    aa = torch.tensor([[1e20, -3e19, 2e19], [0.0, 0.0, 0.0], [1e-9, 0.0, 0.0]], requires_grad=True)
    rot.axis_angle_to_matrix(aa).sum().backward()
    assert torch.isfinite(aa.grad).all()
