"""Warp kernel for the dense part of posing, inference only: pose -> world and skinning transforms.

The torch reference is ``unibody.body._pose_math`` (Rodrigues, T-pose-relative to absolute,
FK, ``G T^-1``): a few hundred tiny tensor operations whose dispatch dominates a batch-1 pose on
the CPU (about 1.1 of 2 ms). Here one thread per batch item walks the joints in tree order, so
the whole step is one launch. It runs float32 on the CPU or CUDA when no gradient is needed;
``BodyLayer.pose`` takes the torch path otherwise (and for other dtypes, procedural twist, or
axis-angles beyond :data:`MAX_ANGLE`). Both agree to float32 rounding (tests/test_body_fast.py).

Outputs are written in the layouts their consumers read: world transforms (B, J, 4, 4) as
returned by ``pose``, and the skinning transforms as the (4J, 3B) right-hand side of the sparse
product, i.e. memory (J, 4, B, 3) (``geometry.skinning``).
"""

from __future__ import annotations

import functools
import warnings

import torch

__all__ = ["MAX_ANGLE", "available", "disable", "pose_transforms"]

MAX_ANGLE = 1.0e3
"""Axis-angles longer than this (radians) take the torch path, whose ``sin``/``cos`` reduce any
angle exactly; the kernel's single-precision reduction is only trusted for moderate angles."""


@functools.cache
def _kernel():
    """Import and initialise Warp and define the kernel, once (never at import time)."""
    import warp as wp

    if hasattr(wp.config, "quiet"):  # Warp < 1.10: keep the start-up banner off stdout
        wp.config.quiet = True
    level = getattr(wp, "LOG_WARNING", None)
    if level is not None and getattr(wp.config, "log_level", level) < level:
        wp.config.log_level = level
    wp.init()

    @wp.func
    def rodrigues(v: wp.vec3) -> wp.mat33:
        # |v| without overflow: scale by the largest component first.
        m = wp.max(wp.max(wp.abs(v[0]), wp.abs(v[1])), wp.abs(v[2]))
        if m == 0.0:
            return wp.identity(n=3, dtype=wp.float32)
        s = v / m
        n = wp.length(s)
        t = m * n
        u = s / n
        k = wp.skew(u)
        h = wp.sin(0.5 * t)
        # I + sin t K + (1 - cos t) K^2, with 1 - cos t = 2 sin^2(t/2) (no cancellation near 0)
        return wp.identity(n=3, dtype=wp.float32) + wp.sin(t) * k + (2.0 * h * h) * (k * k)

    @wp.kernel
    def pose_kernel(
        rot_in: wp.array3d(dtype=wp.float32),
        matrices: int,
        relative: int,
        left: wp.array(dtype=wp.mat33),
        right: wp.array(dtype=wp.mat33),
        parents: wp.array(dtype=wp.int32),
        offsets: wp.array2d(dtype=wp.vec3),
        transl: wp.array(dtype=wp.vec3),
        rest_rot: wp.array2d(dtype=wp.mat33),
        rest_pos: wp.array2d(dtype=wp.vec3),
        world: wp.array4d(dtype=wp.float32),
        mats: wp.array4d(dtype=wp.float32),
    ):
        b = wp.tid()
        bi = b
        if offsets.shape[0] == 1:
            bi = 0
        for j in range(parents.shape[0]):
            rot = wp.identity(n=3, dtype=wp.float32)
            pos = offsets[bi, j]
            if j > 0:
                q = j - 1
                if matrices == 1:
                    local = wp.mat33(
                        rot_in[b, q, 0], rot_in[b, q, 1], rot_in[b, q, 2],
                        rot_in[b, q, 3], rot_in[b, q, 4], rot_in[b, q, 5],
                        rot_in[b, q, 6], rot_in[b, q, 7], rot_in[b, q, 8],
                    )  # fmt: skip
                else:
                    local = rodrigues(wp.vec3(rot_in[b, q, 0], rot_in[b, q, 1], rot_in[b, q, 2]))
                if relative == 1:
                    local = left[q] * local * right[q]
                if j == 1:
                    pos = transl[b]
                p = parents[j]
                parent = wp.mat33(
                    world[b, p, 0, 0], world[b, p, 0, 1], world[b, p, 0, 2],
                    world[b, p, 1, 0], world[b, p, 1, 1], world[b, p, 1, 2],
                    world[b, p, 2, 0], world[b, p, 2, 1], world[b, p, 2, 2],
                )  # fmt: skip
                rot = parent * local
                pos = parent * pos + wp.vec3(world[b, p, 0, 3], world[b, p, 1, 3], world[b, p, 2, 3])
            skin = rot * wp.transpose(rest_rot[bi, j])
            shift = pos - skin * rest_pos[bi, j]
            for r in range(3):
                for c in range(3):
                    world[b, j, r, c] = rot[r, c]
                    mats[j, c, b, r] = skin[r, c]
                world[b, j, r, 3] = pos[r]
                world[b, j, 3, r] = 0.0
                mats[j, 3, b, r] = shift[r]
            world[b, j, 3, 3] = 1.0

    return wp, pose_kernel


_DISABLED: list[str] = []


def available() -> bool:
    """Whether Warp imports and initialises here and has not failed (False: callers keep the torch path)."""
    if _DISABLED:
        return False
    try:
        _kernel()
    except Exception as exc:  # no Warp, or it cannot start: the torch path is always there
        disable(f"{type(exc).__name__}: {exc}")
        return False
    return True


def disable(why: str) -> None:
    """Stop using the kernel in this process, saying why once."""
    if not _DISABLED:
        _DISABLED.append(why)
        warnings.warn(f"unibody: the Warp posing kernel is off ({why}); posing uses torch", RuntimeWarning, 3)


def pose_transforms(
    parents: torch.Tensor,
    rot_in: torch.Tensor,
    matrices: bool,
    relative: bool,
    left: torch.Tensor,
    right: torch.Tensor,
    offsets: torch.Tensor,
    transl: torch.Tensor,
    rest_rot: torch.Tensor,
    rest_pos: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """World (B, J, 4, 4) and joint-major skinning transforms (J, 4, 3, B) of a posed body, float32.

    Args:
        parents: (J,) int32 parent per joint (the root's entry unused); parents precede children.
        rot_in: (B, J - 1, 3) axis-angles or (B, J - 1, 3, 3) matrices of joints 1..J-1.
        matrices: whether ``rot_in`` holds matrices.
        relative: whether the rotations are T-pose-relative (then ``left @ R @ right``).
        left, right: (J - 1, 3, 3) the factors O_p(j)^T and O_j.
        offsets: (Bi, J, 3) rest offsets; transl: (B, 3) joint 1's world position.
        rest_rot: (Bi, J, 3, 3) and rest_pos: (Bi, J, 3), the rest transforms T.
    """
    wp, kernel = _kernel()
    b, j = rot_in.shape[0], parents.shape[0]
    world = rot_in.new_empty(b, j, 4, 4)
    mats = rot_in.new_empty(j, 4, b, 3)
    if b:
        device = wp.device_from_torch(rot_in.device)

        def arr(t: torch.Tensor, dtype=None):
            return wp.from_torch(t.contiguous(), dtype=dtype)

        args = [
            arr(rot_in.reshape(b, j - 1, -1)),
            int(matrices),
            int(relative),
            arr(left, wp.mat33),
            arr(right, wp.mat33),
            arr(parents),
            arr(offsets, wp.vec3),
            arr(transl, wp.vec3),
            arr(rest_rot, wp.mat33),
            arr(rest_pos, wp.vec3),
            arr(world),
            arr(mats),
        ]
        stream = wp.stream_from_torch(rot_in.device) if rot_in.is_cuda else None
        if stream is None:
            wp.launch(kernel, dim=b, inputs=args, device=device)
        else:
            with wp.ScopedStream(stream):
                wp.launch(kernel, dim=b, inputs=args, device=device)
    return world, mats.transpose(2, 3)
