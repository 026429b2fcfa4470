"""Property: any AMASS-like ``.npz`` given to ``read_take`` gives a checked take or a ValueError naming the file.

Input: a valid SMPL-H or SMPL-X take (either pose layout), then fields dropped, added (dmpls),
or replaced by arrays of other shapes, dtypes (int, bool, complex, float16, strings, bytes),
values (NaN, inf, 1e300, 0, negative) or sizes (no frame, one element, 0-d). The answer must be
an :class:`~unibody.convert.amass.AmassTake` whose family, gender and frame rate are valid and
whose arrays are finite float64 of consistent shapes, or a ``ValueError`` whose message starts
with the file's path. Seeded and bounded (tests/conftest.py profiles).
"""

from __future__ import annotations

import warnings

import numpy as np
from hypothesis import event, given
from hypothesis import strategies as st

from conftest import change_fields
from unibody.convert.amass import AmassTake, read_take

_SPLIT = {"root_orient": 3, "pose_body": 63, "pose_jaw": 3, "pose_eye": 6, "pose_hand": 90}
_VALUES = [np.nan, np.inf, -np.inf, 1e300, 0.0, -1.0, 60.0]


def _take(family: str, split: bool, t: int = 4) -> dict:
    rng = np.random.default_rng(0)
    joints = 55 if family == "smplx" else 52
    poses = rng.normal(scale=0.3, size=(t, joints * 3))
    out = {"trans": rng.normal(size=(t, 3)), "betas": rng.normal(size=10 if family == "smplx" else 16)}
    out["gender"] = np.array("female" if family == "smplx" else "male")
    out["mocap_frame_rate" if family == "smplx" else "mocap_framerate"] = np.array(120.0)
    if family == "smplx":
        out["surface_model_type"] = np.array("smplx")
    if split:
        widths = [(k, w) for k, w in _SPLIT.items() if family == "smplx" or k not in ("pose_jaw", "pose_eye")]
        start = 0
        for key, width in widths:
            out[key] = poses[:, start : start + width]
            start += width
    else:
        out["poses"] = poses
    return out


def _replacement(draw, old: np.ndarray) -> np.ndarray:  # noqa: ANN001
    kind = draw(st.sampled_from(["value", "value", "value", "shape", "dtype", "empty", "scalar", "string"]))
    if kind == "value" and old.size and old.dtype.kind == "f":
        new = old.copy()
        new.flat[draw(st.integers(0, old.size - 1))] = draw(st.sampled_from(_VALUES))
        return new
    if kind == "shape":
        shape = tuple(draw(st.lists(st.integers(0, 5), min_size=0, max_size=3)))
        return np.ones(shape)
    if kind == "dtype" and old.dtype.kind in "biufc":
        dtype = draw(st.sampled_from([np.int32, np.bool_, np.complex64, np.float16, np.uint8]))
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # complex -> real, NaN -> int: the cast itself is the point
            return old.astype(dtype)
    if kind == "empty":
        return old[:0] if old.ndim else np.zeros(0)
    if kind == "scalar":
        return np.array(draw(st.sampled_from(_VALUES)))
    return np.array(draw(st.sampled_from(["male", b"FEMALE", "", "robot", "smplx", "smpl+h", "x" * 300])))


@given(family=st.sampled_from(["smplh", "smplx"]), split=st.booleans(), data=st.data())
def test_read_take_gives_a_checked_take_or_names_the_file(tmp_path_factory, family, split, data):
    fields = _take(family, split)
    change_fields(data, fields, ["dmpls", "poses", "root_orient"], _replacement)
    path = tmp_path_factory.mktemp("amass") / "take.npz"
    np.savez(path, **fields)
    try:
        take = read_take(path)
    except ValueError as exc:
        assert str(exc).startswith(str(path)), exc
        event("refused")
        return
    event("read")
    assert isinstance(take, AmassTake) and take.family in ("smplh", "smplx")
    assert take.gender in ("neutral", "male", "female") and np.isfinite(take.fps) and take.fps > 0
    t = take.poses.shape[0]
    assert t >= 1 and take.poses.shape == (t, 55 if take.family == "smplx" else 52, 3)
    assert take.trans.shape == (t, 3) and take.betas.ndim == 1
    for a in (take.poses, take.trans, take.betas):
        assert a.dtype == np.float64 and np.isfinite(a).all()
