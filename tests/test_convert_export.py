"""Rigged exports and mesh sequences of a motion (unibody.convert.export), checked by independent readers.

GLB: the Khronos glTF validator (node + npm gltf-validator) and pygltflib + numpy skinning in this
file; USD: pxr's UsdValidation framework (usdchecker's) and UsdSkel's own skinning. Each reproduces
``BodyLayer.pose`` of a random motion on a non-mean identity.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from unibody import JOINT_NAMES
from unibody.convert import ConvertOptions
from unibody.convert._body import body_for
from unibody.convert.export import GLB_INFLUENCES, write_glb, write_meshes, write_usd
from unibody.motion import Motion, load_mesh_sequence

HERE = Path(__file__).parent
VALIDATOR = HERE / "node" / "node_modules" / "gltf-validator"
FPS = 24.0  # not 30: the rate must be kept, not defaulted
FRAMES = 11
TOL_M = 0.5e-3


@pytest.fixture(scope="module")
def motion() -> Motion:
    """A random motion on a non-mean PCA identity (128 coefficients: the layer body_for caches)."""
    rng = np.random.default_rng(34)
    identity = np.zeros(128, np.float32)
    identity[:6] = rng.normal(size=6) * 1.5
    pose = (rng.normal(size=(FRAMES, 77, 3)) * 0.35).astype(np.float32)
    pose[:, 0] = rng.normal(size=(FRAMES, 3)) * 1.5  # Hips: any orientation
    transl = (rng.normal(size=(FRAMES, 3)) + [0, 1, 0]).astype(np.float32)
    return Motion(pose, transl, FPS, identity, "pca", "test")


@pytest.fixture(scope="module")
def reference(motion) -> np.ndarray:
    """``BodyLayer.pose`` of the motion, (T, V, 3) float64 m."""
    layer, prepared = body_for(motion)
    with torch.no_grad():
        out = layer.pose(prepared, torch.as_tensor(motion.pose), transl=torch.as_tensor(motion.transl))
    return out.vertices.double().numpy()


OPTIONS = ConvertOptions(batch=4)  # 11 frames: batches of 4, 4 and 3


@pytest.fixture(scope="module")
def glb(motion, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("glb") / "motion.glb"
    write_glb(motion, path, OPTIONS)
    return path


# ----------------------------------------------------------------------------- GLB


def _validate(path: Path) -> dict:
    if shutil.which("node") is None:
        pytest.skip("node is not installed (the glTF validator runs on node)")
    if not VALIDATOR.is_dir():
        pytest.skip("gltf-validator missing: npm install --prefix tests/node gltf-validator@2.0.0-dev.3.10")
    run = subprocess.run(
        ["node", str(HERE / "gltf_validate.js"), str(path)], capture_output=True, text=True, timeout=120
    )
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout)


def test_khronos_validator_reports_no_errors(glb, tmp_path):
    report = _validate(glb)
    print(f"gltf-validator: {report['numErrors']} errors, {report['numWarnings']} warnings, {report['numInfos']} infos")
    assert report["numErrors"] == 0, report["messages"]
    assert report["numWarnings"] == 0, report["messages"]
    # The check can fail: the same file with one weight set off its unit sum is an error.
    from pygltflib import GLTF2

    gltf = GLTF2().load(str(glb))
    blob = bytearray(gltf.binary_blob())
    acc = gltf.accessors[gltf.meshes[0].primitives[0].attributes.WEIGHTS_0]
    at = gltf.bufferViews[acc.bufferView].byteOffset
    blob[at : at + 4] = np.float32(3.0).tobytes()
    gltf.set_binary_blob(bytes(blob))
    broken = tmp_path / "broken.glb"
    gltf.save_binary(str(broken))
    assert _validate(broken)["numErrors"] > 0


def _accessor(gltf, blob: bytes, index: int) -> np.ndarray:
    """An accessor's data as numpy, from the glTF 2.0 spec's layout (tightly packed views)."""
    acc = gltf.accessors[index]
    view = gltf.bufferViews[acc.bufferView]
    dtype = {5121: np.uint8, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}[acc.componentType]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[acc.type]
    assert view.byteStride in (None, width * np.dtype(dtype).itemsize)
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    data = np.frombuffer(blob, dtype=dtype, count=acc.count * width, offset=start)
    return data.reshape(acc.count, width) if width > 1 else data


def _quat_xyzw_matrix(q: np.ndarray) -> np.ndarray:
    x, y, z, w = (q / np.linalg.norm(q)).astype(np.float64)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _gltf_skin_at(gltf, blob: bytes, frame: int) -> np.ndarray:
    """Evaluate the animation at keyframe ``frame`` and skin the mesh (glTF 2.0 spec §3.7.3)."""
    local = {}
    for k, node in enumerate(gltf.nodes):
        m = np.eye(4)
        if node.rotation is not None:
            m[:3, :3] = _quat_xyzw_matrix(np.asarray(node.rotation))
        if node.translation is not None:
            m[:3, 3] = node.translation
        local[k] = m
    anim = gltf.animations[0]
    for ch in anim.channels:
        sampler = anim.samplers[ch.sampler]
        times = _accessor(gltf, blob, sampler.input)
        assert sampler.interpolation == "LINEAR"
        np.testing.assert_allclose(times[frame], frame / FPS, rtol=1e-6)
        value = _accessor(gltf, blob, sampler.output)[frame]
        if ch.target.path == "rotation":
            local[ch.target.node][:3, :3] = _quat_xyzw_matrix(value)
        elif ch.target.path == "translation":
            local[ch.target.node][:3, 3] = value
    world = {}

    def visit(k: int, parent: np.ndarray) -> None:
        world[k] = parent @ local[k]
        for c in gltf.nodes[k].children or []:
            visit(c, world[k])

    for k in gltf.scenes[gltf.scene].nodes:
        visit(k, np.eye(4))
    skin = gltf.skins[0]
    ibm = _accessor(gltf, blob, skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)  # column-major
    joint_mats = np.stack([world[n] for n in skin.joints]) @ ibm
    prim = gltf.meshes[0].primitives[0]
    attrs = prim.attributes
    rest = _accessor(gltf, blob, attrs.POSITION).astype(np.float64)
    rest_h = np.concatenate([rest, np.ones((len(rest), 1))], axis=1)
    out = np.zeros_like(rest)
    n_sets = 0
    while getattr(attrs, f"JOINTS_{n_sets}", None) is not None:
        joints = _accessor(gltf, blob, getattr(attrs, f"JOINTS_{n_sets}")).astype(np.int64)
        weights = _accessor(gltf, blob, getattr(attrs, f"WEIGHTS_{n_sets}")).astype(np.float64)
        for c in range(4):
            out += weights[:, c, None] * np.einsum("vij,vj->vi", joint_mats[joints[:, c], :3], rest_h)
        n_sets += 1
    assert n_sets == GLB_INFLUENCES // 4
    return out


def test_independent_reader_reproduces_the_pose(glb, motion, reference):
    pygltflib = pytest.importorskip("pygltflib")
    gltf = pygltflib.GLTF2().load(str(glb))
    blob = gltf.binary_blob()
    assert [gltf.nodes[k].name for k in gltf.skins[0].joints] == list(JOINT_NAMES)
    assert len(gltf.animations[0].channels) == 2 * len(JOINT_NAMES)
    times = _accessor(gltf, blob, gltf.animations[0].samplers[0].input)
    np.testing.assert_allclose(times, np.arange(FRAMES) / FPS, rtol=1e-6)
    errors = []
    for frame in (0, 3, 4, FRAMES - 1):  # batch edges included (batch 4)
        err = np.linalg.norm(_gltf_skin_at(gltf, blob, frame) - reference[frame], axis=1).max()
        errors.append(err)
        assert err <= TOL_M, f"frame {frame}: {err * 1e3:.4f} mm"
    print(f"glTF vs BodyLayer.pose: max {max(errors) * 1e3:.4f} mm")
    # The check can fail: the frame next door is centimetres away.
    assert np.linalg.norm(_gltf_skin_at(gltf, blob, 1) - reference[2], axis=1).max() > 100 * TOL_M


# ----------------------------------------------------------------------------- USD


@pytest.fixture(scope="module")
def usd_paths(motion, tmp_path_factory) -> list[Path]:
    pytest.importorskip("pxr")
    folder = tmp_path_factory.mktemp("usd")
    paths = [folder / "motion.usda", folder / "motion.usdc"]
    for p in paths:
        write_usd(motion, p, OPTIONS)
    return paths


def _usd_errors(stage) -> list[str]:
    from pxr import UsdValidation

    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    errors = UsdValidation.ValidationContext(validators).Validate(stage)
    kinds = UsdValidation.ValidationErrorType
    print(f"UsdValidation: {len(validators)} validators, {len(errors)} findings")
    return [e.GetErrorAsString() for e in errors if e.GetType() == kinds.Error]


def test_usd_validates_and_states_its_layout(usd_paths, motion):
    from pxr import Usd, UsdGeom, UsdSkel

    assert usd_paths[0].read_bytes().startswith(b"#usda 1.0")
    assert usd_paths[1].read_bytes().startswith(b"PXR-USDC")
    for path in usd_paths:
        stage = Usd.Stage.Open(str(path))
        assert _usd_errors(stage) == []
        assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0 and UsdGeom.GetStageUpAxis(stage) == "Y"
        assert stage.GetTimeCodesPerSecond() == FPS
        assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, FRAMES - 1)
        skel = UsdSkel.Skeleton(stage.GetPrimAtPath("/Body/Skeleton"))
        joints = list(skel.GetJointsAttr().Get())
        assert [j.rsplit("/", 1)[-1] for j in joints] == list(JOINT_NAMES)
        assert joints[2] == "Root/Hips/Spine1"
    # The check can fail: a stage without its metadata has errors.
    bare = Usd.Stage.Open(str(usd_paths[0]))
    bare.GetRootLayer().ClearDefaultPrim()
    assert _usd_errors(bare) != []


def test_usdskel_skinning_reproduces_the_pose(usd_paths, reference):
    from pxr import Usd, UsdGeom, UsdSkel

    for path in usd_paths:
        stage = Usd.Stage.Open(str(path))
        cache = UsdSkel.Cache()
        root = UsdSkel.Root(stage.GetDefaultPrim())
        cache.Populate(root, Usd.PrimDefaultPredicate)
        (binding,) = cache.ComputeSkelBindings(root, Usd.PrimDefaultPredicate)
        skel_query = cache.GetSkelQuery(binding.GetSkeleton())
        (target,) = binding.GetSkinningTargets()
        for frame in (0, 5, FRAMES - 1):
            time = Usd.TimeCode(frame)
            points = UsdGeom.Mesh(target.GetPrim()).GetPointsAttr().Get()
            assert target.ComputeSkinnedPoints(skel_query.ComputeSkinningTransforms(time), points, time)
            err = np.linalg.norm(np.asarray(points, np.float64) - reference[frame], axis=1).max()
            assert err <= TOL_M, f"{path.name} frame {frame}: {err * 1e3:.4f} mm"
        print(f"UsdSkel vs BodyLayer.pose ({path.suffix}): last frame {err * 1e3:.4f} mm")


def test_usd_missing_says_how_to_install(motion, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "pxr", None)  # import pxr now raises ImportError
    with pytest.raises(ImportError, match=r"pip install 'unibody\[usd\]'"):
        write_usd(motion, tmp_path / "m.usda", OPTIONS)
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- mesh sequences


def test_meshes_round_trip(motion, reference, tmp_path):
    path = tmp_path / "meshes.npz"
    write_meshes(motion, path, OPTIONS)
    seq = load_mesh_sequence(path)
    assert seq.topology == "canonical" and seq.vertices.dtype == np.float32
    assert seq.vertices.shape == reference.shape
    np.testing.assert_allclose(seq.vertices, reference, atol=1e-6)
    np.testing.assert_array_equal(seq.identity, motion.identity)
    with np.load(path, allow_pickle=False) as data:
        assert float(data["fps"]) == FPS and str(data["identity_backend"]) == "pca"
        layer, _ = body_for(motion)
        np.testing.assert_array_equal(data["faces"], layer.faces.numpy())
    assert [p.name for p in tmp_path.iterdir()] == ["meshes.npz"]  # no temporary left behind


# ----------------------------------------------------------------------------- bad arguments


def _bad_motion(motion: Motion, **fields) -> Motion:
    kw = {"pose": motion.pose, "transl": motion.transl, "fps": motion.fps}
    return Motion(**(kw | fields))


def test_convert_options_are_checked_when_made():
    """A batch of 0, a preset "best" or a dtype "half" passed skeletal readers unseen (the batch
    was clamped, the others ignored) and failed elsewhere only when a path used them."""
    for kw, error, match in (
        ({"batch": 0}, ValueError, r"^batch: expected an integer >= 1, got 0$"),
        ({"batch": 2.5}, ValueError, r"^batch: expected an integer >= 1, got 2.5$"),
        ({"preset": "best"}, ValueError, r"^preset: expected one of fast, analytic, .*got 'best'$"),
        ({"dtype": "half"}, ValueError, r"^dtype: expected float32 or float64, got 'half'$"),
        ({"units": "furlong"}, ValueError, r"^units: expected one of m, cm, mm, in, ft or None"),
        ({"models": 3}, TypeError, r"^models: expected a path or None, got int$"),
    ):
        with pytest.raises(error, match=match):
            ConvertOptions(**kw)


def test_readers_and_writers_name_wrong_argument_types(motion, tmp_path):
    """Through convert.reader / writer (what `unibody convert` uses): options=None failed as
    "'NoneType' object has no attribute 'units'", a dict as "... 'dtype'"; write_bvh wrote a BVH
    into a .glb path."""
    from unibody.convert import reader, writer

    path = tmp_path / "m.motion.npz"
    writer("motion")(motion, path, OPTIONS)
    with pytest.raises(TypeError, match=r"^options: expected a ConvertOptions, got NoneType$"):
        reader("motion")(path, None)
    with pytest.raises(TypeError, match=r"^path: expected a file path, got int$"):
        reader("motion")(3, OPTIONS)
    with pytest.raises(TypeError, match=r"^options: expected a ConvertOptions, got dict$"):
        writer("bvh")(motion, tmp_path / "m.bvh", {"batch": 3})
    with pytest.raises(TypeError, match=r"^motion: expected a unibody.motion.Motion, got str$"):
        writer("bvh")("walk.npz", tmp_path / "m.bvh", OPTIONS)
    with pytest.raises(ValueError, match=r"^path: expected a \.bvh file, got '.*m\.glb'$"):
        writer("bvh")(motion, tmp_path / "m.glb", OPTIONS)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.motion.npz"]


@pytest.mark.parametrize(
    "writer, name, change, match",
    [
        (write_glb, "m.gltf", {}, r"^path: expected a \.glb file, got '.*m\.gltf'$"),
        (write_usd, "m.usdz", {}, r"^path: expected a \.usda or \.usdc or \.usd file"),
        (write_meshes, "m.npy", {}, r"^path: expected a \.npz file"),
        (write_glb, "m.glb", {"motion": "walk.npz"}, r"^motion: expected a unibody.motion.Motion, got str$"),
        (write_glb, "m.glb", {"options": {"batch": 4}}, r"^options: expected a ConvertOptions, got dict$"),
        (write_glb, "m.glb", {"pose": np.zeros((3, 76, 3), np.float32)}, r"^motion.pose: expected \(T, 77, 3\)"),
        (write_glb, "m.glb", {"pose": np.zeros((0, 77, 3), np.float32)}, r"^motion.pose: .*T >= 1"),
        (
            write_glb,
            "m.glb",
            {"nan_frame": 7},
            r"^motion.pose: expected finite values, got NaN/inf at frame\(s\) \[7\]$",
        ),
        (write_glb, "m.glb", {"transl": np.zeros((2, 3), np.float32)}, r"^motion.transl: expected \(11, 3\)"),
        (write_meshes, "m.npz", {"fps": 0.0}, r"^motion.fps: expected a positive"),
    ],
)
def test_bad_arguments(motion, tmp_path, writer, name, change, match):
    change = dict(change)
    options = change.pop("options", OPTIONS)
    if "motion" in change:
        m = change.pop("motion")
    elif "nan_frame" in change:
        pose = motion.pose.copy()
        pose[change.pop("nan_frame"), 3, 1] = np.nan
        m = _bad_motion(motion, pose=pose)
    else:
        m = _bad_motion(motion, **change)
    with pytest.raises(ValueError, match=match) as info:
        writer(m, tmp_path / name, options)
    assert "\n" not in str(info.value)
    assert list(tmp_path.iterdir()) == []
