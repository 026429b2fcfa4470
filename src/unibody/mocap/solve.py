"""MoSh-like body solve: labelled markers -> PCA identity, latent markers and a body motion.

Re-implements the method of MoSh / MoSh++ (paper 003 §4.3, Loper et al. 2014, Mahmood et
al. 2019) with batched torch Gauss-Newton instead of chumpy:

* **Body.** :meth:`BodyLayer.from_pca` with ``shape_components`` coefficients (float64 inside
  the solver). Only the 23 body joints are posed (Hips, spine, neck, head, shoulders, arms,
  forearms, hands, legs, shins, feet, toe bases); fingers stay at a relaxed curl, eyes, jaw
  and ends at zero. Only the marker anchors are skinned, never the whole mesh.
* **Latent markers.** Marker m starts at ``v_a + n_a d_m`` on the rest body (its layout
  vertex, the vertex normal and the layout distance), is skinned with the anchor's weights,
  and may slide in stage 1 (priors toward the initial placement and toward its layout
  distance from the skin, measured along the anchor normal; it is re-anchored to the nearest
  vertex after every anneal level, as MoSh re-finds its local frame).
* **Stage 1** (shape): ``stage1_frames`` frames spread over the sequence (the best visible
  frame of each equal segment), a scale start and a Kabsch root per frame, then joint
  Levenberg-Marquardt over the per-frame poses, the coefficients and the marker slides (Schur
  complement on the per-frame blocks) with prior weights annealed by ``stage1_anneal``.
* **Stage 2** (motion): per-frame pose and translation with the shape and latent markers
  fixed, by a sliding window of ``window`` frames solved as one batch: each new frame starts
  from its predecessor's latest estimate (or a constant-velocity guess from the last two
  finished frames, whichever fits it better), every frame gets ``window`` LM iterations, and
  the cost is one batched iteration per frame. The first frame starts from the relaxed pose and
  a Kabsch root with the pose prior annealed from 10x (MoSh++); after a gap the root is re-found
  by Kabsch, so the global orientation is never restricted (flips, handstands). An acceleration
  prior on the model markers couples neighbouring frames (targets: the neighbours' latest
  estimates). The data weight is renormalised by the number of visible markers and the pose-prior
  weight grows with the missing fraction (MoSh++). Frames with too few visible markers are
  interpolated (slerp) and flagged unsolved.

**Robust data term.** A marker at distance d from its model marker costs
``c^2 log(1 + d^2 / c^2)`` in units of ``marker_std^2`` (Cauchy, ``c = robust``, 15 mm by
default; least squares below c): a mislabelled point, a swapped pair or a ghost taken for a
marker barely pulls the body, and stands out by its residual. Each LM step reweights the
rows (IRLS). On a synthetic body with 8 % of its labels moved to other markers' points the
body joints stay within 4 mm (least squares: 116 mm; ``tests/test_mocap_solve.py``); on the
evaldata files' own labels the median residual falls and the mean rises a little
(``benchmarks/README.md``).

**Pose prior.** Per joint and axis, ``(theta - mu) / sigma`` on the T-pose-relative axis-angle
theta: mu is the relaxed standing pose and sigma half the joint range of
:data:`unibody.joint_limits.JOINT_RANGES` (at least 0.05 rad); none on the Hips. It is a diagonal
Gaussian standing in for MoSh's GMM pose prior: it fixes what the markers leave free (twist of
segments with collinear markers, the split of a bend over Spine1/Spine2/Chest or Neck/Head).

Frames: the solver works in unibody's frame (metres, Y up). :func:`lab_to_unibody` converts
Z-up lab coordinates ((x, y, z) -> (x, z, -y)).

Measured: ``benchmarks/README.md`` (``python benchmarks/mocap.py --sections solve``): 80-180
frames/s on 2 CPU cores, stage 1 included, mean marker residuals 5-6 mm on the CMU files
(``cmu41``: its wrist markers sit 9.5 mm off the skin, CMU's on ~15 cm wrist bars) and
1-7 mm on the Plug-in Gait files. Synthetic known bodies (``tests/test_mocap_solve.py``):
body joints within ~3 mm on average, marker residuals ~0.2 mm.
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
    picked = pick_frames(vis, config.stage1_frames).to(obs.device)
    if picked.numel() == 0:
        raise ValueError("points: no frame has 3 or more visible markers")
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
