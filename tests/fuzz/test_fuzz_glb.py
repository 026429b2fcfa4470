"""Property: a damaged GLB is read as a scene of well-formed triangle meshes, or refused with a ValueError.

Input: a small skinned GLB (:func:`unibody.io.glb.write_skinned_glb`: a cube on three joints,
two frames) and a static one (:func:`unibody.io.glb.write_glb`), then damaged: a value anywhere
in the JSON replaced (by -1, 2**40, 0.5, NaN, a string, null, a list, an object), a key dropped,
bytes of the binary chunk flipped, the file cut short. :func:`unibody.io.glb_scene.read_glb_scene`
must return meshes whose vertices are (V, 3) floats and faces (F, 3) indices below V, or raise
ValueError; and ``unibody view FILE --record`` must record it or exit 3 with one line naming the
file. Seeded and bounded (tests/conftest.py profiles).
"""

from __future__ import annotations

import json
import struct
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import event, given
from hypothesis import strategies as st

from conftest import change_json
from unibody.io.glb import MeshSpec, SkinnedAnimation, write_glb, write_skinned_glb
from unibody.io.glb_scene import read_glb_scene

_JSON, _BIN = 0x4E4F534A, 0x004E4942


def _files() -> list[bytes]:
    v = np.array([[x, y, z] for x in (0.0, 0.2) for y in (0.0, 0.2) for z in (0.0, 0.2)])
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1]])
    rng = np.random.default_rng(3)
    anim = SkinnedAnimation(
        vertices=v,
        faces=f,
        joint_names=("a", "b", "c"),
        parents=np.array([-1, 0, 1]),
        bind_matrices=np.tile(np.eye(4), (3, 1, 1)),
        joint_indices=rng.integers(0, 3, size=(8, 2)),
        joint_weights=np.full((8, 2), 0.5),
        rotations=rng.normal(size=(2, 3, 4)),
        translations=rng.normal(size=(2, 3, 3)) * 0.1,
        fps=30.0,
    )
    with tempfile.TemporaryDirectory() as folder:
        write_skinned_glb(Path(folder) / "a.glb", anim)
        write_glb(Path(folder) / "b.glb", [MeshSpec(v, f, (1.0, 0.5, 0.0), "box")])
        return [(Path(folder) / n).read_bytes() for n in ("a.glb", "b.glb")]


FILES = _files()


def _split(data: bytes) -> tuple[dict, bytes]:
    n = struct.unpack_from("<I", data, 12)[0]
    gltf = json.loads(data[20 : 20 + n])
    m = struct.unpack_from("<I", data, 20 + n)[0]
    return gltf, data[28 + n : 28 + n + m]


def _join(gltf: dict, blob: bytes) -> bytes:
    js = json.dumps(gltf, allow_nan=True).encode()
    js += b" " * (-len(js) % 4)
    blob += b"\0" * (-len(blob) % 4)
    body = struct.pack("<II", len(js), _JSON) + js + struct.pack("<II", len(blob), _BIN) + blob
    return struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body


_VALUES = st.sampled_from([-1, 0, 1, 2**40, 0.5, float("nan"), "x", None, [], {}, [0, 0, 0], {"a": 1}])


@st.composite
def damaged(draw) -> bytes:
    data = FILES[draw(st.integers(0, len(FILES) - 1))]
    gltf, blob = _split(data)
    kind = draw(st.sampled_from(["value", "drop", "flip", "cut"]))
    event(kind)
    if kind in ("value", "drop"):
        change_json(draw, gltf, kind, _VALUES)
        return _join(gltf, blob)
    if kind == "flip":
        blob = bytearray(blob)
        for _ in range(draw(st.integers(1, 8))):
            blob[draw(st.integers(0, len(blob) - 1))] ^= 1 << draw(st.integers(0, 7))
        return _join(gltf, bytes(blob))
    return data[: draw(st.integers(0, len(data) - 1))]


@given(data=damaged())
def test_a_damaged_glb_is_a_well_formed_scene_or_a_value_error(data):
    try:
        meshes = read_glb_scene(data)
    except ValueError as exc:
        event("refused")
        assert str(exc)
        return
    for verts, faces in meshes:
        assert verts.ndim == 2 and verts.shape[1] == 3 and verts.dtype.kind == "f"
        assert faces.ndim == 2 and faces.shape[1] == 3 and len(faces) and faces.dtype.kind == "i"
        assert faces.min() >= 0 and faces.max() < len(verts)


@given(data=damaged())
def test_the_viewer_records_a_damaged_glb_or_names_it(data):
    pytest.importorskip("PIL")
    from unibody.cli import main

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "scene.glb"
        path.write_bytes(data)
        out = Path(folder) / "x.png"
        import contextlib
        import io

        err = io.StringIO()
        with contextlib.redirect_stderr(err):
            code = main(["view", str(path), "--record", str(out), "--size", "32x24"])
        event(f"exit {code}")
        if code == 0:
            assert out.is_file()
        else:
            lines = [x for x in err.getvalue().splitlines() if x.startswith("unibody: error:")]
            assert code == 3 and len(lines) == 1 and str(path) in lines[0], err.getvalue()
            assert not out.exists()
