"""unibody.fitting.retarget: a skeleton made from the canonical body posed by a known motion
(another identity, a subset of joints, foreign joint frames, another facing) comes back."""

from __future__ import annotations

import pytest
import torch

from unibody.body import BodyLayer
from unibody.fitting.retarget import retarget
from unibody.geometry.rotations import axis_angle_to_matrix, rotation_angle
from unibody.synth.poses import sample_poses

NAMES = (
    "Hips Spine1 Chest Neck1 Head LeftShoulder LeftArm LeftForeArm LeftHand RightShoulder RightArm "
    "RightForeArm RightHand LeftLeg LeftShin LeftFoot LeftToeBase RightLeg RightShin RightFoot RightToeBase"
).split()
# Joints whose rotation the mapped positions and orientations pin down (not the spine split).
CONSTRAINED = "LeftArm LeftForeArm LeftHand RightArm RightForeArm LeftLeg LeftShin LeftFoot RightLeg RightShin".split()


@pytest.fixture(scope="module")
def layer() -> BodyLayer:
    return BodyLayer.from_pca(num_components=16, dtype=torch.float64)


def _motion(t: int = 24) -> tuple[torch.Tensor, torch.Tensor]:
    """A smooth motion: linear blends between three seeded key poses, moving forward."""
    keys = sample_poses(3, torch.Generator().manual_seed(3), fingers=False, tumble=0.0, dtype=torch.float64)
    w = torch.linspace(0, 1, t // 2 + 1, dtype=torch.float64)[:-1, None, None]
    pose = torch.cat([keys[0] * (1 - w) + keys[1] * w, keys[1] * (1 - w) + keys[2] * w])
    s = torch.linspace(0, 1, pose.shape[0], dtype=torch.float64)
    transl = torch.stack([0.8 * s, 0.95 + 0.03 * torch.sin(6 * s), 0.2 * s], 1)
    return pose, transl


def _source(layer: BodyLayer, facing: float = 0.0):
    """The canonical body of identity c posed by the motion; joints renamed to columns, frames
    turned by a constant per-joint rotation, the whole motion turned about Y by ``facing``."""
    pose, transl = _motion()
    params = torch.zeros(1, 16, dtype=torch.float64)
    params[0, :4] = torch.tensor([1.2, -0.6, 0.8, 0.4])
    prepared = layer.prepare_identity(params)
    out = layer.pose(prepared, pose, transl=transl)
    idx = [layer.joint_names.index(n) for n in NAMES]
    frame = axis_angle_to_matrix(torch.randn(len(idx), 3, generator=torch.Generator().manual_seed(5)).double())
    turn = axis_angle_to_matrix(torch.tensor([0.0, facing, 0.0], dtype=torch.float64))
    pos = out.joints[:, idx] @ turn.T
    rot = turn @ out.transforms[:, idx, :3, :3] @ frame
    rest = layer.pose(prepared, torch.zeros(1, 77, 3, dtype=torch.float64))
    carrier = turn @ out.transforms[:, layer.parents[idx].clamp_min(1), :3, :3]  # the bone a joint sits on
    return pose, transl, pos, rot, rest.joints[0, idx], rest.transforms[0, idx, :3, :3] @ frame, turn, carrier


def _angles(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return rotation_angle(axis_angle_to_matrix(a).transpose(-1, -2) @ axis_angle_to_matrix(b))


def test_synthetic_skeleton_comes_back(layer):
    """Another identity, 21 joints with foreign frames, facing 120 degrees away from +Z."""
    pose, transl, pos, rot, rpos, rrot, turn, _ = _source(layer, facing=2.1)
    res = retarget(layer, pos, NAMES, orientations=rot, rest_positions=rpos, rest_orientations=rrot)
    assert res.pose.shape == (pos.shape[0], 77, 3) and res.transl.shape == (pos.shape[0], 3)
    assert float(res.joint_error.max()) < 3e-3  # m, every mapped joint of every frame
    assert float(res.bone_error.abs().max()) < 2e-3
    assert float((res.transl - transl @ turn.T).norm(dim=-1).max()) < 3e-3
    # The Hips turned with the source: their world orientation is the truth's turned by 120 degrees.
    want = turn @ axis_angle_to_matrix(pose[:, 0])
    assert float(rotation_angle(want.transpose(-1, -2) @ axis_angle_to_matrix(res.pose[:, 0])).max()) < 0.01
    cols = [layer.joint_names.index(n) - 1 for n in CONSTRAINED]
    ang = _angles(pose[:, cols], res.pose[:, cols])
    assert float(ang.max()) < 0.02  # rad
    # No flips: the recovered per-frame change of every joint stays within the truth's + 1 degree.
    true_step = _angles(pose[:-1], pose[1:]).amax(1)
    got_step = _angles(res.pose[:-1], res.pose[1:]).amax(1)
    assert float((got_step - true_step).max()) < 0.0175


def test_constant_offsets(layer):
    """The source joints sit 3 cm off ours, fixed in the frames of the bones that carry them: the
    fitted offsets absorb that; without them the error stays several times larger."""
    pose, transl, pos, rot, rpos, rrot, turn, carrier = _source(layer)
    off = torch.randn(len(NAMES), 3, generator=torch.Generator().manual_seed(7)).double()
    off = 0.03 * off / off.norm(dim=-1, keepdim=True)
    moved = pos + (carrier @ off[:, :, None]).squeeze(-1)
    kw = {"orientations": rot, "rest_positions": rpos, "rest_orientations": rrot}
    res = retarget(layer, moved, NAMES, offset_frames=carrier, **kw)
    assert float(res.joint_error.mean()) < 4e-3  # measured 2.9 mm (12 mm without offsets)
    assert float(res.joint_error.max()) < 3e-2
    plain = retarget(layer, moved, NAMES, **kw)
    assert float(plain.joint_error.mean()) > 3 * float(res.joint_error.mean())


def test_positions_only(layer):
    """Without orientations the torso is aligned by Kabsch and frames warm-start one from another:
    positions come back, and no joint jumps (twist about bone axes is not observable: not checked)."""
    pose, _, pos, *_ = _source(layer)
    res = retarget(layer, pos, NAMES)
    assert float(res.joint_error.max()) < 3e-3
    true_step = _angles(pose[:-1], pose[1:]).amax(1)
    got_step = _angles(res.pose[:-1], res.pose[1:]).amax(1)
    assert float((got_step - true_step).max()) < 0.087  # 5 degrees


def test_bad_input(layer):
    pos = torch.zeros(4, 3, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match="layer: expected a BodyLayer with an identity backend"):
        retarget(object(), pos, ["Hips", "Chest", "Head"])
    with pytest.raises(ValueError, match=r"joints: expected canonical joint names.*'Pelvis'"):
        retarget(layer, pos, ["Hips", "Pelvis", "Head"])
    with pytest.raises(ValueError, match=r"mapped once, got \['Head'\]"):
        retarget(layer, pos, ["Hips", "Head", "Head"])
    with pytest.raises(ValueError, match="at least 3 mapped joints, got 2"):
        retarget(layer, pos[:, :2], ["Hips", "Head"])
    with pytest.raises(ValueError, match=r"positions: expected at least one frame, got shape \(0, 3, 3\)"):
        retarget(layer, pos[:0], ["Hips", "Chest", "Head"])
    bad = pos.clone()
    bad[2, 1, 0] = float("nan")
    with pytest.raises(ValueError, match=r"positions: .*NaN/inf in 1 frame\(s\): 2$"):
        retarget(layer, bad, ["Hips", "Chest", "Head"])
    rot = torch.eye(3, dtype=torch.float64).expand(4, 3, 3, 3)
    with pytest.raises(ValueError, match="rest_positions, rest_orientations: required with orientations"):
        retarget(layer, pos, ["Hips", "Chest", "Head"], orientations=rot)


# Each was accepted: iterations -1 and prior_weight -1 retargeted 530 and 60 mm off without a word,
# num_components 0 failed inside torch ("max(): Expected reduction dim ..."), max_coeff NaN or -1
# as "identity params: expected finite values", batch 0 or 2.5 ran as something else.
@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("iterations", -1, r"iterations: expected an integer >= 1, got -1"),
        ("batch", 0, r"batch: expected an integer >= 1, got 0"),
        ("batch", 2.5, r"batch: expected an integer >= 1, got 2.5"),
        ("num_components", 0, r"num_components: expected an integer >= 1, got 0"),
        ("identity_steps", -1, r"identity_steps: expected an integer >= 0"),
        ("offset_rounds", True, r"offset_rounds: expected an integer >= 0, got True"),
        ("max_coeff", float("nan"), r"max_coeff: expected a finite number > 0, got nan"),
        ("max_coeff", -1.0, r"max_coeff: expected a finite number > 0, got -1.0"),
        ("prior_weight", -1.0, r"prior_weight: expected a finite number >= 0, got -1.0"),
        ("orientation_weight", float("inf"), r"orientation_weight: expected a finite number >= 0, got inf"),
    ],
)
def test_config_fields_are_checked_by_name(field, value, match):
    from unibody.fitting.retarget import RetargetConfig

    with pytest.raises(ValueError, match=match):
        RetargetConfig(**{field: value})
