"""unibody's motion format and mesh-sequence files (``.npz``, no pickles).

Motion file fields:

============== ============== ==========================================================
``format``     str            ``"unibody.motion/1"``
``pose``       (T, 77, 3) f32 axis-angle (radians), T-pose-relative local rotations of
                              joints 1..77 in ``joint_names`` order (paper 001 convention)
``transl``     (T, 3) f32     Hips world position, metres, Y up, facing +Z
``joint_names`` (77,) str     the posed joints, ``unibody.JOINT_NAMES[1:]``
``fps``        () f32         frames per second
``identity``   (K,) f32       optional: identity parameters of ``identity_backend``
``identity_backend`` () str   optional: e.g. ``"pca"`` or ``"anny"``
``source``     () str         optional: what the motion was converted from, e.g.
                              ``"amass smplx female: walk.npz"`` or ``"bvh: 02_01.bvh"``
============== ============== ==========================================================

Mesh-sequence file fields: ``vertices (T, N, 3)`` metres and ``topology`` (``"canonical"``
or an identity backend's name such as ``"anny"``), optionally ``identity (K,)`` and ``fps ()``
(frames per second; files without it say nothing of their rate).

Readers check every field (shape, dtype, finite values, ``fps > 0``) and raise ``ValueError``
naming the file and the field; a file that is not an npz at all (empty, truncated, random
bytes, pickled) gets the same one-line error. Writers are atomic and write exactly the path
given (numpy alone would append ``.npz`` to a name without it).
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .io.atomic import save_npz
from .io.npz import read_npz, reason
from .rig import JOINT_NAMES

__all__ = [
    "MOTION_FORMAT",
    "Motion",
    "MeshSequence",
    "MAX_DISTANCE",
    "check_fps",
    "check_motion",
    "load_mesh_sequence",
    "load_motion",
    "save_motion",
]

MOTION_FORMAT = "unibody.motion/1"
MAX_DISTANCE = 1e5
"""Metres: the farthest a motion's root or a stored mesh's vertex may be from the origin (the
inverter's ``MAX_COORDINATE``). Motion, glTF, USD and mesh files hold positions in float32, whose
step is 7.8 mm there; anything farther is a unit or export error, not a place."""


@dataclass(frozen=True, slots=True)
class Motion:
    """A motion: ``pose (T, 77, 3)``, ``transl (T, 3)``, ``fps``, optional identity."""

    pose: np.ndarray
    transl: np.ndarray
    fps: float = 30.0
    identity: np.ndarray | None = None
    identity_backend: str | None = None
    source: str = ""


@dataclass(frozen=True, slots=True)
class MeshSequence:
    """Posed meshes ``vertices (T, N, 3)`` on ``topology``, optional ``identity (K,)`` and ``fps``.

    ``fps`` is None when the file does not state its frame rate.
    """

    vertices: np.ndarray
    topology: str
    identity: np.ndarray | None = None
    fps: float | None = None


def _field(data: np.lib.npyio.NpzFile, key: str, path: str | Path) -> np.ndarray:
    """One array of an open npz; a damaged member raises ValueError naming the file and field."""
    try:
        return data[key]
    except KeyError:
        raise ValueError(f"{path}: missing field {key!r} (fields: {', '.join(data.files) or 'none'})") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise ValueError(f"{path}: field {key!r} is unreadable ({reason(exc)})") from None


def _floats(x: np.ndarray, shape: str, ok: bool, where: str) -> np.ndarray:
    """Check a numeric array (shape already tested as ``ok``) and return it as float32."""
    if not ok:
        raise ValueError(f"{where}: expected shape {shape}, got {x.shape}")
    if x.dtype.kind != "f":
        raise ValueError(f"{where}: expected floating-point numbers, got dtype {x.dtype}")
    bad = int(np.size(x) - np.isfinite(x).sum())
    if bad:
        raise ValueError(f"{where}: expected finite values, got {bad} NaN/inf entries")
    with np.errstate(over="ignore"):
        y = x.astype(np.float32, copy=False)
    big = int(np.size(y) - np.isfinite(y).sum())
    if big:
        raise ValueError(
            f"{where}: expected values within float32's range (+-3.4e+38), got {big} beyond it "
            f"(up to {np.abs(x).max():.3g})"
        )
    return y


def _text(x: np.ndarray, where: str) -> str:
    if x.shape != () or x.dtype.kind not in "US":
        raise ValueError(f"{where}: expected a string, got an array of shape {x.shape} and dtype {x.dtype}")
    return str(x)


def check_fps(fps: object, name: str = "fps") -> float:
    """Frames per second as a float: finite and positive (and at most 100,000)."""
    if isinstance(fps, bool | str | complex) or np.iscomplexobj(fps):  # float() would drop an imaginary part
        raise ValueError(f"{name}: expected a positive number, got {fps!r}")
    try:
        value = float(fps)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a positive number, got {fps!r}") from None
    if not (np.isfinite(value) and 0 < value <= 1e5):
        raise ValueError(f"{name}: expected a positive number of frames per second (at most 100000), got {fps!r}")
    return value


def _check_motion(pose: np.ndarray, transl: np.ndarray, identity: np.ndarray | None, where: str) -> tuple:
    pose = _floats(np.asarray(pose), "(T, 77, 3)", np.ndim(pose) == 3 and np.shape(pose)[1:] == (77, 3), f"{where}pose")
    t = pose.shape[0]
    transl = np.asarray(transl)
    ok = transl.shape == (t, 3)
    # The root rule before the float32 cast: a root at 1e300 m is named as such, not as float32's range.
    if ok and t and transl.dtype.kind == "f" and np.isfinite(transl).all():
        if (far := float(np.abs(transl).max())) > MAX_DISTANCE:
            frame = int(np.abs(transl).max(axis=1).argmax())
            raise ValueError(
                f"{where}transl: expected the root within {MAX_DISTANCE:g} m of the origin (positions in metres), "
                f"got {far:.3g} m at frame {frame}"
            )
    transl = _floats(transl, f"({t}, 3)", ok, f"{where}transl")
    if identity is not None:
        identity = np.asarray(identity)
        identity = _floats(identity, "(K,)", identity.ndim == 1 and identity.size > 0, f"{where}identity")
    return pose, transl, identity


def check_motion(motion: Motion, where: str = "motion.") -> None:
    """ValueError (one line: ``where`` then ``pose``, ``transl``, ``identity`` or ``fps``) unless
    ``motion`` holds what a motion file can: float arrays of the right shapes, finite and within
    float32's range, the root within :data:`MAX_DISTANCE` of the origin, a valid frame rate.
    ``where`` is ``"motion."`` for an argument, ``"take.bvh: "`` for what a file gave.
    """
    _check_motion(motion.pose, motion.transl, motion.identity, where)
    check_fps(motion.fps, f"{where}fps")


def save_motion(path: str | Path, motion: Motion) -> None:
    """Write a motion file atomically, exactly at ``path`` (see the module docstring for the fields).

    Raises:
        ValueError: a field has the wrong shape, is not finite or beyond float32, the root is
            farther than :data:`MAX_DISTANCE` from the origin, or ``fps`` is not positive.
    """
    if not isinstance(motion, Motion):
        raise TypeError(f"motion: expected a unibody.motion.Motion, got {type(motion).__name__}")
    pose, transl, identity = _check_motion(motion.pose, motion.transl, motion.identity, "")
    fields = {
        "format": np.asarray(MOTION_FORMAT),
        "pose": pose,
        "transl": transl,
        "joint_names": np.asarray(JOINT_NAMES[1:]),
        "fps": np.asarray(check_fps(motion.fps), np.float32),
    }
    if identity is not None:
        fields["identity"] = identity
        fields["identity_backend"] = np.asarray(motion.identity_backend or "")
    if motion.source:
        fields["source"] = np.asarray(str(motion.source))
    save_npz(path, **fields)


def load_motion(path: str | Path) -> Motion:
    """Read a motion file, checking its format, joint order and every field.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: not a motion file, or a field is malformed (the message names the file and field).
    """
    with read_npz(path) as data:
        fmt = _field(data, "format", path) if "format" in data.files else None
        if fmt is None or fmt.shape != () or str(fmt) != MOTION_FORMAT:
            raise ValueError(f"{path}: not a {MOTION_FORMAT} file (fields: {', '.join(data.files) or 'none'})")
        names = _field(data, "joint_names", path)
        if names.dtype.kind not in "US" or tuple(str(n) for n in names.reshape(-1)) != JOINT_NAMES[1:]:
            raise ValueError(f"{path}: joint_names differ from unibody.JOINT_NAMES[1:]")
        identity = _field(data, "identity", path) if "identity" in data.files else None
        pose, transl, identity = _check_motion(
            _field(data, "pose", path), _field(data, "transl", path), identity, f"{path}: "
        )
        fps = _field(data, "fps", path)
        if fps.shape != () or fps.dtype.kind not in "fiu":
            raise ValueError(f"{path}: fps: expected a number, got shape {fps.shape} and dtype {fps.dtype}")
        fps = check_fps(fps, f"{path}: fps")
        backend = None
        if "identity_backend" in data.files:
            backend = _text(_field(data, "identity_backend", path), f"{path}: identity_backend") or None
        source = _text(_field(data, "source", path), f"{path}: source") if "source" in data.files else ""
        return Motion(pose, transl, fps, identity, backend, source)


def load_mesh_sequence(path: str | Path) -> MeshSequence:
    """Read a mesh-sequence file (``vertices`` and ``topology`` fields), checking every field.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: a field is missing or malformed (the message names the file and field).
    """
    with read_npz(path) as data:
        missing = {"vertices", "topology"} - set(data.files)
        if missing:
            raise ValueError(
                f"{path}: missing field(s) {', '.join(sorted(missing))}; expected vertices (T, N, 3) and topology"
            )
        v = _field(data, "vertices", path)
        vertices = _floats(v, "(T, N, 3)", v.ndim == 3 and v.shape[2] == 3, f"{path}: vertices")
        if vertices.size and (far := float(np.abs(vertices).max())) > MAX_DISTANCE:
            t, n = np.unravel_index(int(np.abs(vertices).max(axis=2).argmax()), vertices.shape[:2])
            raise ValueError(
                f"{path}: vertices: expected positions within {MAX_DISTANCE:g} m of the origin (metres), "
                f"got {far:.3g} m (mesh {t}, vertex {n})"
            )
        identity = _field(data, "identity", path) if "identity" in data.files else None
        if identity is not None:
            ok = identity.ndim == 1 and identity.size > 0
            identity = _floats(identity, "(K,)", ok, f"{path}: identity")
        fps = None
        if "fps" in data.files:
            rate = _field(data, "fps", path)
            if rate.shape != () or rate.dtype.kind not in "fiu":
                raise ValueError(f"{path}: fps: expected a number, got shape {rate.shape} and dtype {rate.dtype}")
            fps = check_fps(rate, f"{path}: fps")
        topology = _text(_field(data, "topology", path), f"{path}: topology")
        return MeshSequence(vertices, topology, identity, fps)
