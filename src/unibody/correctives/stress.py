"""Seeded stress poses of issue 40: deep flexion, abduction and twist, alone and combined.

T-pose-relative axis-angle (:mod:`unibody.body`), left side given, right side mirrored
(x -> -x). Axes as in :mod:`unibody.joint_limits`: the upper arm rises about +Z (150 deg of
abduction is the T-pose's 90 plus 60), the elbow flexes about -Y, the wrist about Z, the hand
twists the forearm about X (its bone in the T-pose), the hip flexes about -X, the knee about +X.
"""

from __future__ import annotations

import math

import torch

from ..rig import JOINT_NAMES

__all__ = ["FAMILIES", "stress_poses", "forearm_twist_pose"]

_D = math.pi / 180
FAMILIES: dict[str, dict[str, tuple[float, float, float]]] = {
    "elbow 150": {"LeftForeArm": (0.0, -150 * _D, 0.0)},
    "knee 150": {"LeftShin": (150 * _D, 0.0, 0.0)},
    "shoulder abduction 150": {"LeftArm": (0.0, 0.0, 60 * _D)},
    "hip flexion 120": {"LeftLeg": (-120 * _D, 0.0, 0.0)},
    "wrist 80": {"LeftHand": (0.0, 0.0, -80 * _D)},
    "forearm twist 150": {"LeftHand": (150 * _D, 0.0, 0.0)},
    "arm forward + elbow 150": {"LeftArm": (0.0, -80 * _D, -30 * _D), "LeftForeArm": (0.0, -150 * _D, 0.0)},
    "squat: hip 120 + knee 150": {"LeftLeg": (-120 * _D, 0.0, 0.0), "LeftShin": (150 * _D, 0.0, 0.0)},
}
"""Each family's left-side joint rotations at full amplitude (radians)."""


def _mirror(name: str, v: tuple[float, float, float]) -> tuple[str, tuple[float, float, float]]:
    return "Right" + name.removeprefix("Left"), (v[0], -v[1], -v[2])


def stress_poses(generator: torch.Generator, *, seeded: int = 16) -> tuple[torch.Tensor, list[str]]:
    """The 16 family poses (8 families, each side) then ``seeded`` combinations: (N, 77, 3) and labels.

    A seeded pose picks, for each side of the body, one arm family and one leg family (or none)
    and scales each at an amplitude uniform in [0.7, 1].
    """
    index = {n: i - 1 for i, n in enumerate(JOINT_NAMES)}
    poses, labels = [], []
    for label, joints in FAMILIES.items():
        for side in ("Left", "Right"):
            p = torch.zeros(77, 3)
            for name, v in joints.items():
                name, v = (name, v) if side == "Left" else _mirror(name, v)
                p[index[name]] = torch.tensor(v)
            poses.append(p)
            labels.append(f"{label} ({side.lower()})")
    arm = [k for k, j in FAMILIES.items() if any(n.startswith("LeftArm") or "Fore" in n or "Hand" in n for n in j)]
    leg = [k for k in FAMILIES if k not in arm]
    for _ in range(seeded):
        p, parts = torch.zeros(77, 3), []
        for side in ("Left", "Right"):
            for group in (arm, leg):
                pick = int(torch.randint(len(group) + 1, (1,), generator=generator))
                if pick == len(group):
                    continue
                amp = 0.7 + 0.3 * float(torch.rand(1, generator=generator))
                for name, v in FAMILIES[group[pick]].items():
                    name, v = (name, v) if side == "Left" else _mirror(name, v)
                    p[index[name]] = amp * torch.tensor(v)
                parts.append(f"{side[0]} {group[pick]} x{amp:.2f}")
        poses.append(p)
        labels.append("; ".join(parts) or "T-pose")
    return torch.stack(poses), labels


def forearm_twist_pose(degrees: float = 150.0) -> torch.Tensor:
    """(1, 77, 3) the left hand turned ``degrees`` about the forearm (T-pose X axis)."""
    p = torch.zeros(1, 77, 3)
    p[0, JOINT_NAMES.index("LeftHand") - 1, 0] = degrees * _D
    return p
