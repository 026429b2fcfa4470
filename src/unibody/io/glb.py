"""Binary glTF 2.0 (``.glb``) export of triangle meshes, in pure numpy.

One scene, one node and one mesh per :class:`MeshSpec`, each with a single
triangle primitive carrying ``POSITION`` and ``NORMAL`` (float32) and uint32
indices, plus one PBR material built from the spec's colour.

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

__all__ = ["MeshSpec", "mesh_list", "vertex_normals", "write_glb", "read_glb_positions", "read_glb_indices"]

_GLB_MAGIC = 0x46546C67  # b"glTF"
_GLB_VERSION = 2
_CHUNK_JSON = 0x4E4F534A  # b"JSON"
_CHUNK_BIN = 0x004E4942  # b"BIN\0"

_FLOAT = 5126
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

    blob = bytearray()
    buffer_views: list[dict] = []
    accessors: list[dict] = []

    def add(array: np.ndarray, component: int, kind: str, target: int, bounds: bool = False) -> int:
        data = np.ascontiguousarray(array).astype("<" + np.dtype(_DTYPES[component]).str[1:], copy=False)
        offset = len(blob)  # always a multiple of 4: every piece below is padded
        raw = data.tobytes()
        blob.extend(_pad4(raw, b"\x00"))
        buffer_views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(raw), "target": target})
        acc: dict = {
            "bufferView": len(buffer_views) - 1,
            "componentType": component,
            "count": int(data.shape[0]) if kind != "SCALAR" else int(data.size),
            "type": kind,
        }
        if bounds:
            flat = data.reshape(acc["count"], _COMPONENTS[kind])
            acc["min"] = [float(x) for x in flat.min(axis=0)]
            acc["max"] = [float(x) for x in flat.max(axis=0)]
        accessors.append(acc)
        return len(accessors) - 1

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
        "asset": {"version": "2.0", "generator": "unibody"},
        "scene": 0,
        "scenes": [{"nodes": list(range(len(nodes)))}],
        "nodes": nodes,
        "meshes": gl_meshes,
        "materials": materials,
        "accessors": accessors,
        "bufferViews": buffer_views,
        "buffers": [{"byteLength": len(blob)}],
    }
    json_chunk = _pad4(json.dumps(gltf, separators=(",", ":")).encode("utf-8"), b" ")
    bin_chunk = bytes(blob)  # already padded to 4
    total = 12 + 8 + len(json_chunk) + 8 + len(bin_chunk)
    with atomic_write(path) as fh:
        fh.write(struct.pack("<III", _GLB_MAGIC, _GLB_VERSION, total))
        fh.write(struct.pack("<II", len(json_chunk), _CHUNK_JSON))
        fh.write(json_chunk)
        fh.write(struct.pack("<II", len(bin_chunk), _CHUNK_BIN))
        fh.write(bin_chunk)


# ----------------------------------------------------------------------------- reading


def _read_glb(path: str | os.PathLike[str]) -> tuple[dict, bytes]:
    with open(path, "rb") as fh:
        data = fh.read()
    if len(data) < 12:
        raise ValueError(f"path: not a GLB file (only {len(data)} bytes)")
    magic, version, length = struct.unpack_from("<III", data, 0)
    if magic != _GLB_MAGIC:
        raise ValueError(f"path: not a GLB file (magic 0x{magic:08x})")
    if version != _GLB_VERSION:
        raise ValueError(f"path: unsupported glTF container version {version}")
    if length > len(data):
        raise ValueError(f"path: truncated GLB file ({len(data)} of {length} bytes)")
    gltf: dict | None = None
    binary = b""
    pos = 12
    while pos + 8 <= length:
        chunk_len, chunk_type = struct.unpack_from("<II", data, pos)
        body = data[pos + 8 : pos + 8 + chunk_len]
        if chunk_type == _CHUNK_JSON and gltf is None:
            gltf = json.loads(body.decode("utf-8"))
        elif chunk_type == _CHUNK_BIN and not binary:
            binary = body
        pos += 8 + chunk_len
    if gltf is None:
        raise ValueError("path: GLB file has no JSON chunk")
    return gltf, binary


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
