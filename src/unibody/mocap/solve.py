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
:data:`unibody.poses.JOINT_RANGES` (at least 0.05 rad); none on the Hips. It is a diagonal
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

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields

import numpy as np
import torch

from ..io.motion import Motion
from ._marker_body import MarkerBody
from ._stage1 import Stage1Result, stage1
from ._stage2 import stage2
from .frames import check_fps, check_marker_units, check_points, lab_to_unibody, unibody_to_lab
from .layout import MarkerLayout

__all__ = [
    "SolveConfig",
    "check_marker_units",
    "SolveResult",
    "derive_layout",
    "lab_to_unibody",
    "pick_frames",
    "solve_markers",
    "unibody_to_lab",
]


_INT_FIELDS = ("shape_components", "stage1_frames", "stage1_iters", "window", "recheck_every", "min_markers")
_NONNEGATIVE_FIELDS = ("pose_prior_weight", "shape_prior_weight", "missing_prior_gain", "min_visible", "robust")


@dataclass(frozen=True)
class SolveConfig:
    """Weights and schedules of :func:`solve_markers` and :func:`derive_layout`.

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


@dataclass(frozen=True, slots=True)
class SolveResult:
    """A solved marker sequence.

    Attributes:
        identity: (K,) PCA coefficients (``BodyLayer.from_pca(num_components=K)``).
        latent: (M, 3) m, latent marker positions on the fitted rest body (bind A-pose, the
            identity's rest mesh frame).
        anchors: (M,) int64, the canonical vertex each latent marker is skinned with.
        pose: (T, 77, 3) axis-angle, T-pose-relative local rotations of joints 1..77.
        transl: (T, 3) m, Hips world position, unibody frame (Y up).
        markers: (T, M, 3) m, the model markers of every frame (unibody frame), missing or not.
        residual: (T, M) m, distance of each observed marker to its model marker after the
            fit; NaN where the marker is missing.
        solved: (T,) bool, False for frames interpolated for lack of visible markers.
        stage1_frames: (F,) int64, the frames stage 1 fitted the shape on.
    """

    identity: torch.Tensor
    latent: torch.Tensor
    anchors: torch.Tensor
    pose: torch.Tensor
    transl: torch.Tensor
    markers: torch.Tensor
    residual: torch.Tensor
    solved: torch.Tensor
    stage1_frames: torch.Tensor

    def to_motion(self, fps: float) -> Motion:
        """The motion (``identity_backend="pca"``); it replays in ``BodyLayer.from_pca(num_components=K)``."""
        check_fps(fps)
        return Motion(
            self.pose.detach().cpu().numpy().astype(np.float32),
            self.transl.detach().cpu().numpy().astype(np.float32),
            float(fps),
            self.identity.detach().cpu().numpy().astype(np.float32),
            "pca",
        )


def pick_frames(vis: torch.Tensor, n: int) -> torch.Tensor:
    """(F <= n,) frames spread over the sequence: the best visible frame of n equal segments.

    In each segment the frame with the most visible markers wins (ties: the one nearest the
    segment's middle), so a sequence with no complete frame still gets its best ones. Frames
    with fewer than 3 visible markers are never picked.
    """
    t = vis.shape[0]
    counts = vis.sum(1)
    bounds = torch.linspace(0, t, min(n, t) + 1).round().long().tolist()
    out = []
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        if hi <= lo:
            continue
        c = counts[lo:hi].double()
        mid = (lo + hi - 1) / 2
        score = c - 1e-3 * (torch.arange(lo, hi, dtype=torch.float64) - mid).abs() / max(1, hi - lo)
        best = lo + int(score.argmax())
        if counts[best] >= 3:
            out.append(best)
    return torch.tensor(out, dtype=torch.long)


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


def derive_layout(
    points: torch.Tensor,
    labels: Sequence[str],
    *,
    name: str,
    config: SolveConfig | None = None,
    initial: MarkerLayout | None = None,
    unlabelled: torch.Tensor | None = None,
    prefix: str = "X",
) -> MarkerLayout:
    """A marker layout from one labelled frame (paper 003 §4.5 / App. G: MoSh on one frame).

    Fits a PCA body, its pose and the latent markers to the frame (stage 1 with one frame and
    the wider ``derive_slide_std``), then takes for each latent marker the nearest canonical
    vertex of the fitted rest body and its signed distance along that vertex's normal.

    With ``unlabelled`` points (a session's markers of another protocol: tracking clusters,
    foot sets), each becomes a new marker ``{prefix}01``, ``{prefix}02``, ...: a first fit to
    the labelled markers places it on the nearest vertex of the posed body, then all markers
    are fitted together. A labeler trained on the result names them instead of confusing
    them with the layout's markers (the paper's one labelled frame per layout variation).

    Args:
        points: (M, 3) m, one frame in unibody's frame (Y up), NaN where missing.
        labels: the M marker labels.
        name: the new layout's name.
        config: weights; default :class:`SolveConfig`.
        initial: the starting placement, a layout holding every label (extra ones are
            ignored); default the shipped ``superset`` layout.
        unlabelled: (K, 3) m, other markers of the same frame (NaN rows are skipped).
        prefix: name prefix of the markers made from ``unlabelled``.

    Returns:
        :class:`MarkerLayout` with the M labels (missing markers keep their initial placement),
        then the new markers.

    Raises:
        TypeError / ValueError: bad points, or labels neither in ``initial`` nor the superset.
    """
    config = SolveConfig() if config is None else config
    labels = tuple(labels)
    check_points(points, "M 3", len(labels))
    if initial is None:
        superset = MarkerLayout.load("superset")
        unknown = [x for x in labels if x not in superset.labels]
        if unknown:
            raise ValueError(f"labels: {unknown} are not in the superset layout; pass initial=MarkerLayout(...)")
        initial = superset.subset(labels)
    elif not isinstance(initial, MarkerLayout):
        raise TypeError(f"initial: expected a MarkerLayout, got {type(initial).__name__}")
    else:
        initial = initial.subset(labels)
    obs = points.detach().to(torch.float64)[None]
    vis = torch.isfinite(obs).all(-1)
    if int(vis.sum()) < 3:
        raise ValueError("points: fewer than 3 visible markers")
    body = MarkerBody(config.shape_components, obs.device)
    anchors = initial.vertices.to(obs.device)
    distance = initial.distance.to(obs)
    slide, surface = config.derive_slide_std, config.derive_surface_std
    s1 = stage1(body, obs, vis, anchors, distance, config, slide_std=slide, surface_std=surface)
    if unlabelled is not None:
        check_points(unlabelled, "K 3", None, name="unlabelled")
        extra = unlabelled.detach().to(obs)
        extra = extra[torch.isfinite(extra).all(-1)]
        if len(extra):
            labels = labels + tuple(f"{prefix}{k + 1:02d}" for k in range(len(extra)))
            if len(set(labels)) != len(labels):
                raise ValueError(f"prefix: {prefix!r} gives names that are already labels")
            anchors, distance = _extend(body, s1, extra, anchors, distance)
            obs = torch.cat([obs, extra[None]], 1)
            vis = torch.isfinite(obs).all(-1)
            s1 = stage1(body, obs, vis, anchors, distance, config, slide_std=slide, surface_std=surface)
    rest = s1.ident.rest
    vertex = torch.cdist(s1.latent, rest[0]).argmin(1)
    signed = ((s1.latent - rest[0, vertex]) * body.normals(rest, vertex)[0]).sum(-1)
    seen = vis[0]
    vertex = torch.where(seen, vertex, anchors)
    signed = torch.where(seen, signed, distance)
    return MarkerLayout(name, labels, vertex.cpu(), signed.float().cpu())


def _extend(body: MarkerBody, s1: Stage1Result, extra, anchors, distance) -> tuple[torch.Tensor, torch.Tensor]:
    """Anchors and distances with those of ``extra`` (K, 3) appended: nearest posed vertex of the stage-1 fit."""
    rest = s1.ident.rest
    every = torch.arange(rest.shape[1], device=rest.device)
    posed, *_ = body.markers(s1.ident, every, rest, s1.local[:1], s1.transl[:1], False)
    vertex = torch.cdist(extra, posed[0]).argmin(1)
    signed = ((extra - posed[0, vertex]) * body.normals(posed, vertex)[0]).sum(-1).clamp(0.0, 0.05)
    return torch.cat([anchors, vertex]), torch.cat([distance, signed])
