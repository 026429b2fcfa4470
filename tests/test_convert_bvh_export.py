"""The canonical BVH export (unibody.convert.bvh_export), read back by bvhio (independent, test-only)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import bvhio_positions
from unibody import JOINT_NAMES
from unibody.convert import ConvertOptions
from unibody.convert._body import body_for
from unibody.convert.bvh_export import (
    BVH_UNITS_PER_METRE,
    CANONICAL_BVH_NAMES,
    canonical_from_bvh,
    is_canonical_bvh,
    write_bvh,
)
from unibody.geometry.rotations import axis_angle_to_matrix
from unibody.io.bvh import read_bvh
from unibody.motion import Motion

FRAMES = 12


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation angle (radians) between two stacks of rotations: ``|A - B|_F = 2 sqrt(2) sin(angle / 2)``."""
    return 2.0 * np.arcsin(np.clip(np.linalg.norm(a - b, axis=(-2, -1)) / (2.0 * np.sqrt(2.0)), 0.0, 1.0))


def _matrices(pose: np.ndarray) -> np.ndarray:
    return axis_angle_to_matrix(torch.from_numpy(pose.astype(np.float64))).numpy()


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> tuple[Motion, Path, np.ndarray]:
    """A random motion of a random PCA identity, its BVH, and the posed joints (T, 78, 3) of the body."""
    rng = np.random.default_rng(34)
    pose = rng.normal(scale=0.5, size=(FRAMES, 77, 3))
    pose[0] = 0.0  # the T-pose
    pose[1, :, :] = [0.0, np.pi - 1e-3, 0.0]  # near half turns everywhere
    pose[2, :, :] = [np.pi / 2, 0.0, 0.0]  # +-90 deg about X: gimbal lock of the ZXY channels
    transl = rng.normal(scale=0.5, size=(FRAMES, 3)) + [0.0, 0.9, 0.0]
    identity = rng.normal(scale=0.5, size=128).astype(np.float32)
    motion = Motion(
        pose.astype(np.float32), transl.astype(np.float32), fps=50.0, identity=identity, identity_backend="pca"
    )
    path = tmp_path_factory.mktemp("bvh") / "take.bvh"
    write_bvh(motion, path, ConvertOptions(dtype="float64"))  # one layer for the export and the reference
    layer, prepared = body_for(motion, torch.float64)
    with torch.no_grad():
        out = layer.pose(
            prepared,
            torch.from_numpy(motion.pose.astype(np.float64)),
            transl=torch.from_numpy(motion.transl.astype(np.float64)),
        )
    return motion, path, out.joints.numpy()


def test_bvhio_reads_the_same_rotations_and_joint_positions(exported):
    bvhio = pytest.importorskip("bvhio")
    glm = pytest.importorskip("glm")
    motion, path, joints = exported
    container = bvhio.readAsBvh(str(path))
    assert container.FrameCount == FRAMES and container.FrameTime == pytest.approx(1 / 50.0, rel=1e-9)
    raw = [entry[0] for entry in container.Root.layout()]
    assert [j.Name for j in raw] == list(CANONICAL_BVH_NAMES)  # bvhio leaves End Sites out
    rot = np.array([[np.array(glm.mat3_cast(j.Keyframes[f].Rotation)) for j in raw] for f in range(FRAMES)])
    assert _angle(rot, _matrices(motion.pose)).max() <= 1e-4
    pos = bvhio_positions(path, FRAMES) / BVH_UNITS_PER_METRE
    assert np.abs(pos - joints[:, 1:]).max() <= 1e-4  # 0.1 mm


def test_file_layout(exported):
    _, path, _ = exported
    lines = path.read_text().splitlines()
    assert lines[:3] == ["HIERARCHY", "ROOT Hips", "{"]
    assert lines[4].split() == [
        "CHANNELS",
        "6",
        "Xposition",
        "Yposition",
        "Zposition",
        "Zrotation",
        "Xrotation",
        "Yrotation",
    ]
    joints = [line.split()[1] for line in lines if line.strip().startswith("JOINT")]
    assert sorted(joints) == sorted(JOINT_NAMES[2:])
    assert sum(line.strip().startswith("CHANNELS 3 ") for line in lines) == 76
    assert lines[lines.index("MOTION") + 1 : lines.index("MOTION") + 3] == [f"Frames: {FRAMES}", "Frame Time: 0.02"]


def test_offsets_are_the_identitys_tpose_in_centimetres(exported):
    motion, path, joints = exported
    m = read_bvh(path)
    assert is_canonical_bvh(m)
    pos, _ = m.world()
    idx = [m.names.index(n) for n in CANONICAL_BVH_NAMES]
    # frame 0 is the T-pose: the file's rest offsets placed at transl reproduce it
    np.testing.assert_allclose(pos[0, idx] / 100.0, joints[0, 1:], atol=1e-7)
    # the identity matters: the mean body's T-pose differs by far more than the tolerance
    layer, mean = body_for(Motion(motion.pose[:1], motion.transl[:1]), torch.float64)
    with torch.no_grad():
        mean_joints = layer.pose(mean, torch.zeros(1, 77, 3, dtype=torch.float64)).joints.numpy()[0, 1:]
    tpose = pos[0, idx] / 100.0 - pos[0, idx[0]] / 100.0
    assert np.abs(tpose - mean_joints).max() > 1e-3


def test_read_back_maps_by_name_exactly(exported):
    motion, path, _ = exported
    m = read_bvh(path)
    pose, transl = canonical_from_bvh(m)
    assert pose.shape == (FRAMES, 77, 3) and pose.dtype == np.float32
    assert _angle(_matrices(pose), _matrices(motion.pose)).max() <= 1e-4
    np.testing.assert_allclose(transl, motion.transl, atol=1e-6)
    assert m.fps == 50.0


def test_is_canonical_bvh_refuses_other_skeletons(exported):
    _, path, _ = exported
    m = read_bvh(path)
    k = m.names.index("LeftForeArm")
    parents = m.parents.copy()
    parents[k] = m.names.index("Hips")
    moved = type(m)(m.names, parents, m.offsets, m.rotations, m.translations, m.fps)
    assert not is_canonical_bvh(moved)
    names = tuple("LeftElbow" if n == "LeftForeArm" else n for n in m.names)
    renamed = type(m)(names, m.parents, m.offsets, m.rotations, m.translations, m.fps)
    assert not is_canonical_bvh(renamed)
    with pytest.raises(ValueError, match="1 joints missing \\('LeftForeArm'"):
        canonical_from_bvh(renamed)


def test_bad_motions_are_refused_and_nothing_is_written(tmp_path):
    out = tmp_path / "out.bvh"
    out.write_text("keep")
    good = np.zeros((3, 77, 3), np.float32)
    nan = good.copy()
    nan[2, 5, 1] = np.nan
    cases = [
        (Motion(nan, np.zeros((3, 3), np.float32)), "motion.pose: expected finite values, got NaN/inf in frames 2"),
        (Motion(good[:, :76], np.zeros((3, 3), np.float32)), "motion.pose: expected shape (T, 77, 3)"),
        (Motion(good, np.zeros((2, 3), np.float32)), "motion.transl: expected shape (3, 3)"),
        (Motion(good, np.zeros((3, 3), np.float32), fps=-1.0), "motion.fps"),
    ]
    for motion, message in cases:
        with pytest.raises(ValueError) as err:
            write_bvh(motion, out, ConvertOptions())
        assert message in str(err.value) and "\n" not in str(err.value), str(err.value)
    assert out.read_text() == "keep" and [p.name for p in tmp_path.iterdir()] == ["out.bvh"]
