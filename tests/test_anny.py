"""Anny backend and topology transfer against the bundled wrap, and the asset cache."""

from __future__ import annotations

import pytest
import torch

from unibody import assets
from unibody.io.obj import read_obj


def test_default_anny_maps_onto_the_wrap(anny_layer64):
    """base_body.obj is Anny's average identity in our axes (shifted); the wrap sits on it."""
    layer = anny_layer64
    rest = layer.identity(layer.identity.default_params())
    base, _ = read_obj(assets.source_dir() / "base_body.obj")
    shift = torch.from_numpy(base) - rest[0]
    assert (shift - shift.mean(0)).abs().max() < 1e-6  # a pure translation: the axes are right
    canonical = layer.topology(rest)
    wrap, _ = read_obj(assets.source_dir() / "SOMA_wrap.obj")
    assert (canonical[0] + shift.mean(0) - torch.from_numpy(wrap)).abs().max() < 1e-6


def test_identities_batch_and_child_is_smaller(anny_layer64):
    params = torch.tensor([[0.5, 0.7, 0.5, 0.5, 0.5, 0.5], [0.5, 0.25, 0.5, 0.5, 0.5, 0.5]], dtype=torch.float64)
    prepared = anny_layer64.prepare_identity(params)
    height = prepared.rest_vertices[..., 1].amax(1) - prepared.rest_vertices[..., 1].amin(1)
    assert 1.5 < float(height[0]) < 1.95 and float(height[1]) < 0.8 * float(height[0])
    one = anny_layer64.prepare_identity(params[1:])
    assert (one.rest_vertices[0] - prepared.rest_vertices[1]).abs().max() < 1e-12


def test_changed_source_is_an_error(monkeypatch):
    assets.canonical_assets.cache_clear()
    monkeypatch.setitem(assets.SOURCE_SHA256, "soma_faces.pt", "0" * 64)
    with pytest.raises(assets.AssetError, match=r"soma_faces.pt changed: expected sha256 0000000000000000"):
        assets.canonical_assets()
    assets.canonical_assets.cache_clear()


def test_missing_source_is_an_error(monkeypatch, tmp_path):
    assets.canonical_assets.cache_clear()
    monkeypatch.setattr(assets, "source_dir", lambda: tmp_path)
    with pytest.raises(assets.AssetError, match=r"soma_rig.pt is missing; reinstall with: pip install"):
        assets.canonical_assets()
    assets.canonical_assets.cache_clear()


def test_cache_is_rebuilt_when_unreadable(monkeypatch, tmp_path):
    monkeypatch.setenv("UNIBODY_CACHE_DIR", str(tmp_path))
    assets.canonical_assets.cache_clear()
    path = assets.cache_dir() / f"canonical-anny{assets.ANNY_VERSION}-{assets._cache_key()}.npz"
    path.parent.mkdir(parents=True)
    path.write_bytes(b"not an npz")
    with pytest.warns(assets.AssetWarning, match="is unusable .*not a zip file"):
        arrays = assets.canonical_assets()
    assert arrays["bind_vertices"].shape == (18056, 3) and path.stat().st_size > 1000
    assets.canonical_assets.cache_clear()


# Anny's own cache (~/.cache/anny): the tests point it at a temporary folder and never write the real one.


@pytest.fixture
def anny_cache(tmp_path, monkeypatch):
    import anny.paths

    saved = anny.paths.get_anny_cache_path()
    anny.paths.set_anny_cache_path(tmp_path / "anny")
    monkeypatch.setenv("UNIBODY_CACHE_DIR", str(tmp_path / "unibody"))  # the build lock lives there
    yield tmp_path / "anny"
    anny.paths.set_anny_cache_path(saved)


def _truncated_safetensors(path):
    from safetensors.torch import save_file

    save_file({"template_vertices": torch.zeros(500, 3)}, str(path))
    path.write_bytes(path.read_bytes()[:300])


def test_an_unloadable_anny_cache_file_is_removed_and_rebuilt(anny_cache, capsys):
    from anny.models.model_data import ModelData
    from torch import nn

    from unibody.identity.anny import _build_anny

    folder = anny_cache / "v14"
    folder.mkdir(parents=True)
    bad, other = folder / "build_compact_model_data_x.safetensors", folder / "load_data_y.safetensors"
    _truncated_safetensors(bad)
    other.write_bytes(b"another entry")
    builds = []

    def make():  # what anny's cache_builder does: load when the file exists, else build and save
        if bad.exists():
            ModelData.load_safetensors(bad)
        builds.append(1)
        bad.write_bytes(b"rebuilt")
        return nn.Identity()

    with pytest.warns(assets.AssetWarning, match=r"Anny's cache file .*_x.safetensors cannot be loaded \(Safetensor"):
        model = _build_anny(make, bad)
    assert isinstance(model, nn.Identity) and builds == [1]
    assert bad.read_bytes() == b"rebuilt" and other.read_bytes() == b"another entry"  # nothing else touched
    err = capsys.readouterr().err
    assert f"unibody: building Anny's model once (about a minute) into {anny_cache}..." in err
    assert "unibody: built Anny's model in" in err
    assert ModelData.__dict__["load_safetensors"].__func__.__module__ == "anny.models.model_data"  # restored


def test_an_unwritable_anny_cache_builds_in_memory(anny_cache, tmp_path):
    import anny.paths
    from torch import nn

    from unibody.identity.anny import _build_anny

    (tmp_path / "a-file").write_text("")
    anny.paths.set_anny_cache_path(tmp_path / "a-file" / "anny")
    seen = []

    def make():  # anny's cache_builder: mkdir the cache folder, unless caching is off (None)
        root = anny.paths.get_anny_cache_path()
        seen.append(root)
        if root is not None:
            (root / "v14").mkdir(parents=True, exist_ok=True)
        return nn.Identity()

    with pytest.warns(assets.AssetWarning, match="cannot write Anny's cache in .*a-file.*Anny's model in memory"):
        _build_anny(make, None)
    assert seen == [tmp_path / "a-file" / "anny", None]
    assert anny.paths.get_anny_cache_path() == tmp_path / "a-file" / "anny"  # restored


def test_the_predicted_anny_cache_file_is_the_one_anny_writes(anny_cache):
    """The prediction only picks a progress message; it mirrors anny's cache_builder key."""
    from pathlib import Path

    from unibody.identity.anny import _anny_model_path

    path = _anny_model_path("none")
    assert path is not None and path.parent.parent == anny_cache
    real = Path.home() / ".cache" / "anny" / path.parent.name
    if real.is_dir() and any(real.glob("build_compact_model_data_*")):
        assert (real / path.name).is_file()


@pytest.mark.slow
def test_a_truncated_anny_model_cache_is_rebuilt_for_real(anny_cache):
    """End to end (~20-60 s): a truncated copy of the installed compact model is rebuilt from its source entry."""
    from pathlib import Path

    from unibody.identity.anny import AnnyIdentity, _anny_model_path

    name = _anny_model_path("none").name
    real = Path.home() / ".cache" / "anny" / "v14"
    sources = sorted(real.glob("build_model_data_*.safetensors")) if real.is_dir() else []
    if not (real / name).is_file() or not sources:
        pytest.skip("no installed Anny cache to copy")
    folder = anny_cache / "v14"
    folder.mkdir(parents=True)
    for src in sources:
        (folder / src.name).write_bytes(src.read_bytes())
    (folder / name).write_bytes((real / name).read_bytes()[:100_000])
    with pytest.warns(assets.AssetWarning, match="cannot be loaded"):
        rebuilt = AnnyIdentity.create()
    import anny.paths

    anny.paths.set_anny_cache_path(real.parent)  # read-only use of the installed cache
    reference = AnnyIdentity.create()
    params = reference.default_params(2)
    params[1, :6] = torch.tensor([0.1, 0.9, 0.3, 0.7, 0.2, 0.8])
    assert torch.equal(rebuilt(params), reference(params))


def test_implements_the_identity_backend_protocol(anny_layer64):
    from unibody.identity import PHENOTYPES
    from unibody.identity.base import IdentityBackend, missing_members

    anny = anny_layer64.identity
    assert isinstance(anny, IdentityBackend) and missing_members(anny) == []
    lo, hi = anny.param_bounds
    n = len(PHENOTYPES)
    assert lo.shape == hi.shape == (anny.num_params,) and lo.dtype == torch.float64
    assert bool((lo[:n] == 0).all() & (hi[:n] == 1).all() & (lo[n:] == -1).all() & (hi[n:] == 1).all())
    template = anny.template()
    assert template.shape == (anny.num_vertices, 3)
    assert torch.equal(template, anny(anny.default_params())[0])
