"""Shape spaces: shipped names and paths, the builder on generated model files, the CLI command."""

from __future__ import annotations

import argparse
import copy
import inspect
import json

import numpy as np
import pytest
import torch

import unibody.registration
from garment_format import write_garment_assets
from mhr_format import write_mhr_assets
from smpl_format import canonical_model, write_npz
from unibody import BodyLayer
from unibody.cli import main as cli_main
from unibody.cli.shape_commands import source_from_spec
from unibody.identity.garment import GarmentIdentity
from unibody.identity.pca import SPACES, PCAIdentity, asset_path, default_asset_path
from unibody.identity.shape_space import (
    HIPS_M,
    AnnyRecipe,
    ShapeSource,
    _duration,
    anny_params,
    anny_sampler,
    backend_sampler,
    build_shape_space,
    parse_weights,
    to_bind_pose,
)
from unibody.identity.smpl import SMPLIdentity
from unibody.rig import Rig

# --------------------------------------------------------------------------- names and paths


def test_asset_path_names_paths_and_errors(tmp_path):
    assert asset_path("v1") == default_asset_path()
    assert asset_path("v2").name == SPACES["v2"]
    f = tmp_path / "mine.npz"
    f.write_bytes(b"")
    assert asset_path(str(f)) == f and asset_path(f) == f
    with pytest.raises(FileNotFoundError, match=r"space: no shape-space file at .*nope\.npz; expected a shipped name"):
        asset_path(tmp_path / "nope.npz")
    with pytest.raises(TypeError, match="space: expected a name"):
        asset_path(3)  # type: ignore[arg-type]


def test_from_pca_default_is_still_v1():
    a, b = BodyLayer.from_pca().identity, PCAIdentity.from_asset("v1")
    assert a.metadata == b.metadata and a.num_params == 128
    assert a.metadata["command"].startswith("python scripts/build_pca.py")
    assert torch.equal(a.basis, b.basis)


# BodyLayer.from_pca(space) lives in body.py, committed apart from this file.
needs_from_pca_space = pytest.mark.skipif(
    "space" not in inspect.signature(BodyLayer.from_pca).parameters, reason="BodyLayer.from_pca has no space argument"
)


@needs_from_pca_space
def test_from_pca_by_name_and_path(tmp_path):
    a = BodyLayer.from_pca("v1", num_components=8)
    assert a.identity.num_params == 8 and a.identity.metadata == PCAIdentity.from_asset().metadata
    with pytest.raises(FileNotFoundError, match=r"PCA asset: no file at .*none\.npz; expected a shipped space's name"):
        BodyLayer.from_pca(tmp_path / "none.npz")
    with pytest.raises(ValueError, match=r"num_components: expected an int in \[1, 128\]"):
        BodyLayer.from_pca("v1", num_components=129)


@needs_from_pca_space
@pytest.mark.skipif(not asset_path("v2").is_file(), reason="pca_v2.npz not built")
def test_v2_loads_by_name_and_is_placed():
    layer = BodyLayer.from_pca("v2", dtype=torch.float64)
    pca = layer.identity
    assert pca.num_params == 128 and pca.metadata["name"] == "pca_v2"
    # the mean body's Hips sit at HIPS_M (every training mesh was placed there)
    hips = layer.prepare_identity(pca.default_params(1)).rest_joints[0, 1]
    assert torch.allclose(hips, hips.new_tensor(HIPS_M), atol=2e-3)
    # one matmul: forward(project(x)) is the least-squares fit, and coefficients round-trip
    c = torch.randn(2, 128, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 0.5
    assert torch.allclose(pca.project(pca(c)), c, atol=1e-8)


# --------------------------------------------------------------------------- samplers


def test_anny_params_recipe():
    rng = np.random.default_rng(0)
    p = anny_params(AnnyRecipe(local_change_probability=0.25, local_change_amplitude=1.0), rng, 400, 20)
    assert p.shape == (400, 11 + 20)
    assert p[:, :8].min() >= 0 and p[:, :8].max() <= 1
    assert np.allclose(p[:, 8:11].sum(1), 1.0)  # the ethnicity blend lies on the simplex
    local = p[:, 11:]
    assert 0.2 < (local != 0).mean() < 0.3 and np.abs(local).max() > 0.95
    with pytest.raises(ValueError, match="phenotype_range: expected 0 <= lo <= hi <= 1"):
        AnnyRecipe(phenotype_range=(0.5, 1.5))
    with pytest.raises(ValueError, match="phenotypes: expected 'default' or 'all'"):
        AnnyRecipe(phenotypes="some")


def test_backend_sampler_spread_and_bounds(tmp_path):
    write_mhr_assets(tmp_path)
    from unibody.identity.mhr import MHRIdentity

    mhr = MHRIdentity.from_files(tmp_path)
    lo, hi = mhr.param_bounds
    x = backend_sampler(mhr)(np.random.default_rng(0), 2000)
    assert x.shape == (2000, mhr.num_params)
    assert bool((x >= lo.double()).all() and (x <= hi.double()).all())
    coeff = x[:, :45]
    assert abs(float(coeff.std()) - 1.0) < 0.05 and abs(float(coeff.mean())) < 0.05


def test_parse_weights():
    assert parse_weights(["smpl=2", "anny=0.5"]) == {"smpl": 2.0, "anny": 0.5}
    for bad in ("smpl", "smpl=0", "smpl=x", "=1", "smpl=inf"):
        with pytest.raises(ValueError, match="--weight: expected NAME=W"):
            parse_weights([bad])


def test_source_from_spec_errors(tmp_path):
    for bad in ("smpl", "anny=x", "foo=bar", "smpl:file"):
        with pytest.raises(ValueError, match="--from: expected 'anny' or KIND=PATH"):
            source_from_spec(bad)
    with pytest.raises(FileNotFoundError, match=r"--from smpl: no such file: .*missing\.npz"):
        source_from_spec(f"smpl={tmp_path / 'missing.npz'}")


# --------------------------------------------------------------------------- the builder


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    """A generated SMPL-format model and a GarmentMeasurements folder on body-shaped templates, with exact transfers."""
    root = tmp_path_factory.mktemp("sources")
    model, transfer = canonical_model("smplh", seed=3, num_shape=10)
    smpl_path = write_npz(root / "SMPL_NEUTRAL.npz", model)
    gmodel, gtransfer = canonical_model("smplx", seed=4, num_shape=1)
    v = gmodel["v_template"]
    rng = np.random.default_rng(5)
    fields = np.stack([((v - v.mean(0)) @ rng.normal(size=(3, 3))).reshape(-1) for _ in range(6)], 1)
    q, _ = np.linalg.qr(fields)
    arrays = {
        "matrix": q,
        "mean": v.reshape(-1),
        "eigenvalues": 0.02**2 * 0.6 ** np.arange(6),
        "faces": gmodel["f"].astype(np.int64),
    }
    write_garment_assets(root / "garment", arrays)
    return {"smpl": (smpl_path, transfer), "garment": (root / "garment", gtransfer)}


@pytest.fixture
def exact_transfers(generated, monkeypatch):
    """``BodyLayer.from_identity`` gets the generated models' exact transfers instead of a registration."""
    by_count = {t.num_source_vertices: t for _, t in generated.values()}

    def fake(vertices, faces, name, **kw):
        return copy.deepcopy(by_count[vertices.shape[0]])

    monkeypatch.setattr(unibody.registration, "topology_transfer", fake)


def _source(kind, path, transfer, weight=1.0):
    identity = SMPLIdentity.from_file(path, dtype=torch.float64) if kind == "smpl" else GarmentIdentity.from_files(path)
    layer = BodyLayer(Rig.canonical(), identity.double(), transfer.double()).double()
    return ShapeSource(kind, layer, backend_sampler(identity), weight)


def _bodies(source: ShapeSource, seed: int, count: int) -> torch.Tensor:
    params = source.sampler(np.random.default_rng(seed), count).double()
    with torch.no_grad():
        return to_bind_pose(source.layer, source.layer.prepare_identity(params).rest_vertices)


def test_builder_represents_its_sources(generated, tmp_path):
    """A space built from generated SMPL and Garment models holds unseen bodies of both (and not of a third)."""
    smpl = _source("smpl", *generated["smpl"], weight=2.0)
    garment = _source("garment", *generated["garment"])
    out = tmp_path / "mine.npz"
    meta = build_shape_space([smpl, garment], out, identities=90, chunk=30, rank=40, components=24)
    assert [s["identities"] for s in meta["sources"]] == [60, 30]  # shares follow the weights
    assert meta["samples"] == 180 and meta["num_components"] == 24
    pca = PCAIdentity.from_asset(out, num_components=None, dtype=torch.float64)
    layer = BodyLayer(Rig.canonical(), pca, None).double()
    for source in (smpl, garment):
        held = _bodies(source, 1234, 5)  # never drawn by the build
        err = held - pca(pca.project(held))
        assert float(err.norm(dim=-1).mean()) < 2e-4, source.name  # < 0.2 mm: in the span
        first = held - pca(torch.nn.functional.pad(pca.project(held, 2), (0, 22)))
        assert float(first.norm(dim=-1).mean()) > 3 * 2e-4  # two components are not enough: the test can fail
    # the mean body stands with its Hips at HIPS_M
    hips = layer.prepare_identity(pca.default_params(1)).rest_joints[0, 1]
    assert torch.allclose(hips, hips.new_tensor(HIPS_M), atol=1e-3)


def test_builder_resumes_to_the_same_space(generated, tmp_path):
    smpl = _source("smpl", *generated["smpl"])
    kw = {"identities": 60, "chunk": 20, "rank": 30, "components": 12}
    whole = tmp_path / "whole.npz"
    build_shape_space([smpl], whole, **kw)
    ckpt, part = tmp_path / "ckpt.npz", tmp_path / "part.npz"
    calls = []

    def stop(line):
        calls.append(line)
        if len(calls) == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        build_shape_space([smpl], part, checkpoint=ckpt, progress=stop, **kw)
    assert ckpt.is_file() and not part.exists()
    assert calls[0].startswith("chunk 1/3: 40 samples") and calls[0].endswith(" left")  # with an ETA
    assert [_duration(x) for x in (42, 4500, 11520, 1e6)] == ["42 s", "75 min", "3.2 h", "12 days"]
    lines = []
    build_shape_space([smpl], part, checkpoint=ckpt, progress=lines.append, **kw)
    assert lines[0].startswith(f"resuming from {ckpt}: chunk 2/3")
    a, b = (np.load(p) for p in (whole, part))
    assert np.array_equal(a["mean"], b["mean"]) and np.allclose(a["components"], b["components"], atol=2e-3)
    with pytest.raises(ValueError, match="made with other settings"):
        build_shape_space([smpl], part, checkpoint=ckpt, seed=9, **kw)


def test_builder_errors(generated, tmp_path):
    smpl = _source("smpl", *generated["smpl"])
    out = tmp_path / "x.npz"
    with pytest.raises(ValueError, match="sources: expected at least one ShapeSource"):
        build_shape_space([], out)
    with pytest.raises(ValueError, match="sources: names must be unique"):
        build_shape_space([smpl, smpl], out)
    with pytest.raises(ValueError, match="weight must be a finite number > 0"):
        build_shape_space([ShapeSource("s", smpl.layer, smpl.sampler, 0.0)], out)
    with pytest.raises(ValueError, match="components: 40 exceeds rank 30"):
        build_shape_space([smpl], out, components=40, rank=30)
    with pytest.raises(ValueError, match="identities: 4 samples cannot give 8 components"):
        build_shape_space([smpl], out, identities=2, components=8, rank=8)
    for seed in (-1, 1.5, True):
        with pytest.raises(ValueError, match=f"seed: expected an int >= 0, got {seed!r}"):
            build_shape_space([smpl], out, identities=20, components=8, rank=8, seed=seed)
    assert not out.exists()


def test_anny_source_with_a_generated_smpl_model(generated, tmp_path):
    """Anny (6 phenotypes) and a generated SMPL model in one space: both represented."""
    anny = BodyLayer.from_anny(dtype=torch.float64)
    a = ShapeSource("anny", anny, anny_sampler(AnnyRecipe(phenotypes="default"), 0), 1.0)
    smpl = _source("smpl", *generated["smpl"])
    out = tmp_path / "mix.npz"
    build_shape_space([a, smpl], out, identities=120, chunk=60, rank=60, components=40)
    pca = PCAIdentity.from_asset(out, num_components=None, dtype=torch.float64)
    for source, tol in ((smpl, 2e-4), (a, 3e-3)):  # Anny's 6 phenotypes are not linear: a few mm at 40
        held = _bodies(source, 99, 4)
        assert float((held - pca(pca.project(held))).norm(dim=-1).mean()) < tol, source.name


# --------------------------------------------------------------------------- the command


def _has_shape_space_command() -> bool:
    from unibody.cli import _parser

    subs = [a for a in _parser()._actions if isinstance(a, argparse._SubParsersAction)]
    return any("shape-space" in a.choices for a in subs)


# The command's registration lives in cli/__init__.py, committed apart from this file.
needs_command = pytest.mark.skipif(not _has_shape_space_command(), reason="unibody shape-space is not registered")


@needs_command
def test_cli_builds_from_generated_files(generated, exact_transfers, tmp_path, capsys):
    smpl_path, _ = generated["smpl"]
    out = tmp_path / "space.npz"
    argv = ["shape-space", "build", "--from", f"smpl={smpl_path}", f"garment={generated['garment'][0]}",
            "--weight", "garment=0.5", "--identities", "60", "--components", "16", "--rank", "32",
            "--chunk", "20", "--out", str(out)]  # fmt: skip
    assert cli_main(argv) == 0
    summary = json.loads(capsys.readouterr().out.split("\nload it")[0])
    assert summary["components"] == 16 and [s["identities"] for s in summary["sources"]] == [40, 20]
    assert not (tmp_path / "space.partial.npz").exists()
    pca = PCAIdentity.from_asset(out, num_components=None)
    assert pca.num_params == 16 and pca.metadata["command"].startswith("unibody shape-space build --from smpl=")
    assert cli_main(argv) == 4  # exists: refused without --force
    assert "exists" in capsys.readouterr().err


@needs_command
@pytest.mark.parametrize(
    ("extra", "code", "message"),
    [
        (["--from", "foo=bar"], 2, "--from: expected 'anny' or KIND=PATH"),
        (["--from", "anny", "--weight", "smpl=2"], 2, "--weight: smpl is not among the --from sources"),
        (["--from", "anny", "--weight", "anny=-1"], 2, "--weight: expected NAME=W"),
        (["--from", "anny", "anny"], 2, "--from: each kind at most once"),
        (["--from", "smpl=/no/such/model.npz"], 3, "--from smpl: no such file: /no/such/model.npz"),
        (["--from", "anny", "--components", "300"], 2, "--rank: expected >= --components"),
        (["--from", "anny", "--seed", "-1"], 2, "--seed: expected an integer >= 0, got -1"),  # was numpy's, unnamed
    ],
)
def test_cli_errors(tmp_path, capsys, extra, code, message):
    assert cli_main(["shape-space", "build", "--out", str(tmp_path / "s.npz"), *extra]) == code
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
