"""Offscreen software renderer for quick looks at bodies: numpy + Pillow only.

Conventions: metres, Y up, bodies face +Z.  The ``"front"`` camera sits on +Z and
looks toward -Z; ``"three_quarter"`` swings it 30 degrees about Y toward +X and
raises it so that it looks 10 degrees down.  The camera is a pinhole with a
30 degree vertical field of view, framed automatically around the meshes'
bounding box. Vectorised rasterisation into a 64-bit depth-and-face-id buffer, deferred
shading, an analytic ground plane, supersampling reduced by Pillow's LANCZOS filter.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from PIL import Image, ImageFilter

from ..io.glb import MeshSpec, mesh_list, vertex_normals

__all__ = ["Camera", "MeshSpec", "frame_camera", "project", "render_image", "render_png"]

View = Literal["front", "three_quarter"]

_FOV_Y = 30.0
_MARGIN = 0.08
_NEAR = 1e-3
_BLOCK = 1 << 21  # candidate pixels per block
_STRIP = 1 << 16  # bounding boxes larger than this are cut into row strips
_EMPTY = np.iinfo(np.int64).max
# 2^30 levels: exactly representable in float32 (2^31 - 2 rounds up to 2^31, and 2^31 << 32
# overflows the int64 key into a negative number that wins every depth test).
_DEPTH_LEVELS = 1 << 30
_EPS = 1e-5  # edge-function slack in barycentric units: closes cracks on shared edges

_BG_TOP = np.array([0.97, 0.975, 0.985])
_BG_BOTTOM = np.array([0.80, 0.82, 0.86])
_GROUND = np.array([0.90, 0.905, 0.91])


@dataclass(frozen=True, slots=True)
class Camera:
    """A pinhole camera: position ``eye`` looking at ``target``, ``fov_y`` in degrees.

    The image size is not part of the camera; the focal length in pixels is
    ``(height / 2) / tan(fov_y / 2)`` for an image ``height`` pixels tall.
    """

    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov_y: float = _FOV_Y

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unit ``(right, up, forward)`` vectors in world coordinates."""
        eye = np.asarray(self.eye, dtype=np.float64)
        fwd = np.asarray(self.target, dtype=np.float64) - eye
        norm = np.linalg.norm(fwd)
        if not norm > 0:
            raise ValueError("camera: eye and target coincide")
        fwd /= norm
        right = np.cross(fwd, np.asarray(self.up, dtype=np.float64))
        rn = np.linalg.norm(right)
        if not rn > 1e-12:
            raise ValueError("camera: up is parallel to the viewing direction")
        right /= rn
        return right, np.cross(right, fwd), fwd

    def focal_px(self, height: int) -> float:
        """Focal length in pixels for an image ``height`` pixels tall."""
        if not 0.0 < self.fov_y < 180.0:
            raise ValueError(f"camera: fov_y must lie in (0, 180) degrees, got {self.fov_y}")
        return 0.5 * height / math.tan(math.radians(self.fov_y) / 2)


def project(camera: Camera, points: np.ndarray, width: int, height: int) -> np.ndarray:
    """Project world ``points`` ``(N, 3)`` to ``(N, 3)``: pixel x, pixel y, depth.

    Pixel coordinates are continuous with the origin at the top-left corner of the
    image (pixel ``(i, j)`` covers ``[i, i+1) x [j, j+1)``, its centre at
    ``(i + 0.5, j + 0.5)``), x to the right, y down.  Depth is the distance along
    the viewing direction; points with depth <= 0 get meaningless pixel values.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points: expected shape (N, 3), got {p.shape}")
    right, up, fwd = camera.basis()
    rel = p - np.asarray(camera.eye, dtype=np.float64)
    xc, yc, zc = rel @ right, rel @ up, rel @ fwd
    f = camera.focal_px(height)
    with np.errstate(divide="ignore", invalid="ignore"):
        px = 0.5 * width + f * xc / zc
        py = 0.5 * height - f * yc / zc
    return np.stack([px, py, zc], axis=1)


def _view_direction(view: str) -> np.ndarray:
    """Unit vector from the scene toward the camera."""
    if view == "front":
        return np.array([0.0, 0.0, 1.0])
    if view == "three_quarter":
        az, el = math.radians(30.0), math.radians(10.0)
        return np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
    raise ValueError(f"view: expected 'front' or 'three_quarter', got {view!r}")


def _fit_axis(a: np.ndarray, h: np.ndarray, tan_half: float) -> tuple[float, float]:
    """Smallest distance D (and the matching lateral shift s) with every point inside.

    Points are at lateral offset ``a`` and depth ``D - h`` from the camera; the
    camera may shift laterally by ``s``: need ``|a - s| <= tan_half * (D - h)``.
    """

    def interval(d: float) -> tuple[float, float]:
        reach = tan_half * (d - h)
        return float(np.max(a - reach)), float(np.min(a + reach))

    lo = float(np.max(h)) + 1e-6
    step = max(1.0, float(np.ptp(a)), float(np.ptp(h)))  # past 1e16 m, lo + 1 == lo: doubling 0 never ends
    hi = lo + step
    while interval(hi)[0] > interval(hi)[1]:
        step *= 2
        hi = lo + step
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        s_lo, s_hi = interval(mid)
        if s_lo <= s_hi:
            hi = mid
        else:
            lo = mid
    s_lo, s_hi = interval(hi)
    return hi, 0.5 * (s_lo + s_hi)


def frame_camera(
    meshes: Sequence[MeshSpec], view: View = "three_quarter", width: int = 1600, height: int = 800
) -> Camera:
    """A camera looking from ``view`` that fits the meshes' bounding box with a margin."""
    pts = _all_vertices(meshes)
    if not np.isfinite(pts).all():
        raise ValueError("meshes: expected finite vertices to frame a camera on")
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    back = _view_direction(view)
    fwd = -back
    right = np.cross(fwd, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    centre = 0.5 * (lo + hi)
    rel = corners - centre
    a, b, h = rel @ right, rel @ up, rel @ back
    tan_y = math.tan(math.radians(_FOV_Y) / 2) * (1 - _MARGIN)
    tan_x = math.tan(math.radians(_FOV_Y) / 2) * width / height * (1 - _MARGIN)
    dx, sx = _fit_axis(a, h, tan_x)
    dy, sy = _fit_axis(b, h, tan_y)
    dist = max(dx, dy, 1e-3)
    # Re-centre along the looser axis for the final distance.
    if dx < dist:
        sx = 0.5 * (np.max(a - tan_x * (dist - h)) + np.min(a + tan_x * (dist - h)))
    if dy < dist:
        sy = 0.5 * (np.max(b - tan_y * (dist - h)) + np.min(b + tan_y * (dist - h)))
    target = centre + sx * right + sy * up
    eye = target + dist * back
    return Camera(tuple(float(x) for x in eye), tuple(float(x) for x in target), (0.0, 1.0, 0.0), _FOV_Y)


def _check_meshes(meshes: Sequence[MeshSpec]) -> list[MeshSpec]:
    meshes = mesh_list(meshes)
    if sum(len(m.vertices) for m in meshes) == 0:
        raise ValueError("meshes: all meshes are empty (no vertices)")
    return meshes


def _all_vertices(meshes: Sequence[MeshSpec]) -> np.ndarray:
    meshes = _check_meshes(meshes)
    return np.concatenate([m.vertices for m in meshes])


# ----------------------------------------------------------------------------- rasterisation


@dataclass(slots=True)
class _Setup:
    """Per-face screen-space data of the triangles that survived culling."""

    fid: np.ndarray  # (T,) global face index
    x0: np.ndarray  # (T,) int bbox
    y0: np.ndarray
    bw: np.ndarray
    bh: np.ndarray
    ox: np.ndarray  # (T,) bbox pixel-centre origin relative to vertex 2, float64
    oy: np.ndarray
    coef: np.ndarray  # (T, 3, 3) rows b0, b1, 1/z as (A, B, C): v = A*dx + B*dy + C at (x2, y2)


def _setup(scr: np.ndarray, faces: np.ndarray, width: int, height: int, cull: bool) -> _Setup:
    x, y, z = scr[:, 0], scr[:, 1], scr[:, 2]
    i0, i1, i2 = faces[:, 0], faces[:, 1], faces[:, 2]
    zmin = np.minimum(np.minimum(z[i0], z[i1]), z[i2])
    keep = zmin > _NEAR
    x0, x1, x2 = x[i0], x[i1], x[i2]
    y0, y1, y2 = y[i0], y[i1], y[i2]
    with np.errstate(invalid="ignore", over="ignore"):
        det = (y1 - y2) * (x0 - x2) + (x2 - x1) * (y0 - y2)
        # In image space (y down) a triangle that is counter-clockwise as seen by
        # the camera has det < 0.
        keep &= (det < -1e-12) if cull else (np.abs(det) > 1e-12)
        bx0 = np.ceil(np.minimum(np.minimum(x0, x1), x2) - 0.5)
        bx1 = np.floor(np.maximum(np.maximum(x0, x1), x2) - 0.5)
        by0 = np.ceil(np.minimum(np.minimum(y0, y1), y2) - 0.5)
        by1 = np.floor(np.maximum(np.maximum(y0, y1), y2) - 0.5)
        keep &= (bx1 >= 0) & (by1 >= 0) & (bx0 <= width - 1) & (by0 <= height - 1) & (bx1 >= bx0) & (by1 >= by0)
    idx = np.flatnonzero(keep)
    bx0 = np.clip(bx0[idx], 0, width - 1).astype(np.int64)
    bx1 = np.clip(bx1[idx], 0, width - 1).astype(np.int64)
    by0 = np.clip(by0[idx], 0, height - 1).astype(np.int64)
    by1 = np.clip(by1[idx], 0, height - 1).astype(np.int64)
    x0, x1, x2, y0, y1, y2, det = (a[idx] for a in (x0, x1, x2, y0, y1, y2, det))
    iz = 1.0 / z
    iz0, iz1, iz2 = iz[i0[idx]], iz[i1[idx]], iz[i2[idx]]
    a0, b0 = (y1 - y2) / det, (x2 - x1) / det
    a1, b1 = (y2 - y0) / det, (x0 - x2) / det
    # At vertex 2: b0 = b1 = 0, 1/z = iz2.
    az = a0 * (iz0 - iz2) + a1 * (iz1 - iz2)
    bz = b0 * (iz0 - iz2) + b1 * (iz1 - iz2)
    coef = np.empty((len(idx), 3, 3))
    coef[:, 0] = np.stack([a0, b0, np.zeros_like(a0)], axis=1)
    coef[:, 1] = np.stack([a1, b1, np.zeros_like(a1)], axis=1)
    coef[:, 2] = np.stack([az, bz, iz2], axis=1)
    return _Setup(
        fid=idx,
        x0=bx0,
        y0=by0,
        bw=bx1 - bx0 + 1,
        bh=by1 - by0 + 1,
        ox=bx0 + 0.5 - x2,
        oy=by0 + 0.5 - y2,
        coef=coef,
    )


def _work_items(s: _Setup) -> tuple[np.ndarray, ...]:
    """Cut big bounding boxes into row strips; returns per-item (tri, row0, rows)."""
    rows_per = np.maximum(1, _STRIP // s.bw)
    nstrip = -(-s.bh // rows_per)
    tri = np.repeat(np.arange(len(s.bw)), nstrip)
    first = np.cumsum(nstrip) - nstrip
    k = np.arange(len(tri)) - np.repeat(first, nstrip)
    row0 = k * rows_per[tri]
    rows = np.minimum(rows_per[tri], s.bh[tri] - row0)
    return tri, row0, rows


def _zpass(s: _Setup, width: int, height: int, iz_lo: float, iz_hi: float) -> np.ndarray:
    """Z-buffer of ``(quantised depth << 32) | face id`` keys, ``_EMPTY`` where uncovered."""
    zbuf = np.full(width * height, _EMPTY, dtype=np.int64)
    if len(s.fid) == 0:
        return zbuf
    tri, row0, rows = _work_items(s)
    n = s.bw[tri] * rows
    ends = np.cumsum(n)
    scale = _DEPTH_LEVELS / max(iz_hi - iz_lo, 1e-30)
    # Per-item constants: barycentrics and 1/z at the item's first pixel centre.
    ox = s.ox[tri]
    oy = s.oy[tri] + row0
    c = s.coef[tri]
    base = c[:, :, 0] * ox[:, None] + c[:, :, 1] * oy[:, None] + c[:, :, 2]
    # 1/z is quantised relative to iz_hi (nearest): key depth = (iz_hi - 1/z) * scale.
    base[:, 2] = (iz_hi - base[:, 2]) * scale
    slope_x = c[:, :, 0].copy()
    slope_y = c[:, :, 1].copy()
    slope_x[:, 2] *= -scale
    slope_y[:, 2] *= -scale
    base32 = base.astype(np.float32)
    sx32 = slope_x.astype(np.float32)
    sy32 = slope_y.astype(np.float32)
    start_pix = (s.y0[tri] + row0) * width + s.x0[tri]
    fid = s.fid[tri]
    bw = s.bw[tri]

    lo_item = 0
    while lo_item < len(tri):
        target = (ends[lo_item - 1] if lo_item else 0) + _BLOCK
        hi_item = max(lo_item + 1, int(np.searchsorted(ends, target, side="right")))
        sl = slice(lo_item, hi_item)
        cnt = n[sl]
        total = int(cnt.sum())
        local = np.repeat(np.arange(hi_item - lo_item, dtype=np.int32), cnt)
        first = (np.cumsum(cnt) - cnt).astype(np.int32)
        k = np.arange(total, dtype=np.int32) - first[local]
        w = bw[sl].astype(np.int32)[local]
        dy = k // w
        dx = k - dy * w
        dxf = dx.astype(np.float32)
        dyf = dy.astype(np.float32)
        b = base32[sl][local]
        gx = sx32[sl][local]
        gy = sy32[sl][local]
        l0 = b[:, 0] + gx[:, 0] * dxf + gy[:, 0] * dyf
        l1 = b[:, 1] + gx[:, 1] * dxf + gy[:, 1] * dyf
        inside = (l0 >= -_EPS) & (l1 >= -_EPS) & (l0 + l1 <= 1 + _EPS)
        sel = np.flatnonzero(inside)
        local = local[sel]
        dx = dx[sel]
        dy = dy[sel]
        q = b[sel, 2] + gx[sel, 2] * dxf[sel] + gy[sel, 2] * dyf[sel]
        q = np.clip(q, 0, _DEPTH_LEVELS).astype(np.int64)
        key = (q << 32) | fid[sl][local]
        pix = start_pix[sl][local] + dy.astype(np.int64) * width + dx
        np.minimum.at(zbuf, pix, key)
        lo_item = hi_item
    return zbuf


# ----------------------------------------------------------------------------- shading


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.power(np.clip(c, 0, 1), 2.2)


_LUT_SIZE = 1 << 14
_SRGB_LUT = (np.power(np.linspace(0.0, 1.0, _LUT_SIZE), 1 / 2.2) * 255 + 0.5).astype(np.uint8)


def _linear_to_srgb8(c: np.ndarray) -> np.ndarray:
    """Linear [0, 1] floats to sRGB-ish (gamma 2.2) uint8 through a lookup table."""
    idx = np.clip(c, 0.0, 1.0)
    idx *= _LUT_SIZE - 1
    idx += 0.5
    return _SRGB_LUT[idx.astype(np.uint16)]


def _contact_shadow(meshes: Sequence[MeshSpec], ground_y: float) -> tuple[np.ndarray, np.ndarray, float]:
    """A soft darkening map on the ground: ``(map (Nz, Nx) in [0, 1], origin (x, z), cell)``."""
    pts = np.concatenate([m.vertices for m in meshes if len(m.vertices)] or [np.zeros((0, 3))])
    height = pts[:, 1] - ground_y
    keep = height > -0.05
    pts, height = pts[keep], height[keep]
    cell = 0.01
    pad = 0.6
    if len(pts) == 0:
        return np.zeros((3, 3), dtype=np.float32), np.zeros(2), cell
    lo = pts[:, [0, 2]].min(axis=0) - pad
    hi = pts[:, [0, 2]].max(axis=0) + pad
    if not np.isfinite(hi - lo).all() or float((hi - lo).max()) > 1e4:  # no shadow worth a grid 10 km wide
        return np.zeros((3, 3), dtype=np.float32), lo, cell
    nx, nz = (np.ceil((hi - lo) / cell).astype(int) + 1).tolist()
    if nx * nz > 4_000_000:  # very large scenes: coarser grid
        cell *= math.sqrt(nx * nz / 4_000_000)
        nx, nz = (np.ceil((hi - lo) / cell).astype(int) + 1).tolist()
    nx, nz = max(nx, 3), max(nz, 3)  # past 1e16 m, lo + pad == lo: a grid of one row has no inside
    ix = np.clip(((pts[:, 0] - lo[0]) / cell).astype(int), 0, nx - 1)
    iz = np.clip(((pts[:, 2] - lo[1]) / cell).astype(int), 0, nz - 1)
    flat = iz * nx + ix

    def blurred(weights: np.ndarray, sigma_m: float) -> np.ndarray:
        occ = np.zeros(nx * nz)
        np.maximum.at(occ, flat, weights)
        img = Image.fromarray((occ.reshape(nz, nx) * 255).astype(np.uint8), mode="L")
        # Vertices are sparse at this resolution: dilate by ~2 cm, then blur.
        img = img.filter(ImageFilter.MaxFilter(2 * max(1, round(0.02 / cell)) + 1))
        img = img.filter(ImageFilter.GaussianBlur(radius=max(sigma_m / cell, 0.5)))
        return np.asarray(img, dtype=np.float32) / 255

    # Broad occlusion under the whole body, stronger for low parts; tight contact near the floor.
    broad = blurred(np.exp(-np.maximum(height, 0) / 0.4), 0.07)
    contact = blurred((height < 0.025).astype(np.float64), 0.02)
    shadow = np.clip(0.4 * broad + 0.45 * contact, 0, 0.75)
    shadow[0, :] = shadow[-1, :] = shadow[:, 0] = shadow[:, -1] = 0  # clamp lookups outside to "no shadow"
    return shadow, lo, cell


def _shade(
    meshes: list[MeshSpec], camera: Camera, W: int, H: int, cull: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rasterise and shade; returns covered pixel indices, their linear RGB and depth."""
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes])
    verts = np.concatenate([m.vertices for m in meshes])
    faces = (
        np.concatenate([m.faces + o for m, o in zip(meshes, offsets[:-1], strict=True)]).astype(np.int64).reshape(-1, 3)
    )
    face_mesh = np.repeat(np.arange(len(meshes)), [len(m.faces) for m in meshes])
    normals = np.concatenate([vertex_normals(m.vertices, m.faces) for m in meshes])
    colors = _srgb_to_linear(np.array([m.color for m in meshes], dtype=np.float64)).astype(np.float32)

    right, up, fwd = camera.basis()
    eye = np.asarray(camera.eye, dtype=np.float64)
    scr = project(camera, verts, W, H)
    s = _setup(scr, faces, W, H, cull)
    if len(s.fid) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 3), dtype=np.float32), np.zeros(0, dtype=np.float32)
    zs = scr[faces[s.fid], 2]
    iz_lo, iz_hi = float(1 / zs.max()), float(1 / zs.min())
    zbuf = _zpass(s, W, H, iz_lo, iz_hi)
    pix = np.flatnonzero(zbuf != _EMPTY)
    gface = (zbuf[pix] & 0xFFFFFFFF).astype(np.int64)  # global face id
    del zbuf
    f = faces[gface]
    # Recompute barycentrics (float64) of the winning face at each pixel centre.
    dx = (pix % W) + 0.5 - scr[f[:, 2], 0]
    dy = (pix // W) + 0.5 - scr[f[:, 2], 1]
    c = s.coef[np.searchsorted(s.fid, gface)]
    l0 = np.clip(c[:, 0, 0] * dx + c[:, 0, 1] * dy, 0, 1)
    l1 = np.clip(c[:, 1, 0] * dx + c[:, 1, 1] * dy, 0, 1 - l0)
    iz = 1 / scr[f, 2]
    wts = np.stack([l0, l1, 1 - l0 - l1], axis=1) * iz  # perspective-correct weights
    izp = wts.sum(axis=1)
    wts = (wts / izp[:, None]).astype(np.float32)
    depth = (1 / izp).astype(np.float32)
    nf = normals.astype(np.float32)[f]
    n = wts[:, 0, None] * nf[:, 0] + wts[:, 1, None] * nf[:, 1] + wts[:, 2, None] * nf[:, 2]
    n /= np.maximum(np.sqrt(np.einsum("pd,pd->p", n, n)), 1e-12)[:, None]
    vf = verts[f]
    pos = wts[:, 0, None] * vf[:, 0] + wts[:, 1, None] * vf[:, 1] + wts[:, 2, None] * vf[:, 2]
    vdir = (eye - pos).astype(np.float32)
    vdir /= np.sqrt(np.einsum("pd,pd->p", vdir, vdir))[:, None]
    ndv = np.einsum("pd,pd->p", n, vdir)
    if not cull:
        flip = ndv < 0
        n[flip] *= -1
        ndv[flip] *= -1
    # Lights fixed to the camera: key from the upper left, weak fill from the right.
    key = -0.55 * right + 0.75 * up - 0.55 * fwd
    key = (key / np.linalg.norm(key)).astype(np.float32)
    fill = 0.7 * right + 0.05 * up - 0.7 * fwd
    fill = (fill / np.linalg.norm(fill)).astype(np.float32)
    ndl = np.clip(n @ key, 0, None)
    ndf = np.clip(n @ fill, 0, None)
    ambient = 0.10 + 0.07 * (1 + n[:, 1])  # hemispheric: brighter facing the sky
    half = vdir + key
    half /= np.sqrt(np.einsum("pd,pd->p", half, half))[:, None]
    spec = 0.06 * np.clip(np.einsum("pd,pd->p", n, half), 0, 1) ** 24 * (ndl > 0)
    rim = 0.10 * (1 - np.clip(ndv, 0, 1)) ** 3  # separates silhouettes from the background
    light = ambient + 0.85 * ndl + 0.22 * ndf + rim
    rgb = colors[face_mesh[gface]] * light[:, None] + spec[:, None]
    return pix, rgb.astype(np.float32), depth


def _ground(
    camera: Camera, W: int, H: int, ground_y: float, meshes: Sequence[MeshSpec], bg_rows: np.ndarray
) -> tuple[int, np.ndarray, np.ndarray] | None:
    """Ground plane for rows ``r0:``: ``(r0, rgb (h, W, 3), depth (h, W) with inf where missed)``."""
    right, up, fwd = camera.basis()
    eye = np.asarray(camera.eye, dtype=np.float64)
    if eye[1] <= ground_y:
        return None
    f = camera.focal_px(H)
    # Ray per pixel: eye + t * (fwd + xn * right + yn * up), t = depth along fwd.
    yn = ((np.arange(H) + 0.5 - 0.5 * H) / -f).astype(np.float32)
    xn = ((np.arange(W) + 0.5 - 0.5 * W) / f).astype(np.float32)
    row_max = fwd[1] + yn * up[1] + np.maximum(xn[0] * right[1], xn[-1] * right[1])
    rows = np.flatnonzero(row_max < 0)
    if len(rows) == 0:
        return None
    r0 = int(rows[0])
    yn = yn[r0:, None]
    xn = xn[None, :]
    dir_y = np.float32(fwd[1]) + xn * np.float32(right[1]) + yn * np.float32(up[1])  # (h, W)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.float32(ground_y - eye[1]) / dir_y
    t[~(dir_y < 0)] = np.inf
    with np.errstate(invalid="ignore"):
        gx = eye[0] + t * (fwd[0] + xn * right[0] + yn * up[0])
        gz = eye[2] + t * (fwd[2] + xn * right[2] + yn * up[2])
    gx = np.nan_to_num(gx, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)
    gz = np.nan_to_num(gz, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)
    scene_dist = float(np.linalg.norm(eye - np.asarray(camera.target, dtype=np.float64)))
    tn = np.minimum(t, 1e6) / np.float32(scene_dist)
    # Subtle checker of 0.5 m tiles, faded with distance to avoid moire.
    checker = (np.floor(gx * 2) + np.floor(gz * 2)) % 2 - 0.5
    tone = 1 + 0.07 * checker * np.exp(-((tn / 2) ** 2))
    # Soft contact shadow looked up in a top-down map.
    shadow, origin, cell = _contact_shadow(meshes, ground_y)
    u = np.clip((gx - np.float32(origin[0])) / np.float32(cell), 0, shadow.shape[1] - 1.001)
    v = np.clip((gz - np.float32(origin[1])) / np.float32(cell), 0, shadow.shape[0] - 1.001)
    iu, iv = u.astype(np.int32), v.astype(np.int32)
    fu, fv = u - iu, v - iv
    top = shadow[iv, iu] * (1 - fu) + shadow[iv, iu + 1] * fu
    bottom = shadow[iv + 1, iu] * (1 - fu) + shadow[iv + 1, iu + 1] * fu
    tone *= 1 - (top * (1 - fv) + bottom * fv)
    # Fog toward the background colour with distance.
    fog = 1 - np.exp(-((tn / 3.5) ** 2))
    ground = _srgb_to_linear(_GROUND).astype(np.float32)
    rgb = (tone * (1 - fog))[..., None] * ground + fog[..., None] * bg_rows[r0:, None, :]
    return r0, rgb.astype(np.float32), t


def render_image(
    meshes: Sequence[MeshSpec],
    *,
    width: int = 1600,
    height: int = 800,
    view: View = "three_quarter",
    ground_y: float | None = 0.0,
    camera: Camera | None = None,
    supersample: int = 2,
    cull_backfaces: bool = True,
) -> np.ndarray:
    """Render ``meshes`` to an ``(height, width, 3)`` uint8 RGB image.

    ``camera`` overrides the automatic framing chosen by ``view``.  ``ground_y``
    places a ground plane at that height (``None``: no ground).  ``supersample``
    renders at that many times the size and downsamples with LANCZOS
    (``1``: no anti-aliasing).  Meshes are expected to wind counter-clockwise
    seen from outside; pass ``cull_backfaces=False`` for meshes that do not.
    With a ``camera``, ``meshes`` may be empty (the background and the ground).
    """
    meshes = list(meshes)
    if meshes or camera is None:
        meshes = _check_meshes(meshes)
    if int(width) != width or width < 1 or int(height) != height or height < 1:
        raise ValueError(f"width, height: expected positive integers, got {width}, {height}")
    if int(supersample) != supersample or not 1 <= supersample <= 8:
        raise ValueError(f"supersample: expected an integer in [1, 8], got {supersample}")
    if ground_y is not None and not math.isfinite(ground_y):
        raise ValueError(f"ground_y: expected a finite float or None, got {ground_y}")
    width, height, supersample = int(width), int(height), int(supersample)
    if camera is None:
        camera = frame_camera(meshes, view, width, height)
    elif not isinstance(camera, Camera):
        raise ValueError(f"camera: expected a Camera, got {type(camera).__name__}")
    W, H = width * supersample, height * supersample

    t_rows = np.linspace(0, 1, H)[:, None]
    bg_rows = _srgb_to_linear(_BG_TOP * (1 - t_rows) + _BG_BOTTOM * t_rows).astype(np.float32)  # (H, 3)
    img = np.empty((H, W, 3), dtype=np.float32)
    img[:] = bg_rows[:, None, :]

    if meshes:
        pix, rgb, depth = _shade(meshes, camera, W, H, cull_backfaces)
    else:
        pix, rgb, depth = np.zeros(0, np.int64), np.zeros((0, 3), np.float32), np.zeros(0, np.float32)

    ground = _ground(camera, W, H, ground_y, meshes, bg_rows) if ground_y is not None else None
    if ground is not None:
        r0, g_rgb, g_t = ground
        hit = np.isfinite(g_t)
        np.copyto(img[r0:], g_rgb, where=hit[..., None])
        # Mesh fragments behind the ground plane lose.
        rel = pix - r0 * W
        below = rel >= 0
        front = np.ones(len(pix), dtype=bool)
        front[below] = depth[below] <= g_t.ravel()[rel[below]]
        pix, rgb = pix[front], rgb[front]
    img.reshape(-1, 3)[pix] = rgb

    out = _linear_to_srgb8(img)
    if supersample > 1:
        out = np.asarray(Image.fromarray(out, mode="RGB").resize((width, height), Image.Resampling.LANCZOS))
    return out


def render_png(
    path: str | os.PathLike[str],
    meshes: Sequence[MeshSpec],
    *,
    width: int = 1600,
    height: int = 800,
    view: View = "three_quarter",
    ground_y: float | None = 0.0,
    camera: Camera | None = None,
    supersample: int = 2,
) -> None:
    """Render ``meshes`` (see :func:`render_image`) and save the result as a PNG at ``path``."""
    image = render_image(
        meshes,
        width=width,
        height=height,
        view=view,
        ground_y=ground_y,
        camera=camera,
        supersample=supersample,
    )
    from ..io.atomic import atomic_path

    with atomic_path(path) as tmp:
        Image.fromarray(image, mode="RGB").save(os.fspath(tmp), format="PNG")
