"""Restricted unpickling of legacy body-model ``.pkl`` files (SMPL, SMPL-H, SMPL-X, MANO).

The official pickles are Python-2 era (read with ``encoding="latin1"``). They hold numpy
arrays, ``scipy.sparse`` matrices (``J_regressor``) and, in SMPL 1.0, SMPL-H and MANO
files, ``chumpy`` objects. :func:`pickle.load` imports and calls whatever a file names, so
a hostile file runs code. :func:`load` never does:

- ``find_class`` answers from an explicit allow-list: stand-ins for numpy's array, dtype
  and scalar reconstructors, the builtins ``set``/``frozenset``/``object``, an empty-only
  ``bytes``, a checked ``copy_reg._reconstructor`` and a latin-1-only ``_codecs.encode``
  (what Python 2 and protocol-2 pickles use for objects and bytes), and stand-ins for
  chumpy and scipy classes. Any other global raises :class:`pickle.UnpicklingError`
  naming it.
- numpy is never handed a buffer, a dtype state or a shape from the file. ``numpy.ndarray``
  cannot be called; ``dtype`` is rebuilt from a plain type code (bool, integer, float,
  complex, bytes, str; object only for arrays pickled as a list of items); arrays are
  rebuilt with ``np.frombuffer(bytes, dtype).reshape(shape).copy()`` after checking that
  the shape is non-negative integers of rank at most 32 and that the byte count is
  exactly ``prod(shape) * itemsize``. So no array can alias memory, hold forged object
  pointers, or be larger than the bytes the file holds.
- chumpy and scipy are never imported. Their classes become stand-ins that only keep the
  pickled state; after loading, the result becomes plain containers and numpy arrays.

Resource bounds, so that a small file cannot hang or exhaust memory:

- the opcode stream is checked first (:mod:`pickletools`): every counted string fits in
  the file, memo indices are no larger than the number of opcodes read so far;
- shared objects are converted once (a memo keyed by identity), so a file of nested
  shared lists costs time linear in its size; cycles are refused;
- every array built (from file bytes, chumpy evaluation, sparse densification, lists)
  is charged to a budget of ``64 MiB + 16 x the file size``; going over raises.

Pickled state layouts (facts from the chumpy and SciPy sources):

- chumpy ``Ch.__getstate__`` is ``__dict__`` minus ``_parents`` and ``_cache``. A plain
  ``Ch`` keeps its value under ``x``. ``chumpy.reordering`` nodes keep their input
  node under ``a``: ``Select`` evaluates to ``a.ravel()[idxs].reshape(preferred_shape)``,
  ``transpose`` to ``np.transpose(a, axes)`` and ``Reshape`` to ``a.reshape(newshape)``.
- SciPy sparse matrices pickle ``__dict__``. csc and csr keep ``data``, ``indices``,
  ``indptr`` and ``_shape`` (``shape`` in very old releases). coo keeps ``data`` and
  ``row``/``col``, or ``coords`` since SciPy 1.13. All of them become dense arrays;
  duplicate entries are summed, as SciPy does.
- numpy arrays pickle as ``_reconstruct(ndarray, (0,), b"b")`` followed by the state
  ``(version, shape, dtype, fortran_order, raw_bytes_or_item_list)``, or (protocol 5) as
  ``_frombuffer(buffer, dtype, shape, order)``; scalars as ``scalar(dtype, raw_bytes)``;
  dtypes as ``dtype(code, align, copy)`` followed by ``(version, byte_order, ...)``.
"""

from __future__ import annotations

import functools
import io
import os
import pickle
import pickletools
import re
import reprlib
from pathlib import Path
from typing import BinaryIO, ClassVar

import numpy as np

__all__ = ["load"]

_MAX_DEPTH = 64  # nesting of containers and chumpy nodes; official files use fewer than 5
_MAX_DENSE = 1 << 28  # entries of a densified sparse matrix (SMPL-X J_regressor: 5.8e5)
_MAX_RANK = 32  # dimensions of an array (numpy allows 64; the files use at most 3)
_BUDGET_BASE = 64 << 20  # bytes every file may allocate for arrays, whatever its size
_BUDGET_PER_BYTE = 16  # ... plus this many bytes per byte of the file


_REPR = reprlib.Repr()
_REPR.maxlevel, _REPR.maxstring, _REPR.maxother = 3, 40, 40


def _r(value: object) -> str:
    """A short repr of file content for messages (bounded work even for huge or shared structures)."""
    return _REPR.repr(value)


class _Budget:
    """Bytes of arrays one file may still allocate (see the module docstring)."""

    def __init__(self, file_size: int) -> None:
        self.file_size = file_size
        self.limit = _BUDGET_BASE + _BUDGET_PER_BYTE * file_size
        self.used = 0

    def charge(self, nbytes: int, what: str) -> None:
        if nbytes > self.limit - self.used:
            raise pickle.UnpicklingError(
                f"{what} needs {nbytes} bytes, over the budget of this {self.file_size}-byte file "
                f"({self.limit} bytes for all its arrays, {self.used} used); the file is malformed or hostile"
            )
        self.used += nbytes


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


# --- numpy stand-ins ---------------------------------------------------------------------------------------------


class _NDArrayType:
    """Stands for ``numpy.ndarray``: valid only as the first argument of ``_reconstruct``.

    Calling it (``ndarray(shape, dtype, buffer, offset, strides)``) would let a file point an
    array at memory of its choosing, so it is refused.
    """

    def __new__(cls, *args: object, **kwargs: object) -> _NDArrayType:
        raise pickle.UnpicklingError(
            "numpy.ndarray may not be called by a pickle (an array over a file-supplied buffer); "
            "arrays are only rebuilt from their pickled dtype, shape and bytes"
        )


_DTYPE_CODE = re.compile(r"([biufc])(\d+)|([SU])(\d+)|(O)[48]")
_BYTE_ORDERS = ("<", ">", "=", "|")


class _DTypeSpec:
    """Stands for ``numpy.dtype(code, align, copy)`` plus its ``__setstate__``; see :meth:`resolve`."""

    __slots__ = ("code", "state")

    def __init__(self, code: object, align: object = False, copy: object = False) -> None:
        self.code = code
        self.state: object = None

    def __setstate__(self, state: object) -> None:
        self.state = state

    def resolve(self) -> np.dtype:
        """The real dtype: a plain bool/int/float/complex/bytes/str/object code and a byte order, nothing else."""
        code = self.code
        match = _DTYPE_CODE.fullmatch(code) if isinstance(code, str) else None
        if match is None:
            raise pickle.UnpicklingError(
                f"numpy dtype: expected a plain type code such as 'f8', 'i4', 'S3' or 'O8', got {_r(code)}"
            )
        dtype = np.dtype("O") if match.group(5) else np.dtype(code)
        if dtype.fields is not None or dtype.subdtype is not None or dtype.itemsize == 0:
            raise pickle.UnpicklingError(f"numpy dtype: unsupported type code {_r(code)}")
        state = self.state
        if state is None:
            return dtype
        if not isinstance(state, tuple) or not 5 <= len(state) <= 9:
            raise pickle.UnpicklingError(f"numpy dtype {code}: expected a state tuple of 5 to 9 items, got {_r(state)}")
        order = state[1]
        extra = state[2:5] if len(state) >= 7 else state[2:4]  # subarray, names, fields (or subarray, fields)
        if order not in _BYTE_ORDERS or any(x is not None for x in extra) or (len(state) == 9 and state[8] is not None):
            raise pickle.UnpicklingError(
                f"numpy dtype {code}: only a byte order may be set (no fields, subarray or metadata), got {_r(state)}"
            )
        if len(state) >= 7 and isinstance(state[5], int) and state[5] not in (-1, dtype.itemsize):
            raise pickle.UnpicklingError(f"numpy dtype {code}: item size {state[5]} does not match {dtype.itemsize}")
        return dtype.newbyteorder(order) if order in "<>" and dtype.kind not in "bSO" else dtype


def _dtype_of(spec: object, what: str) -> np.dtype:
    if not isinstance(spec, _DTypeSpec):
        raise pickle.UnpicklingError(f"{what}: expected a pickled numpy dtype, got {type(spec).__name__}")
    return spec.resolve()


def _raw_bytes(data: object, what: str) -> bytes | bytearray:
    """File bytes: ``bytes``/``bytearray`` as read, or a Python-2 ``str`` decoded as latin-1."""
    if type(data) in (bytes, bytearray):
        return data  # type: ignore[return-value]
    if type(data) is str:
        try:
            return data.encode("latin1")
        except UnicodeEncodeError:
            raise pickle.UnpicklingError(f"{what}: raw data is a str with characters outside latin-1") from None
    raise pickle.UnpicklingError(f"{what}: expected raw data as bytes, got {type(data).__name__}")


def _shape_of(shape: object, what: str) -> tuple[int, ...]:
    if not isinstance(shape, (tuple, list)) or len(shape) > _MAX_RANK:
        raise pickle.UnpicklingError(f"{what}: expected a shape tuple of at most {_MAX_RANK} sizes, got {_r(shape)}")
    if not all(type(n) is int and n >= 0 for n in shape):
        raise pickle.UnpicklingError(f"{what}: expected non-negative integer sizes, got {_r(shape)}")
    return tuple(shape)


def _array_from_bytes(
    budget: _Budget, data: object, dtype: np.dtype, shape: tuple[int, ...], fortran: bool, what: str
) -> np.ndarray:
    if dtype.hasobject:
        raise pickle.UnpicklingError(f"{what}: object arrays cannot be rebuilt from raw bytes")
    raw = _raw_bytes(data, what)
    size = 1
    for n in shape:
        size *= n
    if len(raw) != size * dtype.itemsize:
        raise pickle.UnpicklingError(
            f"{what}: shape {shape} of {dtype} needs {size * dtype.itemsize} bytes, the file gives {len(raw)}"
        )
    budget.charge(len(raw), what)
    order = "F" if fortran else "C"
    return np.frombuffer(raw, dtype=dtype).reshape(shape, order=order).copy(order=order)


class _PendingArray:
    """What ``_reconstruct`` returns: an array rebuilt, checked, by ``__setstate__``."""

    __slots__ = ("budget", "value", "items", "shape", "order")

    def __init__(self, budget: _Budget) -> None:
        self.budget = budget
        self.value: np.ndarray | None = None
        self.items: list[object] | None = None  # object arrays: items converted after loading
        self.shape: tuple[int, ...] = ()
        self.order = "C"

    def __setstate__(self, state: object) -> None:
        what = "numpy array"
        if isinstance(state, tuple) and len(state) == 5:
            version, *rest = state
            if version not in (0, 1):
                raise pickle.UnpicklingError(f"{what}: unsupported state version {_r(version)}")
        elif isinstance(state, tuple) and len(state) == 4:
            rest = list(state)
        else:
            raise pickle.UnpicklingError(
                f"{what}: expected state (version, shape, dtype, fortran, data), got {type(state).__name__}"
            )
        shape, dtype, fortran, data = rest
        shape = _shape_of(shape, what)
        dtype = _dtype_of(dtype, what)
        if fortran not in (0, 1):  # False/True (and Python 2's 0/1)
            raise pickle.UnpicklingError(f"{what}: fortran flag must be a bool, got {_r(fortran)}")
        self.value, self.items, self.shape, self.order = None, None, shape, "F" if fortran else "C"
        if dtype.hasobject:
            size = 1
            for n in shape:
                size *= n
            if type(data) is not list or len(data) != size:
                raise pickle.UnpicklingError(
                    f"{what}: an object array of shape {shape} must be pickled as a list of {size} items, "
                    f"got {type(data).__name__}"
                )
            self.budget.charge(8 * size, what)
            self.items = data
        else:
            self.value = _array_from_bytes(self.budget, data, dtype, shape, bool(fortran), what)


class _PendingScalar:
    """What ``scalar`` returns: a checked numpy scalar (kept apart so that BUILD cannot reach numpy)."""

    __slots__ = ("value",)

    def __init__(self, value: np.generic) -> None:
        self.value = value

    def __setstate__(self, state: object) -> None:
        raise pickle.UnpicklingError("numpy scalar: a pickle may not set state on a scalar")


def _reconstruct(budget: _Budget, subtype: object, shape: object = (0,), typecode: object = b"b") -> _PendingArray:
    """``numpy.core.multiarray._reconstruct``: plain ndarrays only; the state comes next."""
    if subtype is not _NDArrayType or typecode not in (b"b", "b"):
        raise pickle.UnpicklingError(
            f"numpy _reconstruct: only (numpy.ndarray, shape, b'b') is allowed, got ({_r(subtype)}, {_r(typecode)})"
        )
    return _PendingArray(budget)


def _frombuffer(budget: _Budget, buf: object, dtype: object, shape: object, order: object = "C") -> _PendingArray:
    """``numpy.core.numeric._frombuffer`` (protocol 5): in-band bytes only, checked as for ``_reconstruct``."""
    what = "numpy array (protocol 5)"
    if order not in ("C", "F"):
        raise pickle.UnpicklingError(f"{what}: order must be 'C' or 'F', got {_r(order)}")
    out = _PendingArray(budget)
    out.shape, out.order = _shape_of(shape, what), order
    out.value = _array_from_bytes(budget, buf, _dtype_of(dtype, what), out.shape, order == "F", what)
    return out


def _scalar(budget: _Budget, dtype: object, data: object = None) -> _PendingScalar:
    """``numpy.core.multiarray.scalar``: a non-object dtype and exactly ``itemsize`` bytes."""
    what = "numpy scalar"
    real = _dtype_of(dtype, what)
    if real.hasobject:
        raise pickle.UnpicklingError(f"{what}: object scalars are not supported")
    value = _array_from_bytes(budget, data, real, (), False, what)
    return _PendingScalar(value[()])


_NEEDS_BUDGET = (_reconstruct, _frombuffer, _scalar)


# --- other allowed callables ------------------------------------------------------------------------------------


def _reconstructor(cls: object, base: object, state: object) -> _StandIn:
    """``copy_reg._reconstructor`` (protocols 0 and 1), limited to stand-ins built on ``object``."""
    if not (isinstance(cls, type) and issubclass(cls, _StandIn)) or base is not object or state is not None:
        raise pickle.UnpicklingError(
            f"copy_reg._reconstructor: only the chumpy/scipy stand-ins on base 'object' may be rebuilt, "
            f"got ({_r(cls)}, {_r(base)}, {_r(state)})"
        )
    return cls.__new__(cls)


def _latin1_encode(obj: object, encoding: object = "utf-8", errors: object = "strict") -> bytes:
    """``_codecs.encode`` as Python 3 uses it to pickle bytes at protocols 0-2: latin-1 only."""
    if not isinstance(obj, str) or encoding not in ("latin1", "latin-1") or errors != "strict":
        raise pickle.UnpicklingError(f"_codecs.encode: only (str, 'latin1') is allowed, got encoding {_r(encoding)}")
    return obj.encode("latin1")


def _empty_bytes(*args: object) -> bytes:
    """``bytes()``, which is how protocols 0-2 pickle ``b""`` (``bytes(n)`` would allocate n bytes)."""
    if args:
        raise pickle.UnpicklingError(f"builtins.bytes: only bytes() is allowed, got {len(args)} argument(s)")
    return b""


def _allow_list() -> dict[tuple[str, str], object]:
    table: dict[tuple[str, str], object] = {("numpy", "ndarray"): _NDArrayType, ("numpy", "dtype"): _DTypeSpec}
    for core in ("numpy.core", "numpy._core"):  # numpy 1.x and 2.x module names
        table[(f"{core}.multiarray", "_reconstruct")] = _reconstruct
        table[(f"{core}.multiarray", "scalar")] = _scalar
        table[(f"{core}.numeric", "_frombuffer")] = _frombuffer
    for module in ("builtins", "__builtin__"):
        for builtin in (set, frozenset, object):
            table[(module, builtin.__name__)] = builtin
        table[(module, "bytes")] = _empty_bytes
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

    def __init__(self, file: BinaryIO, budget: _Budget) -> None:
        super().__init__(file, encoding="latin1")
        self.budget = budget

    def find_class(self, module: str, name: str) -> object:
        try:
            found = _ALLOWED[(module, name)]
        except KeyError:
            raise pickle.UnpicklingError(
                f"refusing global {module}.{name}: not on the allow-list (numpy arrays, chumpy Ch/Select/"
                "transpose/Reshape, scipy csc/csr/coo matrices); the file may be malicious or of an unsupported kind"
            ) from None
        if found in _NEEDS_BUDGET:
            return functools.partial(found, self.budget)
        return found

    def persistent_load(self, pid: object) -> object:
        raise pickle.UnpicklingError("persistent ids are not supported")


# --- loading ----------------------------------------------------------------------------------------------------


def load(path_or_file: str | os.PathLike[str] | BinaryIO) -> object:
    """Load a pickle without executing code and return plain containers and numpy arrays.

    Args:
        path_or_file: a ``.pkl`` path or a binary file object (read to its end; a seekable
            one is left just after the pickle). Python-2 strings are decoded as latin-1
            (needed for numpy raw data in the official files).

    Returns:
        The unpickled object with every chumpy node and sparse matrix replaced by a dense
        numpy array (dicts, lists, tuples and sets are rebuilt; other values are kept).

    Raises:
        pickle.UnpicklingError: a global outside the allow-list (named in the message),
            a malformed or truncated pickle, an array whose dtype, shape or bytes do not
            check, a chumpy/sparse state that cannot be evaluated, or a file that would
            need more memory than its budget (``64 MiB + 16 x`` its size). Messages start
            with the file name. Nothing else is raised for any file content (no
            MemoryError, no RecursionError).
        FileNotFoundError: ``path_or_file`` does not exist.
    """
    if isinstance(path_or_file, (str, os.PathLike)):
        path = Path(path_or_file)
        with open(path, "rb") as f:
            return _load_bytes(f.read(), str(path))[0]
    f = path_or_file
    where = str(getattr(f, "name", "<stream>"))
    start = f.tell() if f.seekable() else None
    out, consumed = _load_bytes(f.read(), where)
    if start is not None:
        f.seek(start + consumed)
    return out


def _load_bytes(data: bytes, where: str) -> tuple[object, int]:
    _check_opcodes(data, where)
    budget = _Budget(len(data))
    stream = io.BytesIO(data)
    try:
        raw = _RestrictedUnpickler(stream, budget).load()
    except pickle.UnpicklingError as e:
        raise pickle.UnpicklingError(f"{where}: {e}") from None
    except Exception as e:  # malformed input: bad reconstructor arguments, MemoryError, ...
        raise pickle.UnpicklingError(f"{where}: not a loadable pickle ({type(e).__name__}: {e})") from None
    try:
        out = _Converter(where, budget).plain(raw, _Where(where), 0)
    except pickle.UnpicklingError:
        raise
    except Exception as e:  # numpy refusing an evaluation we did not foresee, MemoryError, ...
        raise pickle.UnpicklingError(f"{where}: cannot convert the pickled data ({type(e).__name__}: {e})") from None
    return out, stream.tell()


_MARK = object()  # a MARK on the simulated stack


class _Node:
    """A simulated stack value: what hashing or comparing it would cost (tuple items are visited)."""

    __slots__ = ("cost",)

    def __init__(self, cost: int = 1) -> None:
        self.cost = cost


def _check_opcodes(data: bytes, where: str) -> None:
    """Walk the opcodes before unpickling; raise on anything that would make the unpickler hang or blow up.

    - A counted string or frame longer than the rest of the file, or a memo index beyond the
      opcodes read so far: CPython's unpickler allocates the string, and grows its memo to the
      largest index, before finding that out, so a few bytes could ask for gigabytes.
    - Hashing work: dict keys, set items and call arguments are hashed or compared, and a
      tuple's hash visits every item, again for each reference to a shared one, so a few
      hundred bytes of nested shared tuples would take forever to hash. The stack is
      simulated to bound the total work by ``1e6 + 16 x`` the file size.
    """
    limit = 1_000_000 + 16 * len(data)
    work = 0
    stack: list[object] = []
    memo: dict[int, object] = {}
    count = 0

    def pop() -> _Node:
        if not stack or stack[-1] is _MARK:
            raise pickle.UnpicklingError(f"opcode {op.name} at byte {pos} finds no object on the stack")
        return stack.pop()  # type: ignore[return-value]

    def charge(nodes: list[_Node]) -> None:
        nonlocal work
        work += sum(n.cost for n in nodes)
        if work > limit:
            raise pickle.UnpicklingError(
                f"hashing the keys and arguments up to byte {pos} would visit more than {limit} objects "
                "(nested shared tuples); the file is malformed or hostile"
            )

    def sized(nodes: list[_Node]) -> _Node:
        return _Node(min(limit + 1, 1 + sum(n.cost for n in nodes)))

    try:
        for op, arg, pos in pickletools.genops(data):
            count += 1
            name, before = op.name, op.stack_before
            if name in ("PUT", "BINPUT", "LONG_BINPUT"):
                if not (isinstance(arg, int) and 0 <= arg < count):
                    raise pickle.UnpicklingError(
                        f"memo index {_r(arg)} at byte {pos} is beyond the {count} opcodes read"
                    )
                memo[arg] = stack[-1] if stack else _Node()
                continue
            if name == "MEMOIZE":
                memo[len(memo)] = stack[-1] if stack else _Node()
                continue
            if name == "FRAME" and arg > len(data) - pos:
                raise pickle.UnpicklingError(f"frame of {arg} bytes at byte {pos} runs past the end of the data")
            if name == "STOP":
                break
            if pickletools.markobject in before:  # TUPLE, LIST, DICT, APPENDS, SETITEMS, ADDITEMS, FROZENSET, OBJ, ...
                if _MARK not in stack:
                    raise pickle.UnpicklingError(f"opcode {name} at byte {pos} finds no MARK")
                cut = len(stack) - 1 - stack[::-1].index(_MARK)
                items: list[_Node] = stack[cut + 1 :]  # type: ignore[assignment]
                del stack[cut:]
                below = [pop() for _ in range(before.index(pickletools.markobject))]
                if name in ("DICT", "SETITEMS"):
                    charge(items[0::2])
                elif name in ("FROZENSET", "ADDITEMS", "OBJ", "INST"):
                    charge(items)
                if below:  # APPENDS, SETITEMS, ADDITEMS: the container grows and stays on the stack
                    below[0].cost = min(limit + 1, below[0].cost + sum(n.cost for n in items))
                    stack.append(below[0])
                elif op.stack_after:
                    stack.append(sized(items) if name in ("TUPLE", "LIST", "DICT", "FROZENSET") else _Node())
                continue
            if name == "MARK":
                stack.append(_MARK)
            elif name in ("GET", "BINGET", "LONG_BINGET"):
                stack.append(memo.get(arg, _Node()))  # type: ignore[arg-type]
            elif name == "DUP":
                stack.append(stack[-1] if stack else _Node())
            elif name == "POP":
                if stack:
                    stack.pop()
            elif name in ("TUPLE1", "TUPLE2", "TUPLE3"):
                stack.append(sized([pop() for _ in before]))
            elif name in ("APPEND", "SETITEM"):
                value = pop()
                key = pop() if name == "SETITEM" else _Node(0)
                charge([key])
                target = pop()
                target.cost = min(limit + 1, target.cost + key.cost + value.cost)
                stack.append(target)
            elif name == "BUILD":
                pop()
            else:  # REDUCE, NEWOBJ, NEWOBJ_EX (their arguments may be hashed) and everything else
                popped = [pop() for _ in before]
                if name in ("REDUCE", "NEWOBJ", "NEWOBJ_EX"):
                    charge(popped)
                stack.extend(_Node() for _ in op.stack_after)
    except pickle.UnpicklingError as e:
        raise pickle.UnpicklingError(f"{where}: {e}") from None
    except Exception as e:  # pickletools' ValueError for truncated or unknown opcodes, ...
        raise pickle.UnpicklingError(f"{where}: not a loadable pickle ({type(e).__name__}: {e})") from None


class _Where:
    """Where a value sits in the file (``f.pkl['shapedirs'].a``), formatted only for messages."""

    __slots__ = ("parent", "step", "key")

    def __init__(self, step: str, parent: _Where | None = None, key: object = None) -> None:
        self.parent, self.step, self.key = parent, step, key

    def item(self, key: object) -> _Where:
        return _Where("", self, key)

    def attr(self, name: str) -> _Where:
        return _Where(f".{name}", self)

    def __str__(self) -> str:
        steps: list[str] = []
        node: _Where | None = self
        while node is not None:
            steps.append(node.step or f"[{_r(node.key)}]")
            node = node.parent
        return "".join(reversed(steps))


def _fail(where: _Where, message: str) -> pickle.UnpicklingError:
    return pickle.UnpicklingError(f"{where}: {message}")


class _Converter:
    """Replaces stand-ins by values, once per object (shared objects stay shared), refusing cycles."""

    def __init__(self, file: str, budget: _Budget) -> None:
        self.file = file
        self.budget = budget
        self.done: dict[int, object] = {}  # id of a loaded object -> its conversion
        self.active: set[int] = set()  # the objects being converted (a cycle comes back to one)

    def plain(self, obj: object, where: _Where, depth: int) -> object:
        if depth > _MAX_DEPTH:
            raise _fail(where, f"nested deeper than {_MAX_DEPTH} levels")
        if obj is _NDArrayType:
            return np.ndarray
        if isinstance(obj, _PendingScalar):
            return obj.value
        if isinstance(obj, _DTypeSpec):
            try:
                return obj.resolve()
            except pickle.UnpicklingError as e:
                raise _fail(where, str(e)) from None
        if not isinstance(obj, (_StandIn, _PendingArray, dict, list, tuple, set, frozenset)):
            return obj
        key = id(obj)
        if key in self.done:
            return self.done[key]
        if key in self.active:
            raise _fail(where, "cyclic reference; body-model files hold no cycles")
        self.active.add(key)
        try:
            out = self._convert(obj, where, depth + 1)
        finally:
            self.active.discard(key)
        self.done[key] = out
        return out

    def _convert(self, obj: object, where: _Where, depth: int) -> object:
        if isinstance(obj, _PendingArray):
            return self._array(obj, where, depth)
        if isinstance(obj, _ChumpyNode):
            return self._chumpy_value(obj, where, depth)
        if isinstance(obj, _SparseMatrix):
            return self._sparse_to_dense(obj, where, depth)
        if isinstance(obj, dict):
            out = {}
            for k, v in obj.items():
                key, value = self.plain(k, where.item(k), depth), self.plain(v, where.item(k), depth)
                try:
                    out[key] = value
                except TypeError:
                    raise _fail(where, f"a dict key became unhashable ({type(key).__name__})") from None
            return out
        if isinstance(obj, list):
            return [self.plain(v, where.item(i), depth) for i, v in enumerate(obj)]
        if isinstance(obj, tuple):
            return tuple(self.plain(v, where.item(i), depth) for i, v in enumerate(obj))
        try:  # set or frozenset
            return type(obj)(self.plain(v, where, depth) for v in obj)  # type: ignore[call-overload]
        except TypeError:
            raise _fail(where, "a set item became unhashable") from None

    def _array(self, pending: _PendingArray, where: _Where, depth: int) -> np.ndarray:
        if pending.value is not None:
            return pending.value
        if pending.items is None:
            raise _fail(where, "a numpy array without its pickled state")
        out = np.empty(len(pending.items), dtype=object)
        for i, item in enumerate(pending.items):
            out[i] = self.plain(item, where.item(i), depth)
        return out.reshape(pending.shape, order=pending.order)  # type: ignore[arg-type]

    def _charge(self, nbytes: int, what: str, where: _Where) -> None:
        try:
            self.budget.charge(nbytes, what)
        except pickle.UnpicklingError as e:
            raise _fail(where, str(e)) from None

    def _as_array(self, value: object, what: str, where: _Where) -> np.ndarray:
        """``np.asarray`` after counting (once per shared list) the items it would copy."""
        if isinstance(value, np.ndarray):
            return value
        counted: dict[int, int] = {}

        def count(x: object, level: int) -> int:
            if isinstance(x, np.ndarray):
                return x.size
            if not isinstance(x, (list, tuple)):
                return 1
            if level > _MAX_DEPTH:
                raise _fail(where, f"{what}: nested deeper than {_MAX_DEPTH} levels")
            if id(x) not in counted:
                counted[id(x)] = sum(count(y, level + 1) for y in x)
            return counted[id(x)]

        self._charge(16 * count(value, 0), what, where)
        return np.asarray(value)

    def _state(self, node: _StandIn, where: _Where) -> dict[str, object]:
        state = getattr(node, "state", None)
        if not isinstance(state, dict):
            raise _fail(where, f"{node.kind} has no pickled state dict, got {type(state).__name__}")
        return state

    def _term(self, node: _StandIn, key: str, where: _Where, depth: int) -> object:
        state = self._state(node, where)
        if key not in state:
            raise _fail(where, f"{node.kind} state lacks {_r(key)}")
        return self.plain(state[key], where.attr(key), depth)

    def _chumpy_value(self, node: _ChumpyNode, where: _Where, depth: int) -> np.ndarray:
        """Evaluate a chumpy node the way its ``compute_r`` does."""
        kind, state = node.kind, self._state(node, where)

        def term(key: str) -> object:
            return self._term(node, key, where, depth)

        def array(key: str) -> np.ndarray:
            return self._as_array(term(key), f"{kind}.{key}", where.attr(key))

        try:
            if kind == "chumpy.ch.Ch":
                return self._contiguous(array("x"), kind, where)
            a = array("a")
            if kind == "chumpy.reordering.Select":
                idx = array("idxs")
                if idx.dtype.kind not in "iu":
                    raise TypeError(f"idxs must be integers, got dtype {idx.dtype}")
                self._charge(idx.size * a.itemsize + (0 if a.flags.c_contiguous else a.nbytes), kind, where)
                value = a.ravel()[idx]
                if "preferred_shape" in state:
                    value = value.reshape(term("preferred_shape"))
            elif kind == "chumpy.reordering.transpose":
                value = np.transpose(a, axes=term("axes") if "axes" in state else None)
            else:  # chumpy.reordering.Reshape
                value = a.reshape(term("newshape"))
            return self._contiguous(value, kind, where)
        except (IndexError, ValueError, TypeError, OverflowError) as e:
            raise _fail(where, f"cannot evaluate {kind}: {e}") from None

    def _contiguous(self, value: np.ndarray, kind: str, where: _Where) -> np.ndarray:
        if value.flags.c_contiguous:
            return value
        self._charge(value.nbytes, kind, where)
        return np.ascontiguousarray(value)

    def _sparse_to_dense(self, node: _SparseMatrix, where: _Where, depth: int) -> np.ndarray:
        """Densify a pickled csc/csr/coo matrix (duplicates summed)."""
        state = self._state(node, where)

        def arr(key: str) -> np.ndarray:
            return self._as_array(self._term(node, key, where, depth), f"{node.kind}.{key}", where.attr(key))

        try:
            raw_shape = self._term(node, "_shape" if "_shape" in state else "shape", where, depth)
            shape = tuple(int(n) for n in raw_shape)  # type: ignore[union-attr]
        except (TypeError, ValueError, OverflowError, pickle.UnpicklingError):
            raise _fail(where, f"{node.kind} state has no valid '_shape'") from None
        if len(shape) != 2 or min(shape) < 0 or shape[0] * shape[1] > _MAX_DENSE:
            raise _fail(where, f"{node.kind} has an unsupported shape {shape}")
        data = arr("data").reshape(-1)
        if data.dtype.kind not in "biufc":
            raise _fail(where, f"{node.kind} data must be numeric, got dtype {data.dtype}")
        if node.fmt == "coo":
            if "coords" in state:
                coords = self._term(node, "coords", where, depth)
                if not isinstance(coords, (tuple, list)) or len(coords) != 2:
                    raise _fail(where, f"{node.kind} coords must be a (row, col) pair")
                rows, cols = (self._as_array(c, f"{node.kind}.coords", where).reshape(-1) for c in coords)
            else:
                rows, cols = arr("row").reshape(-1), arr("col").reshape(-1)
        else:
            rows, cols = self._compressed_coords(
                node, arr("indices").reshape(-1), arr("indptr").reshape(-1), shape, where
            )
        n = data.shape[0]
        for label, idx, size in (("row", rows, shape[0]), ("column", cols, shape[1])):
            if idx.shape != (n,) or idx.dtype.kind not in "iu" or (n and (idx.min() < 0 or idx.max() >= size)):
                raise _fail(where, f"{node.kind} has invalid {label} indices for shape {shape}")
        self._charge(shape[0] * shape[1] * data.dtype.itemsize, f"densifying {node.kind} of shape {shape}", where)
        dense = np.zeros(shape, dtype=data.dtype)
        np.add.at(dense, (rows, cols), data)
        return dense

    def _compressed_coords(
        self, node: _SparseMatrix, indices: np.ndarray, indptr: np.ndarray, shape: tuple[int, ...], where: _Where
    ) -> tuple[np.ndarray, np.ndarray]:
        major = shape[1] if node.fmt == "csc" else shape[0]
        if indptr.dtype.kind in "iu":
            indptr = indptr.astype(np.int64)  # a uint64 beyond int64 turns negative and fails the checks below
        ok = indptr.shape == (major + 1,) and indptr.dtype.kind in "iu" and indices.dtype.kind in "iu"
        ok = ok and int(indptr[0]) == 0 and int(indptr[-1]) == indices.shape[0] and bool(np.all(np.diff(indptr) >= 0))
        if not ok:
            raise _fail(where, f"{node.kind} has an invalid indptr for shape {shape}")
        self._charge(8 * indices.shape[0], f"{node.kind} indices", where)
        major_idx = np.repeat(np.arange(major), np.diff(indptr))
        return (indices, major_idx) if node.fmt == "csc" else (major_idx, indices)
