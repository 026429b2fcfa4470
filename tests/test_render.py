"""Software renderer: projection geometry, z-buffer, culling, ground plane, framing, output."""

from __future__ import annotations

import math

import numpy as np
import pytest
from PIL import Image

from conftest import icosphere
from unibody.viz.render import Camera, MeshSpec, frame_camera, project, render_image, render_png


def quad(x0, x1, y0, y1, z, facing: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned rectangle in the plane ``z``; counter-clockwise seen from ``facing * +Z``."""
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], dtype=float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    return v, (f if facing > 0 else f[:, ::-1])


RED, GREEN = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)


def is_red(img: np.ndarray) -> np.ndarray:
    r, g, b = (img[..., k].astype(int) for k in range(3))
    return (r > g + 60) & (r > b + 60)


def is_green(img: np.ndarray) -> np.ndarray:
    r, g, b = (img[..., k].astype(int) for k in range(3))
    return (g > r + 60) & (g > b + 60)


FRONT = Camera(eye=(0.0, 0.0, 4.0), target=(0.0, 0.0, 0.0), fov_y=30.0)


def test_project_pinhole():
    w, h = 400, 300
    p = project(FRONT, np.array([[0.0, 0.0, 0.0], [1.0, 0.5, 0.0], [0.0, 0.0, 2.0]]), w, h)
    f = 0.5 * h / math.tan(math.radians(15))
    np.testing.assert_allclose(p[0], [w / 2, h / 2, 4.0])
    np.testing.assert_allclose(p[1], [w / 2 + f / 4, h / 2 - 0.5 * f / 4, 4.0])  # y down in pixels
    np.testing.assert_allclose(p[2], [w / 2, h / 2, 2.0])


@pytest.mark.parametrize("supersample", [1, 2])
def test_sphere_silhouette_area(supersample):
    r, d, w, h = 0.5, 3.0, 400, 300
    cam = Camera(eye=(0.0, 0.0, d), target=(0.0, 0.0, 0.0), fov_y=30.0)
    v, f = icosphere(4, r)
    img = render_image([MeshSpec(v, f, RED)], width=w, height=h, camera=cam, ground_y=None, supersample=supersample)
    # The silhouette is the circle of tangency: radius r*sqrt(1 - r^2/d^2) at z = r^2/d.
    rim = np.array([[r * math.sqrt(1 - r**2 / d**2), 0.0, r**2 / d], [0.0, 0.0, 0.0]])
    p = project(cam, rim, w, h)
    radius_px = p[0, 0] - p[1, 0]
    expected = math.pi * radius_px**2
    mask = is_red(img)
    assert abs(mask.sum() - expected) / expected < 0.05
    ys, xs = np.nonzero(mask)
    assert abs(xs.mean() + 0.5 - w / 2) < 1 and abs(ys.mean() + 0.5 - h / 2) < 1


@pytest.mark.parametrize("order", [0, 1])
def test_zbuffer_nearer_wins(order):
    far = MeshSpec(*quad(-1.5, 1.5, -1.0, 1.0, 0.0), RED, "far")  # big: also exercises row strips
    near = MeshSpec(*quad(-0.5, 0.5, -0.5, 0.5, 0.3), GREEN, "near")
    meshes = [far, near] if order == 0 else [near, far]
    w, h = 400, 300
    img = render_image(meshes, width=w, height=h, camera=FRONT, ground_y=None, supersample=1)
    c, a = project(FRONT, np.array([[0.0, 0.0, 0.3], [1.0, 0.75, 0.0]]), w, h).astype(int)[:, :2]
    assert is_green(img[c[1], c[0]])
    assert is_red(img[a[1], a[0]])
    # Every pixel of the near quad's interior is green, with no red speckles.
    q = project(FRONT, np.array([[-0.45, 0.45, 0.3], [0.45, -0.45, 0.3]]), w, h).astype(int)
    assert is_green(img[q[0, 1] : q[1, 1], q[0, 0] : q[1, 0]]).all()


def test_interpenetrating_quads_split():
    # A quad tilted through another: each wins on its own side of the intersection line.
    tilted = np.array([[-1, -1, -0.5], [1, -1, -0.5], [1, 1, 0.5], [-1, 1, 0.5]], dtype=float)
    meshes = [MeshSpec(*quad(-1, 1, -1, 1, 0.0), RED), MeshSpec(tilted, np.array([[0, 1, 2], [0, 2, 3]]), GREEN)]
    w, h = 200, 200
    img = render_image(meshes, width=w, height=h, camera=FRONT, ground_y=None, supersample=1)
    up, down = project(FRONT, np.array([[0.0, 0.5, 0.25], [0.0, -0.5, 0.0]]), w, h).astype(int)[:, :2]
    assert is_green(img[up[1], up[0]]) and is_red(img[down[1], down[0]])


def test_no_cracks_in_fine_tessellation():
    n = 80
    xs = np.linspace(-1, 1, n + 1)
    gx, gy = np.meshgrid(xs, xs)
    rng = np.random.default_rng(1)
    jitter = rng.uniform(-0.3, 0.3, gx.shape) * (2 / n)
    jitter[[0, -1], :] = 0
    jitter[:, [0, -1]] = 0
    v = np.stack([gx + jitter, gy + jitter.T, np.zeros_like(gx)], -1).reshape(-1, 3)
    i = np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]
    f = np.concatenate([np.stack([i, i + 1, i + n + 2], -1), np.stack([i, i + n + 2, i + n + 1], -1)]).reshape(-1, 3)
    w, h = 300, 300
    img = render_image([MeshSpec(v, f, RED)], width=w, height=h, camera=FRONT, ground_y=None, supersample=1)
    q = project(FRONT, np.array([[-0.98, 0.98, 0.0], [0.98, -0.98, 0.0]]), w, h).astype(int)
    assert is_red(img[q[0, 1] : q[1, 1], q[0, 0] : q[1, 0]]).all()


def test_backface_culling():
    w, h = 100, 100
    away = MeshSpec(*quad(-0.5, 0.5, -0.5, 0.5, 0.0, facing=-1), RED)
    img = render_image([away], width=w, height=h, camera=FRONT, ground_y=None, supersample=1)
    assert not is_red(img).any()
    img = render_image([away], width=w, height=h, camera=FRONT, ground_y=None, supersample=1, cull_backfaces=False)
    assert is_red(img).sum() > 100
    # A closed mesh seen from outside is unaffected by culling.
    v, f = icosphere(2, 0.5)
    a = render_image([MeshSpec(v, f, RED)], width=w, height=h, camera=FRONT, ground_y=None, supersample=1)
    b = render_image(
        [MeshSpec(v, f, RED)], width=w, height=h, camera=FRONT, ground_y=None, supersample=1, cull_backfaces=False
    )
    assert is_red(a).sum() == is_red(b).sum() > 100


def test_ground_plane_occludes_and_shows():
    cam = Camera(eye=(0.0, 1.0, 4.0), target=(0.0, 0.8, 0.0), fov_y=60.0)
    w, h = 160, 120
    v, f = icosphere(2, 0.4, centre=(0.0, -0.6, 0.0))  # entirely below the floor
    buried = MeshSpec(v, f, RED)
    with_ground = render_image([buried], width=w, height=h, camera=cam, ground_y=0.0, supersample=1)
    without = render_image([buried], width=w, height=h, camera=cam, ground_y=None, supersample=1)
    assert is_red(without).sum() > 50
    assert not is_red(with_ground).any()
    # The ground changes the lower part of the image but not the sky above the horizon.
    diff = np.abs(with_ground.astype(int) - without.astype(int)).sum(-1)
    assert (diff[-10:] > 0).mean() > 0.5
    assert (diff[:5] == 0).all()


@pytest.mark.parametrize("view", ["front", "three_quarter"])
def test_auto_framing_fits_and_fills(view):
    rng = np.random.default_rng(2)
    meshes = []
    for k in range(3):
        v, f = icosphere(1, 0.3, centre=(k * 0.8 - 0.8, 0.3 + rng.uniform(0, 1), 0.0))
        meshes.append(MeshSpec(v, f, (0.5, 0.5, 0.5)))
    w, h = 320, 160
    cam = frame_camera(meshes, view, w, h)
    pts = np.concatenate([m.vertices for m in meshes])
    p = project(cam, pts, w, h)
    assert (p[:, 2] > 0).all()
    assert p[:, 0].min() >= 0 and p[:, 0].max() <= w and p[:, 1].min() >= 0 and p[:, 1].max() <= h
    # The bounding box is framed tightly along at least one axis, with a margin.
    lo, hi = pts.min(0), pts.max(0)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    c = project(cam, corners, w, h)
    assert c[:, 0].min() >= 0 and c[:, 0].max() <= w and c[:, 1].min() >= 0 and c[:, 1].max() <= h
    span = max((c[:, 0].max() - c[:, 0].min()) / w, (c[:, 1].max() - c[:, 1].min()) / h)
    assert 0.8 < span < 0.97
    if view == "three_quarter":  # camera to the +X side, above the target
        assert cam.eye[0] > cam.target[0] and cam.eye[1] > cam.target[1]
    else:
        assert cam.eye[0] == pytest.approx(cam.target[0]) and cam.eye[2] > cam.target[2]


def test_output_shape_dtype_and_png(tmp_path):
    v, f = icosphere(1, 0.5, centre=(0.0, 0.5, 0.0))
    mesh = MeshSpec(v, f, (0.3, 0.5, 0.9))
    img = render_image([mesh], width=64, height=48)
    assert img.shape == (48, 64, 3) and img.dtype == np.uint8
    path = tmp_path / "out.png"
    render_png(path, [mesh], width=80, height=40, view="front")
    with Image.open(path) as im:
        assert im.format == "PNG" and im.size == (80, 40) and im.mode == "RGB"


def test_bad_inputs():
    v, f = icosphere(0)
    with pytest.raises(ValueError, match="^meshes:"):
        render_image([])
    with pytest.raises(ValueError, match="^meshes:"):
        render_png("unused.png", [])
    with pytest.raises(ValueError, match=r"^meshes\[0\]:"):
        render_image([(v, f)])
    with pytest.raises(ValueError, match="^view:"):
        render_image([MeshSpec(v, f)], view="side")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="^supersample:"):
        render_image([MeshSpec(v, f)], supersample=0)


def test_far_scenes_and_empty_frames():
    # A scene 1e20 m away was framed forever (lo + 1 == lo: the search step stayed 0).
    v, f = icosphere(1, 0.3, (0.0, 0.5, 0.0))
    far = [MeshSpec(v * 0.1 + [1e20, 0.0, 0.0], f, (1.0, 0.0, 0.0), "far")]
    cam = frame_camera(far, "front", 64, 48)
    assert np.isfinite(cam.eye).all() and abs(cam.target[0] - 1e20) < 1e6
    with pytest.raises(ValueError, match="expected finite values"):
        frame_camera([MeshSpec(v * np.nan, f, (1.0, 0.0, 0.0), "nan")], "front", 64, 48)
    # With a camera, an empty scene is the background and the ground.
    near = [MeshSpec(v, f, (1.0, 0.0, 0.0), "near")]
    cam = frame_camera(near, "three_quarter", 64, 48)
    empty = render_image([], width=64, height=48, camera=cam, supersample=1)
    full = render_image(near, width=64, height=48, camera=cam, supersample=1)
    assert empty.shape == full.shape == (48, 64, 3) and np.abs(empty.astype(int) - full).sum() > 0
    with pytest.raises(ValueError, match="at least one MeshSpec"):
        render_image([], width=64, height=48)
