"""MoSh-like body solve: labelled markers -> PCA identity, latent markers and a body motion.

Re-implements the method of MoSh / MoSh++ (paper 003 §4.3, Loper et al. 2014, Mahmood et
al. 2019) with batched torch Gauss-Newton instead of chumpy.

Body: the native PCA (``shape_components`` coefficients, float64 inside), 23 posed body joints,
only the marker anchors skinned. Stage 1 fits shape, latent marker placements and the poses of a
few well-visible frames; stage 2 fits each frame by a sliding window of batched
Levenberg-Marquardt steps, with a Cauchy data term (``SolveConfig.robust``) and a diagonal pose
prior from :data:`unibody.joint_limits.JOINT_RANGES`. The solver works in unibody's frame (metres,
Y up). The method in full: docs/mocap.md ("The solve"); figures: benchmarks/README.md.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from ._marker_body import MarkerBody
from ._stage1 import Stage1Result, pick_frames, stage1
from ._stage2 import stage2
from .derive import derive_layout
from .frames import check_fps, check_marker_units, check_points, lab_to_unibody, unibody_to_lab
from .layout import MarkerLayout
from .solve_config import SolveConfig
from .solve_result import SolveResult

# The solve's parts: frames.py (axes, units, input checks), solve_config.py (SolveConfig),
# _stage1.py (the frames, shape and latent markers), _stage2.py (the sliding-window motion),
# solve_result.py (SolveResult, to_motion), derive.py (a layout from one frame). The names
# from them that this module used to define are re-exported here.
__all__ = [
    "SolveConfig",
    "SolveResult",
    "check_marker_units",
    "derive_layout",
    "lab_to_unibody",
    "pick_frames",
    "solve_markers",
    "unibody_to_lab",
]


def _check_layout(layout: MarkerLayout, m: int) -> None:
    if not isinstance(layout, MarkerLayout):
        raise TypeError(f"layout: expected a MarkerLayout, got {type(layout).__name__}")
    if len(layout) != m:
        raise ValueError(f"layout: {len(layout)} markers but points have {m}; use layout.subset(labels)")


def solve_markers(
    points: torch.Tensor,
    layout: MarkerLayout,
    *,
    config: SolveConfig | None = None,
    fps: float = 120.0,
    progress: Callable[[str], None] | None = None,
) -> SolveResult:
    """Solve a labelled marker sequence for a PCA body and its motion (MoSh-like, see the module).

    Args:
        points: (T, M, 3) m, marker positions in unibody's frame (Y up; see
            :func:`lab_to_unibody`), NaN where a marker is missing.
        layout: the M markers in the same order (labels, vertices, distances).
        config: weights and schedules; default :class:`SolveConfig`.
        fps: frame rate of ``points`` (scales the temporal prior).
        progress: called with one-line reports (e.g. ``print``).

    Returns:
        :class:`SolveResult` in the dtype of ``points``.

    Raises:
        TypeError / ValueError: bad points (shape, dtype, inf, all missing, not metres), layout or fps.
    """
    config = SolveConfig() if config is None else config
    check_points(points, "T M 3")
    _check_layout(layout, points.shape[1])
    check_fps(fps)
    obs = points.detach().to(torch.float64)
    vis = torch.isfinite(obs).all(-1)
    body = MarkerBody(config.shape_components, obs.device)
    anchors = layout.vertices.to(obs.device)
    distance = layout.distance.to(obs)
    if not bool(config.solvable(vis).any()):
        raise ValueError(
            f"points: no frame has the {config.needed(vis.shape[1])} visible markers a solve needs "
            f"(SolveConfig.min_markers, min_visible); the most in one frame: {int(vis.sum(1).max())}"
        )
    picked = pick_frames(vis, config.stage1_frames).to(obs.device)
    s1 = stage1(
        body,
        obs[picked],
        vis[picked],
        anchors,
        distance,
        config,
        slide_std=config.slide_std,
        surface_std=config.surface_std,
        progress=progress,
    )
    local, transl, solved = stage2(body, s1.ident, s1.anchors, s1.latent[None], obs, vis, config, float(fps), progress)
    markers = _model_markers(body, s1, local, transl)
    residual = (markers - obs).norm(dim=-1)
    out = points.dtype
    return SolveResult(
        s1.ident.beta[0].to(out),
        s1.latent.to(out),
        s1.anchors.clone(),
        body.relative_pose(local).to(out),
        transl.to(out),
        markers.to(out),
        residual.to(out),
        solved,
        picked,
    )


def _model_markers(
    body: MarkerBody, s1: Stage1Result, local: torch.Tensor, transl: torch.Tensor, chunk: int = 256
) -> torch.Tensor:
    """(T, M, 3) m, the model markers of every frame, in chunks of frames."""
    out = []
    for sl in torch.split(torch.arange(local.shape[0], device=local.device), chunk):
        x, *_ = body.markers(s1.ident, s1.anchors, s1.latent[None], local[sl], transl[sl], False)
        out.append(x)
    return torch.cat(out)
