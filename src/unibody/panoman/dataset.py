"""PanoMan's training set H = H_B ∪ H_F ∪ H_H (paper 004 §4.3), synthesised from unibody bodies.

Each mesh carries one kind of motion on a known identity, so its rest mesh r(V) is exact:
``"body"`` (H_B, poses of :func:`unibody.synth.poses.sample_poses` with procedural twist joints),
``"face"`` (H_F, Anny's facial actions scaled by head size) and ``"hands"`` (H_H, finger
rotations). Identities: the native PCA's first 10 components, N(0, 1) truncated to ±2 σ.

Determinism: identity ``k`` of pool ``seed`` depends on ``(seed, k)`` alone and a set of n
samples is the prefix of any larger set with the same arguments; train on seed 0, evaluate on
seed 1. Units: metres, Y up, +Z forward; poses are (N, 77, 3) T-pose-relative axis-angle.
Meshes are computed in float64 and rounded to ``dtype``; stream large sets with
:func:`iter_batches`:

    train = body_samples(1000, seed=0)
    for batch in iter_batches("face", 10_000, seed=0, batch_size=256):  # bounded memory
        ...
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Literal

import torch

from ..body import BodyLayer, PreparedIdentity
from ..geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from ..joint_limits import JOINT_RANGES
from ..rig import JOINT_NAMES, Rig, joint_index
from ..synth.expressions import FACIAL_ACTIONS, expression_basis, expression_reference
from ..synth.identities import NUM_SHAPE, identity_pool
from ..synth.poses import keyed_generator, mirror_rotation, sample_poses

__all__ = [
    "FINGER_JOINTS",
    "NUM_SHAPE",
    "SUBSETS",
    "PanoSamples",
    "Subset",
    "body_samples",
    "full_samples",
    "face_samples",
    "hand_samples",
    "identity_pool",
    "iter_batches",
    "sample_expressions",
    "sample_hand_poses",
]

Subset = Literal["body", "face", "hands"]
SUBSETS: tuple[str, ...] = ("body", "face", "hands")
_CHUNK = 256  # samples per parameter stream
_DEFAULT_IDENTITIES = {"body": 200, "face": 100, "hands": 300}  # the paper's counts (§4.3)
_FINGERS = ("Index", "Middle", "Ring", "Pinky")
FINGER_JOINTS: tuple[str, ...] = tuple(
    f"{side}Hand{name}"
    for side in ("Left", "Right")
    for name in ("Thumb1", "Thumb2", "Thumb3", *(f"{f}{k}" for f in _FINGERS for k in (1, 2, 3, 4)))
)
_HEAD_JOINTS = ("Head", "HeadEnd", "Jaw", "LeftEye", "RightEye")


@dataclass(frozen=True, slots=True)
class PanoSamples:
    """Meshes of one subset of H, each with its identity's rest mesh.

    Attributes:
        subset: "body", "face" or "hands".
        rest: (N, V, 3) m, the identity's rest mesh r(V) (bind A-pose, Hips at its rest position).
        posed: (N, V, 3) m, the sample, same frame (the Hips stay at the rest position).
        identity: (N,) int64, the identity's index in the pool (:func:`identity_pool`).
        shape: (N, 10) PCA coefficients of the identity, standard deviations.
        pose: (N, 77, 3) T-pose-relative axis-angle of joints 1..77 that produced ``posed``;
            for "face" the identity's rest pose, elsewhere the rest pose with the sampled rows
            (body joints or finger joints) replaced.
        expression: (N, 52) facial-action weights in [0, 1] (order ``FACIAL_ACTIONS``); zero
            outside "face".
    """

    subset: str
    rest: torch.Tensor
    posed: torch.Tensor
    identity: torch.Tensor
    shape: torch.Tensor
    pose: torch.Tensor
    expression: torch.Tensor

    def __len__(self) -> int:
        return self.posed.shape[0]


# --------------------------------------------------------------------------- random streams


def _check_int(value: object, name: str, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ValueError(f"{name}: expected an int >= {low}, got {value!r}")
    return value


# --------------------------------------------------------------------------- facial actions

# Units of activation: symmetric pairs (both sides with p_both, else one), conjugate gaze,
# single actions, mutually exclusive alternatives. tongueOut is left out: the canonical mesh
# has no tongue, so its displacement is zero.
_PAIRS = (
    "browDown", "browOuterUp", "cheekSquint", "eyeBlink", "eyeSquint", "eyeWide", "mouthDimple",
    "mouthFrown", "mouthLowerDown", "mouthPress", "mouthSmile", "mouthStretch", "mouthUpperUp", "noseSneer",
)  # fmt: skip
_GAZE = (
    ("eyeLookUpLeft", "eyeLookUpRight"),
    ("eyeLookDownLeft", "eyeLookDownRight"),
    ("eyeLookOutLeft", "eyeLookInRight"),
    ("eyeLookInLeft", "eyeLookOutRight"),
)
_SINGLES = (
    "browInnerUp", "cheekPuff", "jawForward", "jawOpen", "mouthFunnel", "mouthPucker",
    "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper",
)  # fmt: skip
_EITHER = (("jawLeft", "jawRight"), ("mouthLeft", "mouthRight"))
_NUM_UNITS = len(_PAIRS) + len(_GAZE) + len(_SINGLES) + 1 + len(_EITHER)  # 1: jawOpen with mouthClose
_JAW_UNIT = len(_PAIRS) + len(_GAZE) + _SINGLES.index("jawOpen")


def sample_expressions(
    n: int,
    generator: torch.Generator,
    *,
    max_active: int = 3,
    p_both: float = 0.7,
    p_jaw: float = 0.25,
    dtype: torch.dtype = torch.float64,
) -> torch.Tensor:
    """Sparse random facial-action weights (n, 52) in [0, 1], order ``FACIAL_ACTIONS``.

    Each sample activates 1..``max_active`` units out of 31, each with a weight ~ U(0.1, 1):
    a left/right pair (both sides, the second weight jittered by 0.1, with probability
    ``p_both``, else one side), a conjugate gaze direction, a single action, one of
    jawLeft/jawRight or mouthLeft/mouthRight, or jawOpen with mouthClose (lips kept together
    while the jaw drops, mouthClose <= jawOpen). jawOpen is added to a ``p_jaw`` fraction.
    ``max_active=0`` gives neutral faces (all weights zero). Every unit draws its numbers
    whether active or not, so the stream is fixed.
    """
    _check_int(n, "n", 0)
    _check_int(max_active, "max_active", 0)
    for name, p in (("p_both", p_both), ("p_jaw", p_jaw)):
        if not 0.0 <= p <= 1.0:
            raise ValueError(f"{name}: expected a probability in [0, 1], got {p}")
    index = {name: i for i, name in enumerate(FACIAL_ACTIONS)}
    out = torch.zeros(n, len(FACIAL_ACTIONS), dtype=torch.float64)
    k = torch.randint(min(max_active, 1), min(max_active, _NUM_UNITS) + 1, (n, 1), generator=generator)
    order = torch.rand(n, _NUM_UNITS, generator=generator, dtype=torch.float64).argsort(dim=1)
    active = order.argsort(dim=1) < k  # a random k-subset of the units
    active[:, _JAW_UNIT] |= (torch.rand(n, generator=generator, dtype=torch.float64) < p_jaw) & (max_active > 0)

    def draw() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """A weight ~ U(0.1, 1), a uniform for choices and a normal for jitter, per sample."""
        u = torch.rand(n, 2, generator=generator, dtype=torch.float64)
        return 0.1 + 0.9 * u[:, 0], u[:, 1], torch.randn(n, generator=generator, dtype=torch.float64)

    unit = 0
    for base in _PAIRS:
        w, u, e = draw()
        on = active[:, unit]
        both, left = u < p_both, u < p_both + 0.5 * (1.0 - p_both)
        out[:, index[base + "Left"]] = torch.where(on & left, w, 0.0)
        right = torch.where(both, (w + 0.1 * e).clamp(0.0, 1.0), torch.where(left, 0.0, w))
        out[:, index[base + "Right"]] = torch.where(on, right, 0.0)
        unit += 1
    for a, b in _GAZE:
        w, _, _ = draw()
        out[:, index[a]] = out[:, index[b]] = torch.where(active[:, unit], w, 0.0)
        unit += 1
    for name in _SINGLES:
        w, _, _ = draw()
        out[:, index[name]] = torch.where(active[:, unit], w, 0.0)
        unit += 1
    w, u, _ = draw()  # jawOpen + mouthClose (jawOpen may also be active as a single: keep the larger)
    on = active[:, unit]
    out[:, index["jawOpen"]] = torch.where(on, torch.maximum(w, out[:, index["jawOpen"]]), out[:, index["jawOpen"]])
    out[:, index["mouthClose"]] = torch.where(on, u * out[:, index["jawOpen"]], 0.0)
    unit += 1
    for a, b in _EITHER:
        w, u, _ = draw()
        out[:, index[a]] = torch.where(active[:, unit] & (u < 0.5), w, 0.0)
        out[:, index[b]] = torch.where(active[:, unit] & (u >= 0.5), w, 0.0)
        unit += 1
    return out.to(dtype)


# --------------------------------------------------------------------------- finger poses

# Left hand, T-pose-relative (arm along +X, palm down, thumb forward): a finger flexes about -Z
# and spreads about Y (+ toward the little finger); the thumb flexes across the palm about
# (0, 1, -1)/sqrt(2). Per finger: (spread factor at the MCP joint, cupping of the metacarpal, rad).
_FINGER_SPREAD_CUP = ((-1.0, 0.03), (-0.2, 0.03), (0.6, 0.12), (1.2, 0.25))
_MCP_FLEX, _PIP_FLEX, _DIP_MAX, _THUMB_MCP, _THUMB_IP = 1.55, 1.7, 1.3, 0.9, 1.3


def _left_hand(n: int, gen: torch.Generator) -> dict[str, torch.Tensor]:
    """Rotation vectors (n, 3) of the left finger joints, keyed by name without the side."""
    f64 = torch.float64

    def rand() -> torch.Tensor:
        return torch.rand(n, generator=gen, dtype=f64)

    def randn() -> torch.Tensor:
        return torch.randn(n, generator=gen, dtype=f64)

    def vec(x, y, z) -> torch.Tensor:
        zero = torch.zeros(n, dtype=f64)
        return torch.stack([zero + x, zero + y, zero + z], dim=-1)

    grip, spread, cup = rand(), -0.1 + 0.4 * rand(), rand()
    rows: dict[str, torch.Tensor] = {}
    for finger, (spread_k, cup_k) in zip(_FINGERS, _FINGER_SPREAD_CUP, strict=True):
        curl = (grip + 0.3 * randn()).clamp(-0.15, 1.0)  # < 0: slight hyperextension at the MCP
        pip = _PIP_FLEX * (curl + 0.2 * randn()).clamp(0.0, 1.0)
        dip = (0.65 * pip + 0.1 * randn()).clamp(-0.1, _DIP_MAX)  # the DIP follows the PIP
        abduct = spread_k * spread * (1.0 - 0.7 * curl.clamp(min=0.0))  # fingers close up as they flex
        rows[f"{finger}1"] = vec(0.0, 0.0, -cup_k * cup)
        rows[f"{finger}2"] = vec(0.0, abduct, -_MCP_FLEX * curl)
        rows[f"{finger}3"] = vec(0.0, 0.0, -pip)
        rows[f"{finger}4"] = vec(0.0, 0.0, -dip)
    thumb = (grip + 0.35 * randn()).clamp(-0.2, 1.0)
    oppose, radial = rand(), -0.1 + 0.8 * rand()
    flex_axis = torch.tensor([0.0, 1.0, -1.0], dtype=f64) / math.sqrt(2.0)
    # CMC: pronation about the thumb's axis and palmar abduction grow with opposition; radial
    # abduction (toward +Z, away from the index) shrinks with it.
    rows["Thumb1"] = vec(0.5 * oppose + 0.1 * randn(), -radial * (1.0 - oppose), -0.8 * oppose)
    rows["Thumb2"] = (_THUMB_MCP * thumb.clamp(min=-0.1))[:, None] * flex_axis
    rows["Thumb3"] = (_THUMB_IP * (thumb + 0.25 * randn()).clamp(-0.25, 1.0))[:, None] * flex_axis
    return rows


def sample_hand_poses(n: int, generator: torch.Generator, *, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Random gestures of both hands: (n, 77, 3) T-pose-relative axis-angle, zero except ``FINGER_JOINTS``.

    Per hand a grip in [0, 1] sets the mean curl; each finger deviates from it (curl clamped to
    [-0.15, 1]: MCP flexion up to 1.55 rad with slight hyperextension, PIP up to 1.7 rad, DIP
    about 0.65 of the PIP, at most 1.3 rad); fingers spread by up to 0.3 rad at the MCP (less
    when flexed); the ring and little metacarpals cup the palm by up to 0.12 and 0.25 rad. The
    thumb has its own curl (MCP up to 0.9 rad, IP up to 1.3 rad) and an opposition amount that
    pronates and palmar-abducts its CMC joint. Hands are independent; the right is the mirror
    image of a left-hand draw.
    """
    _check_int(n, "n", 0)
    pose = torch.zeros(n, len(JOINT_NAMES) - 1, 3, dtype=torch.float64)
    for side in ("Left", "Right"):
        for name, v in _left_hand(n, generator).items():
            pose[:, joint_index(f"{side}Hand{name}") - 1] = v if side == "Left" else mirror_rotation(v)
    return pose.to(dtype)


# --------------------------------------------------------------------------- body poses

_ARM_TWISTS = (("Arm", 1.3), ("ForeArm", 1.5))  # largest extra twist, rad: humeral rotation, pro/supination
# The joints a body sample takes from the pose sampler; the others (fingers, jaw, eyes, end
# joints) keep the identity's rest rotations, so H_B holds no hand or face motion.
_BODY_JOINTS: tuple[str, ...] = ("Hips",) + tuple(
    side + name[4:] if name.startswith("Left") else name
    for name in JOINT_RANGES
    for side in (("Left", "Right") if name.startswith("Left") else ("",))
)


def _body_poses(n: int, gen: torch.Generator, twist_fraction: float) -> torch.Tensor:
    """(n, 77, 3) float64: sample_poses with the Hips upright at zero heading, plus arm twists.

    Only the rows of ``_BODY_JOINTS`` are used (the fingers are not drawn).
    In a ``twist_fraction`` of samples (per side) the upper arm and forearm lose the twist
    component of their sampled rotation and get a large one instead: R = R_swing R_x(tau),
    |tau| in [0.5, 1] of the joint's range, random sign (the bones lie along +-X in the T-pose,
    and a rotation vector without X component is a pure swing about X).
    """
    f64 = torch.float64
    pose = sample_poses(n, gen, fingers=False, tumble=0.0, dtype=f64)
    pose[:, joint_index("Hips") - 1] = 0.0
    e_x = torch.tensor([1.0, 0.0, 0.0], dtype=f64)
    for side in ("Left", "Right"):
        pick = torch.rand(n, generator=gen, dtype=f64) < twist_fraction
        for name, largest in _ARM_TWISTS:
            j = joint_index(side + name) - 1
            size = largest * (0.5 + 0.5 * torch.rand(n, generator=gen, dtype=f64))
            tau = torch.where(torch.rand(n, generator=gen, dtype=f64) < 0.5, -size, size)
            swing = pose[:, j] * (1.0 - e_x)
            twisted = matrix_to_axis_angle(axis_angle_to_matrix(swing) @ axis_angle_to_matrix(tau[:, None] * e_x))
            pose[:, j] = torch.where(pick[:, None], twisted, pose[:, j])
    return pose


def _plan(subset: str, n: int, seed: int, twist_fraction: float, max_active: int) -> torch.Tensor:
    """Per-sample parameters, float64 on cpu: body/hands (n, 77, 3) poses, face (n, 52) weights."""
    parts = []
    for chunk in range(-(-n // _CHUNK)):
        if subset == "body":
            gen = keyed_generator("panoman", subset, seed, twist_fraction, chunk)
            parts.append(_body_poses(_CHUNK, gen, twist_fraction))
        elif subset == "face":
            gen = keyed_generator("panoman", subset, seed, max_active, chunk)
            parts.append(sample_expressions(_CHUNK, gen, max_active=max_active))
        else:
            parts.append(sample_hand_poses(_CHUNK, keyed_generator("panoman", subset, seed, chunk)))
    return torch.cat(parts)[:n]


# --------------------------------------------------------------------------- meshes


@functools.cache
def _layer(device: str) -> BodyLayer:
    """The float64 PCA layer (10 components, procedural twist) on ``device``, built once."""
    return BodyLayer.from_pca(num_components=NUM_SHAPE, procedural=True, dtype=torch.float64).to(device)


@functools.cache
def _head_vertices() -> torch.Tensor:
    """(V,) bool: vertices skinned to the head joints only (their weights sum to 1)."""
    w = Rig.canonical().dense_skinning_weights()
    return w[:, [joint_index(name) for name in _HEAD_JOINTS]].sum(1) > 0.999


def _head_radius(rest: torch.Tensor) -> torch.Tensor:
    """(B,) RMS distance of the head vertices of ``rest`` (B, V, 3) from their centroid, m."""
    head = rest[:, _head_vertices().to(rest.device)]
    return (head - head.mean(1, keepdim=True)).pow(2).sum(-1).mean(1).sqrt()


def _rest_pose(layer: BodyLayer, prep: PreparedIdentity) -> torch.Tensor:
    """(M, 77, 3) the identities' rest poses as T-pose-relative axis-angle (they reproduce the rest mesh)."""
    rot = prep.rest_rotations
    local = rot[:, layer.parents[1:]].transpose(-1, -2) @ rot[:, 1:]
    return matrix_to_axis_angle(layer.to_relative(local))


def _select(prep: PreparedIdentity, idx: torch.Tensor) -> PreparedIdentity:
    return PreparedIdentity(prep.rest_vertices[idx], prep.rest_rotations[idx], prep.rest_joints[idx], prep.offsets[idx])


def iter_batches(
    subset: Subset,
    n: int,
    *,
    seed: int,
    identities: int | None = None,
    batch_size: int = 64,
    twist_fraction: float = 0.25,
    max_active: int = 3,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> Iterator[PanoSamples]:
    """Stream the ``n`` samples of a subset in batches (the whole-set functions concatenate them).

    Args:
        subset: "body", "face" or "hands".
        n: number of samples (>= 1).
        seed: the set's seed (identity pool and motion streams); 0 for training, 1 held out.
        identities: pool size M (default: 200 body, 100 face, 300 hands, as in the paper);
            sample i uses identity i mod M.
        batch_size: samples per yielded batch.
        twist_fraction: body only: fraction of arms with a large upper-arm and forearm twist.
        max_active: face only: at most this many facial-action units per sample (0: neutral faces).
        dtype: float32 or float64 of the yielded tensors (computed in float64).
        device: where the meshes are computed and returned (default cpu).

    Raises:
        ValueError: unknown subset, non-positive sizes, a fraction outside [0, 1] or an unsupported dtype.
    """
    if subset not in SUBSETS:
        raise ValueError(f"subset: expected one of {', '.join(SUBSETS)}, got {subset!r}")
    _check_int(n, "n", 1)
    _check_int(seed, "seed", 0)
    _check_int(batch_size, "batch_size", 1)
    _check_int(max_active, "max_active", 0)
    m = _check_int(_DEFAULT_IDENTITIES[subset] if identities is None else identities, "identities", 1)
    if not 0.0 <= twist_fraction <= 1.0:
        raise ValueError(f"twist_fraction: expected a fraction in [0, 1], got {twist_fraction}")
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"dtype: expected torch.float32 or torch.float64, got {dtype}")
    device = torch.device("cpu" if device is None else device)
    return _batches(subset, n, seed, min(m, n), batch_size, twist_fraction, max_active, dtype, device)


def _batches(
    subset: str,
    n: int,
    seed: int,
    m: int,
    batch_size: int,
    twist_fraction: float,
    max_active: int,
    dtype: torch.dtype,
    device: torch.device,
) -> Iterator[PanoSamples]:
    """The generator behind :func:`iter_batches` (arguments already checked; ``m`` <= n)."""
    layer = _layer(str(device))
    plan = _plan(subset, n, seed, twist_fraction, max_active).to(device)
    shape = identity_pool(m, seed=seed, dtype=torch.float64).to(device)
    with torch.no_grad():
        pool = layer.prepare_identity(shape)
        rest_pose = _rest_pose(layer, pool)
        if subset == "face":
            deltas = expression_basis(torch.float64, device)[1]
            scale = _head_radius(pool.rest_vertices) / _head_radius(expression_reference(torch.float64, device)[None])
    fingers = torch.tensor([joint_index(name) - 1 for name in FINGER_JOINTS], device=device)
    body_rows = torch.tensor([joint_index(name) - 1 for name in _BODY_JOINTS], device=device)
    for start in range(0, n, batch_size):
        stop = min(start + batch_size, n)
        idx = torch.arange(start, stop, device=device) % m
        prep = _select(pool, idx)
        expression = plan.new_zeros(stop - start, len(FACIAL_ACTIONS))
        with torch.no_grad():
            if subset == "face":
                expression = plan[start:stop]
                pose = rest_pose[idx]
                offsets = torch.einsum("bk,kvc->bvc", expression, deltas)
                posed = prep.rest_vertices + scale[idx, None, None] * offsets
            else:
                pose = rest_pose[idx].clone()
                rows = body_rows if subset == "body" else fingers
                pose[:, rows] = plan[start:stop, rows]
                posed = layer.pose(prep, pose, transl=prep.rest_joints[:, 1]).vertices
        yield PanoSamples(
            subset,
            prep.rest_vertices.to(dtype),
            posed.to(dtype),
            idx,
            shape[idx].to(dtype),
            pose.to(dtype),
            expression.to(dtype),
        )


def _concat(batches: list[PanoSamples]) -> PanoSamples:
    first = batches[0]
    fields = ("rest", "posed", "identity", "shape", "pose", "expression")
    return PanoSamples(first.subset, *(torch.cat([getattr(b, f) for b in batches]) for f in fields))


def body_samples(
    n: int,
    *,
    seed: int,
    identities: int = 200,
    twist_fraction: float = 0.25,
    batch_size: int = 64,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> PanoSamples:
    """H_B: ``n`` posed bodies (procedural twist on, Hips upright, relaxed fingers); see :func:`iter_batches`."""
    return _concat(list(iter_batches("body", n, seed=seed, identities=identities, batch_size=batch_size,
                                     twist_fraction=twist_fraction, dtype=dtype, device=device)))  # fmt: skip


def face_samples(
    n: int,
    *,
    seed: int,
    identities: int = 100,
    max_active: int = 3,
    batch_size: int = 64,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> PanoSamples:
    """H_F: ``n`` rest meshes with sparse facial expressions (:func:`sample_expressions`); see :func:`iter_batches`."""
    return _concat(list(iter_batches("face", n, seed=seed, identities=identities, batch_size=batch_size,
                                     max_active=max_active, dtype=dtype, device=device)))  # fmt: skip


def hand_samples(
    n: int,
    *,
    seed: int,
    identities: int = 300,
    batch_size: int = 64,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> PanoSamples:
    """H_H: ``n`` rest-pose bodies with random finger poses (:func:`sample_hand_poses`); see :func:`iter_batches`."""
    return _concat(list(iter_batches("hands", n, seed=seed, identities=identities, batch_size=batch_size,
                                     dtype=dtype, device=device)))  # fmt: skip


def full_samples(n: int, *, seed: int, identities: int = 100, dtype: torch.dtype = torch.float32) -> PanoSamples:
    """Full motion for evaluation: a body pose, both hands' gestures and a facial expression at once.

    The three motions are drawn from the same streams as the subsets of ``seed`` (body joints
    from the body plan, finger joints from the hand plan, facial actions from the face plan);
    the expression offsets are added to the rest mesh before posing (the skeleton is the
    identity's own). Subset ``"full"``.
    """
    _check_int(n, "n", 1)
    layer = _layer("cpu")
    m = min(_check_int(identities, "identities", 1), n)
    shape = identity_pool(m, seed=seed, dtype=torch.float64)
    idx = torch.arange(n) % m
    body, hands = _plan("body", n, seed, 0.25, 3), _plan("hands", n, seed, 0.25, 3)
    expression = _plan("face", n, seed, 0.25, 3)
    fingers = torch.tensor([joint_index(name) - 1 for name in FINGER_JOINTS])
    body_rows = torch.tensor([joint_index(name) - 1 for name in _BODY_JOINTS])
    with torch.no_grad():
        pool = layer.prepare_identity(shape)
        prep = _select(pool, idx)
        pose = _rest_pose(layer, pool)[idx]
        pose[:, body_rows] = body[:, body_rows]
        pose[:, fingers] = hands[:, fingers]
        deltas = expression_basis(torch.float64)[1]
        scale = _head_radius(pool.rest_vertices) / _head_radius(expression_reference(torch.float64)[None])
        rest = prep.rest_vertices + scale[idx, None, None] * torch.einsum("bk,kvc->bvc", expression, deltas)
        moved = PreparedIdentity(rest, prep.rest_rotations, prep.rest_joints, prep.offsets)
        posed = layer.pose(moved, pose, transl=prep.rest_joints[:, 1]).vertices
    return PanoSamples("full", prep.rest_vertices.to(dtype), posed.to(dtype), idx, shape[idx].to(dtype),
                       pose.to(dtype), expression.to(dtype))  # fmt: skip
