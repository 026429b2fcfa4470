"""GLB export and the offscreen renderer: checked against independent readers and geometry."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from unibody.io.glb import MeshSpec, read_glb_indices, read_glb_positions, write_glb
from unibody.render import Camera, render_image


def _quad(z: float, color, size: float = 1.0) -> MeshSpec:
    s = size / 2
    v = np.array([[-s, -s, z], [s, -s, z], [s, s, z], [-s, s, z]])
    return MeshSpec(v, np.array([[0, 1, 2], [0, 2, 3]]), color, f"quad{z}")


def test_glb_round_trip_and_header(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    a, b = _quad(0.0, (1, 0, 0)), _quad(0.5, (0, 0, 1), 0.5)
    path = tmp_path / "x.glb"
    write_glb(path, [a, b])
    raw = path.read_bytes()
    magic, version, length = struct.unpack("<4sII", raw[:12])
    assert magic == b"glTF" and version == 2 and length == len(raw) and length % 4 == 0
    for got, mesh in zip(read_glb_positions(path), (a, b), strict=True):
        assert np.allclose(got, mesh.vertices)
    for got, mesh in zip(read_glb_indices(path), (a, b), strict=True):
        assert np.array_equal(np.asarray(got).reshape(-1, 3), mesh.faces)
    scene = trimesh.load(path)  # an independent reader
    assert sum(len(g.faces) for g in scene.geometry.values()) == 4


def test_mesh_spec_errors():
    with pytest.raises(ValueError, match=r"vertices: expected shape \(V, 3\)"):
        MeshSpec(np.zeros((4, 2)), np.array([[0, 1, 2]]))
    with pytest.raises(ValueError, match="faces"):
        MeshSpec(np.zeros((4, 3)), np.array([[0, 1, 9]]))


def test_zbuffer_nearer_wins_regardless_of_order():
    camera = Camera(eye=(0.0, 0.0, 5.0), target=(0.0, 0.0, 0.0), fov_y=30.0)
    near, far = _quad(0.5, (0.0, 0.0, 1.0), 0.6), _quad(0.0, (1.0, 0.0, 0.0), 1.0)
    for order in ([near, far], [far, near]):
        img = render_image(order, width=64, height=64, camera=camera, ground_y=None, supersample=1)
        centre, rim = img[32, 32].astype(int), img[32, 22].astype(int)
        assert centre[2] > centre[0] and rim[0] > rim[2]  # blue in front, red around it


def test_render_needs_meshes():
    with pytest.raises(ValueError):
        render_image([], width=32, height=32)
