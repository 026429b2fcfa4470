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
    arrays = assets.canonical_assets()
    assert arrays["bind_vertices"].shape == (18056, 3) and path.stat().st_size > 1000
    assets.canonical_assets.cache_clear()
