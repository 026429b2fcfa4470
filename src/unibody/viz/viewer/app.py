"""The interactive viewer: a viser server showing :class:`SceneItem` s on one timeline.

Every item (an input file) gets its own scene frame, side by side along +X or overlaid. Its
bodies are one mesh node each, created once: a new frame assigns the node's vertex array
(one ``(V, 3)`` float32 message per body and frame), never re-adds the node. Markers are one
point cloud per take, coloured by kind (:func:`~unibody.viz.viewer.tracks.marker_colors`).

The timeline runs at the highest frame rate of the items; an item with another rate shows
its frame at the same time. Playback follows the wall clock (``speed`` times real time) and
skips frames when updates are slower than the rate, so a motion always plays at its speed.
"""

from __future__ import annotations

import contextlib
import io
import math
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from .tracks import BODY_COLORS, GHOST, BodySource, MarkerTrack, SceneItem, check_spacing, local_frame, marker_colors

__all__ = ["Viewer"]

_SKELETON_COLOR = (30, 30, 30)


@dataclass
class _Body:
    source: BodySource
    mesh: object  # viser MeshHandle
    skeleton: object  # viser LineSegmentsHandle
    segments: np.ndarray  # (S, 2) joint indices of the bones drawn
    offset: np.ndarray  # (3,) m, where the item's scene frame sits
    names: list = field(default_factory=list)  # viser LabelHandles, made on demand
    shown: int = -1
    joints: np.ndarray | None = None
    hits: object | None = None  # viser MeshHandle of the self-intersecting triangles, made on demand
    num_hits: int = 0  # self-intersecting triangles of the frame shown (when they are asked for)


@dataclass
class _Markers:
    track: MarkerTrack
    cloud: object  # viser PointCloudHandle
    colors: np.ndarray  # (T, M, 3) uint8
    offset: np.ndarray
    names: list = field(default_factory=list)
    shown: int = -1


class Viewer:
    """Serve ``items`` on ``host:port`` (the next free port if that one is taken).

    Args:
        items: what to show, one per input file.
        host: address to listen on; the default serves this machine only.
        port: port to ask for; 0 lets the system pick one. :attr:`port` is the one taken.
        layout: ``"side"`` puts item ``i`` at ``x = i * spacing``; ``"overlay"`` draws all
            items in the same place (source vs converted).
        spacing: metres between items side by side.
        max_rate: updates per second while playing, at most (default: the timeline's rate).
    """

    def __init__(
        self,
        items: Sequence[SceneItem],
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
        layout: Literal["side", "overlay"] = "side",
        spacing: float = 1.5,
        max_rate: float | None = None,
    ) -> None:
        import viser

        if not items:
            raise ValueError("items: expected at least one item to show, got none")
        if layout not in ("side", "overlay"):
            raise ValueError(f"layout: expected 'side' or 'overlay', got {layout!r}")
        spacing = check_spacing(spacing)
        self.items = tuple(items)
        self.fps = max(item.fps for item in self.items)
        self.num_frames = max(1, int(round(max(item.duration for item in self.items) * self.fps)) + 1)
        self.requested_port = int(port)
        with contextlib.redirect_stdout(io.StringIO()):  # viser prints its own address box on stdout
            self.server = viser.ViserServer(host=host, port=int(port), verbose=False)
        self.port = self.server.get_port()
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self.frame = 0
        self.playing = False
        self.speed = 1.0
        self.loop = True
        self.show_names = False
        self.show_marker_names = False
        self.show_intersections = False
        self._clock = 0.0
        self._period = 1.0 / float(max_rate or self.fps)
        self._bodies: list[_Body] = []
        self._markers: list[_Markers] = []
        self._build_scene(layout, spacing)
        from .panels import build_panels

        self.gui = build_panels(self)
        self._thread = threading.Thread(target=self._playback, name="unibody-viewer-playback", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ scene

    @property
    def port_note(self) -> str | None:
        """A line saying the port asked for was taken and which one serves, or None."""
        if self.requested_port and self.port != self.requested_port:
            return f"port {self.requested_port} is in use; serving on port {self.port}"
        return None

    @property
    def url(self) -> str:
        host = self.server.get_host()
        return f"http://{'127.0.0.1' if host in ('0.0.0.0', '') else host}:{self.port}"

    @property
    def bodies(self) -> tuple[BodySource, ...]:
        return tuple(b.source for b in self._bodies)

    def _build_scene(self, layout: str, spacing: float) -> None:
        scene = self.server.scene
        scene.set_up_direction("+y")
        scene.add_grid("/ground", width=20.0, height=20.0, plane="xz", position=(0.0, 0.0, 0.0))
        colour = 0
        for i, item in enumerate(self.items):
            offset = np.array([i * spacing if layout == "side" else 0.0, 0.0, 0.0])
            root = f"/item{i}"
            scene.add_frame(root, show_axes=False, position=tuple(offset))
            for j, body in enumerate(item.bodies):
                color = BODY_COLORS[colour % len(BODY_COLORS)]
                self._bodies.append(self._add_body(f"{root}/body{j}", body, color, offset))
                colour += 1
            for k, track in enumerate(item.markers):
                colors = marker_colors(track.labels, track.kinds)
                cloud = scene.add_point_cloud(
                    f"{root}/markers{k}", np.zeros((1, 3), np.float32), np.zeros((1, 3), np.uint8),
                    point_size=0.025, point_shape="circle", point_shading="flat",
                )  # fmt: skip
                self._markers.append(_Markers(track, cloud, colors, offset))
            if item.glb is not None:
                scene.add_glb(f"{root}/glb", item.glb)
        self._frame_camera()
        self.show(0)

    def _add_body(self, name: str, source: BodySource, color: tuple[int, int, int], offset: np.ndarray) -> _Body:
        scene = self.server.scene
        verts, joints = source.frames(np.zeros(1, dtype=np.int64))
        mesh = scene.add_mesh_simple(name, verts[0], np.asarray(source.faces, np.uint32), color=color)
        segments = np.array([(j, p) for j, p in enumerate(source.parents) if p > 0], dtype=np.int64).reshape(-1, 2)
        skeleton = scene.add_line_segments(
            f"{name}/skeleton", joints[0][segments], _SKELETON_COLOR, thickness=0.006, visible=False
        )
        return _Body(source, mesh, skeleton, segments, offset)

    def _frame_camera(self) -> None:
        pts = []
        for b in self._bodies:  # the whole motion, not its first frame: a walk must stay in view
            sample = np.unique(np.linspace(0, b.source.num_frames - 1, 5).astype(np.int64))
            pts.append(b.source.frames(sample)[0].reshape(-1, 3)[::7] + b.offset)
        ghosts = []  # framed only within 2 m of the rest: a reflection 100 km away would shrink the subject to a dot
        for m in self._markers:
            p = m.track.points.reshape(-1, 3)
            seen, ghost = np.isfinite(p).all(1), m.track.kinds.reshape(-1) == GHOST
            pts.append(p[seen & ~ghost] + m.offset)
            ghosts.append(p[seen & ghost] + m.offset)
        pts = [p for p in pts if len(p)]
        if not pts:
            return
        allp = np.concatenate(pts)
        lo, hi = allp.min(0) - 2.0, allp.max(0) + 2.0
        near = np.concatenate([np.zeros((0, 3)), *ghosts])
        allp = np.concatenate([allp, near[((near >= lo) & (near <= hi)).all(1)]])
        lo, hi = allp.min(0), allp.max(0)
        centre = 0.5 * (lo + hi)
        cam = self.server.initial_camera
        # Fit the box's width and height in the view (viser's vertical field of view; a 16:9
        # window less the GUI panel is about 1.4 wide), 15 % margin, from the front (+Z).
        tan_y = math.tan(0.5 * float(cam.fov))
        half = 0.5 * (hi - lo)
        dist = 1.15 * max(half[1] / tan_y, half[0] / (1.4 * tan_y), 0.5) + half[2]
        cam.look_at = tuple(float(x) for x in centre)
        cam.position = (float(centre[0]), float(centre[1] + 0.25 * dist), float(centre[2] + dist))

    # ---------------------------------------------------------------- frames

    def show(self, frame: int, *, force: bool = False) -> None:
        """Show timeline frame ``frame`` (clamped to the timeline)."""
        g = min(max(int(frame), 0), self.num_frames - 1)
        with self._lock, self.server.atomic():
            self.frame = g
            for b in self._bodies:
                k = local_frame(g, self.fps, b.source.fps, b.source.num_frames)
                if k != b.shown or force:
                    self._show_body(b, k)
            for m in self._markers:
                k = local_frame(g, self.fps, m.track.fps, m.track.num_frames)
                if k != m.shown or force:
                    self._show_markers(m, k)

    def _show_body(self, b: _Body, k: int) -> None:
        verts, joints = b.source.frames(np.array([k], dtype=np.int64))
        b.mesh.vertices = verts[0]
        b.joints, b.shown = joints[0], k
        if b.skeleton.visible:
            b.skeleton.points = joints[0][b.segments]
        if self.show_names:
            self._place_names(b)
        if self.show_intersections:
            self._place_hits(b, verts[0])

    def _place_hits(self, b: _Body, verts: np.ndarray) -> None:
        """Draw the triangles of ``verts`` that cut another triangle of the mesh, in red.

        Exact triangle tests (:func:`unibody.geometry.intersect.intersecting_pairs`, ~0.7 s for
        the canonical mesh on one core), so they are skipped while playing and drawn on pause.
        """
        if self.playing:
            if b.hits is not None:
                b.hits.visible = False
            return
        import torch

        from ...geometry.intersect import intersecting_pairs

        faces = np.asarray(b.source.faces, np.int64)
        pairs = intersecting_pairs(torch.from_numpy(np.asarray(verts, np.float64)), torch.from_numpy(faces))
        hit = np.unique(pairs.numpy().reshape(-1))
        b.num_hits = len(hit)
        if b.hits is None:
            name = f"{b.mesh.name}/hits"  # type: ignore[attr-defined]
            b.hits = self.server.scene.add_mesh_simple(
                name, verts, faces[:1].astype(np.uint32), color=(230, 20, 20), side="double", visible=False
            )
        if not len(hit):
            b.hits.visible = False
            return
        b.hits.vertices = verts
        b.hits.faces = faces[hit].astype(np.uint32)
        b.hits.visible = True

    def _place_names(self, b: _Body) -> None:
        scene = self.server.scene
        if not b.names:
            base = b.mesh.name  # type: ignore[attr-defined]
            b.names = [
                scene.add_label(f"{base}/names/{n}", n, position=tuple(p), font_screen_scale=0.6)
                for n, p in zip(b.source.joint_names[1:], b.joints[1:], strict=True)
            ]
        for h, p in zip(b.names, b.joints[1:], strict=True):
            h.position = p

    def _show_markers(self, m: _Markers, k: int) -> None:
        pts = m.track.points[k]
        seen = np.isfinite(pts).all(1)
        m.shown = k
        if not seen.any():
            m.cloud.visible = False
            return
        m.cloud.points = pts[seen]
        m.cloud.colors = m.colors[k][seen]
        m.cloud.visible = True
        if self.show_marker_names:
            self._place_marker_names(m, k, seen)

    def _place_marker_names(self, m: _Markers, k: int, seen: np.ndarray) -> None:
        scene = self.server.scene
        track = m.track
        if not m.names:
            base = m.cloud.name  # type: ignore[attr-defined]
            m.names = [
                scene.add_label(f"{base}/names/{i}", x, position=(0.0, 0.0, 0.0), font_screen_scale=0.6)
                for i, x in enumerate(track.labels)
            ]
        for i, h in enumerate(m.names):
            if not seen[i]:
                h.visible = False
                continue
            text = track.labels[i] if track.kinds[k, i] != GHOST else f"{track.labels[i]} (ghost)"
            if track.residual is not None and np.isfinite(track.residual[k, i]):
                text += f" {1000 * track.residual[k, i]:.0f} mm"
            h.text, h.position, h.visible = text, track.points[k, i], True

    def set_skeleton(self, on: bool) -> None:
        """Show or hide the bones; the mesh turns see-through while they show."""
        with self._lock:
            for b in self._bodies:
                b.skeleton.visible = on
                b.mesh.opacity = 0.45 if on else None
        self.show(self.frame, force=True)

    def set_mesh(self, on: bool) -> None:
        with self._lock:
            for b in self._bodies:
                b.mesh.visible = on

    def set_joint_names(self, on: bool) -> None:
        """Show or hide the joint names (78 labels per body; made on first use)."""
        with self._lock:
            self.show_names = on
            for b in self._bodies:
                for h in b.names:
                    h.visible = on
        if on:
            self.show(self.frame, force=True)

    def set_marker_names(self, on: bool) -> None:
        with self._lock:
            self.show_marker_names = on
            for m in self._markers:
                for h in m.names:
                    h.visible = False
        if on:
            self.show(self.frame, force=True)

    def set_intersections(self, on: bool) -> None:
        """Show or hide the self-intersecting triangles (computed for the frame shown, when paused)."""
        with self._lock:
            self.show_intersections = on
            for b in self._bodies:
                if b.hits is not None:
                    b.hits.visible = False
        if on:
            self.show(self.frame, force=True)

    def refresh(self, body: BodySource | None = None) -> None:
        """Ask ``body`` (every body when None) for its frame again: its identity or pose changed."""
        with self._lock:
            for b in self._bodies:
                if body is None or b.source is body:
                    b.shown = -1
        self.show(self.frame)

    # -------------------------------------------------------------- playback

    def play(self, on: bool = True) -> None:
        with self._lock:
            if on and not self.playing:
                self._clock = self.frame / self.fps
                self._last = time.perf_counter()
            paused = self.playing and not on
            self.playing = on
        if paused and self.show_intersections:
            self.show(self.frame, force=True)

    def seek(self, frame: int) -> None:
        """Show ``frame`` and continue playing from there."""
        with self._lock:
            self._clock = frame / self.fps
        self.show(frame)

    def _advance(self) -> int | None:
        """The frame to show now while playing (None: not playing or unchanged)."""
        with self._lock:
            if not self.playing:
                return None
            now = time.perf_counter()
            self._clock += (now - self._last) * self.speed
            self._last = now
            g = int(self._clock * self.fps + 1e-9)
            if g >= self.num_frames:
                if self.loop and self.num_frames > 1:
                    self._clock %= self.num_frames / self.fps
                    g = int(self._clock * self.fps + 1e-9) % self.num_frames
                else:
                    self.playing, g = False, self.num_frames - 1
            return None if g == self.frame else g

    def _playback(self) -> None:
        # Ticks on a fixed schedule (not a fixed sleep after each update), so the time an update
        # takes does not lower the rate; a tick that falls behind skips to the next one due.
        tick = time.perf_counter()
        while not self._stop.wait(max(0.0, tick - time.perf_counter())):
            tick = max(tick + self._period, time.perf_counter() - self._period)
            g = self._advance()
            if g is not None:
                self.gui.frame.value = g  # the slider's callback shows it

    def stop(self) -> None:
        """Stop playback and the server (clients see it disconnect)."""
        self._stop.set()
        self._thread.join(timeout=5.0)
        with contextlib.redirect_stdout(io.StringIO()):
            self.server.stop()

    def __enter__(self) -> Viewer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
