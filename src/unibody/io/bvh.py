"""BVH motion files (Biovision hierarchy): read any skeleton, write one (numpy only).

Format facts this module relies on:

- ``HIERARCHY`` then one ``ROOT name { OFFSET x y z  CHANNELS n ...  JOINT ... { } End Site { OFFSET } }``
  tree, then ``MOTION``, ``Frames: T``, ``Frame Time: dt`` and T lines of numbers, one value per
  channel in the order the hierarchy lists them (depth first).
- A joint's channels may be any of ``Xposition Yposition Zposition Xrotation Yrotation Zrotation``
  in any order; rotations are degrees, and channels listed ``Zrotation Xrotation Yrotation``
  mean the local rotation ``R = Rz @ Rx @ Ry`` (column vectors: the last listed acts first).
- Position channels replace the matching component of the joint's OFFSET (the root's are its
  world position); a joint without them is translated by its OFFSET.
- BVH states no length unit: :attr:`SkeletalMotion.meters_per_unit` is None.

End Sites become joints named ``<parent>_End`` (``<parent>_End2``, ... when a joint has several)
with identity rotations. The numeric block is parsed by numpy in one go; every value is checked
finite, and bad input raises ``ValueError`` with one line naming the file.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .atomic import atomic_write
from .skeletal import SkeletalMotion

__all__ = ["MAX_CHANNELS", "MAX_FRAMES", "MAX_JOINTS", "euler_to_matrix", "matrix_to_euler", "read_bvh", "write_bvh"]

MAX_JOINTS = 10_000
"""The most joints (End Sites included) a BVH may declare."""
MAX_CHANNELS = 60_000
"""The most channels per frame."""
MAX_FRAMES = 10_000_000
"""The most frames a BVH may declare."""

_AXES = {"X": 0, "Y": 1, "Z": 2}
_CHANNELS = {f"{a}{kind}" for a in "XYZ" for kind in ("position", "rotation")}


def _axis_matrices(axis: int, angles: np.ndarray) -> np.ndarray:
    """Rotations by ``angles`` (radians, any shape S) about coordinate ``axis``: (*S, 3, 3)."""
    c, s = np.cos(angles), np.sin(angles)
    out = np.zeros((*angles.shape, 3, 3))
    i, j = (axis + 1) % 3, (axis + 2) % 3
    out[..., axis, axis] = 1.0
    out[..., i, i] = c
    out[..., j, j] = c
    out[..., j, i] = s
    out[..., i, j] = -s
    return out


def euler_to_matrix(angles: np.ndarray, order: str) -> np.ndarray:
    """Intrinsic Euler angles (radians, ``(..., n)``) to rotations ``(..., 3, 3)``.

    ``order`` lists the axes as a BVH channel list does (e.g. ``"ZXY"``): ``R = Rz @ Rx @ Ry``.
    """
    angles = np.asarray(angles, dtype=np.float64)
    out = np.broadcast_to(np.eye(3), (*angles.shape[:-1], 3, 3)).copy()
    for k, a in enumerate(order):
        out = out @ _axis_matrices(_AXES[a], angles[..., k])
    return out


def matrix_to_euler(R: np.ndarray, order: str) -> np.ndarray:
    """Rotations ``(..., 3, 3)`` to Euler angles (radians, ``(..., 3)``) with ``euler_to_matrix(a, order) == R``.

    ``order`` is a permutation of ``"XYZ"``. At gimbal lock (middle angle ±90°) the first angle
    takes the whole remaining rotation and the last is zero, so the result still reproduces R.
    """
    R = np.asarray(R, dtype=np.float64)
    i, j, k = (_AXES[a] for a in order)
    # sign of the permutation (i, j, k): +1 for cyclic XYZ, YZX, ZXY
    sgn = 1.0 if (j - i) % 3 == 1 else -1.0
    # R = R_i(a) R_j(b) R_k(c): R[i, k] = sgn * sin(b)
    sb = np.clip(sgn * R[..., i, k], -1.0, 1.0)
    cb = np.hypot(R[..., i, i], R[..., i, j])
    b = np.arctan2(sb, cb)
    a = np.arctan2(-sgn * R[..., j, k], R[..., k, k])
    c = np.arctan2(-sgn * R[..., i, j], R[..., i, i])
    lock = cb < 1e-9
    if np.any(lock):
        # cos(b) = 0: only a ± c is defined; set c = 0 and read a from the rows of R that stay non-zero
        a_l = np.arctan2(sgn * R[..., k, j], R[..., j, j])
        a = np.where(lock, a_l, a)
        c = np.where(lock, 0.0, c)
    return np.stack([a, b, c], axis=-1)


def number_token(tok: str, what: str, where: str, line: int) -> float:
    """A finite float from one token of a text file; ValueError naming the file, line and field."""
    try:
        value = float(tok)
    except ValueError:
        raise ValueError(f"{where}: line {line}: expected a number for {what}, got {tok!r}") from None
    if not np.isfinite(value):
        raise ValueError(f"{where}: line {line}: expected a finite number for {what}, got {tok!r}")
    return value


class _Tokens:
    """Whitespace tokens of the hierarchy with their line numbers."""

    def __init__(self, lines: list[str], where: str):
        self.toks: list[tuple[str, int]] = [(t, n + 1) for n, line in enumerate(lines) for t in line.split()]
        self.i = 0
        self.where = where

    def next(self, what: str) -> tuple[str, int]:
        if self.i >= len(self.toks):
            raise ValueError(f"{self.where}: expected {what} in the HIERARCHY, got the end of it (unbalanced braces?)")
        tok = self.toks[self.i]
        self.i += 1
        return tok

    def expect(self, word: str) -> int:
        tok, line = self.next(repr(word))
        if tok != word:
            raise ValueError(f"{self.where}: line {line}: expected {word!r}, got {tok!r} (unbalanced braces?)")
        return line

    def name(self, what: str) -> str:
        """A joint name: the rest of its line (names may hold spaces), up to a '{' there."""
        tok, line = self.next(what)
        parts = [tok]
        while self.i < len(self.toks) and self.toks[self.i][1] == line and self.toks[self.i][0] != "{":
            parts.append(self.toks[self.i][0])
            self.i += 1
        if tok == "{":
            raise ValueError(f"{self.where}: line {line}: expected {what}, got '{{'")
        return " ".join(parts)

    def number(self, what: str) -> float:
        tok, line = self.next(what)
        return number_token(tok, what, self.where, line)


def _parse_hierarchy(lines: list[str], where: str) -> tuple[list[str], list[int], list, list[list[str]]]:
    """Names, parents, offsets and channel lists of the joints, depth first."""
    tk = _Tokens(lines, where)
    tok, line = tk.next("'HIERARCHY'")
    if tok != "HIERARCHY":
        raise ValueError(f"{where}: expected a BVH file starting with 'HIERARCHY', got {tok!r} on line {line}")
    tok, line = tk.next("'ROOT'")
    if tok != "ROOT":
        raise ValueError(f"{where}: line {line}: expected 'ROOT', got {tok!r}")
    names: list[str] = []
    parents: list[int] = []
    offsets: list[tuple[float, float, float]] = []
    channels: list[list[str]] = []
    total = 0
    # stack of (joint index, is_end_site); a joint is opened by its name then '{'
    stack: list[int] = []
    pending: tuple[str, bool] | None = (tk.name("the root's name"), False)
    while True:
        if pending is not None:
            name, end = pending
            pending = None
            tk.expect("{")
            parent = stack[-1] if stack else -1
            if end:
                base = f"{names[parent]}_End"
                name, n = base, 2
                while name in names:
                    name, n = f"{base}{n}", n + 1
            if len(names) >= MAX_JOINTS:
                raise ValueError(f"{where}: expected at most {MAX_JOINTS} joints, got more")
            tk.expect("OFFSET")
            off = (tk.number("OFFSET x"), tk.number("OFFSET y"), tk.number("OFFSET z"))
            chans: list[str] = []
            if not end and tk.i < len(tk.toks) and tk.toks[tk.i][0] == "CHANNELS":
                tk.i += 1
                count_tok, count_line = tk.next("the channel count")
                if not count_tok.isdigit() or int(count_tok) > 64:
                    raise ValueError(f"{where}: line {count_line}: expected a channel count (0..64), got {count_tok!r}")
                for _ in range(int(count_tok)):
                    ch, ch_line = tk.next("a channel name")
                    if ch not in _CHANNELS:
                        raise ValueError(
                            f"{where}: line {ch_line}: expected a channel of {' '.join(sorted(_CHANNELS))}, got {ch!r}"
                        )
                    chans.append(ch)
                total += len(chans)
                if total > MAX_CHANNELS:
                    raise ValueError(f"{where}: expected at most {MAX_CHANNELS} channels per frame, got more")
            names.append(name)
            parents.append(parent)
            offsets.append(off)
            channels.append(chans)
            stack.append(len(names) - 1)
            if end:
                tk.expect("}")
                stack.pop()
        if not stack:
            if tk.i < len(tk.toks):
                tok, line = tk.toks[tk.i]
                raise ValueError(f"{where}: line {line}: expected MOTION after the root's closing brace, got {tok!r}")
            return names, parents, offsets, channels
        tok, line = tk.next("'JOINT', 'End Site' or '}'")
        if tok == "}":
            stack.pop()
        elif tok == "JOINT":
            pending = (tk.name("a joint name"), False)
        elif tok == "End":
            tk.expect("Site")
            pending = ("", True)
        else:
            raise ValueError(f"{where}: line {line}: expected 'JOINT', 'End Site' or '}}', got {tok!r}")


def _motion_header(lines: list[str], start: int, where: str) -> tuple[int, float, int]:
    """``Frames:`` and ``Frame Time:`` after the MOTION line: (frames, frame time, first data line index)."""
    values: dict[str, str] = {}
    n = start
    for key in ("Frames:", "Frame Time:"):
        while n < len(lines) and not lines[n].strip():
            n += 1
        text = lines[n].strip() if n < len(lines) else ""
        if not text.startswith(key):
            raise ValueError(f"{where}: line {n + 1}: expected {key!r} after MOTION, got {text[:40]!r}")
        values[key] = text[len(key) :].strip()
        n += 1
    try:
        frames = int(values["Frames:"])
    except ValueError:
        raise ValueError(f"{where}: expected an integer after 'Frames:', got {values['Frames:']!r}") from None
    if not 0 < frames <= MAX_FRAMES:
        raise ValueError(f"{where}: expected 1..{MAX_FRAMES} frames, got Frames: {frames}")
    try:
        dt = float(values["Frame Time:"])
    except ValueError:
        raise ValueError(f"{where}: expected a number after 'Frame Time:', got {values['Frame Time:']!r}") from None
    if not (np.isfinite(dt) and 1e-5 <= dt <= 1e3):
        raise ValueError(f"{where}: expected a Frame Time between 1e-05 and 1000 s, got {dt!r}")
    return frames, dt, n


def _frame_rate(dt: float) -> float:
    """1 / frame time, snapped to a whole rate when the file rounded it (0.008333 s -> 120 fps)."""
    fps = 1.0 / dt
    whole = round(fps)
    return float(whole) if whole > 0 and abs(fps - whole) <= 1e-4 * fps else fps


def _parse_frames(lines: list[str], first: int, frames: int, width: int, where: str) -> np.ndarray:
    """The (frames, width) numeric block starting at line index ``first``."""
    rows = [(n, line) for n, line in enumerate(lines[first:], start=first + 1) if line.strip()]
    if len(rows) < frames:
        raise ValueError(f"{where}: expected {frames} frames (Frames:), got {len(rows)}")
    rows = rows[:frames]  # text after the declared frames is ignored, as BVH readers do
    text = [line.split() for _, line in rows]
    counts = np.fromiter(map(len, text), dtype=np.int64, count=frames)
    bad = np.flatnonzero(counts != width)
    if bad.size:
        n, k = rows[int(bad[0])][0], int(bad[0])
        raise ValueError(f"{where}: line {n} (frame {k}): expected {width} values, got {int(counts[k])}")
    try:
        data = np.array(text, dtype=np.float64).reshape(frames, width)
    except ValueError:
        for k, tokens in enumerate(text):  # the error path only: find the line with the bad token
            for tok in tokens:
                try:
                    float(tok)
                except ValueError:
                    raise ValueError(f"{where}: line {rows[k][0]} (frame {k}): expected numbers, got {tok!r}") from None
        raise
    finite = np.isfinite(data).all(axis=1)
    if not finite.all():
        idx = np.flatnonzero(~finite)
        shown = ", ".join(map(str, idx[:10])) + (", ..." if idx.size > 10 else "")
        raise ValueError(f"{where}: expected finite values, got NaN/inf in {idx.size} frames (indices {shown})")
    return data


def read_bvh(path: str | os.PathLike[str]) -> SkeletalMotion:
    """Read a BVH file into a :class:`SkeletalMotion` (file units, ``meters_per_unit`` None).

    Raises:
        ValueError: one line naming the file: not a BVH (no HIERARCHY or MOTION), unbalanced
            braces, an unknown channel, a frame line with the wrong number of values (its line),
            fewer frames than ``Frames:`` declares, NaN/inf values (their frame indices), sizes
            beyond :data:`MAX_JOINTS`, :data:`MAX_CHANNELS` or :data:`MAX_FRAMES`.
        OSError: the file cannot be read.
    """
    where = str(path)
    raw = Path(path).read_bytes()
    if b"\0" in raw[:4096]:
        raise ValueError(f"{where}: expected a BVH text file, got binary data")
    lines = raw.decode("utf-8", errors="replace").splitlines()
    motion_at = next((n for n, line in enumerate(lines) if line.strip() == "MOTION"), None)
    if not any(line.strip() for line in lines):
        raise ValueError(f"{where}: expected a BVH file, got an empty file")
    if motion_at is None:
        if not any(line.strip().startswith("HIERARCHY") for line in lines[:50]):
            raise ValueError(f"{where}: expected a BVH file (HIERARCHY ... MOTION), got neither")
        raise ValueError(f"{where}: expected a MOTION section after the HIERARCHY, got none")
    names, parents, offsets, channels = _parse_hierarchy(lines[:motion_at], where)
    frames, dt, first = _motion_header(lines, motion_at + 1, where)
    width = sum(map(len, channels))
    data = _parse_frames(lines, first, frames, width, where)

    num = len(names)
    off = np.asarray(offsets, dtype=np.float64).reshape(num, 3)
    rotations = np.broadcast_to(np.eye(3), (frames, num, 3, 3)).copy()
    translations = np.broadcast_to(off, (frames, num, 3)).copy()
    col = 0
    for j, chans in enumerate(channels):
        rot_cols = [col + c for c, ch in enumerate(chans) if ch.endswith("rotation")]
        order = "".join(ch[0] for ch in chans if ch.endswith("rotation"))
        for c, ch in enumerate(chans):
            if ch.endswith("position"):
                translations[:, j, _AXES[ch[0]]] = data[:, col + c]
        if rot_cols:
            rotations[:, j] = euler_to_matrix(np.radians(data[:, rot_cols]), order)
        col += len(chans)
    return SkeletalMotion(
        names=tuple(names),
        parents=np.asarray(parents, dtype=np.int64),
        offsets=off,
        rotations=rotations,
        translations=translations,
        fps=_frame_rate(dt),
        meters_per_unit=None,
        source="bvh",
    )


def _check_array(x: object, shape: tuple[int | None, ...], name: str) -> np.ndarray:
    """A finite float64 array of ``shape`` (None: any size); one-line ValueError otherwise."""
    arr = np.asarray(x)
    if arr.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, arr.shape, strict=True)):
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name}: expected shape {want}, got {arr.shape}")
    if arr.dtype.kind not in "biuf":
        raise ValueError(f"{name}: expected numbers, got dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    if not np.isfinite(arr).all():
        raise ValueError(f"{name}: expected finite values, got {int(np.size(arr) - np.isfinite(arr).sum())} NaN/inf")
    return arr


def _check_skeleton(names: object, parents: object) -> tuple[list[str], np.ndarray]:
    names = [str(n) for n in names]  # type: ignore[union-attr]
    if not names or len(names) > MAX_JOINTS:
        raise ValueError(f"names: expected 1..{MAX_JOINTS} joint names, got {len(names)}")
    bad = [n for n in names if not n or any(c.isspace() for c in n) or n in "{}"]
    if bad:
        raise ValueError(f"names: expected names without spaces, got {bad[0]!r}")
    if len(set(names)) != len(names):
        raise ValueError(f"names: expected unique names, got {len(names) - len(set(names))} repeated")
    par = np.asarray(parents)
    if par.shape != (len(names),) or par.dtype.kind not in "iu":
        raise ValueError(f"parents: expected ({len(names)},) integers, got shape {par.shape} dtype {par.dtype}")
    par = par.astype(np.int64)
    if par[0] != -1 or np.any(par[1:] < 0) or np.any(par[1:] >= np.arange(1, len(names))):
        raise ValueError(f"parents: expected -1 for the root (index 0) and parents before children, got {par.tolist()}")
    return names, par


def write_bvh(
    path: str | os.PathLike[str],
    names: tuple[str, ...] | list[str],
    parents: np.ndarray,
    offsets: np.ndarray,
    rotations: np.ndarray,
    root_positions: np.ndarray,
    fps: float,
    *,
    order: str = "ZYX",
    end_sites: dict[str, np.ndarray] | None = None,
) -> None:
    """Write a skeleton and its motion as a BVH file, atomically, exactly at ``path``.

    Args:
        path: the output file.
        names: J joint names (no spaces), the root first.
        parents: (J,) parent indices, -1 for the root, parents before children.
        offsets: (J, 3) rest offsets in the parent's frame (any length unit; written as given).
        rotations: (T, J, 3, 3) local rotations (identity at rest), as in :class:`SkeletalMotion`.
        root_positions: (T, 3) the root's position per frame (replaces its offset).
        fps: frames per second (``Frame Time: 1/fps``).
        order: rotation channel order, a permutation of ``"XYZ"``; ``"ZXY"`` writes
            ``Zrotation Xrotation Yrotation`` (R = Rz @ Rx @ Ry).
        end_sites: offsets of End Sites by joint name; a leaf joint not named here gets a zero
            End Site (what BVH readers expect at the end of every chain).

    The root has 6 channels (``Xposition Yposition Zposition`` then its rotations), every other
    joint 3 rotation channels; animated translations of non-root joints are not written. Angles
    are written with 1e-6 degree resolution and lengths with 9 significant digits; each Euler
    channel is unwrapped over frames (no 360° jumps).

    Raises:
        ValueError: a one-line message naming the argument with the wrong shape, a NaN/inf, or a
            bad name, parent list, order or fps.
    """
    names, par = _check_skeleton(names, parents)
    j = len(names)
    if not (isinstance(order, str) and sorted(order) == ["X", "Y", "Z"]):
        raise ValueError(f"order: expected a permutation of 'XYZ' such as 'ZXY', got {order!r}")
    off = _check_array(offsets, (j, 3), "offsets")
    rot = _check_array(rotations, (None, j, 3, 3), "rotations")
    t = rot.shape[0]
    if not 0 < t <= MAX_FRAMES:
        raise ValueError(f"rotations: expected 1..{MAX_FRAMES} frames, got {t}")
    err = np.abs(np.swapaxes(rot, -1, -2) @ rot - np.eye(3)).max(axis=(-2, -1)) + (np.linalg.det(rot) <= 0)
    if err.max() > 1e-4:
        f, k = np.unravel_index(int(np.argmax(err)), err.shape)
        raise ValueError(f"rotations: expected rotation matrices, got a non-rotation at frame {f}, joint {names[k]!r}")
    root = _check_array(root_positions, (t, 3), "root_positions")
    if isinstance(fps, bool) or not isinstance(fps, int | float | np.floating | np.integer) or not 0 < fps <= 1e5:
        raise ValueError(f"fps: expected a positive number (at most 100000), got {fps!r}")
    ends = {str(k): _check_array(v, (3,), f"end_sites[{k!r}]") for k, v in (end_sites or {}).items()}
    unknown = sorted(set(ends) - set(names))
    if unknown:
        raise ValueError(f"end_sites: expected joint names, got {unknown[0]!r}")

    angles = np.degrees(np.unwrap(matrix_to_euler(rot, order), axis=0))  # (T, J, 3)
    data = np.concatenate([root, angles.reshape(t, 3 * j)], axis=1)
    children: list[list[int]] = [[] for _ in range(j)]
    for k in range(1, j):
        children[par[k]].append(k)
    rot_channels = " ".join(f"{a}rotation" for a in order)
    out: list[str] = ["HIERARCHY"]
    order_written = _depth_first(children)
    depth = np.zeros(j, dtype=np.int64)
    for k in range(1, j):
        depth[k] = depth[par[k]] + 1
    for n, k in enumerate(order_written):  # open each joint; close those whose subtree ends here
        pad = "\t" * int(depth[k])
        pos = "Xposition Yposition Zposition " if k == 0 else ""
        out += [f"{pad}{'ROOT' if k == 0 else 'JOINT'} {names[k]}", f"{pad}{{"]
        out.append(f"{pad}\tOFFSET {off[k, 0]:.9g} {off[k, 1]:.9g} {off[k, 2]:.9g}")
        out.append(f"{pad}\tCHANNELS {6 if k == 0 else 3} {pos}{rot_channels}")
        if not children[k]:
            _close(out, k, names, par, depth, ends, order_written[n + 1] if n + 1 < j else None)
    cols = np.concatenate([np.arange(3), 3 + (3 * np.asarray(order_written)[:, None] + np.arange(3)).ravel()])
    data = data[:, cols]
    out += ["MOTION", f"Frames: {t}", f"Frame Time: {1.0 / float(fps):.10g}"]
    fmt = " ".join(["%.9g"] * 3 + ["%.6f"] * (3 * j))
    with atomic_write(path, "w") as f:
        f.write("\n".join(out) + "\n")
        f.writelines(fmt % tuple(row) + "\n" for row in data)


def _close(
    out: list[str], k: int, names: list[str], par: np.ndarray, depth: np.ndarray, ends: dict, following: int | None
) -> None:
    """After leaf ``k``: close it and every ancestor whose subtree ends here, End Sites first.

    ``following`` is the next joint written (None at the end); the ancestors below its parent close.
    A leaf always gets an End Site (zero unless ``ends`` names it), any other joint only if named.
    """
    stop = -1 if following is None else int(par[following])
    leaf = True
    while k != stop:
        pad = "\t" * int(depth[k])
        if leaf or names[k] in ends:
            e = ends.get(names[k], np.zeros(3))
            out += [f"{pad}\tEnd Site", f"{pad}\t{{", f"{pad}\t\tOFFSET {e[0]:.9g} {e[1]:.9g} {e[2]:.9g}", f"{pad}\t}}"]
        out.append(f"{pad}}}")
        k, leaf = int(par[k]), False


def _depth_first(children: list[list[int]]) -> list[int]:
    """Joint indices in the depth-first order a BVH lists them (the channel order of each frame)."""
    seen: list[int] = []
    stack = [0]
    while stack:
        k = stack.pop()
        seen.append(k)
        stack.extend(reversed(children[k]))
    return seen
