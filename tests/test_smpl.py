"""SMPL-family identity backend on generated official-format files (and real ones when supplied)."""

from __future__ import annotations

import os
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch

from smpl_format import SIZES, dumps, make_model, real_template, write_npz, write_pkl
from unibody.identity.smpl import FAMILIES, SMPLIdentity, gender_from_path, shape_columns

TOL = {torch.float32: 2e-6, torch.float64: 1e-12}
FORMATS = {
    "npz": lambda path, m: write_npz(path.with_suffix(".npz"), m),
    "npz-object-regressor": lambda path, m: write_npz(path.with_suffix(".npz"), m, object_keys=("J_regressor",)),
    "pkl-p2-plain": lambda path, m: write_pkl(path.with_suffix(".pkl"), m),
    "pkl-p0-chumpy": lambda path, m: write_pkl(path.with_suffix(".pkl"), m, protocol=0, chumpy=True),
    "pkl-p2-chumpy": lambda path, m: write_pkl(path.with_suffix(".pkl"), m, chumpy=True),
    "pkl-p2-select": lambda path, m: write_pkl(path.with_suffix(".pkl"), m, chumpy=True, select_shapedirs=True),
    "pkl-p4-modern": lambda path, m: write_pkl(path.with_suffix(".pkl"), m, protocol=4, chumpy=True, legacy=False),
}


@pytest.fixture(scope="module")
def models():
    return {family: make_model(family, seed=i) for i, family in enumerate(SIZES)}


@pytest.fixture(scope="module")
def smpl_files(models, tmp_path_factory):
    """One SMPL file per format: (model arrays, {format: path})."""
    folder = tmp_path_factory.mktemp("smpl")
    return models["smpl"], {name: write(folder / f"SMPL_NEUTRAL_{i}", models["smpl"]) for i, (name, write) in
                             enumerate(FORMATS.items())}  # fmt: skip


def _expected(model, betas):
    """v_template + shapedirs @ betas in numpy float64, independent of the module."""
    k = betas.shape[1]
    return model["v_template"][None] + np.einsum("vck,bk->bvc", model["shapedirs"][:, :, :k], betas)


@pytest.mark.parametrize("family", list(SIZES))
@pytest.mark.parametrize("fmt", ["npz", "pkl-p2-chumpy"])
def test_rest_mesh_is_template_plus_blend_shapes(family, fmt, dtype, models, tmp_path):
    model = models[family]
    path = FORMATS[fmt](tmp_path / f"{family.upper()}_MALE", model)
    layer = SMPLIdentity.from_file(path, dtype=dtype)
    assert layer.name == family and layer.gender == "male"
    assert (layer.num_vertices, layer.num_joints) == SIZES[family][:2]
    betas = np.random.default_rng(7).normal(size=(3, layer.num_params)) * 2
    rest = layer(torch.from_numpy(betas).to(dtype))
    assert rest.dtype == dtype and rest.shape == (3, layer.num_vertices, 3)
    assert np.abs(rest.numpy() - _expected(model, betas)).max() < TOL[dtype]
    zero = layer(layer.default_params(2))
    assert torch.equal(zero[1], layer.template()) and torch.equal(zero[0], zero[1])
    assert np.array_equal(layer.faces().numpy(), model["f"].astype(np.int64))
    joints = layer.rest_joints(rest)
    assert np.abs(joints.numpy() - np.einsum("jv,bvc->bjc", model["J_regressor"], rest.numpy())).max() < TOL[dtype]


def test_every_format_loads_the_same_arrays(smpl_files):
    model, paths = smpl_files
    layers = {name: SMPLIdentity.from_file(p, dtype=torch.float64) for name, p in paths.items()}
    parents = (-1, *model["kintree_table"][0, 1:].tolist())
    for name, layer in layers.items():
        assert np.array_equal(layer.v_template.numpy(), model["v_template"]), name
        assert np.array_equal(layer.shapedirs.numpy(), model["shapedirs"]), name
        assert np.array_equal(layer.joint_regressor.numpy(), model["J_regressor"]), name
        assert np.array_equal(layer.faces().numpy(), model["f"]), name
        assert layer.parents == parents and layer.gender == "neutral", name


def test_family_detection_and_shape_columns(models):
    assert FAMILIES == {(6890, 24): "smpl", (6890, 52): "smplh", (10475, 55): "smplx"}
    args = {f: (m["v_template"], m["shapedirs"], m["f"], m["J_regressor"], _parents(m)) for f, m in models.items()}
    assert [SMPLIdentity(*a).num_params for a in args.values()] == [10, 16, 10]  # SMPL-X v1.0: 10 shape + 10 expr.
    assert shape_columns("smplx", 400) == 300 and shape_columns("smplx", 20) == 10
    assert shape_columns("smpl", 300) == 300 and shape_columns("smplh", 16) == 16
    v, _, f, reg, parents = args["smplx"]
    wide = np.random.default_rng(0).standard_normal((10475, 3, 400), dtype=np.float32)
    layer = SMPLIdentity(v, wide, f, reg, parents)
    assert layer.name == "smplx" and layer.num_params == 300 and layer.shapedirs.shape == (10475, 3, 300)
    assert layer.param_names[0] == "beta0" and layer.param_names[-1] == "beta299"
    betas = torch.zeros(1, 300)
    betas[0, 299] = 1.0  # the last shape column, never an expression column
    assert torch.allclose(layer(betas)[0] - layer.template(), torch.from_numpy(wide[:, :, 299]), atol=1e-6)


def _parents(model):
    return np.concatenate([[-1], model["kintree_table"][0, 1:]])


@pytest.mark.parametrize(
    ("name", "gender"),
    [
        ("SMPL_NEUTRAL.pkl", "neutral"),
        ("SMPLX_FEMALE.npz", "female"),
        ("SMPLX_NEUTRAL_2020.npz", "neutral"),
        ("SMPLH_male.pkl", "male"),
        ("basicModel_f_lbs_10_207_0_v1.0.0.pkl", "female"),
        ("basicmodel_m_lbs_10_207_0_v1.1.0.pkl", "male"),
        ("basicModel_neutral_lbs_10_207_0_v1.0.0.pkl", "neutral"),
        ("smplh/female/model.npz", "female"),
        ("model.npz", "unknown"),
        ("MANO_RIGHT.pkl", "unknown"),
        ("smpl_f_male.pkl", "male"),  # single letters count only in SMPL 1.0 names
        ("male_female.pkl", "unknown"),
    ],
)
def test_gender_from_path(name, gender):
    assert gender_from_path(Path("/models") / name) == gender


def test_gender_override_and_num_betas(smpl_files):
    model, paths = smpl_files
    layer = SMPLIdentity.from_file(paths["npz"], num_betas=4, gender="female", dtype=torch.float64)
    assert layer.gender == "female" and layer.num_params == 4 and layer.shapedirs.shape[-1] == 4
    assert layer.param_names == ("beta0", "beta1", "beta2", "beta3") and layer.num_shape_columns == 10
    betas = np.random.default_rng(1).normal(size=(2, 4))
    assert np.abs(layer(torch.from_numpy(betas)).numpy() - _expected(model, betas)).max() < 1e-12
    assert "name=smpl, gender=female" in repr(layer)


def test_gradcheck_betas(smpl_files):
    _, paths = smpl_files
    layer = SMPLIdentity.from_file(paths["npz"], num_betas=3, dtype=torch.float64)
    betas = torch.randn(2, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(layer, (betas,), fast_mode=True)
    grad = torch.autograd.grad(layer(betas)[1, 5, 2], betas)[0]
    assert torch.equal(grad[1], layer.shapedirs[5, 2]) and not grad[0].any()


def test_dtype_and_device_follow_the_module(smpl_files):
    _, paths = smpl_files
    layer = SMPLIdentity.from_file(paths["npz"])
    assert layer.v_template.dtype == torch.float32 and layer.faces().dtype == torch.int64
    layer = layer.double()
    assert layer(torch.zeros(1, 10, dtype=torch.float64)).dtype == torch.float64
    assert layer.state_dict() == {}  # licensed arrays never reach checkpoints


def test_real_template_is_metres_y_up_facing_plus_z():
    """The CC BY 4.0 SMPL-topology body: our frame is SMPL's (no conversion needed)."""
    mesh = real_template(6890)
    if mesh is None:
        pytest.skip("evaluation meshes not present ($UNIBODY_EVALDATA)")
    v, f = mesh
    model = make_model("smpl")
    layer = SMPLIdentity(v, model["shapedirs"], f, model["J_regressor"], _parents(model), dtype=torch.float64)
    rest = layer.template().numpy()
    height = rest[:, 1].max() - rest[:, 1].min()
    assert 1.6 < height < 2.0  # metres, Y up: the tallest extent
    assert np.ptp(rest[:, 0]) > np.ptp(rest[:, 2]) * 3  # T-pose arms span X
    feet = rest[rest[:, 1] < rest[:, 1].min() + 0.05]
    assert feet[:, 2].max() > 1.5 * -feet[:, 2].min()  # toes point to +Z: the body faces +Z


# --- errors ---------------------------------------------------------------------------------------------------


def test_file_errors(tmp_path, models):
    model = models["smpl"]
    with pytest.raises(FileNotFoundError, match="no SMPL-family model file"):
        SMPLIdentity.from_file(tmp_path / "SMPL_NEUTRAL.pkl")
    (tmp_path / "SMPL.obj").write_text("v 0 0 0\n")
    with pytest.raises(ValueError, match=r"expected a \.npz or \.pkl .* got 'SMPL\.obj'"):
        SMPLIdentity.from_file(tmp_path / "SMPL.obj")
    for key in ("shapedirs", "kintree_table"):
        partial = {k: v for k, v in model.items() if k != key}
        for path in (write_npz(tmp_path / "a.npz", partial), write_pkl(tmp_path / "a.pkl", partial)):
            with pytest.raises(ValueError, match=rf"{path.name}: missing key '{key}'"):
                SMPLIdentity.from_file(path)
    (tmp_path / "b.pkl").write_bytes(dumps([1, 2]))
    with pytest.raises(ValueError, match=r"b\.pkl: expected a pickled dict"):
        SMPLIdentity.from_file(tmp_path / "b.pkl")
    (tmp_path / "c.npz").write_bytes(dumps(model))  # a pickle disguised as npz is never unpickled
    with pytest.raises(ValueError, match=r"c\.npz: not a readable \.npz archive"):
        SMPLIdentity.from_file(tmp_path / "c.npz")
    np.save(tmp_path / "d.npy", np.zeros(3))
    (tmp_path / "d.npy").rename(tmp_path / "d.npz")
    with pytest.raises(ValueError, match=r"d\.npz: not an \.npz archive"):
        SMPLIdentity.from_file(tmp_path / "d.npz")
    (tmp_path / "e.pkl").write_bytes(b"cos\nsystem\n(S'true'\ntR.")
    with pytest.raises(pickle.UnpicklingError, match=r"e\.pkl: refusing global os\.system"):
        SMPLIdentity.from_file(tmp_path / "e.pkl")
    text = write_npz(tmp_path / "f.npz", {**model, "shapedirs": np.array(["a", "b"])})
    with pytest.raises(ValueError, match=r"f\.npz: shapedirs: expected a numeric array"):
        SMPLIdentity.from_file(text)
    kintree = write_npz(tmp_path / "g.npz", {**model, "kintree_table": model["kintree_table"][:1]})
    with pytest.raises(ValueError, match=r"g\.npz: kintree_table: expected integer shape \(2, J\)"):
        SMPLIdentity.from_file(kintree)
    bad = write_npz(tmp_path / "h.npz", {**model, "J_regressor": model["J_regressor"][:, :100]})
    with pytest.raises(ValueError, match=r"h\.npz: joint_regressor \(key 'J_regressor'\): expected shape \(\?, 6890\)"):
        SMPLIdentity.from_file(bad)
    with pytest.raises(ValueError, match=r"SMPL_NEUTRAL_\d\.npz: gender: expected one of"):
        SMPLIdentity.from_file(write_npz(tmp_path / "SMPL_NEUTRAL_0.npz", model), gender="woman")


def _args(model, **changes):
    args = {
        "v_template": model["v_template"],
        "shapedirs": model["shapedirs"],
        "faces": model["f"],
        "joint_regressor": model["J_regressor"],
        "parents": _parents(model),
    }
    return {**args, **changes}


@pytest.mark.parametrize(
    ("change", "error", "match"),
    [
        (
            {"v_template": [[0.0, 0.0, 0.0]]},
            TypeError,
            r"v_template: expected a numpy array or torch\.Tensor, got list",
        ),
        ({"v_template": np.zeros((6890, 2))}, ValueError, r"v_template: expected shape \(\?, 3\), got \(6890, 2\)"),
        ({"shapedirs": np.zeros((6890, 30))}, ValueError, r"shapedirs: expected shape \(6890, 3, \?\)"),
        ({"shapedirs": np.zeros((6890, 3, 0))}, ValueError, "at least one shape column"),
        ({"shapedirs": np.full((6890, 3, 2), np.nan)}, ValueError, "shapedirs: expected finite values"),
        ({"faces": np.zeros((5, 3))}, TypeError, r"faces \(key 'f'\): expected integer values"),
        ({"faces": np.full((5, 3), 6890)}, ValueError, r"expected vertex ids in \[0, 6890\)"),
        (
            {"joint_regressor": np.zeros((30, 6890)), "parents": np.array([-1] + [0] * 29)},
            ValueError,
            "6890 vertices and 30 joints match no SMPL-family model",
        ),
        ({"parents": np.arange(24)}, ValueError, "parents: expected -1 for the root"),
        ({"parents": np.zeros(23, dtype=np.int64)}, ValueError, r"parents: expected shape \(24,\), got \(23,\)"),
        ({"num_betas": 11}, ValueError, r"num_betas: expected an int in \[1, 10\] for this smpl model, got 11"),
        ({"num_betas": 0}, ValueError, "num_betas: expected an int"),
        ({"num_betas": True}, ValueError, "num_betas: expected an int"),
        ({"gender": "f"}, ValueError, "gender: expected one of neutral, male, female, unknown"),
        ({"dtype": torch.int32}, TypeError, "dtype: expected a floating dtype"),
    ],
)
def test_constructor_errors(models, change, error, match):
    with pytest.raises(error, match=match):
        SMPLIdentity(**_args(models["smpl"], **change))


def test_forward_errors(smpl_files):
    _, paths = smpl_files
    layer = SMPLIdentity.from_file(paths["npz"])
    with pytest.raises(ValueError, match=r"betas: expected shape \(B, 10\), got \(2, 9\)"):
        layer(torch.zeros(2, 9))
    with pytest.raises(ValueError, match=r"betas: expected shape \(B, 10\), got \(10,\)"):
        layer(torch.zeros(10))
    with pytest.raises(TypeError, match="betas: is float64 on cpu but the SMPL backend is float32"):
        layer(torch.zeros(1, 10, dtype=torch.float64))
    with pytest.raises(TypeError, match="betas: is int64"):
        layer(torch.zeros(1, 10, dtype=torch.int64))
    with pytest.raises(TypeError, match="betas: expected a torch.Tensor, got ndarray"):
        layer(np.zeros((1, 10), dtype=np.float32))
    with pytest.raises(ValueError, match="betas: expected finite values, got 1 NaN/inf"):
        layer(torch.tensor([[float("nan")] + [0.0] * 9]))
    with pytest.raises(ValueError, match=r"vertices: expected shape \(B, 6890, 3\)"):
        layer.rest_joints(torch.zeros(1, 100, 3))
    with pytest.raises(ValueError, match="batch: expected a positive int, got 0"):
        layer.default_params(0)


# --- real licensed files ------------------------------------------------------------------------------------------


def _licensed_files():
    folder = os.environ.get("UNIBODY_SMPL_DIR")
    if not folder:
        return []
    return sorted(p for p in Path(folder).rglob("*") if p.suffix.lower() in (".pkl", ".npz") and p.is_file())


@pytest.mark.licensed
def test_real_model_files_load():
    files = _licensed_files()
    if not files:
        pytest.skip("set UNIBODY_SMPL_DIR to a folder with official SMPL / SMPL-H / SMPL-X .pkl or .npz files")
    loaded = 0
    for path in files:
        if "mano" in path.name.lower():  # MANO hands: same file format, not a body family
            continue
        try:
            layer = SMPLIdentity.from_file(path, dtype=torch.float64)
        except ValueError as e:  # a side file in the folder (regressors, landmarks...), not a model
            if "missing key" in str(e) or "expected a pickled dict" in str(e):
                continue
            raise
        loaded += 1
        rest = layer(layer.default_params(1))[0]
        height = float(rest[:, 1].max() - rest[:, 1].min())
        assert 1.2 < height < 2.2, f"{path}: rest height {height:.2f} m"
        joints = layer.rest_joints(rest[None])[0]
        assert torch.isfinite(joints).all() and layer.parents[0] == -1
        betas = torch.zeros(1, layer.num_params, dtype=torch.float64)
        betas[0, 0] = 2.0
        assert (layer(betas)[0] - rest).abs().max() > 1e-3, f"{path}: beta0 does not change the shape"
    assert loaded, f"no SMPL-family files among {files}"


def test_implements_the_identity_backend_protocol(smpl_files):
    from unibody.identity.base import IdentityBackend, missing_members

    _, paths = smpl_files
    model = SMPLIdentity.from_file(paths["npz"])
    assert isinstance(model, IdentityBackend) and missing_members(model) == []
    assert model.param_bounds is None  # betas are unbounded
    assert torch.equal(model.template(), model(model.default_params())[0])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_posed_forward_of_no_pose_is_empty(tmp_path, dtype):
    """A batch of 0 poses gives 0 meshes (it failed as "cannot reshape tensor of 0 elements")."""
    from unibody.identity.smpl_model import SMPLModel

    model = SMPLModel.from_file(write_npz(tmp_path / "SMPL_NEUTRAL.npz", make_model("smpl", oracle=True)), dtype=dtype)
    out = model(torch.zeros(0, model.num_joints, 3, dtype=dtype), transl=torch.zeros(0, 3, dtype=dtype))
    assert out.vertices.shape == (0, model.num_vertices, 3) and out.joints.shape == (0, model.num_joints, 3)
