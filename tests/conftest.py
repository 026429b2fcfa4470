"""Shared fixtures: a tiny synthetic rig for exhaustive checks, the real canonical layer once."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from unibody.rig import Rig

# Property-based tests (tests/fuzz): seeded and bounded so the default suite stays fast; the long
# run is `pytest tests/fuzz --hypothesis-profile=long`.
_FUZZ = dict(derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow], database=None)
settings.register_profile("default", max_examples=30, **_FUZZ)
settings.register_profile("long", max_examples=1000, **_FUZZ)

TOL = {torch.float32: 1e-5, torch.float64: 1e-10}


def chain_rig(num_joints: int = 5, rings: int = 4, per_ring: int = 6, seed: int = 0) -> Rig:
    """A Root + chain of joints along +Y wrapped in a tube mesh with smooth random weights.

    Each joint's RBF row averages the ring of vertices around it, so it reproduces the bind
    joints exactly; bind rotations are random so that nothing relies on identity frames.
    """
    rng = np.random.default_rng(seed)
    parents = [-1] + list(range(num_joints - 1))
    heights = np.arange(num_joints, dtype=np.float64) * 0.2
    heights[0] = heights[1] = 0.0
    verts, faces = [], []
    n_rings = (num_joints - 1) * rings
    for r in range(n_rings):
        y = 0.2 * r / rings
        for s in range(per_ring):
            a = 2 * np.pi * s / per_ring
            verts.append([0.05 * np.cos(a), y, 0.05 * np.sin(a)])
    for r in range(n_rings - 1):
        for s in range(per_ring):
            a, b = r * per_ring + s, r * per_ring + (s + 1) % per_ring
            faces += [[a, b + per_ring, b], [a, a + per_ring, b + per_ring]]
    verts = np.asarray(verts)
    joints = np.stack([np.zeros(num_joints), heights, np.zeros(num_joints)], 1)
    d = np.abs(verts[:, 1:2] - joints[None, 1:, 1])
    w = np.exp(-((d / 0.12) ** 2)) * (d < 0.25)
    w = np.concatenate([np.zeros((len(verts), 1)), w], 1)
    w /= w.sum(1, keepdims=True)
    sv, sj = np.nonzero(w)
    rbf = np.zeros((num_joints, len(verts)))
    for j in range(1, num_joints):
        ring = np.argsort(np.abs(verts[:, 1] - heights[j]))[:per_ring]
        rbf[j, ring] = 1.0 / per_ring
    rj, rv = np.nonzero(rbf)
    q = rng.normal(size=(num_joints, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, s = q.T
    rot = np.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - s * z),
            2 * (x * z + s * y),
            2 * (x * y + s * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - s * x),
            2 * (x * z - s * y),
            2 * (y * z + s * x),
            1 - 2 * (x * x + y * y),
        ],
        1,
    ).reshape(-1, 3, 3)
    rot[0] = np.eye(3)
    bind = np.tile(np.eye(4), (num_joints, 1, 1))
    bind[:, :3, :3], bind[:, :3, 3] = rot, joints
    tpose = rot.copy()
    tpose[1:] = np.eye(3)
    names = ["Root"] + [f"J{i}" for i in range(1, num_joints)]
    return Rig.from_arrays(
        {
            "joint_names": np.asarray(names),
            "parents": np.asarray(parents),
            "bind_vertices": verts,
            "faces": np.asarray(faces, dtype=np.int64),
            "skin_vertex": sv,
            "skin_joint": sj,
            "skin_weight": w[sv, sj],
            "rbf_joint": rj,
            "rbf_vertex": rv,
            "rbf_weight": rbf[rj, rv],
            "bind_transforms": bind,
            "tpose_orient": tpose,
        }
    )


def icosahedron() -> tuple[np.ndarray, np.ndarray]:
    """The unit icosahedron: 12 vertices, 20 outward-facing triangles."""
    t = (1 + 5**0.5) / 2
    v = np.array(
        [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
         [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]],
        dtype=np.float64,
    )  # fmt: skip
    f = np.array(
        [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
         [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
         [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    )  # fmt: skip
    return v / np.linalg.norm(v, axis=1, keepdims=True), f


def icosphere(levels: int, radius: float = 1.0, centre=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """The icosahedron split ``levels`` times (each triangle into four at its edge midpoints),
    projected to the sphere of ``radius`` about ``centre``: float64 vertices, int64 outward triangles."""
    v, f = icosahedron()
    for _ in range(levels):
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        unique, inverse = np.unique(edges, axis=0, return_inverse=True)
        mid = v[unique[:, 0]] + v[unique[:, 1]]
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        ids = len(v) + inverse.reshape(3, -1)  # midpoints of edges 01, 12, 20
        v = np.concatenate([v, mid])
        a, b, c = f.T
        m01, m12, m20 = ids
        f = np.concatenate([np.stack(x, 1) for x in ((a, m01, m20), (b, m12, m01), (c, m20, m12), (m01, m12, m20))])
    return v * radius + np.asarray(centre), f.astype(np.int64)


def fk_loop(parents, rot: torch.Tensor, trans: torch.Tensor) -> torch.Tensor:
    """Independent FK reference: one joint at a time, 4x4 matrices; world transforms (B, J, 4, 4)."""
    b, j = rot.shape[:2]
    local = torch.zeros(b, j, 4, 4, dtype=rot.dtype)
    local[..., :3, :3], local[..., :3, 3], local[..., 3, 3] = rot, trans, 1
    world = [local[:, 0]]
    for k in range(1, j):
        world.append(world[parents[k]] @ local[:, k])
    return torch.stack(world, 1)


@pytest.fixture(scope="session")
def small_rig() -> Rig:
    return chain_rig()


@pytest.fixture(scope="session")
def rig() -> Rig:
    return Rig.canonical()


@pytest.fixture(scope="session")
def anny_layer64():
    """The real layer (canonical rig + Anny), float64, built once per session."""
    from unibody import BodyLayer

    return BodyLayer.from_anny(dtype=torch.float64)


@pytest.fixture(params=[torch.float32, torch.float64], ids=["f32", "f64"])
def dtype(request) -> torch.dtype:
    return request.param


# ----------------------------------------------------------------------------- property-test helpers


def change_fields(data, fields: dict, extra: list[str], replacement) -> dict:
    """One or two of an npz's ``fields`` dropped, added (``extra`` names: a (4, 8) array) or replaced.

    ``data`` is hypothesis's ``st.data()``; ``replacement(draw, old)`` makes the new array.
    """
    for _ in range(data.draw(st.integers(1, 2), label="changes")):
        key = data.draw(st.sampled_from(sorted(fields) + extra), label="key")
        if key not in fields:
            fields[key] = np.zeros((4, 8))
        elif data.draw(st.booleans(), label="drop"):
            del fields[key]
        else:
            fields[key] = replacement(data.draw, fields[key])
    return fields


def mutate_text(data, text: bytes, tokens: list[bytes], separator: bytes | None = None) -> bytes:
    """``text`` after 1-6 edits drawn by hypothesis's ``st.data()``: a byte flipped, the end cut,
    a token inserted, a few bytes deleted, a line doubled, or (with ``separator``) one field
    between separators replaced by a token."""
    buf = bytearray(text)
    kinds = ["flip", "truncate", "insert", "delete", "duplicate_line"] + (["replace_field"] if separator else [])
    for _ in range(data.draw(st.integers(1, 6), label="edits")):
        kind = data.draw(st.sampled_from(kinds))
        pos = data.draw(st.integers(0, max(len(buf) - 1, 0)))
        if kind == "flip" and buf:
            buf[pos] = data.draw(st.integers(0, 255))
        elif kind == "truncate":
            del buf[pos:]
        elif kind == "insert":
            buf[pos:pos] = data.draw(st.sampled_from(tokens))
        elif kind == "delete":
            del buf[pos : pos + data.draw(st.integers(1, 8))]
        elif kind == "replace_field":
            fields = bytes(buf).split(separator)
            fields[data.draw(st.integers(0, len(fields) - 1))] = data.draw(st.sampled_from(tokens))
            buf = bytearray(separator.join(fields))
        elif kind == "duplicate_line":
            lines = bytes(buf).split(b"\n")
            i = data.draw(st.integers(0, len(lines) - 1))
            lines.insert(i, lines[i])
            buf = bytearray(b"\n".join(lines))
    return bytes(buf)


def json_paths(x, at: tuple = (), width: int = 8) -> list[tuple]:
    """Every path into a JSON tree: dict keys and list indices (the first ``width`` of each)."""
    out = [at]
    if isinstance(x, dict):
        for k, v in list(x.items())[:width]:
            out += json_paths(v, (*at, k), width)
    elif isinstance(x, list):
        for i, v in enumerate(x[:width]):
            out += json_paths(v, (*at, i), width)
    return out


def change_json(draw, tree, kind: str, values, keys=None) -> None:
    """Change one place of a JSON ``tree`` in place: ``kind`` "drop" deletes a dict entry, "add"
    puts a new key (drawn from ``keys``) in a dict, anything else replaces a value; new values
    are drawn from the strategy ``values`` (property tests)."""
    paths = [p for p in json_paths(tree) if p]
    path = paths[draw(st.integers(0, len(paths) - 1))]
    parent = tree
    for k in path[:-1]:
        parent = parent[k]
    if kind == "drop" and isinstance(parent, dict):
        del parent[path[-1]]
    elif kind == "add" and isinstance(parent, dict) and keys is not None:
        parent[draw(keys)] = copy.deepcopy(draw(values))  # a fresh [] or {}: never shared, never a cycle
    else:
        parent[path[-1]] = copy.deepcopy(draw(values))


def bvhio_positions(path, frames: int) -> np.ndarray:
    """(T, J, 3) world positions of a BVH's joints in its own units, read by bvhio (End Sites left out)."""
    bvhio = pytest.importorskip("bvhio")
    root = bvhio.readAsHierarchy(str(path))
    layout = [entry[0] for entry in root.layout()]
    out = []
    for f in range(frames):
        root.loadPose(f)
        out.append([list(j.PositionWorld) for j in layout])
    return np.asarray(out, np.float64)
