"""Pictures and videos of what the viewer shows, without a browser (:mod:`unibody.viz.render`).

A motion is sampled at ``fps`` over its duration; a turntable turns the camera once around
the first frame's scene. Bodies keep the viewer's colours; markers are small octahedra in
their label colours (grey unlabelled, magenta ghosts). ``.mp4`` goes through imageio-ffmpeg
(H.264, yuv420p); ``.png`` writes one file, or numbered files ``stem_0000.png``... for
several frames. Every file is written atomically.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from ..render import Camera, MeshSpec, frame_camera, render_image
from .tracks import BODY_COLORS, GHOST, SceneItem, check_spacing, local_frame, marker_colors

__all__ = ["frame_count", "png_paths", "record", "render_frames"]

_OCTA_V = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float64)
_OCTA_F = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])


def _scene(
    items: Sequence[SceneItem], t: float, spacing: float, overlay: bool, radius: float, near: np.ndarray | None = None
) -> list[MeshSpec]:
    """Meshes of every item at time ``t`` (seconds).

    Ghost markers (far from their subject) are drawn only within ``near`` (a (2, 3) box: the
    rest grown by 2 m), and not at all without one; the camera frames what is drawn, so a
    reflection 100 km away neither shrinks the subject to a dot nor hangs the renderer.
    """
    meshes, colour = [], 0
    for i, item in enumerate(items):
        shift = np.array([0.0 if overlay else i * spacing, 0.0, 0.0])
        for body in item.bodies:
            k = local_frame(int(round(t * body.fps)), body.fps, body.fps, body.num_frames)
            verts, _ = body.frames(np.array([k]))
            rgb = tuple(c / 255 for c in BODY_COLORS[colour % len(BODY_COLORS)])
            meshes.append(MeshSpec(verts[0] + shift, np.asarray(body.faces, np.int64), rgb, body.name))
            colour += 1
        for k, (verts, faces) in enumerate(item.still):
            rgb = tuple(c / 255 for c in BODY_COLORS[colour % len(BODY_COLORS)])
            meshes.append(MeshSpec(verts + shift, faces, rgb, f"{item.name}:{k}"))
            colour += 1
        for track in item.markers:
            k = local_frame(int(round(t * track.fps)), track.fps, track.fps, track.num_frames)
            pts = track.points[k]
            seen = np.isfinite(pts).all(1)
            ghost = track.kinds[k] == GHOST
            if near is None:
                seen &= ~ghost
            else:
                seen &= ~ghost | ((pts >= near[0]) & (pts <= near[1])).all(1)
            colors = marker_colors(track.labels, track.kinds[k])
            for p, c in zip(pts[seen], colors[seen], strict=True):
                meshes.append(MeshSpec(p + shift + radius * _OCTA_V, _OCTA_F, tuple(c / 255.0), "marker"))
    return meshes


def _turn(camera: Camera, angle: float) -> Camera:
    """``camera`` turned by ``angle`` radians about the vertical axis through its target."""
    eye, target = np.asarray(camera.eye), np.asarray(camera.target)
    c, s = math.cos(angle), math.sin(angle)
    d = eye - target
    d = np.array([c * d[0] + s * d[2], d[1], -s * d[0] + c * d[2]])
    return Camera(tuple(float(x) for x in target + d), camera.target, camera.up, camera.fov_y)


def render_frames(
    items: Sequence[SceneItem],
    *,
    fps: float = 30.0,
    turntable: float | None = None,
    width: int = 960,
    height: int = 540,
    spacing: float = 1.5,
    overlay: bool = False,
    supersample: int = 1,
) -> Iterator[np.ndarray]:
    """``(height, width, 3)`` uint8 images of ``items``: the motion at ``fps``, or a turntable.

    Args:
        turntable: seconds for one turn of the camera around the first frame (None: play the
            motion; a still scene gives one image).
        overlay: draw every item in the same place instead of side by side ``spacing`` apart.

    The camera is framed once around the whole motion (first, middle and last frames), so a
    walking body walks through the picture instead of the picture following it.
    """
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps: expected a positive frame rate, got {fps}")
    spacing = check_spacing(spacing)
    if turntable is not None and not (math.isfinite(turntable) and turntable > 0):
        raise ValueError(f"turntable: expected a positive number of seconds, got {turntable}")
    duration = max(item.duration for item in items)
    radius = 0.02  # m, the markers' octahedra
    n = frame_count(items, fps=fps, turntable=turntable)
    if turntable is not None:
        scene = _scene(items, 0.0, spacing, overlay, radius)
        if not scene:
            raise ValueError("items: nothing to draw at the first frame (no body, no visible marker)")
        scene = _scene(items, 0.0, spacing, overlay, radius, _near(scene))
        base = frame_camera(scene, "front", width, height)
        for i in range(n):
            cam = _turn(base, 2 * math.pi * i / n)
            yield render_image(scene, width=width, height=height, camera=cam, supersample=supersample)
        return
    times = np.arange(n) / fps
    looks = [0.0, duration / 2, duration]
    probe = [m for t in looks for m in _scene(items, t, spacing, overlay, radius)]
    if not probe:  # nothing visible at the first, middle and last frames: look everywhere
        looks = [float(t) for t in np.linspace(0, duration, 33)]
        probe = [m for t in looks for m in _scene(items, t, spacing, overlay, radius)]
    if not probe:
        raise ValueError("items: nothing to draw (no body, no visible marker near its subject)")
    near = _near(probe)
    probe = [m for t in looks for m in _scene(items, t, spacing, overlay, radius, near)]
    camera = frame_camera(probe, "three_quarter", width, height)
    for t in times:  # a frame with nothing visible is the empty floor
        scene = _scene(items, float(t), spacing, overlay, radius, near)
        yield render_image(scene, width=width, height=height, camera=camera, supersample=supersample)


def _near(meshes: list[MeshSpec], margin: float = 2.0) -> np.ndarray:
    """(2, 3) the meshes' bounding box grown by ``margin`` m: where ghost markers are drawn."""
    pts = np.concatenate([m.vertices for m in meshes])
    return np.stack([pts.min(0) - margin, pts.max(0) + margin])


def frame_count(items: Sequence[SceneItem], *, fps: float, turntable: float | None = None) -> int:
    """How many images :func:`render_frames` makes."""
    if turntable is not None:
        return max(1, int(round(turntable * fps)))
    return int(math.floor(max(item.duration for item in items) * fps + 1e-9)) + 1


def png_paths(out: Path, count: int) -> list[Path]:
    """Where ``count`` PNG frames go: ``out`` itself for one, ``stem_0000.png``... for more."""
    if count == 1:
        return [out]
    return [out.with_name(f"{out.stem}_{i:04d}{out.suffix}") for i in range(count)]


def record(images: Iterator[np.ndarray], out: str | os.PathLike[str], *, fps: float, count: int) -> list[Path]:
    """Write ``count`` images to ``out`` (``.mp4`` or ``.png``); return the files written."""
    from PIL import Image

    from ...io.atomic import atomic_path

    out = Path(out)
    if out.suffix.lower() == ".png":
        paths = png_paths(out, count)
        for path, image in zip(paths, images, strict=False):
            with atomic_path(path) as tmp:
                Image.fromarray(image, mode="RGB").save(os.fspath(tmp), format="PNG")
        return paths
    if out.suffix.lower() != ".mp4":
        raise ValueError(f"out: expected a .mp4 or .png file, got {str(out)!r}")
    import imageio_ffmpeg

    with atomic_path(out) as tmp:
        writer = None
        try:
            for image in images:
                if writer is None:
                    h, w = image.shape[:2]
                    writer = imageio_ffmpeg.write_frames(
                        os.fspath(tmp), (w, h), fps=fps, codec="libx264", pix_fmt_out="yuv420p",
                        macro_block_size=2, output_params=["-y"], ffmpeg_log_level="error",
                    )  # fmt: skip
                    writer.send(None)
                writer.send(np.ascontiguousarray(image))
        finally:
            if writer is not None:
                writer.close()
    return [out]
