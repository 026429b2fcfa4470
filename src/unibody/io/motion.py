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
``identity_backend`` () str   optional: e.g. ``"anny"``
============== ============== ==========================================================

Mesh-sequence file fields: ``vertices (T, N, 3)`` metres and ``topology`` (``"canonical"``
or an identity backend's name such as ``"anny"``), optionally ``identity (K,)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..rig import JOINT_NAMES

__all__ = ["MOTION_FORMAT", "Motion", "MeshSequence", "load_mesh_sequence", "load_motion", "save_motion"]

MOTION_FORMAT = "unibody.motion/1"


@dataclass(frozen=True, slots=True)
class Motion:
    """A motion: ``pose (T, 77, 3)``, ``transl (T, 3)``, ``fps``, optional identity."""

    pose: np.ndarray
    transl: np.ndarray
    fps: float = 30.0
    identity: np.ndarray | None = None
    identity_backend: str | None = None


@dataclass(frozen=True, slots=True)
class MeshSequence:
    """Posed meshes ``vertices (T, N, 3)`` on ``topology``, optional ``identity (K,)``."""

    vertices: np.ndarray
    topology: str
    identity: np.ndarray | None = None


def save_motion(path: str | Path, motion: Motion) -> None:
    """Write a motion file (see the module docstring for the fields)."""
    pose, transl = np.asarray(motion.pose, np.float32), np.asarray(motion.transl, np.float32)
    if pose.ndim != 3 or pose.shape[1:] != (77, 3):
        raise ValueError(f"pose: expected shape (T, 77, 3), got {pose.shape}")
    if transl.shape != (pose.shape[0], 3):
        raise ValueError(f"transl: expected shape ({pose.shape[0]}, 3), got {transl.shape}")
    fields = {
        "format": np.asarray(MOTION_FORMAT),
        "pose": pose,
        "transl": transl,
        "joint_names": np.asarray(JOINT_NAMES[1:]),
        "fps": np.asarray(motion.fps, np.float32),
    }
    if motion.identity is not None:
        fields["identity"] = np.asarray(motion.identity, np.float32)
        fields["identity_backend"] = np.asarray(motion.identity_backend or "")
    np.savez(path, **fields)


def load_motion(path: str | Path) -> Motion:
    """Read a motion file, checking its format and joint order."""
    with np.load(path, allow_pickle=False) as data:
        if "format" not in data.files or str(data["format"]) != MOTION_FORMAT:
            raise ValueError(f"{path}: not a {MOTION_FORMAT} file (fields: {', '.join(data.files)})")
        names = tuple(str(n) for n in data["joint_names"])
        if names != JOINT_NAMES[1:]:
            raise ValueError(f"{path}: joint_names differ from unibody.JOINT_NAMES[1:]")
        identity = data["identity"] if "identity" in data.files else None
        backend = str(data["identity_backend"]) if "identity_backend" in data.files else None
        return Motion(data["pose"], data["transl"], float(data["fps"]), identity, backend or None)


def load_mesh_sequence(path: str | Path) -> MeshSequence:
    """Read a mesh-sequence file (``vertices`` and ``topology`` fields)."""
    with np.load(path, allow_pickle=False) as data:
        missing = {"vertices", "topology"} - set(data.files)
        if missing:
            raise ValueError(
                f"{path}: missing field(s) {', '.join(sorted(missing))}; expected vertices (T, N, 3) and topology"
            )
        vertices = data["vertices"]
        if vertices.ndim != 3 or vertices.shape[2] != 3:
            raise ValueError(f"{path}: vertices: expected shape (T, N, 3), got {vertices.shape}")
        identity = data["identity"] if "identity" in data.files else None
        return MeshSequence(vertices, str(data["topology"]), identity)
