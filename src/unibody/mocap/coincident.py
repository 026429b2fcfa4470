"""Coincident points: copies of a marker at (nearly) the same position, found and labelled as one.

Some exports carry a marker twice: a column that is an exact copy of another (a virtual marker
or a gap-filled duplicate written out as a trajectory of its own), or, in single frames, two
reconstructions of one marker. Given to the labeler, two points on one spot confuse it (one of
them must be null, and the frame looks unlike any it was trained on: its confidence falls and
the retry path runs), so labels get worse and labelling gets slower.

:func:`find_coincident` finds them before labelling: in each frame, a visible point within
``tol`` (1 mm, :data:`COINCIDENT_TOL`) of a visible point of an earlier column is a **copy** of
it (chains are followed to the first column). Two physical markers cannot lie that close: their
centres are at least a marker diameter apart (6-25 mm), and a lab's reconstruction noise is
well under 1 mm, so a point that close is the same reconstruction. A column that is a copy of
one other column in at least ``share`` (95 %, :data:`COLUMN_SHARE`) of the frames where both
are visible is a **copy column** (reported by name); other copies are per-frame coincidences
(counted).

:func:`~unibody.mocap.pipeline.label_sequence` hides the copies from the labeler, the tracklets
and the body check, and gives each copy its original's label: in the labelled file the two are
one point (the original's), and its per-point labels (``LabelledSequence.point_labels``) give
the copy the original's label. Where the original is absent, a copy column's point is an
ordinary point and labelled like any other.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["COINCIDENT_TOL", "COLUMN_SHARE", "Coincident", "find_coincident"]

COINCIDENT_TOL = 1.0e-3  # m: closer than any two physical markers (>= a marker diameter apart), above lab noise
COLUMN_SHARE = 0.95  # a column that copies another in this share of their common frames is a copy column
_CHUNK = 1024  # frames per block of pairwise distances


@dataclass(frozen=True)
class Coincident:
    """Copies found by :func:`find_coincident` in a (T, N, 3) sequence.

    Attributes:
        original: (T, N) int64, the column each point copies (its own column where it is no copy,
            and where it is not visible).
        columns: (copy, original) column pairs: copy columns (see the module), in column order.
        tol: m, the distance within which two points coincide.
    """

    original: np.ndarray
    columns: tuple[tuple[int, int], ...]
    tol: float

    @property
    def copy(self) -> np.ndarray:
        """(T, N) bool: the points that copy another column's point."""
        return self.original != np.arange(self.original.shape[1])

    @property
    def frame_copies(self) -> int:
        """Copies outside the copy columns' frames of copying (isolated per-frame coincidences)."""
        mask = self.copy.copy()
        for c, o in self.columns:
            mask[:, c] &= self.original[:, c] != o
        return int(mask.sum())

    def spread(self, labels: np.ndarray) -> np.ndarray:
        """(T, N) labels of the originals given to their copies (``labels`` (T, N), copies' entries ignored)."""
        return np.take_along_axis(np.asarray(labels), self.original, axis=1)

    def describe(self, names: tuple[str, ...] | list[str]) -> str:
        """One line naming the copy columns (``copy=original``) and counting the other copies; '' if none."""
        parts = []
        if self.columns:
            pairs = ", ".join(f"{names[c]}={names[o]}" for c, o in self.columns)
            parts.append(f"merged {len(self.columns)} columns that copy others within {1000 * self.tol:g} mm ({pairs})")
        if n := self.frame_copies:
            parts.append(f"merged {n} more points that coincide with another within {1000 * self.tol:g} mm")
        return "; ".join(parts)


def find_coincident(points: np.ndarray, *, tol: float = COINCIDENT_TOL, share: float = COLUMN_SHARE) -> Coincident:
    """Find the points that copy another column's point of their frame (see the module).

    Args:
        points: (T, N, 3) m, NaN for missing points.
        tol: m, points at most this far apart coincide (default 1 mm).
        share: a column that copies one other column in at least this fraction of the frames
            where both are visible is reported as a copy column.

    Returns:
        :class:`Coincident`.

    Raises:
        ValueError: bad shape, ``tol`` not in (0, 0.005] m (closer than any two markers), or
            ``share`` not in (0, 1].
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 3 or pts.shape[2] != 3:
        raise ValueError(f"points: expected shape (T, N, 3), got {pts.shape}")
    if not 0 < tol <= 0.005:
        raise ValueError(f"tol: expected a distance in (0, 0.005] m (markers are farther apart), got {tol}")
    if not 0 < share <= 1:
        raise ValueError(f"share: expected 0 < share <= 1, got {share}")
    t, n, _ = pts.shape
    vis = np.isfinite(pts).all(-1)
    original = np.broadcast_to(np.arange(n), (t, n)).copy()
    both = np.zeros((n, n), dtype=np.int64)
    if n < 2 or t == 0:
        return Coincident(original, (), float(tol))
    earlier = np.tri(n, k=-1, dtype=bool)  # [j, i]: i < j
    for s in range(0, t, _CHUNK):
        p, v = pts[s : s + _CHUNK], vis[s : s + _CHUNK]
        pair = v[:, :, None] & v[:, None, :]  # (c, j, i)
        both += pair.sum(0)
        with np.errstate(invalid="ignore"):
            near = (np.linalg.norm(p[:, :, None] - p[:, None, :], axis=-1) <= tol) & pair & earlier
        f, j = np.nonzero(near.any(axis=2))
        if len(f):
            original[s + f, j] = near[f, j].argmax(axis=1)  # the first earlier column it coincides with
    for _ in range(n):  # follow chains (a copy of a copy) to the first column
        nxt = np.take_along_axis(original, original, axis=1)
        if np.array_equal(nxt, original):
            break
        original = nxt
    cols = []
    for c in range(n):
        o = original[:, c]
        hit = np.bincount(o[o != c], minlength=n)
        if hit.any():
            k = int(hit.argmax())
            if hit[k] >= share * both[c, k]:
                cols.append((c, k))
    return Coincident(original, tuple(cols), float(tol))
