"""Pictures of bodies with markers: front and back views side by side (for layouts and solves)."""

from __future__ import annotations

import os

import numpy as np
import torch
from PIL import Image, ImageDraw

from ..viz.render import Camera, MeshSpec, frame_camera, project, render_image

__all__ = ["render_markers"]

_OCTA_V = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float64)
_OCTA_F = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])


def _blobs(points: np.ndarray, radius: float, color, name: str) -> MeshSpec:
    """One octahedron per point, as a single mesh."""
    v = (points[:, None, :] + radius * _OCTA_V[None]).reshape(-1, 3)
    f = (_OCTA_F[None] + 6 * np.arange(len(points))[:, None, None]).reshape(-1, 3)
    return MeshSpec(v, f, color, name)


def render_markers(
    path: str | os.PathLike[str] | None,
    vertices: torch.Tensor | np.ndarray,
    faces: torch.Tensor | np.ndarray,
    markers: torch.Tensor | np.ndarray,
    *,
    observed: torch.Tensor | np.ndarray | None = None,
    labels: list[str] | None = None,
    size: int = 700,
) -> np.ndarray:
    """Render a body (V, 3) with its model markers (M, 3, red) and observed points (K, 3, blue).

    Returns the (size, 2 size, 3) uint8 image (front | back) and writes it to ``path`` if given.
    NaN markers or points are skipped. ``labels`` (M) are drawn next to the model markers.
    """
    v = np.asarray(vertices, dtype=np.float64)
    m = np.asarray(markers, dtype=np.float64)
    keep = np.isfinite(m).all(axis=1)
    meshes = [MeshSpec(v, np.asarray(faces), (0.78, 0.76, 0.74), "body"), _blobs(m[keep], 0.012, (0.85, 0.1, 0.1), "m")]
    if observed is not None:
        o = np.asarray(observed, dtype=np.float64)
        o = o[np.isfinite(o).all(axis=1)]
        if len(o):
            meshes.append(_blobs(o, 0.008, (0.1, 0.3, 0.9), "obs"))
    ground = float(v[:, 1].min())
    front = frame_camera(meshes, "front", size, size)
    target = np.asarray(front.target)
    eye = 2 * target - np.asarray(front.eye)  # the front eye mirrored through the target
    back = Camera(tuple(eye), front.target, front.up, front.fov_y)
    halves = []
    for cam in (front, back):
        img = Image.fromarray(render_image(meshes, width=size, height=size, camera=cam, ground_y=ground))
        if labels is not None:
            draw = ImageDraw.Draw(img)
            px = project(cam, np.where(keep[:, None], m, 0.0), size, size)
            toward = (m - np.asarray(cam.target)) @ (np.asarray(cam.eye) - np.asarray(cam.target))
            for (x, y, _), label, ok, t in zip(px, labels, keep, toward, strict=True):
                if ok and t > 0:
                    draw.text((x + 4, y - 6), label, fill=(20, 20, 20))
        halves.append(np.asarray(img))
    image = np.concatenate(halves, axis=1)
    if path is not None:
        Image.fromarray(image).save(os.fspath(path), format="PNG")
    return image
