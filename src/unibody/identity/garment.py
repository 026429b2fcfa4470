"""GarmentMeasurements identity backend: K PCA shape coefficients -> rest mesh (native topology).

GarmentMeasurements is the body-shape model of GarmentCodeData (Korosteleva et al.): a
linear PCA over registered body scans, K components (15 in paper 000, §3.2), on a
~23.7k-vertex mesh in metres, Y up, facing +Z (unibody's frame: no conversion needed).
A parameter vector ``c`` gives ``mean + sum_k (c_k sigma_k) u_k`` with ``sigma_k`` the
standard deviation of component k, so ``c`` is in standard deviations (typical range
-3..3, the range of the upstream shape sliders). Parameters are named ``pc_00, pc_01, ...``.

Assets, one folder holding the mesh ``mean.obj`` (for the triangles) and the PCA as either
    * ``point.pca``, the upstream binary (github.com/mbotsch/GarmentMeasurements,
      ``data/pca/``), or
    * ``point.npz``, the same arrays converted by py-soma-x's ``convert_gm_pca_to_npz.py``
      (``pca_matrix (3V, K)``, ``pca_mean (3V,)``, ``eigenvalues (K,)``).
``point.pca`` is preferred when both are present.

Facts relied on (no code copied):
    * mbotsch/GarmentMeasurements ``src/character/PCA.cpp``, ``PCA::load``: uint32 ``m``,
      uint32 ``n``, then the (m, n) PCA matrix as m*n float64 in Eigen's default
      column-major order (column k = component k), the mean (m float64) and the
      eigenvalues (n float64), native byte order (little-endian on the x86/ARM machines the
      file comes from). ``PCA::evaluate(p) = matrix @ p + mean``; ``PCA::scale_parameters``
      multiplies p_k by sqrt(eigenvalue_k) if eigenvalue_k > 1e-13, else by |eigenvalue_k|.
    * same repository, ``src/apps/generate_shapes/Viewer.cpp``: ``evaluate_shape`` uses
      ``evaluate(scale_parameters(params))`` and reads vertex i as entries 3i..3i+2 (x, y, z
      interleaved); shape sliders span -3..3; ``data/pca/mean.obj`` ("OBJ export from
      PMP", triangles ``f v/vt/vn``) is metres, Y up, the face towards +Z.
    * NVlabs/SOMA-X ``soma/body/identity_model.py``, ``GarmentMeasurementIdentityModel``:
      reads ``GarmentMeasurements/point.npz`` keys ``pca_matrix`` (3V, K), ``pca_mean`` and
      ``eigenvalues``, faces from ``mean.obj``, rest = mean + (c * sqrt(eig)) @ matrix.T
      reshaped (V, 3); native unit metres, up +Y, forward +Z.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from .._checks import check_finite, check_like, check_shape
from ..geometry.tetra import quads_to_triangles
from ..io.npz import check_npz_members
from ..io.obj import read_obj

__all__ = ["GarmentIdentity", "GarmentPCA", "load_garment_pca", "read_point_pca", "read_point_npz"]

_HEADER = np.dtype([("m", "<u4"), ("n", "<u4")])
_TINY_EIGENVALUE = 1e-13  # upstream PCA::scale_parameters threshold


@dataclass(frozen=True, eq=False)
class GarmentPCA:
    """A GarmentMeasurements PCA model, float64 numpy, metres, unibody axes.

    Attributes:
        mean: (V, 3) m, the mean body.
        components: (K, V, 3) unit-norm principal directions (m per unit coefficient).
        eigenvalues: (K,) variances (m^2).
        faces: (F, 3) int64 triangles.
    """

    mean: np.ndarray
    components: np.ndarray
    eigenvalues: np.ndarray
    faces: np.ndarray


def read_point_pca(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read the upstream binary ``point.pca``.

    Returns:
        ``(matrix (m, n), mean (m,), eigenvalues (n,))`` float64.

    Raises:
        FileNotFoundError: the file is missing. ValueError: its size does not match its header.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"GarmentMeasurements PCA {path} is missing")
    raw = path.read_bytes()
    if len(raw) < _HEADER.itemsize:
        raise ValueError(f"GarmentMeasurements PCA {path}: {len(raw)} bytes, too short for the (m, n) header")
    head = np.frombuffer(raw, dtype=_HEADER, count=1)[0]
    m, n = int(head["m"]), int(head["n"])
    expected = _HEADER.itemsize + 8 * (m * n + m + n)
    if m == 0 or n == 0 or len(raw) != expected:
        raise ValueError(
            f"GarmentMeasurements PCA {path}: header says m={m}, n={n} (expected {expected} bytes: "
            f"uint32 m, uint32 n, float64 matrix, mean, eigenvalues), file has {len(raw)} bytes"
        )
    body = np.frombuffer(raw, dtype="<f8", offset=_HEADER.itemsize).astype(np.float64)
    matrix = body[: m * n].reshape(n, m).T  # Eigen stores column-major: column k is component k
    return matrix, body[m * n : m * n + m], body[m * n + m :]


def read_point_npz(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read py-soma-x's ``point.npz`` (``pca_matrix``, ``pca_mean``, ``eigenvalues``); same returns."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"GarmentMeasurements PCA {path} is missing")
    try:
        check_npz_members(path)
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise ValueError(f"GarmentMeasurements PCA {path}: not a readable .npz file ({exc})") from exc
    if not isinstance(data, np.lib.npyio.NpzFile):
        raise ValueError(f"GarmentMeasurements PCA {path}: expected an .npz archive, got a single array")
    with data:
        missing = [k for k in ("pca_matrix", "pca_mean", "eigenvalues") if k not in data.files]
        if missing:
            raise ValueError(f"GarmentMeasurements PCA {path}: missing array(s) {', '.join(map(repr, missing))}")
        matrix, mean, eig = (np.asarray(data[k], dtype=np.float64) for k in ("pca_matrix", "pca_mean", "eigenvalues"))
    if matrix.ndim != 2 or mean.shape != (matrix.shape[0],) or eig.shape != (matrix.shape[1],):
        raise ValueError(
            f"GarmentMeasurements PCA {path}: expected pca_matrix (3V, K), pca_mean (3V,), eigenvalues (K,), "
            f"got {matrix.shape}, {mean.shape}, {eig.shape}"
        )
    return matrix, mean, eig


def _assemble(source: Path, arrays: tuple[np.ndarray, np.ndarray, np.ndarray], mesh_path: Path) -> GarmentPCA:
    matrix, mean, eig = arrays
    m, k = matrix.shape
    if m % 3:
        raise ValueError(f"GarmentMeasurements PCA {source}: dimension {m} is not 3 x vertices")
    for name, a in (("matrix", matrix), ("mean", mean), ("eigenvalues", eig)):
        if not np.isfinite(a).all():
            raise ValueError(f"GarmentMeasurements PCA {source}: {name} holds NaN/inf values")
    if not mesh_path.is_file():
        raise FileNotFoundError(f"GarmentMeasurements mesh {mesh_path} is missing (needed for the triangles)")
    vertices, polygons = read_obj(mesh_path)
    if len(vertices) != m // 3:
        raise ValueError(
            f"GarmentMeasurements mesh {mesh_path}: {len(vertices)} vertices, but the PCA {source} has {m // 3}"
        )
    faces = quads_to_triangles(polygons).numpy()
    if faces.size == 0 or faces.min() < 0 or faces.max() >= m // 3:
        raise ValueError(f"GarmentMeasurements mesh {mesh_path}: no faces, or a face index outside [0, {m // 3})")
    return GarmentPCA(
        mean=mean.reshape(-1, 3),
        components=np.ascontiguousarray(matrix.T).reshape(k, -1, 3),
        eigenvalues=eig,
        faces=faces,
    )


def load_garment_pca(folder: str | Path) -> GarmentPCA:
    """Load ``point.pca`` (or ``point.npz``) and ``mean.obj`` from ``folder``.

    Raises:
        FileNotFoundError: no PCA file or no ``mean.obj``. ValueError: malformed content.
    """
    folder = Path(folder)
    pca, npz = folder / "point.pca", folder / "point.npz"
    if pca.is_file():
        return _assemble(pca, read_point_pca(pca), folder / "mean.obj")
    if npz.is_file():
        return _assemble(npz, read_point_npz(npz), folder / "mean.obj")
    raise FileNotFoundError(
        f"GarmentMeasurements PCA: neither {pca} nor {npz} exists; copy data/pca/point.pca and mean.obj "
        "from github.com/mbotsch/GarmentMeasurements into that folder"
    )


class GarmentIdentity(nn.Module):
    """Rest meshes of GarmentMeasurements identities on the model's native topology.

    Args:
        pca: the model data, from :func:`load_garment_pca`.
        dtype: dtype of the buffers (float32 or float64); ``.to()`` changes it later.
    """

    name = "garment"

    def __init__(self, pca: GarmentPCA, *, dtype: torch.dtype = torch.float32) -> None:
        super().__init__()
        k = pca.components.shape[0]
        self.num_vertices = int(pca.mean.shape[0])
        self.param_names: tuple[str, ...] = tuple(f"pc_{i:02d}" for i in range(k))
        eig = pca.eigenvalues
        sigma = np.where(eig > _TINY_EIGENVALUE, np.sqrt(np.abs(eig)), np.abs(eig))
        self.register_buffer("mean", torch.as_tensor(pca.mean, dtype=dtype))
        self.register_buffer("components", torch.as_tensor(pca.components.reshape(k, -1), dtype=dtype))
        self.register_buffer("sigma", torch.as_tensor(sigma, dtype=dtype))
        self.register_buffer("face_indices", torch.as_tensor(pca.faces, dtype=torch.long), persistent=False)

    @classmethod
    def from_files(cls, folder: str | Path, *, dtype: torch.dtype = torch.float32) -> GarmentIdentity:
        """Load ``point.pca`` (or ``point.npz``) and ``mean.obj`` from ``folder``."""
        return cls(load_garment_pca(folder), dtype=dtype)

    @classmethod
    def from_file(
        cls, pca_path: str | Path, mesh_path: str | Path, *, dtype: torch.dtype = torch.float32
    ) -> GarmentIdentity:
        """Load a PCA file (``.pca`` binary or ``.npz``) and the OBJ mesh giving its triangles."""
        pca_path = Path(pca_path)
        read = read_point_npz if pca_path.suffix == ".npz" else read_point_pca
        return cls(_assemble(pca_path, read(pca_path), Path(mesh_path)), dtype=dtype)

    @property
    def num_params(self) -> int:
        """K: number of PCA components."""
        return len(self.param_names)

    @property
    def param_bounds(self) -> None:
        """None: coefficients are unbounded (the upstream sliders span -3..3, but any finite
        value is a shape of the linear model and :meth:`forward` accepts it)."""
        return None

    def default_params(self, batch: int = 1) -> torch.Tensor:
        """(B, K) the mean body: every coefficient 0."""
        return self.mean.new_zeros(batch, self.num_params)

    def faces(self) -> torch.Tensor:
        """(F, 3) triangles of the native mesh (long)."""
        return self.face_indices

    def template(self) -> torch.Tensor:
        """(V, 3) m, the mean body."""
        return self.mean.clone()

    def extra_repr(self) -> str:
        return f"vertices={self.num_vertices}, components={self.num_params}"

    def forward(self, params: torch.Tensor) -> torch.Tensor:
        """Rest meshes.

        Args:
            params: (B, K) PCA coefficients in standard deviations, order of ``param_names``.

        Returns:
            (B, V, 3) rest vertices, metres, Y up, facing +Z.
        """
        check_shape(params, f"B {self.num_params}", name="identity params")
        check_like(params, self.mean, name="identity params", owner="the GarmentMeasurements backend")
        check_finite(params, "identity params")
        offsets = (params * self.sigma) @ self.components
        return self.mean + offsets.view(-1, self.num_vertices, 3)
