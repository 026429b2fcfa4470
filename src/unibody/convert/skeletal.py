"""BVH and ASF/AMC motions onto the canonical body.

A BVH of the canonical skeleton (joint names ``unibody.JOINT_NAMES[1:]``, end sites allowed,
T-pose rest with world-aligned joint frames, as :mod:`unibody.convert.bvh_export` writes it) is
mapped by name: its local rotations are the T-pose-relative rotations, exactly. Any other
skeleton is retargeted (:func:`unibody.fitting.retarget.retarget`): joints are matched by the
name rules below (CMU's 31-bone ASF skeleton and its BVH conversions, the 43-joint
cgspeed/DAZ CMU conversion, Mixamo, canonical names), overridden by ``options.mapping`` (a JSON
object ``{"source name": "CanonicalName" | null}``); the rule set that matches most joints wins.
Lengths are ``options.units``, else the file's own unit (ASF ``:units length``), else detected
from the rest skeleton's standing height (:data:`UNITS`). Sources are Y up (BVH and CMU's
ASF/AMC are); their facing is free (the retargeting aligns the torsos).

Statistics (``Converted.stats``): ``frames``, ``fps``, ``mapped_joints``, ``metres_per_unit``,
``retarget_mean_mm`` / ``retarget_p95_mm`` / ``retarget_max_mm`` (mapped canonical joints to
their source joints), ``max_joint_change_deg`` (largest change of a local rotation between two
frames) and ``source_max_joint_change_deg``, ``seconds``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch

from ..body import BodyLayer
from ..fitting.retarget import RetargetConfig, fit_tpose_offsets, retarget
from ..geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from ..io.asfamc import read_asf_amc
from ..io.bvh import read_bvh as read_bvh_file
from ..io.skeletal import SkeletalMotion
from ..motion import MAX_DISTANCE, Motion
from ..rig import JOINT_NAMES
from ._body import _layer as _body_layer
from ._types import Converted, ConvertOptions

__all__ = ["MIN_MAPPED", "NAME_RULES", "UNITS", "map_joints", "read_amc", "read_bvh", "skeletal_to_motion"]

MIN_MAPPED = 8
"""Fewest joints a skeleton must map to retarget it."""

UNITS: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254, "ft": 0.3048}
"""Length units ``options.units`` takes (metres per unit)."""
_DETECT = {**UNITS, "CMU ASF unit (0.0254/0.45 m)": 0.0254 / 0.45}
_HEIGHT_LIKELY = (0.9, 2.3)  # m: detection prefers a unit that puts the height here...
_HEIGHT_OK = (0.4, 3.0)  # ...and refuses one outside this (a body 100x too large or small)


def _side(rules: dict[str, str]) -> dict[str, str]:
    """Add the right side of left-side rules ('L'/'l'/'Left' prefixes, 'Left' in the target)."""
    out = dict(rules)
    for src, dst in rules.items():
        for a, b in (("Left", "Right"), ("left", "right"), ("L", "R"), ("l", "r")):
            if src.startswith(a):
                out[b + src[len(a) :]] = dst.replace("Left", "Right")
                break
    return out


_LIMBS = ("Shoulder", "Arm", "ForeArm", "Hand", "Leg", "Shin", "Foot", "ToeBase", "ToeEnd")
NAME_RULES: dict[str, dict[str, str]] = {
    # CMU's ASF bones; joints sit at the bone's start (lfemur: the hip joint). Some BVH
    # conversions keep these names with a root called "hip".
    "cmu_asf": _side(
        {
            "root": "Hips",
            "hip": "Hips",
            "upperback": "Spine2",
            "thorax": "Chest",
            "lowerneck": "Neck1",
            "upperneck": "Neck2",
        }
        | {"head": "Head", "lclavicle": "LeftShoulder", "lhumerus": "LeftArm", "lradius": "LeftForeArm"}
        | {"lwrist": "LeftHand", "lfemur": "LeftLeg", "ltibia": "LeftShin", "lfoot": "LeftFoot", "ltoes": "LeftToeBase"}
    ),
    # The same skeleton converted to BVH (31 joints: Hips, LHipJoint, LeftHip, LeftKnee, ...).
    "cmu_bvh": _side(
        {"Hips": "Hips", "Chest": "Spine2", "Chest2": "Chest", "LowerNeck": "Neck1", "Neck": "Neck2", "Head": "Head"}
        | {"LeftCollar": "LeftShoulder", "LeftShoulder": "LeftArm", "LeftElbow": "LeftForeArm"}
        | {"LeftWrist": "LeftHand", "LeftHip": "LeftLeg", "LeftKnee": "LeftShin", "LeftAnkle": "LeftFoot"}
        | {"LeftToe": "LeftToeBase"}
    ),
    # cgspeed's 43-joint CMU conversion (DAZ names); lFoot's end site is at the toes.
    "daz": _side(
        {"hip": "Hips", "abdomen": "Spine2", "chest": "Chest", "neck": "Neck1", "head": "Head"}
        | {"lCollar": "LeftShoulder", "lShldr": "LeftArm", "lForeArm": "LeftForeArm", "lHand": "LeftHand"}
        | {"lThigh": "LeftLeg", "lShin": "LeftShin", "lFoot": "LeftFoot", "lFoot_End": "LeftToeBase"}
    ),
    "mixamo": _side(
        {"Hips": "Hips", "Spine": "Spine1", "Spine1": "Spine2", "Spine2": "Chest", "Neck": "Neck1", "Head": "Head"}
        | {"HeadTop_End": "HeadEnd", "LeftShoulder": "LeftShoulder", "LeftArm": "LeftArm"}
        | {"LeftForeArm": "LeftForeArm", "LeftHand": "LeftHand", "LeftUpLeg": "LeftLeg", "LeftLeg": "LeftShin"}
        | {"LeftFoot": "LeftFoot", "LeftToeBase": "LeftToeBase", "LeftToe_End": "LeftToeEnd"}
    ),
    "canonical": {n: n for n in JOINT_NAMES[1:]},
}
"""Source joint name -> canonical joint, per skeleton family (matched case-insensitively, after
dropping a ``namespace:`` prefix such as ``mixamorig:``)."""


def _key(name: str) -> str:
    return name.rsplit(":", 1)[-1].lower()


def map_joints(names: tuple[str, ...], mapping: Path | None = None, where: str = "") -> dict[int, str]:
    """Source joint index -> canonical joint name, by the best rule set and ``mapping`` overrides.

    Raises:
        ValueError: the mapping file is not a JSON object of names to canonical names or null,
            names a joint the skeleton lacks or an unknown canonical joint.
    """
    keys = [_key(n) for n in names]
    best: dict[int, str] = {}
    for rules in NAME_RULES.values():
        low = {k.lower(): v for k, v in rules.items()}
        found = {i: low[k] for i, k in enumerate(keys) if k in low}
        if len(found) > len(best):
            best = found
    if mapping is not None:
        best = _override(best, names, Path(mapping), where)
    seen: dict[str, int] = {}
    for i, c in sorted(best.items()):
        if c in seen:
            raise ValueError(
                f"{where}mapping: {names[seen[c]]!r} and {names[i]!r} both map to {c!r}; map each canonical joint once"
            )
        seen[c] = i
    return best


def _override(best: dict[int, str], names: tuple[str, ...], path: Path, where: str) -> dict[int, str]:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: expected a JSON object {{source name: canonical name or null}}, got {exc}") from None
    form = "a JSON object {source name: canonical name or null}"
    if not isinstance(data, dict) or not all(v is None or isinstance(v, str) for v in data.values()):
        raise ValueError(f"{path}: expected {form}, got {json.dumps(data)[:80]}")
    index = {n: i for i, n in enumerate(names)}
    missing = [k for k in data if k not in index]
    if missing:
        raise ValueError(f"{path}: expected joints of the skeleton of {where or 'the file'}got {missing} (not in it)")
    unknown = [v for v in data.values() if v is not None and v not in JOINT_NAMES[1:]]
    if unknown:
        raise ValueError(f"{path}: expected canonical joint names (unibody.JOINT_NAMES[1:]) or null, got {unknown}")
    out = dict(best)
    for k, v in data.items():
        out.pop(index[k], None)
        if v is not None:
            out[index[k]] = v
    return out


def _rest_world(sk: SkeletalMotion) -> tuple[np.ndarray, np.ndarray]:
    """Rest-pose world positions (J, 3) (file units, root at the origin) and orientations (J, 3, 3)."""
    rest = SkeletalMotion(
        sk.names, sk.parents, sk.offsets, np.eye(3)[None, None].repeat(len(sk.names), 1), sk.offsets[None].copy(), 1.0
    )
    pos, rot = rest.world()
    pos = pos[0] - sk.offsets[0]
    return pos, rot[0]


def _height(rest: np.ndarray) -> float:
    ext = rest.max(0) - rest.min(0)
    return float(ext[1] if ext[1] >= 0.5 * ext.max() else ext.max())


def metres_per_unit(sk: SkeletalMotion, units: str | None, where: str) -> float:
    """The length unit: ``units``, else the file's, else detected from the standing height.

    Raises:
        ValueError: an unknown unit, or a height outside 0.4-3 m (the message names the likely unit).
    """
    h = _height(_rest_world(sk)[0])
    fits = {u: h * f for u, f in _DETECT.items() if _HEIGHT_OK[0] <= h * f <= _HEIGHT_OK[1]}
    likely = [u for u, m in fits.items() if _HEIGHT_LIKELY[0] <= m <= _HEIGHT_LIKELY[1]] or list(fits)
    guess = min(likely, key=lambda u: abs(np.log(fits[u] / 1.7)), default=None)
    if units is not None:
        if units not in UNITS:
            raise ValueError(f"units: expected one of {', '.join(UNITS)}, got {units!r}")
        m = h * UNITS[units]
        if not _HEIGHT_OK[0] <= m <= _HEIGHT_OK[1]:
            hint = f"; the file is likely in {guess}" if guess else ""
            lo, hi = _HEIGHT_OK
            raise ValueError(f"{where}units {units!r} make the skeleton {m:.4g} m tall (expected {lo}-{hi} m){hint}")
        return UNITS[units]
    if sk.meters_per_unit is not None:
        m = h * sk.meters_per_unit
        if not _HEIGHT_OK[0] <= m <= _HEIGHT_OK[1]:
            raise ValueError(
                f"{where}the file's unit ({sk.meters_per_unit:g} m) makes the skeleton {m:.4g} m tall "
                f"(expected {_HEIGHT_OK[0]}-{_HEIGHT_OK[1]} m); pass units"
            )
        return float(sk.meters_per_unit)
    if guess is None:
        raise ValueError(
            f"{where}cannot detect the length unit: the rest skeleton is {h:.4g} units tall, which is no "
            f"{_HEIGHT_OK[0]}-{_HEIGHT_OK[1]} m body in {', '.join(UNITS)}; pass units"
        )
    return _DETECT[guess]


def _layer(num_components: int, dtype: torch.dtype) -> BodyLayer:
    """The PCA layer of ``num_components`` (the one cache of :mod:`unibody.convert._body`: the
    128-component layer that fits a canonical BVH is also the one its motion plays on)."""
    return _body_layer("pca", num_components, dtype)


_COINCIDENT_M = 0.01


def _drop_coincident(sk: SkeletalMotion, mapping: dict[int, str], rest_m: np.ndarray, where: str) -> list[str]:
    """Unmap joints that sit on their nearest mapped source ancestor at rest (within 1 cm).

    Some conversions put a joint on its parent (CMU BVHs with ASF names place ``lowerneck`` and
    the clavicles at the thorax's start): two canonical joints cannot both follow one point.
    Changes ``mapping`` in place; returns one warning per dropped joint.
    """
    out = []
    for i in sorted(mapping):
        a = int(sk.parents[i])
        while a >= 0 and a not in mapping:
            a = int(sk.parents[a])
        if a >= 0 and np.linalg.norm(rest_m[i] - rest_m[a]) < _COINCIDENT_M:
            out.append(f"{where}joint {sk.names[i]!r} sits on {sk.names[a]!r} at rest; {mapping.pop(i)} left unmapped")
    return out


def _max_change_deg(rot: np.ndarray) -> float:
    """Largest angle (deg) between consecutive frames of local rotations (T, J, 3, 3)."""
    if rot.shape[0] < 2:
        return 0.0
    rel = np.einsum("tjba,tjbc->tjac", rot[:-1], rot[1:])
    cos = np.clip((np.trace(rel, axis1=-2, axis2=-1) - 1) / 2, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos)).max())


def _check_frames(sk: SkeletalMotion, where: str) -> None:
    bad = ~(np.isfinite(sk.rotations).reshape(sk.num_frames, -1).all(1))
    bad |= ~np.isfinite(sk.translations).reshape(sk.num_frames, -1).all(1)
    if bad.any():
        idx = np.flatnonzero(bad).tolist()
        shown = ", ".join(map(str, idx[:10])) + (" ..." if len(idx) > 10 else "")
        raise ValueError(f"{where}expected finite joint values, got NaN/inf in {len(idx)} frame(s): {shown}")
    if sk.num_frames == 0:
        raise ValueError(f"{where}expected at least one frame, got 0")


def _canonical_skeleton(sk: SkeletalMotion, parents: tuple[int, ...]) -> bool:
    """Whether the joints (end sites aside) are the canonical ones, in order, with the canonical ``parents``."""
    keep = [i for i, n in enumerate(sk.names) if "_End" not in n]
    if tuple(sk.names[i] for i in keep) != JOINT_NAMES[1:]:
        return False
    parent_names = [sk.names[p] if p >= 0 else "Root" for p in sk.parents[keep]]
    return parent_names == [JOINT_NAMES[max(p, 0)] for p in parents[1:]]


def _by_name(
    sk: SkeletalMotion, layer: BodyLayer, scale: float, cfg: RetargetConfig, source: str, start: float
) -> Converted:
    """A canonical skeleton: rotations by name (exact); the identity fitted to the rest offsets."""
    src_change = _max_change_deg(sk.rotations)
    dtype = layer.tpose_orient.dtype
    cols = [sk.names.index(n) for n in JOINT_NAMES[1:]]
    rot = torch.as_tensor(sk.rotations[:, cols], dtype=torch.float64)
    pose = matrix_to_axis_angle(rot).numpy().astype(np.float32)
    transl = (sk.translations[:, 0] * scale).astype(np.float32)
    # The identity from the rest offsets (world-axis vectors in the T-pose): all coefficients, linear.
    full = _layer(128, dtype)
    offsets = torch.as_tensor(sk.offsets[cols] * scale, dtype=dtype)
    params, bone_err = fit_tpose_offsets(full, offsets)
    identity = params.double().numpy().astype(np.float32)
    motion = Motion(pose, transl, float(sk.fps), identity, "pca", source)
    stats = {"frames": sk.num_frames, "fps": float(sk.fps), "mapped_joints": 77, "metres_per_unit": scale}
    stats["identity_bone_rms_mm"] = float(bone_err.double().square().mean().sqrt()) * 1e3
    stats |= {"retarget_mean_mm": 0.0, "retarget_p95_mm": 0.0, "retarget_max_mm": 0.0}
    stats |= {"max_joint_change_deg": src_change, "source_max_joint_change_deg": src_change}
    return Converted(motion, stats | {"seconds": time.perf_counter() - start})


def skeletal_to_motion(
    sk: SkeletalMotion, options: ConvertOptions, source: str, where: str = "", config: RetargetConfig | None = None
) -> Converted:
    """Map (canonical skeleton) or retarget (any other) a :class:`SkeletalMotion` onto the canonical body.

    Raises:
        ValueError: NaN frames (their indices), fewer than :data:`MIN_MAPPED` mapped joints (the
            unmapped ones listed), units that give an implausible height, or a root farther than
            :data:`~unibody.motion.MAX_DISTANCE` from the origin.
    """
    start = time.perf_counter()
    _check_frames(sk, where)
    scale = metres_per_unit(sk, options.units, where)
    root = np.abs(sk.translations[:, np.asarray(sk.parents) < 0]).max(axis=(1, 2)) * scale
    if root.max() > MAX_DISTANCE:
        raise ValueError(
            f"{where}expected the root within {MAX_DISTANCE:g} m of the origin, got {root.max():.3g} m "
            f"at frame {int(root.argmax())} ({scale:g} m per unit)"
        )
    dtype = torch.float64 if options.dtype == "float64" else torch.float32
    src_change = _max_change_deg(sk.rotations)
    cfg = config or RetargetConfig(batch=max(1, int(options.batch)))
    layer = _layer(cfg.num_components, dtype)
    if _canonical_skeleton(sk, layer.rig_tree.parents) and options.mapping is None:
        return _by_name(sk, layer, scale, cfg, source, start)
    mapping = map_joints(sk.names, options.mapping, where)
    rest_pos, rest_rot = _rest_world(sk)
    warnings = _drop_coincident(sk, mapping, rest_pos * scale, where)
    if len(mapping) < MIN_MAPPED:
        unmapped = [n for i, n in enumerate(sk.names) if i not in mapping]
        raise ValueError(
            f"{where}only {len(mapping)} joint(s) map to the canonical rig (need {MIN_MAPPED}); unmapped: "
            f"{', '.join(unmapped)}; give a mapping JSON {{source name: canonical name}}"
        )
    cols = sorted(mapping)
    pos, rot = sk.world()
    as_t = lambda x: torch.as_tensor(np.ascontiguousarray(x), dtype=dtype)  # noqa: E731
    res = retarget(
        layer,
        as_t(pos[:, cols] * scale),
        [mapping[c] for c in cols],
        orientations=as_t(rot[:, cols]),
        rest_positions=as_t(rest_pos[cols] * scale),
        rest_orientations=as_t(rest_rot[cols]),
        offset_frames=as_t(rot[:, [max(int(sk.parents[c]), 0) for c in cols]]),
        config=cfg,
    )
    pose = res.pose.double().numpy()
    err = res.joint_error.double().numpy() * 1e3
    change = _max_change_deg(axis_angle_to_matrix(torch.as_tensor(pose)).numpy())
    motion = Motion(
        pose.astype(np.float32),
        res.transl.double().numpy().astype(np.float32),
        float(sk.fps),
        res.identity.double().numpy().astype(np.float32),
        "pca",
        source,
    )
    stats = {"frames": sk.num_frames, "fps": float(sk.fps), "mapped_joints": len(cols), "metres_per_unit": scale}
    stats |= {"retarget_mean_mm": float(err.mean()), "retarget_p95_mm": float(np.percentile(err, 95))}
    stats |= {"retarget_max_mm": float(err.max()), "max_joint_change_deg": change}
    raw = res.raw_error.double().numpy() * 1e3
    stats |= {"retarget_raw_mean_mm": float(raw.mean()), "retarget_raw_p95_mm": float(np.percentile(raw, 95))}
    stats |= {"source_max_joint_change_deg": src_change, "seconds": time.perf_counter() - start}
    return Converted(motion, stats, tuple(warnings))


def read_bvh(path: Path, options: ConvertOptions) -> Converted:
    """A BVH motion of any skeleton -> canonical motion (see the module docstring).

    Raises:
        ValueError: an unreadable BVH (from :func:`unibody.io.bvh.read_bvh`), NaN frames, too
            few mappable joints, implausible units; one line naming the file.
    """
    path = Path(path)
    sk = read_bvh_file(path)
    return skeletal_to_motion(sk, options, f"bvh: {path.name}", f"{path}: ")


def find_asf(amc: Path) -> Path:
    """The skeleton of an AMC file: the only ``.asf`` beside it, or the one whose stem prefixes the AMC's.

    Raises:
        ValueError: none, or several that fit equally.
    """
    amc = Path(amc)
    asfs = sorted(p for p in amc.parent.iterdir() if p.suffix.lower() == ".asf")
    if len(asfs) == 1:
        return asfs[0]
    fit = [p for p in asfs if amc.stem.startswith(p.stem)]
    longest = max((len(p.stem) for p in fit), default=0)
    fit = [p for p in fit if len(p.stem) == longest]
    if len(fit) == 1:
        return fit[0]
    found = ", ".join(p.name for p in asfs) or "none"
    raise ValueError(
        f"{amc}: expected its skeleton as the only .asf in {amc.parent} or one whose name prefixes "
        f"{amc.stem!r}, got {found}"
    )


def read_amc(path: Path, options: ConvertOptions) -> Converted:
    """An AMC motion (its ASF skeleton beside it, :func:`find_asf`) -> canonical motion.

    Raises:
        ValueError: no matching ASF, unreadable files, NaN frames, too few mapped joints, units.
    """
    path = Path(path)
    sk = read_asf_amc(find_asf(path), path)
    return skeletal_to_motion(sk, options, f"asf/amc: {path.name}", f"{path}: ")
