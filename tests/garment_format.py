"""Write seeded GarmentMeasurements PCA assets in the real formats, for tests.

* ``point.pca``: the upstream binary of github.com/mbotsch/GarmentMeasurements
  (``PCA::save``): uint32 m, uint32 n, the (m, n) matrix as float64 column-major, the mean
  (m float64), the eigenvalues (n float64), little-endian;
* ``point.npz``: the py-soma-x conversion (``pca_matrix (3V, K)``, ``pca_mean (3V,)``,
  ``eigenvalues (K,)``);
* ``mean.obj``: the mesh as PMP writes it (``v``, ``vt``, ``vn`` lines, ``f v/vt/vn`` triangles).

Values are synthetic: a tube 1.7 m tall standing on y = 0 (metres, Y up), orthonormal random
components and decreasing eigenvalues. ``python tests/garment_format.py OUT_DIR [--full]``
writes a set (``--full``: 23,712 vertices, 15 components).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def make_garment_arrays(
    *, rings: int = 6, per_ring: int = 5, num_components: int = 15, seed: int = 0
) -> dict[str, np.ndarray]:
    """``matrix (3V, K)`` orthonormal columns, ``mean (3V,)``, ``eigenvalues (K,)``, ``faces (F, 3)``."""
    rng = np.random.default_rng(seed)
    y = np.repeat(np.linspace(0.0, 1.7, rings), per_ring)
    a = np.tile(np.linspace(0.0, 2 * np.pi, per_ring, endpoint=False), rings)
    radius = 0.15 + 0.05 * np.sin(3.0 * y)
    mean = np.stack([radius * np.cos(a), y, 0.8 * radius * np.sin(a)], axis=1)
    mean += rng.normal(scale=0.002, size=mean.shape)
    m = mean.size
    q, _ = np.linalg.qr(rng.normal(size=(m, num_components)))
    eig = 0.02 * 0.5 ** np.arange(num_components)
    faces = []
    for r in range(rings - 1):
        for s in range(per_ring):
            i, j = r * per_ring + s, r * per_ring + (s + 1) % per_ring
            faces += [[i, j, j + per_ring], [i, j + per_ring, i + per_ring]]
    return {"matrix": q, "mean": mean.reshape(-1), "eigenvalues": eig, "faces": np.asarray(faces, dtype=np.int64)}


def write_point_pca(path: str | Path, matrix: np.ndarray, mean: np.ndarray, eigenvalues: np.ndarray) -> None:
    """The upstream ``PCA::save`` layout."""
    m, n = matrix.shape
    with open(path, "wb") as f:
        f.write(np.array([m, n], dtype="<u4").tobytes())
        f.write(np.asarray(matrix, dtype="<f8").tobytes(order="F"))  # Eigen: column-major
        f.write(np.asarray(mean, dtype="<f8").tobytes())
        f.write(np.asarray(eigenvalues, dtype="<f8").tobytes())


def write_point_npz(path: str | Path, matrix: np.ndarray, mean: np.ndarray, eigenvalues: np.ndarray) -> None:
    """The py-soma-x conversion of ``point.pca``."""
    np.savez(path, pca_matrix=matrix, pca_mean=mean, eigenvalues=eigenvalues)


def write_pmp_obj(path: str | Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """An OBJ as PMP writes it: positions, texcoords, normals, ``f v/vt/vn`` (1-based)."""
    lines = ["# OBJ export from PMP"]
    lines += [f"v {x:.10f} {y:.10f} {z:.10f}" for x, y, z in vertices]
    lines += [f"vt {x:.6f} {y / 1.7:.6f}" for x, y, _ in vertices]
    normals = vertices * np.array([1.0, 0.0, 1.0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    lines += [f"vn {x:.6f} {y:.6f} {z:.6f}" for x, y, z in normals]
    lines += ["f " + " ".join(f"{i + 1}/{i + 1}/{i + 1}" for i in tri) for tri in faces]
    Path(path).write_text("\n".join(lines) + "\n")


def write_garment_assets(
    folder: str | Path, arrays: dict[str, np.ndarray] | None = None, *, npz: bool = False, **sizes: int
) -> dict[str, np.ndarray]:
    """Write ``point.pca`` (or ``point.npz`` when ``npz``) and ``mean.obj`` into ``folder``."""
    arrays = make_garment_arrays(**sizes) if arrays is None else arrays
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    pca = (arrays["matrix"], arrays["mean"], arrays["eigenvalues"])
    if npz:
        write_point_npz(folder / "point.npz", *pca)
    else:
        write_point_pca(folder / "point.pca", *pca)
    write_pmp_obj(folder / "mean.obj", arrays["mean"].reshape(-1, 3), arrays["faces"])
    return arrays


FULL_SIZES = {"rings": 152, "per_ring": 156, "num_components": 15}

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--full", action="store_true", help="23,712 vertices, 15 components")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    write_garment_assets(args.out, seed=args.seed, **(FULL_SIZES if args.full else {}))
    print(f"wrote {args.out / 'point.pca'} and {args.out / 'mean.obj'}")
