"""Binary glTF export: structure per the glTF 2.0 spec, round trips, input validation."""

from __future__ import annotations

import json
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest

from conftest import icosahedron
from unibody.io.glb import (
    MeshSpec,
    SkinnedAnimation,
    read_glb_indices,
    read_glb_positions,
    vertex_normals,
    write_glb,
    write_skinned_glb,
)


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


# ----------------------------------------------------------------------------- skinned animation

PARENTS = np.array([-1, 0, 1, 1, 3, 0])  # a branching 6-joint tree
NODE = shutil.which("node")
VALIDATOR = Path(__file__).parent / "node" / "node_modules" / "gltf-validator"


def _rotation_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def skinned(frames: int = 5, k: int = 5, **changes) -> SkinnedAnimation:
    """A cube skinned to 6 joints with k distinct influences per vertex (some of weight 0)."""
    rng = np.random.default_rng(7)
    v, f = cube(1.0, (0.0, 1.0, 0.0))
    bind = np.tile(np.eye(4), (6, 1, 1))
    for j in range(6):
        bind[j, :3, :3] = _rotation_z(0.3 * j)
        bind[j, :3, 3] = (0.1 * j, 0.4 * j, -0.05 * j)
    idx = np.stack([rng.permutation(6)[:k] for _ in range(len(v))])
    w = rng.dirichlet(np.ones(k), size=len(v))
    w[0, -1] = 0.0  # an unused slot
    w /= w.sum(axis=1, keepdims=True)
    q = rng.normal(size=(frames, 6, 4))
    args = {
        "vertices": v,
        "faces": f,
        "joint_names": tuple(f"j{i}" for i in range(6)),
        "parents": PARENTS,
        "bind_matrices": bind,
        "joint_indices": idx,
        "joint_weights": w,
        "rotations": q,
        "translations": rng.normal(size=(frames, 6, 3)),
        "fps": 25.0,
    }
    return SkinnedAnimation(**(args | changes))


def test_skinned_structure(tmp_path):
    anim = skinned()
    path = tmp_path / "a.glb"
    write_skinned_glb(path, anim)
    data = path.read_bytes()
    (_, js), (_, blob) = _chunks(data)
    gltf = json.loads(js)
    j = len(PARENTS)
    # Hierarchy: children lists are the parents array inverted; the scene holds the root and the mesh.
    for k, node in enumerate(gltf["nodes"][:j]):
        assert sorted(node.get("children", [])) == np.flatnonzero(PARENTS == k).tolist()
    mesh_node = gltf["nodes"][j]
    assert mesh_node == {"name": "body", "mesh": 0, "skin": 0}  # no transform of its own
    assert gltf["scenes"][0]["nodes"] == [0, j]
    skin = gltf["skins"][0]
    assert skin["joints"] == list(range(j)) and skin["skeleton"] == 0

    def acc(i):
        a = gltf["accessors"][i]
        view = gltf["bufferViews"][a["bufferView"]]
        dt = {5121: np.uint8, 5126: np.float32}[a["componentType"]]
        width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[a["type"]]
        out = np.frombuffer(blob, dt, a["count"] * width, view["byteOffset"])
        return a, view, out.reshape(a["count"], width)

    a, view, ibm = acc(skin["inverseBindMatrices"])
    assert "target" not in view
    np.testing.assert_allclose(
        ibm.reshape(j, 4, 4).transpose(0, 2, 1) @ anim.bind_matrices, np.tile(np.eye(4), (j, 1, 1)), atol=1e-6
    )
    attrs = gltf["meshes"][0]["primitives"][0]["attributes"]
    assert sorted(attrs) == ["JOINTS_0", "JOINTS_1", "NORMAL", "POSITION", "WEIGHTS_0", "WEIGHTS_1"]
    joints = np.concatenate([acc(attrs[f"JOINTS_{n}"])[2] for n in (0, 1)], axis=1)
    weights = np.concatenate([acc(attrs[f"WEIGHTS_{n}"])[2] for n in (0, 1)], axis=1)
    assert acc(attrs["JOINTS_0"])[0]["componentType"] == 5121
    assert np.all(np.abs(weights.sum(axis=1, dtype=np.float32) - 1) <= 1.2e-7)
    assert np.all(weights[:, 5:] == 0) and np.all(joints[:, 5:] == 0)  # padding: joint 0, weight 0
    assert weights[0, 4] == 0 and joints[0, 4] == 0  # an unused input slot too
    # The same (joint -> weight) blend as the input, per vertex.
    dense = np.zeros((8, j))
    np.add.at(dense, (np.repeat(np.arange(8), 8), joints.ravel()), weights.ravel())
    ref = np.zeros((8, j))
    np.add.at(ref, (np.repeat(np.arange(8), 5), anim.joint_indices.ravel()), anim.joint_weights.ravel())
    np.testing.assert_allclose(dense, ref, atol=1e-7)
    for name in ("POSITION", "NORMAL", "JOINTS_0", "WEIGHTS_1"):
        assert acc(attrs[name])[1]["target"] == 34962
    anim_json = gltf["animations"][0]
    assert len(anim_json["channels"]) == 2 * j
    a, view, times = acc(anim_json["samplers"][0]["input"])
    assert "target" not in view
    np.testing.assert_allclose(times[:, 0], np.arange(5) / 25.0, rtol=1e-7)
    assert (a["min"], a["max"]) == ([0.0], [float(np.float32(4) / np.float32(25))])
    for view in gltf["bufferViews"]:
        assert view["byteOffset"] % 4 == 0


def test_quaternions_keep_their_sign_between_frames(tmp_path):
    q = np.tile(np.array([0.1, 0.2, 0.3, 0.9]), (6, 6, 1)) * 2.0  # not unit
    q[1::2] *= -1  # the same rotation, flipped sign every other frame
    q[:, 2] = [0.0, 0.0, 0.0, 1.0]
    q[3:, 2] = [0.0, 0.0, 0.0, -1.0]
    path = tmp_path / "q.glb"
    write_skinned_glb(path, skinned(frames=6, rotations=q))
    (_, js), (_, blob) = _chunks(path.read_bytes())
    gltf = json.loads(js)
    for ch in gltf["animations"][0]["channels"]:
        if ch["target"]["path"] != "rotation":
            continue
        a = gltf["accessors"][gltf["animations"][0]["samplers"][ch["sampler"]]["output"]]
        off = gltf["bufferViews"][a["bufferView"]]["byteOffset"]
        written = np.frombuffer(blob, np.float32, 24, off).reshape(6, 4).astype(np.float64)
        np.testing.assert_allclose(np.linalg.norm(written, axis=1), 1.0, atol=1e-7)
        assert np.all(np.einsum("tc,tc->t", written[1:], written[:-1]) > 0)
        src = q[:, ch["target"]["node"]] / np.linalg.norm(q[:, ch["target"]["node"]], axis=1, keepdims=True)
        np.testing.assert_allclose(np.abs(np.einsum("tc,tc->t", written, src)), 1.0, atol=1e-6)


def test_skinned_passes_the_khronos_validator(tmp_path):
    if NODE is None or not VALIDATOR.is_dir():
        pytest.skip("node or the npm gltf-validator is missing (npm install --prefix tests/node gltf-validator)")
    path = tmp_path / "a.glb"
    write_skinned_glb(path, skinned(frames=1))  # one frame: a single keyframe is valid too
    script = Path(__file__).parent / "gltf_validate.js"
    run = subprocess.run([NODE, str(script), str(path)], capture_output=True, text=True, timeout=120)
    report = json.loads(run.stdout)
    assert (report["numErrors"], report["numWarnings"]) == (0, 0), report["messages"]


@pytest.mark.parametrize(
    "changes, name",
    [
        ({"joint_names": ("a", "a", "b", "c", "d", "e")}, "joint_names"),
        ({"parents": np.array([-1, 0, 3, 1, 3, 0])}, "parents"),
        ({"parents": np.array([-1, 0, 1])}, "parents"),
        ({"faces": np.array([[0, 1, 8]])}, "faces"),
        ({"vertices": np.zeros((0, 3))}, "vertices"),
        ({"bind_matrices": np.zeros((6, 4, 4))}, "bind_matrices"),
        ({"joint_indices": np.full((8, 5), 6)}, "joint_indices"),
        ({"joint_weights": np.full((8, 5), 0.5)}, "joint_weights"),
        ({"rotations": np.zeros((5, 6, 4))}, "rotations"),
        ({"rotations": np.zeros((5, 6, 3))}, "rotations"),
        ({"translations": np.zeros((4, 6, 3))}, "translations"),
        ({"translations": np.full((5, 6, 3), np.nan)}, "translations"),
        ({"fps": 0.0}, "fps"),
        ({"fps": True}, "fps"),
    ],
)
def test_bad_skinned_inputs(changes, name):
    with pytest.raises(ValueError, match=rf"^{name}:") as info:
        skinned(**changes)
    assert "\n" not in str(info.value)


def test_bad_skinned_write(tmp_path):
    with pytest.raises(ValueError, match="^animation: expected a SkinnedAnimation, got tuple$"):
        write_skinned_glb(tmp_path / "a.glb", (np.zeros((3, 3)),))
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- reading a scene (the viewer's recorder)


def _glb(gltf: dict, blob: bytes) -> bytes:
    """A GLB container of ``gltf`` and ``blob`` (glTF 2.0 §4.4), written here, not by unibody."""
    js = json.dumps(gltf).encode()
    js += b" " * (-len(js) % 4)
    blob += b"\0" * (-len(blob) % 4)
    body = struct.pack("<II", len(js), 0x4E4F534A) + js + struct.pack("<II", len(blob), 0x004E4942) + blob
    return struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body


def _edited(data: bytes, edit) -> bytes:
    (_, js), (_, blob) = _chunks(data)
    gltf = json.loads(js)
    edit(gltf)
    return _glb(gltf, blob)


def _quat_matrix(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def test_scene_reader_poses_the_skin_as_the_nodes_stand(tmp_path):
    from unibody.io.glb_scene import read_glb_scene

    anim = skinned()
    write_skinned_glb(tmp_path / "a.glb", anim)
    ((verts, faces),) = read_glb_scene((tmp_path / "a.glb").read_bytes())
    np.testing.assert_array_equal(faces, anim.faces)
    # Linear blend skinning at frame 0 (the nodes' own transforms), from the animation's arrays.
    world = []
    for j, p in enumerate(PARENTS):
        local = np.eye(4)
        local[:3, :3], local[:3, 3] = _quat_matrix(anim.rotations[0, j]), anim.translations[0, j]
        world.append(local if p < 0 else world[p] @ local)
    mats = np.stack(world) @ np.linalg.inv(anim.bind_matrices)
    rest = np.concatenate([anim.vertices, np.ones((8, 1))], axis=1)
    expected = np.einsum("vk,vkij,vj->vi", anim.joint_weights, mats[anim.joint_indices, :3], rest)
    np.testing.assert_allclose(verts, expected, atol=1e-5)
    assert np.abs(verts - anim.vertices).max() > 0.1  # the check can fail: the skin moved the cube


def test_scene_reader_places_meshes_as_trimesh_does(tmp_path, scene):
    from unibody.io.glb_scene import read_glb_scene

    trimesh = pytest.importorskip("trimesh")
    write_glb(tmp_path / "s.glb", scene)

    def transforms(gltf):  # node 0 under node 1; TRS on one, a matrix on the other
        gltf["nodes"][0] |= {"translation": [0.5, -1.0, 2.0], "rotation": [0.0, 0.6, 0.0, 0.8], "scale": [1, 2, 1]}
        gltf["nodes"][1]["matrix"] = [0, 0, -1, 0, 0, 1, 0, 0, 1, 0, 0, 0, 3, 0, 0, 1]  # column-major
        gltf["nodes"][1]["children"] = [0]
        gltf["scenes"][0]["nodes"] = [1]

    data = _edited((tmp_path / "s.glb").read_bytes(), transforms)
    ours = read_glb_scene(data)
    (tmp_path / "t.glb").write_bytes(data)
    theirs = trimesh.load(tmp_path / "t.glb", process=False, force="scene").dump()
    assert len(ours) == len(theirs) == 2
    theirs = sorted(theirs, key=lambda g: len(g.vertices))
    for (v, f), g in zip(sorted(ours, key=lambda p: len(p[0])), theirs, strict=True):
        np.testing.assert_allclose(v, g.vertices, atol=1e-5)
        np.testing.assert_array_equal(f, g.faces)
    cube_verts = next(v for v, _ in ours if len(v) == len(scene[0].vertices))
    assert np.abs(cube_verts - scene[0].vertices).max() > 1.0  # the check can fail: the nodes moved it


def _cycle(g):
    g["nodes"][0]["children"] = [1]
    g["nodes"][1]["children"] = [0]


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda g: g.update(extensionsRequired=["KHR_draco_mesh_compression"]), "requires extension"),
        (lambda g: g["buffers"][0].update(uri="data.bin"), "only the GLB-embedded buffer"),
        (_cycle, "reached twice"),
        (lambda g: g["meshes"][0]["primitives"][0]["attributes"].pop("POSITION"), r"malformed glTF \(KeyError"),
        (lambda g: g["nodes"][1].update(mesh=7), r"malformed glTF \(IndexError"),
        (lambda g: g["accessors"][0].update(count=10**9), "buffer is smaller"),
        (lambda g: g["nodes"][0].update(rotation="up"), "could not convert string to float: 'up'"),
    ],
)
def test_scene_reader_refuses_what_it_cannot_read(tmp_path, scene, edit, message):
    from unibody.io.glb_scene import read_glb_scene

    write_glb(tmp_path / "s.glb", scene)
    with pytest.raises(ValueError, match=message):
        read_glb_scene(_edited((tmp_path / "s.glb").read_bytes(), edit))


def test_scene_reader_refuses_broken_containers(tmp_path, scene):
    from unibody.io.glb_scene import read_glb_scene

    write_glb(tmp_path / "s.glb", scene)
    data = (tmp_path / "s.glb").read_bytes()
    for bad, message in [
        (b"glTF", "only 4 bytes"),
        (b"PK\3\4" + data[4:], "magic"),
        (data[: len(data) // 2], "truncated GLB file"),
        (_glb({"asset": 1}, b"")[:20] + b"{not json" + b" " * 100, "truncated|not JSON"),
    ]:
        with pytest.raises(ValueError, match=message):
            read_glb_scene(bad)
