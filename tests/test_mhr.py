"""MHR identity backend against files in MHR's converted format and a numpy reference."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import torch

from mhr_format import make_mhr_arrays, write_mhr_assets
from unibody.geometry.rotations import quat_xyzw_to_matrix
from unibody.identity.mhr import MHRIdentity, load_mhr_assets, momentum_euler_xyz_to_matrix

# --- independent reference: skeleton states (t, q xyzw, s) in numpy, centimetres --------------


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    x1, y1, z1, w1 = a
    x2, y2, z2, w2 = b
    return np.array(
        [
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        ]
    )


def _qrot(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    q = q / np.linalg.norm(q)
    u, w = q[:3], q[3]
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def _axis_quat(axis: int, angle: float) -> np.ndarray:
    q = np.zeros(4)
    q[axis], q[3] = np.sin(angle / 2), np.cos(angle / 2)
    return q


def _state_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a after b: t = t_a + s_a R_a t_b, q = q_a q_b, s = s_a s_b."""
    return np.concatenate([a[:3] + a[7] * _qrot(a[3:7], b[:3]), _qmul(a[3:7], b[3:7]), [a[7] * b[7]]])


def reference_rest_mesh(rig: dict, lod: dict, identity: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """MHR rest mesh (m) of one identity: blendshapes, scale-only model parameters, FK, LBS."""
    f = lambda k: np.asarray(rig[k], dtype=np.float64)  # noqa: E731
    rest = lod["base_shape"].astype(np.float64) + np.einsum("k,kvc->vc", identity, lod["shape_vectors"][:45])
    model = np.zeros(rig["parameter_transform"].shape[1])
    model[np.flatnonzero(rig["scaling_parameters"])] = scales
    jp = (f("parameter_transform") @ model).reshape(-1, 7)
    parents = rig["joint_parents"]
    world: dict[int, np.ndarray] = {}
    while len(world) < len(parents):
        for j, p in enumerate(parents):
            if j in world or (p >= 0 and p not in world):
                continue
            euler = _qmul(_axis_quat(2, jp[j, 5]), _qmul(_axis_quat(1, jp[j, 4]), _axis_quat(0, jp[j, 3])))
            local = np.concatenate([jp[j, :3] + f("joint_offsets")[j], _qmul(f("joint_prerotations")[j], euler)])
            local = np.concatenate([local, [2.0 ** jp[j, 6]]])
            world[j] = local if p < 0 else _state_mul(world[p], local)
    out = np.zeros_like(rest)
    for v in range(rest.shape[0]):
        for k, w in zip(lod["skin_indices"][v], lod["skin_weights"][v].astype(np.float64), strict=True):
            skin = _state_mul(world[int(k)], f("inverse_bind_pose")[k])
            out[v] += w * (skin[:3] + _qrot(skin[3:7], skin[7] * rest[v]))
    return out / 100.0


# --- fixtures ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def assets(tmp_path_factory) -> tuple[Path, dict, dict]:
    folder = tmp_path_factory.mktemp("mhr")
    rig, lod = write_mhr_assets(folder, seed=3)
    return folder, rig, lod


@pytest.fixture(scope="module")
def model64(assets) -> MHRIdentity:
    return MHRIdentity.from_files(assets[0], dtype=torch.float64)


def _random_params(model: MHRIdentity, batch: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    p = torch.randn(batch, model.num_params, generator=g, dtype=torch.float64)
    p[:, 45:] *= 0.4
    return p


# --- semantics -----------------------------------------------------------------------------------


def test_rest_mesh_matches_numpy_reference(assets, model64):
    _, rig, lod = assets
    params = _random_params(model64, 3, seed=0)
    ours = model64(params)
    for b in range(3):
        ref = reference_rest_mesh(rig, lod, params[b, :45].numpy(), params[b, 45:].numpy())
        assert np.abs(ours[b].numpy() - ref).max() < 1e-12
    assert (ours[0] - ours[1]).abs().max() > 1e-3  # the parameters do change the mesh


def test_zero_params_give_the_template(assets, dtype):
    folder, _, lod = assets
    base_m = torch.from_numpy(lod["base_shape"].astype(np.float64)) / 100
    model = MHRIdentity.from_files(folder, dtype=dtype)
    rest = model(model.default_params(2))
    # The inverse bind pose is stored in float32, so FK(0) * inverse bind is identity to ~1e-7.
    assert (rest.double() - base_m).abs().max() < 1e-6
    assert (model.template().double() - base_m).abs().max() < 1e-6


def test_momentum_euler_is_z_y_x():
    """Momentum's XYZ Euler angles: q = q_z q_y q_x (R = Rz Ry Rx), checked against quaternions."""
    angles = np.random.default_rng(0).uniform(-2.0, 2.0, size=(5, 3))
    for a in angles:
        q = _qmul(_axis_quat(2, a[2]), _qmul(_axis_quat(1, a[1]), _axis_quat(0, a[0])))
        ours = momentum_euler_xyz_to_matrix(torch.from_numpy(a))
        assert (ours - quat_xyzw_to_matrix(torch.from_numpy(q))).abs().max() < 1e-14


def test_units_are_metres_and_axes_unchanged(tmp_path):
    rig, lod = make_mhr_arrays(seed=5)
    lod["base_shape"][0] = (10.0, 170.0, 5.0)  # cm: MHR is Y up, facing +Z like unibody
    write_mhr_assets(tmp_path, rig, lod)
    model = MHRIdentity.from_files(tmp_path, dtype=torch.float64)
    assert torch.allclose(model.template()[0], torch.tensor([0.1, 1.7, 0.05], dtype=torch.float64), atol=1e-6)
    assets = load_mhr_assets(tmp_path)
    assert np.allclose(assets.offsets * 100, rig["joint_offsets"]) and np.allclose(
        assets.identity_dirs * 100, lod["shape_vectors"][:45]
    )


def test_identity_blendshapes_are_linear_in_metres(assets, model64):
    _, _, lod = assets
    p = model64.default_params(1)
    p[0, 7] = 2.0
    delta = model64(p)[0] - model64.template()  # carried by LBS at the (float32-stored) bind: ~1e-7 relative
    assert (delta - 2.0 * torch.from_numpy(lod["shape_vectors"][7].astype(np.float64)) / 100).abs().max() < 1e-8


def test_bone_scale_scales_about_the_joint(tmp_path):
    """A vertex skinned only to a leaf joint whose log2 scale is 1 doubles its offset from it."""
    rig, lod = make_mhr_arrays(seed=7, num_scales=2)
    parents = rig["joint_parents"]
    leaf = max(j for j in range(1, len(parents)) if j not in set(parents.tolist()))
    col = np.flatnonzero(rig["scaling_parameters"])[1]
    rig["parameter_transform"][:, col] = 0.0
    rig["parameter_transform"][7 * leaf + 6, col] = 1.0
    lod["skin_indices"][0] = 0
    lod["skin_indices"][0, 0], lod["skin_weights"][0] = leaf, 0.0
    lod["skin_weights"][0, 0] = 1.0
    write_mhr_assets(tmp_path, rig, lod)
    model = MHRIdentity.from_files(tmp_path, dtype=torch.float64)
    p = model.default_params(1)
    p[0, 46] = 1.0
    ibp = rig["inverse_bind_pose"][leaf].astype(np.float64)
    joint = torch.from_numpy(-_qrot(ibp[3:7] * [-1, -1, -1, 1], ibp[:3]) / ibp[7]) / 100  # world position
    rest, grown = model.template()[0], model(p)[0, 0]
    assert (grown - joint - 2.0 * (rest - joint)).abs().max() < 1e-6
    assert (model(p)[0, 1:] - model.template()[1:]).abs().max() > 0  # other vertices follow the bones


def test_joint_order_does_not_matter(assets, tmp_path):
    """Children listed before their parents give the same meshes (joints are reordered at load)."""
    folder, rig, lod = assets
    j = len(rig["joint_parents"])
    perm = np.arange(j)[::-1].copy()  # new index i holds old joint perm[i]
    inv = np.argsort(perm)
    rig2 = dict(rig)
    for k in ("joint_offsets", "joint_prerotations", "inverse_bind_pose", "joint_names"):
        rig2[k] = rig[k][perm]
    rig2["joint_parents"] = np.where(rig["joint_parents"][perm] < 0, -1, inv[rig["joint_parents"][perm]])
    rig2["parameter_transform"] = rig["parameter_transform"].reshape(j, 7, -1)[perm].reshape(7 * j, -1)
    lod2 = dict(lod, skin_indices=inv[lod["skin_indices"]].astype(np.int32))
    write_mhr_assets(tmp_path, rig2, lod2)
    a = MHRIdentity.from_files(folder, dtype=torch.float64)
    b = MHRIdentity.from_files(tmp_path, dtype=torch.float64)
    params = _random_params(a, 2, seed=4)
    assert (a(params) - b(params)).abs().max() < 1e-12


def test_batch_rows_are_independent_and_float32_agrees(assets, model64):
    params = _random_params(model64, 4, seed=1)
    full = model64(params)
    assert (model64(params[2:3])[0] - full[2]).abs().max() < 1e-13
    f32 = MHRIdentity.from_files(assets[0])(params.float())
    assert f32.dtype == torch.float32 and (f32.double() - full).abs().max() < 1e-5


def test_param_names_and_limits(assets, model64):
    _, rig, _ = assets
    cols = np.flatnonzero(rig["scaling_parameters"])
    assert model64.param_names[:3] == ("body_00", "body_01", "body_02")
    assert model64.param_names[40:45] == ("hands_0", "hands_1", "hands_2", "hands_3", "hands_4")
    assert model64.param_names[45:] == tuple(str(rig["parameter_names"][c]) for c in cols)
    assert model64.num_params == 45 + len(cols) == model64.default_params(2).shape[1]
    limits = model64.param_limits()
    assert limits.shape == (model64.num_params, 2) and torch.isinf(limits[:45]).all()
    assert torch.equal(limits[45:, 0], torch.full((len(cols),), -1.0, dtype=torch.float64))
    assert model64.faces().shape == (2 * model64.num_vertices, 3) and model64.faces().dtype == torch.long


def test_gradcheck(tmp_path):
    write_mhr_assets(tmp_path, seed=2, num_joints=5, num_vertices=12, num_scales=4, num_expression=2)
    model = MHRIdentity.from_files(tmp_path, dtype=torch.float64)
    params = (0.3 * _random_params(model, 2, seed=2)).requires_grad_(True)
    assert torch.autograd.gradcheck(model, (params,), eps=1e-6, atol=1e-8)


# --- errors ----------------------------------------------------------------------------------------


def test_bad_params_raise(model64):
    with pytest.raises(ValueError, match=r"identity params: expected shape \(B, 51\), got \(2, 50\)"):
        model64(torch.zeros(2, 50, dtype=torch.float64))
    with pytest.raises(TypeError, match=r"identity params: is float32 on cpu but the MHR backend is float64"):
        model64(torch.zeros(1, 51))
    bad = model64.default_params(1)
    bad[0, 3] = float("nan")
    with pytest.raises(ValueError, match="identity params: expected finite values, got 1 NaN/inf"):
        model64(bad)


def test_missing_files_are_named(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"rig\.npz is missing; expected MHR converted assets"):
        MHRIdentity.from_files(tmp_path)
    (tmp_path / "lod1.fbx").write_bytes(b"Kaydara FBX Binary")
    with pytest.raises(FileNotFoundError, match=r"holds the FBX release .*convert_assets\.py"):
        MHRIdentity.from_files(tmp_path)
    write_mhr_assets(tmp_path, seed=0)
    with pytest.raises(FileNotFoundError, match=r"lod3\.npz is missing"):
        MHRIdentity.from_files(tmp_path, lod=3)
    with pytest.raises(ValueError, match=r"lod: expected an integer in 0\.\.6, got 9"):
        MHRIdentity.from_files(tmp_path, lod=9)


@pytest.mark.parametrize(
    ("file", "edit", "message"),
    [
        ("rig", lambda r: r.pop("inverse_bind_pose"), r"rig\.npz: missing array\(s\) 'inverse_bind_pose'"),
        ("lod", lambda d: d.pop("skin_weights"), r"lod1\.npz: missing array\(s\) 'skin_weights'"),
        ("rig", lambda r: r.update(schema_version=np.array(2)), r"schema_version \[2\] is not supported"),
        ("lod", lambda d: d.update(lod=np.array(2)), r"lod1\.npz: holds LOD 2, expected 1"),
        (
            "rig",
            lambda r: r.update(joint_offsets=r["joint_offsets"][:-1]),
            r"'joint_offsets' expected shape \(8, 3\), got \(7, 3\)",
        ),
        (
            "lod",
            lambda d: d.update(shape_vectors=d["shape_vectors"][:30]),
            r"'shape_vectors' has 30 shapes, expected >= 45",
        ),
        ("lod", lambda d: d["base_shape"].__setitem__((3, 1), np.nan), r"'base_shape' holds NaN/inf"),
        ("lod", lambda d: d["skin_indices"].__setitem__((0, 0), 99), r"'skin_indices' index out of range \[0, 8\)"),
        ("lod", lambda d: d["faces"].__setitem__((0, 0), -1), r"'faces' index out of range"),
        (
            "rig",
            lambda r: r["joint_parents"].__setitem__(0, 3),
            r"rig\.npz: 'joint_parents': the hierarchy has a cycle",
        ),
    ],
)
def test_bad_files_raise(tmp_path, file, edit, message):
    rig, lod = make_mhr_arrays(seed=0)
    edit(rig if file == "rig" else lod)
    write_mhr_assets(tmp_path, rig, lod, file_lod=1)
    with pytest.raises(ValueError, match=message):
        MHRIdentity.from_files(tmp_path)


def test_unreadable_file_raises(tmp_path):
    write_mhr_assets(tmp_path, seed=0)
    (tmp_path / "rig.npz").write_bytes(b"not a zip archive")
    with pytest.raises(ValueError, match=r"rig\.npz: not a readable \.npz file"):
        MHRIdentity.from_files(tmp_path)


# --- real files ------------------------------------------------------------------------------------


@pytest.mark.licensed
@pytest.mark.skipif(not os.environ.get("UNIBODY_MHR_DIR"), reason="set UNIBODY_MHR_DIR to MHR converted assets")
def test_real_mhr_assets_load():
    model = MHRIdentity.from_files(os.environ["UNIBODY_MHR_DIR"], lod=1)
    assert model.num_params == 45 + model.num_scales and model.num_scales > 0
    rest = model.template()
    extent = rest.amax(0) - rest.amin(0)
    assert 1.2 < float(extent[1]) < 2.3 and int(extent.argmax()) in (0, 1)  # metres, Y up (arms may span X)
    assert int(model.faces().max()) < model.num_vertices
    params = model.default_params(2)
    params[0, :45] = 1.0
    params[1, 45:] = 0.2
    out = model(params)
    assert torch.isfinite(out).all() and (out[0] - rest).abs().max() > 1e-3 and (out[1] - rest).abs().max() > 1e-3


def test_implements_the_identity_backend_protocol(model64):
    import math

    from unibody.identity.base import IdentityBackend, missing_members

    assert isinstance(model64, IdentityBackend) and missing_members(model64) == []
    lo, hi = model64.param_bounds
    limits = model64.param_limits()
    assert lo.shape == hi.shape == (model64.num_params,) and lo.dtype == torch.float64
    assert torch.equal(lo, limits[:, 0]) and torch.equal(hi, limits[:, 1])
    assert bool((lo[:45] == -math.inf).all() & (hi[:45] == math.inf).all())  # identity coefficients
    assert bool(torch.isfinite(lo[45:]).all() & (lo[45:] < hi[45:]).all())  # bone scales: the file's limits
