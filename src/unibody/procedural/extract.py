"""Twist channels: the angle a driver joint turns about its bone, three ways (paper 001).

Every extractor reads ``D = R_bind^T R``: the driver's local rotation relative to its bind
local rotation, i.e. its rotation in its own bind frame (the bind pose has zero twist).

- ``local_x_euler``: the X angle of intrinsic XYZ Euler angles, ``D = Rx(a) Ry(b) Rz(c)``.
- ``local_x_swing_twist``: ``D = swing @ twist`` with ``twist`` about local X; from the xyzw
  quaternion with ``w >= 0`` (half-angle stabilization) the angle is ``2 atan2(q_x, q_w)``.
- ``aligned_x_swing_twist``: the same split about the segment's bone direction expressed in
  the driver's bind frame: the X twist of the virtual orientation ``V = G A`` whose X axis
  ``A`` aligns with the bone, so a driver whose X is not along the bone (a foot driving the
  shin) still measures twist about the bone.
"""

from __future__ import annotations

import torch

from ..geometry.rotations import matrix_to_euler_xyz, swing_twist

__all__ = ["EXTRACTORS", "twist_channel"]

EXTRACTORS = ("local_x_euler", "local_x_swing_twist", "aligned_x_swing_twist")


def twist_channel(mode: str, d: torch.Tensor, bone: torch.Tensor | None = None) -> torch.Tensor:
    """Twist angles (radians) of relative rotations ``d`` (..., 3, 3).

    Args:
        mode: one of :data:`EXTRACTORS`.
        d: rotations of the drivers in their bind frames, ``R_bind^T R``.
        bone: (..., 3) bone directions in the drivers' bind frames; ``aligned_x_swing_twist`` only.

    Returns:
        (...) angles in (-pi, pi].
    """
    if mode == "local_x_euler":
        return matrix_to_euler_xyz(d)[..., 0]
    if mode == "local_x_swing_twist":
        return swing_twist(d, d.new_tensor([1.0, 0.0, 0.0]))[1]
    if mode == "aligned_x_swing_twist":
        if bone is None:
            raise ValueError("bone: aligned_x_swing_twist needs the bone directions")
        return swing_twist(d, bone)[1]
    raise ValueError(f"mode: expected one of {EXTRACTORS}, got {mode!r}")
