"""Mocap corruption: occlusion/ghost statistics, exact label bookkeeping, broken trajectories."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from unibody.mocap.corrupt import MocapBatch, break_trajectories, corrupt_frames, permute_frames


def _frames(b: int, m: int, seed: int = 0, dtype=torch.float32) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    body = torch.randn(b, m, 3, generator=g, dtype=dtype) * torch.tensor([0.3, 0.8, 0.2], dtype=dtype)
    return body + torch.randn(b, 1, 3, generator=g, dtype=dtype) * 2.0


def _gen(seed: int = 1) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _check_bookkeeping(markers: torch.Tensor, out: MocapBatch, ghost_max: int) -> None:
    """Every invariant that ties a MocapBatch to the markers it came from."""
    b, m, _ = markers.shape
    assert out.points.shape == (b, m + ghost_max, 3) and out.num_labels == m
    lab = out.labels
    is_marker = lab < m
    # Labelled points are exactly the marker they claim to be.
    src = markers.gather(1, lab.clamp_max(m - 1)[..., None].expand(-1, -1, 3))
    assert torch.equal(out.points[is_marker], src[is_marker])
    assert not torch.isnan(out.points).any()
    # Real points first, padding (zeros, null label) after.
    assert torch.equal(out.mask, out.mask.sort(dim=1, descending=True).values)
    assert (out.points[~out.mask] == 0).all() and (lab[~out.mask] == m).all()
    assert not is_marker[~out.mask].any()
    # available <=> the label is present, at most once per frame; never for missing markers.
    counts = torch.zeros(b, m + 1, dtype=torch.long).scatter_add_(1, lab, torch.ones_like(lab))[:, :m]
    assert counts.max() <= 1
    assert torch.equal(out.available, counts == 1)
    assert not (out.available & torch.isnan(markers).any(-1)).any()


def test_occlusion_count_statistics():
    b, m = 20000, 41
    markers = _frames(b, m)
    out = corrupt_frames(markers, _gen(), occlusions=(0, 5), ghosts=(0, 0))
    occluded = m - out.available.sum(1)
    assert occluded.float().mean().item() == pytest.approx(2.5, rel=0.02)
    freq = torch.bincount(occluded, minlength=6).float() / b
    assert freq.shape == (6,) and torch.allclose(freq, torch.full((6,), 1 / 6), atol=0.015)
    # Which markers are hit is uniform too.
    per_marker = (~out.available).float().mean(0)
    assert torch.allclose(per_marker, torch.full((m,), 2.5 / m), atol=0.01)


def test_ghost_count_and_distribution():
    b, m = 20000, 41
    markers = _frames(b, m, dtype=torch.float64)
    out = corrupt_frames(markers, _gen(), occlusions=(0, 0), ghosts=(0, 3))
    ghost = out.mask & (out.labels == m)
    freq = torch.bincount(ghost.sum(1), minlength=4).double() / b
    assert torch.allclose(freq, torch.full((4,), 0.25, dtype=torch.float64), atol=0.015)
    # Reference statistics computed independently (numpy; M is odd so the median is unique).
    x = markers.numpy()
    centre, std = np.median(x, axis=1), x.std(axis=1)
    bi, _ = torch.nonzero(ghost, as_tuple=True)
    z = (out.points[ghost].numpy() - centre[bi.numpy()]) / std[bi.numpy()]
    assert np.abs(z.mean(0)).max() < 0.02
    assert np.abs(z.std(0) - 1.0).max() < 0.02
    scaled = corrupt_frames(markers, _gen(), occlusions=(0, 0), ghosts=(3, 3), ghost_scale=2.0)
    g2 = scaled.mask & (scaled.labels == m)
    z2 = (scaled.points[g2].numpy() - np.repeat(centre, 3, 0)) / np.repeat(std, 3, 0)
    assert np.abs(z2.std(0) - 2.0).max() < 0.04


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_labels_follow_points_through_permutation(dtype):
    b, m = 512, 41
    markers = _frames(b, m, dtype=dtype)
    markers[:, 5] = float("nan")  # not in this layout
    markers[::3, 7, 1] = float("nan")  # missing in some frames (one NaN coordinate is enough)
    out = corrupt_frames(markers, _gen(), occlusions=(1, 4), ghosts=(0, 3))
    assert out.points.dtype == dtype and out.labels.dtype == torch.long and out.mask.dtype == torch.bool
    _check_bookkeeping(markers, out, 3)
    assert not out.available[:, 5].any() and not out.available[::3, 7].any()
    visible = (~torch.isnan(markers).any(-1)).sum(1)
    occluded = visible - out.available.sum(1)
    assert occluded.min() >= 1 and occluded.max() <= 4
    ghosts = (out.mask & (out.labels == m)).sum(1)
    assert torch.equal(out.mask.sum(1), out.available.sum(1) + ghosts)
    # The order really is shuffled.
    assert (out.labels[:, :10] != torch.arange(10)).float().mean() > 0.5


def test_exact_occlusions_and_cap():
    b, m = 300, 41
    markers = _frames(b, m)
    out = corrupt_frames(markers, _gen(), occlusions=(0, 5), ghosts=(0, 0), exact=True)
    assert (out.available.sum(1) == m - 5).all()
    few = markers.clone()
    few[:, 3:] = float("nan")  # only 3 visible: all of them go
    out = corrupt_frames(few, _gen(), occlusions=(0, 5), ghosts=(2, 2), exact=True)
    assert not out.available.any()
    assert (out.mask.sum(1) == 2).all()  # ghosts still come from the visible markers' statistics


def test_no_permutation_keeps_slots():
    markers = _frames(64, 10)
    out = corrupt_frames(markers, _gen(), occlusions=(2, 2), ghosts=(1, 1), permute=False)
    lab = out.labels[:, :10]
    slot = torch.arange(10).expand(64, 10)
    assert torch.equal(lab, torch.where(out.available, slot, torch.full_like(slot, 10)))
    assert torch.equal(out.points[:, :10][out.available], markers[out.available])
    assert out.mask[:, 10].all()


def test_determinism_and_empty_frames():
    markers = _frames(32, 12)
    markers[0] = float("nan")  # a frame with nothing visible gets nothing, not NaN ghosts
    a = corrupt_frames(markers, _gen(7))
    b = corrupt_frames(markers, _gen(7))
    for x, y in zip((a.points, a.mask, a.labels, a.available), (b.points, b.mask, b.labels, b.available), strict=True):
        assert torch.equal(x, y)
    assert not a.mask[0].any() and not torch.isnan(a.points).any()


def test_corrupt_errors():
    g = _gen()
    with pytest.raises(ValueError, match=r"markers: expected shape \(B, M, 3\)"):
        corrupt_frames(torch.zeros(4, 3), g)
    with pytest.raises(TypeError, match="floating-point"):
        corrupt_frames(torch.zeros(2, 4, 3, dtype=torch.long), g)
    with pytest.raises(ValueError, match="infinite"):
        corrupt_frames(torch.full((2, 4, 3), float("inf")), g)
    with pytest.raises(ValueError, match=r"occlusions: expected 0 <= lo <= hi, got \(3, 1\)"):
        corrupt_frames(torch.zeros(2, 4, 3), g, occlusions=(3, 1))
    with pytest.raises(ValueError, match="ghosts"):
        corrupt_frames(torch.zeros(2, 4, 3), g, ghosts=(-1, 2))
    with pytest.raises(ValueError, match="ghost_scale"):
        corrupt_frames(torch.zeros(2, 4, 3), g, ghost_scale=-1.0)
    with pytest.raises(ValueError, match="at least one marker"):
        corrupt_frames(torch.zeros(2, 0, 3), g)


# --------------------------------------------------------------------- broken trajectories


def _sequence(t: int = 200, n: int = 20, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(t, n, 3))
    pts[rng.random((t, n)) < 0.1] = np.nan  # real gaps
    pts[:, 4] = np.nan  # a column that is never visible
    return pts


def test_break_trajectories_keeps_every_sample_once():
    pts = _sequence()
    t, n, _ = pts.shape
    out, source = break_trajectories(pts, 50, np.random.default_rng(3))
    assert out.shape == (t, n + 50, 3) and source.shape == (n + 50,)
    assert np.array_equal(source[:n], np.arange(n)) and source.dtype == np.int64
    vis = ~np.isnan(out).any(axis=2)
    for c in range(n):
        cols = np.flatnonzero(source == c)
        # At most one piece holds a sample at any frame, and together they rebuild the column.
        assert (vis[:, cols].sum(axis=1) <= 1).all()
        rebuilt = np.nansum(np.where(vis[:, cols, None], out[:, cols], 0.0), axis=1)
        rebuilt[~vis[:, cols].any(axis=1)] = np.nan
        np.testing.assert_array_equal(rebuilt, pts[:, c])
    # Each new column is empty before its cut, which lies in [2, T-1).
    first = np.array([np.flatnonzero(vis[:, k])[0] for k in range(n, n + 50) if vis[:, k].any()])
    assert first.min() >= 2 and first.max() < t - 1
    assert 4 not in source[n:]


def test_break_trajectories_edge_cases():
    pts = _sequence(t=10, n=5)
    out, source = break_trajectories(pts, 0, np.random.default_rng(0))
    np.testing.assert_array_equal(out, pts)
    with pytest.raises(ValueError, match="at least 4 frames"):
        break_trajectories(pts[:3], 1, np.random.default_rng(0))
    with pytest.raises(ValueError, match="no visible sample"):
        break_trajectories(np.full((10, 5, 3), np.nan), 1, np.random.default_rng(0))
    with pytest.raises(ValueError, match="count"):
        break_trajectories(pts, -1, np.random.default_rng(0))
    with pytest.raises(ValueError, match=r"\(T, N, 3\)"):
        break_trajectories(pts[..., :2], 1, np.random.default_rng(0))


def test_permute_frames_after_breaking():
    m = 15  # columns 0..14 are markers, 15..19 ghosts ('*n' slots)
    pts = _sequence()
    out, source = break_trajectories(pts, 30, np.random.default_rng(5))
    col_labels = torch.from_numpy(np.where(source < m, source, m))
    x = torch.from_numpy(out)
    batch, order = permute_frames(x, _gen(), labels=col_labels, num_labels=m)
    b, n = x.shape[:2]
    assert torch.equal(order.sort(dim=1).values, torch.arange(n).expand(b, n))
    visible = ~torch.isnan(x).any(-1)
    assert torch.equal(batch.mask, visible.gather(1, order))
    assert torch.equal(batch.points[batch.mask], x.gather(1, order[..., None].expand(-1, -1, 3))[batch.mask])
    assert torch.equal(batch.labels, torch.where(batch.mask, col_labels[order], m))
    # Scatter back to columns with the inverse permutation.
    inverse = order.argsort(dim=1)
    assert torch.equal(batch.labels.gather(1, inverse), torch.where(visible, col_labels.expand(b, n), m))
    want = torch.zeros(b, m, dtype=torch.bool)
    for c in range(m):
        want[:, c] = visible[:, source == c].any(1) if (source == c).any() else False
    assert torch.equal(batch.available, want)
    assert torch.equal(batch.mask, batch.mask.sort(dim=1, descending=True).values)


def test_permute_frames_errors():
    x = torch.zeros(2, 3, 3)
    with pytest.raises(ValueError, match="two visible columns"):
        permute_frames(x, _gen(), labels=torch.tensor([0, 0, 1]), num_labels=2)
    with pytest.raises(ValueError, match=r"expected values in \[0, 2\]"):
        permute_frames(x, _gen(), labels=torch.tensor([0, 1, 3]), num_labels=2)
    with pytest.raises(TypeError, match="int64"):
        permute_frames(x, _gen(), labels=torch.tensor([0.0, 1.0, 2.0]), num_labels=2)
    with pytest.raises(ValueError, match="labels: expected shape"):
        permute_frames(x, _gen(), labels=torch.tensor([0, 1]), num_labels=2)


def test_extras_are_real_null_points_never_occluded():
    markers = torch.randn(50, 6, 3, generator=torch.Generator().manual_seed(0))
    extras = torch.randn(50, 4, 3, generator=torch.Generator().manual_seed(1))
    extras[:, 3] = float("nan")  # the fourth extra is absent everywhere
    b = corrupt_frames(markers, torch.Generator().manual_seed(2), occlusions=(6, 6), ghosts=(0, 0), extras=extras)
    assert b.points.shape == (50, 10, 3)
    assert not b.available.any()  # every marker occluded ...
    assert (b.mask.sum(1) == 3).all() and (b.labels[b.mask] == 6).all()  # ... the three extras stay, null
    got = b.points[b.mask].view(50, 3, 3)
    assert torch.allclose(got.sort(dim=1).values, extras[:, :3].sort(dim=1).values)
    with pytest.raises(ValueError, match="extras"):
        corrupt_frames(markers, torch.Generator(), extras=extras[:10])
