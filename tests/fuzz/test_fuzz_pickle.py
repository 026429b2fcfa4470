"""Property: any bytes given to ``safe_pickle.load`` give plain data or ``pickle.UnpicklingError``.

Never another exception type, a crash, a hang or a MemoryError. Loads run in one child process
(3 GiB address space, a time limit per input) so that a segfault or a hang fails the test with
the input instead of killing pytest. Inputs: random bytes, truncations and byte edits of valid
SMPL-style pickles (protocols 0-5, chumpy and scipy stand-ins), and opcode sequences built
from the allow-listed globals. Seeded and bounded (profiles in tests/conftest.py).
"""

from __future__ import annotations

import os
import pickle
import select
import struct
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from smpl_format import chumpy_ch, chumpy_select, dumps, sparse_matrix
from unibody.io import safe_pickle

_WORKER = r"""
import importlib.util, io, pickle, resource, struct, sys
import numpy as np
resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))
spec = importlib.util.spec_from_file_location("safe_pickle", sys.argv[1])
safe_pickle = importlib.util.module_from_spec(spec)
spec.loader.exec_module(safe_pickle)
PLAIN = (str, bytes, int, float, complex, bool, type(None), np.generic, np.dtype, type)

def check(x, seen):
    if isinstance(x, PLAIN) or id(x) in seen:
        return
    seen.add(id(x))
    if isinstance(x, np.ndarray):
        assert x.flags.owndata or x.base is None or isinstance(x.base, np.ndarray), "array over a foreign buffer"
        assert x.nbytes == x.size * x.dtype.itemsize and x.ndim <= 32
        if x.dtype.hasobject:
            assert x.dtype == np.dtype("O"), f"dtype {x.dtype} mixes objects"
            for item in x.reshape(-1):
                check(item, seen)
        return
    if isinstance(x, dict):
        for k, v in x.items():
            check(k, seen); check(v, seen)
        return
    if isinstance(x, (list, tuple, set, frozenset)):
        for v in x:
            check(v, seen)
        return
    if callable(x):
        return  # an allow-listed function or class named by the file
    raise AssertionError(f"unexpected {type(x).__name__} in the result")

out = sys.stdout
stdin = sys.stdin.buffer
while True:
    head = stdin.read(4)
    if len(head) < 4:
        break
    data = stdin.read(struct.unpack("<I", head)[0])
    try:
        value = safe_pickle.load(io.BytesIO(data))
        check(value, set())
        line = "OK"
    except pickle.UnpicklingError as e:
        line = "UnpicklingError" if str(e).startswith("<stream>") else "BAD message without the file name: " + str(e)
    except BaseException as e:
        line = f"BAD {type(e).__name__}: {e}"
    out.write(line.replace("\n", " ")[:500] + "\n")
    out.flush()
"""

_TIMEOUT = 20.0


class _Worker:
    def __init__(self) -> None:
        self.proc: subprocess.Popen | None = None

    def start(self) -> None:
        env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
        self.proc = subprocess.Popen(
            [sys.executable, "-c", _WORKER, safe_pickle.__file__],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            env=env,
        )

    def load(self, data: bytes) -> str:
        if self.proc is None or self.proc.poll() is not None:
            self.start()
        proc = self.proc
        try:
            proc.stdin.write(struct.pack("<I", len(data)) + data)
            proc.stdin.flush()
        except BrokenPipeError:
            pass
        ready, _, _ = select.select([proc.stdout], [], [], _TIMEOUT)
        if not ready:
            self.stop()
            return f"HANG: no answer within {_TIMEOUT} s"
        line = proc.stdout.readline().decode().strip()
        if not line:
            code = proc.wait()
            self.proc = None
            return f"CRASH: the loader died (exit {code})"
        return line

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait()
            self.proc = None


@pytest.fixture(scope="module")
def worker():
    w = _Worker()
    yield w
    w.stop()


def _assert_documented(worker: _Worker, data: bytes) -> None:
    result = worker.load(data)
    assert result in ("OK", "UnpicklingError"), f"{result} for input {data[:300]!r}"


def _seed_payload(kind: int) -> object:
    rng = np.random.default_rng(kind)
    dense = np.zeros((3, 6))
    dense[[0, 1, 2], [1, 3, 5]] = [0.5, 0.25, 1.0]
    return {
        "v_template": chumpy_ch(rng.normal(size=(6, 3))) if kind % 2 else rng.normal(size=(6, 3)),
        "shapedirs": chumpy_select(rng.normal(size=(6, 3, 4)), 2),
        "J_regressor": sparse_matrix(dense, ("csc", "csr", "coo")[kind % 3], legacy=kind < 3),
        "weights": np.asfortranarray(rng.random((6, 2))),
        "kintree_table": np.array([[4294967295, 0], [0, 1]], dtype=np.uint32),
        "f": np.array([[0, 1, 2], [3, 4, 5]], dtype=np.uint32),
        "bs_style": "lbs",
        "scale": np.float64(1.5),
        "shared": [("a", 1)] * 2,
    }


SEEDS = [dumps(_seed_payload(k), protocol=p, legacy=k < 3) for k in range(4) for p in (0, 2, 4, 5)]


def test_seed_files_load(worker):
    for data in SEEDS:
        assert worker.load(data) == "OK"


@given(st.binary(max_size=300))
def test_random_bytes(worker, data):
    _assert_documented(worker, data)


@given(st.data())
def test_mutated_valid_files(worker, data):
    buf = bytearray(data.draw(st.sampled_from(SEEDS), label="seed"))
    for _ in range(data.draw(st.integers(1, 4), label="edits")):
        kind = data.draw(st.sampled_from(["flip", "truncate", "insert", "delete"]))
        pos = data.draw(st.integers(0, len(buf) - 1)) if buf else 0
        if kind == "flip" and buf:
            buf[pos] = data.draw(st.integers(0, 255))
        elif kind == "truncate":
            del buf[pos:]
        elif kind == "insert":
            buf[pos:pos] = data.draw(st.binary(min_size=1, max_size=9))
        else:
            del buf[pos : pos + data.draw(st.integers(1, 9))]
    _assert_documented(worker, bytes(buf))


_GLOBALS = [
    b"numpy\nndarray",
    b"numpy\ndtype",
    b"numpy.core.multiarray\n_reconstruct",
    b"numpy.core.multiarray\nscalar",
    b"numpy._core.numeric\n_frombuffer",
    b"builtins\nset",
    b"builtins\nbytes",
    b"builtins\nobject",
    b"copy_reg\n_reconstructor",
    b"_codecs\nencode",
    b"chumpy.ch\nCh",
    b"chumpy.reordering\nSelect",
    b"chumpy.reordering\nReshape",
    b"scipy.sparse._csr\ncsr_matrix",
    b"scipy.sparse._coo\ncoo_matrix",
]


def _op() -> st.SearchStrategy[bytes]:
    def counted(op: bytes, fmt: str, body: bytes) -> bytes:
        return op + struct.pack(fmt, len(body)) + body

    return st.one_of(
        st.sampled_from(_GLOBALS).map(lambda g: b"c" + g + b"\n"),
        st.sampled_from(
            [
                b"(",
                b"t",
                b")",
                b"\x85",
                b"\x86",
                b"\x87",
                b"]",
                b"}",
                b"l",
                b"d",
                b"a",
                b"e",
                b"s",
                b"u",
                b"R",
                b"b",
                b"\x81",
                b"N",
                b"\x88",
                b"\x89",
                b"0",
                b"2",
                b"1",
                b"\x94",
            ]
        ),  # fmt: skip
        st.integers(-(2**70), 2**70).map(lambda n: b"I" + str(n).encode() + b"\n"),
        st.integers(0, 2**32 - 1).map(lambda n: b"J" + struct.pack("<I", n)),
        st.sampled_from([b"f8", b"<f8", b"O8", b"V8", b"i4", b"c32", b"S3", b"U2", b"b", b"C", b"F", b"latin1"]).map(
            lambda s: counted(b"U", "<B", s)
        ),
        st.binary(max_size=24).map(lambda b: counted(b"C", "<B", b)),
        st.integers(0, 6).map(lambda i: b"q" + bytes([i])),
        st.integers(0, 6).map(lambda i: b"h" + bytes([i])),
        st.sampled_from([b"r\x00\x00\x00\x10", b"\x8e" + struct.pack("<Q", 2**40), b"\x95" + struct.pack("<Q", 2**40)]),
    )


@settings(max_examples=60)
@given(st.lists(_op(), min_size=1, max_size=24))
def test_crafted_opcode_sequences(worker, ops):
    _assert_documented(worker, b"\x80\x02" + b"".join(ops) + b".")


def test_the_worker_reports_crashes_and_hangs(worker):
    # the harness itself can fail: a crash and a non-UnpicklingError are reported as such
    assert worker.load(pickle.dumps({"a": np.ones(2)})) == "OK"
    worker.proc.kill()
    worker.proc.wait()
    assert worker.load(b"N.").startswith(("CRASH", "OK"))


def _text(s: str) -> bytes:
    return b"U" + bytes([len(s)]) + s.encode()


def _dtype_ops(code: str, order: str, fields: bool) -> bytes:
    """``dtype(code)`` plus a state: a byte order, or (``fields``) one object field hidden behind flags 0."""
    head = b"cnumpy\ndtype\n(" + _text(code) + b"\x89\x88tR"
    if not fields:
        return head + b"(K\x03" + _text(order) + b"NNNJ\xff\xff\xff\xffJ\xff\xff\xff\xffK\x00tb"
    obj = (
        b"cnumpy\ndtype\n("
        + _text("O8")
        + b"\x89\x88tR(K\x03"
        + _text("|")
        + b"NNNJ\xff\xff\xff\xffJ\xff\xff\xff\xffK?tb"
    )
    return (
        head
        + b"(K\x03"
        + _text("|")
        + b"N("
        + _text("a")
        + b"t}"
        + _text("a")
        + b"("
        + obj
        + b"K\x00tsK\x08K\x01K\x00tb"
    )


_CODES = ["f8", "i4", "u1", "b1", "c16", "c32", "S4", "U2", "O8", "V8", "M8", "f8,f8", ""]


@given(
    kind=st.sampled_from(["ndarray", "reconstruct", "frombuffer", "scalar"]),
    code=st.sampled_from(_CODES),
    order=st.sampled_from(["<", ">", "|", "="]),
    fields=st.booleans(),
    shape=st.lists(st.one_of(st.integers(-2, 4), st.sampled_from([2**31, 2**40, 2**62])), max_size=4),
    raw=st.binary(max_size=64),
    fortran=st.booleans(),
)
def test_crafted_arrays(worker, kind, code, order, fields, shape, raw, fortran):
    """Array, scalar and dtype reconstructors with arbitrary dtype codes, states, shapes and bytes."""
    dtype = _dtype_ops(code, order, fields)
    shp = b"(" + b"".join(b"\x8a" + bytes([8]) + n.to_bytes(8, "little", signed=True) for n in shape) + b"t"
    data = b"C" + bytes([len(raw)]) + raw
    if kind == "ndarray":  # ndarray(shape, dtype, buffer): what crashed the old loader for object dtypes
        body = b"cnumpy\nndarray\n(" + shp + dtype + data + b"tR"
    elif kind == "reconstruct":
        body = b"cnumpy.core.multiarray\n_reconstruct\n(cnumpy\nndarray\n(K\x00tC\x01btR"
        body += b"(K\x01" + shp + dtype + (b"\x88" if fortran else b"\x89") + data + b"tb"
    elif kind == "frombuffer":
        body = b"cnumpy._core.numeric\n_frombuffer\n(" + data + dtype + shp + _text("F" if fortran else "C") + b"tR"
    else:
        body = b"cnumpy.core.multiarray\nscalar\n(" + dtype + data + b"tR"
    _assert_documented(worker, b"\x80\x02" + body + b".")
