"""A cached topology transfer per source mesh, built from an automatic registration.

The key is the sha256 of the source's float64 vertices, its triangulated int64 faces,
the registration algorithm version and the configuration, so any change to one of them
makes a new entry. Entries live under ``unibody.assets.cache_dir() / "registration"`` as
``<key>.npz`` (``face_vertices``, ``weights``, ``wrap``, the normalisation), written to a
temporary file and renamed into place (atomic); an unreadable or inconsistent entry is
logged and rebuilt.
"""

from __future__ import annotations

import hashlib
import logging
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from ..topology import TopologyTransfer
from . import _register
from ._mesh import as_triangles, as_vertices
from ._register import RegistrationConfig

logger = logging.getLogger(__name__)

__all__ = ["REGISTRATION_VERSION", "cache_key", "cache_path", "topology_transfer"]

# Bump whenever the algorithm's output changes: old cache entries are then ignored.
REGISTRATION_VERSION = 1
_CANONICAL_VERTICES = 18056


def cache_key(vertices: torch.Tensor, faces: torch.Tensor, config: RegistrationConfig) -> str:
    """sha256 hex digest of the float64 vertices, int64 triangles, algorithm version and config."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(vertices.numpy(), dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(faces.numpy(), dtype=np.int64).tobytes())
    h.update(f"unibody.registration/{REGISTRATION_VERSION}/{config!r}".encode())
    return h.hexdigest()


def cache_path(key: str) -> Path:
    """Where the entry of ``key`` lives."""
    from ..assets import cache_dir

    return cache_dir() / "registration" / f"{key}.npz"


def _load(path: Path, num_source_vertices: int) -> tuple[np.ndarray, np.ndarray] | None:
    try:
        with np.load(path, allow_pickle=False) as data:
            fv, w = data["face_vertices"], data["weights"]
            version = int(data["version"])
    except (OSError, ValueError, KeyError) as exc:
        logger.warning("rebuilding unreadable registration cache %s (%s)", path, exc)
        return None
    ok = (
        version == REGISTRATION_VERSION
        and fv.shape == (_CANONICAL_VERTICES, 3)
        and w.shape == (_CANONICAL_VERTICES, 4)
        and np.issubdtype(fv.dtype, np.integer)
        and fv.min() >= 0
        and fv.max() < num_source_vertices
        and np.isfinite(w).all()
    )
    if not ok:
        logger.warning("rebuilding inconsistent registration cache %s", path)
        return None
    return fv.astype(np.int64), w.astype(np.float64)


def _save(path: Path, reg: _register.Registration) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.stem}.tmp{os.getpid()}.npz")
    n = reg.normalization
    np.savez(
        tmp,
        version=np.int64(REGISTRATION_VERSION),
        face_vertices=reg.correspondence.face_vertices.numpy(),
        weights=reg.correspondence.weights.numpy(),
        wrap=reg.wrap.numpy(),
        unit=np.str_(n.unit),
        scale=np.float64(n.scale),
        rotation=n.rotation.numpy(),
        translation=n.translation.numpy(),
    )
    os.replace(tmp, path)


def topology_transfer(
    vertices: torch.Tensor | np.ndarray,
    faces: torch.Tensor | np.ndarray | Sequence[Sequence[int]],
    name: str,
    *,
    config: RegistrationConfig | None = None,
    cache: bool = True,
) -> TopologyTransfer:
    """The topology transfer of a new source mesh, registered automatically (cached).

    Args:
        vertices: (Vs, 3) the source template (any unit and axes; see :func:`register`).
        faces: (F, 3) triangles, (F, 4) quads or a ragged polygon list.
        name: the source topology's name (used in the transfer's messages).
        config: registration options; ``PRESETS["default"]`` when None.
        cache: read and write the cache (False: always register, write nothing).

    Returns:
        A float64 :class:`~unibody.topology.TopologyTransfer` from this topology to the
        canonical one; ``.to(dtype)`` as needed. Its input must be in the same frame and
        units as ``vertices`` (the tetrahedral weights are not scale-invariant).
    """
    if not isinstance(name, str) or not name:
        raise ValueError(f"name: expected a non-empty string, got {name!r}")
    config = _register._check_config(_register.PRESETS["default"] if config is None else config)
    v = as_vertices(vertices)
    f = as_triangles(faces, v.shape[0])
    path = cache_path(cache_key(v, f, config))
    loaded = _load(path, v.shape[0]) if cache and path.is_file() else None
    if loaded is None:
        reg = _register.register(v, f, config=config)
        if cache:
            _save(path, reg)
        fv, w = reg.correspondence.face_vertices, reg.correspondence.weights
    else:
        fv, w = torch.from_numpy(loaded[0]), torch.from_numpy(loaded[1])
    return TopologyTransfer(name, v.shape[0], fv, w)
