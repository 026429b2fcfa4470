"""Binary glTF 2.0 (``.glb``) export of triangle meshes and skinned animations, in pure numpy.

:func:`write_glb`: one scene, one node and one mesh per :class:`MeshSpec`, each with a
single triangle primitive carrying ``POSITION`` and ``NORMAL`` (float32) and uint32
indices, plus one PBR material built from the spec's colour.

:func:`write_skinned_glb`: one skinned mesh and one animation (:class:`SkinnedAnimation`):
a node per joint in the joint hierarchy, a skin with inverse bind matrices, ``JOINTS_n`` /
``WEIGHTS_n`` sets of four influences each (as many sets as the animation has influences
per vertex, padded with zero weights) and, per joint, a LINEAR rotation and a translation
channel keyed at ``i / fps`` seconds. glTF's conventions hold throughout: metres, column
vectors, quaternions ``(x, y, z, w)``, joint matrix = world transform @ inverse bind matrix.

The layout follows the glTF 2.0 specification: a 12-byte header, a JSON chunk
padded with spaces and a BIN chunk padded with zeros, both to a multiple of 4
bytes; every bufferView starts at a 4-byte aligned offset.
"""

from __future__ import annotations

import json
import os
import struct
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .atomic import atomic_write

__all__ = [
    "MeshSpec",
    "SkinnedAnimation",
    "mesh_list",
    "vertex_normals",
    "write_glb",
    "write_skinned_glb",
    "read_glb_positions",
    "read_glb_indices",
]

_GLB_MAGIC = 0x46546C67  # b"glTF"
_GLB_VERSION = 2
_CHUNK_JSON = 0x4E4F534A  # b"JSON"
_CHUNK_BIN = 0x004E4942  # b"BIN\0"

_FLOAT = 5126
_UNSIGNED_BYTE = 5121
_UNSIGNED_SHORT = 5123
_UNSIGNED_INT = 5125
_ARRAY_BUFFER = 34962
_ELEMENT_ARRAY_BUFFER = 34963
_TRIANGLES = 4

_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
_DTYPES = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}


def _as_numpy(x: object) -> np.ndarray:
    """Accept numpy arrays, sequences and (CPU or not) torch tensors."""
    if hasattr(x, "detach") and hasattr(x, "cpu"):
        x = x.detach().cpu().numpy()  # type: ignore[union-attr]
    return np.asarray(x)


@dataclass(frozen=True, slots=True)
class MeshSpec:
    """A triangle mesh to export or render.

    ``vertices`` is ``(V, 3)`` float, ``faces`` is ``(F, 3)`` integer indices into
    ``vertices``, ``color`` is an ``(r, g, b)`` triple in ``[0, 1]``.  Inputs are
    validated and stored as read-only ``float64`` / ``int64`` numpy arrays.
    """

    vertices: np.ndarray
    faces: np.ndarray
    color: tuple[float, float, float] = (0.75, 0.75, 0.75)
    name: str = "mesh"

    def __post_init__(self) -> None:
        v = _as_numpy(self.vertices)
        if v.ndim != 2 or v.shape[1] != 3:
            raise ValueError(f"vertices: expected shape (V, 3), got {v.shape}")
        if not (np.issubdtype(v.dtype, np.floating) or np.issubdtype(v.dtype, np.integer)):
            raise ValueError(f"vertices: expected a real-valued array, got dtype {v.dtype}")
        v = np.array(v, dtype=np.float64)
        if not np.isfinite(v).all():
            bad = int((~np.isfinite(v)).any(axis=1).sum())
            raise ValueError(f"vertices: expected finite values, got {bad} vertices with NaN/inf")

        f = _as_numpy(self.faces)
        if f.ndim != 2 or f.shape[1] != 3:
            raise ValueError(f"faces: expected shape (F, 3), got {f.shape}")
        if f.size and not np.issubdtype(f.dtype, np.integer):
            raise ValueError(f"faces: expected an integer array, got dtype {f.dtype}")
        f = np.array(f, dtype=np.int64)
        if f.size:
            lo, hi = int(f.min()), int(f.max())
            if lo < 0 or hi >= len(v):
                raise ValueError(
                    f"faces: indices must lie in [0, {len(v) - 1}] for {len(v)} vertices, got range [{lo}, {hi}]"
                )

        c = np.asarray(self.color, dtype=np.float64)
        if c.shape != (3,):
            raise ValueError(f"color: expected an (r, g, b) triple, got shape {c.shape}")
        if not np.isfinite(c).all() or c.min() < 0.0 or c.max() > 1.0:
            raise ValueError(f"color: expected values in [0, 1], got {tuple(float(x) for x in c)}")
        if not isinstance(self.name, str):
            raise ValueError(f"name: expected a str, got {type(self.name).__name__}")

        v.flags.writeable = False
        f.flags.writeable = False
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "faces", f)
        object.__setattr__(self, "color", (float(c[0]), float(c[1]), float(c[2])))


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals, ``(V, 3)`` float64.

    A numpy twin of :func:`unibody.geometry.mesh.vertex_normals` kept here because ``io`` is
    a leaf that imports nothing from ``unibody``, and glTF wants unit normals everywhere
    (hence ``(0, 0, 1)`` instead of zero below).

    Each face contributes its unnormalised normal (twice its area times the unit
    normal, counter-clockwise winding) to its three vertices.  Vertices touched by
    no face, or whose contributions cancel, get ``(0, 0, 1)``.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    n = np.zeros_like(v)
    if len(f):
        p0, p1, p2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        fn = np.cross(p1 - p0, p2 - p0)
        idx = f.ravel()
        for k in range(3):
            n[:, k] = np.bincount(idx, weights=np.repeat(fn[:, k], 3), minlength=len(v))
    length = np.linalg.norm(n, axis=1)
    ok = length > 1e-300
    n[ok] /= length[ok, None]
    n[~ok] = (0.0, 0.0, 1.0)
    return n


def _pad4(data: bytes, fill: bytes) -> bytes:
    return data + fill * (-len(data) % 4)


class _Builder:
    """Accessors and buffer views over one binary blob; :meth:`write` emits the GLB atomically."""

    def __init__(self) -> None:
        self.blob = bytearray()
        self.buffer_views: list[dict] = []
        self.accessors: list[dict] = []

    def add(self, array: np.ndarray, component: int, kind: str, target: int | None = None, bounds: bool = False) -> int:
        """Append ``array`` as a new 4-byte aligned buffer view and accessor; return the accessor index."""
        data = np.ascontiguousarray(array).astype("<" + np.dtype(_DTYPES[component]).str[1:], copy=False)
        offset = len(self.blob)  # always a multiple of 4: every piece is padded
        raw = data.tobytes()
        self.blob.extend(_pad4(raw, b"\x00"))
        view = {"buffer": 0, "byteOffset": offset, "byteLength": len(raw)}
        if target is not None:
            view["target"] = target
        self.buffer_views.append(view)
        acc: dict = {
            "bufferView": len(self.buffer_views) - 1,
            "componentType": component,
            "count": int(data.shape[0]) if kind != "SCALAR" else int(data.size),
            "type": kind,
        }
        if bounds:
            flat = data.reshape(acc["count"], _COMPONENTS[kind])
            acc["min"] = [float(x) for x in flat.min(axis=0)]
            acc["max"] = [float(x) for x in flat.max(axis=0)]
        self.accessors.append(acc)
        return len(self.accessors) - 1

    def write(self, path: str | os.PathLike[str], gltf: dict) -> None:
        gltf = {
            "asset": {"version": "2.0", "generator": "unibody"},
            **gltf,
            "accessors": self.accessors,
            "bufferViews": self.buffer_views,
            "buffers": [{"byteLength": len(self.blob)}],
        }
        json_chunk = _pad4(json.dumps(gltf, separators=(",", ":")).encode("utf-8"), b" ")
        bin_chunk = bytes(self.blob)  # already padded to 4
        total = 12 + 8 + len(json_chunk) + 8 + len(bin_chunk)
        with atomic_write(path) as fh:
            fh.write(struct.pack("<III", _GLB_MAGIC, _GLB_VERSION, total))
            fh.write(struct.pack("<II", len(json_chunk), _CHUNK_JSON))
            fh.write(json_chunk)
            fh.write(struct.pack("<II", len(bin_chunk), _CHUNK_BIN))
            fh.write(bin_chunk)


def mesh_list(meshes: Sequence[MeshSpec]) -> list[MeshSpec]:
    """``meshes`` as a list, or ValueError if it is empty or holds anything but MeshSpec."""
    meshes = list(meshes)
    if not meshes:
        raise ValueError("meshes: expected at least one MeshSpec, got an empty sequence")
    for i, m in enumerate(meshes):
        if not isinstance(m, MeshSpec):
            raise ValueError(f"meshes[{i}]: expected a MeshSpec, got {type(m).__name__}")
    return meshes


def write_glb(path: str | os.PathLike[str], meshes: Sequence[MeshSpec]) -> None:
    """Write ``meshes`` to ``path`` as a binary glTF 2.0 file.

    Raises ValueError for an empty list, a non-MeshSpec entry or a mesh with no
    vertices or faces (glTF accessors need at least one element).
    """
    meshes = mesh_list(meshes)
    for i, m in enumerate(meshes):
        if len(m.vertices) == 0 or len(m.faces) == 0:
            raise ValueError(
                f"meshes[{i}]: expected at least one vertex and one face, "
                f"got {len(m.vertices)} vertices and {len(m.faces)} faces"
            )
        if len(m.vertices) > np.iinfo(np.uint32).max:
            raise ValueError(f"meshes[{i}]: too many vertices for uint32 indices ({len(m.vertices)})")

    out = _Builder()
    add = out.add

    gl_meshes: list[dict] = []
    materials: list[dict] = []
    nodes: list[dict] = []
    for i, m in enumerate(meshes):
        pos = m.vertices.astype(np.float32)
        nrm = vertex_normals(m.vertices, m.faces).astype(np.float32)
        a_pos = add(pos, _FLOAT, "VEC3", _ARRAY_BUFFER, bounds=True)
        a_nrm = add(nrm, _FLOAT, "VEC3", _ARRAY_BUFFER)
        a_idx = add(m.faces.astype(np.uint32).ravel(), _UNSIGNED_INT, "SCALAR", _ELEMENT_ARRAY_BUFFER)
        materials.append(
            {
                "name": f"{m.name}_material",
                "pbrMetallicRoughness": {
                    "baseColorFactor": [*m.color, 1.0],
                    "metallicFactor": 0.0,
                    "roughnessFactor": 0.8,
                },
                "doubleSided": False,
            }
        )
        gl_meshes.append(
            {
                "name": m.name,
                "primitives": [
                    {
                        "attributes": {"POSITION": a_pos, "NORMAL": a_nrm},
                        "indices": a_idx,
                        "material": i,
                        "mode": _TRIANGLES,
                    }
                ],
            }
        )
        nodes.append({"name": m.name, "mesh": i})

    gltf = {
        "scene": 0,
        "scenes": [{"nodes": list(range(len(nodes)))}],
        "nodes": nodes,
        "meshes": gl_meshes,
        "materials": materials,
    }
    out.write(path, gltf)


# ----------------------------------------------------------------------------- skinned animation


@dataclass(frozen=True, slots=True)
class SkinnedAnimation:
    """A mesh bound to a joint hierarchy, and T frames of the joints' local transforms.

    Conventions: metres, column vectors, joint ``k``'s world transform is
    ``G_k = G_parent(k) @ [R_k | t_k]`` with ``(R_k, t_k)`` its local rotation and translation
    (a root's local transform is its world one). The mesh is stored in the pose of
    ``bind_matrices``: a vertex moves as ``v' = sum_n w_n G_(j_n) bind_(j_n)^-1 v``.

    Attributes:
        vertices: (V, 3) mesh in the bind pose, m.
        faces: (F, 3) triangle indices into ``vertices``.
        joint_names: J joint names (unique).
        parents: (J,) parent index per joint, -1 for a root; parents precede their children.
        bind_matrices: (J, 4, 4) world transforms of the joints in the pose the mesh is stored in.
        joint_indices: (V, K) joint of each influence (any index where the weight is 0).
        joint_weights: (V, K) influence weights, >= 0, each row summing to 1 (within 1e-3;
            the writers renormalise).
        rotations: (T, J, 4) local rotations as quaternions ``(x, y, z, w)`` (normalised on write).
        translations: (T, J, 3) local translations, m, in the parent's frame.
        fps: frames per second (frame i is at i / fps seconds).
        name: the mesh's name.
    """

    vertices: np.ndarray
    faces: np.ndarray
    joint_names: tuple[str, ...]
    parents: np.ndarray
    bind_matrices: np.ndarray
    joint_indices: np.ndarray
    joint_weights: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    fps: float
    name: str = "body"

    def __post_init__(self) -> None:
        names = tuple(self.joint_names)
        j = len(names)
        if j == 0 or len(set(names)) != j or not all(isinstance(n, str) and n for n in names):
            raise ValueError(f"joint_names: expected unique non-empty strings, got {names[:5]}...")
        parents = np.asarray(self.parents)
        if parents.shape != (j,) or parents.dtype.kind not in "iu":
            raise ValueError(f"parents: expected ({j},) integers, got shape {parents.shape} and dtype {parents.dtype}")
        bad = [k for k, p in enumerate(parents.tolist()) if not -1 <= p < k]
        if bad:
            raise ValueError(f"parents: expected -1 or an earlier joint, got {int(parents[bad[0]])} at joint {bad[0]}")
        v = _finite(self.vertices, "vertices", lambda s: len(s) == 2 and s[0] > 0 and s[1] == 3, "(V, 3)")
        f = _as_numpy(self.faces)
        if f.ndim != 2 or f.shape[1] != 3 or not len(f) or f.dtype.kind not in "iu":
            raise ValueError(f"faces: expected (F, 3) integers with F > 0, got shape {f.shape} and dtype {f.dtype}")
        if f.min() < 0 or f.max() >= len(v):
            raise ValueError(f"faces: indices must lie in [0, {len(v) - 1}], got range [{f.min()}, {f.max()}]")
        bind = _finite(self.bind_matrices, "bind_matrices", lambda s: s == (j, 4, 4), f"({j}, 4, 4)")
        if not np.allclose(bind[:, 3], [0, 0, 0, 1]) or not np.all(np.abs(np.linalg.det(bind[:, :3, :3])) > 1e-12):
            raise ValueError("bind_matrices: expected invertible affine transforms (bottom row 0 0 0 1)")
        idx = _as_numpy(self.joint_indices)
        if idx.ndim != 2 or idx.shape[0] != len(v) or idx.dtype.kind not in "iu":
            raise ValueError(
                f"joint_indices: expected ({len(v)}, K) integers, got shape {idx.shape} and dtype {idx.dtype}"
            )
        if idx.min() < 0 or idx.max() >= j:
            raise ValueError(f"joint_indices: indices must lie in [0, {j - 1}], got range [{idx.min()}, {idx.max()}]")
        w = _finite(self.joint_weights, "joint_weights", lambda s: s == idx.shape, f"{idx.shape}")
        total = w.sum(axis=1)
        if w.min() < 0 or not np.all(np.abs(total - 1) <= 1e-3):
            worst = int(np.argmax(np.abs(total - 1) + (w.min(axis=1) < 0)))
            raise ValueError(
                f"joint_weights: expected non-negative rows summing to 1, got row {worst} = {w[worst].tolist()}"
            )
        rot = _finite(
            self.rotations, "rotations", lambda s: len(s) == 3 and s[0] > 0 and s[1:] == (j, 4), f"(T, {j}, 4)"
        )
        t = rot.shape[0]
        if not np.all(np.linalg.norm(rot, axis=-1) > 1e-6):
            raise ValueError("rotations: expected non-zero quaternions (x, y, z, w), got a zero one")
        trans = _finite(self.translations, "translations", lambda s: s == (t, j, 3), f"({t}, {j}, 3)")
        if isinstance(self.fps, bool) or not isinstance(self.fps, int | float | np.number):
            raise ValueError(f"fps: expected a positive number, got {self.fps!r}")
        if not (np.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"fps: expected a positive number, got {self.fps!r}")
        if not isinstance(self.name, str):
            raise ValueError(f"name: expected a str, got {type(self.name).__name__}")
        fields = {"joint_names": names, "parents": parents.astype(np.int64), "vertices": v, "faces": f}
        fields |= {"bind_matrices": bind, "joint_indices": idx, "joint_weights": w, "rotations": rot}
        fields |= {"translations": trans, "fps": float(self.fps)}
        for key, value in fields.items():
            object.__setattr__(self, key, value)

    @property
    def num_frames(self) -> int:
        return self.rotations.shape[0]

    def unit_quaternions(self) -> np.ndarray:
        """(T, J, 4) float64 rotations, normalised, each joint's sign chosen so that
        consecutive frames have a non-negative dot product (LINEAR interpolation then takes the
        short way)."""
        q = self.rotations / np.linalg.norm(self.rotations, axis=-1, keepdims=True)
        dots = np.einsum("tjc,tjc->tj", q[1:], q[:-1])
        flips = np.cumprod(np.where(dots < 0, -1.0, 1.0), axis=0)
        return np.concatenate([q[:1], q[1:] * flips[..., None]])

    def normalized_weights(self) -> np.ndarray:
        """(V, K) float32 weights renormalised so that each row sums to 1 in float32 too.

        The float32 rounding remainder goes to each row's largest weight.
        """
        w = self.joint_weights / self.joint_weights.sum(axis=1, keepdims=True)
        w32 = w.astype(np.float32)
        top = np.argmax(w32, axis=1)
        rows = np.arange(len(w32))
        rest = w32.sum(axis=1, dtype=np.float32) - w32[rows, top]
        w32[rows, top] = np.float32(1) - rest
        return w32


def _finite(x: object, name: str, ok, shape: str) -> np.ndarray:
    """``x`` as float64, or ValueError naming ``name`` unless ``ok(shape)`` and all finite."""
    a = _as_numpy(x)
    if not ok(a.shape) or a.dtype.kind not in "fiu":
        raise ValueError(f"{name}: expected shape {shape} of real numbers, got shape {a.shape} and dtype {a.dtype}")
    a = np.asarray(a, dtype=np.float64)
    if not np.isfinite(a).all():
        raise ValueError(f"{name}: expected finite values, got {int((~np.isfinite(a)).sum())} NaN/inf entries")
    return a


def write_skinned_glb(path: str | os.PathLike[str], animation: SkinnedAnimation) -> None:
    """Write a skinned, animated mesh to ``path`` as a binary glTF 2.0 file (atomically).

    Nodes 0..J-1 are the joints (named, in the hierarchy of ``parents``, at the frame-0
    pose), node J the skinned mesh (at the scene root, no transform of its own, as the
    specification asks). The skin lists the joints in order, so ``JOINTS_n`` values are joint
    indices; its inverse bind matrices are ``bind_matrices^-1``. The K influences per vertex
    are written as ceil(K / 4) ``JOINTS_n`` (unsigned byte, or short past 256 joints) /
    ``WEIGHTS_n`` (float) sets. The one animation has, per joint, a rotation and a translation
    channel sampled LINEARLY at ``i / fps`` seconds (float32).

    Raises:
        ValueError: ``animation`` is not a SkinnedAnimation.
    """
    if not isinstance(animation, SkinnedAnimation):
        raise ValueError(f"animation: expected a SkinnedAnimation, got {type(animation).__name__}")
    a = animation
    j, t = len(a.joint_names), a.num_frames
    out = _Builder()
    quats = a.unit_quaternions().astype(np.float32)
    trans = a.translations.astype(np.float32)

    nodes: list[dict] = []
    for k, name in enumerate(a.joint_names):
        node = {"name": name, "rotation": quats[0, k].tolist(), "translation": trans[0, k].tolist()}
        children = np.flatnonzero(a.parents == k).tolist()
        if children:
            node["children"] = children
        nodes.append(node)
    nodes.append({"name": a.name, "mesh": 0, "skin": 0})
    roots = np.flatnonzero(a.parents < 0).tolist()

    k_sets = -(-a.joint_indices.shape[1] // 4)
    pad = 4 * k_sets - a.joint_indices.shape[1]
    joints = np.pad(a.joint_indices, ((0, 0), (0, pad)))
    weights = np.pad(a.normalized_weights(), ((0, 0), (0, pad)))
    joints = np.where(weights > 0, joints, 0)  # unused slots: joint 0 with weight 0
    joint_type = _UNSIGNED_BYTE if j <= 256 else _UNSIGNED_SHORT
    attributes = {
        "POSITION": out.add(a.vertices.astype(np.float32), _FLOAT, "VEC3", _ARRAY_BUFFER, bounds=True),
        "NORMAL": out.add(vertex_normals(a.vertices, a.faces).astype(np.float32), _FLOAT, "VEC3", _ARRAY_BUFFER),
    }
    for n in range(k_sets):
        cols = slice(4 * n, 4 * n + 4)
        attributes[f"JOINTS_{n}"] = out.add(joints[:, cols], joint_type, "VEC4", _ARRAY_BUFFER)
        attributes[f"WEIGHTS_{n}"] = out.add(weights[:, cols], _FLOAT, "VEC4", _ARRAY_BUFFER)
    indices = out.add(a.faces.astype(np.uint32).ravel(), _UNSIGNED_INT, "SCALAR", _ELEMENT_ARRAY_BUFFER)
    inverse_bind = np.linalg.inv(a.bind_matrices)
    inverse_bind[:, 3] = (0.0, 0.0, 0.0, 1.0)  # exactly affine, as the validator checks
    ibm = out.add(inverse_bind.transpose(0, 2, 1).astype(np.float32), _FLOAT, "MAT4")  # column-major

    times = out.add(
        np.arange(t, dtype=np.float64).astype(np.float32) / np.float32(a.fps), _FLOAT, "SCALAR", bounds=True
    )
    samplers, channels = [], []
    for k in range(j):
        for path_name, values, kind in (("rotation", quats[:, k], "VEC4"), ("translation", trans[:, k], "VEC3")):
            samplers.append({"input": times, "output": out.add(values, _FLOAT, kind), "interpolation": "LINEAR"})
            channels.append({"sampler": len(samplers) - 1, "target": {"node": k, "path": path_name}})

    skin: dict = {"name": "skeleton", "joints": list(range(j)), "inverseBindMatrices": ibm}
    if len(roots) == 1:
        skin["skeleton"] = roots[0]
    material = {
        "name": f"{a.name}_material",
        "pbrMetallicRoughness": {
            "baseColorFactor": [0.75, 0.75, 0.75, 1.0],
            "metallicFactor": 0.0,
            "roughnessFactor": 0.8,
        },
    }
    primitive = {"attributes": attributes, "indices": indices, "material": 0, "mode": _TRIANGLES}
    gltf = {
        "scene": 0,
        "scenes": [{"nodes": [*roots, j]}],
        "nodes": nodes,
        "meshes": [{"name": a.name, "primitives": [primitive]}],
        "materials": [material],
        "skins": [skin],
        "animations": [{"name": "motion", "samplers": samplers, "channels": channels}],
    }
    out.write(path, gltf)


# ----------------------------------------------------------------------------- reading


def _parse_glb(data: bytes) -> tuple[dict, bytes]:
    """A GLB's JSON (a dict) and BIN chunk, or ValueError saying what is wrong with the container."""
    if len(data) < 12:
        raise ValueError(f"not a GLB file (only {len(data)} bytes)")
    magic, version, length = struct.unpack_from("<III", data, 0)
    if magic != _GLB_MAGIC:
        raise ValueError(f"not a GLB file (magic 0x{magic:08x})")
    if version != _GLB_VERSION:
        raise ValueError(f"unsupported glTF container version {version}")
    if length > len(data):
        raise ValueError(f"truncated GLB file ({len(data)} of {length} bytes)")
    gltf: object = None
    binary = b""
    pos = 12
    while pos + 8 <= length:
        chunk_len, chunk_type = struct.unpack_from("<II", data, pos)
        body = data[pos + 8 : pos + 8 + chunk_len]
        if chunk_type == _CHUNK_JSON and gltf is None:
            try:
                gltf = json.loads(body.decode("utf-8"))
            except (UnicodeDecodeError, ValueError) as exc:
                raise ValueError(f"the JSON chunk is not JSON ({exc})") from None
        elif chunk_type == _CHUNK_BIN and not binary:
            binary = body
        pos += 8 + chunk_len
    if not isinstance(gltf, dict):
        raise ValueError("GLB file has no JSON chunk holding an object")
    return gltf, binary


def _read_glb(path: str | os.PathLike[str]) -> tuple[dict, bytes]:
    with open(path, "rb") as fh:
        data = fh.read()
    try:
        return _parse_glb(data)
    except ValueError as exc:
        raise ValueError(f"path: {exc}") from None


def _accessor(gltf: dict, binary: bytes, index: int) -> np.ndarray:
    acc = gltf["accessors"][index]
    dtype = np.dtype(_DTYPES[acc["componentType"]]).newbyteorder("<")
    ncomp = _COMPONENTS[acc["type"]]
    count = acc["count"]
    if "bufferView" not in acc:  # all zeros per spec
        return np.zeros((count, ncomp) if ncomp > 1 else count, dtype=dtype)
    view = gltf["bufferViews"][acc["bufferView"]]
    if view.get("buffer", 0) != 0:
        raise ValueError("path: only the GLB-embedded buffer is supported")
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    elem = dtype.itemsize * ncomp
    stride = view.get("byteStride", elem)
    raw = np.frombuffer(binary, dtype=np.uint8, count=stride * (count - 1) + elem, offset=start)
    rows = np.lib.stride_tricks.as_strided(raw, shape=(count, elem), strides=(stride, 1))
    out = np.ascontiguousarray(rows).view(dtype).reshape(count, ncomp)
    return out if ncomp > 1 else out.reshape(count)


def _read_primitives(path: str | os.PathLike[str], what: str) -> list[np.ndarray]:
    gltf, binary = _read_glb(path)
    result = []
    for mesh in gltf.get("meshes", []):
        parts = []
        offset = 0
        for prim in mesh["primitives"]:
            pos = _accessor(gltf, binary, prim["attributes"]["POSITION"])
            if what == "positions":
                parts.append(pos)
            else:
                if "indices" in prim:
                    idx = _accessor(gltf, binary, prim["indices"]).astype(np.int64)
                else:
                    idx = np.arange(len(pos), dtype=np.int64)
                parts.append(idx.reshape(-1, 3) + offset)
            offset += len(pos)
        result.append(np.concatenate(parts) if parts else np.zeros((0, 3)))
    return result


def read_glb_positions(path: str | os.PathLike[str]) -> list[np.ndarray]:
    """Each mesh's ``POSITION`` data, ``(V, 3)`` float32, in mesh order.

    A minimal reader meant for tests: it understands the embedded buffer only
    and concatenates the primitives of a mesh.
    """
    return _read_primitives(path, "positions")


def read_glb_indices(path: str | os.PathLike[str]) -> list[np.ndarray]:
    """Each mesh's triangle indices, ``(F, 3)`` int64, in mesh order (triangle lists only)."""
    return _read_primitives(path, "indices")
