"""The settings of the marker solve (:class:`SolveConfig`): weights, priors and schedules."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch

__all__ = ["SolveConfig"]


_INT_FIELDS = ("shape_components", "stage1_frames", "stage1_iters", "window", "recheck_every", "min_markers")
_NONNEGATIVE_FIELDS = (
    "pose_prior_weight",
    "shape_prior_weight",
    "missing_prior_gain",
    "min_visible",
    "robust",
    "acceleration_robust",
)


@dataclass(frozen=True)
class SolveConfig:
    """Weights and schedules of :func:`~.solve.solve_markers` and :func:`~.derive.derive_layout`.

    Every residual is divided by a standard deviation, so weights are in units of "sigmas".

    Attributes:
        shape_components: K, PCA coefficients fitted in stage 1.
        stage1_frames: frames of stage 1 (all frames when the sequence is shorter).
        stage1_iters: LM iterations per anneal level (and of the pose-only warm-up).
        stage1_anneal: multipliers of the pose, shape and slide prior weights, one level each
            (MoSh: [1, .5, .25, .125] relative to the data).
        marker_std: m, std of a marker residual (model and placement error, not only noise).
        robust: m, Cauchy scale of the marker residuals: a marker d from its model marker costs
            ``c^2 log(1 + d^2 / c^2) / marker_std^2``, so a few mislabelled points barely pull
            the body; 0 fits least squares.
        pose_prior_weight: weight of the pose prior (in sigmas of the joint range).
        shape_prior_weight: weight of the N(0, 1) prior on the PCA coefficients.
        slide_std: m, std of a latent marker's slide from its layout placement (stage 1).
        surface_std: m, std of a latent marker's distance from the skin minus its layout distance.
        derive_slide_std, derive_surface_std: m, the slide and surface stds of
            :func:`derive_layout` (its start is a guess and its distances are fitted).
        window: stage-2 sliding window: frames solved as one batch, and the LM iterations
            each frame gets (the first frame gets three times as many, with the pose prior
            annealed from 10x).
        recheck_every: stage 2 re-solves a frame from scratch (like the first frame) at least
            every this many frames, and whenever its cost jumps; the better solution is kept and
            offered to the window, so a wrong minimum (a limb turned the wrong way) carried
            by the warm starts does not last.
        acceleration_std: m/s^2, std of a model marker's acceleration (temporal prior).
        acceleration_robust: m/s^2, Cauchy scale of that prior (0: squares): past it the prior
            gives way to the markers, so a glitch frame (the whole subject displaced) neither is
            held back nor drags the frames around it. 1000 m/s^2 (about 100 g) is several times
            the peak of a running foot's strike.
        missing_prior_gain: the pose-prior weight is multiplied by sqrt(1 + gain * missing / M).
        min_visible: a frame is solved when at least this fraction of the markers is visible...
        min_markers: ...and at least this many (else it is interpolated and flagged unsolved).
    """

    shape_components: int = 16
    stage1_frames: int = 12
    stage1_iters: int = 5
    stage1_anneal: tuple[float, ...] = (8.0, 4.0, 2.0, 1.0)
    marker_std: float = 0.005
    robust: float = 0.015
    pose_prior_weight: float = 0.1
    shape_prior_weight: float = 1.0
    slide_std: float = 0.02
    surface_std: float = 0.002
    derive_slide_std: float = 0.05
    derive_surface_std: float = 0.01
    window: int = 4
    recheck_every: int = 30
    acceleration_std: float = 100.0
    acceleration_robust: float = 1000.0
    missing_prior_gain: float = 2.5
    min_visible: float = 0.3
    min_markers: int = 6

    def __post_init__(self) -> None:
        for f in fields(self):
            name, v = f.name, getattr(self, f.name)
            if name == "stage1_anneal":
                if not v or not all(isinstance(a, int | float) and math.isfinite(a) and a > 0 for a in v):
                    raise ValueError(f"stage1_anneal: expected a non-empty tuple of factors > 0, got {v!r}")
            elif name in _INT_FIELDS:
                if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                    raise ValueError(f"{name}: expected an int >= 1, got {v!r}")
            elif isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ValueError(f"{name}: expected a finite number, got {v!r}")
            elif v < 0 or (v == 0 and name not in _NONNEGATIVE_FIELDS):
                bound = ">=" if name in _NONNEGATIVE_FIELDS else ">"
                raise ValueError(f"{name}: expected a value {bound} 0, got {v!r}")
        if self.shape_components > 128:
            raise ValueError(f"shape_components: expected at most 128 (the PCA asset's K), got {self.shape_components}")
        if self.min_visible > 1:
            raise ValueError(f"min_visible: expected a fraction in [0, 1], got {self.min_visible}")

    def needed(self, num_markers: int) -> int:
        """Visible markers a frame needs to be solved (else it is interpolated): ``min_markers``
        and the ``min_visible`` fraction of ``num_markers``."""
        return max(self.min_markers, int(self.min_visible * num_markers + 0.999))

    def solvable(self, visible: torch.Tensor) -> torch.Tensor:
        """(T,) bool: the frames of a (T, M) visibility mask with :meth:`needed` markers."""
        return visible.sum(-1) >= self.needed(visible.shape[-1])
