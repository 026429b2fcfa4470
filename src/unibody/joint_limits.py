"""Anatomical ranges of the canonical rig's joints: the pose sampler's ranges and the mocap solve's prior.

Ranges are on T-pose-relative axis-angle components (paper 001 convention, :mod:`unibody.body`),
about the axes of the T-pose world frame carried by the parents (X to the body's left, Y up,
Z forward); left side only, the right side mirrors it.
"""

from __future__ import annotations

__all__ = ["JOINT_RANGES"]

# name: ((lo_x, lo_y, lo_z), (hi_x, hi_y, hi_z), (relaxed_x, relaxed_y, relaxed_z)), left side, radians.
# Arms: about Z lowers (-) / raises (+) the arm, about Y swings it forward (-) / back (+), about X
# twists it. Legs: about X flexes the hip forward (-) / the knee backward (+).
JOINT_RANGES: dict[str, tuple[tuple[float, float, float], ...]] = {
    "Spine1": ((-0.15, -0.2, -0.15), (0.35, 0.2, 0.15), (0.0, 0.0, 0.0)),
    "Spine2": ((-0.15, -0.2, -0.15), (0.35, 0.2, 0.15), (0.0, 0.0, 0.0)),
    "Chest": ((-0.1, -0.2, -0.1), (0.25, 0.2, 0.1), (0.0, 0.0, 0.0)),
    "Neck1": ((-0.25, -0.35, -0.2), (0.35, 0.35, 0.2), (0.0, 0.0, 0.0)),
    "Neck2": ((-0.2, -0.3, -0.15), (0.3, 0.3, 0.15), (0.0, 0.0, 0.0)),
    "Head": ((-0.2, -0.3, -0.15), (0.3, 0.3, 0.15), (0.0, 0.0, 0.0)),
    "LeftShoulder": ((-0.1, -0.3, -0.15), (0.1, 0.2, 0.3), (0.0, 0.0, 0.0)),
    "LeftArm": ((-0.9, -1.5, -1.45), (0.9, 0.7, 1.2), (0.0, -0.1, -1.2)),
    "LeftForeArm": ((-1.0, -2.4, -0.1), (1.2, 0.0, 0.1), (0.3, -0.3, 0.0)),
    "LeftHand": ((-0.3, -0.4, -1.0), (0.3, 0.4, 0.9), (0.0, 0.0, 0.0)),
    "LeftLeg": ((-2.0, -0.6, -0.4), (0.5, 0.6, 1.0), (0.0, 0.0, 0.05)),
    "LeftShin": ((0.0, -0.2, -0.05), (2.3, 0.2, 0.05), (0.1, 0.0, 0.0)),
    "LeftFoot": ((-0.8, -0.3, -0.3), (0.5, 0.3, 0.3), (0.0, 0.0, 0.0)),
    "LeftToeBase": ((-0.5, -0.05, -0.05), (0.3, 0.05, 0.05), (0.0, 0.0, 0.0)),
}
