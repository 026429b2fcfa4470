"""Native PCA shape space: the shipped asset, the backend, the incremental fit, the build script."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from unibody import BodyLayer
from unibody.geometry.kinematics import relative_to_parent
from unibody.identity.pca import (
    IPCAState,
    PCAIdentity,
    default_asset_path,
    ipca_finalize,
    ipca_init,
    ipca_update,
    read_asset,
    write_asset,
)
from unibody.symmetry import mirror

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def pca64() -> PCAIdentity:
    return PCAIdentity.from_asset(dtype=torch.float64)


@pytest.fixture(scope="module")
def raw():
    with np.load(default_asset_path(), allow_pickle=False) as data:
        return {k: data[k] for k in data.files}


# --------------------------------------------------------------------------- the shipped asset


def test_asset_format(raw):
    assert int(raw["format_version"]) == 1
    assert raw["mean"].dtype == np.float32 and raw["mean"].shape == (18056, 3)
    assert raw["components"].dtype == np.float16 and raw["components"].shape == (128, 18056, 3)
    assert raw["std"].dtype == np.float32 and raw["std"].shape == (128,)
    assert raw["components_lo"].dtype == np.float16 and raw["components_lo"].shape == (1, 18056, 3)
    std = raw["std"]
    assert (std > 0).all() and (np.diff(std) <= 0).all()
    meta = json.loads(str(raw["metadata"]))
    for key in ("command", "seed", "identities", "samples", "recipe"):
        assert key in meta
    assert meta["samples"] == 2 * meta["identities"]  # mirror-augmented
    assert meta["recipe"]["mirror_augmented"] is True
    assert default_asset_path().stat().st_size < 16_000_000


def test_stored_components_orthonormal_to_float16_tolerance(raw):
    c = raw["components"].reshape(128, -1).astype(np.float64)
    gram = c @ c.T
    assert np.abs(gram - np.eye(128)).max() < 5e-4  # float16 keeps 11 bits; measured 4e-5


def test_backend_attributes(pca64, rig):
    assert pca64.name == "pca"
    assert pca64.num_params == pca64.num_components == 128
    assert pca64.num_vertices == 18056
    assert pca64.param_names[0] == "pc000" and len(pca64.param_names) == 128
    assert torch.equal(pca64.faces(), rig.faces)
    assert pca64.default_params(3).shape == (3, 128)
    b = pca64.basis
    assert (b @ b.T - torch.eye(128, dtype=b.dtype)).abs().max() < 1e-12  # re-orthonormalised


def test_zero_coefficients_give_the_mean(pca64, raw):
    out = pca64(pca64.default_params(2))
    assert torch.equal(out[0], out[1])
    assert (out[0] - torch.from_numpy(raw["mean"]).double()).abs().max() == 0


def test_one_std_moves_along_the_component(pca64, raw):
    c = pca64.default_params(1)
    c[0, 5] = 1.0
    step = (pca64(c) - pca64.mean).flatten()
    assert abs(float(step.norm()) - float(raw["std"][5])) < 1e-6 * float(raw["std"][5])
    direction = torch.from_numpy(raw["components"][5].astype(np.float64)).flatten()
    assert float(step @ direction) / float(step.norm() * direction.norm()) > 1 - 1e-4  # float16 rounding


def test_project_inverts_forward(pca64):
    gen = torch.Generator().manual_seed(0)
    c = torch.randn(4, 128, generator=gen, dtype=torch.float64)
    assert (pca64.project(pca64(c)) - c).abs().max() < 1e-9
    c[:, 20:] = 0
    assert (pca64.project(pca64(c), 20) - c[:, :20]).abs().max() < 1e-9


def test_project_float32(rig):
    pca = PCAIdentity.from_asset(num_components=64)
    assert pca.mean.dtype == torch.float32
    c = torch.randn(3, 64, generator=torch.Generator().manual_seed(1))
    assert (pca.project(pca(c)) - c).abs().max() < 1e-3  # measured 6e-5 std at K = 128


def test_project_is_least_squares(pca64, rig):
    # A mesh outside the span: the residual is orthogonal to the first n directions.
    x = rig.bind_vertices[None] * 1.1
    n = 32
    c = pca64.project(x, n)
    full = torch.cat([c, c.new_zeros(1, 128 - n)], 1)
    resid = (x - pca64(full)).flatten()
    assert (pca64.basis[:n] @ resid).abs().max() < 1e-9 * resid.norm()
    assert (pca64.basis[n:] @ resid).abs().max() > 1e-3 * resid.norm()


def test_mean_is_mirror_symmetric(pca64):
    mean = pca64.mean[None]
    assert (mirror(mean) - mean).abs().max() < 1e-5  # mirror-augmented training set


def test_leading_components_are_symmetric_or_antisymmetric(pca64):
    # The augmented covariance commutes with the mirror: its eigenvectors are mirror-even or odd.
    comps = pca64.basis[:16].reshape(16, -1, 3)
    overlap = (mirror(comps).flatten(1) * comps.flatten(1)).sum(1)
    assert (overlap.abs() > 0.99).all()
    assert (overlap > 0).any() and (overlap < 0).any()


def test_mean_is_in_the_bind_pose(pca64, rig):
    # Training meshes were reposed to the bind A-pose: the skeleton fitted to the mean has the
    # bind orientations (Anny's own rest pose is 20-37 degrees away at the hands and fingers).
    layer = BodyLayer(rig, pca64, None)
    prepared = layer.prepare_identity(pca64.default_params(1))
    rel = prepared.rest_rotations[0] @ rig.bind_transforms[:, :3, :3].transpose(-1, -2)
    angle = torch.rad2deg(torch.acos(((rel.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)))
    assert float(angle.mean()) < 2.0 and float(angle.max()) < 10.0


def test_bodylayer_poses_pca_identity(pca64, rig):
    layer = BodyLayer(rig, pca64, None)  # no topology transfer: the PCA is on the canonical mesh
    gen = torch.Generator().manual_seed(2)
    coeffs = torch.randn(2, 128, generator=gen, dtype=torch.float64)
    prepared = layer.prepare_identity(coeffs)
    assert torch.equal(prepared.rest_vertices, pca64(coeffs))
    pose = 0.3 * torch.randn(2, 77, 3, generator=gen, dtype=torch.float64)
    transl = torch.randn(2, 3, generator=gen, dtype=torch.float64)
    out = layer.pose(prepared, pose, transl=transl)
    assert out.vertices.shape == (2, 18056, 3) and out.joints.shape == (2, 78, 3)
    assert torch.isfinite(out.vertices).all()
    assert (out.joints[:, 1] - transl).abs().max() < 1e-12
    # The pose that reproduces each identity's own rest skeleton gives back its rest mesh.
    local, _ = relative_to_parent(rig.tree, prepared.rest_rotations, prepared.rest_joints)
    rest = layer.pose(prepared, local[:, 1:], transl=prepared.rest_joints[:, 1], absolute=True)
    assert (rest.vertices - prepared.rest_vertices).abs().max() < 1e-9
    # Different coefficients, different bodies.
    assert (out.rest_vertices[0] - out.rest_vertices[1]).norm(dim=-1).mean() > 1e-3


def test_from_pca_float32_poses():
    layer = BodyLayer.from_pca(num_components=16)
    coeffs = torch.zeros(1, 16)
    coeffs[0, 1] = 1.5
    out = layer(coeffs, torch.zeros(2, 77, 3))
    assert out.vertices.dtype == torch.float32 and out.vertices.shape == (2, 18056, 3)
    # Reposed to the bind pose, a PCA body is its own rest mesh (the shape space lives in the bind pose).
    prepared = layer.prepare_identity(coeffs)
    assert (layer.repose_to_bind(prepared) - prepared.rest_vertices).norm(dim=-1).max() < 2e-3


def test_gradcheck_forward_and_project():
    pca = PCAIdentity.from_asset(num_components=4, dtype=torch.float64)
    c = torch.randn(2, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(pca, (c,), fast_mode=True)
    x = pca(c.detach()).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda m: pca.project(m, 3), (x,), fast_mode=True)


# --------------------------------------------------------------------------- errors


def test_errors(pca64, tmp_path):
    with pytest.raises(ValueError, match=r"num_components: expected an int in \[1, 128\].*got 129"):
        PCAIdentity.from_asset(num_components=129)
    with pytest.raises(ValueError, match="num_components"):
        PCAIdentity.from_asset(num_components=0)
    with pytest.raises(ValueError, match=r"identity params: expected shape \(B, 128\), got \(2, 5\)"):
        pca64(torch.zeros(2, 5, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"identity params: expected shape \(B, 128\), got \(128,\)"):
        pca64(torch.zeros(128, dtype=torch.float64))
    bad = torch.zeros(1, 128, dtype=torch.float64)
    bad[0, 3] = float("nan")
    with pytest.raises(ValueError, match="identity params: expected finite values, got 1 NaN/inf"):
        pca64(bad)
    with pytest.raises(TypeError, match="identity params: is float32 on cpu but the PCA backend is float64"):
        pca64(torch.zeros(1, 128))
    with pytest.raises(TypeError, match="identity params: expected a torch.Tensor"):
        pca64(np.zeros((1, 128)))
    lo, hi = pca64.param_bounds
    assert lo.shape == hi.shape == (128,) and torch.equal(lo, -hi)
    assert float(hi[0]) == pytest.approx(10.0) and torch.allclose(hi * pca64.std, 10 * pca64.std[0])
    huge = torch.zeros(2, 128, dtype=torch.float64)
    huge[1, 5] = 1e30
    with pytest.raises(ValueError, match=r"identity params: coefficient pc005 = 1e\+30 at batch 1 is outside \[-"):
        pca64(huge)
    with pytest.raises(
        ValueError, match=r"identity params: coefficient pc000 = -10.01 at batch 0 is outside \[-10, 10"
    ):
        pca64(torch.full((1, 128), -10.01, dtype=torch.float64))
    assert torch.isfinite(pca64(hi[None])).all() and torch.isfinite(pca64(lo[None])).all()  # inclusive
    mesh = pca64.mean[None]
    with pytest.raises(ValueError, match=r"num_components: expected an int in \[1, 128\], got 200"):
        pca64.project(mesh, 200)
    with pytest.raises(ValueError, match=r"meshes: expected shape \(B, 18056, 3\), got \(18056, 3\)"):
        pca64.project(pca64.mean)
    with pytest.raises(ValueError, match="meshes: expected finite values"):
        pca64.project(mesh * float("nan"))
    with pytest.raises(FileNotFoundError, match="PCA asset: no file at .*build_pca.py"):
        PCAIdentity.from_asset(tmp_path / "missing.npz")


def _tiny(k: int = 3, v: int = 18056, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3 * v, k)))
    return {"mean": rng.normal(size=(v, 3)), "components": q.T.reshape(k, v, 3), "std": np.array([3.0, 2.0, 1.0])[:k]}


def test_asset_round_trip_and_corrupt_files(tmp_path):
    arrays = _tiny()
    path = tmp_path / "tiny.npz"
    size = write_asset(path, **arrays, metadata={"note": "test"})
    assert size == path.stat().st_size
    back = read_asset(path)
    assert np.array_equal(back["mean"], arrays["mean"].astype(np.float32))
    # The leading component keeps ~22 bits (float16 hi + lo), the others float16's 11.
    err = np.abs(back["components"] - arrays["components"]).max(axis=(1, 2)) / np.abs(arrays["components"]).max()
    assert err[0] < 5e-6 and err[1] > 5 * err[0]  # measured 1.5e-6 and 3.6e-4 of the largest entry
    assert json.loads(back["metadata"]) == {"note": "test"}
    pca = PCAIdentity.from_asset(path, num_components=2, dtype=torch.float64)
    assert pca.num_params == 2 and pca.metadata == {"note": "test"}
    c = torch.tensor([[0.5, -1.0]], dtype=torch.float64)
    assert (pca.project(pca(c)) - c).abs().max() < 1e-10

    np.savez(tmp_path / "nokey.npz", mean=arrays["mean"], std=arrays["std"])
    with pytest.raises(
        ValueError, match=r"missing arrays \['format_version', 'components', 'components_lo', 'metadata'\]"
    ):
        read_asset(tmp_path / "nokey.npz")
    with np.load(path, allow_pickle=False) as data:
        stored = {k: data[k] for k in data.files}
    np.savez(tmp_path / "v2.npz", **{**stored, "format_version": np.asarray(2)})
    with pytest.raises(ValueError, match="format_version 2 is not supported"):
        read_asset(tmp_path / "v2.npz")
    np.savez(tmp_path / "shape.npz", **{**stored, "std": stored["std"][:2]})
    with pytest.raises(ValueError, match=r"expected mean \(V, 3\), components \(K, V, 3\), .* got .* \(2,\)"):
        read_asset(tmp_path / "shape.npz")
    small = _tiny(v=100)
    write_asset(tmp_path / "small.npz", **small, metadata={})
    with pytest.raises(ValueError, match="100 vertices, but the canonical mesh has 18056"):
        PCAIdentity.from_asset(tmp_path / "small.npz", num_components=3)


def test_constructor_errors():
    a = {k: torch.from_numpy(v) for k, v in _tiny(v=50).items()}
    faces = torch.tensor([[0, 1, 2]])
    with pytest.raises(ValueError, match="components: expected orthonormal rows"):
        PCAIdentity(a["mean"], 2 * a["components"], a["std"], faces)
    with pytest.raises(ValueError, match="std: expected positive standard deviations"):
        PCAIdentity(a["mean"], a["components"], -a["std"], faces)
    with pytest.raises(ValueError, match=r"components: expected shape \(K, V, 3\) with V=50"):
        PCAIdentity(a["mean"], a["components"][:, :40], a["std"], faces)


# --------------------------------------------------------------------------- incremental PCA


def _low_rank(n: int, d: int, rank: int, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    scales = torch.logspace(1, -2, rank, dtype=torch.float64)
    z = torch.randn(n, rank, generator=gen, dtype=torch.float64) * scales
    return z @ torch.randn(rank, d, generator=gen, dtype=torch.float64) + 2.0


def _exact(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    mu = x.mean(0)
    _, s, vt = torch.linalg.svd(x - mu, full_matrices=False)
    return mu, vt, s / (x.shape[0] - 1) ** 0.5


def test_ipca_equals_exact_pca_when_the_rank_fits():
    x = _low_rank(300, 80, 12, seed=0)
    state = ipca_init(80)
    for s in range(0, 300, 41):  # uneven chunks
        state = ipca_update(state, x[s : s + 41], rank=20)
    mean, comps, std = ipca_finalize(state, 12)
    mu, vt, s = _exact(x)
    assert (mean - mu).abs().max() < 1e-12
    assert ((std - s[:12]) / s[:12]).abs().max() < 1e-9
    assert ((comps @ vt[:12].T).abs() - torch.eye(12, dtype=torch.float64)).abs().max() < 1e-8
    assert abs(state.sum_sq - float(((x - mu) ** 2).sum())) < 1e-9 * state.sum_sq
    probe = torch.randn(80, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert (comps @ probe > 0).all()  # the sign convention


def test_ipca_truncation_keeps_the_leading_directions():
    # Full-rank data, streaming rank well above the shipped count: the leading ones stay exact.
    gen = torch.Generator().manual_seed(1)
    scales = torch.logspace(0, -3, 60, dtype=torch.float64)
    x = torch.randn(400, 60, generator=gen, dtype=torch.float64) * scales
    state = ipca_init(60)
    for s in range(0, 400, 50):
        state = ipca_update(state, x[s : s + 50], rank=30)
    _, comps, std = ipca_finalize(state, 10)
    _, vt, s = _exact(x)
    assert ((std - s[:10]) / s[:10]).abs().max() < 1e-6
    assert (comps @ vt[:10].T).abs().diagonal().min() > 1 - 1e-6


def test_ipca_state_round_trip_resumes_identically():
    x = _low_rank(120, 30, 6, seed=2)
    a = ipca_update(ipca_update(ipca_init(30), x[:60], 10), x[60:], 10)
    saved = ipca_update(ipca_init(30), x[:60], 10).to_numpy()
    b = ipca_update(IPCAState.from_numpy(saved), x[60:], 10)
    assert a.count == b.count == 120
    assert torch.equal(a.basis, b.basis) and torch.equal(a.singular, b.singular) and a.sum_sq == b.sum_sq


def test_ipca_errors():
    state = ipca_init(10)
    with pytest.raises(ValueError, match=r"batch: expected shape \(M, D\) with D=10, got \(4, 9\)"):
        ipca_update(state, torch.zeros(4, 9), 5)
    with pytest.raises(ValueError, match="batch: expected finite values"):
        ipca_update(state, torch.full((4, 10), float("nan")), 5)
    with pytest.raises(ValueError, match="num_components: 3 requested but the state holds 0 directions"):
        ipca_finalize(state, 3)


# --------------------------------------------------------------------------- the build script


@pytest.fixture(scope="module")
def build_pca():
    spec = importlib.util.spec_from_file_location("build_pca", ROOT / "scripts/build_pca.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["build_pca"] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    yield module
    del sys.modules["build_pca"]


@pytest.fixture(scope="module")
def anny_all(build_pca):
    return build_pca.anny_layer()


def test_sample_params(build_pca):
    recipe = build_pca.Recipe()
    p = build_pca.sample_params(recipe, 400, seed=0, num_local=256)
    assert p.shape == (400, 262)
    assert p[:, :6].min() >= 0 and p[:, :6].max() <= 1
    local = p[:, 6:]
    assert np.abs(local).max() <= 0.5
    assert 0.1 < (local != 0).mean() < 0.15  # each change active with probability 1/8
    # Row i does not depend on how many rows are drawn (resume and the held-out check rely on it).
    assert np.array_equal(build_pca.sample_params(recipe, 5, 0, 256, start=100), p[100:105])
    assert not np.array_equal(build_pca.sample_params(recipe, 5, 1, 256), p[:5])


def test_repose_gives_the_bind_skeleton(build_pca, anny_all):
    params = build_pca.sample_params(build_pca.Recipe(), 2, seed=5, num_local=256)
    rest, reposed = build_pca.canonical_samples(anny_all, params)
    layer = anny_all
    local = layer.bind_local_rotations().expand(2, -1, -1, -1)
    prepared = layer.prepare_rest(rest)
    out = layer.pose(prepared, local, transl=prepared.rest_joints[:, 1], absolute=True)
    assert torch.equal(out.vertices, reposed)
    bind_rot = layer.skeleton.bind_rot
    assert (out.transforms[..., :3, :3] - bind_rot).abs().max() < 1e-5
    assert (out.joints[:, 1] - prepared.rest_joints[:, 1]).abs().max() == 0
    assert (reposed - rest).norm(dim=-1).mean() > 0.005  # Anny's rest pose is not the bind pose


def test_build_script_resumes_to_the_same_asset(build_pca, anny_all, tmp_path, monkeypatch):
    monkeypatch.setattr(build_pca, "anny_layer", lambda dtype=torch.float32: anny_all)
    common = ["--identities", "5", "--chunk", "2", "--rank", "6", "--components", "4"]
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    build_pca.main([*common, "--out", str(a), "--checkpoint", str(tmp_path / "ca.npz")])
    build_pca.main([*common, "--out", str(b), "--checkpoint", str(tmp_path / "cb.npz"), "--stop-after", "1"])
    assert not b.exists()
    build_pca.main([*common, "--out", str(b), "--checkpoint", str(tmp_path / "cb.npz")])
    ra, rb = read_asset(a), read_asset(b)
    for key in ("mean", "components", "std"):
        assert np.array_equal(ra[key], rb[key])
    meta = json.loads(rb["metadata"])
    assert meta["samples"] == 10 and meta["identities"] == 5 and meta["seed"] == 0
    assert "--identities 5 --seed 0" in meta["command"]
    with pytest.raises(SystemExit, match="other settings"):
        build_pca.main([*common[:5], "7", *common[6:], "--out", str(b), "--checkpoint", str(tmp_path / "cb.npz")])


def test_demo_with_two_backends(tmp_path):
    from unibody.cli import main

    assert main(["demo", "--backends", "anny", "pca", "--out", str(tmp_path)]) == 0
    assert (tmp_path / "demo.glb").stat().st_size > 0 and (tmp_path / "demo.png").stat().st_size > 0
    # The CLI reports argument errors as one line and exit code 2 (no SystemExit since 82badfa).
    assert main(["demo", "--backends", "smplz", "--out", str(tmp_path)]) == 2


def test_empty_batch():
    """B = 0 gives empty outputs of the right shapes (it used to fail reshaping 0 elements)."""
    layer = BodyLayer.from_pca(num_components=10)
    v = layer.num_vertices
    assert layer.identity(torch.zeros(0, 10)).shape == (0, v, 3)
    prepared = layer.prepare_identity(torch.zeros(0, 10))
    assert prepared.rest_vertices.shape == (0, v, 3) and prepared.rest_rotations.shape == (0, 78, 3, 3)
    out = layer(torch.zeros(0, 10), torch.zeros(0, 77, 3))
    assert out.vertices.shape == (0, v, 3) and out.joints.shape == (0, 78, 3)
    assert out.transforms.shape == (0, 78, 4, 4) and out.rest_vertices.shape == (0, v, 3)


def test_implements_the_identity_backend_protocol(pca64):
    from unibody.identity.base import IdentityBackend, missing_members

    assert isinstance(pca64, IdentityBackend) and missing_members(pca64) == []
    template = pca64.template()
    assert template.shape == (pca64.num_vertices, 3) and template.dtype == torch.float64
    assert torch.equal(template, pca64(pca64.default_params())[0])
    assert template.data_ptr() != pca64.mean.data_ptr()  # a copy: editing it leaves the model alone
