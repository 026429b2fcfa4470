"""What the viewer shows, as plain arrays: bodies over time, marker tracks, their colours.

Conventions: metres, Y up, bodies face +Z (as :mod:`unibody.viz.render`). The viewer never
poses a body itself: a :class:`BodySource` hands it posed vertices and joints for frame
indices, so this floor needs no body model (the ``unibody view`` command builds sources from
``BodyLayer``).
"""

from __future__ import annotations

import math
import numbers
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

__all__ = [
    "BODY_COLORS",
    "GHOST",
    "GHOST_COLOR",
    "LABELLED",
    "UNLABELLED",
    "UNLABELLED_COLOR",
    "MAX_SPACING",
    "BodySource",
    "IdentityControls",
    "MarkerTrack",
    "SceneItem",
    "check_spacing",
    "local_frame",
    "nearest_joint",
    "marker_color",
    "marker_colors",
]

LABELLED, UNLABELLED, GHOST = 0, 1, 2
"""Point kinds of a :class:`MarkerTrack`: a named marker, an unnamed ``*n`` point on the body,
an unnamed point away from the body (a reflection or noise)."""
UNLABELLED_COLOR = (140, 140, 140)
GHOST_COLOR = (255, 0, 255)
BODY_COLORS = ((217, 140, 115), (115, 153, 217), (242, 191, 89), (153, 191, 140), (179, 140, 204))
"""RGB (0..255) of the bodies, in the order they are shown."""
MAX_SPACING = 100.0
"""Metres between items side by side, at most: one picture still shows a few of them (at 1e20
m the recorder drew an empty floor, at 1e300 the camera overflowed)."""


def check_spacing(spacing: float) -> float:
    """``spacing`` as a float, if it is a number of metres in (0, :data:`MAX_SPACING`]; else ValueError."""
    x = float(spacing) if isinstance(spacing, numbers.Real) and not isinstance(spacing, bool) else math.nan
    if not 0 < x <= MAX_SPACING:
        raise ValueError(f"spacing: expected metres between items in (0, {MAX_SPACING:g}], got {spacing!r}")
    return x


def local_frame(g: int, master_fps: float, fps: float, n: int) -> int:
    """The frame of a track of ``n`` frames at ``fps`` shown at frame ``g`` of a ``master_fps`` timeline."""
    return min(max(int(g * fps / master_fps + 1e-6), 0), n - 1)


def nearest_joint(joints: np.ndarray, origin: np.ndarray, direction: np.ndarray) -> int:
    """The joint (1..J-1, never the Root) closest to the ray ``origin + t direction``, t >= 0."""
    d = np.asarray(direction, np.float64)
    d = d / max(float(np.linalg.norm(d)), 1e-12)
    rel = np.asarray(joints, np.float64)[1:] - np.asarray(origin, np.float64)
    t = np.clip(rel @ d, 0.0, None)
    return 1 + int(np.argmin(np.linalg.norm(rel - t[:, None] * d, axis=1)))


def marker_color(label: str) -> tuple[int, int, int]:
    """The RGB colour (0..255) of a labelled marker: a hue fixed by the label's name.

    Saturated and bright, far from the grey of unlabelled points and the magenta of ghosts,
    so the same label has the same colour in every file and every run.
    """
    hue = (zlib.crc32(label.encode()) % 360) / 360.0
    if 0.78 < hue < 0.92:  # magenta is the ghosts' colour
        hue -= 0.2
    h6 = hue * 6.0
    x = 1.0 - abs(h6 % 2.0 - 1.0)
    rgb = [(1, x, 0), (x, 1, 0), (0, 1, x), (0, x, 1), (x, 0, 1), (1, 0, x)][int(h6) % 6]
    return tuple(int(round(40 + 200 * c)) for c in rgb)  # type: ignore[return-value]


def marker_colors(labels: Sequence[str], kinds: np.ndarray) -> np.ndarray:
    """``(..., M, 3)`` uint8 colours of points of ``kinds (..., M)`` with column ``labels (M)``."""
    per_label = np.array([marker_color(x) for x in labels], dtype=np.uint8).reshape(-1, 3)
    kinds = np.asarray(kinds)
    out = np.broadcast_to(per_label, (*kinds.shape, 3)).copy()
    out[kinds == UNLABELLED] = UNLABELLED_COLOR
    out[kinds == GHOST] = GHOST_COLOR
    return out


@dataclass(frozen=True)
class IdentityControls:
    """Sliders of a body's identity: one per parameter.

    Attributes:
        backend: the identity backend's name (``"anny"``, ``"pca"``).
        names: K parameter names (Anny phenotypes, ``"pc1"``...).
        low, high: (K,) slider ranges.
        values: (K,) the values the body starts with.
    """

    backend: str
    names: tuple[str, ...]
    low: np.ndarray
    high: np.ndarray
    values: np.ndarray

    def __post_init__(self) -> None:
        k = len(self.names)
        for name in ("low", "high", "values"):
            a = np.asarray(getattr(self, name), dtype=np.float64)
            if a.shape != (k,) or not np.isfinite(a).all():
                raise ValueError(f"{name}: expected ({k},) finite values, one per name, got shape {a.shape}")
            object.__setattr__(self, name, a)


@runtime_checkable
class BodySource(Protocol):
    """A body over time that the viewer can ask for any frame.

    ``frames(index)`` returns ``vertices (n, V, 3)`` and ``joints (n, J, 3)``, float32, for the
    frame indices ``index (n,)`` in ``[0, num_frames)``. ``set_identity`` and
    ``set_joint_rotation`` change what later calls return (the viewer asks again); a body
    without identity sliders has ``identity`` None and may ignore ``set_identity``.
    """

    name: str
    faces: np.ndarray
    num_frames: int
    fps: float
    joint_names: tuple[str, ...]
    parents: tuple[int, ...]
    identity: IdentityControls | None

    def frames(self, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...

    def set_identity(self, values: np.ndarray) -> None: ...

    def set_joint_rotation(self, joint: int, axis_angle: np.ndarray) -> None: ...


@dataclass(frozen=True)
class MarkerTrack:
    """A marker take: ``points (T, M, 3)`` m (NaN: missing), ``kinds (T, M)`` (:data:`LABELLED`...).

    ``residual (T, M)`` m is the distance of each point to the solved body's marker, NaN where
    there is none (None: not solved).
    """

    name: str
    points: np.ndarray
    labels: tuple[str, ...]
    kinds: np.ndarray
    fps: float
    residual: np.ndarray | None = None

    def __post_init__(self) -> None:
        pts = np.asarray(self.points, dtype=np.float32)
        if pts.ndim != 3 or pts.shape[2] != 3:
            raise ValueError(f"{self.name}: points: expected shape (T, M, 3), got {pts.shape}")
        t, m = pts.shape[:2]
        if len(self.labels) != m:
            raise ValueError(f"{self.name}: labels: expected {m}, one per column, got {len(self.labels)}")
        kinds = np.asarray(self.kinds, dtype=np.uint8)
        if kinds.shape != (t, m) or (kinds > GHOST).any():
            raise ValueError(f"{self.name}: kinds: expected ({t}, {m}) values in 0..2, got shape {kinds.shape}")
        if not (np.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"{self.name}: fps: expected a positive frame rate, got {self.fps}")
        object.__setattr__(self, "points", pts)
        object.__setattr__(self, "kinds", kinds)
        object.__setattr__(self, "labels", tuple(map(str, self.labels)))

    @property
    def num_frames(self) -> int:
        return self.points.shape[0]


@dataclass(frozen=True)
class SceneItem:
    """One input file: its bodies, marker tracks and static GLB scene, drawn together.

    A GLB is kept twice: ``glb``, the file's bytes, which the browser draws as they are, and
    ``still``, its triangle meshes ``(vertices (V, 3), faces (F, 3))`` in world coordinates at
    rest, which the recorder draws.
    """

    name: str
    bodies: tuple[BodySource, ...] = ()
    markers: tuple[MarkerTrack, ...] = ()
    glb: bytes | None = field(default=None, repr=False)
    still: tuple[tuple[np.ndarray, np.ndarray], ...] = field(default=(), repr=False)

    @property
    def duration(self) -> float:
        """Seconds of the longest track (0 for a still item)."""
        spans = [(b.num_frames - 1) / b.fps for b in self.bodies] + [(m.num_frames - 1) / m.fps for m in self.markers]
        return max(spans, default=0.0)

    @property
    def fps(self) -> float:
        """The highest frame rate of the item's tracks (30 for a still item)."""
        return max([b.fps for b in self.bodies] + [m.fps for m in self.markers], default=30.0)
