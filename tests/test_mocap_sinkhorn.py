"""Log-domain Sinkhorn with dustbins: marginals, gradients, padding, and a plain reference.

Without gradients the iterations run on scalings (the labelling path); with gradients in the
log domain: ``_run`` picks one, and the value tests run on both."""

from __future__ import annotations

import pytest
import torch

from unibody.mocap.sinkhorn import log_sinkhorn


def _case(b=3, n=7, num_labels=5, dtype=torch.float64, seed=0, scale=1.0):
    g = torch.Generator().manual_seed(seed)
    scores = scale * torch.randn(b, n, num_labels, generator=g, dtype=dtype)
    mask = torch.ones(b, n, dtype=torch.bool)
    mask[0, 5:] = False  # two padding rows
    mask[1, 0] = False  # padding not only at the end
    mask[1, 3] = False
    return scores, torch.tensor(0.7, dtype=dtype), mask


def _run(scores, bin_score, mask, iters, grad):
    """log_sinkhorn by its log-domain path (grad=True, scores need gradients) or its scaling path."""
    if grad:
        return log_sinkhorn(scores.detach().requires_grad_(True), bin_score, mask, iters).detach()
    with torch.no_grad():
        return log_sinkhorn(scores, bin_score, mask, iters)


def _plain_sinkhorn(scores, bin_score, mask, iters):
    """Textbook multiplicative Sinkhorn on the unnormalised marginals (the reference)."""
    b, n, num_labels = scores.shape
    z = torch.full((b, n + 1, num_labels + 1), float(bin_score), dtype=scores.dtype)
    z[:, :n, :num_labels] = scores
    k = z.exp()
    n_valid = mask.sum(1).to(scores.dtype)
    mu = torch.cat([mask.to(scores.dtype), torch.full((b, 1), float(num_labels), dtype=scores.dtype)], 1)
    nu = torch.cat([torch.ones(b, num_labels, dtype=scores.dtype), n_valid[:, None]], 1)
    a = torch.ones_like(mu)
    c = torch.ones_like(nu)
    for _ in range(iters):
        a = mu / (k @ c[:, :, None])[..., 0]
        c = nu / (k.transpose(1, 2) @ a[:, :, None])[..., 0]
    return a[:, :, None] * k * c[:, None, :]


@pytest.mark.parametrize("grad", [False, True])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_marginals_with_padding(dtype, grad):
    scores, bin_score, mask = _case(dtype=dtype, scale=2.0)
    plan = _run(scores, bin_score, mask, 300, grad).exp()
    b, n, num_labels = scores.shape
    assert plan.shape == (b, n + 1, num_labels + 1)
    rows, cols = plan.sum(2), plan.sum(1)
    n_valid = mask.sum(1).to(dtype)
    torch.testing.assert_close(rows[:, :n], mask.to(dtype), atol=1e-4, rtol=0)
    torch.testing.assert_close(rows[:, n], torch.full((b,), float(num_labels), dtype=dtype), atol=1e-4, rtol=0)
    torch.testing.assert_close(cols[:, :num_labels], torch.ones(b, num_labels, dtype=dtype), atol=1e-4, rtol=0)
    torch.testing.assert_close(cols[:, num_labels], n_valid, atol=1e-4, rtol=0)
    # padding rows carry exactly no mass, so they cannot steal a label
    assert float(plan[~torch.cat([mask, torch.ones(b, 1, dtype=torch.bool)], 1)].abs().max()) == 0.0


@pytest.mark.parametrize("grad", [False, True])
def test_more_points_than_labels_and_empty_frame(grad):
    g = torch.Generator().manual_seed(3)
    scores = torch.randn(2, 9, 4, generator=g, dtype=torch.float64)
    mask = torch.ones(2, 9, dtype=torch.bool)
    mask[1] = False  # a frame with no real points: all label mass goes to the dustbin row
    plan = _run(scores, torch.tensor(1.0, dtype=torch.float64), mask, 200, grad).exp()
    torch.testing.assert_close(plan[0, :9].sum(1), torch.ones(9, dtype=torch.float64), atol=1e-4, rtol=0)
    torch.testing.assert_close(plan[0, 9].sum(), torch.tensor(4.0, dtype=torch.float64), atol=1e-4, rtol=0)
    torch.testing.assert_close(plan[1, 9, :4], torch.ones(4, dtype=torch.float64), atol=1e-6, rtol=0)
    assert float(plan[1, :9].abs().max()) == 0.0


@pytest.mark.parametrize("grad", [False, True])
def test_matches_plain_sinkhorn(grad):
    scores, bin_score, mask = _case(scale=1.0, seed=1)
    ref = _plain_sinkhorn(scores, bin_score, mask, iters=50)
    got = _run(scores, bin_score, mask, 50, grad).exp()
    torch.testing.assert_close(got, ref, atol=1e-10, rtol=1e-8)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_scaling_path_matches_log_path(dtype):
    # labeler-like sizes and score spreads (rows of the shipped labelers span up to ~57)
    scores, bin_score, mask = _case(b=16, n=44, num_labels=41, dtype=dtype, seed=4, scale=8.0)
    mask[2] = False  # an empty frame
    fast, slow = _run(scores, bin_score, mask, 35, False), _run(scores, bin_score, mask, 35, True)
    real = torch.cat([mask, torch.ones(16, 1, dtype=torch.bool)], 1)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(fast.exp(), slow.exp(), atol=tol, rtol=tol)  # the dustbin corner holds ~40
    live = real[..., None] & (slow > -1e3)  # the empty frame's dustbin column has mass 0 in both
    torch.testing.assert_close(fast[live], slow[live], atol=1e3 * tol, rtol=0)  # logs of tiny entries: looser
    assert bool((fast[~live] < -5e3).all())  # padding rows and no-mass entries: very negative, no mass


def test_wide_rows_take_the_log_path():
    # Frame 0 forces mass through entries exp(-150) below their rows' tops: float32 scalings
    # would underflow there and drift from the log-domain plan (by ~0.01 after 300 iterations).
    scores = torch.tensor([[[0.0, -150.0], [0.0, -150.0]], [[0.0, 0.0], [1.0, 0.0]]])
    mask = torch.ones(2, 2, dtype=torch.bool)
    for iters in (35, 300):
        fast, slow = (_run(scores, torch.tensor(-100.0), mask, iters, g) for g in (False, True))
        torch.testing.assert_close(fast.exp(), slow.exp(), atol=1e-6, rtol=0)
        assert torch.isfinite(fast).all()


def test_strong_scores_pick_the_permutation():
    # A clear one-to-one assignment with one ghost point and one missing label.
    scores = torch.full((1, 4, 4), -8.0, dtype=torch.float64)
    for p, lab in [(0, 2), (1, 0), (2, 3)]:
        scores[0, p, lab] = 8.0
    plan = log_sinkhorn(scores, torch.tensor(0.0, dtype=torch.float64), torch.ones(1, 4, dtype=torch.bool), 100)
    best = plan[0, :4].argmax(1)
    assert best.tolist() == [2, 0, 3, 4]  # point 3 is a ghost -> dustbin column 4
    # label 1 is unmatched: its column mass sits in the dustbin row; the corner holds the 3 matches
    torch.testing.assert_close(plan[0, 4, 1].exp(), torch.tensor(1.0, dtype=torch.float64), atol=1e-3, rtol=0)
    torch.testing.assert_close(plan[0, 4, 4].exp(), torch.tensor(3.0, dtype=torch.float64), atol=0.2, rtol=0)


def test_gradcheck_float64():
    scores, _, mask = _case(b=2, n=4, num_labels=3, seed=2)
    scores.requires_grad_(True)
    bin_score = torch.tensor(0.3, dtype=torch.float64, requires_grad=True)
    mask = torch.tensor([[True, True, False, True], [True, True, True, True]])
    # padding rows excluded from the checked output: their value is a -1e4 sentinel
    keep = torch.cat([mask, torch.ones(2, 1, dtype=torch.bool)], 1)

    def f(s, bs):
        return log_sinkhorn(s, bs, mask, iters=10)[keep]

    assert torch.autograd.gradcheck(f, (scores, bin_score), eps=1e-6, atol=1e-6)


def test_no_nan_with_padding_forward_and_backward():
    scores, bin_score, mask = _case(dtype=torch.float32, scale=30.0)
    scores.requires_grad_(True)
    bin_score = bin_score.float().requires_grad_(True)
    plan = log_sinkhorn(scores, bin_score, mask)
    assert torch.isfinite(plan).all()
    # a loss that touches every entry, padding rows included
    (plan * torch.rand_like(plan)).sum().backward()
    assert torch.isfinite(scores.grad).all() and torch.isfinite(bin_score.grad).all()


def test_errors():
    s = torch.zeros(1, 3, 2)
    m = torch.ones(1, 3, dtype=torch.bool)
    with pytest.raises(ValueError, match="row_mask: expected shape"):
        log_sinkhorn(s, torch.tensor(1.0), m[:, :2])
    with pytest.raises(TypeError, match="row_mask: expected a bool"):
        log_sinkhorn(s, torch.tensor(1.0), m.float())
    with pytest.raises(ValueError, match="bin_score: expected a scalar"):
        log_sinkhorn(s, torch.ones(2), m)
    with pytest.raises(ValueError, match="iters"):
        log_sinkhorn(s, torch.tensor(1.0), m, iters=0)
