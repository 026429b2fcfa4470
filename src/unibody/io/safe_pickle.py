"""Restricted unpickling of legacy body-model ``.pkl`` files (SMPL, SMPL-H, SMPL-X, MANO).

The official pickles are Python-2 era (read with ``encoding="latin1"``). They hold numpy
arrays, ``scipy.sparse`` matrices (``J_regressor``) and, in SMPL 1.0, SMPL-H and MANO
files, ``chumpy`` objects. :func:`pickle.load` imports and calls whatever a file names, so
a hostile file runs code. :func:`load` never does:

- ``find_class`` answers from an explicit allow-list: numpy's array, dtype and scalar
  reconstructors, the builtins ``set``/``frozenset``/``bytes``/``object``, a checked
  ``copy_reg._reconstructor`` and a latin-1-only ``_codecs.encode`` (what Python 2 and
  protocol-2 pickles use for objects and bytes), and stand-ins for chumpy and scipy
  classes. Any other global raises :class:`pickle.UnpicklingError` naming it.
- chumpy and scipy are never imported. Their classes become stand-ins that only keep the
  pickled state; after loading, the result becomes plain containers and numpy arrays.

Pickled state layouts (facts from the chumpy and SciPy sources):

- chumpy ``Ch.__getstate__`` is ``__dict__`` minus ``_parents`` and ``_cache``. A plain
  ``Ch`` keeps its value under ``x``. ``chumpy.reordering`` nodes keep their input
  node under ``a``: ``Select`` evaluates to ``a.ravel()[idxs].reshape(preferred_shape)``,
  ``transpose`` to ``np.transpose(a, axes)`` and ``Reshape`` to ``a.reshape(newshape)``.
- SciPy sparse matrices pickle ``__dict__``. csc and csr keep ``data``, ``indices``,
  ``indptr`` and ``_shape`` (``shape`` in very old releases). coo keeps ``data`` and
  ``row``/``col``, or ``coords`` since SciPy 1.13. All of them become dense arrays;
  duplicate entries are summed, as SciPy does.
"""

from __future__ import annotations

import os
import pickle
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO, ClassVar

import numpy as np

__all__ = ["load"]

_MAX_DEPTH = 64  # nesting of containers and chumpy nodes; official files use fewer than 5
_MAX_DENSE = 1 << 28  # entries of a densified sparse matrix (SMPL-X J_regressor: 5.8e5)


class _StandIn:
    """An object whose real class is never imported: it keeps its pickled state only."""

    __slots__ = ("state",)
    kind: ClassVar[str] = ""

    def __setstate__(self, state: object) -> None:
        self.state = state


class _ChumpyNode(_StandIn):
    __slots__ = ()


class _SparseMatrix(_StandIn):
    __slots__ = ()
    fmt: ClassVar[str] = ""


_CHUMPY_KINDS = ("chumpy.ch.Ch", "chumpy.reordering.Select", "chumpy.reordering.transpose", "chumpy.reordering.Reshape")


def _reconstructor(cls: object, base: object, state: object) -> _StandIn:
    """``copy_reg._reconstructor`` (protocols 0 and 1), limited to stand-ins built on ``object``."""
    if not (isinstance(cls, type) and issubclass(cls, _StandIn)) or base is not object or state is not None:
        raise pickle.UnpicklingError(
            f"copy_reg._reconstructor: only the chumpy/scipy stand-ins on base 'object' may be rebuilt, "
            f"got ({cls!r}, {base!r}, {state!r})"
        )
    return cls.__new__(cls)


def _latin1_encode(obj: object, encoding: object = "utf-8", errors: object = "strict") -> bytes:
    """``_codecs.encode`` as Python 3 uses it to pickle bytes at protocols 0-2: latin-1 only."""
    if not isinstance(obj, str) or encoding not in ("latin1", "latin-1") or errors != "strict":
        raise pickle.UnpicklingError(f"_codecs.encode: only (str, 'latin1') is allowed, got encoding {encoding!r}")
    return obj.encode("latin1")


def _allow_list() -> dict[tuple[str, str], object]:
    reconstruct = np.zeros(1).__reduce__()[0]
    scalar = np.float64(0.0).__reduce__()[0]
    frombuffer = np.zeros(1).__reduce_ex__(5)[0]
    table: dict[tuple[str, str], object] = {("numpy", "ndarray"): np.ndarray, ("numpy", "dtype"): np.dtype}
    for core in ("numpy.core", "numpy._core"):  # numpy 1.x and 2.x module names
        table[(f"{core}.multiarray", "_reconstruct")] = reconstruct
        table[(f"{core}.multiarray", "scalar")] = scalar
        table[(f"{core}.numeric", "_frombuffer")] = frombuffer
    for module in ("builtins", "__builtin__"):
        for builtin in (set, frozenset, bytes, object):
            table[(module, builtin.__name__)] = builtin
    for module in ("copyreg", "copy_reg"):
        table[(module, "_reconstructor")] = _reconstructor
    table[("_codecs", "encode")] = _latin1_encode
    for kind in _CHUMPY_KINDS:
        module, name = kind.rsplit(".", 1)
        table[(module, name)] = type(name, (_ChumpyNode,), {"__slots__": (), "kind": kind})
    for fmt in ("csc", "csr", "coo"):
        for module in (f"scipy.sparse.{fmt}", f"scipy.sparse._{fmt}"):  # SciPy < 1.8 and >= 1.8
            for name in (f"{fmt}_matrix", f"{fmt}_array"):
                attrs = {"__slots__": (), "kind": f"{module}.{name}", "fmt": fmt}
                table[(module, name)] = type(name, (_SparseMatrix,), attrs)
    return table


_ALLOWED = _allow_list()


class _RestrictedUnpickler(pickle.Unpickler):
    """Resolves globals from the allow-list only; never imports anything."""

    def find_class(self, module: str, name: str) -> object:
        try:
            return _ALLOWED[(module, name)]
        except KeyError:
            raise pickle.UnpicklingError(
                f"refusing global {module}.{name}: not on the allow-list (numpy arrays, chumpy Ch/Select/"
                "transpose/Reshape, scipy csc/csr/coo matrices); the file may be malicious or of an unsupported kind"
            ) from None

    def persistent_load(self, pid: object) -> object:
        raise pickle.UnpicklingError("persistent ids are not supported")


def load(path_or_file: str | os.PathLike[str] | BinaryIO) -> object:
    """Load a pickle without executing code and return plain containers and numpy arrays.

    Args:
        path_or_file: a ``.pkl`` path or a binary file object. Python-2 strings are
            decoded as latin-1 (needed for numpy raw data in the official files).

    Returns:
        The unpickled object with every chumpy node and sparse matrix replaced by a dense
        numpy array (dicts, lists and tuples are rebuilt; other values are kept).

    Raises:
        pickle.UnpicklingError: a global outside the allow-list (named in the message),
            a malformed or truncated pickle, or a chumpy/sparse state that cannot be
            evaluated. Messages start with the file name.
        FileNotFoundError: ``path_or_file`` does not exist.
    """
    if isinstance(path_or_file, (str, os.PathLike)):
        path = Path(path_or_file)
        with open(path, "rb") as f:
            return _load_stream(f, str(path))
    return _load_stream(path_or_file, str(getattr(path_or_file, "name", "<stream>")))


def _load_stream(f: BinaryIO, where: str) -> object:
    try:
        raw = _RestrictedUnpickler(f, encoding="latin1").load()
    except pickle.UnpicklingError as e:
        raise pickle.UnpicklingError(f"{where}: {e}") from None
    except Exception as e:  # malformed input: truncated streams, bad reconstructor arguments, ...
        raise pickle.UnpicklingError(f"{where}: not a loadable pickle ({type(e).__name__}: {e})") from e
    return _plain(raw, where, 0, set())


def _plain(obj: object, where: str, depth: int, active: set[int]) -> object:
    """Replace stand-ins by arrays, recursively through dicts, lists, tuples and object arrays."""
    if depth > _MAX_DEPTH:
        raise pickle.UnpicklingError(f"{where}: nested deeper than {_MAX_DEPTH} levels")
    if not isinstance(obj, (_StandIn, dict, list, tuple, np.ndarray)):
        return obj
    if isinstance(obj, np.ndarray) and not obj.dtype.hasobject:
        return obj
    if id(obj) in active:
        raise pickle.UnpicklingError(f"{where}: cyclic reference; body-model files hold no cycles")
    active.add(id(obj))
    try:
        return _convert(obj, where, depth + 1, active)
    finally:
        active.discard(id(obj))


def _convert(obj: object, where: str, depth: int, active: set[int]) -> object:
    if isinstance(obj, _ChumpyNode):
        return _chumpy_value(obj, where, depth, active)
    if isinstance(obj, _SparseMatrix):
        return _sparse_to_dense(obj, where, depth, active)
    if isinstance(obj, dict):
        return {k: _plain(v, f"{where}[{k!r}]", depth, active) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_plain(v, f"{where}[{i}]", depth, active) for i, v in enumerate(obj)]
    if isinstance(obj, tuple):
        return tuple(_plain(v, f"{where}[{i}]", depth, active) for i, v in enumerate(obj))
    return _object_array(obj, where, depth, active)  # type: ignore[arg-type]


def _object_array(obj: np.ndarray, where: str, depth: int, active: set[int]) -> np.ndarray:
    """Convert the items of an object array, keeping its shape."""
    out = np.empty(obj.size, dtype=object)
    for i, item in enumerate(obj.reshape(-1)):
        out[i] = _plain(item, f"{where}[{i}]", depth, active)
    return out.reshape(obj.shape)


def _state(node: _StandIn, where: str) -> dict[str, object]:
    state = getattr(node, "state", None)
    if not isinstance(state, dict):
        raise pickle.UnpicklingError(f"{where}: {node.kind} has no pickled state dict, got {type(state).__name__}")
    return state


def _term(node: _StandIn, key: str, where: str, depth: int, active: set[int]) -> object:
    state = _state(node, where)
    if key not in state:
        raise pickle.UnpicklingError(f"{where}: {node.kind} state lacks {key!r}")
    return _plain(state[key], f"{where}.{key}", depth, active)


def _chumpy_value(node: _ChumpyNode, where: str, depth: int, active: set[int]) -> np.ndarray:
    """Evaluate a chumpy node the way its ``compute_r`` does."""
    kind, state = node.kind, _state(node, where)

    def term(key: str) -> object:
        return _term(node, key, where, depth, active)

    try:
        if kind == "chumpy.ch.Ch":
            return np.ascontiguousarray(term("x"))
        a = np.asarray(term("a"))
        if kind == "chumpy.reordering.Select":
            value = _select(a, term("idxs"), state, term)
        elif kind == "chumpy.reordering.transpose":
            value = np.transpose(a, axes=term("axes") if "axes" in state else None)
        else:  # chumpy.reordering.Reshape
            value = a.reshape(term("newshape"))
        return np.ascontiguousarray(value)
    except (IndexError, ValueError, TypeError) as e:
        raise pickle.UnpicklingError(f"{where}: cannot evaluate {kind}: {e}") from None


def _select(a: np.ndarray, idxs: object, state: dict[str, object], term: Callable[[str], object]) -> np.ndarray:
    idx = np.asarray(idxs)
    if idx.dtype.kind not in "iu":
        raise TypeError(f"idxs must be integers, got dtype {idx.dtype}")
    out = a.ravel()[idx]
    return out.reshape(term("preferred_shape")) if "preferred_shape" in state else out


def _sparse_to_dense(node: _SparseMatrix, where: str, depth: int, active: set[int]) -> np.ndarray:
    """Densify a pickled csc/csr/coo matrix (duplicates summed)."""
    state = _state(node, where)

    def arr(key: str) -> np.ndarray:
        return np.asarray(_term(node, key, where, depth, active))

    try:
        raw_shape = state["_shape"] if "_shape" in state else state["shape"]
        shape = tuple(int(n) for n in raw_shape)  # type: ignore[union-attr]
    except (KeyError, TypeError, ValueError):
        raise pickle.UnpicklingError(f"{where}: {node.kind} state has no valid '_shape'") from None
    if len(shape) != 2 or min(shape) < 0 or shape[0] * shape[1] > _MAX_DENSE:
        raise pickle.UnpicklingError(f"{where}: {node.kind} has an unsupported shape {shape}")
    data = arr("data").reshape(-1)
    if data.dtype.kind not in "biufc":
        raise pickle.UnpicklingError(f"{where}: {node.kind} data must be numeric, got dtype {data.dtype}")
    if node.fmt == "coo":
        coords = _term(node, "coords", where, depth, active) if "coords" in state else (arr("row"), arr("col"))
        rows, cols = (np.asarray(c).reshape(-1) for c in coords)  # type: ignore[union-attr]
    else:
        rows, cols = _compressed_coords(node, arr("indices").reshape(-1), arr("indptr").reshape(-1), shape, where)
    n = data.shape[0]
    for label, idx, size in (("row", rows, shape[0]), ("column", cols, shape[1])):
        if idx.shape != (n,) or idx.dtype.kind not in "iu" or (n and (idx.min() < 0 or idx.max() >= size)):
            raise pickle.UnpicklingError(f"{where}: {node.kind} has invalid {label} indices for shape {shape}")
    dense = np.zeros(shape, dtype=data.dtype)
    np.add.at(dense, (rows, cols), data)
    return dense


def _compressed_coords(
    node: _SparseMatrix, indices: np.ndarray, indptr: np.ndarray, shape: tuple[int, ...], where: str
) -> tuple[np.ndarray, np.ndarray]:
    major = shape[1] if node.fmt == "csc" else shape[0]
    ok = indptr.shape == (major + 1,) and indptr.dtype.kind in "iu"
    ok = ok and int(indptr[0]) == 0 and int(indptr[-1]) == indices.shape[0] and bool(np.all(np.diff(indptr) >= 0))
    if not ok:
        raise pickle.UnpicklingError(f"{where}: {node.kind} has an invalid indptr for shape {shape}")
    major_idx = np.repeat(np.arange(major), np.diff(indptr))
    return (indices, major_idx) if node.fmt == "csc" else (major_idx, indices)
