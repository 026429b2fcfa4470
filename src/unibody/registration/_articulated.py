"""Stage 2: articulated alignment of the canonical template to a source surface.

ICP-style: each outer iteration fixes nearest-neighbour pairs in both directions between
template samples and source samples (nearest in position and normal: ``|x - y|^2 +
kappa^2 |n_x - n_y|^2``, so the front of an arm does not pair with the side of the torso),
then a few Adam steps minimise a robust (Cauchy) point-to-plane + point-to-point energy
over the template parameters (pose deltas, bone and size scales, global similarity), plus
priors that keep the pose near the start and the scales near one and smooth along the
skeleton. Phases free the parameters coarse to fine: similarity, then the body joints and
scales, then fingers and jaw, then the hands alone against dense source points near them.

Hands are where the chamfer has the worst local minima (fingers one finger over, two
template fingers on one source finger, crossed fingers, straight template fingers across
curled source ones). Three things keep them out: the "hands" phase tries nine starts per
hand (turned about the palm normal x fingers curled or straightened) and keeps each hand's
best; a coarse-to-fine robust scale (the bare source finger of a wrong assignment pulls
hard under a wide loss); and finger anatomy as penalties (hinge joints only flex, knuckles
do not twist, neighbouring fingers keep apart and in order across the palm).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..geometry.mesh import vertex_normals
from ..geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from ._template import Template, TemplateParams

__all__ = ["ArticulatedFit", "Phase", "fit_articulated", "nearest"]

_FINE = ("Thumb", "Index", "Middle", "Ring", "Pinky", "Jaw")
_STIFF = ("Spine1", "Spine2", "Chest", "Neck1", "Neck2", "Head")


@dataclass(frozen=True, slots=True)
class Phase:
    """One phase of the articulated fit.

    Attributes:
        free: what moves: "similarity" (global scale, rotation, translation), "body" (+ the
            body joints and all scales), "all" (+ fingers and jaw), "hands" (only the hand
            and finger joints and their bone scales, fitted to dense source points near each
            hand from several starts per hand) or "fingers" (the same from the current pose).
        outer: nearest-neighbour updates.
        inner: Adam steps per update.
        sigma: m, scale of the robust (Cauchy) loss.
        lr: Adam step of the rotations (rad); the other steps are proportional.
    """

    free: str
    outer: int
    inner: int
    sigma: float
    lr: float


@dataclass(frozen=True, slots=True)
class ArticulatedFit:
    """Result of :func:`fit_articulated`: parameters, posed vertices (V, 3) m, final energy."""

    params: TemplateParams
    vertices: torch.Tensor
    energy: float


def nearest(a: torch.Tensor, b: torch.Tensor, chunk: int = 4096) -> torch.Tensor:
    """Index into ``b (M, D)`` of the nearest row for each row of ``a (N, D)`` (Euclidean)."""
    out = [torch.cdist(a[s : s + chunk].float(), b.float()).argmin(1) for s in range(0, a.shape[0], chunk)]
    return torch.cat(out)


def _pose_weights(template: Template) -> torch.Tensor:
    """(J,) prior weight on each joint's rotation delta: stiff spine, free limbs."""
    w = []
    for n in template.rig.joint_names:
        metacarpal = n.endswith("1") and "Hand" in n and "Thumb" not in n  # the palm barely bends
        w.append(4.0 if n in _STIFF else 50.0 if metacarpal else 0.5 if any(f in n for f in _FINE) else 1.0)
    return torch.tensor(w, dtype=torch.float64)


def _masks(template: Template, free: str) -> tuple[torch.Tensor, torch.Tensor, bool]:
    """Which joint rotations ``(J,)`` and scale groups ``(G,)`` move in a phase, and the similarity."""
    names = template.rig.joint_names
    movable = template.skinned.clone()
    movable[:2] = False  # Root is virtual; the Hips orientation is the global rotation
    groups = torch.ones(template.num_groups, dtype=torch.bool)
    if free == "similarity":
        return torch.zeros_like(movable), torch.zeros_like(groups), True
    if free == "body":
        return movable & torch.tensor([not any(f in n for f in _FINE) for n in names]), groups, True
    if free in ("hands", "fingers"):
        hand = torch.tensor(["Hand" in n for n in names])
        return movable & hand, torch.zeros_like(groups).index_fill_(0, template.group[hand], True), False
    if free == "all":
        return movable, groups, True
    raise ValueError(f"phase: free must be 'similarity', 'body', 'all', 'hands' or 'fingers', got {free!r}")


def hand_vertices(template: Template) -> torch.Tensor:
    """(V,) bool: template vertices carried mostly (> 1/2) by hand and finger joints."""
    hand = torch.tensor(["Hand" in n for n in template.rig.joint_names])
    return template.weights[:, hand].sum(1) > 0.5


def _apart(
    template: Template, q: TemplateParams, joints: torch.Tensor, ratio: float = 0.5, weight: float = 10.0
) -> torch.Tensor:
    """Keep neighbouring fingers apart and in order across the palm.

    Penalises joints of neighbouring fingers (same level) closer than ``ratio`` x their bind
    distance, and closer than half of that along the palm's width (index -> pinky knuckle
    direction, so two fingers may not cross). The canonical T-pose (fingers together) is
    inside both bounds. Two template fingers on one source finger, or
    crossed over one another, fit the source nearly as well as the right assignment (the
    finger left bare only pulls through the robust reverse term): local minima the chamfer
    alone does not leave, and configurations real hands cannot take.
    """
    idx, bind, side_of, knuckles = template.finger_pairs
    d0 = ratio * bind * torch.exp(q.log_scale)
    gap = joints[idx[:, 1]] - joints[idx[:, 0]]
    width = joints[knuckles[:, 1]] - joints[knuckles[:, 0]]  # (2, 3) index -> pinky knuckle, per side
    width = width / width.norm(dim=-1, keepdim=True)
    along = (gap * width[side_of]).sum(-1)
    close = torch.relu(d0 - gap.norm(dim=-1)) / d0
    crossed = torch.relu(0.5 * d0 - along) / d0
    return weight * (close.square().sum() + crossed.square().sum())


def _anatomy(template: Template, delta: torch.Tensor, weight: float = 20.0) -> torch.Tensor:
    """Finger joints move like fingers: hinges only flex, knuckles flex and spread but do not twist.

    ``delta`` (J, 3) are the pose changes from the start (axis-angle, bind frames); the
    rotation components a joint cannot make are penalised. Without it curled source fingers
    (SMPL-X's rest hands) can be matched by crossed template fingers.
    """
    hinge, flex, knuckle, bone, _ = template.finger_axes
    d = delta[hinge]
    off_axis = d - (d * flex).sum(-1, keepdim=True) * flex
    twist = (delta[knuckle] * bone).sum(-1)
    return weight * (off_axis.square().sum() + twist.square().sum())


def _energy(r: torch.Tensor, n: torch.Tensor, sigma: float, beta: float = 0.2) -> torch.Tensor:
    e = (r * n).sum(-1).square() + beta * r.square().sum(-1)
    return torch.log1p(e / sigma**2).mean()


def fit_articulated(
    template: Template,
    src_points: torch.Tensor,
    src_normals: torch.Tensor,
    samples: torch.Tensor,
    init: TemplateParams,
    phases: tuple[Phase, ...],
    *,
    dense: tuple[torch.Tensor, torch.Tensor] | None = None,
    kappa: float = 0.05,
    prior: float = 0.02,
    hand_radius: float = 0.03,
    log: list[str] | None = None,
) -> ArticulatedFit:
    """Fit the template to source samples.

    Args:
        template: the canonical template.
        src_points, src_normals: (N, 3) source surface samples and unit normals, m, unibody axes.
        samples: (S,) template vertex ids that take part (inner mouth/eyes left out).
        init: start parameters (their pose is also the prior's mean).
        phases: the schedule.
        dense: ``(points, normals)`` denser source samples for "hands"/"fingers" phases (those
            within ``hand_radius`` m of the posed template hands take part); default ``src_points``.
        kappa: m, weight of normal differences in the pairing distance.
        prior: weight of the pose and scale priors.
    """
    p = init.detached()
    theta0 = init.theta.detach().clone()
    energy = torch.tensor(0.0)
    hands = torch.nonzero(hand_vertices(template)[samples]).squeeze(1)
    for phase in phases:
        sel, pts, nrms = samples, src_points, src_normals
        if phase.free in ("hands", "fingers"):
            sel = samples[hands]
            pts, nrms = dense if dense is not None else (src_points, src_normals)
            with torch.no_grad():
                x_hand = template.pose(p, sel)[0]
            near = torch.cat([torch.cdist(c.float(), x_hand.float()).amin(1) for c in pts.split(4096)])
            pts, nrms = pts[near < hand_radius], nrms[near < hand_radius]
        if phase.free == "hands":  # multi-start search; "fingers" refines from the current pose
            p, energy = _fit_hands(template, p, theta0, pts, nrms, sel, phase, kappa, prior, log)
        else:
            p, energy = _run_phase(template, p, theta0, pts, nrms, sel, phase, kappa, prior, log)
    with torch.no_grad():
        x_all, _ = template.pose(p)
    return ArticulatedFit(p, x_all, float(energy.detach()))


# Starts of a "hands" phase: each hand turned about its palm normal (through the wrist) by
# about one finger spacing at the knuckles (~2 cm at ~10 cm) either way, times the four
# fingers curled (or straightened) by an angle at each of their three joints.
_HAND_TURNS = (0.0, 0.2, -0.2)
_FINGER_CURLS = (0.0, 0.5, -0.5)


def _start_hands(template: Template, p: TemplateParams, turn: float, curl: float) -> TemplateParams:
    """Both hands turned about their palm normals by ``turn`` and fingers bent by ``curl`` rad."""
    names = template.rig.joint_names
    p = p.detached()
    g_r, g_p = template.joints(p)
    theta = p.theta.clone()
    hinge, flex, knuckle, _, knuckle_flex = template.finger_axes
    for side in ("Left", "Right"):
        h, i1, p1 = (names.index(f"{side}Hand{s}") for s in ("", "Index1", "Pinky1"))
        n = torch.linalg.cross(g_p[i1] - g_p[h], g_p[p1] - g_p[h], dim=-1)
        rot = axis_angle_to_matrix(turn * n / n.norm())
        delta = axis_angle_to_matrix(p.theta[h])
        a = g_r[h] @ delta.T  # world frame of the hand joint before its own delta
        theta[h] = matrix_to_axis_angle(a.T @ rot @ a @ delta)
    if curl:
        axes = torch.cat([flex, knuckle_flex])
        joints = torch.cat([hinge, knuckle])
        bend = axis_angle_to_matrix(curl * axes)
        theta[joints] = matrix_to_axis_angle(axis_angle_to_matrix(theta[joints]) @ bend)
    return TemplateParams(theta, p.bone, p.size, p.log_scale, p.rot, p.transl)


def _hand_scores(template, p, pts, nrms, samples, kappa, sigma) -> torch.Tensor:
    """(2,) two-way data energy of the left and right hands separately."""
    with torch.no_grad():
        x_all, _ = template.pose(p)
        nrm = vertex_normals(x_all, template.faces)[samples]
        xs = x_all[samples]
        names = template.rig.joint_names
        left = template.weights[samples][:, [i for i, n in enumerate(names) if n.startswith("LeftHand")]].sum(1) > 0.5
        src_left = torch.cdist(pts.float(), xs[left].float()).amin(1) < torch.cdist(
            pts.float(), xs[~left].float()
        ).amin(1)
        out = []
        for tm, sm in ((left, src_left), (~left, ~src_left)):
            a6 = torch.cat([xs[tm], kappa * nrm[tm]], 1)
            b6 = torch.cat([pts[sm], kappa * nrms[sm]], 1)
            fwd, rev = nearest(a6, b6), nearest(b6, a6)
            e = _energy(xs[tm] - pts[sm][fwd], nrms[sm][fwd], sigma) + _energy(
                xs[tm][rev] - pts[sm], nrm[tm][rev], sigma
            )
            out.append(e)
        return torch.stack(out)


def _fit_hands(template, p, theta0, pts, nrms, samples, phase, kappa, prior, log):
    """A "hands" phase from several starts of each hand; each hand keeps its best.

    The chamfer has local minima with every finger one finger over (one source finger left
    bare) or with straight template fingers across strongly curled source ones; starts
    turned by about a finger spacing and with curled or straightened fingers reach the
    other basins. The two hands are independent (own joints, own scale groups), so each
    picks its own winner.
    """
    names = template.rig.joint_names
    fits, scores = [], []
    starts = [(t, c) for t in _HAND_TURNS for c in _FINGER_CURLS]
    for turn, curl in starts:
        start = _start_hands(template, p, turn, curl).detached()
        fit, _ = _run_phase(template, start, theta0, pts, nrms, samples, phase, kappa, prior, log)
        fits.append(fit)
        scores.append(_hand_scores(template, fit, pts, nrms, samples, kappa, phase.sigma))
    best = torch.stack(scores).argmin(0)  # (2,) winner per side
    theta, bone, size = p.theta.clone(), p.bone.clone(), p.size.clone()
    for side, k in zip(("Left", "Right"), best.tolist(), strict=True):
        joints = torch.tensor([n.startswith(f"{side}Hand") for n in names])
        groups = torch.unique(template.group[joints])
        theta[joints], bone[groups], size[groups] = fits[k].theta[joints], fits[k].bone[groups], fits[k].size[groups]
    if log is not None:
        log.append(f"hands: scores {torch.stack(scores).tolist()} -> starts {best.tolist()}")
    out = TemplateParams(theta, bone, size, p.log_scale, p.rot, p.transl)
    return out, torch.stack(scores).amin(0).sum()


@torch.enable_grad()  # an optimisation: it descends a gradient whatever its caller (convert runs under no_grad)
def _run_phase(template, p, theta0, src_points, src_normals, samples, phase, kappa, prior, log):
    """Adam on the free parameters of one phase, with nearest neighbours refreshed ``outer`` times."""
    joint_mask, group_mask, similarity = _masks(template, phase.free)
    fingers = bool(joint_mask[template.finger_axes[0]].any())
    jm, gm = joint_mask.to(torch.float64)[:, None], group_mask.to(torch.float64)
    start = p.detached()
    pose_w = _pose_weights(template)
    parents, group = template.parents, template.group
    src6 = torch.cat([src_points, kappa * src_normals], 1)
    leaves = [p.theta, p.bone, p.size] + ([p.log_scale, p.rot, p.transl] if similarity else [])
    for t in leaves:
        t.requires_grad_(True)
    lr = phase.lr
    groups = [{"params": [p.theta], "lr": lr}, {"params": [p.bone, p.size], "lr": 0.5 * lr}]
    if similarity:
        groups += [{"params": [p.rot], "lr": lr}, {"params": [p.transl], "lr": 0.25 * lr},
                   {"params": [p.log_scale], "lr": 0.5 * lr}]  # fmt: skip
    opt = torch.optim.Adam(groups)

    def effective() -> TemplateParams:
        return TemplateParams(
            start.theta + jm * (p.theta - start.theta),
            start.bone + gm * (p.bone - start.bone),
            start.size + gm * (p.size - start.size),
            p.log_scale,
            p.rot,
            p.transl,
        )

    energy = torch.tensor(0.0)
    for _ in range(phase.outer):
        with torch.no_grad():
            x_all, _ = template.pose(effective())
            nrm = vertex_normals(x_all, template.faces)[samples]
            xs = x_all[samples]
            fwd = nearest(torch.cat([xs, kappa * nrm], 1), src6)
            rev = nearest(src6, torch.cat([xs, kappa * nrm], 1))
        for _ in range(phase.inner):
            opt.zero_grad()
            q = effective()
            x, joints = template.pose(q, samples)
            e_f = _energy(x - src_points[fwd], src_normals[fwd], phase.sigma)
            e_r = _energy(x[rev] - src_points, nrm[rev], phase.sigma)
            pose_prior = (pose_w * (q.theta - theta0).square().sum(-1)).sum()
            scale_prior = (q.bone.square().sum() + q.size.square().sum()) * 0.5
            smooth = ((q.bone[group] - q.bone[group[parents]]).square().sum()
                      + (q.size[group] - q.size[group[parents]]).square().sum())  # fmt: skip
            energy = e_f + e_r + prior * (pose_prior + scale_prior + smooth)
            if fingers:
                energy = energy + _apart(template, q, joints) + _anatomy(template, q.theta - theta0)
            energy.backward()
            opt.step()
        if log is not None:
            e = (float(t.detach()) for t in (e_f, e_r, energy))
            log.append("{} e_f={:.4f} e_r={:.4f} E={:.4f}".format(phase.free, *e))
    with torch.no_grad():
        out = effective().detached()
    return out, energy
