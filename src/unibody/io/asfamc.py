"""Acclaim ASF/AMC motion files (CMU's original format): read into a :class:`SkeletalMotion` (numpy only).

The ASF file holds the skeleton: ``:units`` (``mass``, ``length``, ``angle deg|rad``), ``:root``
(``order`` of the root's AMC values, ``axis`` its rotation order, rest ``position`` and
``orientation``), ``:bonedata`` (per bone: ``id``, ``name``, unit ``direction`` and ``length`` in
world axes at rest, ``axis a b c ORDER`` its local frame, ``dof`` and ``limits``) and
``:hierarchy`` (``parent child child ...``). The AMC file holds frames: a frame number, then one
line per moving bone, ``name v1 v2 ...`` in the bone's ``dof`` order (``:DEGREES`` or
``:RADIANS``; the ASF angle unit when neither is stated).

Facts of the format used here (Acclaim conventions):

- an order ``XYZ`` means the rotations are applied about x first, then y, then z, about fixed
  axes: ``R = Rz(c) @ Ry(b) @ Rx(a)``; the three ``axis`` values go with the letters as listed;
- a bone's axis rotation ``C`` gives its local frame in world axes; its motion ``M`` (from the
  ``rx ry rz`` dofs, missing ones zero, applied in the bone's axis order) acts in that frame, so
  in world-aligned frames the bone's local rotation is ``L = C @ M @ C^-1``; the root likewise
  with its ``orientation`` and ``axis``;
- a bone rotates about its start, which is the end of its parent bone (the root position for
  bones attached to the root); translation dofs ``tx ty tz`` move the bone's start in its axis
  frame, and ``l`` lengthens it along its direction.

The result follows the :class:`SkeletalMotion` convention: joint 0 is ``root``; each bone is a
joint named after it, placed at the bone's **start** (so ``lfemur`` is the hip joint and
``ltibia`` the knee), with offset = its parent bone's vector ``length * direction`` (zero under
the root); a bone without children ends in a joint ``<bone>_End``. Rest rotations are identity
and rest frames are world-aligned. Lengths stay in file units; ``meters_per_unit`` is
``0.0254 / length`` from ``:units length`` (VICON/CMU files scale inches by it: CMU's 0.45 gives
0.0564 m per unit), None when the ASF states no length.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .bvh import MAX_FRAMES, MAX_JOINTS, euler_to_matrix, number_token
from .skeletal import SkeletalMotion

__all__ = ["read_asf", "read_asf_amc", "AsfSkeleton"]

_ROT_DOFS = ("rx", "ry", "rz")
_DOFS = {"rx", "ry", "rz", "tx", "ty", "tz", "l"}


@dataclass(slots=True)
class _Bone:
    name: str
    direction: np.ndarray = field(default_factory=lambda: np.zeros(3))
    length: float = 0.0
    axis: np.ndarray = field(default_factory=lambda: np.zeros(3))
    order: str = "XYZ"
    dof: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class AsfSkeleton:
    """An ASF skeleton: bones in depth-first order (parents first) and the root's settings.

    Attributes:
        names: bone names, ``"root"`` first.
        parents: (B,) parent index per bone, -1 for the root.
        directions: (B, 3) unit direction of each bone in world axes at rest (root: zero).
        lengths: (B,) bone lengths in file units (root: zero).
        axes: (B, 3, 3) each bone's axis frame ``C`` in world axes (root: from ``orientation``).
        dofs: per bone, its AMC values in order (root: ``order``, e.g. ``tx ty tz rx ry rz``).
        orders: per bone, the rotation order of its motion (root: ``axis``).
        root_position: (3,) the root's rest position.
        angle_scale: radians per ASF angle unit.
        meters_per_unit: ``0.0254 / :units length``, None when the ASF states no length.
    """

    names: tuple[str, ...]
    parents: np.ndarray
    directions: np.ndarray
    lengths: np.ndarray
    axes: np.ndarray
    dofs: tuple[tuple[str, ...], ...]
    orders: tuple[str, ...]
    root_position: np.ndarray
    angle_scale: float
    meters_per_unit: float | None


def acclaim_rotation(angles: np.ndarray, order: str) -> np.ndarray:
    """Rotations for angles (radians, ``(..., 3)``, one per letter of ``order``) applied in that order about fixed axes.

    ``order="XYZ"`` gives ``Rz(c) @ Ry(b) @ Rx(a)``.
    """
    angles = np.asarray(angles, dtype=np.float64)
    return euler_to_matrix(angles[..., ::-1], order[::-1])


_num = number_token


def _order(tok: str, where: str, line: int) -> str:
    order = tok.upper()
    if sorted(order) != ["X", "Y", "Z"]:
        raise ValueError(f"{where}: line {line}: expected a rotation order such as XYZ, got {tok!r}")
    return order


def _sections(lines: list[str], where: str) -> dict[str, list[tuple[int, list[str]]]]:
    """Lines (number, tokens) of each ``:keyword`` section; comments and blank lines dropped."""
    out: dict[str, list[tuple[int, list[str]]]] = {}
    current: list[tuple[int, list[str]]] | None = None
    for n, raw in enumerate(lines, start=1):
        text = raw.split("#", 1)[0].strip()
        if not text:
            continue
        if text.startswith(":"):
            key, *rest = text.split()
            current = out.setdefault(key.lower(), [])
            if rest:
                current.append((n, rest))
            continue
        if current is None:
            raise ValueError(f"{where}: line {n}: expected a ':keyword' section (an ASF file), got {text[:40]!r}")
        current.append((n, text.split()))
    for key in (":root", ":bonedata", ":hierarchy"):
        if key not in out:
            raise ValueError(f"{where}: expected an ASF file with a {key} section, got none")
    return out


def _units(rows: list[tuple[int, list[str]]], where: str) -> tuple[float, float | None]:
    angle, length = np.pi / 180.0, None
    for n, toks in rows:
        if len(toks) < 2:
            raise ValueError(f"{where}: line {n}: expected ':units' entries 'name value', got {' '.join(toks)!r}")
        if toks[0] == "angle":
            if toks[1].lower() not in ("deg", "rad"):
                raise ValueError(f"{where}: line {n}: expected 'angle deg' or 'angle rad', got {toks[1]!r}")
            angle = np.pi / 180.0 if toks[1].lower() == "deg" else 1.0
        elif toks[0] == "length":
            length = _num(toks[1], "the length unit", where, n)
            if length <= 0:
                raise ValueError(f"{where}: line {n}: expected a positive length unit, got {toks[1]!r}")
    return angle, (None if length is None else 0.0254 / length)


def _root(rows: list[tuple[int, list[str]]], angle: float, where: str) -> _Bone:
    root = _Bone("root", dof=("tx", "ty", "tz", "rx", "ry", "rz"))
    for n, toks in rows:
        key, vals = toks[0].lower(), toks[1:]
        if key == "order":
            dof = tuple(v.lower() for v in vals)
            if not set(dof) <= _DOFS - {"l"} or len(set(dof)) != len(dof):
                raise ValueError(
                    f"{where}: line {n}: expected ':root order' of TX TY TZ RX RY RZ, got {' '.join(vals)!r}"
                )
            root.dof = dof
        elif key == "axis":
            root.order = _order(vals[0] if vals else "", where, n)
        elif key in ("position", "orientation"):
            if len(vals) != 3:
                raise ValueError(f"{where}: line {n}: expected 3 numbers after {key}, got {len(vals)}")
            xyz = np.array([_num(v, f"root {key}", where, n) for v in vals])
            if key == "position":
                root.direction = xyz  # the rest position, kept here until the skeleton is built
            else:
                root.axis = xyz * angle
    return root


def _bones(rows: list[tuple[int, list[str]]], angle: float, where: str) -> list[_Bone]:
    bones: list[_Bone] = []
    bone: _Bone | None = None
    last_key = ""
    for n, toks in rows:
        key, vals = toks[0].lower(), toks[1:]
        if key == "begin":
            if bone is not None:
                raise ValueError(f"{where}: line {n}: expected 'end' before the next 'begin' in :bonedata")
            bone, last_key = _Bone(""), ""
            continue
        if bone is None:
            raise ValueError(f"{where}: line {n}: expected 'begin' in :bonedata, got {toks[0]!r}")
        if key == "end":
            if not bone.name:
                raise ValueError(f"{where}: line {n}: expected a 'name' in the bone ending here, got none")
            bones.append(bone)
            bone = None
            if len(bones) >= MAX_JOINTS:
                raise ValueError(f"{where}: expected at most {MAX_JOINTS} bones, got more")
            continue
        if key == "name" and vals:
            bone.name = vals[0]
        elif key == "direction" or key == "axis":
            if len(vals) < 3:
                raise ValueError(f"{where}: line {n}: expected 3 numbers after {key}, got {len(vals)}")
            xyz = np.array([_num(v, key, where, n) for v in vals[:3]])
            if key == "direction":
                bone.direction = xyz
            else:
                bone.axis = xyz * angle
                bone.order = _order(vals[3], where, n) if len(vals) > 3 else "XYZ"
        elif key == "length" and vals:
            bone.length = _num(vals[0], "length", where, n)
            if bone.length < 0:
                raise ValueError(f"{where}: line {n}: expected a length >= 0, got {vals[0]!r}")
        elif key == "dof":
            dof = tuple(v.lower() for v in vals)
            if not set(dof) <= _DOFS or len(set(dof)) != len(dof):
                raise ValueError(f"{where}: line {n}: expected dofs among rx ry rz tx ty tz l, got {' '.join(vals)!r}")
            bone.dof = dof
        elif key.startswith("(") and last_key == "limits":
            continue  # limits continue on the following lines
        last_key = key
    if bone is not None:
        raise ValueError(f"{where}: expected 'end' closing bone {bone.name or '?'!r} in :bonedata, got the end of it")
    return bones


def _hierarchy(rows: list[tuple[int, list[str]]], names: set[str], where: str) -> dict[str, list[str]]:
    children: dict[str, list[str]] = {}
    started = ended = False
    for n, toks in rows:
        if toks[0].lower() == "begin":
            started = True
            continue
        if toks[0].lower() == "end":
            ended = True
            continue
        for name in toks:
            if name not in names:
                raise ValueError(f"{where}: line {n}: expected a bone of :bonedata in :hierarchy, got {name!r}")
        children.setdefault(toks[0], []).extend(toks[1:])
    if not (started and ended):
        raise ValueError(f"{where}: expected ':hierarchy' between 'begin' and 'end', got unbalanced blocks")
    return children


def read_asf(path: str | os.PathLike[str]) -> AsfSkeleton:
    """Read an ASF skeleton file.

    Raises:
        ValueError: one line naming the file: a missing section, unbalanced begin/end, a bone
            defined twice or missing from :hierarchy, a cycle, a bad number, unit, order or dof.
    """
    where = str(path)
    lines = _text(path).splitlines()
    sec = _sections(lines, where)
    angle, mpu = _units(sec.get(":units", []), where)
    root = _root(sec[":root"], angle, where)
    bones = _bones(sec[":bonedata"], angle, where)
    by_name = {b.name: b for b in bones}
    if len(by_name) != len(bones) or "root" in by_name:
        raise ValueError(f"{where}: expected unique bone names (and none named 'root'), got a repeated name")
    children = _hierarchy(sec[":hierarchy"], set(by_name) | {"root"}, where)
    order: list[_Bone] = []
    parents: list[int] = []
    stack: list[tuple[str, int]] = [("root", -1)]
    seen: set[str] = set()
    while stack:
        name, parent = stack.pop()
        if name in seen:
            raise ValueError(f"{where}: expected a tree in :hierarchy, got bone {name!r} twice (a cycle?)")
        seen.add(name)
        order.append(root if name == "root" else by_name[name])
        parents.append(parent)
        stack.extend((c, len(order) - 1) for c in reversed(children.get(name, [])))
    missing = sorted(set(by_name) - seen)
    if missing:
        raise ValueError(
            f"{where}: expected every bone under root in :hierarchy, got {len(missing)} unattached ({missing[0]!r})"
        )
    directions = np.array([b.direction for b in order])
    norms = np.linalg.norm(directions[1:], axis=1)
    if np.any((norms < 1e-9) & (np.array([b.length for b in order[1:]]) > 0)):
        raise ValueError(f"{where}: expected a non-zero direction for every bone with a length, got a zero one")
    directions[1:] /= np.maximum(norms, 1e-300)[:, None]
    directions[0] = 0.0
    return AsfSkeleton(
        names=tuple(b.name for b in order),
        parents=np.asarray(parents, dtype=np.int64),
        directions=directions,
        lengths=np.array([0.0] + [b.length for b in order[1:]]),
        axes=_axes(order),
        dofs=tuple(b.dof for b in order),
        orders=tuple(b.order for b in order),
        root_position=root.direction.copy(),
        angle_scale=angle,
        meters_per_unit=mpu,
    )


def _axes(order: list[_Bone]) -> np.ndarray:
    return np.stack([acclaim_rotation(b.axis, b.order) for b in order])


def _text(path: str | os.PathLike[str]) -> str:
    raw = Path(path).read_bytes()
    if b"\0" in raw[:4096]:
        raise ValueError(f"{path}: expected a text file, got binary data")
    if not raw.strip():
        raise ValueError(f"{path}: expected an ASF/AMC text file, got an empty file")
    return raw.decode("utf-8", errors="replace")


def _amc(path: str | os.PathLike[str], asf: AsfSkeleton, asf_angle: float) -> tuple[list[np.ndarray], float, int]:
    """Per bone the (T, len(dof)) AMC values (file units, angles as written), radians per angle unit, T."""
    where = str(path)
    text = _text(path)
    fast = _amc_fast(text, asf, asf_angle)
    if fast is not None:
        return fast
    index = {name: k for k, name in enumerate(asf.names)}
    rows: list[list[list[str]]] = [[] for _ in asf.names]
    frames_of: list[list[int]] = [[] for _ in asf.names]
    angle = asf_angle
    frame, first_number = -1, None
    for n, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        if line.startswith(":"):
            if frame >= 0:
                raise ValueError(f"{where}: line {n}: expected frame data, got the header line {line[:40]!r}")
            angle = _angle_unit(line, angle)
            continue
        toks = line.split()
        if len(toks) == 1 and toks[0].isdigit():
            number = int(toks[0])
            if first_number is None:
                first_number = number
            elif number != first_number + frame + 1:
                raise ValueError(f"{where}: line {n}: expected frame number {first_number + frame + 1}, got {number}")
            frame += 1
            if frame >= MAX_FRAMES:
                raise ValueError(f"{where}: expected at most {MAX_FRAMES} frames, got more")
            continue
        k = index.get(toks[0])
        if k is None:
            raise ValueError(f"{where}: line {n}: expected a bone of the ASF skeleton, got {toks[0][:40]!r}")
        if frame < 0:
            raise ValueError(f"{where}: line {n}: expected a frame number before the first bone line, got {toks[0]!r}")
        if len(toks) - 1 != len(asf.dofs[k]):
            dof = " ".join(asf.dofs[k]) or "none"
            raise ValueError(
                f"{where}: line {n} (frame {frame}): expected {len(asf.dofs[k])} values for {toks[0]} ({dof}), "
                f"got {len(toks) - 1}"
            )
        rows[k].append(toks[1:])
        frames_of[k].append(frame)
    t = frame + 1
    if t <= 0:
        raise ValueError(f"{where}: expected AMC frames (a frame number, then one line per bone), got none")
    values: list[np.ndarray] = []
    for k, name in enumerate(asf.names):
        if not asf.dofs[k]:
            values.append(np.zeros((t, 0)))
            continue
        got = np.asarray(frames_of[k], dtype=np.int64)
        if got.size != t or np.any(got != np.arange(t)):
            counts = np.bincount(got, minlength=t) if got.size else np.zeros(t, dtype=np.int64)
            bad = int(np.flatnonzero(counts != 1)[0])
            raise ValueError(f"{where}: frame {bad}: expected one line for bone {name}, got {int(counts[bad])}")
        try:
            arr = np.array(rows[k], dtype=np.float64)
        except ValueError:
            raise ValueError(f"{where}: expected numbers on the lines of bone {name}, got text") from None
        finite = np.isfinite(arr).all(axis=1)
        if not finite.all():
            idx = np.flatnonzero(~finite)
            shown = ", ".join(map(str, idx[:10])) + (", ..." if idx.size > 10 else "")
            raise ValueError(f"{where}: expected finite values, got NaN/inf for bone {name} in frames {shown}")
        values.append(arr)
    return values, angle, t


def _angle_unit(line: str, angle: float) -> float:
    key = line.split()[0].upper()
    return np.pi / 180.0 if key == ":DEGREES" else 1.0 if key == ":RADIANS" else angle


def _amc_fast(text: str, asf: AsfSkeleton, angle: float) -> tuple[list[np.ndarray], float, int] | None:
    """The AMC values when every frame lists the same bones in the same order, read in one numpy pass.

    Returns None for anything else (comments in the frames, a varying layout, a bad token): the
    line-by-line reader then reads the file and names the line at fault.
    """
    body = text
    while True:  # header lines (":FULLY-SPECIFIED", ":DEGREES", comments) up to the first frame number
        end = body.find("\n")
        line = (body if end < 0 else body[:end]).strip()
        if line.startswith(":") or line.startswith("#") or not line:
            if line.startswith(":"):
                angle = _angle_unit(line, angle)
            if end < 0:
                return None
            body = body[end + 1 :]
            continue
        break
    if "#" in body or ":" in body:
        return None
    tokens = body.split()
    if not tokens or not tokens[0].isdigit():
        return None
    index = {name: k for k, name in enumerate(asf.names)}
    layout: list[tuple[int, int]] = []  # (bone, column of its first value)
    width = 1
    while width < len(tokens) and tokens[width] in index:
        k = index[tokens[width]]
        layout.append((k, width + 1))
        width += 1 + len(asf.dofs[k])
    bones = [k for k, _ in layout]
    if len(set(bones)) != len(bones) or set(bones) != {k for k, d in enumerate(asf.dofs) if d}:
        return None
    if len(tokens) % width or len(tokens) // width > MAX_FRAMES:
        return None
    grid = np.array(tokens).reshape(-1, width)
    t = grid.shape[0]
    names = np.array([asf.names[k] for k in bones])
    if not np.array_equal(grid[:, [c - 1 for _, c in layout]], np.broadcast_to(names, (t, len(bones)))):
        return None
    try:
        numbers = grid[:, 0].astype(np.int64)
    except ValueError:
        return None
    if not np.array_equal(numbers, numbers[0] + np.arange(t)):
        return None
    values: list[np.ndarray] = [np.zeros((t, 0)) for _ in asf.names]
    try:
        for k, c in layout:
            values[k] = grid[:, c : c + len(asf.dofs[k])].astype(np.float64)
    except ValueError:
        return None
    if not all(np.isfinite(v).all() for v in values):
        return None
    return values, angle, t


def read_asf_amc(
    asf_path: str | os.PathLike[str], amc_path: str | os.PathLike[str], fps: float = 120.0
) -> SkeletalMotion:
    """Read an ASF skeleton and an AMC motion of it into a :class:`SkeletalMotion` (see the module notes).

    Args:
        asf_path: the skeleton (``.asf``).
        amc_path: the motion (``.amc``).
        fps: frames per second (AMC files do not state it; CMU's are 120).

    Raises:
        ValueError: one line naming the file: see :func:`read_asf`; in the AMC, a bone the ASF
            lacks, a line with the wrong number of values (its line), a bone missing from a
            frame, a frame number out of sequence, NaN/inf values (their frames), or a bad fps.
    """
    if isinstance(fps, bool) or not isinstance(fps, int | float | np.integer | np.floating) or not 0 < fps <= 1e5:
        raise ValueError(f"fps: expected a positive number of frames per second (at most 100000), got {fps!r}")
    asf = read_asf(asf_path)
    values, angle, t = _amc(amc_path, asf, asf.angle_scale)
    nb = len(asf.names)
    leaves = [k for k in range(1, nb) if k not in set(asf.parents.tolist())]
    parents = np.concatenate([asf.parents, np.asarray(leaves, dtype=np.int64)])
    names = asf.names + tuple(f"{asf.names[k]}_End" for k in leaves)
    bone_vec = asf.lengths[:, None] * asf.directions  # (B, 3), root zero
    offsets = np.concatenate([np.zeros((nb, 3)), bone_vec[leaves]])
    offsets[1:nb] = bone_vec[asf.parents[1:nb]]
    offsets[0] = asf.root_position
    j = len(names)
    rotations = np.broadcast_to(np.eye(3), (t, j, 3, 3)).copy()
    translations = np.broadcast_to(offsets, (t, j, 3)).copy()
    children = [np.flatnonzero(parents == k) for k in range(nb)]
    for k in range(nb):
        dof, vals = asf.dofs[k], values[k]
        if not dof:
            continue
        rot = np.zeros((t, 3))
        shift = np.zeros((t, 3))
        for c, d in enumerate(dof):
            if d in _ROT_DOFS:
                rot[:, _ROT_DOFS.index(d)] = vals[:, c] * angle
            elif d == "l":
                translations[:, children[k]] += vals[:, c, None, None] * asf.directions[k]
            else:
                shift[:, "xyz".index(d[1])] = vals[:, c]
        if any(d in _ROT_DOFS for d in dof):
            order = asf.orders[k]
            m = acclaim_rotation(rot[:, ["XYZ".index(a) for a in order]], order)
            C = asf.axes[k]
            rotations[:, k] = C @ m @ C.T
        if k == 0:  # the root's translation channels are its world position
            for c, d in enumerate(dof):
                if d in ("tx", "ty", "tz"):
                    translations[:, 0, "xyz".index(d[1])] = vals[:, c]
        elif any(d in ("tx", "ty", "tz") for d in dof):
            translations[:, k] += shift @ asf.axes[k].T
    return SkeletalMotion(
        names=names,
        parents=parents,
        offsets=offsets,
        rotations=rotations,
        translations=translations,
        fps=float(fps),
        meters_per_unit=asf.meters_per_unit,
        source="asf/amc",
    )
