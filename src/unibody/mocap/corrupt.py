"""Mocap corruption (paper 003 §4.4): occlusions, ghost points, permutation, broken trajectories.

One frame of M labelled markers becomes an unordered point cloud of N = M + G slots
(G = the most ghosts a frame can get, so batches stack):

- occlusion: a per-frame count drawn uniformly from ``occlusions`` of the visible markers
  disappears, the markers chosen uniformly;
- ghosts: a per-frame count drawn uniformly from ``ghosts`` of points sampled from a
  Gaussian centred on the per-axis median of the frame's visible markers, with the
  per-axis standard deviation of those markers (times ``ghost_scale``) as its std;
- permutation: the real points (markers and ghosts) move to the front of the frame in a
  random order; padding slots (zeros) follow.

``labels`` holds, for every slot, the marker index in [0, M) or M (the null label) for
ghosts and padding. :func:`break_trajectories` is the test-time noise of real sequences
(a tracked trajectory is cut in two, as passive optical systems do) and
:func:`permute_frames` turns real frames into the same :class:`MocapBatch`.

Points are raw metres in any frame; nothing here centres or rotates them. Missing input
samples are NaN (a sample with any NaN coordinate is missing).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .._checks import check_shape

__all__ = ["MocapBatch", "break_trajectories", "corrupt_frames", "permute_frames"]


@dataclass(frozen=True, slots=True)
class MocapBatch:
    """A batch of unordered mocap frames with ground-truth labels.

    Attributes:
        points: (B, N, 3) m, raw positions; padding slots are zeros.
        mask: (B, N) bool, True for real points (markers and ghosts).
        labels: (B, N) int64, marker index in [0, M) for markers, M (null) for ghosts and padding.
        available: (B, M) bool, True where marker m is among the frame's points.
    """

    points: torch.Tensor
    mask: torch.Tensor
    labels: torch.Tensor
    available: torch.Tensor

    def __post_init__(self) -> None:
        sizes: dict[str, int] = {}
        check_shape(self.points, "B N 3", name="points", sizes=sizes)
        check_shape(self.mask, "B N", name="mask", sizes=sizes)
        check_shape(self.labels, "B N", name="labels", sizes=sizes)
        check_shape(self.available, "B M", name="available", sizes=sizes)

    @property
    def num_labels(self) -> int:
        """M, the number of marker labels (the null label is M)."""
        return self.available.shape[1]

    def to(self, device: torch.device | str) -> MocapBatch:
        """The batch on ``device``."""
        return MocapBatch(*(x.to(device) for x in (self.points, self.mask, self.labels, self.available)))


def _check_counts(value: tuple[int, int], name: str) -> tuple[int, int]:
    lo, hi = (int(v) for v in value)
    if not 0 <= lo <= hi:
        raise ValueError(f"{name}: expected 0 <= lo <= hi, got {tuple(value)}")
    return lo, hi


def _check_points(points: torch.Tensor, spec: str, name: str) -> torch.Tensor:
    check_shape(points, spec, name=name)
    if not points.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point tensor, got {points.dtype}")
    if torch.isinf(points).any():
        raise ValueError(f"{name}: infinite values; use NaN for missing markers")
    return ~torch.isnan(points).any(dim=-1)


def _draw_counts(lo: int, hi: int, b: int, generator: torch.Generator, device: torch.device) -> torch.Tensor:
    return torch.randint(lo, hi + 1, (b,), generator=generator, device=device)


def _ghost_points(
    markers: torch.Tensor, visible: torch.Tensor, g: int, scale: float, generator: torch.Generator
) -> torch.Tensor:
    """(B, g, 3) samples of N(median of visible markers, diag(std of visible markers * scale)^2).

    The median is the lower median for an even count (torch.nanmedian); the std is the
    population std. Frames without visible markers give NaN (callers switch those ghosts off).
    """
    ref = markers.masked_fill(~visible[..., None], float("nan"))
    centre = ref.nanmedian(dim=1).values
    count = visible.sum(dim=1, keepdim=True).clamp_min(1).to(markers.dtype)
    mean = ref.nansum(dim=1) / count
    std = ((ref - mean[:, None]).square().nansum(dim=1) / count).sqrt()
    noise = torch.randn(markers.shape[0], g, 3, generator=generator, device=markers.device, dtype=markers.dtype)
    return centre[:, None] + noise * (std * scale)[:, None]


def _pack(
    slots: torch.Tensor,
    real: torch.Tensor,
    slot_labels: torch.Tensor,
    available: torch.Tensor,
    generator: torch.Generator | None,
) -> tuple[MocapBatch, torch.Tensor]:
    """Zero the padding, set null labels, and (with a generator) shuffle real points to the front."""
    m = available.shape[1]
    labels = torch.where(real, slot_labels, torch.full_like(slot_labels, m))
    points = torch.where(real[..., None], slots, torch.zeros_like(slots))
    b, n = real.shape
    if generator is None:
        order = torch.arange(n, device=real.device).expand(b, n)
    else:
        # Random keys in [0, 1) for real slots and [1, 2) for padding: one argsort shuffles
        # the real points and keeps them ahead of the padding.
        key = torch.rand(b, n, generator=generator, device=real.device) + (~real).to(slots.dtype)
        order = key.argsort(dim=1)
        points = points.gather(1, order[..., None].expand(b, n, 3))
        real, labels = real.gather(1, order), labels.gather(1, order)
    return MocapBatch(points, real, labels, available), order


def corrupt_frames(
    markers: torch.Tensor,
    generator: torch.Generator,
    *,
    occlusions: tuple[int, int] = (0, 5),
    ghosts: tuple[int, int] = (0, 3),
    ghost_scale: float = 1.0,
    permute: bool = True,
    exact: bool = False,
    extras: torch.Tensor | None = None,
) -> MocapBatch:
    """Occlude, add ghosts to and shuffle a batch of labelled marker frames (paper 003 §4.4).

    Args:
        markers: (B, M, 3) m, float32 or float64; NaN for markers that are missing or not
            in the layout (never counted as occlusions, never available).
        generator: torch generator on the markers' device; every random draw uses it.
        occlusions: per-frame count drawn uniformly from [lo, hi] (both included), capped
            at the number of visible markers.
        ghosts: per-frame ghost count drawn uniformly from [lo, hi]; N = M + hi slots.
            Frames without any visible marker get no ghosts.
        ghost_scale: multiplies the std of the ghost distribution.
        permute: shuffle the real points to the front of each frame. Without it, slot i < M
            holds marker i (zeros when absent) and slots M.. the ghosts.
        exact: occlude exactly ``occlusions[1]`` markers per frame (capped as above), as
            in the exact-occlusion benchmark (paper 003 Table 2).
        extras: (B, E, 3) m, optional points that are real but not in the layout (markers of
            another protocol); NaN where absent. Labelled null, never occluded.

    Returns:
        A :class:`MocapBatch` with N = M + ghosts[1] (+ E) slots per frame.

    Raises:
        TypeError: non-float markers. ValueError: bad shapes, inf values or bad ranges.
    """
    visible = _check_points(markers, "B M 3", "markers")
    lo, hi = _check_counts(occlusions, "occlusions")
    g_lo, g_hi = _check_counts(ghosts, "ghosts")
    if not ghost_scale >= 0:
        raise ValueError(f"ghost_scale: expected >= 0, got {ghost_scale}")
    b, m, _ = markers.shape
    if m == 0:
        raise ValueError("markers: expected at least one marker column, got shape (B, 0, 3)")
    dev = markers.device
    n_vis = visible.sum(dim=1)
    k = torch.full((b,), hi, device=dev) if exact else _draw_counts(lo, hi, b, generator, dev)
    # Rank visible markers by a random key (invisible ones rank last): the k first are occluded.
    key = torch.rand(b, m, generator=generator, device=dev).masked_fill(~visible, 2.0)
    rank = key.argsort(dim=1).argsort(dim=1)
    available = visible & (rank >= torch.minimum(k, n_vis)[:, None])

    ghost = _ghost_points(markers, visible, g_hi, ghost_scale, generator)
    n_ghost = _draw_counts(g_lo, g_hi, b, generator, dev).masked_fill(n_vis == 0, 0)
    ghost_on = torch.arange(g_hi, device=dev) < n_ghost[:, None]

    slots, real = torch.cat([markers, ghost], dim=1), torch.cat([available, ghost_on], dim=1)
    if extras is not None:
        check_shape(extras, "B E 3", name="extras", sizes={"B": b})
        slots = torch.cat([slots, extras.to(markers.dtype)], dim=1)
        real = torch.cat([real, ~torch.isnan(extras).any(-1)], dim=1)
    null = torch.full((slots.shape[1] - m,), m, device=dev)
    slot_labels = torch.cat([torch.arange(m, device=dev), null]).expand(b, -1)
    return _pack(slots, real, slot_labels, available, generator if permute else None)[0]


def permute_frames(
    points: torch.Tensor,
    generator: torch.Generator,
    *,
    labels: torch.Tensor,
    num_labels: int,
) -> tuple[MocapBatch, torch.Tensor]:
    """Turn real frames with known column labels into a shuffled :class:`MocapBatch`.

    For the real-data benchmark: columns of a sequence (labelled markers, ``*n`` ghosts,
    pieces of broken trajectories) become unordered points; ``order`` maps every output
    slot back to its column, so per-point predictions scatter back to columns.

    Args:
        points: (B, N, 3) m, one row per frame, NaN where a column has no sample.
        generator: torch generator on the points' device.
        labels: (N,) or (B, N) int64, each column's label in [0, num_labels], num_labels
            for ghosts. Two columns visible in the same frame must not share a label < M.
        num_labels: M.

    Returns:
        ``(batch, order)``: ``order`` (B, N) int64 is a permutation of the columns per
        frame, ``batch.points[b, i] = points[b, order[b, i]]`` for real points;
        ``order.argsort(dim=1)`` inverts it.

    Raises:
        TypeError / ValueError: bad dtypes, shapes or label values.
    """
    visible = _check_points(points, "B N 3", "points")
    b, n, _ = points.shape
    check_shape(labels, "N", "B N", name="labels", sizes={"B": b, "N": n})
    if labels.dtype != torch.long:
        raise TypeError(f"labels: expected int64, got {labels.dtype}")
    if labels.numel() and (labels.min() < 0 or labels.max() > num_labels):
        raise ValueError(f"labels: expected values in [0, {num_labels}], got [{labels.min()}, {labels.max()}]")
    slot_labels = labels.expand(b, n)
    hit = torch.where(visible, slot_labels, torch.full_like(slot_labels, num_labels))
    avail = torch.zeros(b, num_labels + 1, dtype=torch.long, device=points.device).scatter_add_(
        1, hit, torch.ones_like(hit)
    )[:, :num_labels]
    if (avail > 1).any():
        raise ValueError("labels: two visible columns of one frame share a marker label")
    return _pack(points, visible, slot_labels, avail > 0, generator)


def break_trajectories(points: np.ndarray, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Cut ``count`` random trajectories in two, as passive optical systems do (paper 003 §4.4).

    Each cut picks a frame t in [2, T-1) that has a visible sample (uniformly among those)
    and a column visible at t (uniformly): its samples from t on move to a new column, and
    the old column becomes NaN from t on. Cuts may hit earlier pieces again.

    Args:
        points: (T, N, 3) m, NaN for missing samples.
        count: number of cuts (SOMA's evaluation uses 50).
        rng: numpy generator.

    Returns:
        ``(out, source)``: ``out`` (T, N + count, 3) holds every input sample exactly once;
        ``source`` (N + count,) int64 is the input column each output column came from.

    Raises:
        ValueError: bad shape, negative count, or cuts requested on fewer than 4 frames or
            on a sequence with no visible sample in frames [2, T-1).
    """
    pts = np.asarray(points)
    if pts.ndim != 3 or pts.shape[2] != 3:
        raise ValueError(f"points: expected shape (T, N, 3), got {pts.shape}")
    if count < 0:
        raise ValueError(f"count: expected >= 0, got {count}")
    t, n, _ = pts.shape
    out = np.full((t, n + count, 3), np.nan, dtype=np.result_type(pts.dtype, np.float32))
    out[:, :n] = pts
    source = np.concatenate([np.arange(n), np.zeros(count, dtype=np.int64)])
    if count == 0:
        return out, source
    if t < 4:
        raise ValueError(f"points: breaking needs at least 4 frames (t in [2, T-1)), got {t}")
    visible = ~np.isnan(pts).any(axis=2)
    times = np.flatnonzero(visible[2 : t - 1].any(axis=1)) + 2
    if times.size == 0:
        raise ValueError("points: no visible sample in frames [2, T-1) to break")
    for i in range(count):
        at = times[rng.integers(times.size)]
        cols = np.flatnonzero(~np.isnan(out[at, : n + i]).any(axis=1))
        c = cols[rng.integers(cols.size)]
        out[at:, n + i] = out[at:, c]
        out[at:, c] = np.nan
        source[n + i] = source[c]
    return out, source
