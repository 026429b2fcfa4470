"""py-soma-x motion npz in and out: our motions round-trip exactly, and every variant py-soma-x
writes (centimetres, matrices, absolute rotations, a kept Root, its own joint order and
orientations) reads as the same motion."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from unibody import JOINT_NAMES
from unibody.convert import ConvertOptions
from unibody.convert.formats import reader
from unibody.convert.soma import read_soma, write_soma
from unibody.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from unibody.motion import Motion
from unibody.rig import Rig

OPTS = ConvertOptions()


@pytest.fixture(scope="module")
def orient() -> torch.Tensor:
    return Rig.canonical().tpose_orient.double()


@pytest.fixture(scope="module")
def parents() -> list[int]:
    return list(Rig.canonical().tree.parents)


def _motion(frames: int = 6, seed: int = 0, identity: bool = True) -> Motion:
    gen = np.random.default_rng(seed)
    return Motion(
        pose=(0.3 * gen.standard_normal((frames, 77, 3))).astype(np.float32),
        transl=(gen.standard_normal((frames, 3)) + [0, 1, 0]).astype(np.float32),
        fps=59.94,
        identity=gen.standard_normal(12).astype(np.float32) if identity else None,
        identity_backend="pca" if identity else None,
    )


def _soma_fields(m: Motion, orient: torch.Tensor, parents: list[int], *, absolute=False, matrix=False,
                 keep_root=False, unit="meters", order=None, own_orient=None, root_rot=None) -> dict:  # fmt: skip
    """A py-soma-x file of ``m`` built independently of read_soma: R_abs,j = O_pᵀ R_rel,j O_j."""
    R_rel = axis_angle_to_matrix(torch.from_numpy(m.pose).double())  # (N, 77, 3, 3)
    p = torch.tensor([max(q, 0) for q in parents[1:]])
    R = orient[p].transpose(-1, -2) @ R_rel @ orient[1:]  # absolute local rotations, joints 1..77
    names = list(JOINT_NAMES[1:])
    own = orient.clone() if own_orient is None else own_orient
    if keep_root:
        turn = torch.eye(3, dtype=R.dtype) if root_rot is None else root_rot
        root = turn.expand(len(R), 1, 3, 3)
        if root_rot is not None:  # the file's Hips is below a turned Root: R_hips' = Rootᵀ R_hips
            R = R.clone()
            R[:, 0] = root_rot.T @ R[:, 0]
        R = torch.cat([root, R], 1)
        names = ["Root", *names]
        jo = own
    else:
        jo = own[1:]
    if not absolute:  # relative to the file's orientations: R_rel' = O'_p R_abs O'_jᵀ
        rel = []
        for k, name in enumerate(names):
            j = JOINT_NAMES.index(name)
            if j == 0:
                Op = torch.eye(3, dtype=R.dtype)  # the Root's parent is the world
            else:  # without a Root in the file, the Hips' parent orientation is the canonical one
                Op = own[parents[j]] if (parents[j] > 0 or keep_root) else orient[0]
            rel.append(Op @ R[:, k] @ own[j].T)
        R = torch.stack(rel, 1)
    order = np.arange(len(names)) if order is None else order(len(names))
    R, names = R[:, order], [names[i] for i in order]
    fields = {
        "poses": (R if matrix else matrix_to_axis_angle(R)).numpy(),
        "transl": m.transl.astype(np.float64) / {"meters": 1, "centimeters": 0.01, "millimeters": 0.001}[unit],
        "joint_names": np.asarray(names),
        "identity_model_type": np.asarray(m.identity_backend or "none"),
        "identity_coeffs": np.repeat(m.identity[None], len(m.pose), 0) if m.identity is not None else np.zeros((1, 0)),
        "keep_root": np.asarray(keep_root),
        "absolute_pose": np.asarray(absolute),
        "rotation_repr": np.asarray("matrix" if matrix else "rotvec"),
        "unit": np.asarray(unit),
        "mocap_frame_rate": np.asarray(m.fps),
    }
    if not absolute:
        fields["joint_orient"] = jo[order].numpy()
    return fields


def _save(path: Path, fields: dict) -> Path:
    np.savez_compressed(path, **fields)
    return path


def _same(a: Motion, b: Motion, atol: float = 1e-6) -> None:
    assert b.pose.shape == a.pose.shape and b.pose.dtype == np.float32
    np.testing.assert_allclose(b.pose, a.pose, atol=atol, rtol=0)
    np.testing.assert_allclose(b.transl, a.transl, atol=atol, rtol=0)
    assert b.fps == pytest.approx(a.fps, rel=1e-6)


def test_motion_soma_motion_is_exact(tmp_path):
    m = _motion()
    path = tmp_path / "m.soma.npz"
    write_soma(m, path, OPTS)
    with np.load(path, allow_pickle=False) as data:
        assert data["poses"].shape == (6, 77, 3) and str(data["rotation_repr"]) == "rotvec"
        assert not bool(data["keep_root"]) and not bool(data["absolute_pose"]) and str(data["unit"]) == "meters"
        assert data["joint_orient"].shape == (77, 3, 3) and tuple(data["joint_names"]) == JOINT_NAMES[1:]
    got = read_soma(path, OPTS)
    _same(m, got.motion, atol=0)
    np.testing.assert_array_equal(got.motion.identity, m.identity)
    assert got.motion.identity_backend == "pca" and got.warnings == () and got.stats["frames"] == 6
    plain = _motion(identity=False)
    write_soma(plain, path, OPTS)
    back = read_soma(path, OPTS).motion
    assert back.identity is None and back.identity_backend is None


@pytest.mark.parametrize(
    "variant",
    [
        {"unit": "centimeters"},
        {"unit": "millimeters", "matrix": True},
        {"matrix": True},
        {"absolute": True},
        {"absolute": True, "matrix": True, "keep_root": True},
        {"keep_root": True},
        {"order": lambda n: np.random.default_rng(3).permutation(n)},
        {"own_orient": "random"},
        {"keep_root": True, "root_rot": "turned"},
    ],
    ids=[
        "cm",
        "mm-matrix",
        "matrix",
        "absolute",
        "absolute-matrix-root",
        "root",
        "shuffled",
        "own-orient",
        "root-turned",
    ],
)
def test_soma_variants_read_as_the_same_motion(tmp_path, orient, parents, variant):
    m = _motion(identity=True)
    variant = dict(variant)
    if variant.get("own_orient") == "random":
        aa = torch.from_numpy(np.random.default_rng(5).standard_normal((78, 3)))
        variant["own_orient"] = axis_angle_to_matrix(aa)
    if variant.get("root_rot") == "turned":
        variant["root_rot"] = axis_angle_to_matrix(torch.tensor([0.0, 1.2, 0.3], dtype=torch.float64))
    path = _save(tmp_path / "v.npz", _soma_fields(m, orient, parents, **variant))
    got = read_soma(path, OPTS)
    _same(m, got.motion, atol=2e-6)
    assert got.motion.identity_backend == "pca"


def test_soma_frame_rate_and_identity_rules(tmp_path, orient, parents):
    m = _motion()
    fields = _soma_fields(m, orient, parents)
    del fields["mocap_frame_rate"]
    fields["identity_model_type"] = np.asarray("mhr")
    got = read_soma(_save(tmp_path / "a.npz", fields), OPTS)
    assert got.motion.fps == 30.0 and got.motion.identity is None
    assert any("assumed 30 fps" in w for w in got.warnings)
    assert any("'mhr' is not played here" in w for w in got.warnings)
    fields = _soma_fields(m, orient, parents)
    fields["identity_coeffs"] = np.random.default_rng(0).standard_normal((6, 12))
    fields["fps"] = np.asarray(120)
    got = read_soma(_save(tmp_path / "b.npz", fields), OPTS)
    assert got.motion.fps == 120 and any("vary over the frames" in w for w in got.warnings)
    np.testing.assert_allclose(got.motion.identity, fields["identity_coeffs"][0], rtol=1e-6)


def test_soma_reader_errors_name_the_file_and_field(tmp_path, orient, parents):
    m = _motion(frames=3)
    good = _soma_fields(m, orient, parents)
    nan_transl = good["transl"].copy()
    nan_transl[2, 1] = np.nan
    not_rotation = _soma_fields(m, orient, parents, matrix=True)["poses"].copy()
    not_rotation[1, 4] *= 2
    cases = [
        (
            {"joint_names": np.asarray([*JOINT_NAMES[1:76], "Tail", "Tail2"])},
            r"joint_names: 2 SOMA joint\(s\) missing: RightToeBase, RightToeEnd",
        ),
        ({"transl": nan_transl}, r"transl: non-finite values in 1 frame\(s\), first at frame 2"),
        ({"unit": np.asarray("furlongs")}, "unit: expected meters, centimeters or millimeters, got 'furlongs'"),
        ({"rotation_repr": np.asarray("matrix")}, r"poses: expected shape \(N, 77, 3, 3\), got \(3, 77, 3\)"),
        ({"rotation_repr": np.asarray("quat")}, "rotation_repr: expected 'rotvec' or 'matrix'"),
        (
            {"rotation_repr": np.asarray("matrix"), "poses": not_rotation},
            "poses: frame 1, joint 4 is not a rotation matrix",
        ),
        ({"fps": np.asarray(-1.0)}, "fps: expected a positive number"),
        ({"fps": np.asarray(30 + 5j)}, r"fps: expected a positive number, got np.complex128\(30\+5j\)"),  # was 30
        ({"joint_orient": None}, "missing field 'joint_orient'"),
        # found by tests/fuzz/test_fuzz_soma.py: a raw numpy error, then motions read from garbage
        ({"poses": good["poses"][:0], "transl": good["transl"][:0]}, r"poses: expected at least one frame"),
        ({"joint_orient": good["joint_orient"] * 100}, r"joint_orient: joint 0 is not a rotation matrix"),
        ({"transl": good["transl"] + 1e30}, r"transl: expected the root within 100000 m"),
        (
            {"transl": good["transl"] + 1e300},
            r"transl: expected the root within 100000 m .* got 1e\+300 m",
        ),  # was "NaN/inf"
        ({"identity_coeffs": good["identity_coeffs"].astype(np.float64) * 1e300}, r"identity: expected values within"),
    ]
    for change, message in cases:
        fields = {**good, **change}
        fields = {k: v for k, v in fields.items() if v is not None}
        path = _save(tmp_path / "bad.npz", fields)
        with pytest.raises(ValueError, match=f"bad.npz: {message}"):
            reader("soma")(path, OPTS)  # as unibody convert and unibody view read it
