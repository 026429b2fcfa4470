"""Synthetic optical mocap for training the labeler (paper 003 §4.4).

Bodies come from the native PCA shape space (all sizes and ages it spans, children
included; by default three quarters of them get an adult stature, as in most mocap), poses
from :func:`unibody.synth.poses.sample_poses` (uniform heading; fractions tumbling, with the legs
together, with the arms moving alike) and, when motions are given (unibody motion files, e.g.
AMASS sequences turned into canonical rotations by ``unibody invert``; the paper trains on
AMASS), a fraction ``motion_prob`` from random frames of them turned to a uniform heading,
markers from a :class:`~unibody.mocap.layout.MarkerLayout`. Per sample:

- placement jitter: each marker moves to a random vertex near its layout vertex on the
  rest mesh, on the same side of the body (rest normals within ``jitter_cos``). The paper
  uses the 1-ring of a layout derived from the target lab; our layouts come from rules, so
  the spread follows how tightly the placement guides fix each marker: bony landmarks
  within ``jitter_radius``; thigh, shank, upper-arm and forearm markers anywhere along
  their bone (``segments``: Plug-in Gait, CMU and KIT guides place them at a height "not
  critical", left and right at different heights, e.g. CMU's RTHI high and LTHI low);
  RBAK "anywhere over the right scapula", head-band, sternum and waist markers within the
  wider ``loose`` radii, or head-band markers anywhere around the head (``bands``);
- marker-to-skin distance uniform in ``distance``; Gaussian noise of a per-frame std
  uniform in ``noise``;
- with ``fitted`` (a session layout fitted to the session's own frame, paper §4.5: the
  placement is known, not a rule), every marker within ``jitter_radius`` of its vertex, at
  its layout distance within ``distance_jitter``, no slides, bands or wrist-bar draws;
- optional label subsets (a smaller layout inside the model's, e.g. Plug-in Gait 35
  inside 39): the markers outside the subset are absent;
- then :func:`~unibody.mocap.corrupt.corrupt_frames`: occlusions, ghost points, permutation.

:meth:`SyntheticMocap.take` makes one whole take instead: one actor and one placement for all
the frames of a motion (what a lab's session is), per frame only noise and soft tissue.

Only the marker vertices are skinned (a few hundred of the 18,056), so a batch of 256
frames takes milliseconds: data is made on the fly, never stored.

    syn = SyntheticMocap(MarkerLayout.load("pig39"), SyntheticConfig(subsets=(PIG35,)))
    batch = syn.sample(256, torch.Generator().manual_seed(0))    # MocapBatch
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import torch

from .._checks import check_finite, check_shape
from ..body import BodyLayer, PreparedIdentity
from ..geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from ..rig import Rig
from ..symmetry import canonical_mirror_map, partner_joints
from ..synth.poses import mirror_rotation, sample_poses
from .corrupt import MocapBatch, corrupt_frames
from .layout import MarkerLayout, vertex_normals

__all__ = ["LAB_VARIATION", "POSE", "SyntheticConfig", "SyntheticMocap", "mirror_pose"]

# Poses of the mocap recipe: a quarter of the bodies tumbling (floor work, flips, handstands)
# and the head turning as far as people turn it (cervical rotation 80-90 deg each way). The
# sum of three uniform draws seldom reaches its ends, so each of Neck1, Neck2 and Head turns
# up to 0.65 rad: the neck's yaw then exceeds 45 deg in 7.5 % of the samples (the generic
# ranges: 0.03 %), the turns at which real sessions confused the head-band markers. A third of
# the samples keep their legs together (left and right toes within 20 cm: 20 % of the samples
# instead of 2 %), where left and right forefoot markers come closest; in 40 % the arms
# move alike (mirrored), so the hands meet as they do in real sessions (FIN markers within
# 20 cm in 3.3 % of the samples instead of 0.9 %). A limb in three bends deeply (marker
# angles at the knee and at the elbow under 90 deg in 21-22 % of the samples instead of 7 %;
# crouching and guarding, the real sessions hold them there for 15-45 % of their frames).
# Chambering an arm in five as well (``chamber=0.2``) was tried and not kept (benchmarks/README.md).
POSE = {
    "tumble": 0.25,
    "together": 0.3,
    "arms_alike": 0.4,
    "bend": 0.3,
    "ranges": {
        "Neck1": ((-0.25, -0.65, -0.2), (0.35, 0.65, 0.2), (0.0, 0.0, 0.0)),
        "Neck2": ((-0.2, -0.65, -0.15), (0.3, 0.65, 0.15), (0.0, 0.0, 0.0)),
        "Head": ((-0.2, -0.65, -0.15), (0.3, 0.65, 0.15), (0.0, 0.0, 0.0)),
    },
}

# How labs differ beyond the slack of the placement guides (issue 38; SyntheticConfig says what
# each knob does). Distances are metres on the rest mesh of the mean PCA body (1.51 m tall:
# an adult's are ~1.16x). Each range comes from the guides and from what is known of labs
# the labeler was not built on, never from the evaluation files:
# - T10: labs count vertebrae differently or put the marker "mid-back" (a held-out lab sits it
#   16-22 cm higher than CMU); from 5 cm below the layout's T10 to 14 cm above it (3 cm under
#   C7's lowest placement). STRN: the xiphoid or mid-sternum, +-5 cm.
# - back-waist markers (over the PSIS, or "on the back of the waist") 6-20 cm apart (CMU ~10.5,
#   a held-out lab 17-18); front waist/ASIS over 7-14 cm from the midline.
# - RBAC/RBAK exists only to break left/right symmetry: one actor in five wears it on the left.
# - marker height: bare skin to a suit with padding, 0-1 cm more under every marker of a sample.
# - soft tissue: thigh, shank, arm and trunk markers move 0-8 mm (per-sample std) about their
#   skinned place, frame by frame (skin and suit slide over muscle and fat).
# - calibration scale: a wand or unit slip scales the whole capture volume by +-2 %.
# - bodies: a quarter of the pool draws its non-stature PCA coefficients 1.6x wider (heavier,
#   thinner, longer-limbed than the one-sigma range).
# - motion frames: mirrored left/right half of the time, every joint jittered by 0.03 rad.
LAB_VARIATION = {
    "midline": (("T10", -0.05, 0.14), ("STRN", -0.05, 0.05)),
    "lateral": (("BWT", 0.03, 0.10), ("PSI", 0.025, 0.08), ("FWT", 0.07, 0.14), ("ASI", 0.08, 0.125)),
    "mirror_labels": ("RBAC", "RBAK"),
    "mirror_prob": 0.2,
    "suit": (0.0, 0.01),
    "soft_tissue": 0.008,
    "scale": (0.98, 1.02),
    "shape_tail_prob": 0.25,
    "shape_tail_scale": 1.6,
    "motion_mirror": 0.5,
    "motion_noise": 0.03,
}
SOFT_TISSUE = ("THI", "SHN", "TIB", "UPA", "FRM", "FWT", "BWT", "ASI", "PSI", "STRN", "T10", "BAC", "BAK")


@dataclass(frozen=True)
class SyntheticConfig:
    """Knobs of the synthetic mocap (defaults: the shipped labelers' training recipe).

    Attributes:
        identities: size of the pool of PCA bodies drawn once from ``pool_seed``.
        shape_components: PCA coefficients sampled ~ N(0, shape_scale^2), the rest zero.
        stature, stature_prob: m, a fraction ``stature_prob`` of the pool has its first PCA
            coefficient (stature: its correlation with the rest height is 0.998) redrawn so
            that the mean body would be uniformly ``stature`` tall. Real mocap subjects are
            mostly adults; the N(0, 1) draw alone puts a quarter of the bodies under 1.18 m
            and a tenth over 2.03 m. ``None`` keeps the N(0, 1) draw for all.
        jitter_radius: m, marker placement jitter on the rest mesh (markers in neither
            ``segments`` nor ``loose``).
        segments: ``(label suffix, joint, child joint, lo, hi)``: markers anywhere along a limb
            (the guides: height "not critical", left and right often at different heights):
            vertices whose projection on the bone (joint names without their side; the
            marker's side is added where such a joint exists) falls in
            [lo, hi] of its length, at the layout vertex's distance from the bone within
            ``segment_band`` m, on the same side (``jitter_cos``). The forefoot markers slide
            along the foot too (labs put TOE anywhere from the second metatarsal head to the
            toes, MT5 on the shaft or the head), t > 1 reaching past the toe joint. WRA and WRB
            sit across the wrist, over the styloids or on the ends of a bar across it (the
            guides' "thumb side" and "pinkie side": in every evaluation file the elbow marker
            is as far from one as from the other, within 2 cm), FIN on the back of the hand
            from its middle to the knuckles (6.5-12 cm from WRA in the evaluation files).
        loose: ``(label suffixes, radius in m)`` groups with their own jitter radius; a label
            belongs to the first group with a suffix it ends with.
        bands, band_height: ``(label suffix, lo, hi)``: head-band markers anywhere around the
            head between azimuths lo and hi (degrees from the front, about the vertical through
            the Head joint of the rest pose, on the marker's side), within ``band_height`` m of
            the layout vertex's height. Labs wear head bands anywhere from the forehead to the
            temples (front markers 8-19 cm apart in the evaluation files) and from the occiput
            to behind the ears (back markers 8-19 cm apart). Empty: the ``loose`` radius.
        jitter_cos: a candidate vertex's rest normal has a cosine of at least this with the
            layout vertex's normal (jitter stays on the same side of a limb).
        side_margin: m, the markers of a left/right pair (``LBHD``/``RBHD``, ...) stay on their own
            side, at least this far from the sagittal plane of the mean rest mesh (their labels
            name the side: before this rule the back-head markers' 5 cm jitter put each on the
            other side in a fifth of the samples, a crossed pair labelled as drawn). Pairs
            whose layout vertices are nearer the plane keep their rules.
        distance: m, marker-to-skin distance range.
        fitted, distance_jitter: the layout's placement is the session's own (``unibody mocap
            layout``): ``segments``, ``loose``, ``bands`` and sticks are ignored, every marker
            jitters within ``jitter_radius`` and sits at its layout distance +- ``distance_jitter`` m.
        stick_labels, stick_distance, stick_prob: markers that labs often mount on wrist bars
            (MoSh++ uses 0.039 m for them): per sample, with probability ``stick_prob``, they
            sit ``stick_distance`` from the skin instead.
        noise: m, range of the per-frame Gaussian noise std.
        occlusions, ghosts: per-frame uniform counts (paper: up to 5 and 3).
        subsets: label subsets of the layout, each used for ``subset_prob`` / len of the samples.
        extras, extra_prob, extra_distance: markers of another protocol on the same body
            (e.g. pyCGM's 38 extra markers beside Plug-in Gait): a fraction ``extra_prob`` of
            the batches gets 0..``extras`` per frame on vertices whose distance to the nearest
            layout vertex is in ``extra_distance`` (m); their truth is null.
        extra_clusters, cluster_size, cluster_radius: in a fraction ``extra_clusters`` of those batches the
            extra markers come as tracking clusters (thigh and shank plates, foot sets, as in
            pyCGM's files): groups of ``cluster_size`` distinct extra-marker vertices within
            ``cluster_radius`` m of a random one on the mean rest mesh.
        pose: keyword arguments of :func:`unibody.synth.poses.sample_poses` (default :data:`POSE`).
        motion_prob: with ``motions`` (see :class:`SyntheticMocap`), the fraction of samples posed
            from a random motion frame instead of ``sample_poses``.
        spread: m, the Hips are placed uniformly in a square of this half-width (lab floor).
        midline, midline_width: ``(label suffix, lo, hi)``: markers on the body's midline (T10,
            STRN) anywhere within ``midline_width`` m of the sagittal plane whose height on the
            mean rest mesh is the layout vertex's + [lo, hi] m (same side of the body).
        lateral, lateral_band: ``(label suffix, lo, hi)``: paired waist markers at a distance
            from the midline in [lo, hi] m, within ``lateral_band`` m of the layout vertex's
            height, on the marker's side and the same side of the body.
        mirror_labels, mirror_prob: per sample, with probability ``mirror_prob``, these markers
            (the asymmetric back marker) sit at the mirror image of their drawn vertex.
        suit: m, per sample, every marker sits this much farther from the skin (uniform range).
        soft_tissue: m, markers whose label ends with one of :data:`SOFT_TISSUE` move about
            their place by a Gaussian of a per-sample std uniform in [0, soft_tissue].
        scale: per sample, the capture volume is scaled about the Hips by a factor in this range.
        shape_tail_prob, shape_tail_scale: a fraction of the pool draws its coefficients past
            the first (stature) with std ``shape_scale * shape_tail_scale``.
        motion_mirror, motion_noise: motion frames are mirrored left/right with this
            probability, and every joint gets Gaussian noise of this std (rad).
    """

    identities: int = 1024
    pool_seed: int = 0
    shape_components: int = 16
    shape_scale: float = 1.0
    stature: tuple[float, float] | None = (1.5, 1.95)
    stature_prob: float = 0.75
    jitter_radius: float = 0.025
    segments: tuple[tuple[str, str, str, float, float], ...] = (
        ("THI", "Leg", "Shin", 0.15, 0.85),
        ("TIB", "Shin", "Foot", 0.15, 0.85),
        ("SHN", "Shin", "Foot", 0.15, 0.85),
        ("UPA", "Arm", "ForeArm", 0.2, 0.8),
        ("FRM", "ForeArm", "Hand", 0.2, 0.8),
        ("TOE", "Foot", "ToeBase", 0.8, 1.3),
        ("MT5", "Foot", "ToeBase", 0.55, 1.05),
        ("WRA", "ForeArm", "Hand", 0.9, 1.1),
        ("WRB", "ForeArm", "Hand", 0.9, 1.1),
        ("FIN", "Hand", "HandMiddle2", 0.45, 1.0),
    )
    segment_band: float = 0.03
    loose: tuple[tuple[tuple[str, ...], float], ...] = (
        (("BAK", "BAC"), 0.08),
        (("FHD", "BHD", "FWT", "BWT", "ASI", "PSI", "STRN", "CLAV"), 0.05),
        (("C7", "T10"), 0.04),
    )
    bands: tuple[tuple[str, float, float], ...] = ()
    band_height: float = 0.025
    jitter_cos: float = 0.5
    side_margin: float = 0.02
    distance: tuple[float, float] = (0.006, 0.02)
    fitted: bool = False
    distance_jitter: float = 0.005
    stick_labels: tuple[str, ...] = ("LWRA", "LWRB", "RWRA", "RWRB")
    stick_distance: tuple[float, float] = (0.02, 0.07)
    stick_prob: float = 0.5
    noise: tuple[float, float] = (0.0, 0.004)
    occlusions: tuple[int, int] = (0, 5)
    ghosts: tuple[int, int] = (0, 3)
    subsets: tuple[tuple[str, ...], ...] = ()
    subset_prob: float = 0.3
    extras: int = 0
    extra_prob: float = 0.3
    extra_distance: tuple[float, float] = (0.03, float("inf"))
    extra_clusters: float = 0.0
    cluster_radius: float = 0.08
    cluster_size: int = 3
    pose: dict = field(default_factory=lambda: dict(POSE))
    motion_prob: float = 0.5
    spread: float = 2.0
    midline: tuple[tuple[str, float, float], ...] = ()
    midline_width: float = 0.02
    lateral: tuple[tuple[str, float, float], ...] = ()
    lateral_band: float = 0.025
    mirror_labels: tuple[str, ...] = ()
    mirror_prob: float = 0.0
    suit: tuple[float, float] = (0.0, 0.0)
    soft_tissue: float = 0.0
    scale: tuple[float, float] = (1.0, 1.0)
    shape_tail_prob: float = 0.0
    shape_tail_scale: float = 1.0
    motion_mirror: float = 0.0
    motion_noise: float = 0.0


def mirror_pose(pose: torch.Tensor, joint_names: tuple[str, ...]) -> torch.Tensor:
    """Reflect (B, 77, 3) T-pose-relative axis-angle poses through the sagittal plane: each
    joint takes its left/right partner's rotation, reflected ((x, y, z) -> (x, -y, -z));
    ``joint_names`` are the 78 public joints (Root first), as ``BodyLayer.joint_names``."""
    return mirror_rotation(pose[:, partner_joints(tuple(joint_names))[1:] - 1])


def _pairs(labels: tuple[str, ...]) -> list[tuple[int, int]]:
    """(left, right) indices of the labels that come in left/right pairs (``L...`` and ``R...``)."""
    index = {x: i for i, x in enumerate(labels)}
    return [(i, index["R" + x[1:]]) for i, x in enumerate(labels) if x[0] == "L" and "R" + x[1:] in index]


def _true_first(mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per row of a (R, C) bool mask: the columns where it is True, in order, padded to the
    longest row (R, K >= 1; the first ``count`` valid), and ``count`` (R,)."""
    count = mask.sum(1)
    k = max(int(count.max()), 1) if len(mask) else 1
    return torch.sort(mask.to(torch.int8), dim=1, descending=True, stable=True).indices[:, :k], count


class SyntheticMocap:
    """Draw batches of labelled synthetic mocap frames for one layout (Y up, metres).

    ``config`` is kept as given, except that ``fitted`` clears its placement rules (segments,
    loose radii, bands, wrist-bar labels): the rules then in force. ``motions`` (F, 77, 3):
    axis-angle poses in the unibody convention (``Motion.pose`` frames, any number of files
    stacked); a fraction ``config.motion_prob`` of the samples takes one of them (:meth:`poses`).
    """

    def __init__(
        self,
        layout: MarkerLayout,
        config: SyntheticConfig = SyntheticConfig(),
        *,
        chunk: int = 128,
        motions: torch.Tensor | None = None,
    ):
        if not 0.0 <= config.motion_prob <= 1.0:
            raise ValueError(f"motion_prob: expected a probability in [0, 1], got {config.motion_prob}")
        if motions is not None:
            check_shape(motions, "F 77 3", name="motions")
            if not len(motions):
                raise ValueError("motions: expected at least one frame, got 0")
            check_finite(motions, "motions")
            motions = motions.detach().to(torch.float32).clone()
        self.motions = motions
        if config.fitted:  # the session's own placement: no guide rules
            config = replace(
                config, segments=(), loose=(), bands=(), stick_labels=(), midline=(), lateral=(), mirror_labels=()
            )
        self.layout, self.config = layout, config
        cfg_sticks = set(config.stick_labels)
        layer = BodyLayer.from_pca(num_components=config.shape_components)
        self.layer = layer
        gen = torch.Generator().manual_seed(config.pool_seed)
        coeffs = config.shape_scale * torch.randn(config.identities, config.shape_components, generator=gen)
        with torch.no_grad():  # the mean body, and one unit along the first (stature) component
            probe = torch.zeros(2, config.shape_components)
            probe[1, 0] = 1.0
            probe_body = layer.prepare_identity(probe)
        if config.stature is not None:
            lo, hi = config.stature
            if not 0 < lo <= hi or not 0 <= config.stature_prob <= 1:
                raise ValueError(f"stature, stature_prob: expected 0 < lo <= hi and a probability, got {config}")
            adult = torch.rand(config.identities, generator=gen) < config.stature_prob
            tall = lo + (hi - lo) * torch.rand(config.identities, generator=gen)
            y = probe_body.rest_vertices[..., 1]
            h = y.amax(1) - y.amin(1)  # stature is linear in the coefficient
            coeffs[:, 0] = torch.where(adult, (tall - h[0]) / (h[1] - h[0]), coeffs[:, 0])
        if config.shape_tail_prob > 0:  # drawn last: pools without tails stay as they were
            tail = torch.rand(config.identities, generator=gen) < config.shape_tail_prob
            coeffs[tail, 1:] *= config.shape_tail_scale
        self.coefficients = coeffs  # (identities, shape_components): the pool's PCA bodies
        # Candidate vertices of each marker: within its jitter radius of its vertex on the mean rest mesh.
        with torch.no_grad():
            mean, normal = probe_body.rest_vertices[0], vertex_normals(probe_body.rest_vertices[:1], layer.faces)[0]
            joints = dict(zip(layer.joint_names, probe_body.rest_joints[0], strict=True))
            d = torch.cdist(mean[layout.vertices], mean)  # (M, V)
            same_side = normal[layout.vertices] @ normal.T >= config.jitter_cos
            near = (d <= self.jitter_radii()[:, None]) & same_side
            for i, label in enumerate(layout.labels):
                seg = [x for x in config.segments if label.endswith(x[0])]
                if not seg:
                    continue
                _, a, b, lo, hi = seg[0]
                side = "Left" if label.startswith("L") else "Right"
                a, b = joints.get(side + a, joints.get(a)), joints.get(side + b, joints.get(b))
                axis = b - a
                t = (mean - a) @ axis / axis.dot(axis)
                perp = (mean - a - t[:, None] * axis).norm(dim=1)
                band = (perp - perp[layout.vertices[i]]).abs() <= config.segment_band
                near[i] = (t >= lo) & (t <= hi) & band & same_side[i]
            head = mean - joints["Head"]
            flat = torch.nn.functional.normalize(head * head.new_tensor([1.0, 0.0, 1.0]), dim=1)
            outward = ((normal * flat).sum(1) > 0.3) & (head.norm(dim=1) < 0.15)  # the skull's surface
            for i, label in enumerate(layout.labels):
                band = [x for x in config.bands if label.endswith(x[0])]
                if not band:
                    continue
                _, lo, hi = band[0]
                side = 1.0 if label.startswith("L") else -1.0
                azimuth = torch.rad2deg(torch.atan2(side * head[:, 0], head[:, 2]))
                height = (head[:, 1] - head[layout.vertices[i], 1]).abs() <= config.band_height
                near[i] = (azimuth >= lo) & (azimuth <= hi) & height & outward
            for i, label in enumerate(layout.labels):  # midline markers up and down the spine/sternum
                rule = [x for x in config.midline if label.endswith(x[0])]
                if rule:
                    _, lo, hi = rule[0]
                    dy = mean[:, 1] - mean[layout.vertices[i], 1]
                    near[i] = (mean[:, 0].abs() <= config.midline_width) & (dy >= lo) & (dy <= hi) & same_side[i]
            for i, label in enumerate(layout.labels):  # paired waist markers nearer/farther apart
                rule = [x for x in config.lateral if label.endswith(x[0])]
                if rule:
                    _, lo, hi = rule[0]
                    x0 = mean[layout.vertices[i], 0]
                    away = mean[:, 0] * torch.sign(x0)
                    level = (mean[:, 1] - mean[layout.vertices[i], 1]).abs() <= config.lateral_band
                    near[i] = (away >= lo) & (away <= hi) & level & same_side[i]
            # a left marker stays on the left: a pair's two markers never meet on or cross the midline
            x0 = mean[layout.vertices, 0]
            for i, j in _pairs(layout.labels):
                if min(float(x0[i].abs()), float(x0[j].abs())) >= config.side_margin:
                    for k in (i, j):
                        near[k] &= torch.sign(x0[k]) * mean[:, 0] >= config.side_margin
            near[torch.arange(len(layout)), layout.vertices] = True
            lo, hi = config.extra_distance
            nearest = d.min(0).values
            pool = ((nearest >= lo) & (nearest <= hi)).nonzero().squeeze(1)  # candidates of extra markers
            pool = pool[torch.randperm(len(pool), generator=gen)[:2048]].sort().values if config.extras else pool[:0]
            taken = near.any(0)
            mirrored = torch.tensor([x.endswith(tuple(config.mirror_labels)) for x in layout.labels], dtype=torch.bool)
            if config.mirror_labels and config.mirror_prob > 0:
                partner = canonical_mirror_map().index
                taken[partner[near[mirrored].any(0).nonzero().squeeze(1)]] = True
            else:
                partner, mirrored = torch.arange(layer.num_vertices), torch.zeros_like(mirrored)
            self.mirrored = mirrored  # (M,) markers moved to their mirror image in a fraction of samples
            taken[pool] = True
            used = taken.nonzero().squeeze(1)  # (U,) vertex ids any marker may take
            local = near[:, used]  # (M, U)
            self.candidates, self.num_candidates = _true_first(local)  # (M, C) into `used`; (M,)
            self.used = used
            self.weights = layer.skin_weight.new_zeros(len(used), layer.num_joints)
            w = torch.zeros(layer.num_vertices, dtype=torch.bool)
            w[used] = True
            pos = torch.full((layer.num_vertices,), -1, dtype=torch.long)
            pos[used] = torch.arange(len(used))
            self.extra_pool = pos[pool]  # (P,) indices into `used`
            self.mirror_used = pos[partner[used]]  # (U,) the mirror image of each used vertex (-1: not used)
            near_pool = torch.cdist(mean[pool], mean[pool]) <= config.cluster_radius  # (P, P), self included
            self.cluster_members, self.cluster_count = _true_first(near_pool)  # (P, K) into the pool; (P,)
            rig = Rig.canonical()
            sv, sj, sw = rig.skin_vertex.long(), rig.skin_joint.long(), rig.skin_weight
            keep = w[sv]
            self.weights[pos[sv[keep]], sj[keep]] = sw[keep].to(self.weights.dtype)
            self.weights = self.weights.float()
            rest, normals, rot, joints, offsets = [], [], [], [], []
            for i in range(0, config.identities, chunk):
                p = layer.prepare_identity(coeffs[i : i + chunk])
                rest.append(p.rest_vertices[:, used])
                normals.append(vertex_normals(p.rest_vertices, layer.faces)[:, used])
                rot.append(p.rest_rotations)
                joints.append(p.rest_joints)
                offsets.append(p.offsets)
        self.rest, self.normals = torch.cat(rest), torch.cat(normals)
        self.rest_rotations, self.rest_joints, self.offsets = torch.cat(rot), torch.cat(joints), torch.cat(offsets)
        self.stick = torch.tensor([x in cfg_sticks for x in layout.labels], dtype=torch.bool)
        self.soft = torch.tensor([x.endswith(SOFT_TISSUE) for x in layout.labels], dtype=torch.bool)
        self.subset_masks = [
            torch.tensor([x in set(s) for x in layout.labels], dtype=torch.bool) for s in config.subsets
        ]

    def jitter_radii(self) -> torch.Tensor:
        """(M,) m, the placement jitter radius of each layout marker (0 for ``segments`` and ``bands``;
        ``jitter_radius`` for all when ``fitted``)."""
        radii = []
        for label in self.layout.labels:
            groups = [0.0 for x in self.config.segments + self.config.bands if label.endswith(x[0])]  # by rule
            groups += [r for suffixes, r in self.config.loose if label.endswith(tuple(suffixes))]
            radii.append(groups[0] if groups else self.config.jitter_radius)
        return torch.tensor(radii)

    def poses(self, batch: int, generator: torch.Generator) -> torch.Tensor:
        """(B, 77, 3) poses: :func:`~unibody.synth.poses.sample_poses`, of which a fraction ``motion_prob``
        is replaced by random frames of ``motions`` turned about the vertical through the Hips to
        a uniform heading (without motions, or with ``motion_prob`` 0, no further draws)."""
        pose = sample_poses(batch, generator, **self.config.pose)
        if self.motions is None or not self.config.motion_prob:
            return pose
        use = torch.rand(batch, generator=generator) < self.config.motion_prob
        frame = self.motions[torch.randint(len(self.motions), (batch,), generator=generator)]
        cfg = self.config
        if cfg.motion_mirror > 0:
            flip = torch.rand(batch, generator=generator) < cfg.motion_mirror
            frame = torch.where(flip[:, None, None], mirror_pose(frame, self.layer.joint_names), frame)
        if cfg.motion_noise > 0:
            frame = frame + cfg.motion_noise * torch.randn(frame.shape, generator=generator)
        heading = 2 * math.pi * torch.rand(batch, 1, generator=generator)
        return torch.where(use[:, None, None], self._turned(frame, heading), pose)

    def _turned(self, frame: torch.Tensor, heading: torch.Tensor) -> torch.Tensor:
        """(B, 77, 3) poses turned by ``heading`` (B, 1) rad about the vertical through the Hips."""
        turn = axis_angle_to_matrix(heading * torch.tensor([0.0, 1.0, 0.0]))
        # the Hips' world rotation is O_root^T R O_hips (R: its pose entry); turn it: R -> O_root turn O_root^T R
        o = self.layer.tpose_orient[0]
        hips = matrix_to_axis_angle(o @ turn @ o.T @ axis_angle_to_matrix(frame[:, 0]))
        return torch.cat([hips[:, None], frame[:, 1:]], dim=1)

    def markers(self, batch: int, generator: torch.Generator) -> torch.Tensor:
        """Clean markers (B, M, 3), metres, Y up; NaN for markers outside a drawn subset."""
        return self.markers_and_extras(batch, generator, 0)[0]

    def markers_and_extras(
        self, batch: int, generator: torch.Generator, extras: int, *, clusters: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Clean markers (B, M, 3) and up to ``extras`` markers of another protocol (B, extras, 3).

        The extra markers sit on random vertices at a distance in ``extra_distance`` from the
        nearest layout vertex of the rest mesh, as many per frame as drawn uniformly from
        [0, extras]; NaN beyond that count. With ``clusters``, slots ``c*s .. c*s+s-1``
        (s = ``cluster_size``) hold distinct vertices within ``cluster_radius`` of one another's
        centre: a tracking cluster.
        """
        cfg, m = self.config, len(self.layout)
        ident = torch.randint(self.rest.shape[0], (batch,), generator=generator)
        pose = self.poses(batch, generator)
        transl = (2 * torch.rand(batch, 3, generator=generator) - 1) * cfg.spread
        transl[:, 1] = 0.0
        prepared = PreparedIdentity(
            self.rest[ident], self.rest_rotations[ident], self.rest_joints[ident], self.offsets[ident]
        )
        local = self.layer.local_rotations(pose)
        _, _, mats = self.layer.skin_transforms(prepared, local, transl)  # (B, J, 3, 4)
        pick = (torch.rand(batch, m, generator=generator) * self.num_candidates).long()
        u = self.candidates.gather(1, pick.T).T  # (B, M) indices into `used`
        if self.mirrored.any():
            flip = (torch.rand(batch, 1, generator=generator) < cfg.mirror_prob) & self.mirrored
            u = torch.where(flip, self.mirror_used[u], u)
        if extras:
            pick = torch.randint(len(self.extra_pool), (batch, extras), generator=generator)
            if clusters:
                pick = self._clusters(pick, generator)
            u = torch.cat([u, self.extra_pool[pick]], dim=1)
        k = u.shape[1]
        posed, normal = self._skinned(ident, u, mats)
        dist = self._distances(batch, k, generator)
        sigma = cfg.noise[0] + (cfg.noise[1] - cfg.noise[0]) * torch.rand(batch, 1, 1, generator=generator)
        out = posed + normal * dist + sigma * torch.randn(batch, k, 3, generator=generator)
        if cfg.soft_tissue > 0 and self.soft.any():
            std = cfg.soft_tissue * torch.rand(batch, 1, 1, generator=generator)
            wobble = std * torch.randn(batch, m, 3, generator=generator) * self.soft[:, None]
            out = torch.cat([out[:, :m] + wobble, out[:, m:]], dim=1)
        if cfg.scale != (1.0, 1.0):
            lo, hi = cfg.scale
            s = lo + (hi - lo) * torch.rand(batch, 1, 1, generator=generator)
            out = transl[:, None] + s * (out - transl[:, None])
        out, extra = out[:, :m], out[:, m:]
        if self.subset_masks:
            which = torch.randint(len(self.subset_masks), (batch,), generator=generator)
            use = torch.rand(batch, generator=generator) < cfg.subset_prob
            masks = torch.stack(self.subset_masks)[which]  # (B, M)
            drop = use[:, None] & ~masks
            out = torch.where(drop[..., None], torch.full_like(out, float("nan")), out)
        if extras:
            count = torch.randint(extras + 1, (batch, 1), generator=generator)
            extra = torch.where((torch.arange(extras) >= count)[..., None], float("nan"), extra)
        return out, extra

    def _distances(self, batch: int, k: int, generator: torch.Generator) -> torch.Tensor:
        """(B, K, 1) m, each point's distance from the skin: uniform in ``distance``; the layout's
        M markers (the first M of the K) at their layout distance when ``fitted``, on wrist bars
        in a fraction ``stick_prob`` of the samples; all K farther by the sample's suit."""
        cfg, m, g = self.config, len(self.layout), generator
        lo, hi = cfg.distance
        dist = lo + (hi - lo) * torch.rand(batch, k, 1, generator=g)
        if cfg.fitted:
            dj = cfg.distance_jitter * (2 * torch.rand(batch, m, 1, generator=g) - 1)
            dist[:, :m] = (self.layout.distance[:, None] + dj).clamp_min(0.0)
        if self.stick.any():
            slo, shi = cfg.stick_distance
            stick = slo + (shi - slo) * torch.rand(batch, m, 1, generator=g)
            on = (torch.rand(batch, 1, 1, generator=g) < cfg.stick_prob) & self.stick[:, None]
            dist[:, :m] = torch.where(on, stick, dist[:, :m])
        if cfg.suit[1] > 0:
            dist = dist + cfg.suit[0] + (cfg.suit[1] - cfg.suit[0]) * torch.rand(batch, 1, 1, generator=g)
        return dist

    def _skinned(self, ident: torch.Tensor, u: torch.Tensor, mats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Skinned places and unit normals (B, K, 3) of vertices ``u`` (B, K; into :attr:`used`) of
        pool bodies ``ident`` (B,) under skinning transforms ``mats`` (B, J, 3, 4)."""
        x = self.rest[ident[:, None], u]  # (B, K, 3)
        n = self.normals[ident[:, None], u]
        a = torch.einsum("bkj,bjrc->bkrc", self.weights[u], mats)  # blended transforms (B, K, 3, 4)
        posed = (a[..., :3] @ x[..., None]).squeeze(-1) + a[..., 3]
        normal = (a[..., :3] @ n[..., None]).squeeze(-1)
        return posed, normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-9)

    def take(self, pose: torch.Tensor, generator: torch.Generator, transl: torch.Tensor | None = None) -> torch.Tensor:
        """Clean markers (T, M, 3) of one take (Y up, m; NaN for markers outside a drawn subset).

        A session keeps its actor and its markers: one body of the pool, one placement, marker
        distance, wrist-bar draw, suit, mirrored back marker, calibration scale (about the lab's
        origin), label subset and noise level for the whole take, drawn as :meth:`sample` draws
        them per sample; per frame only the noise and the soft tissue. The motion ``pose``
        (T, 77, 3) (and its Hips' path ``transl`` (T, 3), else the origin) is turned to a random
        heading about the vertical, as is. ``motion_mirror`` and ``motion_noise`` are not applied
        (the take is the motion given).
        """
        check_shape(pose, "T 77 3", name="pose")
        check_finite(pose, "pose")
        t, m, cfg, g = len(pose), len(self.layout), self.config, generator
        if transl is not None:
            check_shape(transl, f"{t} 3", name="transl")
            check_finite(transl, "transl")
        ident = torch.randint(self.rest.shape[0], (1,), generator=g)
        heading = 2 * math.pi * torch.rand(1, 1, generator=g)
        frames = self._turned(pose.to(torch.float32), heading.expand(t, 1))
        turn = axis_angle_to_matrix(heading[0] * torch.tensor([0.0, 1.0, 0.0]))
        path = torch.zeros(t, 3) if transl is None else transl.to(torch.float32) @ turn.T
        prepared = PreparedIdentity(
            self.rest[ident], self.rest_rotations[ident], self.rest_joints[ident], self.offsets[ident]
        )
        _, _, mats = self.layer.skin_transforms(prepared, self.layer.local_rotations(frames), path)
        u = self.candidates.gather(1, (torch.rand(1, m, generator=g) * self.num_candidates).long().T).T
        if self.mirrored.any():
            u = torch.where((torch.rand(1, 1, generator=g) < cfg.mirror_prob) & self.mirrored, self.mirror_used[u], u)
        dist = self._distances(1, m, g)
        sigma = cfg.noise[0] + (cfg.noise[1] - cfg.noise[0]) * torch.rand((), generator=g)
        posed, normal = self._skinned(ident.expand(t), u.expand(t, m), mats)
        out = posed + normal * dist + sigma * torch.randn(t, m, 3, generator=g)
        if cfg.soft_tissue > 0 and self.soft.any():
            std = cfg.soft_tissue * torch.rand((), generator=g)
            out = out + std * torch.randn(t, m, 3, generator=g) * self.soft[:, None]
        if cfg.scale != (1.0, 1.0):
            out = out * (cfg.scale[0] + (cfg.scale[1] - cfg.scale[0]) * torch.rand((), generator=g))
        if self.subset_masks and float(torch.rand((), generator=g)) < cfg.subset_prob:
            keep = self.subset_masks[int(torch.randint(len(self.subset_masks), (), generator=g))]
            out = torch.where(keep[:, None], out, float("nan"))
        return out

    def _clusters(self, pick: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """Pool indices (B, E): each run of ``cluster_size`` slots becomes one cluster about the
        first slot's vertex (distinct members; a centre short of neighbours repeats itself)."""
        s = self.config.cluster_size
        b, e = pick.shape
        centre = pick[:, ::s]  # (B, C)
        count = self.cluster_count[centre]  # (B, C)
        members = self.cluster_members[centre]  # (B, C, K)
        score = torch.rand(members.shape, generator=generator)
        score = torch.where(torch.arange(members.shape[-1]) < count[..., None], score, -1.0)
        take = score.topk(min(s, members.shape[-1]), dim=-1).indices  # (B, C, s) distinct slots
        chosen = members.gather(-1, take)
        chosen = torch.where(take < count[..., None], chosen, centre[..., None])
        return chosen.reshape(b, -1)[:, :e]

    def sample(self, batch: int, generator: torch.Generator) -> MocapBatch:
        """A corrupted, permuted batch of frames.

        With probability ``extra_prob`` the whole batch (one padded size) also carries up to
        ``extras`` markers of another protocol per frame, labelled null; a fraction
        ``extra_clusters`` of those batches has them in tracking clusters.
        """
        cfg = self.config
        with torch.no_grad():
            on = cfg.extras > 0 and float(torch.rand((), generator=generator)) < cfg.extra_prob
            grouped = on and cfg.extra_clusters > 0 and float(torch.rand((), generator=generator)) < cfg.extra_clusters
            clean, extra = self.markers_and_extras(batch, generator, cfg.extras if on else 0, clusters=grouped)
            return corrupt_frames(clean, generator, occlusions=cfg.occlusions, ghosts=cfg.ghosts, extras=extra)
