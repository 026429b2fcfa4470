"""BVH reading and writing (unibody.io.bvh), checked against bvhio, an independent parser (test-only)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from unibody.io.bvh import euler_to_matrix, matrix_to_euler, read_bvh, write_bvh
from unibody.io.skeletal import SkeletalMotion

CMU_BVH = Path(__file__).resolve().parents[2] / "shared" / "motions" / "cmu" / "bvh"
ORDERS = ("XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX")


def _bvhio_world(path: Path, frames: list[int]) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Joint names (End Sites left out), world positions (F, J, 3) and local rotations (F, J, 3, 3) by bvhio.

    Positions come from bvhio's hierarchy (which re-orients its rest frames along the bones, so
    its local rotations are not the file's); local rotations from its raw BVH keyframes.
    """
    bvhio = pytest.importorskip("bvhio")
    glm = pytest.importorskip("glm")  # bvhio's math library
    root = bvhio.readAsHierarchy(str(path))
    layout = [entry[0] for entry in root.layout()]
    raw = [entry[0] for entry in bvhio.readAsBvh(str(path)).Root.layout()]
    assert [j.Name for j in raw] == [j.Name for j in layout]
    pos, rot = [], []
    for f in frames:
        root.loadPose(f)
        pos.append([list(j.PositionWorld) for j in layout])
        rot.append([np.array(glm.mat3_cast(j.Keyframes[f].Rotation)) for j in raw])  # numpy reads glm row by row
    return [j.Name for j in layout], np.asarray(pos, dtype=np.float64), np.asarray(rot, dtype=np.float64)


def _write(tmp_path: Path, text: str, name: str = "m.bvh", newline: str = "\n") -> Path:
    path = tmp_path / name
    path.write_bytes(text.replace("\n", newline).encode())
    return path


# Unusual channel orders, 6 channels on a non-root joint, a root with rotations first, tabs.
UNUSUAL = """HIERARCHY
ROOT pelvis
{
\tOFFSET 1.5 2.0e0 -0.5
\tCHANNELS 6 Yrotation Xposition Zrotation Yposition Xrotation Zposition
\tJOINT spine
\t{
\t\tOFFSET 0 10 0.25
\t\tCHANNELS 3 Xrotation Yrotation Zrotation
\t\tJOINT head
\t\t{
\t\t\tOFFSET 0.5 8 -1
\t\t\tCHANNELS 6 Xposition Yposition Zposition Yrotation Zrotation Xrotation
\t\t\tEnd Site
\t\t\t{
\t\t\t\tOFFSET 0 3 0
\t\t\t}
\t\t}
\t}
\tJOINT leg
\t{
\t\tOFFSET 2 -1 0
\t\tCHANNELS 3 Yrotation Zrotation Xrotation
\t\tEnd Site
\t\t{
\t\t\tOFFSET 0 -9 1.5e+00
\t\t}
\t}
}
MOTION
Frames: {frames}
Frame Time: 3.3333333e-02
{data}
"""


def _unusual(tmp_path: Path, frames: int = 4, seed: int = 0, newline: str = "\n") -> tuple[Path, np.ndarray]:
    rng = np.random.default_rng(seed)
    data = rng.uniform(-170, 170, size=(frames, 18))
    data[:, [1, 3, 5, 9, 10, 11]] = rng.uniform(-20, 20, size=(frames, 6))  # positions
    body = "\n".join(" ".join(f"{v:.6e}" for v in row) for row in data)
    data = np.array([[float(v) for v in line.split()] for line in body.splitlines()])  # the values as written
    return _write(tmp_path, UNUSUAL.replace("{frames}", str(frames)).replace("{data}", body), newline=newline), data


def test_euler_round_trip_every_order_and_gimbal_lock():
    rng = np.random.default_rng(1)
    for order in ORDERS:
        a = rng.uniform(-np.pi, np.pi, size=(200, 3))
        a[:, 1] /= 2
        a[:10, 1] = np.pi / 2
        a[10:20, 1] = -np.pi / 2
        R = euler_to_matrix(a, order)
        np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
        np.testing.assert_allclose(euler_to_matrix(matrix_to_euler(R, order), order), R, atol=1e-9)
    # the BVH convention: "Zrotation Xrotation Yrotation" is Rz @ Rx @ Ry
    z, x, y = 0.3, -0.7, 1.1
    Rz = np.array([[np.cos(z), -np.sin(z), 0], [np.sin(z), np.cos(z), 0], [0, 0, 1]])
    Rx = np.array([[1, 0, 0], [0, np.cos(x), -np.sin(x)], [0, np.sin(x), np.cos(x)]])
    Ry = np.array([[np.cos(y), 0, np.sin(y)], [0, 1, 0], [-np.sin(y), 0, np.cos(y)]])
    np.testing.assert_allclose(euler_to_matrix(np.array([z, x, y]), "ZXY"), Rz @ Rx @ Ry, atol=1e-15)


def test_read_real_cmu_bvh_agrees_with_bvhio():
    path = CMU_BVH / "002" / "02_01.bvh"
    if not path.exists():
        pytest.skip("CMU motions not present")
    m = read_bvh(path)
    assert m.fps == 120.0 and m.meters_per_unit is None and m.source == "bvh"
    assert m.rotations.shape == (m.num_frames, len(m.names), 3, 3) and m.num_frames == 344
    frames = [0, 171, 343]
    names, pos_ref, _ = _bvhio_world(path, frames)
    idx = [m.names.index(n) for n in names]
    pos, _ = m.world()
    scale = np.abs(pos_ref).max()
    assert np.abs(pos[frames][:, idx] - pos_ref).max() <= 1e-6 * scale


@pytest.mark.parametrize("newline", ["\n", "\r\n"])
def test_read_unusual_channels_agrees_with_bvhio(tmp_path, newline):
    path, data = _unusual(tmp_path, newline=newline)
    m = read_bvh(path)
    assert m.names == ("pelvis", "spine", "head", "head_End", "leg", "leg_End")
    assert m.parents.tolist() == [-1, 0, 1, 2, 0, 4]
    assert m.fps == 30.0
    # 6-channel joints take their positions from the channels; others keep their offsets
    np.testing.assert_array_equal(m.translations[:, 0], data[:, [1, 3, 5]])
    np.testing.assert_array_equal(m.translations[:, 2], data[:, [9, 10, 11]])
    np.testing.assert_array_equal(m.translations[:, 4], np.broadcast_to([2.0, -1.0, 0.0], (4, 3)))
    np.testing.assert_array_equal(m.rotations[:, 3], np.broadcast_to(np.eye(3), (4, 3, 3)))
    np.testing.assert_allclose(m.rotations[:, 0], euler_to_matrix(np.radians(data[:, [0, 2, 4]]), "YZX"), atol=1e-15)
    names, pos_ref, rot_ref = _bvhio_world(path, list(range(4)))
    assert names == ["pelvis", "spine", "head", "leg"]
    idx = [m.names.index(n) for n in names]
    pos, _ = m.world()
    scale = np.abs(pos_ref).max()
    assert np.abs(pos[:, idx] - pos_ref).max() <= 1e-6 * scale
    assert np.abs(m.rotations[:, idx] - rot_ref).max() <= 1e-6


def test_joint_names_may_hold_spaces(tmp_path):
    text = UNUSUAL.replace("JOINT leg", "JOINT left leg {").replace("\tJOINT left leg {\n\t{", "\tJOINT left leg {")
    text = text.replace("{frames}", "1").replace("{data}", "0 " * 18)
    m = read_bvh(_write(tmp_path, text))
    assert m.names[-2:] == ("left leg", "left leg_End") and m.parents[-2:].tolist() == [0, 4]


def test_read_bvh_speed_on_a_real_file():
    path = CMU_BVH / "002" / "02_01.bvh"
    if not path.exists():
        pytest.skip("CMU motions not present")
    t = time.perf_counter()
    read_bvh(path)
    assert time.perf_counter() - t < 1.0  # about 30 ms here; a per-value Python parse is ~10x slower


@pytest.mark.slow
def test_read_every_cmu_bvh():
    files = sorted(CMU_BVH.glob("*/*.bvh"))
    if len(files) < 68:
        pytest.skip("CMU motions not present")
    t = time.perf_counter()
    frames = 0
    for path in files:
        m = read_bvh(path)
        frames += m.num_frames
        assert m.num_frames > 0 and np.isfinite(m.rotations).all() and np.isfinite(m.translations).all()
    print(f"{len(files)} BVH files, {frames} frames in {time.perf_counter() - t:.1f} s")


HEADER = UNUSUAL.split("MOTION")[0]


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "empty file"),
        ("hello world\n", "HIERARCHY ... MOTION"),
        (HEADER, "expected a MOTION section"),
        (HEADER.replace("\t}\n}\n", "\t}\n") + "MOTION\nFrames: 1\nFrame Time: 0.1\n" + "0 " * 18, "braces"),
        (HEADER + "MOTION\nFrames: 1\nFrame Time: 0.1\n" + "0 " * 17, "line 33 (frame 0): expected 18 values, got 17"),
        (
            HEADER + "MOTION\nFrames: 3\nFrame Time: 0.1\n" + ("0 " * 18 + "\n") * 2,
            "expected 3 frames (Frames:), got 2",
        ),
        (HEADER + "MOTION\nFrames: 2\nFrame Time: 0.1\n" + "0 " * 18 + "\n" + "0 nan " + "0 " * 16, "indices 1)"),
        (HEADER + "MOTION\nFrames: 1\nFrame Time: 0.1\n" + "0 inf " + "0 " * 16, "NaN/inf in 1 frames"),
        (HEADER + "MOTION\nFrames: 1\nFrame Time: 0.1\n" + "0 x " + "0 " * 16, "expected numbers, got 'x'"),
        (HEADER + "MOTION\nFrames: 99999999999\nFrame Time: 0.1\n", "frames, got Frames: 99999999999"),
        (HEADER + "MOTION\nFrames: 1\nFrame Time: 0\n" + "0 " * 18, "Frame Time"),
        (HEADER + "MOTION\nFrame Time: 0.1\n" + "0 " * 18, "expected 'Frames:'"),
        (HEADER.replace("Xrotation Yrotation Z", "Xrotation Wrotation Z") + "MOTION\n", "got 'Wrotation'"),
        (HEADER.replace("OFFSET 0 10 0.25", "OFFSET 0 nan 0.25") + "MOTION\n", "finite number for OFFSET y"),
        (HEADER + "ROOT other\n{\n}\nMOTION\n", "line 30: expected MOTION after the root's closing brace, got 'ROOT'"),
        (HEADER.replace("JOINT spine", "JOINT") + "MOTION\n", "expected a joint name, got '{'"),
    ],
)
def test_read_bvh_errors(tmp_path, text, message):
    path = _write(tmp_path, text)
    with pytest.raises(ValueError) as err:
        read_bvh(path)
    msg = str(err.value)
    assert "\n" not in msg and str(path) in msg and message in msg, msg


def test_read_bvh_refuses_absurd_joint_counts(tmp_path, monkeypatch):
    import unibody.io.bvh as bvh

    monkeypatch.setattr(bvh, "MAX_JOINTS", 3)
    path, _ = _unusual(tmp_path)
    with pytest.raises(ValueError, match="at most 3 joints"):
        read_bvh(path)


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation angle (radians) between two stacks of rotations: ``|A - B|_F = 2 sqrt(2) sin(angle / 2)``."""
    return 2.0 * np.arcsin(np.clip(np.linalg.norm(a - b, axis=(-2, -1)) / (2.0 * np.sqrt(2.0)), 0.0, 1.0))


def _random_skeleton(rng: np.random.Generator, frames: int):
    names = ["hips", "spine", "head", "l_leg", "l_foot", "r_leg", "neck_twist"]
    parents = np.array([-1, 0, 1, 0, 3, 0, 1])
    offsets = rng.normal(scale=0.3, size=(7, 3))  # metres
    angles = rng.uniform(-np.pi, np.pi, size=(frames, 7, 3))
    rotations = euler_to_matrix(angles, "XYZ")
    # gimbal lock in the written order ZXY: middle (X) angle at +-90 degrees
    rotations[:3, 2] = euler_to_matrix(
        np.array([[0.4, np.pi / 2, -1.0], [2.0, -np.pi / 2, 0.3], [0, np.pi / 2, 0]]), "ZXY"
    )
    root = rng.normal(size=(frames, 3))
    return names, parents, offsets, rotations, root


@pytest.mark.parametrize("order", ["ZXY", "XYZ"])
def test_write_read_round_trip(tmp_path, order):
    rng = np.random.default_rng(7)
    names, parents, offsets, rotations, root = _random_skeleton(rng, 50)
    path = tmp_path / "out.bvh"
    write_bvh(path, names, parents, offsets, rotations, root, 60.0, order=order, end_sites={"head": [0, 0.2, 0]})
    m = read_bvh(path)
    assert m.fps == 60.0 and m.num_frames == 50
    idx = [m.names.index(n) for n in names]
    assert m.parents[idx[1:]].tolist() == [idx[p] for p in parents[1:]]
    assert _angle(m.rotations[:, idx], rotations).max() <= 1e-4
    np.testing.assert_allclose(m.offsets[m.names.index("head_End")], [0, 0.2, 0], atol=1e-9)
    ref = SkeletalMotion(tuple(names), parents, offsets, rotations, _translations(offsets, root), 60.0)
    pos_ref, _ = ref.world()
    pos, _ = m.world()
    assert np.abs(pos[:, idx] - pos_ref).max() <= 1e-4  # metres: 0.1 mm
    # an independent parser reads the same rotations
    names_b, pos_b, rot_b = _bvhio_world(path, [0, 1, 2, 49])
    idx_b = [names.index(n) for n in names_b]
    assert _angle(rot_b, rotations[[0, 1, 2, 49]][:, idx_b]).max() <= 1e-4
    assert np.abs(pos_b - pos_ref[[0, 1, 2, 49]][:, idx_b]).max() <= 1e-4


def _translations(offsets: np.ndarray, root: np.ndarray) -> np.ndarray:
    t = np.broadcast_to(offsets, (root.shape[0], *offsets.shape)).copy()
    t[:, 0] = root
    return t


def test_write_bvh_is_atomic_and_checks_its_arguments(tmp_path):
    rng = np.random.default_rng(3)
    names, parents, offsets, rotations, root = _random_skeleton(rng, 4)
    path = tmp_path / "out.bvh"
    path.write_text("previous")
    bad_rot = rotations.copy()
    bad_rot[2, 1, 0, 0] = np.nan
    scaled = rotations.copy()
    scaled[3, 2] *= 1.01
    mirrored = rotations.copy()
    mirrored[1, 4] *= -1.0
    cases = [
        (dict(rotations=bad_rot), "rotations: expected finite values"),
        (dict(rotations=scaled), "non-rotation at frame 3, joint 'head'"),
        (dict(rotations=mirrored), "non-rotation at frame 1, joint 'l_foot'"),
        (dict(rotations=rotations[:, :3]), "rotations: expected shape (*, 7, 3, 3)"),
        (dict(root_positions=root[:2]), "root_positions: expected shape (4, 3)"),
        (dict(parents=np.array([0, 0, 1, 0, 3, 0, 1])), "parents: expected -1 for the root"),
        (dict(parents=np.array([-1, 2, 1, 0, 3, 0, 1])), "parents before children"),
        (dict(names=["a b", *names[1:]]), "names: expected names without spaces"),
        (dict(names=[names[1], *names[1:]]), "names: expected unique names"),
        (dict(fps=0.0), "fps: expected a positive number"),
        (dict(order="XXZ"), "order: expected a permutation"),
    ]
    args = dict(names=names, parents=parents, offsets=offsets, rotations=rotations, root_positions=root, fps=30.0)
    for change, message in cases:
        with pytest.raises(ValueError) as err:
            write_bvh(path, **{**args, **change})
        assert message in str(err.value) and "\n" not in str(err.value), str(err.value)
    assert path.read_text() == "previous"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.bvh"]  # no temporary file left behind
