"""unibody.convert.skeletal: canonical BVH by name (exact), name rules, overrides, units, bad input,
and short real CMU clips (BVH and ASF/AMC) retargeted within issue 34's targets."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from unibody.convert import ConvertOptions
from unibody.convert.skeletal import (
    _drop_coincident,
    _layer,
    find_asf,
    map_joints,
    read_amc,
    read_bvh,
    skeletal_to_motion,
)
from unibody.geometry.rotations import axis_angle_to_matrix
from unibody.io.skeletal import SkeletalMotion
from unibody.rig import JOINT_NAMES
from unibody.synth.poses import sample_poses

CMU = Path(__file__).resolve().parents[2] / "shared" / "motions" / "cmu"
CMU_ASF = [
    *"root lhipjoint lfemur ltibia lfoot ltoes rhipjoint rfemur rtibia rfoot rtoes lowerback upperback".split(),
    *"thorax lowerneck upperneck head lclavicle lhumerus lradius lwrist lhand lfingers lthumb rclavicle".split(),
    *"rhumerus rradius rwrist rhand rfingers rthumb".split(),
]
CMU_BVH = [
    *"Hips LHipJoint LeftHip LeftKnee LeftAnkle LeftToe RHipJoint RightHip RightKnee RightAnkle RightToe".split(),
    *"lowerback Chest Chest2 lowerneck Neck Head LeftCollar LeftShoulder LeftElbow LeftWrist lhand".split(),
    *"LFingers LThumb RightCollar RightShoulder RightElbow RightWrist rhand RFingers RThumb".split(),
]
DAZ = [
    *"hip abdomen chest neck head leftEye rightEye rCollar rShldr rForeArm rHand rThumb1 rThumb2".split(),
    *"rIndex1 rIndex2 rMid1 rMid2 rRing1 rRing2 rPinky1 rPinky2 lCollar lShldr lForeArm lHand lThumb1".split(),
    *"lThumb2 lIndex1 lIndex2 lMid1 lMid2 lRing1 lRing2 lPinky1 lPinky2 rButtock rThigh rShin rFoot".split(),
    *"lButtock lThigh lShin lFoot lFoot_End rFoot_End".split(),
]
MIXAMO = [
    f"mixamorig:{n}"
    for n in "Hips Spine Spine1 Spine2 Neck Head HeadTop_End LeftShoulder LeftArm LeftForeArm LeftHand RightShoulder "
    "RightArm RightForeArm RightHand LeftUpLeg LeftLeg LeftFoot LeftToeBase LeftToe_End RightUpLeg RightLeg "
    "RightFoot RightToeBase RightToe_End".split()
]


def _named(names: list[str], mapping: dict[int, str]) -> dict[str, str]:
    return {names[i]: c for i, c in mapping.items()}


def test_name_rules():
    asf = _named(CMU_ASF, map_joints(tuple(CMU_ASF)))
    assert len(asf) == 22 and asf["lfemur"] == "LeftLeg" and asf["rwrist"] == "RightHand" and "lhipjoint" not in asf
    bvh = _named(CMU_BVH, map_joints(tuple(CMU_BVH)))
    # CMU's BVH "LeftShoulder" is the humerus, "Chest" the upper back: its rules beat the canonical names.
    assert len(bvh) == 22 and bvh["LeftShoulder"] == "LeftArm" and bvh["Chest"] == "Spine2"
    assert bvh["RightHip"] == "RightLeg" and bvh["Neck"] == "Neck2"
    daz = _named(DAZ, map_joints(tuple(DAZ)))
    assert len(daz) == 21 and daz["rShldr"] == "RightArm" and daz["lFoot_End"] == "LeftToeBase"
    assert "lIndex1" not in daz and daz["hip"] == "Hips"
    mix = _named(MIXAMO, map_joints(tuple(MIXAMO)))
    assert len(mix) == 25 and mix["mixamorig:LeftLeg"] == "LeftShin" and mix["mixamorig:RightUpLeg"] == "RightLeg"
    canon = map_joints(JOINT_NAMES[1:])
    assert len(canon) == 77 and all(JOINT_NAMES[i + 1] == c for i, c in canon.items())


def test_asf_names_in_a_bvh():
    """Some CMU BVHs keep the ASF bone names with a root called "hip", and put the clavicles and
    lowerneck on the thorax's start: the root maps, the joints sitting on a mapped one do not."""
    names = ("hip",) + tuple(CMU_ASF[1:])
    mapping = map_joints(names)
    assert mapping[0] == "Hips" and len(mapping) == 22
    parents = np.array([-1, 0, 1, 2, 3, 4, 0, 6, 7, 8, 9, 0, 11, 12, 13, 14, 15, 13, 17, 18, 19, 20, 21, 21])
    parents = np.concatenate([parents, [13, 24, 25, 26, 27, 28, 28]])
    rest = np.cumsum(np.full((31, 3), 0.05), 0)
    rest[[CMU_ASF.index(n) for n in ("lowerneck", "lclavicle", "rclavicle")]] = rest[CMU_ASF.index("thorax")]
    sk = SkeletalMotion(names, parents, np.zeros((31, 3)), np.zeros((1, 31, 3, 3)), np.zeros((1, 31, 3)), 30.0)
    warnings = _drop_coincident(sk, mapping, rest, "x.bvh: ")
    assert len(mapping) == 19 and {"Neck1", "LeftShoulder", "RightShoulder"}.isdisjoint(mapping.values())
    assert warnings[0] == "x.bvh: joint 'lowerneck' sits on 'thorax' at rest; Neck1 left unmapped"


def test_mapping_override(tmp_path):
    f = tmp_path / "map.json"
    f.write_text(json.dumps({"lShldr": None, "abdomen": "Spine1", "lThumb1": "LeftHandThumb1"}))
    daz = _named(DAZ, map_joints(tuple(DAZ), f))
    assert "lShldr" not in daz and daz["abdomen"] == "Spine1" and daz["lThumb1"] == "LeftHandThumb1"
    assert len(daz) == 21
    f.write_text(json.dumps({"lShldr": "LeftUpperArm"}))
    with pytest.raises(ValueError, match=r"map.json: expected canonical joint names .* got \['LeftUpperArm'\]"):
        map_joints(tuple(DAZ), f)
    f.write_text(json.dumps({"pelvis": "Hips"}))
    with pytest.raises(ValueError, match=r"map.json: expected joints of the skeleton .*\['pelvis'\]"):
        map_joints(tuple(DAZ), f)
    f.write_text(json.dumps({"lCollar": "LeftArm"}))
    with pytest.raises(ValueError, match="'lCollar' and 'lShldr' both map to 'LeftArm'"):
        map_joints(tuple(DAZ), f)
    f.write_text("[1, 2]")
    with pytest.raises(ValueError, match=r"map.json: expected a JSON object"):
        map_joints(tuple(DAZ), f)


def _canonical_bvh(t: int = 6, scale: float = 100.0) -> tuple[SkeletalMotion, np.ndarray, np.ndarray]:
    """The canonical skeleton (a PCA identity, T-pose rest, world-aligned frames) in cm, as the
    canonical BVH export writes it, posed by seeded poses; an end site on a finger."""
    layer = _layer(16, torch.float32)
    prepared = layer.prepare_identity(torch.tensor([[1.5, -1.0, 0.5] + [0.0] * 13]))
    rest = layer.pose(prepared, torch.zeros(1, 77, 3)).joints[0].double().numpy()
    parents = np.array([p - 1 for p in layer.rig_tree.parents[1:]])
    offsets = np.where(parents[:, None] >= 0, rest[1:] - rest[np.maximum(parents, 0) + 1], 0.0) * scale
    pose = sample_poses(t, torch.Generator().manual_seed(11), dtype=torch.float64)
    transl = np.stack([np.linspace(0, 1, t), np.full(t, 0.9), np.zeros(t)], 1)
    rot = axis_angle_to_matrix(pose).numpy()
    names = JOINT_NAMES[1:] + ("LeftHandIndexEnd_End",)
    parents = np.append(parents, JOINT_NAMES.index("LeftHandIndexEnd") - 1)
    offsets = np.vstack([offsets, [[1.0, 0.0, 0.0]]])
    rot = np.concatenate([rot, np.broadcast_to(np.eye(3), (t, 1, 3, 3))], 1)
    trans = np.broadcast_to(offsets, (t, 78, 3)).copy()
    trans[:, 0] = transl * scale
    return SkeletalMotion(names, parents, offsets, rot, trans, 60.0), pose.numpy(), transl


def test_canonical_bvh_maps_exactly():
    sk, pose, transl = _canonical_bvh()
    conv = skeletal_to_motion(sk, ConvertOptions(), "bvh: canon.bvh")
    m = conv.motion
    assert m.fps == 60.0 and m.source == "bvh: canon.bvh" and conv.stats["metres_per_unit"] == 0.01
    got = axis_angle_to_matrix(torch.as_tensor(m.pose, dtype=torch.float64))
    assert np.abs(got.numpy() - axis_angle_to_matrix(torch.as_tensor(pose)).numpy()).max() < 1e-5
    assert np.abs(m.transl - transl).max() < 1e-6
    # The identity comes back from the rest offsets, and the convention itself
    # holds: the file's world joints are the body's joints posed by the motion.
    assert m.identity_backend == "pca" and conv.stats["identity_bone_rms_mm"] < 0.01
    layer = _layer(128, torch.float32)
    with torch.no_grad():
        prepared = layer.prepare_identity(torch.as_tensor(m.identity)[None])
        out = layer.pose(prepared, torch.as_tensor(m.pose), transl=torch.as_tensor(m.transl))
    world = sk.world()[0][:, :77] / 100.0
    assert np.abs(out.joints[:, 1:].numpy() - world).max() < 1e-4  # m: the 0.1 mm


def test_units_and_bad_input():
    sk, _, _ = _canonical_bvh(t=6)
    with pytest.raises(
        ValueError,
        match=r"units 'mm' make the skeleton 0.2\d+ m tall \(expected 0.4-3.0 m\); the file is likely in cm",
    ):
        skeletal_to_motion(sk, ConvertOptions(units="mm"), "", "x.bvh: ")
    with pytest.raises(ValueError, match=r"units: expected one of m, cm, mm, in, ft.*, got 'km'"):
        skeletal_to_motion(sk, ConvertOptions(units="km"), "", "x.bvh: ")
    huge = replace(sk, offsets=sk.offsets * 1e4, translations=sk.translations * 1e4)
    with pytest.raises(
        ValueError,
        match=r"x.bvh: cannot detect the length unit: the rest skeleton is 2.2\d*e\+06 units tall, which is no",
    ):
        skeletal_to_motion(huge, ConvertOptions(), "", "x.bvh: ")
    rot = sk.rotations.copy()
    rot[[2, 4], 5, 0, 0] = np.nan
    with pytest.raises(ValueError, match=r"x.bvh: expected finite joint values, got NaN/inf in 2 frame\(s\): 2, 4$"):
        skeletal_to_motion(replace(sk, rotations=rot), ConvertOptions(), "", "x.bvh: ")
    # a root 1e300 units away was cast to float32 and refused as "NaN/inf"; 1e30 gave a body at 1e28 m
    for far, shown in ((1e30, r"1e\+28"), (1e300, r"1e\+298")):
        moved = sk.translations.copy()
        moved[3, 0, 1] = far
        with pytest.raises(ValueError, match=rf"x.bvh: expected the root within 100000 m .* {shown} m at frame 3 "):
            skeletal_to_motion(replace(sk, translations=moved), ConvertOptions(units="cm"), "", "x.bvh: ")
    few = SkeletalMotion(
        ("hip", "abdomen", "chest", "tail", "wing"),
        np.array([-1, 0, 1, 0, 2]),
        np.array([[0, 0, 0], [0, 20, 0], [0, 60, 0], [0, -90, -10], [30, 0, 0]], dtype=float),
        np.broadcast_to(np.eye(3), (3, 5, 3, 3)).copy(),
        np.zeros((3, 5, 3)),
        30.0,
    )
    with pytest.raises(ValueError, match=r"x.bvh: only 3 joint\(s\) map .*need 8\); unmapped: tail, wing; give a"):
        skeletal_to_motion(few, ConvertOptions(), "", "x.bvh: ")


def test_find_asf(tmp_path):
    for name in ("05.asf", "06.asf", "05_02.amc", "x.amc"):
        (tmp_path / name).write_text("")
    assert find_asf(tmp_path / "05_02.amc") == tmp_path / "05.asf"
    with pytest.raises(ValueError, match=r"x.amc: expected its skeleton as the only .asf .* got 05.asf, 06.asf"):
        find_asf(tmp_path / "x.amc")
    (tmp_path / "06.asf").unlink()
    assert find_asf(tmp_path / "x.amc") == tmp_path / "05.asf"


def _targets(stats: dict) -> None:
    assert stats["retarget_mean_mm"] <= 20.0 and stats["retarget_p95_mm"] <= 40.0
    assert stats["max_joint_change_deg"] <= stats["source_max_joint_change_deg"] + 5.0


@pytest.mark.skipif(not CMU.is_dir(), reason="../shared/motions/cmu is not here")
def test_real_cmu_bvh_clip(tmp_path):
    """The first 60 frames of a cgspeed/DAZ BVH (subject 02, walking)."""
    lines = (CMU / "bvh" / "002" / "02_01.bvh").read_text().splitlines()
    at = next(i for i, s in enumerate(lines) if s.startswith("Frames:"))
    clip = tmp_path / "02_01.bvh"
    clip.write_text("\n".join(lines[:at] + ["Frames: 60"] + lines[at + 1 : at + 62]) + "\n")
    conv = read_bvh(clip, ConvertOptions())
    m = conv.motion
    assert m.pose.shape == (60, 77, 3) and m.fps == pytest.approx(120.0, rel=1e-3) and m.source == "bvh: 02_01.bvh"
    assert m.identity_backend == "pca" and m.identity.shape == (16,) and np.isfinite(m.pose).all()
    assert conv.stats["metres_per_unit"] == 0.01 and conv.stats["mapped_joints"] == 21
    _targets(conv.stats)


@pytest.mark.skipif(not CMU.is_dir(), reason="../shared/motions/cmu is not here")
def test_real_cmu_amc_clip(tmp_path):
    """The first 60 frames of an AMC (subject 05) with its subject's ASF beside it."""
    shutil.copy(CMU / "asfamc" / "005" / "05.asf", tmp_path / "05.asf")
    lines = (CMU / "asfamc" / "005" / "05_02.amc").read_text().splitlines()
    (tmp_path / "05_02.amc").write_text("\n".join(lines[: lines.index("61")]) + "\n")
    conv = read_amc(tmp_path / "05_02.amc", ConvertOptions())
    m = conv.motion
    assert m.pose.shape == (60, 77, 3) and m.fps == 120.0 and m.source == "asf/amc: 05_02.amc"
    assert conv.stats["mapped_joints"] == 22 and abs(conv.stats["metres_per_unit"] - 0.0254 / 0.45) < 1e-9
    _targets(conv.stats)
