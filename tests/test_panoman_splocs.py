"""Sparse localized components (unibody.panoman.splocs) on synthetic bumps over a grid graph.

The ground truth is a 50 × 50 grid (8-neighbour graph, unit square, 2,500 elements) carrying a
few compact bumps of different radii with disjoint supports; samples are random weights of the
bumps plus N(0, 0.01²) noise.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import dijkstra

from unibody.panoman.splocs import (
    SplocsConfig,
    SplocsResult,
    element_graph,
    project,
    sparse_localized_components,
)

SIDE = 50
RAMPS = ((0.03, 0.08), (0.06, 0.16), (0.12, 0.32))  # candidate supports in grid units
NOISE = 0.01


def grid(side: int = SIDE) -> tuple[np.ndarray, np.ndarray]:
    """(D, 3) positions on the unit square and (P, 2) 8-neighbour pairs."""
    h = 1.0 / (side - 1)
    i, j = np.meshgrid(np.arange(side), np.arange(side), indexing="ij")
    pos = np.stack([i.ravel() * h, j.ravel() * h, np.zeros(side * side)], 1)
    ids = np.arange(side * side).reshape(side, side)
    pairs = [
        (ids[:-1, :], ids[1:, :]),
        (ids[:, :-1], ids[:, 1:]),
        (ids[:-1, :-1], ids[1:, 1:]),
        (ids[1:, :-1], ids[:-1, 1:]),
    ]
    return pos, np.concatenate([np.stack([a.ravel(), b.ravel()], 1) for a, b in pairs])


def bumps(pos: np.ndarray, centres, radii) -> np.ndarray:
    """(T, D) compact bumps (1 − (d/r)²)² of Euclidean distance d, zero beyond r."""
    d = np.linalg.norm(pos[None, :, :2] - np.asarray(centres)[:, None, :], axis=2) / np.asarray(radii)[:, None]
    return np.clip(1.0 - d**2, 0.0, None) ** 2


def samples(truth: np.ndarray, n: int, seed: int, dtype=torch.float64) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    w = rng.uniform(-1.0, 1.0, (n, truth.shape[0]))
    x = 0.3 + w @ truth + NOISE * rng.normal(size=(n, truth.shape[1]))
    return torch.as_tensor(x, dtype=dtype)


def explained(result: SplocsResult, x: torch.Tensor, weights: torch.Tensor) -> float:
    """Fraction of the variance of x (about the training mean) explained by the weights."""
    err = (x - result.reconstruct(weights)).square().sum()
    return 1.0 - float(err / (x - result.mean).square().sum())


def cosine(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(T, K) cosine similarity (uncentred correlation) between rows of a and rows of b."""
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-300)
    return a @ b.T


@pytest.fixture(scope="module")
def scene():
    pos, pairs = grid()
    centres = [(0.2, 0.2), (0.75, 0.25), (0.3, 0.7), (0.75, 0.75)]
    radii = [0.07, 0.12, 0.18, 0.1]
    return pos, element_graph(pos, pairs), bumps(pos, centres, radii), np.asarray(radii)


@pytest.fixture(scope="module")
def solved(scene):
    pos, graph, truth, radii = scene
    x = samples(truth, 200, seed=1)
    cfg = SplocsConfig(num_components=4, adaptive_supports=RAMPS, iterations=10)
    return x, sparse_localized_components(x, graph, cfg)


def test_recovers_each_bump_once(scene, solved):
    _, _, truth, _ = scene
    _, res = solved
    sim = np.abs(cosine(truth, res.components.numpy()))
    match = sim.argmax(1)
    assert sorted(match.tolist()) == [0, 1, 2, 3], f"bumps map to components {match}, similarities\n{sim}"
    assert sim.max(1).min() > 0.9, f"best similarity per bump {sim.max(1)}"
    assert (np.sort(sim, axis=1)[:, -2] < 0.2).all(), "a bump is split over two components"


def test_components_are_localized_and_sparse(scene, solved):
    pos, graph, truth, radii = scene
    _, res = solved
    comps = res.components.numpy()
    match = np.abs(cosine(truth, comps)).argmax(0)  # true bump of each component
    dist = dijkstra(graph, directed=False, indices=res.centers.numpy())
    sizes = res.support_sizes().numpy()
    for k in range(comps.shape[0]):
        nz = np.flatnonzero(comps[k])
        d_max = float(res.supports[k, 1])
        assert dist[k, nz].max() <= d_max + 1e-12, f"component {k} reaches beyond its support"
        bump = truth[match[k]] > 0
        assert bump[res.centers[k]], f"component {k} is centred outside its bump"
        outside = (comps[k][~bump] ** 2).sum() / (comps[k] ** 2).sum()
        assert outside < 0.01, f"component {k}: {outside:.3%} of its energy lies outside its bump"
        assert sizes[k] <= 3 * bump.sum(), f"support sizes {sizes} vs bump sizes {(truth > 0).sum(1)}"
    assert sizes.sum() < 0.35 * comps.size, f"support sizes {sizes} of {comps.shape[1]} elements each"


def test_reconstruction_train_and_held_out(scene, solved):
    _, _, truth, _ = scene
    x, res = solved
    # The noise floor leaves 0.8 % of the variance unexplainable; 0.9 % is lost here.
    assert explained(res, x, res.weights) > 0.985
    held_out = samples(truth, 100, seed=2)
    assert explained(res, held_out, project(res, held_out)) > 0.985
    assert float(res.weights.abs().max()) <= 1.0 + 1e-12
    assert (torch.diff(res.objective) <= 1e-9 * res.objective[0]).all(), res.objective
    assert float(res.objective[-1]) < 0.95 * float(res.objective[0])  # the alternation improves on greedy


def test_adaptive_support_grows_with_the_bump():
    pos, pairs = grid()
    graph = element_graph(pos, pairs)
    truth = bumps(pos, [(0.2, 0.25), (0.65, 0.6)], [0.06, 0.27])
    x = samples(truth, 150, seed=3)
    res = sparse_localized_components(x, graph, SplocsConfig(num_components=2, adaptive_supports=RAMPS))
    match = np.abs(cosine(truth, res.components.numpy())).argmax(1)
    small, large = (float(res.supports[k, 1]) for k in match)
    assert (small, large) == (0.08, 0.32), f"small bump got d_max {small}, large got {large}"


def test_fixed_support_applies_to_all(scene):
    _, graph, truth, _ = scene
    x = samples(truth, 100, seed=4)
    res = sparse_localized_components(x, graph, SplocsConfig(num_components=3, support=(0.05, 0.15), iterations=3))
    assert torch.equal(res.supports, torch.tensor([[0.05, 0.15]] * 3, dtype=x.dtype))
    dist = dijkstra(graph, directed=False, indices=res.centers.numpy())
    assert all(dist[k, res.components[k].numpy() != 0].max() <= 0.15 for k in range(3))


def test_more_components_never_increase_training_error(scene):
    _, graph, truth, _ = scene
    x = samples(truth, 80, seed=5)
    errors = []
    for k in range(1, 7):
        res = sparse_localized_components(
            x, graph, SplocsConfig(num_components=k, adaptive_supports=RAMPS, iterations=5)
        )
        errors.append(float((x - res.reconstruct(res.weights)).square().sum()))
    assert all(b <= a * (1 + 1e-9) for a, b in zip(errors[:-1], errors[1:], strict=True)), errors
    assert errors[3] < 0.1 * errors[0]  # four components explain four bumps


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_deterministic_and_dtype(scene, dtype):
    _, graph, truth, _ = scene
    x = samples(truth, 60, seed=6, dtype=dtype)
    cfg = SplocsConfig(num_components=3, adaptive_supports=RAMPS, iterations=3)
    calls = []
    a = sparse_localized_components(x, graph, cfg, progress=lambda *s: calls.append(s))
    b = sparse_localized_components(x, graph, cfg)
    for field in ("mean", "components", "weights", "centers", "supports", "objective"):
        assert torch.equal(getattr(a, field), getattr(b, field)), field
    assert a.components.dtype == a.weights.dtype == a.mean.dtype == dtype
    assert a.centers.dtype == torch.long and a.support_sizes().shape == (3,)
    assert calls == [("init", i, 3) for i in (1, 2, 3)] + [("iterate", i, 3) for i in (1, 2, 3)]


def test_project_recovers_exact_weights(solved):
    _, res = solved
    w = torch.linspace(-2.0, 2.0, 40, dtype=res.mean.dtype).reshape(10, 4)
    torch.testing.assert_close(project(res, res.reconstruct(w)), w, atol=1e-9, rtol=0)


def test_adjacency_forms_agree(scene):
    pos, graph, truth, _ = scene
    x = samples(truth, 40, seed=7)
    coo = graph.tocoo()
    cfg = SplocsConfig(num_components=2, adaptive_supports=RAMPS, iterations=2)
    a = sparse_localized_components(x, graph, cfg)
    b = sparse_localized_components(x, (torch.as_tensor(coo.row), coo.col, coo.data), cfg)
    assert torch.equal(a.components, b.components)
    assert abs(graph - graph.T).max() == 0
    i, j = coo.row[0], coo.col[0]
    assert graph[i, j] == pytest.approx(np.linalg.norm(pos[i] - pos[j]))


def test_bad_inputs_raise(scene):
    _, graph, truth, _ = scene
    x = samples(truth, 10, seed=8)
    cfg = SplocsConfig(num_components=2)
    with pytest.raises(ValueError, match="num_components"):
        SplocsConfig(num_components=0)
    with pytest.raises(ValueError, match="support"):
        SplocsConfig(num_components=1, support=(0.2, 0.1))
    with pytest.raises(ValueError, match="adaptive_supports"):
        SplocsConfig(num_components=1, adaptive_supports=())
    with pytest.raises(ValueError, match="sparsity"):
        SplocsConfig(num_components=1, sparsity=-1.0)
    with pytest.raises(ValueError, match=r"X: expected shape \(N, D\)"):
        sparse_localized_components(x[0], graph, cfg)
    with pytest.raises(ValueError, match="X: expected at least 2 samples"):
        sparse_localized_components(x[:1], graph, cfg)
    bad = x.clone()
    bad[3, 5] = float("nan")
    with pytest.raises(ValueError, match="X: expected finite"):
        sparse_localized_components(bad, graph, cfg)
    with pytest.raises(ValueError, match="X: expected a floating-point"):
        sparse_localized_components(x.long(), graph, cfg)
    with pytest.raises(ValueError, match="adjacency: expected shape"):
        sparse_localized_components(x[:, :-1], graph, cfg)
    with pytest.raises(ValueError, match="adjacency: edge weights"):
        sparse_localized_components(x, -graph, cfg)
    with pytest.raises(ValueError, match="adjacency: element ids"):
        sparse_localized_components(x, (np.array([0]), np.array([x.shape[1]]), np.array([1.0])), cfg)
    with pytest.raises(ValueError, match="adjacency: expected a scipy sparse"):
        sparse_localized_components(x, graph.toarray(), cfg)
    with pytest.raises(TypeError, match="config"):
        sparse_localized_components(x, graph, {"num_components": 2})
    with pytest.raises(ValueError, match="pairs"):
        element_graph(np.zeros((3, 3)), np.array([[0, 3]]))
    res = sparse_localized_components(x, graph, SplocsConfig(num_components=1, iterations=1))
    with pytest.raises(ValueError, match=r"X: expected shape \(N, D\) with D=2500"):
        project(res, x[:, :-1])
    with pytest.raises(TypeError, match="X: is float32"):
        project(res, x.float())
    assert sp.issparse(graph)


def test_input_is_not_modified(scene):
    _, graph, truth, _ = scene
    x = samples(truth, 30, seed=9).T.contiguous().T  # a transposed view: the layout the solver uses
    before = x.clone()
    sparse_localized_components(x, graph, SplocsConfig(num_components=2, iterations=1))
    assert torch.equal(x, before)


def test_constant_data_gives_empty_components(scene):
    _, graph, _, _ = scene
    x = torch.full((6, SIDE * SIDE), 0.25, dtype=torch.float64)
    res = sparse_localized_components(x, graph, SplocsConfig(num_components=2, iterations=2))
    assert res.support_sizes().tolist() == [0, 0]
    assert torch.equal(res.weights, torch.zeros_like(res.weights))
    assert torch.equal(project(res, x), torch.zeros(6, 2, dtype=x.dtype))
    torch.testing.assert_close(res.reconstruct(res.weights), x)
