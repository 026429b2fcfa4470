"""A skeleton and its motion as BVH and ASF/AMC files hold them (numpy, file units).

Both readers (:mod:`unibody.io.bvh`, :mod:`unibody.io.asfamc`) return a :class:`SkeletalMotion`;
the retargeting solver (:mod:`unibody.fitting.retarget`) and the BVH writer consume one.
Conventions: joint ``j``'s world transform is ``G_j = G_parent(j) @ [R_j | t_j]`` with ``R_j``
its local rotation (identity at rest) and ``t_j`` its local translation in the parent's frame
(the rest offset, or the per-frame position channels where a file animates them). The root's
``t`` is its world position. Lengths stay in the file's unit; ``meters_per_unit`` says how to
get metres when the format states it (ASF ``:units length``), else it is None (BVH: detect).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["SkeletalMotion"]


@dataclass(frozen=True, slots=True)
class SkeletalMotion:
    """A skeleton (J joints, parents before children) and T frames of its motion.

    Attributes:
        names: J joint names (end sites included, named ``<parent>_End`` when the file has none).
        parents: (J,) int64, parent index, -1 for the root (index 0).
        offsets: (J, 3) float64, rest offset of each joint in its parent's frame (file units).
        rotations: (T, J, 3, 3) float64 local rotations (identity at rest).
        translations: (T, J, 3) float64 local translations (offsets unless animated; root: world).
        fps: frames per second.
        meters_per_unit: metres per file unit when the file states it, else None.
        source: what was read, e.g. ``"bvh"`` or ``"asf/amc"``.
    """

    names: tuple[str, ...]
    parents: np.ndarray
    offsets: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    fps: float
    meters_per_unit: float | None = None
    source: str = ""

    @property
    def num_frames(self) -> int:
        return self.rotations.shape[0]

    def world(self) -> tuple[np.ndarray, np.ndarray]:
        """World joint positions (T, J, 3) in file units and world orientations (T, J, 3, 3)."""
        t, j = self.rotations.shape[:2]
        rot = np.empty((t, j, 3, 3))
        pos = np.empty((t, j, 3))
        for k in range(j):  # parents come first; a loop over joints, vectorised over frames
            p = int(self.parents[k])
            if p < 0:
                rot[:, k], pos[:, k] = self.rotations[:, k], self.translations[:, k]
            else:
                rot[:, k] = rot[:, p] @ self.rotations[:, k]
                pos[:, k] = pos[:, p] + np.einsum("tab,tb->ta", rot[:, p], self.translations[:, k])
        return pos, rot
