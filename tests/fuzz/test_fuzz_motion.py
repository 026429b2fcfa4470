"""Motion and mesh-sequence files, and the CLI that reads them, under arbitrary input.

Property: a ``ValueError`` that names the file, or a fully checked result (right shapes,
finite values, fps > 0); the CLI answers exit 0 or 3 with one error line, never a crash.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from unibody.cli import main
from unibody.motion import MOTION_FORMAT, Motion, load_mesh_sequence, load_motion, save_motion
from unibody.rig import JOINT_NAMES

FLOATS = st.sampled_from([0.0, 1.0, -1.0, 1e-30, 1e30, np.inf, -np.inf, np.nan, 30.0, 120.0])


def _valid_motion(frames: int = 2) -> dict[str, np.ndarray]:
    return {
        "format": np.asarray(MOTION_FORMAT),
        "pose": np.zeros((frames, 77, 3), np.float32),
        "transl": np.zeros((frames, 3), np.float32),
        "joint_names": np.asarray(JOINT_NAMES[1:]),
        "fps": np.asarray(30.0, np.float32),
        "identity": np.zeros(10, np.float32),
        "identity_backend": np.asarray("pca"),
    }


def _array(draw, value: np.ndarray) -> np.ndarray:
    """A mutation of one field: another shape, dtype, or poisoned values."""
    kind = draw(st.sampled_from(["shape", "dtype", "poison", "string", "keep"]))
    if kind == "shape":
        shape = tuple(draw(st.lists(st.integers(0, 4), max_size=4)))
        return np.zeros(shape, np.float32)
    if kind == "dtype" and value.dtype.kind not in "US":
        return value.astype(draw(st.sampled_from([np.int64, np.bool_, np.float16, np.complex64, np.uint8])))
    if kind == "poison" and value.dtype.kind == "f":
        out = value.copy().reshape(-1)
        if out.size:
            out[draw(st.integers(0, out.size - 1))] = draw(FLOATS)
        return out.reshape(value.shape)
    if kind == "string":
        return np.asarray(draw(st.text(max_size=8)))
    return value


@st.composite
def motion_fields(draw) -> dict[str, np.ndarray]:
    fields = _valid_motion(draw(st.integers(0, 3)))
    for key in draw(st.lists(st.sampled_from(sorted(fields)), max_size=3, unique=True)):
        if draw(st.booleans()):
            del fields[key]
        else:
            fields[key] = _array(draw, fields[key])
    return fields


def _check_motion(motion: Motion) -> None:
    t = motion.pose.shape[0]
    assert motion.pose.shape == (t, 77, 3) and motion.transl.shape == (t, 3)
    assert np.isfinite(motion.pose).all() and np.isfinite(motion.transl).all()
    assert np.isfinite(motion.fps) and motion.fps > 0
    assert motion.identity is None or (motion.identity.ndim == 1 and np.isfinite(motion.identity).all())


@given(fields=motion_fields())
def test_motion_fields(tmp_path_factory, fields):
    path = tmp_path_factory.mktemp("m") / "motion.npz"
    np.savez(path, **fields)
    try:
        motion = load_motion(path)
    except ValueError as exc:
        assert str(path) in str(exc)
        return
    _check_motion(motion)


def _mutations(data: bytes):
    return st.one_of(
        st.integers(0, len(data)).map(lambda n: data[:n]),  # truncated
        st.tuples(st.integers(0, len(data) - 1), st.integers(1, 255)).map(
            lambda f: data[: f[0]] + bytes([data[f[0]] ^ f[1]]) + data[f[0] + 1 :]  # one byte flipped
        ),
        st.binary(max_size=512),  # anything
    )


def _motion_bytes(tmp: Path) -> bytes:
    save_motion(tmp / "valid.npz", Motion(np.zeros((2, 77, 3)), np.zeros((2, 3)), 30.0, np.zeros(10), "pca"))
    return (tmp / "valid.npz").read_bytes()


@pytest.fixture(scope="module")
def motion_bytes(tmp_path_factory) -> bytes:
    return _motion_bytes(tmp_path_factory.mktemp("valid"))


@given(data=st.data())
def test_motion_bytes(tmp_path_factory, motion_bytes, data):
    path = tmp_path_factory.mktemp("b") / "motion.npz"
    path.write_bytes(data.draw(_mutations(motion_bytes)))
    try:
        motion = load_motion(path)
    except ValueError as exc:
        assert str(path) in str(exc)
        return
    _check_motion(motion)


@given(
    vertices=st.one_of(
        st.tuples(st.integers(0, 3), st.integers(0, 5), st.integers(0, 4)).map(lambda s: np.zeros(s, np.float32)),
        st.sampled_from([np.zeros((1, 4, 3), np.int32), np.full((1, 4, 3), np.nan), np.zeros(3), np.asarray("v")]),
    ),
    topology=st.one_of(st.text(max_size=10).map(np.asarray), st.just(np.zeros(2))),
    identity=st.one_of(st.none(), st.just(np.zeros(0)), st.just(np.full(6, np.inf)), st.just(np.zeros((2, 3)))),
)
def test_mesh_sequence_fields(tmp_path_factory, vertices, topology, identity):
    path = tmp_path_factory.mktemp("s") / "seq.npz"
    extra = {} if identity is None else {"identity": identity}
    np.savez(path, vertices=vertices, topology=topology, **extra)
    try:
        seq = load_mesh_sequence(path)
    except ValueError as exc:
        assert str(path) in str(exc)
        return
    assert seq.vertices.ndim == 3 and seq.vertices.shape[2] == 3 and np.isfinite(seq.vertices).all()
    assert isinstance(seq.topology, str)
    assert seq.identity is None or np.isfinite(seq.identity).all()


@settings(max_examples=12, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_cli_pose_answers_0_or_3(tmp_path_factory, capsys, motion_bytes, data):  # capsys is read after each run
    folder = tmp_path_factory.mktemp("cli")
    src = folder / "motion.npz"
    if data.draw(st.booleans()):
        src.write_bytes(data.draw(_mutations(motion_bytes)))
    else:
        np.savez(src, **data.draw(motion_fields()))
    code = main(["pose", str(src), "--out", str(folder / "meshes.npz")])
    err = capsys.readouterr().err
    assert code in (0, 3) and "Traceback" not in err, err
    names = sorted(p.name for p in folder.iterdir())
    assert names == (["meshes.npz", "motion.npz"] if code == 0 else ["motion.npz"])  # no stray temp or lock
    if code == 0:
        with zipfile.ZipFile(folder / "meshes.npz") as z:
            assert z.testzip() is None
