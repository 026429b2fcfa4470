"""Retries only where a sequence's settled labels can still change (issue 38 item 5)."""

from __future__ import annotations

import numpy as np
import torch

from unibody.mocap.labeler import Labeler, frame_probabilities, sequence_probabilities
from unibody.mocap.tracklets import column_spans, undecided_frames

L = 5  # labels 0..4, null 5


def _random_prob(t: int, n: int, seed: int, sharp: float = 3.0) -> tuple[torch.Tensor, torch.Tensor]:
    """(T, N, L+1) noisy evidence: each column favours one label, frames disagree now and then."""
    g = torch.Generator().manual_seed(seed)
    favour = torch.randint(L + 1, (n,), generator=g)
    logits = torch.randn(t, n, L + 1, generator=g)
    logits[torch.arange(t)[:, None], torch.arange(n)[None], favour[None].expand(t, n)] += sharp
    vis = torch.rand(t, n, generator=g) < 0.85
    return torch.where(vis[..., None], logits.softmax(-1), 0.0), vis


def _span_best(prob, vis, span) -> np.ndarray:
    s, p = span.numpy(), prob.double().numpy()
    v = vis.numpy() & (s >= 0)
    ev = np.zeros((int(s.max()) + 1, p.shape[2]))
    np.add.at(ev, s[v], p[v])
    return ev.argmax(1)


def test_frames_left_out_cannot_change_any_span_label():
    """The bound: whatever the unsure frames left out become, every span keeps its best label."""
    for seed in range(6):
        prob, vis = _random_prob(60, 7, seed, sharp=1.0 + 0.5 * seed)
        unsure = torch.rand(60, generator=torch.Generator().manual_seed(100 + seed)) < 0.3
        redo = undecided_frames(prob, vis, unsure)
        assert bool((redo <= unsure).all())  # only unsure frames are ever retried
        span = column_spans(prob, vis)
        best = _span_best(prob, vis, span)
        left = unsure & ~redo
        g = torch.Generator().manual_seed(200 + seed)
        for _ in range(20):  # adversarial: the left-out frames' rows become one-hot on other labels
            other = prob.clone()
            k = torch.randint(L + 1, (int(left.sum()), 7), generator=g)
            other[left] = torch.nn.functional.one_hot(k, L + 1).float()
            other = torch.where(vis[..., None], other, 0.0)
            assert np.array_equal(_span_best(other, vis, span), best)


def test_close_spans_are_retried_and_clear_ones_are_not():
    t = 40
    prob = torch.zeros(t, 2, L + 1)
    prob[:, 0, 0] = 1.0  # column 0: label 0 in every frame, a lead of 40
    prob[:, 1, 1], prob[:, 1, 2] = 0.52, 0.48  # column 1: label 1 ahead by 0.04 a frame
    vis = torch.ones(t, 2, dtype=torch.bool)
    unsure = torch.zeros(t, dtype=torch.bool)
    unsure[[3, 17]] = True
    assert undecided_frames(prob, vis, unsure).nonzero()[:, 0].tolist() == [3, 17]
    vis[:, 1] = False  # only the clear column is left: nothing can change
    assert not bool(undecided_frames(prob, vis, unsure).any())
    assert not bool(undecided_frames(prob, vis, torch.zeros(t, dtype=torch.bool)).any())


def test_sequence_probabilities_retry_only_the_undecided_frames(monkeypatch):
    """Retried frames come from the full labeller, the others from the one pass without retries."""
    import unibody.mocap.tracklets as tracklets

    torch.manual_seed(1)
    first = Labeler(L, width=16, layers=1, heads=2, refine=1)
    template, torso = torch.randn(L, 3), torch.arange(L) < 4
    model = Labeler(L, width=16, layers=1, heads=2, orienter=first, template=template, torso=torso, retry=1.0).eval()
    g = torch.Generator().manual_seed(3)
    walk = torch.randn(1, 6, 3, generator=g) * 0.3 + 0.01 * torch.randn(48, 6, 3, generator=g).cumsum(0)
    walk[5:9, 2] = float("nan")  # a gap
    plain = frame_probabilities(model, walk, retry=0.0)
    full = frame_probabilities(model, walk)
    vis = torch.isfinite(walk).all(-1)
    # an untrained model leaves every span close: undecided_frames (tested above) would pick every
    # unsure frame; pick every third instead to see each frame come from the right pass
    seen = {}

    def every_third(prob, visible, unsure, config=None):
        seen["unsure"] = unsure.clone()
        torch.testing.assert_close(prob, plain.prob)
        assert torch.equal(visible, vis)
        return unsure & (torch.arange(len(unsure)) % 3 == 0)

    monkeypatch.setattr(tracklets, "undecided_frames", every_third)
    seq = sequence_probabilities(model, walk)
    assert bool(seen["unsure"].all())  # retry 1.0: every frame is unsure
    redo = torch.arange(48) % 3 == 0
    torch.testing.assert_close(seq.prob[redo], full.prob[redo])
    torch.testing.assert_close(seq.prob[~redo], plain.prob[~redo])
    assert torch.equal(seq.labels[~redo], plain.labels[~redo]) and torch.equal(seq.labels[redo], full.labels[redo])
    assert not torch.allclose(full.prob[redo], plain.prob[redo])  # the retries changed those frames
    off = sequence_probabilities(model.with_config(retry=0.0), walk)  # no retries asked: one pass
    torch.testing.assert_close(off.prob, plain.prob)
