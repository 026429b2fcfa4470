"""The restricted unpickler: hostile pickles never run code; chumpy/scipy-era pickles load as arrays."""

from __future__ import annotations

import io
import os
import pickle
import re
import subprocess
import sys

import numpy as np
import pytest

from smpl_format import chumpy_ch, chumpy_node, chumpy_select, dumps, sparse_matrix
from unibody.io import safe_pickle


def _load(data: bytes) -> object:
    return safe_pickle.load(io.BytesIO(data))


def _hostile(target):
    """Protocol-0 text pickles that would create ``target`` if any global were resolved."""
    t = str(target)
    return {
        "os.system": f"cos\nsystem\n(S'touch {t}'\ntR.",
        "posix.system": f"cposix\nsystem\n(S'touch {t}'\ntR.",
        "builtins.eval": f"cbuiltins\neval\n(S'open({t!r}, \"w\").close()'\ntR.",
        "__builtin__.eval": f"c__builtin__\neval\n(S'open({t!r}, \"w\").close()'\ntR.",
        "subprocess.Popen": f"csubprocess\nPopen\n((lp0\nS'touch'\naS'{t}'\natR.",
        "builtins.open": f"cbuiltins\nopen\n(S'{t}'\nS'w'\ntR.",  # a REDUCE that creates a file
        "__builtin__.getattr": "c__builtin__\ngetattr\n(cnumpy\nndarray\nS'tofile'\ntR.",
        "numpy.load": f"cnumpy\nload\n(S'{t}'\ntR.",
    }


@pytest.mark.parametrize(
    "name",
    [
        "os.system",
        "posix.system",
        "builtins.eval",
        "__builtin__.eval",
        "subprocess.Popen",
        "builtins.open",
        "__builtin__.getattr",
        "numpy.load",
    ],
)
def test_hostile_globals_are_refused_without_side_effect(tmp_path, name):
    target = tmp_path / "pwned"
    payload = _hostile(target)[name].encode()
    with pytest.raises(pickle.UnpicklingError, match=rf"refusing global {name}\b"):
        _load(payload)
    assert not target.exists()
    if name == "builtins.open":  # the test can fail: the stock unpickler does create the file
        pickle.loads(payload).close()
        assert target.exists()


class _Evil:
    def __init__(self, func, args):
        self.func, self.args = func, args

    def __reduce__(self):
        return self.func, self.args


@pytest.mark.parametrize("protocol", range(pickle.HIGHEST_PROTOCOL + 1))
@pytest.mark.parametrize("how", ["system", "popen", "eval"])
def test_reduce_payloads_of_every_protocol_are_refused(tmp_path, protocol, how):
    target = tmp_path / "pwned"
    func, args = {
        "system": (os.system, (f"touch {target}",)),
        "popen": (subprocess.Popen, (["touch", str(target)],)),
        "eval": (eval, (f"open({str(target)!r}, 'w').close()",)),
    }[how]
    data = pickle.dumps({"v_template": np.zeros(3), "evil": _Evil(func, args)}, protocol=protocol)
    with pytest.raises(pickle.UnpicklingError, match="refusing global"):
        _load(data)
    assert not target.exists()


@pytest.mark.parametrize(
    ("payload", "match"),
    [
        # copy_reg._reconstructor is allowed for stand-ins only, not to build arbitrary classes
        (b"ccopy_reg\n_reconstructor\n(c__builtin__\nset\nc__builtin__\nobject\nNtR.", "only the chumpy/scipy"),
        (b"ccopy_reg\n_reconstructor\n(cchumpy.ch\nCh\nc__builtin__\nset\nNtR.", "only the chumpy/scipy"),
        # _codecs.encode is allowed with latin-1 only
        (b"c_codecs\nencode\n(S'abc'\nS'rot13'\ntR.", "only \\(str, 'latin1'\\)"),
        (b"cnumpy.testing._private.utils\nrunstring\n(S'1'\n(dtR.", "refusing global numpy.testing"),
        (b"cchumpy.ch_ops\nadd\n)\x81.", "refusing global chumpy.ch_ops.add"),
        (b"cscipy.sparse.linalg\neigs\n.", "refusing global scipy.sparse.linalg.eigs"),
        (b"(S'true'\nios\nsystem\n.", "refusing global os.system"),  # the INST opcode
    ],
)
def test_misuse_of_allowed_names_is_refused(payload, match):
    with pytest.raises(pickle.UnpicklingError, match=match):
        _load(payload)


def test_persistent_ids_are_refused():
    with pytest.raises(pickle.UnpicklingError, match="persistent ids"):
        _load(b"P1\n.")


def _reference_payload(legacy):
    rng = np.random.default_rng(3)
    full = rng.normal(size=(5, 3, 4))
    dense = np.zeros((4, 7))
    dense[[0, 1, 1, 3], [2, 0, 6, 6]] = [1.5, -2.0, 0.25, 3.0]
    payload = {
        "x": chumpy_ch(full[..., 0]),
        "select": chumpy_select(full, 2),
        "transpose": chumpy_node("transpose", a=chumpy_ch(full[:, :, 0]), axes=None),
        "reshape": chumpy_node("Reshape", a=chumpy_ch(full), newshape=(15, 4)),
        "csc": sparse_matrix(dense, "csc", legacy=legacy),
        "csr": sparse_matrix(dense, "csr", legacy=legacy),
        "coo": sparse_matrix(dense, "coo", legacy=legacy, coords=not legacy),
        "plain": [np.arange(3, dtype=np.int32), ("lbs", 2.5, None)],
    }
    expected = {
        "x": full[..., 0],
        "select": full[..., :2],
        "transpose": full[:, :, 0].T,
        "reshape": full.reshape(15, 4),
        "csc": dense,
        "csr": dense,
        "coo": dense,
    }
    return payload, expected


@pytest.mark.parametrize("protocol", [0, 2, 4, 5])
@pytest.mark.parametrize("legacy", [True, False], ids=["py2-names", "modern-names"])
def test_chumpy_and_scipy_era_pickles_load_as_arrays(protocol, legacy):
    payload, expected = _reference_payload(legacy)
    before = set(sys.modules)
    out = _load(dumps(payload, protocol=protocol, legacy=legacy))
    assert isinstance(out, dict) and set(out) == set(payload)
    for key, want in expected.items():
        assert type(out[key]) is np.ndarray, key
        assert out[key].shape == want.shape and np.array_equal(out[key], want), key
    assert np.array_equal(out["plain"][0], np.arange(3)) and out["plain"][0].dtype == np.int32
    assert out["plain"][1] == ("lbs", 2.5, None)
    added = {m.split(".")[0] for m in set(sys.modules) - before}
    assert not added & {"chumpy", "scipy"}


def test_sparse_duplicates_are_summed_like_scipy():
    coo = sparse_matrix(np.zeros((2, 3)), "coo")
    coo.data, coo.row, coo.col = np.array([1.0, 2.0, 4.0]), np.array([1, 1, 0]), np.array([2, 2, 0])
    out = _load(dumps({"m": coo}))
    assert np.array_equal(out["m"], [[4.0, 0.0, 0.0], [0.0, 0.0, 3.0]])


def test_old_scipy_shape_attribute_and_object_arrays():
    m = sparse_matrix(np.eye(3), "csr")
    m.shape = m.__dict__.pop("_shape")  # SciPy before 0.14 kept a plain ``shape`` attribute
    holder = np.empty(2, dtype=object)
    holder[0], holder[1] = m, "tag"
    out = _load(dumps({"holder": holder}, protocol=4, legacy=False))
    assert out["holder"].dtype == object and out["holder"].shape == (2,)
    assert np.array_equal(out["holder"][0], np.eye(3)) and out["holder"][1] == "tag"


def test_file_paths_are_named_in_errors(tmp_path):
    path = tmp_path / "SMPL_NEUTRAL.pkl"
    path.write_bytes(b"cos\nsystem\n(S'true'\ntR.")
    with pytest.raises(pickle.UnpicklingError, match=r"SMPL_NEUTRAL\.pkl: refusing global os\.system"):
        safe_pickle.load(path)
    path.write_bytes(dumps({"a": np.ones(2)})[:-20])
    with pytest.raises(pickle.UnpicklingError, match=r"SMPL_NEUTRAL\.pkl: (pickle data was truncated|not a loadable)"):
        safe_pickle.load(str(path))
    with pytest.raises(FileNotFoundError):
        safe_pickle.load(tmp_path / "missing.pkl")
    path.write_bytes(dumps({"a": chumpy_ch(np.ones(2))}))
    with path.open("rb") as f:
        assert np.array_equal(safe_pickle.load(f)["a"], np.ones(2))


def _bad_states():
    sel = chumpy_select(np.ones((2, 3, 2)), 1)
    sel.idxs = sel.idxs.astype(np.float64)
    out_of_range = chumpy_select(np.ones((2, 3, 2)), 1)
    out_of_range.idxs = out_of_range.idxs + 100
    no_x = chumpy_ch(np.ones(2))
    del no_x.x
    indptr = sparse_matrix(np.eye(3), "csc")
    indptr.indptr = indptr.indptr[:-1]
    rows = sparse_matrix(np.eye(3), "coo")
    rows.row = rows.row + 5
    no_shape = sparse_matrix(np.eye(3), "csr")
    del no_shape._shape
    huge = sparse_matrix(np.eye(3), "csr")
    huge._shape = (10**6, 10**6)
    return {
        "float idxs": (sel, r"\['m'\]: cannot evaluate chumpy.reordering.Select: idxs must be integers"),
        "idxs out of range": (out_of_range, "cannot evaluate chumpy.reordering.Select"),
        "Ch without x": (no_x, r"chumpy.ch.Ch state lacks 'x'"),
        "bad indptr": (indptr, "invalid indptr"),
        "row out of range": (rows, "invalid row indices"),
        "no shape": (no_shape, "has no valid '_shape'"),
        "huge": (huge, "unsupported shape"),
    }


@pytest.mark.parametrize("case", list(_bad_states()))
def test_malformed_states_raise(case):
    obj, match = _bad_states()[case]
    with pytest.raises(pickle.UnpicklingError, match=match):
        _load(dumps({"m": obj}))


def test_cycles_and_deep_nesting_raise():
    cyclic: list = []
    cyclic.append(cyclic)
    with pytest.raises(pickle.UnpicklingError, match="cyclic reference"):
        _load(pickle.dumps(cyclic))
    node = chumpy_ch(np.ones(1))
    for _ in range(80):
        node = chumpy_node("Reshape", a=node, newshape=(1,))
    with pytest.raises(pickle.UnpicklingError, match="nested deeper than 64"):
        _load(dumps(node))


def test_standins_refuse_construction_with_arguments():
    # REDUCE on an allowed stand-in class with arguments (no class of the real files is called so)
    with pytest.raises(pickle.UnpicklingError, match="not a loadable pickle"):
        _load(b"cchumpy.ch\nCh\n(S'x'\ntR.")


# --- arrays are rebuilt only from checked dtype, shape and bytes (no file-supplied buffers) ----------------------

_ISOLATED = """
import importlib.util, resource, sys
resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))
spec = importlib.util.spec_from_file_location("safe_pickle", sys.argv[1])
safe_pickle = importlib.util.module_from_spec(spec)
spec.loader.exec_module(safe_pickle)
try:
    out = safe_pickle.load(sys.argv[2])
except BaseException as e:
    print("ERR", type(e).__name__, str(e)[:300])
else:
    if sys.argv[3] == "repr":
        print("OK", repr(out)[:200])  # touches every object of an array: forged pointers crash here
    else:
        print("OK", type(out).__name__)
"""


def _load_isolated(tmp_path, data: bytes, *, touch: bool = False, timeout: float = 60.0):
    """Load in a child process (3 GiB address space): a crash, hang or blow-up fails the test, not pytest."""
    path = tmp_path / "hostile.pkl"
    path.write_bytes(data)
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    try:
        proc = subprocess.run(
            [sys.executable, "-c", _ISOLATED, safe_pickle.__file__, str(path), "repr" if touch else "type"],
            capture_output=True,
            text=True,
            timeout=timeout,
            env=env,
        )
    except subprocess.TimeoutExpired:
        pytest.fail(f"loading {len(data)} bytes did not finish within {timeout} s")
    assert proc.returncode == 0, f"the loader crashed (exit {proc.returncode}): {proc.stderr[-500:]}"
    return proc.stdout.strip()


def _p0_dtype(code: str, order: str = "|", names: str = "N", fields: str = "N", elsize: int = -1, flags: int = 0):
    """Protocol-0 text of ``numpy.dtype(code)`` with a hand-written ``__setstate__`` tuple."""
    return (
        f"cnumpy\ndtype\n(S'{code}'\nI0\nI1\ntR(I3\nS'{order}'\nN{names}{fields}I{elsize}\nI-1\nI{flags}\ntb"
    ).encode()


_O8 = _p0_dtype("O8", flags=63)


def _record_dtype() -> bytes:
    """``dtype('V8')`` set to one object field named 'a' at offset 0, with its flags saying 'no objects'."""
    return b"cnumpy\ndtype\n(S'V8'\nI0\nI1\ntR(I3\nS'|'\nN(S'a'\nt(dS'a'\n(" + _O8 + b"I0\ntsI8\nI1\nI0\ntb"


def _reconstruct_p0(dtype: bytes, shape: str, raw: bytes, fortran: str = "I00\n") -> bytes:
    head = b"cnumpy.core.multiarray\n_reconstruct\n(cnumpy\nndarray\n(I0\ntC\x01btR(I1\n(" + shape.encode() + b"t"
    return head + dtype + fortran.encode() + b"C" + bytes([len(raw)]) + raw + b"tb."


_FORGED = b"AAAAAAAA"  # read as a PyObject* by an object array built over it


def _segfault_payloads() -> dict[str, bytes]:
    return {
        # numpy.ndarray(shape, dtype, buffer): an object array over file bytes (crashed with exit 139)
        "ndarray over buffer": b"cnumpy\nndarray\n((I1\nt" + _O8 + b"C\x08" + _FORGED + b"tR.",
        # _reconstruct + a dtype whose state hides an object field + raw bytes (crashed with exit 139)
        "record dtype hiding an object field": _reconstruct_p0(_record_dtype(), "I1\n", _FORGED),
        # the same through protocol 5's _frombuffer and numpy scalars
        "object _frombuffer": b"cnumpy.core.numeric\n_frombuffer\n(C\x08" + _FORGED + _O8 + b"(I1\ntS'C'\ntR.",
        "object scalar": b"cnumpy.core.multiarray\nscalar\n(" + _O8 + b"C\x08" + _FORGED + b"tR.",
    }


@pytest.mark.parametrize("case", list(_segfault_payloads()))
def test_object_arrays_over_file_bytes_are_refused_without_crashing(tmp_path, case):
    out = _load_isolated(tmp_path, _segfault_payloads()[case], touch=True)
    assert out.startswith(f"ERR UnpicklingError {tmp_path / 'hostile.pkl'}: "), out
    assert any(s in out for s in ("object", "numpy.ndarray may not be called", "only a byte order may be set")), out


@pytest.mark.parametrize(
    ("payload", "match"),
    [
        (b"cnumpy\nndarray\n((I2\ntS'f8'\ntR.", "numpy.ndarray may not be called"),
        (_reconstruct_p0(_p0_dtype("f8", "<"), "I-1\n", b""), "non-negative integer sizes"),
        (
            _reconstruct_p0(_p0_dtype("f8", "<"), "I2\n", b"\0" * 8),
            r"shape \(2,\) of float64 needs 16 bytes, the file gives 8",
        ),
        (_reconstruct_p0(_p0_dtype("f8", "<"), "I1\n" * 33, b""), "at most 32 sizes"),
        (_reconstruct_p0(_p0_dtype("M8", "<"), "I1\n", b"\0" * 8), "plain type code"),
        (_reconstruct_p0(_p0_dtype("f8", "<"), "F1.0\n", b"\0" * 8), "non-negative integer sizes"),
        (_reconstruct_p0(_p0_dtype("f8", "<", elsize=4), "I1\n", b"\0" * 8), "item size 4 does not match 8"),
        (_reconstruct_p0(_p0_dtype("f8", "<"), "I1\n", b"\0" * 8, fortran="I7\n"), "fortran flag"),
        (_reconstruct_p0(_O8, "I1\n", b"\0" * 8), "must be pickled as a list of 1 items"),
        (b"cnumpy.core.multiarray\n_reconstruct\n(c__builtin__\nobject\n(I0\ntC\x01btR.", "only \\(numpy.ndarray"),
        (
            b"cnumpy.core.multiarray\nscalar\n(" + _p0_dtype("f8", "<") + b"C\x04abcdtR.",
            "needs 8 bytes, the file gives 4",
        ),
        (
            b"cnumpy.core.numeric\n_frombuffer\n((I1\nt" + _p0_dtype("f8") + b"(I1\ntS'C'\ntR.",
            "expected raw data as bytes",
        ),
        (
            b"cnumpy.core.multiarray\nscalar\n(" + _p0_dtype("f8", "<") + b"C\x08abcdefghtR(tb.",
            "may not set state on a scalar",
        ),
    ],
)
def test_array_states_are_checked(payload, match):
    with pytest.raises(pickle.UnpicklingError, match=match):
        _load(payload)


@pytest.mark.parametrize("protocol", [0, 2, 4, 5])
@pytest.mark.parametrize("legacy", [True, False], ids=["py2-names", "modern-names"])
def test_array_layouts_dtypes_and_scalars_round_trip(protocol, legacy):
    rng = np.random.default_rng(5)
    payload = {
        "fortran": np.asfortranarray(rng.normal(size=(3, 4))),
        "big_endian": np.arange(6, dtype=">i4").reshape(2, 3),
        "complex": (rng.normal(size=3) + 1j).astype(np.complex64),
        "bool": np.array([True, False, True]),
        "empty": np.zeros((0, 3)),
        "bytes": np.array([b"ab", b"c"]),
        "text": np.array(["lbs", "x"]),
        "scalars": [np.float64(2.5), np.int32(-7), np.bool_(True), np.float32(0.5)],
        "zero_d": np.array(3.0),
    }
    out = _load(dumps(payload, protocol=protocol, legacy=legacy))
    for key in ("fortran", "big_endian", "complex", "bool", "empty", "bytes", "text", "zero_d"):
        assert type(out[key]) is np.ndarray and out[key].dtype == payload[key].dtype, key
        assert out[key].shape == payload[key].shape and np.array_equal(out[key], payload[key]), key
        assert out[key].flags.writeable, key
    assert out["fortran"].flags.f_contiguous
    for got, want in zip(out["scalars"], payload["scalars"], strict=True):
        assert type(got) is type(want) and got == want


def test_arrays_never_share_memory_with_the_file():
    data = bytearray(pickle.dumps(np.arange(4.0), protocol=5))
    out = _load(bytes(data))
    out[0] = 99.0  # a writeable copy: neither the pickle bytes nor a cached buffer change
    assert np.array_equal(_load(bytes(data)), np.arange(4.0))


# --- bounded time and memory ------------------------------------------------------------------------------------


def _shared_lists(levels: int) -> bytes:
    x: list = []
    for _ in range(levels):
        x = [x, x]
    return pickle.dumps(x, protocol=2)


def test_shared_nested_lists_convert_in_linear_time(tmp_path):
    data = _shared_lists(60)  # 2**60 paths: the old converter walked them as a tree and never finished
    assert len(data) < 500
    assert _load_isolated(tmp_path, data, timeout=60) == "OK list"
    out = _load(data)
    assert out[0] is out[1] and out[0][0] is out[0][1]  # shared objects stay shared


def _shared_tuple_key(levels: int) -> bytes:
    """``{t: 1}`` with t = (t', t'), t' = (t'', t''), ...: hashing t visits 2**levels tuples."""
    body = b"\x80\x02}N"
    for i in range(levels):
        body += b"q" + bytes([i]) + b"0h" + bytes([i]) + b"h" + bytes([i]) + b"\x86"  # PUT, POP, (GET, GET)
    return body + b"K\x01s."


def test_keys_of_shared_nested_tuples_are_refused_before_hashing(tmp_path):
    data = _shared_tuple_key(60)
    assert len(data) < 500
    out = _load_isolated(tmp_path, data, timeout=60)
    assert out.startswith("ERR UnpicklingError") and "nested shared tuples" in out, out
    assert _load(_shared_tuple_key(8)) == {_nested_pairs(8): 1}  # small ones still load


def _nested_pairs(levels: int) -> object:
    t: object = None
    for _ in range(levels):
        t = (t, t)
    return t


def _huge_sparse() -> bytes:
    m = sparse_matrix(np.eye(1), "coo")
    m._shape = (1 << 14, 1 << 14)  # 2**28 entries: within the old entry cap, 8 GiB as complex256
    m.data = np.ones(1, dtype=np.clongdouble)
    return dumps({"J_regressor": m}, protocol=2, legacy=False)


def _stride0_ch() -> bytes:
    """A chumpy Ch over ``ndarray((2**30,), 'f8', buffer=8 bytes, strides=(0,))``: 8 GiB once made contiguous."""
    view = b"cnumpy\nndarray\n((J\x00\x00\x00@t" + _p0_dtype("f8", "<") + b"C\x08" + b"\0" * 8 + b"K\x00(K\x00ttR"
    return b"\x80\x02cchumpy.ch\nCh\n)\x81}X\x01\x00\x00\x00x" + view + b"sb."


@pytest.mark.parametrize(
    ("case", "match"),
    [
        ("sparse 8 GiB", "over the budget of this"),
        ("stride-0 view", "numpy.ndarray may not be called"),
        ("bytes(10**10)", r"only bytes\(\) is allowed"),
        ("memo index 2**28", "memo index 268435456 at byte 3 is beyond"),
        ("BINBYTES8 of 2**40", "not a loadable pickle"),
    ],
)
def test_small_files_cannot_ask_for_gigabytes(tmp_path, case, match):
    data = {
        "sparse 8 GiB": _huge_sparse,
        "stride-0 view": _stride0_ch,
        "bytes(10**10)": lambda: b"cbuiltins\nbytes\n(L10000000000L\ntR.",
        "memo index 2**28": lambda: b"\x80\x02]r\x00\x00\x00\x10.",
        "BINBYTES8 of 2**40": lambda: b"\x80\x05\x8e\x00\x00\x00\x00\x00\x01\x00\x00abc.",
    }[case]()
    assert len(data) < 600
    out = _load_isolated(tmp_path, data)
    assert out.startswith("ERR UnpicklingError"), out
    assert re.search(match, out), out


def test_budget_scales_with_the_file():
    big = np.zeros((300, 300))  # 720 kB of file: densifying a 2000 x 2000 sparse matrix (32 MB) stays allowed
    m = sparse_matrix(np.eye(3), "csr")
    m._shape = (2000, 2000)
    m.indptr = np.concatenate([[0, 1, 2, 3], np.full(1997, 3)]).astype(np.int32)
    out = _load(dumps({"pad": big, "m": m}))
    assert out["m"].shape == (2000, 2000) and out["m"].sum() == 3
    m._shape, m.data = (6000, 6000), np.ones(3, dtype=np.complex128)  # 576 MB from a 720 kB file: refused
    m.indptr = np.concatenate([[0, 1, 2, 3], np.full(5997, 3)]).astype(np.int32)
    with pytest.raises(pickle.UnpicklingError, match=r"\['m'\]: densifying .* needs 576000000 bytes, over the budget"):
        _load(dumps({"pad": big, "m": m}))
