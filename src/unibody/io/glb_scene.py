"""A binary glTF's scene as triangle meshes in world coordinates, posed as the file stands.

What a glTF viewer shows before any animation plays: every mesh of the default scene placed by
its nodes' own transforms (TRS or matrix), and a skinned mesh deformed by its skin at those
transforms (glTF 2.0 §3.7.3: joint matrix = the joint's world transform @ its inverse bind
matrix; the skinned mesh node's own transform is ignored). Triangle primitives only (mode 4);
morph targets are not applied. Written by hand: trimesh reads the meshes but not skins, and
pygltflib parses without posing.

Only the GLB-embedded buffer is read; a file that needs anything else (external or data-URI
buffers, sparse accessors, a required extension such as Draco) is refused in one line.
"""

from __future__ import annotations

import numpy as np

from .glb import _accessor, _parse_glb

__all__ = ["read_glb_scene"]

_NORMALIZED = {5121: 255.0, 5123: 65535.0}  # unsigned byte / short weights (glTF 2.0 §3.6.2.5)


def _local(node: dict) -> np.ndarray:
    """A node's own 4x4 transform (column vectors)."""
    m = np.eye(4)
    if "matrix" in node:
        return np.asarray(node["matrix"], np.float64).reshape(4, 4).T  # column-major in the file
    if "rotation" in node:
        x, y, z, w = np.asarray(node["rotation"], np.float64) / np.linalg.norm(node["rotation"])
        m[:3, :3] = [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    if "scale" in node:
        m[:3, :3] = m[:3, :3] * np.asarray(node["scale"], np.float64)
    if "translation" in node:
        m[:3, 3] = node["translation"]
    return m


def _world(gltf: dict) -> dict[int, np.ndarray]:
    """World transforms of the default scene's nodes (each must be reached once)."""
    nodes = gltf.get("nodes", [])
    scenes = gltf.get("scenes", [])
    roots = scenes[gltf.get("scene", 0)]["nodes"] if scenes else range(len(nodes))
    world: dict[int, np.ndarray] = {}
    stack = [(int(k), np.eye(4)) for k in roots]
    while stack:
        k, parent = stack.pop()
        if k in world:
            raise ValueError(f"node {k} is reached twice: the node graph must be a forest")
        world[k] = parent @ _local(nodes[k])
        stack += [(int(c), world[k]) for c in nodes[k].get("children", [])]
    return world


def _skinned(gltf: dict, binary: bytes, prim: dict, skin: dict, world: dict, pos: np.ndarray) -> np.ndarray:
    """``pos`` (V, 3) deformed by ``skin`` at the nodes' own transforms."""
    joints = [int(j) for j in skin["joints"]]
    missing = [j for j in joints if j not in world]
    if missing:
        raise ValueError(f"skin joint node {missing[0]} is not in the scene")
    if "inverseBindMatrices" in skin:
        ibm = _accessor(gltf, binary, skin["inverseBindMatrices"]).astype(np.float64).reshape(-1, 4, 4)
        ibm = ibm.transpose(0, 2, 1)  # column-major
    else:
        ibm = np.broadcast_to(np.eye(4), (len(joints), 4, 4))
    mats = np.stack([world[j] for j in joints]) @ ibm  # (J, 4, 4)
    rest = np.concatenate([pos, np.ones((len(pos), 1))], axis=1)
    out = np.zeros_like(pos)
    attrs, n = prim["attributes"], 0
    while f"JOINTS_{n}" in attrs and f"WEIGHTS_{n}" in attrs:
        index = _accessor(gltf, binary, attrs[f"JOINTS_{n}"]).astype(np.int64).reshape(len(pos), 4)
        acc = gltf["accessors"][attrs[f"WEIGHTS_{n}"]]
        weight = _accessor(gltf, binary, attrs[f"WEIGHTS_{n}"]).astype(np.float64).reshape(len(pos), 4)
        weight = weight / _NORMALIZED.get(acc["componentType"], 1.0)
        if index.min() < 0 or index.max() >= len(joints):
            raise ValueError(f"JOINTS_{n}: expected joint indices below {len(joints)}, got up to {index.max()}")
        for c in range(4):
            out += weight[:, c, None] * np.einsum("vij,vj->vi", mats[index[:, c], :3], rest)
        n += 1
    if n == 0:
        raise ValueError("a skinned mesh has no JOINTS_0 / WEIGHTS_0")
    return out


def read_glb_scene(data: bytes) -> list[tuple[np.ndarray, np.ndarray]]:
    """The triangle meshes of a GLB file's default scene: ``[(vertices (V, 3) float64, faces (F, 3) int64)]``.

    Vertices are in world coordinates, posed by the nodes' own transforms (and skins); one
    entry per triangle primitive with at least one face. They are not checked: a file holding
    NaN or huge numbers gives non-finite vertices.

    Raises:
        ValueError: not a GLB, a broken or truncated one, or one this reader does not take
            (see the module notes); the message says which part.
    """
    gltf, binary = _parse_glb(data)
    try:
        with np.errstate(all="ignore"):  # NaN in the file gives NaN vertices: the caller checks
            return _meshes(gltf, binary)
    except (KeyError, IndexError, TypeError, AttributeError, OverflowError, np.linalg.LinAlgError) as exc:
        raise ValueError(f"malformed glTF ({type(exc).__name__}: {exc})") from None


def _meshes(gltf: dict, binary: bytes) -> list[tuple[np.ndarray, np.ndarray]]:
    required = gltf.get("extensionsRequired", [])
    if required:
        raise ValueError(f"the file requires extension(s) {', '.join(map(str, required))}")
    for b in gltf.get("buffers", []):
        if "uri" in b:
            raise ValueError("only the GLB-embedded buffer is read (the file names a buffer by uri)")
    if any("sparse" in a for a in gltf.get("accessors", [])):
        raise ValueError("sparse accessors are not read")
    world = _world(gltf)
    out = []
    for k, m in world.items():
        node = gltf["nodes"][k]
        if "mesh" not in node:
            continue
        skin = gltf["skins"][node["skin"]] if "skin" in node else None
        for prim in gltf["meshes"][node["mesh"]]["primitives"]:
            if prim.get("mode", 4) != 4:
                continue
            pos = _accessor(gltf, binary, prim["attributes"]["POSITION"]).astype(np.float64).reshape(-1, 3)
            if "indices" in prim:
                faces = _accessor(gltf, binary, prim["indices"]).astype(np.int64).reshape(-1, 3)
            else:
                faces = np.arange(len(pos) - len(pos) % 3, dtype=np.int64).reshape(-1, 3)
            if not len(faces):
                continue
            if faces.min() < 0 or faces.max() >= len(pos):
                raise ValueError(f"indices: expected vertex indices below {len(pos)}, got up to {faces.max()}")
            if skin is not None:
                verts = _skinned(gltf, binary, prim, skin, world, pos)
            else:
                verts = pos @ m[:3, :3].T + m[:3, 3]
            out.append((verts, faces))
    return out
