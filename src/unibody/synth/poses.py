"""A seeded generator of plausible body poses for the canonical rig (synthetic data).

Poses are T-pose-relative axis-angle vectors (paper 001 convention, :mod:`unibody.body`):
a joint's relative rotation acts about the axes of the T-pose world frame carried by its
parents (X to the body's left, Y up, Z forward), so ranges read anatomically. In the T-pose
the arms point along +-X with the palms down and the legs along -Y.

Each joint draws every component of its rotation vector uniformly in ``[lo, hi]`` (radians,
left side; the right side is mirrored), then pulls it toward a relaxed value by a per-sample
amplitude ``s ~ U(min_amplitude, 1)``: ``v = relaxed + s (u - relaxed)``. Small amplitudes
give everyday poses (arms down, legs straight), large ones the edges of the ranges. The
Hips carry a uniform heading about Y; a fraction of samples (``tumble``) get a uniformly
random orientation instead (flips, handstands, lying down). Independent draws seldom bring
the feet or the hands together, or bend an elbow or a knee deeply; ``together``,
``arms_alike`` and ``bend`` set fractions of samples with the legs together, the arms
mirrored and limbs bent.

    gen = torch.Generator().manual_seed(0)
    pose = sample_poses(256, gen)               # (256, 77, 3)
"""

from __future__ import annotations

import hashlib

import torch

from ..geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from ..joint_limits import JOINT_RANGES
from ..rig import JOINT_NAMES

__all__ = ["JOINT_RANGES", "keyed_generator", "mirror_rotation", "sample_poses"]

_FINGER_CURL = (-1.2, 0.15, -0.3)  # about Z (palm down: - curls the finger), lo, hi, relaxed


def keyed_generator(*key: object) -> torch.Generator:
    """A CPU generator seeded by a hash of ``key`` (independent streams for distinct keys, and the
    same stream for the same key in any process: resumable, order-free synthetic data)."""
    digest = hashlib.blake2b(repr(key).encode(), digest_size=8).digest()
    return torch.Generator().manual_seed(int.from_bytes(digest, "little"))


def mirror_rotation(v: torch.Tensor) -> torch.Tensor:
    """Reflect rotation vectors through the body's sagittal plane (x -> -x): (x, y, z) -> (x, -y, -z)."""
    return v * v.new_tensor([1.0, -1.0, -1.0])


def _uniform(n: int, lo, hi, gen: torch.Generator, dtype: torch.dtype) -> torch.Tensor:
    lo, hi = torch.tensor(lo, dtype=dtype), torch.tensor(hi, dtype=dtype)
    return lo + (hi - lo) * torch.rand(n, *lo.shape, generator=gen, dtype=dtype)


def _random_rotations(n: int, gen: torch.Generator, dtype: torch.dtype) -> torch.Tensor:
    """(n, 3, 3) rotations uniform on SO(3) (normalised Gaussian quaternions)."""
    q = torch.randn(n, 4, generator=gen, dtype=dtype)
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
            2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
            2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).view(n, 3, 3)  # fmt: skip


def sample_poses(
    n: int,
    generator: torch.Generator,
    *,
    min_amplitude: float = 0.2,
    tilt: float = 0.3,
    tumble: float = 0.1,
    together: float = 0.0,
    arms_alike: float = 0.0,
    bend: float = 0.0,
    chamber: float = 0.0,
    fold: float = 0.0,
    fingers: bool = True,
    ranges: dict[str, tuple[tuple[float, float, float], ...]] | None = None,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """Sample ``n`` body poses.

    Args:
        n: number of poses.
        generator: the random stream (the result is a function of its state).
        min_amplitude: lower end of the per-sample amplitude in [0, 1] (see the module docstring).
        tilt: radians, the largest pitch/roll of the Hips for upright samples.
        tumble: fraction of samples with a uniformly random Hips orientation.
        together: fraction of samples with the legs together: each hip adducted 0-0.15 rad
            (about Z), the right hip and knee flexed as the left ones +-0.15 rad (about X).
            Independent draws seldom bring the feet within 20 cm of each other; people stand,
            squat and lie with their feet together all the time.
        arms_alike: fraction of samples whose right arm mirrors the left one (shoulder to
            hand, +-0.15 rad per component): symmetric movements, where the hands meet
            (within 20 cm in 7 % of these samples, 0.9 % of independent ones).
        bend: fraction of limbs (each arm and each leg on its own) bent deeply: the elbow
            flexed 1.2-2.4 rad with the arm swung anywhere from 1.5 rad forward to 1.0 rad
            back (guards, hands on the hips, fists drawn back), or the knee 1.2-2.3 rad with
            the hip flexed from 0 to as much (kneeling to squatting). The draws pulled toward
            the relaxed pose bend an elbow or a knee past 90 deg in about 7 % of the samples;
            guards, punches and crouches hold them there far longer.
        chamber: fraction of arms (each on its own) held with the fist at the waist: the arm
            lowered 1.25-1.5 rad and drawn back 0.2-0.8 rad, the elbow flexed 1.4-2.3 rad
            (martial-arts chambers, hands on the hips, running arms). ``bend`` swings bent
            arms about the vertical, which seldom brings the hand beside the waist.
        fold: fraction of samples folded at the hips: both hips flexed 1.2-2.0 rad (the
            right as the left +-0.2), each knee 0-2.3 rad, the spine and chest flexed forward up
            to their range (sitting on the floor, squats, tucks, pikes). The independent draws
            close the angle between trunk and thigh under 105 deg in 5 % of the samples; floor
            work holds it there for a fifth of its frames.
        fingers: whether fingers curl (else they stay straight, as in the T-pose).
        ranges: entries that replace those of :data:`JOINT_RANGES` (same format, left-side names).
        dtype: float32 or float64.

    Returns:
        (n, 77, 3) axis-angle T-pose-relative local rotations of joints 1..77.
    """
    if not isinstance(n, int) or n < 0:
        raise ValueError(f"n: expected a non-negative int, got {n!r}")
    if not 0.0 <= min_amplitude <= 1.0:
        raise ValueError(f"min_amplitude: expected a value in [0, 1], got {min_amplitude}")
    if not 0.0 <= tumble <= 1.0:
        raise ValueError(f"tumble: expected a fraction in [0, 1], got {tumble}")
    if not 0.0 <= together <= 1.0:
        raise ValueError(f"together: expected a fraction in [0, 1], got {together}")
    if not 0.0 <= arms_alike <= 1.0:
        raise ValueError(f"arms_alike: expected a fraction in [0, 1], got {arms_alike}")
    if not 0.0 <= bend <= 1.0:
        raise ValueError(f"bend: expected a fraction in [0, 1], got {bend}")
    if not 0.0 <= chamber <= 1.0:
        raise ValueError(f"chamber: expected a fraction in [0, 1], got {chamber}")
    if not 0.0 <= fold <= 1.0:
        raise ValueError(f"fold: expected a fraction in [0, 1], got {fold}")
    index = {name: i - 1 for i, name in enumerate(JOINT_NAMES)}  # pose rows are joints 1..77
    pose = torch.zeros(n, len(JOINT_NAMES) - 1, 3, dtype=dtype)
    amp = min_amplitude + (1.0 - min_amplitude) * torch.rand(n, 1, generator=generator, dtype=dtype)

    def draw(lo, hi, relaxed) -> torch.Tensor:
        u = _uniform(n, lo, hi, generator, dtype)
        r = torch.tensor(relaxed, dtype=dtype)
        return r + amp * (u - r)

    table = dict(JOINT_RANGES)
    for name, value in (ranges or {}).items():
        if name not in JOINT_RANGES:
            raise ValueError(f"ranges: unknown joint {name!r}; expected one of {', '.join(JOINT_RANGES)}")
        table[name] = value
    for name, (lo, hi, relaxed) in table.items():
        for side in ("Left", "Right") if name.startswith("Left") else ("",):
            v = draw(lo, hi, relaxed)
            if side == "Right":
                name_r = "Right" + name[4:]
                pose[:, index[name_r]] = mirror_rotation(v)
            else:
                pose[:, index[name]] = v
    if fingers:
        lo, hi, relaxed = _FINGER_CURL
        for side, sign in (("Left", 1.0), ("Right", -1.0)):
            curl = draw((lo,), (hi,), (relaxed,))  # one curl per hand, shared by its fingers, plus spread
            for finger in ("Index", "Middle", "Ring", "Pinky"):
                for k in (1, 2, 3):
                    jitter = 0.15 * torch.randn(n, 1, generator=generator, dtype=dtype)
                    pose[:, index[f"{side}Hand{finger}{k}"], 2] = sign * (curl + jitter).squeeze(-1)
            thumb = 0.3 * torch.randn(n, 3, generator=generator, dtype=dtype)
            pose[:, index[f"{side}HandThumb2"]] = thumb if sign > 0 else mirror_rotation(thumb)
    # Hips: heading about Y, small tilt; a `tumble` fraction uniformly random.
    heading = (2 * torch.rand(n, generator=generator, dtype=dtype) - 1) * torch.pi
    tilt_v = (2 * torch.rand(n, 3, generator=generator, dtype=dtype) - 1) * tilt
    tilt_v[:, 1] = 0.0
    root = axis_angle_to_matrix(heading[:, None] * torch.tensor([0.0, 1.0, 0.0], dtype=dtype))
    root = root @ axis_angle_to_matrix(tilt_v)
    tumbling = torch.rand(n, generator=generator, dtype=dtype) < tumble
    if bool(tumbling.any()):
        root[tumbling] = _random_rotations(int(tumbling.sum()), generator, dtype)
    pose[:, index["Hips"]] = matrix_to_axis_angle(root)
    if bend > 0:  # before `together` and `arms_alike` (they copy the left limbs); bend=0 keeps the stream
        u = torch.rand(n, 4, 3, generator=generator, dtype=dtype)  # per limb: whether, depth, swing/hip share
        bent = u[..., 0] < bend
        for k, (side, sign) in enumerate((("Left", 1.0), ("Right", -1.0))):  # the right side mirrors Y
            elbow, arm = index[side + "ForeArm"], index[side + "Arm"]
            flex, swing = -sign * (1.2 + 1.2 * u[:, k, 1]), sign * (-1.5 + 2.5 * u[:, k, 2])
            pose[:, elbow, 1] = torch.where(bent[:, k], flex, pose[:, elbow, 1])
            pose[:, arm, 1] = torch.where(bent[:, k], swing, pose[:, arm, 1])  # forward to far back
            hip, knee = index[side + "Leg"], index[side + "Shin"]
            flex = 1.2 + 1.1 * u[:, k + 2, 1]
            hip_flex = (-flex * u[:, k + 2, 2]).clamp_min(table["LeftLeg"][0][0])
            pose[:, knee, 0] = torch.where(bent[:, k + 2], flex, pose[:, knee, 0])
            pose[:, hip, 0] = torch.where(bent[:, k + 2], hip_flex, pose[:, hip, 0])
    if together > 0:  # drawn after `bend`: the stream of together=0 is unchanged
        close = torch.rand(n, generator=generator, dtype=dtype) < together
        u = 2 * torch.rand(n, 4, generator=generator, dtype=dtype) - 1
        ll, rl, ls, rs = (index[x] for x in ("LeftLeg", "RightLeg", "LeftShin", "RightShin"))
        adduct = 0.075 + 0.075 * u[:, :2]  # 0-0.15 rad toward the midline, each leg
        pose[:, ll, 2] = torch.where(close, -adduct[:, 0], pose[:, ll, 2])
        pose[:, rl, 2] = torch.where(close, adduct[:, 1], pose[:, rl, 2])
        for left, right, k, name in ((ll, rl, 2, "LeftLeg"), (ls, rs, 3, "LeftShin")):  # flex alike, in range
            lo, hi = table[name][0][0], table[name][1][0]
            alike = (pose[:, left, 0] + 0.15 * u[:, k]).clamp(lo, hi)
            pose[:, right, 0] = torch.where(close, alike, pose[:, right, 0])
    if chamber > 0:  # drawn after `together`, before `arms_alike` (it may copy a chambered left arm)
        u = torch.rand(n, 2, 4, generator=generator, dtype=dtype)  # per arm: whether, lower, back, flex
        for k, (side, sign) in enumerate((("Left", 1.0), ("Right", -1.0))):
            on = u[:, k, 0] < chamber
            lower = axis_angle_to_matrix(-(1.25 + 0.25 * u[:, k, 1, None]) * pose.new_tensor([0.0, 0.0, 1.0]))
            back = axis_angle_to_matrix((0.2 + 0.6 * u[:, k, 2, None]) * pose.new_tensor([1.0, 0.0, 0.0]))
            arm = matrix_to_axis_angle(back @ lower)  # lowered to the side, then drawn back
            arm = arm if sign > 0 else mirror_rotation(arm)
            elbow, upper = index[side + "ForeArm"], index[side + "Arm"]
            pose[:, upper] = torch.where(on[:, None], arm, pose[:, upper])
            pose[:, elbow, 1] = torch.where(on, -sign * (1.4 + 0.9 * u[:, k, 3]), pose[:, elbow, 1])
    if arms_alike > 0:  # drawn after `together`: the streams without it are unchanged
        alike = torch.rand(n, generator=generator, dtype=dtype)[:, None] < arms_alike
        for name in ("Shoulder", "Arm", "ForeArm", "Hand"):
            left, right = index["Left" + name], index["Right" + name]
            noise = 0.15 * (2 * torch.rand(n, 3, generator=generator, dtype=dtype) - 1)
            pose[:, right] = torch.where(alike, mirror_rotation(pose[:, left]) + noise, pose[:, right])
    if fold > 0:  # drawn last: the streams without it are unchanged
        u = torch.rand(n, 7, generator=generator, dtype=dtype)  # whether, hip, right hip, 2 knees, spine, chest
        on = u[:, 0] < fold
        lo = table["LeftLeg"][0][0]
        hip = -(1.2 + 0.8 * u[:, 1])
        flex = {"LeftLeg": hip, "RightLeg": (hip + 0.4 * u[:, 2] - 0.2).clamp(lo, 0.0)}
        flex |= {"LeftShin": 2.3 * u[:, 3], "RightShin": 2.3 * u[:, 4]}
        for k, name in ((5, "Spine1"), (5, "Spine2"), (6, "Chest")):  # forward, up to the range's end
            flex[name] = table[name][1][0] * u[:, k]
        for name, value in flex.items():
            pose[:, index[name], 0] = torch.where(on, value, pose[:, index[name], 0])
    return pose
