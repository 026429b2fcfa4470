"""GarmentMeasurements identity backend against files in the upstream formats."""

from __future__ import annotations

import os
import struct

import numpy as np
import pytest
import torch

from garment_format import make_garment_arrays, write_garment_assets, write_point_pca
from unibody.identity.garment import GarmentIdentity, load_garment_pca


def _reference(path, coeffs: np.ndarray) -> np.ndarray:
    """Parse point.pca with struct and evaluate mean + M (c * sqrt(eig)) by explicit indexing."""
    raw = open(path, "rb").read()
    m, n = struct.unpack("<II", raw[:8])
    vals = struct.unpack(f"<{m * n + m + n}d", raw[8:])
    col = lambda k: np.array(vals[k * m : (k + 1) * m])  # noqa: E731 - Eigen column-major: column k
    mean = np.array(vals[m * n : m * n + m])
    eig = np.array(vals[m * n + m :])
    flat = mean + sum(col(k) * coeffs[k] * np.sqrt(eig[k]) for k in range(n))
    return np.stack([flat[0::3], flat[1::3], flat[2::3]], axis=1)  # x, y, z interleaved per vertex


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    path = tmp_path_factory.mktemp("garment")
    write_garment_assets(path, seed=1)
    return path


@pytest.fixture(scope="module")
def model64(folder) -> GarmentIdentity:
    return GarmentIdentity.from_files(folder, dtype=torch.float64)


def test_rest_mesh_matches_the_upstream_evaluation(folder, model64):
    params = torch.from_numpy(np.random.default_rng(0).normal(size=(3, model64.num_params)))
    ours = model64(params)
    for b in range(3):
        assert np.abs(ours[b].numpy() - _reference(folder / "point.pca", params[b].numpy())).max() < 1e-12
    assert (ours[0] - ours[1]).abs().max() > 1e-3


def test_npz_conversion_gives_the_same_model(folder, model64, tmp_path):
    write_garment_assets(tmp_path, seed=1, npz=True)
    other = GarmentIdentity.from_files(tmp_path, dtype=torch.float64)
    params = torch.randn(2, model64.num_params, dtype=torch.float64)
    assert torch.equal(other(params), model64(params)) and torch.equal(other.faces(), model64.faces())
    same = GarmentIdentity.from_file(tmp_path / "point.npz", folder / "mean.obj", dtype=torch.float64)
    assert torch.equal(same(params), model64(params))


def test_zero_params_give_the_mean_in_metres_unchanged_axes(tmp_path, dtype):
    arrays = make_garment_arrays(seed=2)
    arrays["mean"][:3] = (0.1, 1.7, 0.05)  # metres, Y up, facing +Z, like unibody: no conversion
    write_garment_assets(tmp_path, arrays)
    model = GarmentIdentity.from_files(tmp_path, dtype=dtype)
    rest = model(model.default_params(2))
    mean = torch.from_numpy(arrays["mean"].reshape(-1, 3)).to(dtype)
    assert torch.equal(rest[1], mean) and torch.equal(model.template(), mean)
    assert rest.dtype == dtype and torch.equal(rest[0, 0], torch.tensor([0.1, 1.7, 0.05], dtype=dtype))


def test_coefficients_are_in_standard_deviations(tmp_path):
    """Component k moves the mesh by c sqrt(eig_k) along its unit direction; tiny eigenvalues use |eig|."""
    arrays = make_garment_arrays(seed=3, num_components=4)
    arrays["eigenvalues"][2:] = (1e-15, -1e-14)
    arrays["mean"][:] = 0.0  # so that offsets of 1e-15 are not lost against the mean
    write_garment_assets(tmp_path, arrays)
    model = GarmentIdentity.from_files(tmp_path, dtype=torch.float64)
    for k, sigma in enumerate([np.sqrt(0.02), np.sqrt(0.01), 1e-15, 1e-14]):
        p = model.default_params(1)
        p[0, k] = 2.0
        delta = (model(p)[0] - model.template()).reshape(-1).numpy()
        assert np.allclose(delta, 2.0 * sigma * arrays["matrix"][:, k], rtol=1e-12, atol=1e-300)


def test_layout_is_column_major_and_vertex_interleaved(tmp_path):
    arrays = make_garment_arrays(seed=4, num_components=2)
    v = arrays["mean"].size // 3
    arrays["matrix"][:] = 0.0
    arrays["matrix"][1::3, 0] = 1.0 / np.sqrt(v)  # component 0 lifts every vertex along +Y
    write_garment_assets(tmp_path, arrays)
    model = GarmentIdentity.from_files(tmp_path, dtype=torch.float64)
    p = model.default_params(1)
    p[0, 0] = 1.0
    delta = model(p)[0] - model.template()
    assert torch.allclose(delta[:, 1], torch.full((v,), np.sqrt(0.02 / v), dtype=torch.float64))
    assert delta[:, [0, 2]].abs().max() == 0


def test_loaded_arrays(folder):
    pca = load_garment_pca(folder)
    assert pca.mean.shape == (30, 3) and pca.components.shape == (15, 30, 3) and pca.faces.shape == (50, 3)
    gram = np.einsum("avc,bvc->ab", pca.components, pca.components)
    assert np.abs(gram - np.eye(15)).max() < 1e-12  # the columns of the upstream matrix are orthonormal


def test_interface(model64):
    assert model64.name == "garment" and model64.num_params == 15
    assert model64.param_names[:2] == ("pc_00", "pc_01") and model64.default_params(3).shape == (3, 15)
    faces = model64.faces()
    assert faces.dtype == torch.long and faces.shape[1] == 3 and int(faces.max()) < model64.num_vertices == 30


def test_gradcheck(folder):
    model = GarmentIdentity.from_files(folder, dtype=torch.float64)
    params = torch.randn(2, model.num_params, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(model, (params,), eps=1e-6, atol=1e-8)


def test_bad_params_raise(model64):
    with pytest.raises(ValueError, match=r"identity params: expected shape \(B, 15\), got \(2, 14\)"):
        model64(torch.zeros(2, 14, dtype=torch.float64))
    with pytest.raises(TypeError, match="is float32 on cpu but the GarmentMeasurements backend is float64"):
        model64(torch.zeros(1, 15))
    with pytest.raises(ValueError, match="identity params: expected finite values, got 1 NaN/inf"):
        model64(torch.tensor([[float("inf")] + [0.0] * 14], dtype=torch.float64))


def test_missing_files_raise(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"neither .*point\.pca nor .*point\.npz exists"):
        GarmentIdentity.from_files(tmp_path)
    arrays = write_garment_assets(tmp_path, seed=0)
    (tmp_path / "mean.obj").unlink()
    with pytest.raises(FileNotFoundError, match=r"mean\.obj is missing \(needed for the triangles\)"):
        GarmentIdentity.from_files(tmp_path)
    with pytest.raises(FileNotFoundError, match=r"nothere\.pca is missing"):
        GarmentIdentity.from_file(tmp_path / "nothere.pca", tmp_path / "mean.obj")
    assert arrays["faces"].shape[1] == 3


def test_malformed_pca_raises(tmp_path):
    arrays = write_garment_assets(tmp_path, seed=0)
    raw = (tmp_path / "point.pca").read_bytes()
    (tmp_path / "point.pca").write_bytes(raw[:-8])
    with pytest.raises(ValueError, match=r"header says m=90, n=15 \(expected 11648 bytes.*file has 11640 bytes"):
        GarmentIdentity.from_files(tmp_path)
    (tmp_path / "point.pca").write_bytes(raw[:5])
    with pytest.raises(ValueError, match="too short for the"):
        GarmentIdentity.from_files(tmp_path)
    bad = dict(arrays, mean=arrays["mean"][:-1], matrix=arrays["matrix"][:-1])
    write_point_pca(tmp_path / "point.pca", bad["matrix"], bad["mean"], bad["eigenvalues"])
    with pytest.raises(ValueError, match="dimension 89 is not 3 x vertices"):
        GarmentIdentity.from_files(tmp_path)
    nan = dict(arrays, eigenvalues=arrays["eigenvalues"].copy())
    nan["eigenvalues"][3] = np.nan
    write_point_pca(tmp_path / "point.pca", nan["matrix"], nan["mean"], nan["eigenvalues"])
    with pytest.raises(ValueError, match="eigenvalues holds NaN/inf"):
        GarmentIdentity.from_files(tmp_path)


def test_mesh_must_match_the_pca(tmp_path):
    arrays = make_garment_arrays(seed=0)
    write_garment_assets(tmp_path, arrays)
    other = make_garment_arrays(seed=0, rings=5)
    write_garment_assets(tmp_path / "other", other)
    with pytest.raises(ValueError, match=r"mean\.obj: 25 vertices, but the PCA .*point\.pca has 30"):
        GarmentIdentity.from_file(tmp_path / "point.pca", tmp_path / "other" / "mean.obj")


def test_malformed_npz_raises(tmp_path):
    arrays = make_garment_arrays(seed=0)
    write_garment_assets(tmp_path, arrays, npz=True)
    np.savez(tmp_path / "point.npz", pca_matrix=arrays["matrix"], pca_mean=arrays["mean"])
    with pytest.raises(ValueError, match=r"point\.npz: missing array\(s\) 'eigenvalues'"):
        GarmentIdentity.from_files(tmp_path)
    np.savez(tmp_path / "point.npz", pca_matrix=arrays["matrix"], pca_mean=arrays["mean"][:-3], eigenvalues=[1.0])
    with pytest.raises(ValueError, match=r"expected pca_matrix \(3V, K\), pca_mean \(3V,\), eigenvalues \(K,\)"):
        GarmentIdentity.from_files(tmp_path)
    (tmp_path / "point.npz").write_bytes(b"garbage")
    with pytest.raises(ValueError, match=r"point\.npz: not a readable \.npz file"):
        GarmentIdentity.from_files(tmp_path)


@pytest.mark.licensed
@pytest.mark.skipif(
    not os.environ.get("UNIBODY_GARMENT_DIR"), reason="set UNIBODY_GARMENT_DIR to a folder with point.pca + mean.obj"
)
def test_real_garment_assets_load():
    model = GarmentIdentity.from_files(os.environ["UNIBODY_GARMENT_DIR"])
    rest = model.template()
    extent = rest.amax(0) - rest.amin(0)
    assert 1.2 < float(extent[1]) < 2.3 and int(extent.argmax()) in (0, 1)  # metres, Y up
    assert int(model.faces().max()) < model.num_vertices and model.num_params >= 10
    params = model.default_params(2)
    params[1, 0] = 2.0
    out = model(params)
    assert torch.isfinite(out).all() and (out[1] - rest).abs().max() > 1e-3


def test_implements_the_identity_backend_protocol(model64):
    from unibody.identity.base import IdentityBackend, missing_members

    assert isinstance(model64, IdentityBackend) and missing_members(model64) == []
    assert model64.param_bounds is None  # any finite coefficient is a body of the linear model
    assert torch.equal(model64.template(), model64(model64.default_params())[0])
