"""Rotation conversions and utilities: the one rotations module of ``unibody``.

Conventions, shared by every function here:

* Rotation matrices act on column vectors (``R @ v``); frames are right-handed.
* Angles are in radians.
* Quaternions are ordered **xyzw** (scalar last, as in roma and scipy); the order
  is spelled out in every quaternion function name. Unit quaternions are returned
  with ``w >= 0`` where a sign must be chosen.
* Axis-angle vectors are ``angle * unit_axis``.

All functions are pure torch, accept any leading batch dimensions ``(...)``,
follow the dtype and device of their input and never modify it. Gradients are
finite for every valid input (nonzero vectors and quaternions), including angle 0
and pi and exactly antiparallel directions: each singular expression is evaluated
on a *safe* argument selected with ``torch.where`` and replaced by a Taylor series
near the singular point, so neither branch produces inf/NaN in the backward pass.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from .procrustes import polar_svd

__all__ = [
    "axis_angle_to_matrix", "axis_angle_to_quat_xyzw", "euler_xyz_to_matrix",
    "matrix_to_axis_angle", "matrix_to_euler_xyz", "matrix_to_quat_xyzw", "matrix_to_rot6d",
    "orthonormalize", "quat_xyzw_conjugate", "quat_xyzw_multiply", "quat_xyzw_to_axis_angle",
    "quat_xyzw_to_matrix", "rot6d_to_matrix", "rotation_angle", "shortest_arc", "skew",
    "swing_twist",
]  # fmt: skip


def _safe_norm(v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Return ``(t, t2, small)`` for ``t = |v|`` over the last dim.

    ``t`` is replaced by 1 where ``small`` so sqrt and divisions by ``t`` have a
    finite gradient; ``t2`` is zeroed where not small so polynomials in it cannot
    overflow. Callers must select the Taylor branch with ``small``.
    """
    sq = (v * v).sum(-1)
    # Below t^2 = eps^(1/3) direct formulas lose ~eps/t^2 relative accuracy in their
    # derivatives, while the Taylor remainders (O(t^6)) stay below eps.
    small = sq < torch.finfo(v.dtype).eps ** (1.0 / 3.0)
    t = torch.sqrt(torch.where(small, torch.ones_like(sq), sq))
    return t, torch.where(small, sq, torch.zeros_like(sq)), small


def _angle_axis(aa: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`_safe_norm` of axis-angle vectors plus ``u = aa / t``, finite for any finite ``aa``.

    Where ``|aa|^2`` overflows (``|aa| > sqrt(float max)``, 1.8e19 in float32) the norm and
    the unit axis are recomputed from ``aa`` scaled by its largest component. An angle beyond
    the dtype's largest value (only with components within sqrt(3) of it) is clamped to it:
    still a rotation about the right axis.
    """
    t, t2, small = _safe_norm(aa)
    huge = torch.isinf(t)
    one = torch.ones_like(t)
    m = torch.where(huge, aa.abs().amax(-1), one)  # 1 where unused: no 0 / 0
    scaled = aa / m[..., None]
    # sqrt of a safe argument: 1 where unused, so a zero aa keeps a finite gradient.
    n = torch.sqrt(torch.where(huge, (scaled * scaled).sum(-1), one))
    t = torch.where(huge, (m * n).clamp_max(torch.finfo(aa.dtype).max), t)
    u = torch.where(huge[..., None], scaled / n[..., None], aa / t[..., None])
    return t, t2, small, u


def skew(v: torch.Tensor) -> torch.Tensor:
    """Cross-product matrix ``[v]_x`` with ``[v]_x @ u == v x u``.

    Args:
        v: Vectors, shape ``(..., 3)``.

    Returns:
        Skew-symmetric matrices, shape ``(..., 3, 3)``.
    """
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).unflatten(-1, (3, 3))


def axis_angle_to_matrix(aa: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula ``R = I + sin(t) U + (1 - cos t) U^2`` with ``U = [aa / t]_x``.

    Finite and correct for every finite input, however large: the axis is normalised
    before it is squared (no ``|aa|^2`` overflow), ``|aa|`` itself is computed without
    overflow, and ``sin``/``cos`` reduce the angle modulo 2 pi exactly (e.g. an angle of
    1e20 rad gives the rotation by ``1e20 mod 2 pi``); an angle beyond the dtype's largest
    value is clamped to it (see :func:`_angle_axis`). Near 0 the Taylor form
    ``I + a K + b K^2`` with ``K = [aa]_x`` is used instead (``U = K`` there, ``t := 1``).

    Args:
        aa: Axis-angle vectors, shape ``(..., 3)``.

    Returns:
        Rotation matrices, shape ``(..., 3, 3)``.
    """
    t, t2, small, u = _angle_axis(aa)
    x = t2 / 4
    # Near 0: a = sinc(t), b = (1 - cos t) / t^2 = sinc(t/2)^2 / 2 (Taylor, on K itself).
    # Elsewhere: sin t and 1 - cos t = 2 sin^2(t/2) (no cancellation), on the unit axis.
    a = torch.where(small, 1 - t2 / 6 + t2 * t2 / 120, torch.sin(t))
    half = torch.where(small, 1 - x / 6 + x * x / 120, torch.sin(t / 2))
    b = torch.where(small, 0.5, 2.0) * half * half
    # U^2 = u u^T - |u|^2 I (|u|^2 = 1 off the Taylor branch): elementwise, as a batched
    # matmul of 3x3 matrices costs ~0.15 us per product.
    sq = torch.where(small, t2, torch.ones_like(t2))
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device)
    outer = u[..., :, None] * u[..., None, :]
    return (1 - b * sq)[..., None, None] * eye + a[..., None, None] * skew(u) + b[..., None, None] * outer


def matrix_to_axis_angle(R: torch.Tensor) -> torch.Tensor:
    """Axis-angle of rotation matrices, angle in ``[0, pi]``.

    Goes through :func:`matrix_to_quat_xyzw`, which is well conditioned at every
    angle, including exactly pi where the skew part of ``R`` vanishes.

    Args:
        R: Rotation matrices, shape ``(..., 3, 3)``.

    Returns:
        Axis-angle vectors, shape ``(..., 3)``.
    """
    return quat_xyzw_to_axis_angle(matrix_to_quat_xyzw(R))


def axis_angle_to_quat_xyzw(aa: torch.Tensor) -> torch.Tensor:
    """Unit quaternion ``(sin(t/2) axis, cos(t/2))`` of axis-angle vectors.

    Args:
        aa: Axis-angle vectors, shape ``(..., 3)``.

    Returns:
        Quaternions xyzw, shape ``(..., 4)``.
    """
    t, t2, small, u = _angle_axis(aa)  # finite for any finite aa
    x = t2 / 4
    w = torch.where(small, 1 - x / 2 + x * x / 24, torch.cos(t / 2))
    # sin(t/2) on the unit axis (t := 1 near 0, where the Taylor sinc(t/2) / 2 applies).
    s = torch.where(small, 0.5 * (1 - x / 6 + x * x / 120), torch.sin(t / 2))
    return torch.cat([u * s[..., None], w[..., None]], -1)


def quat_xyzw_to_axis_angle(q: torch.Tensor) -> torch.Tensor:
    """Axis-angle of (not necessarily unit, nonzero) quaternions, angle in ``[0, pi]``.

    Args:
        q: Quaternions xyzw, shape ``(..., 4)``.

    Returns:
        Axis-angle vectors, shape ``(..., 3)``.
    """
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    q = torch.where(q[..., 3:] < 0, -q, q)  # q and -q are the same rotation
    v, w = q[..., :3], q[..., 3]
    s, s2, small = _safe_norm(v)
    # angle / s = 2 atan2(s, w) / s; near s = 0 use (2 / w) atan(r) / r with r = s / w.
    # There w ~ 1; the clamps only keep the unused series branch finite.
    r2 = s2 / (w * w).clamp_min(0.5)
    series = 2 / w.clamp_min(0.5) * (1 - r2 / 3 + r2 * r2 / 5)
    factor = torch.where(small, series, 2 * torch.atan2(s, w) / s)
    return v * factor[..., None]


def quat_xyzw_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of quaternions; the input is normalized first (must be nonzero).

    Args:
        q: Quaternions xyzw, shape ``(..., 4)``.

    Returns:
        Rotation matrices, shape ``(..., 3, 3)``.
    """
    x, y, z, w = (q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)).unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return torch.stack(rows, -1).unflatten(-1, (3, 3))


def matrix_to_quat_xyzw(R: torch.Tensor) -> torch.Tensor:
    """Unit quaternion (``w >= 0``) of rotation matrices, Shepperd-style.

    Each row of the 4x4 matrix built below equals ``4 q_k q`` for one component
    ``k``; the row whose diagonal ``4 q_k^2`` is largest (>= 1) is normalized.
    This needs no square root and never divides by a small number.

    Args:
        R: Rotation matrices, shape ``(..., 3, 3)``.

    Returns:
        Quaternions xyzw, shape ``(..., 4)``.
    """
    r = R.flatten(-2).unbind(-1)  # r[3*i + j] = R[i, j]
    d0, d1, d2 = r[0], r[4], r[8]
    a01, a02, a12 = r[1] + r[3], r[2] + r[6], r[5] + r[7]
    sx, sy, sz = r[7] - r[5], r[2] - r[6], r[3] - r[1]
    rows = [
        1 + d0 - d1 - d2, a01, a02, sx,
        a01, 1 - d0 + d1 - d2, a12, sy,
        a02, a12, 1 - d0 - d1 + d2, sz,
        sx, sy, sz, 1 + d0 + d1 + d2,
    ]  # fmt: skip
    M = torch.stack(rows, -1).unflatten(-1, (4, 4))
    k = torch.diagonal(M, dim1=-2, dim2=-1).argmax(-1)
    q = torch.gather(M, -2, k[..., None, None].expand(*k.shape, 1, 4)).squeeze(-2)
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    return torch.where(q[..., 3:] < 0, -q, q)


def quat_xyzw_multiply(q1: torch.Tensor, q2: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``q1 * q2`` (rotate by ``q2`` then ``q1``, like ``R1 @ R2``).

    Args:
        q1: Quaternions xyzw, shape ``(..., 4)``.
        q2: Quaternions xyzw, broadcastable with ``q1``.

    Returns:
        Quaternions xyzw, shape ``(..., 4)`` (broadcast shape).
    """
    q1, q2 = torch.broadcast_tensors(q1, q2)
    v1, w1 = q1[..., :3], q1[..., 3:]
    v2, w2 = q2[..., :3], q2[..., 3:]
    v = w1 * v2 + w2 * v1 + torch.linalg.cross(v1, v2, dim=-1)
    w = w1 * w2 - (v1 * v2).sum(-1, keepdim=True)
    return torch.cat([v, w], -1)


def quat_xyzw_conjugate(q: torch.Tensor) -> torch.Tensor:
    """Conjugate ``(-v, w)``, the inverse rotation of a unit quaternion; ``(..., 4) -> (..., 4)``."""
    return torch.cat([-q[..., :3], q[..., 3:]], -1)


def rot6d_to_matrix(x: torch.Tensor) -> torch.Tensor:
    """Zhou et al. (2019) 6D ``[col0, col1]`` to ``R`` by Gram-Schmidt, ``b3 = b1 x b2``.

    Args:
        x: 6D vectors, shape ``(..., 6)``; the two halves must be non-parallel.

    Returns:
        Rotation matrices, shape ``(..., 3, 3)``.
    """
    a1, a2 = x[..., :3], x[..., 3:]
    b1 = F.normalize(a1, dim=-1)
    b2 = F.normalize(a2 - (b1 * a2).sum(-1, keepdim=True) * b1, dim=-1)
    return torch.stack([b1, b2, torch.linalg.cross(b1, b2, dim=-1)], -1)


def matrix_to_rot6d(R: torch.Tensor) -> torch.Tensor:
    """First two columns of ``R`` concatenated; ``(..., 3, 3) -> (..., 6)``."""
    return torch.cat([R[..., :, 0], R[..., :, 1]], -1)


def euler_xyz_to_matrix(angles: torch.Tensor) -> torch.Tensor:
    """Intrinsic X-Y-Z Euler angles: ``R = Rx(a) @ Ry(b) @ Rz(c)``.

    Args:
        angles: ``(a, b, c)``, shape ``(..., 3)``.

    Returns:
        Rotation matrices, shape ``(..., 3, 3)``.
    """
    ca, cb, cc = torch.cos(angles).unbind(-1)
    sa, sb, sc = torch.sin(angles).unbind(-1)
    rows = [
        cb * cc, -cb * sc, sb,
        sa * sb * cc + ca * sc, ca * cc - sa * sb * sc, -sa * cb,
        sa * sc - ca * sb * cc, ca * sb * sc + sa * cc, ca * cb,
    ]  # fmt: skip
    return torch.stack(rows, -1).unflatten(-1, (3, 3))


def matrix_to_euler_xyz(R: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`euler_xyz_to_matrix`, with ``b`` in ``[-pi/2, pi/2]``.

    ``a`` comes from the last column; ``b`` and ``c`` are then solved from
    ``Rx(a)^T R = Ry(b) Rz(c)``, which keeps the three angles consistent even
    when ``a`` is poorly determined. Gimbal lock (``|b| = pi/2``, detected as
    ``cos b < sqrt(eps)``): only ``a + c`` (``b > 0``) or ``c - a`` (``b < 0``)
    is defined, so ``a`` is set to 0 and ``c`` absorbs the whole rotation.

    Args:
        R: Rotation matrices, shape ``(..., 3, 3)``.

    Returns:
        Angles ``(a, b, c)``, shape ``(..., 3)``.
    """
    r12, r22 = R[..., 1, 2], R[..., 2, 2]
    lock = r12 * r12 + r22 * r22 < torch.finfo(R.dtype).eps
    # Safe atan2 arguments: atan2(0, 0) has a NaN gradient.
    a = torch.atan2(torch.where(lock, 0.0, -r12), torch.where(lock, 1.0, r22))
    ca, sa = torch.cos(a), torch.sin(a)
    cos_b = ca * r22 - sa * r12
    b = torch.atan2(R[..., 0, 2], cos_b)
    sin_c = ca * R[..., 1, 0] + sa * R[..., 2, 0]
    cos_c = ca * R[..., 1, 1] + sa * R[..., 2, 1]
    return torch.stack([a, b, torch.atan2(sin_c, cos_c)], -1)


def swing_twist(R: torch.Tensor, axis: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Split ``R = swing @ twist`` with ``twist`` a rotation about ``axis``.

    The quaternion vector part is projected onto ``axis``: twist quaternion
    ``normalize((p . n) n, w)`` with ``w >= 0``, hence a twist angle in
    ``(-pi, pi]``. The swing's rotation axis is perpendicular to ``axis``.
    When the projection is degenerate (``R`` is a half-turn about an axis
    perpendicular to ``axis``, i.e. a swing of pi) the twist is undefined;
    the twist angle is then 0 and ``swing = R``.

    Args:
        R: Rotation matrices, shape ``(..., 3, 3)``.
        axis: Twist axis, shape ``(3,)`` or ``(..., 3)``; normalized internally.

    Returns:
        ``swing`` of shape ``(..., 3, 3)`` and ``twist_angle`` of shape ``(...)``.
    """
    n = F.normalize(axis, dim=-1)
    q = matrix_to_quat_xyzw(R)  # w >= 0 already
    d, w = (q[..., :3] * n).sum(-1), q[..., 3]
    degenerate = d * d + w * w < torch.finfo(R.dtype).eps
    # Safe atan2 arguments (atan2(0, 0) has a NaN gradient); the pi-wrap keeps
    # the angle in (-pi, pi] when w == 0 and d < 0.
    angle = 2 * torch.atan2(torch.where(degenerate, 0.0, d), torch.where(degenerate, 1.0, w))
    angle = torch.where(angle <= -torch.pi, angle + 2 * torch.pi, angle)
    twist = axis_angle_to_matrix(n * angle[..., None])
    return R @ twist.transpose(-1, -2), angle


def shortest_arc(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Minimal rotation taking direction ``a`` to direction ``b``.

    Uses the quaternion ``(u x v, (1 + u.v))`` with ``u, v`` the unit directions
    and ``1 + u.v = |u + v|^2 / 2`` (no cancellation). Parallel inputs give the
    identity. Within ``pi - angle < sqrt(eps)`` of antiparallel the rotation is
    a half-turn about ``u x e_k``, ``e_k`` the basis vector most perpendicular to
    ``u`` (deterministic); accuracy there is O(sqrt(eps)), which is intrinsic:
    the axis of a near half-turn is set by a vanishing cross product.

    Args:
        a: Source directions, shape ``(..., 3)``, nonzero.
        b: Target directions, broadcastable with ``a``, nonzero.

    Returns:
        Rotation matrices, shape ``(..., 3, 3)``.
    """
    a, b = torch.broadcast_tensors(a, b)
    u, v = F.normalize(a, dim=-1), F.normalize(b, dim=-1)
    s = u + v
    w = 0.5 * (s * s).sum(-1, keepdim=True)
    anti = w < 0.5 * torch.finfo(a.dtype).eps
    e = F.one_hot(u.abs().argmin(-1), 3).to(u.dtype)
    q_anti = torch.cat([F.normalize(torch.linalg.cross(u, e, dim=-1), dim=-1), torch.zeros_like(w)], -1)
    q_reg = torch.cat([torch.linalg.cross(u, v, dim=-1), w], -1)
    # Select before quat_xyzw_to_matrix normalizes: the vanishing q_reg of the
    # antiparallel case is never divided by its norm, so its gradient stays finite.
    return quat_xyzw_to_matrix(torch.where(anti, q_anti, q_reg))


def rotation_angle(R: torch.Tensor) -> torch.Tensor:
    """Geodesic angle in ``[0, pi]`` as ``atan2(|skew part|, trace part)``.

    Unlike ``acos((tr - 1) / 2)`` this keeps full accuracy near 0 and pi.

    Args:
        R: Rotation matrices, shape ``(..., 3, 3)``.

    Returns:
        Angles, shape ``(...)``.
    """
    A = R - R.transpose(-1, -2)
    sq = 0.5 * (A * A).sum((-1, -2))  # = (2 sin(angle))^2
    zero = sq == 0
    # Safe sqrt: a zero (not NaN) gradient where the skew part vanishes (angle 0 or pi).
    sin2 = torch.where(zero, 0.0, torch.sqrt(torch.where(zero, 1.0, sq)))
    cos2 = torch.diagonal(R, dim1=-2, dim2=-1).sum(-1) - 1
    return torch.atan2(sin2, cos2)


def orthonormalize(R: torch.Tensor) -> torch.Tensor:
    """Nearest rotation (Frobenius) via SVD with a determinant fix; not for hot paths.

    The one implementation is :func:`unibody.geometry.procrustes.polar_svd`; this name is
    kept because error messages point users to it.

    Args:
        R: Approximate rotation matrices, shape ``(..., 3, 3)``.

    Returns:
        Rotation matrices, shape ``(..., 3, 3)``.
    """
    return polar_svd(R)
