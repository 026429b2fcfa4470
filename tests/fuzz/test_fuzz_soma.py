"""Property: a py-soma-x-like ``.npz`` reads as a motion every writer takes, or a ValueError names the file.

Input: a valid py-soma-x motion (rotation vectors or matrices, T-pose-relative with
``joint_orient`` or absolute, with or without the Root, metres or centimetres, a PCA, Anny or
foreign identity), then one or two fields dropped, added, or replaced by arrays of other shapes,
dtypes (int, bool, complex, float16, strings), values (NaN, inf, 1e300, 0) or sizes (no frame);
or ``joint_orient`` / a matrix pose made a non-rotation (zeros, 100 I, a reflection).
:func:`unibody.convert.soma.read_soma`, as ``unibody convert`` and ``unibody view`` call it
(:func:`unibody.convert.formats.reader`), must return a motion of at least one frame that
:func:`unibody.motion.check_motion` accepts (finite, within float32 and 1e5 m, a valid rate),
read from genuine rotations only; or raise a ``ValueError`` whose message starts with the file's
path. Seeded and bounded (tests/conftest.py profiles).
"""

from __future__ import annotations

import warnings

import numpy as np
import torch
from hypothesis import event, given
from hypothesis import strategies as st

from conftest import change_fields
from unibody import JOINT_NAMES
from unibody.convert import ConvertOptions
from unibody.convert.formats import reader
from unibody.geometry.rotations import axis_angle_to_matrix
from unibody.motion import check_motion
from unibody.rig import Rig

_VALUES = [np.nan, np.inf, -np.inf, 1e300, 1e30, 0.0, -1.0, 30.0]
_NOT_ROTATIONS = {"zero": np.zeros((3, 3)), "scaled": 100 * np.eye(3), "mirror": np.diag([1.0, 1.0, -1.0])}


def _file(draw) -> dict:
    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    t = 3
    keep_root = draw(st.booleans())
    names = list(JOINT_NAMES if keep_root else JOINT_NAMES[1:])
    matrix = draw(st.booleans())
    rotvec = rng.normal(scale=0.3, size=(t, len(names), 3))
    poses = axis_angle_to_matrix(torch.from_numpy(rotvec)).numpy() if matrix else rotvec
    orient = Rig.canonical().tpose_orient.double().numpy()[0 if keep_root else 1 :]
    backend = draw(st.sampled_from(["pca", "anny", "none", "smplx"]))
    coeffs = {"pca": rng.normal(size=(1, 12)), "anny": np.full((1, 6), 0.5), "none": np.zeros((1, 0))}
    return {
        "poses": poses,
        "transl": rng.normal(size=(t, 3)) * (100.0 if draw(st.booleans()) else 1.0),
        "joint_names": np.asarray(names),
        "identity_model_type": np.asarray(backend),
        "identity_coeffs": coeffs.get(backend, rng.normal(size=(1, 10))),
        "keep_root": np.asarray(keep_root),
        "absolute_pose": np.asarray(draw(st.booleans())),
        "joint_orient": orient,
        "rotation_repr": np.asarray("matrix" if matrix else "rotvec"),
        "unit": np.asarray(draw(st.sampled_from(["meters", "centimeters", "mm"]))),
        "fps": np.asarray(draw(st.sampled_from([30.0, 120.0, 59.94]))),
    }


def _replacement(draw, old: np.ndarray) -> np.ndarray:  # noqa: ANN001
    kind = draw(st.sampled_from(["value", "value", "value", "rotation", "shape", "dtype", "empty", "scalar", "string"]))
    event(f"replace: {kind}")
    if kind == "value" and old.size and old.dtype.kind == "f":
        new = old.copy()
        new.flat[draw(st.integers(0, old.size - 1))] = draw(st.sampled_from(_VALUES))
        return new
    if kind == "rotation" and old.ndim >= 3 and old.shape[-2:] == (3, 3) and old.size:
        new = old.copy().reshape(-1, 3, 3)
        new[draw(st.integers(0, len(new) - 1))] = _NOT_ROTATIONS[draw(st.sampled_from(sorted(_NOT_ROTATIONS)))]
        return new.reshape(old.shape)
    if kind == "shape":
        return np.ones(tuple(draw(st.lists(st.integers(0, 5), max_size=4))))
    if kind == "dtype" and old.dtype.kind in "biufc":
        dtype = draw(st.sampled_from([np.int32, np.bool_, np.complex64, np.float16]))
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the cast itself is the point
            return old.astype(dtype)
    if kind == "empty":
        return old[:0] if old.ndim else np.zeros(0)
    if kind == "scalar":
        return np.array(draw(st.sampled_from(_VALUES)))
    return np.array(draw(st.sampled_from(["meters", "matrix", "rotvec", "", "Hips", "x" * 300])))


def _rotations(m: np.ndarray) -> bool:
    m = np.asarray(m, np.float64).reshape(-1, 3, 3)  # float16 is read too (as float64)
    return bool(np.all(np.abs(np.swapaxes(m, -1, -2) @ m - np.eye(3)) <= 1e-3) and np.all(np.linalg.det(m) > 0))


@given(data=st.data())
def test_read_soma_gives_a_writable_motion_or_names_the_file(tmp_path_factory, data):
    fields = _file(data.draw)
    change_fields(data, fields, ["mocap_frame_rate", "global_scale"], _replacement)
    path = tmp_path_factory.mktemp("soma") / "take.npz"
    np.savez(path, **fields)
    try:
        converted = reader("soma")(path, ConvertOptions())
    except ValueError as exc:
        assert str(exc).startswith(str(path)) and "\n" not in str(exc), exc
        event("refused")
        return
    event("read")
    motion = converted.motion
    assert len(motion.pose) >= 1
    check_motion(motion)
    if motion.identity is not None:
        assert motion.identity_backend in ("pca", "anny")
    # It was read from genuine rotations: the file's matrices and the orientations it used.
    if str(fields.get("rotation_repr")) == "matrix":
        assert _rotations(fields["poses"])
    if not bool(fields.get("absolute_pose", False)):
        assert _rotations(fields["joint_orient"])
