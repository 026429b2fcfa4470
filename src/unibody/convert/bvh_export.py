"""The canonical motion as a BVH of the 77-joint canonical skeleton (``--to bvh``).

What the file holds:

- the skeleton: ``ROOT Hips`` (6 channels: ``Xposition Yposition Zposition`` then rotations)
  and every other joint of ``JOINT_NAMES[2:]`` (3 rotation channels), parents from the
  canonical rig; leaf joints (``HeadEnd``, ``Jaw``, eyes, finger and toe ends) close with a
  zero-length End Site;
- OFFSETs: the motion's own identity (:func:`~unibody.convert._body.body_for`) in the T-pose
  (zero pose): each joint's position minus its parent's, in world axes (Y up, facing +Z);
  the Hips OFFSET is zero (its position channels give it);
- per frame: the Hips world position (``transl``) and the motion's **T-pose-relative** local
  rotations as Euler angles (:data:`ROTATION_ORDER`, degrees).
- lengths in **centimetres** (:data:`BVH_UNITS_PER_METRE` = 100), what Blender and
  MotionBuilder expect of a BVH; ``Frame Time`` is ``1 / fps``.

Why this is exact: the rest pose is the T-pose with every joint frame aligned to the world
axes, so with ``O`` the T-pose joint orientations the world rotation relative to the T-pose,
``W_j = G_j O_j^T``, obeys ``W_j = W_parent(j) R_rel,j``: the BVH local rotations *are* the
T-pose-relative rotations and the joint positions follow from the world-axis offsets.

Reading one back (no IK, no retargeting): :func:`is_canonical_bvh` recognises the skeleton
(every name of :data:`CANONICAL_BVH_NAMES` with its canonical parent; ``<joint>_End`` End
Sites and other extra joints are ignored), and :func:`canonical_from_bvh` maps the rotations
by name to the ``(T, 77, 3)`` pose and the Hips' positions to ``transl`` in metres. The
identity is not in the file (BVH has nowhere to put it); the offsets say only its T-pose
joint positions.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from ..io.bvh import write_bvh as _write_skeleton
from ..io.skeletal import SkeletalMotion
from ..motion import Motion, check_fps, check_motion
from ..rig import JOINT_NAMES
from ._body import body_for
from ._types import ConvertOptions

__all__ = [
    "BVH_UNITS_PER_METRE",
    "CANONICAL_BVH_NAMES",
    "ROTATION_ORDER",
    "canonical_from_bvh",
    "canonical_parents",
    "is_canonical_bvh",
    "write_bvh",
]

CANONICAL_BVH_NAMES: tuple[str, ...] = JOINT_NAMES[1:]
"""The joints of a canonical BVH, in file order (Hips first): the posed joints of the motion."""
BVH_UNITS_PER_METRE = 100.0
"""The canonical BVH's length unit: centimetres."""
ROTATION_ORDER = "ZXY"
"""Rotation channels ``Zrotation Xrotation Yrotation`` (R = Rz @ Rx @ Ry), as CMU's BVH files."""


def canonical_parents(layer_parents: tuple[int, ...]) -> np.ndarray:
    """Parents of :data:`CANONICAL_BVH_NAMES` (indices into it, -1 for Hips) from the rig's 78 parents."""
    parents = np.asarray(layer_parents[1:], dtype=np.int64) - 1
    parents[0] = -1
    return parents


def _check(motion: Motion) -> tuple[np.ndarray, np.ndarray, float]:
    pose, transl = np.asarray(motion.pose), np.asarray(motion.transl)
    if pose.ndim != 3 or pose.shape[1:] != (77, 3) or pose.shape[0] < 1:
        raise ValueError(f"motion.pose: expected shape (T, 77, 3) with T >= 1, got {pose.shape}")
    if transl.shape != (pose.shape[0], 3):
        raise ValueError(f"motion.transl: expected shape ({pose.shape[0]}, 3), got {transl.shape}")
    for name, x in (("pose", pose), ("transl", transl)):
        if x.dtype.kind != "f":
            raise ValueError(f"motion.{name}: expected floating-point numbers, got dtype {x.dtype}")
        bad = np.flatnonzero(~np.isfinite(x.reshape(x.shape[0], -1)).all(axis=1))
        if bad.size:
            shown = ", ".join(map(str, bad[:10])) + (", ..." if bad.size > 10 else "")
            raise ValueError(f"motion.{name}: expected finite values, got NaN/inf in frames {shown}")
    check_motion(motion)  # float32's range, the root's distance, the identity, the rate
    return pose.astype(np.float64), transl.astype(np.float64), check_fps(motion.fps, "motion.fps")


def write_bvh(motion: Motion, path: Path, options: ConvertOptions) -> None:
    """Write ``motion`` as a BVH of the canonical skeleton, atomically, exactly at ``path`` (see the module notes).

    ``options.dtype`` is the precision of the T-pose (float32 keeps offsets to about a micrometre).

    Raises:
        ValueError: one line: the motion's pose, transl or fps is malformed or not finite, or
            its identity does not fit its backend.
    """
    if Path(path).suffix.lower() != ".bvh":
        raise ValueError(f"path: expected a .bvh file, got {str(path)!r}")
    pose, transl, fps = _check(motion)
    dtype = torch.float64 if options.dtype == "float64" else torch.float32
    layer, prepared = body_for(motion, dtype)
    with torch.no_grad():
        zero = torch.zeros(1, 77, 3, dtype=dtype)
        tpose = layer.pose(prepared, zero, transl=torch.zeros(1, 3, dtype=dtype)).joints[0, 1:]
    tpose = tpose.to(torch.float64).numpy()
    parents = canonical_parents(tuple(layer.rig_tree.parents))
    offsets = tpose - tpose[np.maximum(parents, 0)]
    offsets[0] = 0.0
    rotations = axis_angle_to_matrix(torch.from_numpy(pose)).numpy()
    _write_skeleton(
        path,
        CANONICAL_BVH_NAMES,
        parents,
        offsets * BVH_UNITS_PER_METRE,
        rotations,
        transl * BVH_UNITS_PER_METRE,
        fps,
        order=ROTATION_ORDER,
    )


def is_canonical_bvh(motion: SkeletalMotion, layer_parents: tuple[int, ...] | None = None) -> bool:
    """Whether a read BVH holds every canonical joint, each under its canonical parent, Hips the root.

    ``layer_parents`` are the rig's 78 parents (``BodyLayer.rig_tree.parents``); None reads
    the canonical rig's.
    """
    if layer_parents is None:
        from ..rig import Rig

        layer_parents = tuple(Rig.canonical().tree.parents)
    index = {name: k for k, name in enumerate(motion.names)}
    if motion.names[:1] != ("Hips",) or not all(n in index for n in CANONICAL_BVH_NAMES):
        return False
    parents = canonical_parents(layer_parents)
    return all(
        int(motion.parents[index[name]]) == index[CANONICAL_BVH_NAMES[p]]
        for name, p in zip(CANONICAL_BVH_NAMES[1:], parents[1:], strict=True)
    )


def canonical_from_bvh(motion: SkeletalMotion, meters_per_unit: float = 1.0 / BVH_UNITS_PER_METRE) -> tuple:
    """The canonical ``pose (T, 77, 3)`` (axis-angle, float32) and ``transl (T, 3)`` (m) of a canonical BVH.

    Rotations map by name (they are the T-pose-relative rotations); ``transl`` is the Hips'
    position channels times ``meters_per_unit`` (centimetres, as :func:`write_bvh` writes, by
    default). Check the skeleton with :func:`is_canonical_bvh` first.

    Raises:
        ValueError: a canonical joint is missing from ``motion``.
    """
    index = {name: k for k, name in enumerate(motion.names)}
    missing = [n for n in CANONICAL_BVH_NAMES if n not in index]
    if missing:
        raise ValueError(
            f"bvh: expected the canonical skeleton, got {len(missing)} joints missing ({missing[0]!r}, ...)"
        )
    cols = [index[n] for n in CANONICAL_BVH_NAMES]
    rot = torch.from_numpy(np.ascontiguousarray(motion.rotations[:, cols]))
    pose = matrix_to_axis_angle(rot).numpy().astype(np.float32)
    transl = (motion.translations[:, index["Hips"]] * meters_per_unit).astype(np.float32)
    return pose, transl
