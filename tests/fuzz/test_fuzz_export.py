"""Property: an export of any finite motion reads back, through an independent reader, as the motion's body.

Input: 1-3 frames of hostile but finite values: half turns, a frame turned against the one
before, angles of 1e10 rad, tiny angles, a root 0 to 1e30 m from the origin (1e300 in float64),
frame rates 1e-5 to 1e5, an identity at its bounds (PCA ±10σ on the leading component, Anny 0
or 1), float32 or float64 posing, batches of 1-3. Each example writes one format and reads it
back without unibody's readers:

- ``.glb``: pygltflib; each node's rest TRS, the animation's keys (at i / fps s) and forward
  kinematics give the joints' world positions;
- ``.usda``: UsdSkel's SkeletonQuery (joint transforms in skeleton space) at each time code;
- ``.bvh``: bvhio (world positions of the joints, centimetres);
- ``.npz`` mesh sequence: numpy (the vertices).

Each must match ``BodyLayer.pose`` of the motion in the writer's dtype to 1 mm plus eight float32
steps at the root's distance (float32 posing, files and bvhio round there at each joint of a
chain), with the frame count and rate kept; or the writer refuses with one line starting ``motion.`` and leaves no file.
A root farther than 1e5 m must be refused. Seeded and bounded (tests/conftest.py profiles).
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import event, example, given
from hypothesis import strategies as st

from conftest import bvhio_positions
from unibody.convert import ConvertOptions
from unibody.convert._body import body_for
from unibody.convert.bvh_export import write_bvh
from unibody.convert.export import write_glb, write_meshes, write_usd
from unibody.motion import Motion

FAR = 1e5  # m: the farthest root a writer may accept (its float32 step there is 7.8 mm)
WRITERS = {".glb": write_glb, ".usda": write_usd, ".bvh": write_bvh, ".npz": write_meshes}


def _float32_step(x: float) -> float:
    return float(np.spacing(np.float32(min(abs(x), 3e38))))


# ----------------------------------------------------------------------------- readers


def _gltf_joints(path, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """(T, J, 3) world positions of the skin's joints at each key, and the key times (glTF 2.0 §3.7, §3.11)."""
    pygltflib = pytest.importorskip("pygltflib")
    gltf = pygltflib.GLTF2().load(str(path))
    blob = gltf.binary_blob()

    def accessor(index: int) -> np.ndarray:
        acc = gltf.accessors[index]
        view = gltf.bufferViews[acc.bufferView]
        width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc.type]
        assert acc.componentType == 5126  # FLOAT
        start = (view.byteOffset or 0) + (acc.byteOffset or 0)
        return np.frombuffer(blob, np.float32, acc.count * width, start).reshape(acc.count, width).astype(np.float64)

    def matrix(t, q) -> np.ndarray:
        x, y, z, w = np.asarray(q, np.float64) / np.linalg.norm(q)
        m = np.eye(4)
        m[:3, :3] = [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
        m[:3, 3] = t
        return m

    trs = [[list(n.translation or [0, 0, 0]), list(n.rotation or [0, 0, 0, 1])] for n in gltf.nodes]
    anim = gltf.animations[0]
    keys = {}
    times = None
    for ch in anim.channels:
        sampler = anim.samplers[ch.sampler]
        times = accessor(sampler.input)[:, 0]
        keys[ch.target.node, ch.target.path] = accessor(sampler.output)
    out = []
    for f in range(frames):
        local = []
        for k, (t, q) in enumerate(trs):
            t = keys[k, "translation"][f] if (k, "translation") in keys else t
            q = keys[k, "rotation"][f] if (k, "rotation") in keys else q
            local.append(matrix(t, q))
        world = {}
        stack = [(k, np.eye(4)) for k in gltf.scenes[gltf.scene].nodes]
        while stack:
            k, parent = stack.pop()
            world[k] = parent @ local[k]
            stack += [(c, world[k]) for c in gltf.nodes[k].children or []]
        out.append([world[n][:3, 3] for n in gltf.skins[0].joints])
    return np.asarray(out), times


def _usd_joints(path, frames: int) -> tuple[np.ndarray, float]:
    """(T, J, 3) skeleton-space joint positions at time codes 0..T-1, and timeCodesPerSecond."""
    from pxr import Usd, UsdSkel

    stage = Usd.Stage.Open(str(path))
    cache = UsdSkel.Cache()
    query = cache.GetSkelQuery(UsdSkel.Skeleton(stage.GetPrimAtPath("/Body/Skeleton")))
    out = []
    for f in range(frames):
        xforms = query.ComputeJointSkelTransforms(Usd.TimeCode(f))
        out.append([list(m.ExtractTranslation()) for m in xforms])  # row-vector matrices: row 3
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, frames - 1)
    return np.asarray(out, np.float64), stage.GetTimeCodesPerSecond()


def _bvh_joints(path, frames: int) -> tuple[np.ndarray, float]:
    """(T, 77, 3) world positions in metres (Hips first; no Root in a BVH) and the frame rate."""
    bvhio = pytest.importorskip("bvhio")
    container = bvhio.readAsBvh(str(path))
    assert container.FrameCount == frames
    return bvhio_positions(path, frames) / 100.0, 1.0 / container.FrameTime


# ----------------------------------------------------------------------------- inputs


def _rotation_vectors(draw, rng: np.random.Generator, frames: int) -> np.ndarray:
    kind = draw(st.sampled_from(["normal", "half", "against", "huge", "tiny", "zero"]))
    event(f"pose: {kind}")
    pose = rng.normal(scale=0.5, size=(frames, 77, 3))
    if kind == "half":  # exactly pi about random axes: the quaternion's w is 0
        pose = pose / np.linalg.norm(pose, axis=-1, keepdims=True) * math.pi
    elif kind == "against":  # every joint turned by ~pi against the frame before
        pose[1::2] = -pose[1::2] / np.linalg.norm(pose[1::2], axis=-1, keepdims=True) * (math.pi - 1e-3)
    elif kind == "huge":
        pose *= 2e10
    elif kind == "tiny":
        pose *= 1e-30
    elif kind == "zero":
        pose[:] = 0.0
    return pose


@st.composite
def motions(draw) -> tuple[Motion, ConvertOptions]:
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    frames = draw(st.integers(1, 3))
    dtype = draw(st.sampled_from(["float32", "float64"]))
    pose = _rotation_vectors(draw, rng, frames)
    if draw(st.integers(0, 3)) < 3:  # most draws: a root that is written
        far = draw(st.sampled_from([0.0, 1.0, 1e3, 9e4]))
    else:
        far = draw(st.sampled_from([1.1e5, 1e7, 1e30] + ([1e300] if dtype == "float64" else [])))
    event(f"root at {far:g} m")
    transl = rng.normal(size=(frames, 3)) + [0.0, 1.0, 0.0]
    transl[:, draw(st.integers(0, 2))] += far * draw(st.sampled_from([1, -1]))
    backend = draw(st.sampled_from([None, "pca", "anny"]))
    identity = None
    if backend == "pca":
        identity = np.zeros(128)
        identity[0] = draw(st.sampled_from([-10.0, 10.0, 0.0]))
        identity[1:6] = rng.normal(size=5)
    elif backend == "anny":
        identity = rng.choice([0.0, 1.0, 0.5], size=6)
    fps = draw(st.sampled_from([1e-5, 0.5, 23.976, 30.0, 120.0, 3e4, 1e5]))
    np_dtype = np.float32 if dtype == "float32" else np.float64
    motion = Motion(
        pose.astype(np_dtype),
        transl.astype(np_dtype),
        fps,
        None if identity is None else identity.astype(np.float32),
        backend,
        "fuzz",
    )
    return motion, ConvertOptions(batch=draw(st.integers(1, 3)), dtype=dtype)


def _reference(motion: Motion, dtype: str) -> tuple[np.ndarray, np.ndarray]:
    """``BodyLayer.pose`` of the motion as the writer poses it: joints (T, 78, 3), vertices (T, V, 3)."""
    torch_dtype = {"float32": torch.float32, "float64": torch.float64}[dtype]
    layer, prepared = body_for(motion, torch_dtype)
    with torch.no_grad():
        out = layer.pose(
            prepared,
            torch.as_tensor(np.asarray(motion.pose), dtype=torch_dtype),
            transl=torch.as_tensor(np.asarray(motion.transl), dtype=torch_dtype),
        )
    return out.joints.double().numpy(), out.vertices.double().numpy()


# ----------------------------------------------------------------------------- the property


@given(case=motions(), suffix=st.sampled_from(list(WRITERS)))
@example(  # a root 200 km away (kilometres given as metres)
    case=(
        Motion(np.zeros((1, 77, 3), np.float32), np.array([[2e5, 1.0, 0.0]], np.float32), 30.0),
        ConvertOptions(),
    ),
    suffix=".glb",
)
def test_an_export_reads_back_as_the_motion_or_is_refused(case, suffix):
    if suffix == ".usda":
        pytest.importorskip("pxr")
    event(f"writer: {suffix}")
    event(f"identity: {case[0].identity_backend}")
    with tempfile.TemporaryDirectory() as folder:
        _check_export(*case, suffix, Path(folder))


def _check_export(motion: Motion, options: ConvertOptions, suffix: str, tmp_path: Path) -> None:
    path = tmp_path / f"take{suffix}"
    far = float(np.abs(motion.transl).max())
    try:
        WRITERS[suffix](motion, path, options)
    except ValueError as exc:
        event("refused")
        message = str(exc)
        assert message.startswith("motion.") and "\n" not in message, message
        assert list(tmp_path.iterdir()) == []
        assert far > FAR or not np.isfinite(_reference(motion, options.dtype)[1]).all(), message
        return
    assert far <= FAR, f"a root {far:g} m from the origin was written"
    frames = len(motion.pose)
    joints, vertices = _reference(motion, options.dtype)
    # float32 posing rounds at the root's distance at every joint of a chain: at 9e4 m the
    # float32 layer is 8-23 mm from the float64 one, which the float64 export matches exactly
    tol = 1e-3 + 8 * _float32_step(far)
    if suffix == ".glb":
        got, times = _gltf_joints(path, frames)
        np.testing.assert_allclose(times, np.arange(frames) / motion.fps, rtol=1e-6)
    elif suffix == ".usda":
        got, rate = _usd_joints(path, frames)
        assert rate == pytest.approx(motion.fps, rel=1e-12)
    elif suffix == ".bvh":
        got, rate = _bvh_joints(path, frames)
        assert rate == pytest.approx(motion.fps, rel=1e-6)
        # write_bvh turns rotations into Euler angles in float64 whatever options.dtype (the
        # T-pose's precision): at 1e9 rad a float32 angle is off by radians
        joints = _reference(motion, "float64")[0][:, 1:]  # no Root in a BVH
    else:
        with np.load(path, allow_pickle=False) as data:
            got = data["vertices"].astype(np.float64)
            assert float(data["fps"]) == pytest.approx(motion.fps, rel=1e-6)
        joints = vertices
    assert got.shape == joints.shape and np.isfinite(got).all()
    err = float(np.abs(got - joints).max())
    assert err <= tol, f"{suffix}: {err * 1e3:.3f} mm off (tolerance {tol * 1e3:.3f} mm)"
