"""Identity fitting through the unified pipeline (unibody.fitting.shape_fit): recovery, limits, errors."""

from __future__ import annotations

import math

import pytest
import torch

from unibody import BodyLayer, Rig
from unibody.fitting.shape_fit import IdentityFit, _Bounded, _lbfgs, _Reporter, fit_identity, param_limits
from unibody.identity import PHENOTYPES


@pytest.fixture(scope="module")
def anny32() -> BodyLayer:
    return BodyLayer.from_anny()


@pytest.fixture(scope="module")
def pca32() -> BodyLayer:
    return BodyLayer.from_pca(num_components=10)


def _reposed(layer: BodyLayer, params: torch.Tensor) -> torch.Tensor:
    with torch.no_grad():
        return layer.repose_to_bind(layer.prepare_identity(params))


def test_recovers_anny_phenotypes_from_the_default_start():
    # Not every phenotype vector is reachable from the average identity: the multilinear
    # phenotype model has local minima (e.g. muscle 0.6 at age 0.7 ends at muscle 0.48).
    # float64: in float32 the line search stops at rounding level, and where that is depends
    # on the CPU kernels and library versions (one machine: 1e-5 m, another: 1.7 mm).
    anny64 = BodyLayer.from_anny().double()
    truth = torch.tensor([[0.8, 0.35, 0.3, 0.7, 0.3, 0.6], [0.15, 0.9, 0.5, 0.55, 0.8, 0.3]], dtype=torch.float64)
    targets = _reposed(anny64, truth)
    start = _reposed(anny64, anny64.identity.default_params(2))
    fit = fit_identity(anny64, targets, lbfgs_steps=100)
    assert isinstance(fit, IdentityFit) and fit.params.shape == (2, 6) and fit.vertices.shape == targets.shape
    assert fit.params.dtype == torch.float64 and not fit.params.requires_grad
    assert float((start - targets).norm(dim=-1).amax()) > 0.05  # the start is far away
    assert float(fit.per_vertex_error.amax()) < 1e-9  # m
    assert float((fit.params - truth).abs().amax()) < 1e-9
    assert torch.allclose(fit.per_vertex_error, (fit.vertices - targets).norm(dim=-1))
    assert fit.adam_steps == 0 and 0 < fit.lbfgs_steps < 100  # stopped: converged


def test_recovers_pca_coefficients(pca32):
    truth = 0.8 * torch.randn(2, 10, generator=torch.Generator().manual_seed(3))
    fit = fit_identity(pca32, _reposed(pca32, truth), lbfgs_steps=50)
    assert float(fit.per_vertex_error.amax()) < 1e-3
    assert float((fit.params - truth).abs().amax()) < 0.02


def test_recovers_every_component_of_the_native_pca():
    # The shipped space (128 components; limits |c_k| <= 10 sigma_0 / sigma_k, up to 38,490) failed
    # on its own bodies: the first L-BFGS step made an 18.8 m body and the layer refused it.
    layer = BodyLayer.from_pca().double()
    # The second of these bodies: with slopes in proportion to the spans it stops 0.13 m off.
    truth = 0.8 * torch.randn(2, 128, generator=torch.Generator().manual_seed(3), dtype=torch.float64)[1:]
    fit = fit_identity(layer, _reposed(layer, truth), lbfgs_steps=100)
    assert float(fit.per_vertex_error.amax()) < 1e-5 and float((fit.params - truth)[:, :32].abs().amax()) < 1e-3
    bounded = _Bounded(param_limits(layer.identity), truth)
    z = bounded.inverse(truth)
    assert torch.allclose(bounded(z), truth, atol=1e-9)
    step = bounded(z + 1.0) - truth  # a unit step moves the leading coefficient by <= 1 sigma
    assert 0.5 < float(step[0, 0]) <= 1.0


def test_a_trial_past_the_layers_extent_is_backtracked():
    from unibody.fitting.shape_fit import _Objective, _trial

    layer = BodyLayer.from_pca(num_components=10).double()
    bounded = _Bounded(param_limits(layer.identity), layer.skeleton.bind_rot)
    targets = _reposed(layer, layer.identity.default_params(2))
    objective = _Objective(layer, bounded, targets)
    z = bounded.inverse(torch.tensor([[0.5] + [0.0] * 9, [9.99] + [0.0] * 9], dtype=torch.float64))
    z[1, 1:] = 50.0  # a body far past 10 m: the layer refuses it, the trial is +inf
    with pytest.raises(ValueError, match="bounding-box diagonal"):
        objective(z, torch.arange(2))
    f, g = _trial(objective, z, torch.arange(2))
    assert math.isfinite(float(f[0])) and f[1] == math.inf and bool(g[1].eq(0).all())
    assert torch.equal(f[:1], objective(z[:1], torch.arange(1))[0])


def test_parameters_stay_in_their_limits(anny32):
    # A giant (the tallest Anny scaled by 1.2 about the Hips): the fit pushes height to its
    # limit, and Anny (which rejects phenotypes outside [0, 1]) never sees an invalid value.
    tall = _reposed(anny32, torch.tensor([[0.5, 0.5, 0.5, 0.5, 1.0, 0.5]]))
    hips = tall.mean(1, keepdim=True)
    fit = fit_identity(anny32, hips + 1.2 * (tall - hips), steps=15, lr=0.5, lbfgs_steps=0)
    assert fit.adam_steps == 15 and fit.lbfgs_steps == 0
    assert bool(((fit.params >= 0) & (fit.params <= 1)).all())
    assert float(fit.params[0, PHENOTYPES.index("height")]) > 0.9


def test_no_steps_returns_the_start(anny32):
    targets = _reposed(anny32, torch.tensor([[0.2, 0.6, 0.5, 0.5, 0.5, 0.5]]))
    fit = fit_identity(anny32, targets, steps=0, lbfgs_steps=0)
    assert torch.allclose(fit.params, anny32.identity.default_params(), atol=1e-6)
    init = torch.tensor([[0.3, 0.4, 0.5, 0.6, 0.7, 0.0]])  # on a limit: moved just inside it
    fit = fit_identity(anny32, targets, steps=0, lbfgs_steps=0, init=init)
    assert torch.allclose(fit.params, init, atol=1e-3) and float(fit.params[0, 5]) > 0


def test_bounded_map_round_trips_and_respects_limits():
    inf = math.inf
    limits = torch.tensor([[0.0, 1.0], [-1.0, 1.0], [0.5, inf], [-inf, 2.0], [-inf, inf]], dtype=torch.float64)
    ref = torch.zeros((), dtype=torch.float64)
    bounded = _Bounded(limits, ref)
    params = torch.tensor([[0.25, -0.5, 3.0, -4.0, 7.0], [0.9, 0.1, 0.6, 1.9, -2.0]], dtype=torch.float64)
    assert torch.allclose(bounded(bounded.inverse(params)), params, atol=1e-10)
    z = torch.linspace(-60, 60, 11, dtype=torch.float64)[:, None].expand(-1, 5)
    p = bounded(z)
    assert bool((p >= limits[:, 0]).all() & (p <= limits[:, 1]).all())
    with pytest.raises(ValueError, match=r"init: parameter 2 must lie in \[0.5, inf\], got 0.2 at batch 1"):
        bounded.inverse(torch.tensor([[0.5, 0.0, 1.0, 0.0, 0.0], [0.5, 0.0, 0.2, 0.0, 0.0]], dtype=torch.float64))
    with pytest.raises(ValueError, match=r"param limits: parameter 0 has min 1.0 >= max 1.0"):
        _Bounded(torch.tensor([[1.0, 1.0]], dtype=torch.float64), ref)


class _Quadratic:
    """Per-item f_b(z) = 1/2 (z - m_b)^T A_b (z - m_b) + 1, condition numbers 1e2 and 1e4."""

    def __init__(self) -> None:
        gen = torch.Generator().manual_seed(0)
        q, _ = torch.linalg.qr(torch.randn(2, 8, 8, generator=gen, dtype=torch.float64))
        spectra = torch.stack([torch.logspace(0, 2, 8), torch.logspace(0, 4, 8)]).double()
        self.a = q @ torch.diag_embed(spectra) @ q.transpose(-1, -2)
        self.m = torch.randn(2, 8, generator=gen, dtype=torch.float64)
        self.calls: list[int] = []

    def __call__(self, z: torch.Tensor, items: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        idx = torch.arange(2) if items is None else items
        self.calls.append(len(idx))
        g = ((z - self.m[idx])[:, None, :] @ self.a[idx]).squeeze(1)
        return 0.5 * (g * (z - self.m[idx])).sum(-1) + 1.0, g


def test_batched_lbfgs_solves_each_item_on_its_own():
    quad = _Quadratic()
    z, iters = _lbfgs(quad, torch.zeros(2, 8, dtype=torch.float64), 60, _Reporter(None, 60, 2), first=0)
    assert float((z - quad.m).abs().amax()) < 1e-6
    assert iters < 60  # both items stopped once converged to float precision
    assert min(quad.calls[1:]) < 2  # line searches ran on the items still searching only


class _Limited(torch.nn.Module):
    num_params = 3

    def __init__(self, bounds) -> None:
        super().__init__()
        self.param_bounds = bounds


def test_param_limits(anny32, pca32):
    anny = param_limits(anny32.identity)
    assert anny.shape == (6, 2) and bool((anny == torch.tensor([0.0, 1.0], dtype=torch.float64)).all())
    pca = param_limits(pca32.identity)
    bound = pca32.identity.param_bound.double()
    assert pca.shape == (10, 2) and torch.equal(pca[:, 0], -bound) and torch.equal(pca[:, 1], bound)
    assert float(bound.min()) == 10.0  # the leading component: 10 sigma
    own = torch.tensor([[0.0, 1.0], [-2.0, math.inf], [-math.inf, math.inf]])
    assert torch.equal(param_limits(_Limited((own[:, 0], own[:, 1]))), own.double())
    unbounded = param_limits(_Limited(None))
    assert bool((unbounded[:, 0] == -math.inf).all() & (unbounded[:, 1] == math.inf).all())
    with pytest.raises(
        ValueError,
        match=r"identity.param_bounds: expected \(lower, upper\) of shape \(3,\) each, got \[\(3, 3\), \(3,\)\]",
    ):
        param_limits(_Limited((torch.zeros(3, 3), torch.zeros(3))))
    with pytest.raises(ValueError, match=r"identity.param_bounds: expected .* got \[\(3,\)\]"):
        param_limits(_Limited((torch.zeros(3),)))


def test_bad_input_errors(anny32):
    good = _reposed(anny32, anny32.identity.default_params())
    with pytest.raises(TypeError, match=r"layer: expected a BodyLayer, got str"):
        fit_identity("anny", good)
    with pytest.raises(ValueError, match=r"layer: has no identity backend"):
        fit_identity(BodyLayer(Rig.canonical()), good)
    with pytest.raises(ValueError, match=r"targets: expected shape \(B, 18056, 3\), got \(1, 100, 3\)"):
        fit_identity(anny32, good[:, :100])
    with pytest.raises(TypeError, match=r"targets: is float64 on cpu but the layer is float32 on cpu"):
        fit_identity(anny32, good.double())
    bad = good.clone()
    bad[0, 7, 1] = math.nan
    with pytest.raises(ValueError, match=r"targets: expected finite values, got 1 NaN/inf entries"):
        fit_identity(anny32, bad)
    with pytest.raises(TypeError, match=r"targets: expected a torch.Tensor, got list"):
        fit_identity(anny32, [[0.0]])
    for kw, msg in (
        ({"steps": -1}, r"steps: expected an int >= 0, got -1"),
        ({"steps": True}, r"steps: expected an int >= 0, got True"),
        ({"lbfgs_steps": 2.0}, r"lbfgs_steps: expected an int >= 0, got 2.0"),
        ({"lr": 0.0}, r"lr: expected a finite float > 0, got 0.0"),
        ({"lr": math.nan}, r"lr: expected a finite float > 0, got nan"),
    ):
        with pytest.raises(ValueError, match=msg):
            fit_identity(anny32, good, **kw)
    with pytest.raises(ValueError, match=r"init: expected shape \(B, 6\), got \(1, 5\)"):
        fit_identity(anny32, good, init=torch.zeros(1, 5))
    with pytest.raises(ValueError, match=r"init: expected batch 1 or 1 \(the targets' batch\), got 2"):
        fit_identity(anny32, good, init=torch.full((2, 6), 0.5))
    with pytest.raises(ValueError, match=r"init: parameter 1 must lie in \[0, 1\], got 1.5 at batch 0"):
        fit_identity(anny32, good, init=torch.tensor([[0.5, 1.5, 0.5, 0.5, 0.5, 0.5]]))
