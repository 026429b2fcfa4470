"""Property: ``PoseInverter.invert`` on any mesh gives a finite result or a documented error.

Meshes are clean posed bodies (B in {0, 1, 2}) changed by a drawn transformation: scaled
(units), mirrored, noisy, shuffled, random, with NaN/inf, with far or absurd outlier vertices,
or cast to integers. The answer must be a finite result or a ValueError/TypeError whose message
names ``vertices`` (or ``prepared``): never NaN, a raw LinAlgError or another exception type.
Seeded and bounded (profiles in tests/conftest.py); ``--hypothesis-profile=long`` for 1000.
"""

from __future__ import annotations

import pytest
import torch
from hypothesis import example, given
from hypothesis import strategies as st

from unibody import BodyLayer
from unibody.fitting.inversion import PRESETS, PoseInverter


@pytest.fixture(scope="module")
def setup():
    layer = BodyLayer.from_anny(dtype=torch.float32)
    prepared = layer.prepare_identity(torch.full((1, 6), 0.5))
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        meshes = layer.pose(
            prepared, 0.3 * torch.randn(2, 77, 3, generator=gen), transl=torch.randn(2, 3, generator=gen)
        ).vertices
    inverters = {p: PoseInverter(layer, PRESETS[p]) for p in ("fast", "analytic")}
    return layer, prepared, meshes, inverters


KINDS = ["clean", "scale", "mirror", "noise", "shuffle", "random", "nan", "inf", "outliers", "int", "flat"]


@st.composite
def bad_meshes(draw):
    return dict(
        batch=draw(st.sampled_from([0, 1, 2])),
        kind=draw(st.sampled_from(KINDS)),
        scale=10 ** draw(st.floats(-4, 4)),
        axis=draw(st.integers(0, 2)),
        noise=10 ** draw(st.floats(-4, 0)),
        count=draw(st.integers(1, 400)),
        distance=10 ** draw(st.floats(-1, 32)),
        seed=draw(st.integers(0, 2**16)),
        preset=draw(st.sampled_from(["fast", "analytic"])),
    )


def _make(meshes: torch.Tensor, c: dict) -> torch.Tensor:
    gen = torch.Generator().manual_seed(c["seed"])
    v = meshes[: c["batch"]].clone()
    n = v.shape[1]
    kind = c["kind"]
    if kind == "scale":
        v = v * c["scale"]
    elif kind == "mirror":
        v[..., c["axis"]] *= -1
    elif kind == "noise":
        v = v + c["noise"] * torch.randn(v.shape, generator=gen)
    elif kind == "shuffle":
        v = v[:, torch.randperm(n, generator=gen)]
    elif kind == "random":
        v = c["scale"] * torch.rand(v.shape, generator=gen)
    elif kind in ("nan", "inf"):
        v[:, torch.randint(n, (c["count"],), generator=gen), c["axis"]] = float(kind)
    elif kind == "outliers":
        idx = torch.randint(n, (c["count"],), generator=gen)
        direction = torch.nn.functional.normalize(torch.randn(v.shape[0], c["count"], 3, generator=gen), dim=-1)
        v[:, idx] = v[:, idx] + min(c["distance"], 1e30) * direction
    elif kind == "int":
        v = v.long()
    elif kind == "flat":
        v[..., c["axis"]] = 0.0
    return v


@given(bad_meshes())
def test_invert_gives_finite_result_or_clear_error(setup, case):
    layer, prepared, meshes, inverters = setup
    v = _make(meshes, case)
    try:
        with torch.no_grad():
            r = inverters[case["preset"]].invert(v, prepared)
    except (ValueError, TypeError) as e:
        assert str(e).startswith(("vertices:", "prepared:")), repr(e)
        assert "LinAlgError" not in type(e).__name__
        return
    assert r.pose.shape == (v.shape[0], 77, 3) and r.transl.shape == (v.shape[0], 3)
    for x in (r.pose, r.rotations, r.transl, r.vertices):
        assert bool(torch.isfinite(x).all())
    if case["kind"] in ("clean", "noise") and v.shape[0] and case["noise"] < 1e-3:
        assert float(r.per_vertex_error.mean()) < 0.05


# Found by the long run (2026-11-29): 265 vertices 1 m off un-posed to a rest shape 17 m across,
# refused by prepare_rest as "rest_vertices: ... not in metres", naming neither the input nor the cause.
_OUTLIERS = dict(batch=1, kind="outliers", scale=1.0, axis=0, noise=1.0, count=265, distance=1.0, seed=2)


@given(bad_meshes())
@example(case={**_OUTLIERS, "preset": "fast"})
def test_estimate_identity_gives_finite_rest_or_clear_error(setup, case):
    layer, prepared, meshes, inverters = setup
    v = _make(meshes, case)
    try:
        with torch.no_grad():
            rest = inverters["fast"].estimate_identity(v)
    except (ValueError, TypeError) as e:
        assert str(e).startswith("vertices:"), repr(e)
        return
    assert rest.rest_vertices.shape == (v.shape[0], layer.num_vertices, 3)
    assert bool(torch.isfinite(rest.rest_vertices).all())
