"""A cached topology transfer per source mesh, built from an automatic registration.

The key is the sha256 of the source's float64 vertices, its triangulated int64 faces,
the registration algorithm version and the configuration, so any change to one of them
makes a new entry. Entries live under ``unibody.assets.cache_dir() / "registration"`` as
``<key>.npz`` (``face_vertices``, ``weights``, ``wrap``, the normalisation, and the sha256
of these arrays), written atomically under a lock (a second process waits for the first
and reads its entry). An entry is verified on load (checksum, keys, dtypes, shapes, index
ranges, finite values, weights summing to 1); an unusable one is rebuilt with an
:class:`~unibody.assets.AssetWarning`, and an unwritable cache folder means registering in
memory (one warning).
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from ..topology import CANONICAL_VERTICES, TopologyTransfer
from . import _register
from ._mesh import as_triangles, as_vertices
from ._register import RegistrationConfig

__all__ = ["REGISTRATION_VERSION", "cache_key", "cache_path", "topology_transfer"]

# Bump whenever the algorithm's output changes: old cache entries are then ignored.
REGISTRATION_VERSION = 1
_KEYS = frozenset(("version", "face_vertices", "weights", "wrap", "unit", "scale", "rotation", "translation"))
_UNITS = ("m", "cm", "mm", "in")


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


def _checker(num_source_vertices: int):
    """A check of an entry's arrays for a source of ``num_source_vertices`` vertices (raises ValueError)."""
    from ..assets import _check_keys, _expect, _in_range, _orthonormal

    def check(a: dict[str, np.ndarray]) -> None:
        _check_keys(a, _KEYS)
        version = _expect(a, "version", "i", ())
        if int(version) != REGISTRATION_VERSION:
            raise ValueError(f"version: {int(version)}, expected {REGISTRATION_VERSION}")
        n = CANONICAL_VERTICES
        _in_range("face_vertices", _expect(a, "face_vertices", "i", (n, 3)), 0, num_source_vertices)
        if np.abs(_expect(a, "weights", "f", (n, 4)).sum(1) - 1).max() > 1e-9:
            raise ValueError("weights: a vertex's weights do not sum to 1")
        _expect(a, "wrap", "f", (n, 3))
        if str(_expect(a, "unit", "U", ())) not in _UNITS:
            raise ValueError(f"unit: {str(a['unit'])!r}, expected one of {_UNITS}")
        if not float(_expect(a, "scale", "f", ())) > 0:
            raise ValueError("scale: not positive")
        _orthonormal("rotation", _expect(a, "rotation", "f", (3, 3))[None])
        _expect(a, "translation", "f", (3,))

    return check


def _arrays(reg: _register.Registration) -> dict[str, np.ndarray]:
    n = reg.normalization
    return {
        "version": np.asarray(REGISTRATION_VERSION, dtype=np.int64),
        "face_vertices": reg.correspondence.face_vertices.numpy().astype(np.int64),
        "weights": reg.correspondence.weights.numpy().astype(np.float64),
        "wrap": reg.wrap.numpy().astype(np.float64),
        "unit": np.asarray(n.unit, dtype=np.str_),
        "scale": np.asarray(n.scale, dtype=np.float64),
        "rotation": n.rotation.numpy().astype(np.float64),
        "translation": n.translation.numpy().astype(np.float64),
    }


def topology_transfer(
    vertices: torch.Tensor | np.ndarray,
    faces: torch.Tensor | np.ndarray | Sequence[Sequence[int]],
    name: str,
    *,
    config: RegistrationConfig | None = None,
    cache: bool = True,
    check_fit: bool = True,
) -> TopologyTransfer:
    """The topology transfer of a new source mesh, registered automatically (cached).

    Args:
        vertices: (Vs, 3) the source template (any unit and axes; see :func:`register`).
        faces: (F, 3) triangles, (F, 4) quads or a ragged polygon list.
        name: the source topology's name (used in the transfer's messages).
        config: registration options; ``PRESETS["default"]`` when None.
        cache: read and write the cache (False: always register, write nothing).
        check_fit: refuse a mesh the canonical body does not fit (:func:`register`).

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
    if not cache:
        reg = _register.register(v, f, config=config, check_fit=check_fit)
        fv, w = reg.correspondence.face_vertices, reg.correspondence.weights
        return TopologyTransfer(name, v.shape[0], fv, w)
    from ..assets import cached_arrays

    arrays = cached_arrays(
        cache_path(cache_key(v, f, config)),
        lambda: _arrays(_register.register(v, f, config=config, check_fit=check_fit)),
        _checker(v.shape[0]),
        what=f"the registration of {name!r}",
        estimate="about a minute",
    )
    fv, w = torch.from_numpy(arrays["face_vertices"]), torch.from_numpy(arrays["weights"])
    return TopologyTransfer(name, v.shape[0], fv, w)
