"""Orient mocap frames by their torso: a rigid fit of the layout's torso markers to labelled points.

A labeler trained on frames in every orientation (any heading, tumbling bodies) must tell
left from right and up from down from the point cloud alone, and it does so worst where
bodies lie, tumble or lean. The two-stage labeler (:class:`~unibody.mocap.labeler.Labeler`
with an ``orienter``) first labels each frame with such a labeler, then fits the layout's
torso markers, placed on the mean body in its rest pose (Y up, +X to the body's left, +Z
forward), to the points given their labels, and labels the frame again rotated into that
rest frame, where up, left and front are fixed axes.

Torso markers are those whose vertex is skinned mostly to the Hips or the spine below the
neck (Plug-in Gait and CMU: C7, T10, CLAV, STRN, the back marker, the four pelvis markers):
they move with the trunk whatever the head and limbs do. The fit is a weighted Kabsch
(:func:`unibody.geometry.procrustes.kabsch`), reweighted a few times by a Cauchy function
of the residuals so that a torso label given to the wrong point does not tilt the frame.

    template, torso = torso_template(MarkerLayout.load("cmu41"))
    rot = fit_rotation(points, weights, template[labels])      # (B, 3, 3): R p + t ~ template

:data:`TILTS` are the 13 turns from which a frame the first stage turned the wrong way is
oriented again, and :data:`NUDGES` the small turns tried about the orientation found
(``Labeler(retry=...)``).
"""

from __future__ import annotations

import math

import torch

from .._checks import check_shape
from ..geometry.procrustes import kabsch
from ..geometry.rotations import axis_angle_to_matrix
from .layout import MarkerLayout, place_markers

__all__ = ["NUDGES", "TILTS", "TORSO_JOINTS", "fit_rotation", "torso_template"]

TORSO_JOINTS = ("Hips", "Spine1", "Spine2", "Chest")


def _turn(axis: int, angle: float) -> torch.Tensor:
    return axis_angle_to_matrix(torch.eye(3, dtype=torch.float64)[axis] * angle)


def _tilts() -> torch.Tensor:
    """(13, 3, 3) float64 rotations that tip an upright frame onto its back, front, sides or head.

    Quarter and half turns about the left (X) axis, quarter turns about the forward (Z) axis,
    and the eight eighth-turn combinations X(+-45, +-135 deg) Z(+-45 deg). No turn about the
    vertical: the labelers are trained on every heading.
    """
    quarter, eighth = math.pi / 2, math.pi / 4
    out = [_turn(0, a) for a in (quarter, -quarter, 2 * quarter)] + [_turn(2, a) for a in (quarter, -quarter)]
    out += [_turn(0, a) @ _turn(2, b) for a in (eighth, -eighth, 3 * eighth, -3 * eighth) for b in (eighth, -eighth)]
    return torch.stack(out)


# Where a frame the first stage could not orient is tried again (``Labeler(retry=...)``): TILTS
# tip it over; NUDGES (the identity, then 20 deg either way about each axis) turn a fitted
# orientation a little.
TILTS = _tilts()
NUDGES = torch.stack([torch.eye(3, dtype=torch.float64)] + [_turn(k, a) for k in range(3) for a in (0.35, -0.35)])


def torso_template(layout: MarkerLayout) -> tuple[torch.Tensor, torch.Tensor]:
    """The layout's markers on the mean PCA body in its rest pose, and which of them are torso markers.

    Returns:
        template: (M, 3) float32 m, Y up, facing +Z.
        torso: (M,) bool, the marker's vertex is skinned mostly to one of :data:`TORSO_JOINTS`.
    """
    from ..body import BodyLayer  # the body layer builds the canonical assets: only here
    from ..rig import Rig

    layer = BodyLayer.from_pca(num_components=1)
    with torch.no_grad():
        rest = layer.prepare_identity(torch.zeros(1, 1)).rest_vertices
        template = place_markers(rest, layer.faces, layout.vertices, layout.distance)[0].float()
    rig = Rig.canonical()
    weights = rig.dense_skinning_weights()[layout.vertices]  # (M, J)
    torso_ids = torch.tensor([rig.joint_names.index(j) for j in TORSO_JOINTS])
    return template, torch.isin(weights.argmax(dim=1), torso_ids)


def fit_rotation(
    points: torch.Tensor, weights: torch.Tensor, targets: torch.Tensor, *, iters: int = 3, scale: float = 0.08
) -> torch.Tensor:
    """Rotation of each frame that best maps its points onto their targets, up to a translation.

    Minimises sum_i w_i rho(|R p_i + t - q_i|) over rotations R and translations t, with the
    Cauchy weights w_i = weights_i / (1 + (r_i / scale)^2) of the last fit's residuals r_i
    (``iters`` fits in all; the first uses ``weights`` alone).

    Args:
        points: (B, K, 3) observed points p.
        weights: (B, K) non-negative; 0 drops a point (padding, unlabelled points).
        targets: (B, K, 3) where each point belongs, q (e.g. the template of its label).
        iters: weighted Kabsch fits (>= 1).
        scale: m, residual at which a point's weight halves.

    Returns:
        (B, 3, 3) rotations; the identity for frames with fewer than 4 weighted points.
    """
    sizes: dict[str, int] = {}
    check_shape(points, "B K 3", name="points", sizes=sizes)
    check_shape(weights, "B K", name="weights", sizes=sizes)
    check_shape(targets, "B K 3", name="targets", sizes=sizes)
    if iters < 1 or scale <= 0:
        raise ValueError(f"iters, scale: expected >= 1 and > 0, got {iters}, {scale}")
    base, w = weights, weights
    for _ in range(iters):
        total = w.sum(dim=1, keepdim=True).clamp_min(torch.finfo(points.dtype).tiny)[..., None]
        p = points - (w[..., None] * points).sum(dim=1, keepdim=True) / total
        q = targets - (w[..., None] * targets).sum(dim=1, keepdim=True) / total
        rot = kabsch(p, q, w)
        residual = (p @ rot.transpose(1, 2) - q).norm(dim=-1)
        w = base / (1.0 + (residual / scale) ** 2)
    enough = (weights > 0).sum(dim=1) >= 4
    eye = torch.eye(3, dtype=points.dtype, device=points.device)
    return torch.where(enough[:, None, None], rot, eye)
