"""py-soma-x motion files (``.npz``) in and out, losslessly against unibody's motion.

py-soma-x writes ``poses`` (N, J, 3) rotation vectors or (N, J, 3, 3) matrices
(``rotation_repr`` "rotvec" | "matrix") in ``joint_names`` order, ``transl`` (N, 3) in ``unit``
("meters" | "centimeters" | "millimeters"), ``identity_model_type`` and ``identity_coeffs``
(N, C) or (1, C), ``keep_root`` (J = 78 with the virtual Root, else 77) and ``absolute_pose``:
true means absolute local rotations, false T-pose-relative ones with ``joint_orient`` (J, 3, 3),
the T-pose world orientations they are relative to. Ours are T-pose-relative to the canonical
``Rig.tpose_orient`` O: ``R_rel,j = O_p R_abs,j O_jᵀ``.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from ..geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from ..io.atomic import atomic_write
from ..io.npz import read_npz, reason
from ..motion import Motion, check_fps
from ..rig import JOINT_NAMES
from ._body import BACKENDS
from ._types import Converted, ConvertOptions

__all__ = ["UNITS", "read_soma", "write_soma"]

UNITS = {"meters": 1.0, "m": 1.0, "centimeters": 0.01, "cm": 0.01, "millimeters": 0.001, "mm": 0.001}
"""Metres per unit of ``transl``, by the names py-soma-x's ``unit`` field takes."""


@lru_cache(maxsize=1)
def _canonical() -> tuple[torch.Tensor, tuple[int, ...]]:
    """(78, 3, 3) float64 T-pose world orientations of the canonical rig, and its parents."""
    from ..rig import Rig

    rig = Rig.canonical()
    return rig.tpose_orient.to(torch.float64), rig.tree.parents


class _File:
    """Checked access to the fields of one open npz, every error naming the file and field."""

    def __init__(self, data, path: Path) -> None:
        self.data, self.path = data, path

    def has(self, key: str) -> bool:
        return key in self.data.files

    def array(self, key: str) -> np.ndarray:
        if key not in self.data.files:
            fields = ", ".join(self.data.files) or "none"
            raise ValueError(f"{self.path}: missing field {key!r} of a py-soma-x motion (fields: {fields})")
        try:
            return self.data[key]
        except (OSError, ValueError, EOFError) as exc:
            raise ValueError(f"{self.path}: field {key!r} is unreadable ({reason(exc)})") from None

    def floats(self, key: str, shape: str, ok: bool) -> np.ndarray:
        x = self.array(key)
        if not ok(x):
            raise ValueError(f"{self.path}: {key}: expected shape {shape}, got {x.shape}")
        if x.dtype.kind != "f":
            raise ValueError(f"{self.path}: {key}: expected floating-point numbers, got dtype {x.dtype}")
        bad = np.argwhere(~np.isfinite(x.reshape(len(x), -1)).all(1)) if x.ndim and x.size else []
        if len(bad):
            raise ValueError(
                f"{self.path}: {key}: non-finite values in {len(bad)} frame(s), first at frame {bad[0][0]}"
            )
        return x.astype(np.float64)

    def text(self, key: str, default: str | None = None) -> str:
        if default is not None and not self.has(key):
            return default
        x = self.array(key)
        if x.shape != () or x.dtype.kind not in "US":
            raise ValueError(f"{self.path}: {key}: expected a string, got shape {x.shape} and dtype {x.dtype}")
        return str(x)

    def flag(self, key: str, default: bool) -> bool:
        if not self.has(key):
            return default
        x = self.array(key)
        if x.shape != () or x.dtype.kind not in "biu":
            raise ValueError(f"{self.path}: {key}: expected a boolean, got shape {x.shape} and dtype {x.dtype}")
        return bool(x)


def _rotations(f: _File, n_names: int) -> tuple[np.ndarray, str]:
    """(N, J, 3, 3) or (N, J, 3) float64 rotations as stored, and the representation."""
    repr_ = f.text("rotation_repr")
    if repr_ == "rotvec":
        return f.floats("poses", f"(N, {n_names}, 3)", lambda x: x.shape[1:] == (n_names, 3)), repr_
    if repr_ != "matrix":
        raise ValueError(f"{f.path}: rotation_repr: expected 'rotvec' or 'matrix', got {repr_!r}")
    R = f.floats("poses", f"(N, {n_names}, 3, 3)", lambda x: x.ndim == 4 and x.shape[1:] == (n_names, 3, 3))
    _check_rotations(R, f"{f.path}: poses: frame {{}}, joint {{}}")
    return R, repr_


def _check_rotations(R: np.ndarray, where: str) -> None:
    """ValueError unless every (..., 3, 3) matrix of ``R`` is a rotation; ``where`` formats its index."""
    if not R.size:
        return
    with np.errstate(all="ignore"):
        err = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max(axis=(-1, -2))
        det = np.linalg.det(R)
        bad = np.argwhere(~(err <= 1e-3) | ~(det > 0))
    if len(bad):
        at = tuple(bad[0])
        raise ValueError(f"{where.format(*at)} is not a rotation matrix (|RᵀR - I| = {err[at]:.3g}, det {det[at]:.3g})")


def _to_canonical(R: torch.Tensor, names: list[str], orient: torch.Tensor | None, path: Path) -> torch.Tensor:
    """(N, 77, 3, 3) canonical T-pose-relative rotations of the file's (N, J, 3, 3) ``R``.

    ``orient`` is the file's (J, 3, 3) ``joint_orient`` (None: ``R`` holds absolute local rotations).
    """
    Oc, parents = _canonical()
    index = {name: i for i, name in enumerate(names)}
    n = R.shape[0]
    eye = torch.eye(3, dtype=R.dtype).expand(n, 3, 3)
    absolute = []
    for j, name in enumerate(JOINT_NAMES):
        if name not in index:  # only the Root may be absent
            absolute.append(eye)
            continue
        Rj = R[:, index[name]]
        if orient is not None:  # R_abs,j = O'_pᵀ R_rel,j O'_j with the file's own orientations
            p = parents[j]
            if p < 0:  # the Root's parent is the world
                Op = torch.eye(3, dtype=R.dtype)
            else:  # a parent the file does not hold (the Root) has the canonical orientation
                Op = orient[index[JOINT_NAMES[p]]] if JOINT_NAMES[p] in index else Oc[p]
            Rj = Op.T @ Rj @ orient[index[name]]
        absolute.append(Rj)
    A = torch.stack(absolute, 1)
    A[:, 1] = A[:, 0] @ A[:, 1]  # a Root rotation (if any) turns the Hips: fold it in
    p = torch.tensor([max(q, 0) for q in parents[1:]])
    return Oc[p] @ A[:, 1:] @ Oc[1:].transpose(-1, -2)


def _identity(f: _File, model: str, warnings: list[str]) -> tuple[np.ndarray | None, str | None]:
    if model.lower() in ("", "none") and (not f.has("identity_coeffs") or f.array("identity_coeffs").size == 0):
        return None, None
    if model.lower() not in BACKENDS:
        warnings.append(
            f"{f.path.name}: identity_model_type {model!r} is not played here ({', '.join(BACKENDS)}); "
            "the identity is dropped (the motion plays on the PCA mean body)"
        )
        return None, None
    coeffs = f.floats("identity_coeffs", "(N, K) or (1, K)", lambda x: x.ndim == 2 and x.shape[1] > 0)
    if len(coeffs) == 0:
        return None, None
    if not np.allclose(coeffs, coeffs[:1]):
        warnings.append(f"{f.path.name}: identity_coeffs vary over the frames; kept frame 0's")
    return coeffs[0], model.lower()  # float64: a value past float32 is refused by name, not cast to inf


def read_soma(path: Path, options: ConvertOptions) -> Converted:
    """Read a py-soma-x motion npz (any of its variants) as the canonical motion.

    Joints are matched by name (an extra ``Root`` is folded into the Hips), absolute rotations are
    made T-pose-relative, ``transl`` goes to metres. The frame rate comes from an ``fps`` or
    ``mocap_frame_rate`` field, else 30 with a warning.

    Raises:
        ValueError: a field is missing or malformed, or a canonical joint is missing (one line naming the file).
    """
    path = Path(path)
    warnings: list[str] = []
    with read_npz(path) as data:
        f = _File(data, path)
        names_arr = f.array("joint_names")
        if names_arr.ndim != 1 or names_arr.dtype.kind not in "US":
            raise ValueError(f"{path}: joint_names: expected (J,) strings, got shape {names_arr.shape}")
        names = [str(n) for n in names_arr]
        missing = [n for n in JOINT_NAMES[1:] if n not in names]
        if missing:
            shown = ", ".join(missing[:8]) + (", ..." if len(missing) > 8 else "")
            raise ValueError(f"{path}: joint_names: {len(missing)} SOMA joint(s) missing: {shown}")
        extra = [n for n in names if n not in JOINT_NAMES]
        if extra:
            warnings.append(f"{path.name}: joints not in the SOMA rig are ignored: {', '.join(extra[:8])}")
        poses, repr_ = _rotations(f, len(names))
        n = len(poses)
        if n == 0:
            raise ValueError(f"{path}: poses: expected at least one frame, got shape {poses.shape}")
        transl = f.floats("transl", f"({n}, 3)", lambda x: x.shape == (n, 3))
        unit = f.text("unit", "meters")
        if unit.lower() not in UNITS:
            raise ValueError(f"{path}: unit: expected meters, centimeters or millimeters, got {unit!r}")
        absolute = f.flag("absolute_pose", False)
        orient = None
        if not absolute:
            J = len(names)
            orient = f.floats("joint_orient", f"({J}, 3, 3)", lambda x: x.shape == (J, 3, 3))
            _check_rotations(orient, f"{path}: joint_orient: joint {{}}")
        fps_key = next((k for k in ("fps", "mocap_frame_rate", "mocap_framerate") if f.has(k)), None)
        if fps_key is None:
            fps = 30.0
            warnings.append(f"{path.name}: no frame rate in the file (fps); assumed 30 fps")
        else:
            rate = f.array(fps_key)
            fps = check_fps(rate.reshape(-1)[0] if rate.size == 1 else rate.shape, f"{path}: {fps_key}")
        identity, backend = _identity(f, f.text("identity_model_type"), warnings)
        if f.has("global_scale") and np.size(f.array("global_scale")) and not np.allclose(f.array("global_scale"), 1):
            warnings.append(f"{path.name}: global_scale is not applied (the identity sets the body's size)")
    pose = _pose(poses, repr_, names, orient, absolute, path)
    transl = transl * UNITS[unit.lower()]  # float64: check_motion names a far root before any float32 cast
    motion = Motion(pose, transl, fps, identity, backend, f"soma: {path.name}")
    return Converted(motion, {"frames": n, "fps": fps}, tuple(warnings))


def _pose(poses: np.ndarray, repr_: str, names: list[str], orient, absolute: bool, path: Path) -> np.ndarray:
    """(N, 77, 3) float32 canonical pose; rotation vectors relative to our own orientations pass unchanged."""
    Oc, _ = _canonical()
    index = [names.index(n) for n in JOINT_NAMES[1:]]
    root = names.index("Root") if "Root" in names else None
    if repr_ == "rotvec" and not absolute:
        same = np.allclose(orient[index], Oc[1:].numpy(), atol=1e-6) and (
            root is None or (np.allclose(orient[root], Oc[0].numpy(), atol=1e-6) and not np.abs(poses[:, root]).any())
        )
        if same:
            return poses[:, index].astype(np.float32)
    R = torch.from_numpy(poses)
    if repr_ == "rotvec":
        R = axis_angle_to_matrix(R)
    rel = _to_canonical(R, names, None if absolute else torch.from_numpy(orient), path)
    return matrix_to_axis_angle(rel).numpy().astype(np.float32)


def write_soma(motion: Motion, path: Path, options: ConvertOptions) -> None:
    """Write ``motion`` as a py-soma-x motion npz: rotation vectors, T-pose-relative with
    ``joint_orient``, no Root, ``transl`` in metres, plus ``fps``; atomically, exactly at ``path``."""
    Oc, _ = _canonical()
    pose = np.asarray(motion.pose, np.float32)
    identity = None if motion.identity is None else np.asarray(motion.identity, np.float32)
    fields = {
        "poses": pose,
        "transl": np.asarray(motion.transl, np.float32),
        "joint_names": np.asarray(JOINT_NAMES[1:]),
        "identity_model_type": np.asarray((motion.identity_backend or "none") if identity is not None else "none"),
        "identity_coeffs": (identity[None] if identity is not None else np.zeros((1, 0), np.float32)),
        "keep_root": np.asarray(False),
        "absolute_pose": np.asarray(False),
        "joint_orient": Oc[1:].numpy(),
        "rotation_repr": np.asarray("rotvec"),
        "unit": np.asarray("meters"),
        "fps": np.asarray(check_fps(motion.fps), np.float32),
    }
    with atomic_write(path) as f:
        np.savez_compressed(f, **fields)
