"""Property: any bytes given to ``read_markers`` (C3D or npz) give a valid sequence or a ValueError naming the file.

Inputs: random bytes, truncations and byte flips of a small valid C3D (written by
``write_c3d``) and of a valid marker npz (``write_npz``). Each parse runs in one worker process
(started once per module), so a crash in the C3D library shows as a failed test, not a dead run.
The answer must be a :class:`MarkerSequence` whose points are finite or NaN (missing), or a
ValueError whose message names the file. Seeded and bounded (tests/conftest.py profiles).
"""

from __future__ import annotations

import multiprocessing
import tempfile
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from unibody.mocap.c3d import MarkerSequence, read_markers, write_c3d, write_npz

pytest.importorskip("ezc3d")

_DIR = Path(tempfile.mkdtemp(prefix="fuzz_c3d_"))


def _valid(suffix: str) -> bytes:
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(4, 3, 3))
    pts[1, 2] = np.nan
    seq = MarkerSequence(pts, ("A", "B", "*2"), ("S", "S", ""), 100.0)
    path = _DIR / f"valid{suffix}"
    (write_c3d if suffix == ".c3d" else write_npz)(path, seq)
    return path.read_bytes()


VALID = {s: _valid(s) for s in (".c3d", ".npz")}


@pytest.fixture(scope="module")
def worker():
    pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"))
    yield pool
    pool.shutdown()


_count = iter(range(10**9))


def _check(worker, data: bytes, suffix: str) -> None:
    path = _DIR / f"case{next(_count)}{suffix}"
    path.write_bytes(data)
    try:
        seq = worker.submit(read_markers, path).result(timeout=60)
    except BrokenProcessPool:  # pragma: no cover - the failure this test exists to catch
        pytest.fail(f"the reader crashed the process on {len(data)} bytes: {data[:64]!r}...")
    except ValueError as e:
        assert str(path) in str(e), repr(e)
        return
    finally:
        path.unlink(missing_ok=True)
    assert isinstance(seq, MarkerSequence)
    pts = seq.points
    assert pts.ndim == 3 and pts.shape[1] == len(seq.labels) == len(seq.subjects)
    assert not np.isinf(pts).any() and np.isfinite(seq.rate) and seq.rate > 0


suffixes = st.sampled_from([".c3d", ".npz"])


@given(suffixes, st.binary(max_size=2048))
def test_random_bytes(worker, suffix, data):
    _check(worker, data, suffix)


@given(suffixes, st.floats(0.0, 1.0, exclude_max=True))
def test_truncations(worker, suffix, where):
    valid = VALID[suffix]
    _check(worker, valid[: int(where * len(valid))], suffix)


@given(
    suffixes, st.lists(st.tuples(st.floats(0.0, 1.0, exclude_max=True), st.integers(0, 255)), min_size=1, max_size=8)
)
def test_byte_flips(worker, suffix, flips):
    data = bytearray(VALID[suffix])
    for where, value in flips:
        data[int(where * len(data))] = value
    _check(worker, bytes(data), suffix)


def test_valid_files_read(worker):
    for suffix in VALID:
        _check(worker, VALID[suffix], suffix)
