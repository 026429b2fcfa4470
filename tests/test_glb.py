"""Binary glTF export: structure per the glTF 2.0 spec, round trips, input validation."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from conftest import icosahedron
from unibody.io.glb import MeshSpec, read_glb_indices, read_glb_positions, vertex_normals, write_glb


def cube(size: float = 1.0, centre=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned cube, 8 vertices, 12 outward counter-clockwise triangles."""
    v = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)]) * size
    v += np.asarray(centre)
    f = np.array(
        [
            [0, 1, 3], [0, 3, 2],  # -x
            [4, 6, 7], [4, 7, 5],  # +x
            [0, 4, 5], [0, 5, 1],  # -y
            [2, 3, 7], [2, 7, 6],  # +y
            [0, 2, 6], [0, 6, 4],  # -z
            [1, 5, 7], [1, 7, 3],  # +z
        ]
    )  # fmt: skip
    return v, f


@pytest.fixture
def scene() -> list[MeshSpec]:
    cv, cf = cube(0.5, (1.0, 2.0, -3.0))
    iv, if_ = icosahedron()
    rng = np.random.default_rng(0)
    return [
        MeshSpec(cv, cf, (1.0, 0.0, 0.0), "cube"),
        MeshSpec(iv * 0.3 + rng.normal(size=3), if_, (0.2, 0.4, 0.6), "ico"),
    ]


def _chunks(data: bytes) -> list[tuple[int, bytes]]:
    out, pos = [], 12
    while pos < len(data):
        n, kind = struct.unpack_from("<II", data, pos)
        out.append((kind, data[pos + 8 : pos + 8 + n]))
        pos += 8 + n
    assert pos == len(data)
    return out


def test_header_chunks_and_alignment(tmp_path, scene):
    path = tmp_path / "s.glb"
    write_glb(path, scene)
    data = path.read_bytes()
    magic, version, length = struct.unpack_from("<III", data, 0)
    assert data[:4] == b"glTF" and magic == 0x46546C67
    assert version == 2
    assert length == len(data)
    chunks = _chunks(data)
    assert [k for k, _ in chunks] == [0x4E4F534A, 0x004E4942]  # JSON then BIN
    for _, body in chunks:
        assert len(body) % 4 == 0
    js = chunks[0][1]
    assert js.rstrip(b" ") == js.rstrip()  # padded with spaces only
    gltf = json.loads(js)
    assert gltf["asset"]["version"] == "2.0"
    assert gltf["buffers"][0]["byteLength"] == len(chunks[1][1])
    for view in gltf["bufferViews"]:
        assert view["byteOffset"] % 4 == 0
        assert view["byteOffset"] + view["byteLength"] <= len(chunks[1][1])
    assert len(gltf["nodes"]) == len(gltf["meshes"]) == len(gltf["materials"]) == 2
    assert gltf["scenes"][gltf["scene"]]["nodes"] == [0, 1]


def test_accessors_materials_and_normals(tmp_path, scene):
    path = tmp_path / "s.glb"
    write_glb(path, scene)
    gltf = json.loads(_chunks(path.read_bytes())[0][1])
    for spec, mesh, mat in zip(scene, gltf["meshes"], gltf["materials"], strict=True):
        prim = mesh["primitives"][0]
        pos = gltf["accessors"][prim["attributes"]["POSITION"]]
        nrm = gltf["accessors"][prim["attributes"]["NORMAL"]]
        idx = gltf["accessors"][prim["indices"]]
        assert (pos["componentType"], pos["type"], pos["count"]) == (5126, "VEC3", len(spec.vertices))
        assert (nrm["componentType"], nrm["type"], nrm["count"]) == (5126, "VEC3", len(spec.vertices))
        assert (idx["componentType"], idx["type"], idx["count"]) == (5125, "SCALAR", 3 * len(spec.faces))
        v32 = spec.vertices.astype(np.float32)
        np.testing.assert_array_equal(np.float32(pos["min"]), v32.min(0))
        np.testing.assert_array_equal(np.float32(pos["max"]), v32.max(0))
        assert prim.get("mode", 4) == 4
        pbr = mat["pbrMetallicRoughness"]
        assert pbr["baseColorFactor"] == pytest.approx([*spec.color, 1.0])
        assert pbr["metallicFactor"] == 0.0 and pbr["roughnessFactor"] == pytest.approx(0.8)
        assert mat["doubleSided"] is False


def test_vertex_normals_area_weighted():
    # Icosahedron: by symmetry every vertex normal is radial.
    v, f = icosahedron()
    np.testing.assert_allclose(vertex_normals(v, f), v, atol=1e-12)
    # Corner of two unequal faces: the bigger face dominates in proportion to its area.
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 3]], dtype=float)
    f = np.array([[0, 1, 2], [0, 3, 1]])  # areas 0.5 (normal +z) and 1.5 (normal +y)
    n = vertex_normals(v, f)[0]
    expected = np.array([0, 1.5, 0.5]) / np.linalg.norm([0, 1.5, 0.5])
    np.testing.assert_allclose(n, expected, atol=1e-12)


def test_vertex_normals_match_the_torch_ones():
    # The leaf writer's numpy twin agrees with unibody.geometry.mesh on a lumpy closed mesh.
    import torch

    from unibody.geometry.mesh import vertex_normals as torch_normals

    v, f = icosahedron()
    v = v * np.random.default_rng(0).uniform(0.5, 1.5, size=(len(v), 1))
    ref = torch_normals(torch.from_numpy(v), torch.from_numpy(f)).numpy()
    np.testing.assert_allclose(vertex_normals(v, f), ref, atol=1e-14)


def test_round_trip_own_reader(tmp_path, scene):
    path = tmp_path / "s.glb"
    write_glb(path, scene)
    positions = read_glb_positions(path)
    indices = read_glb_indices(path)
    assert len(positions) == len(indices) == len(scene)
    for spec, pos, idx in zip(scene, positions, indices, strict=True):
        assert pos.dtype == np.float32
        np.testing.assert_array_equal(pos, spec.vertices.astype(np.float32))
        np.testing.assert_array_equal(idx, spec.faces)


def test_round_trip_trimesh_oracle(tmp_path, scene):
    trimesh = pytest.importorskip("trimesh")
    path = tmp_path / "s.glb"
    write_glb(path, scene)
    loaded = trimesh.load(path, process=False)
    geoms = loaded.geometry if hasattr(loaded, "geometry") else {"only": loaded}
    assert len(geoms) == len(scene)
    by_count = sorted((len(g.vertices), len(g.faces)) for g in geoms.values())
    assert by_count == sorted((len(s.vertices), len(s.faces)) for s in scene)
    for spec in scene:
        g = geoms[spec.name]
        np.testing.assert_allclose(g.vertices, spec.vertices, atol=1e-6)
        np.testing.assert_array_equal(g.faces, spec.faces)
    all_v = np.concatenate([s.vertices for s in scene])
    np.testing.assert_allclose(loaded.bounds, [all_v.min(0), all_v.max(0)], atol=1e-6)


def test_accepts_torch_and_lists(tmp_path):
    torch = pytest.importorskip("torch")
    v, f = cube()
    spec = MeshSpec(torch.tensor(v, requires_grad=True), f.tolist(), (0.5, 0.5, 0.5), "t")
    assert spec.vertices.dtype == np.float64 and spec.faces.dtype == np.int64
    write_glb(tmp_path / "t.glb", [spec])
    np.testing.assert_allclose(read_glb_positions(tmp_path / "t.glb")[0], v)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"faces": np.array([[0, 1, 8]])}, "faces"),
        ({"faces": np.array([[0, -1, 2]])}, "faces"),
        ({"faces": np.array([0, 1, 2])}, "faces"),
        ({"faces": np.array([[0.0, 1.0, 2.0]])}, "faces"),
        ({"vertices": np.zeros((8, 2))}, "vertices"),
        ({"vertices": np.full((8, 3), np.nan)}, "vertices"),
        ({"color": (1.2, 0.0, 0.0)}, "color"),
        ({"color": (1.0, 0.0)}, "color"),
    ],
)
def test_bad_mesh_inputs(kwargs, name):
    v, f = cube()
    args = {"vertices": v, "faces": f, "color": (0.5, 0.5, 0.5), "name": "c"} | kwargs
    with pytest.raises(ValueError, match=rf"^{name}:"):
        MeshSpec(**args)


def test_bad_write_inputs(tmp_path):
    v, f = cube()
    with pytest.raises(ValueError, match="^meshes:"):
        write_glb(tmp_path / "x.glb", [])
    with pytest.raises(ValueError, match=r"^meshes\[1\]:"):
        write_glb(tmp_path / "x.glb", [MeshSpec(v, f), (v, f)])
    with pytest.raises(ValueError, match=r"^meshes\[0\]:"):
        write_glb(tmp_path / "x.glb", [MeshSpec(v, np.zeros((0, 3), dtype=int))])
    assert not (tmp_path / "x.glb").exists()
