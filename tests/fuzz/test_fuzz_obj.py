"""Property: any bytes given to ``read_obj`` give a checked mesh or a ValueError naming the file.

Never another exception type, a hang, a NaN vertex or an out-of-range face index. Seeded and
bounded (profiles in tests/conftest.py); ``--hypothesis-profile=long`` runs 1000 examples each.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from conftest import mutate_text
from unibody.io.obj import read_obj

VALID = b"""# cube
o cube
v -1 -1 -1
v 1 -1 -1
v 1 1 -1
v -1 1 -1
v -1 -1 1
v 1 -1 1
v 1 1 1
v -1 1 1
vt 0 0
vn 0 0 1
f 1/1/1 2/1/1 3/1/1 4/1/1
f 5//1 8//1 7//1 6//1
f 1 5 6 2
f -6 -2 -1 -5
f 3 7 8 4
f 5 1 4 8
"""

TOKENS = [b"v", b"f", b"vt", b"vn", b"#", b"o", b"1", b"-1", b"0", b"2", b"8", b"9", b"1.5", b"-2e3", b"1e999", b"nan",
          b"inf", b"1/1", b"1//1", b"/1", b"//", b"99999999999999999999999", b"-99", b"1_0", b"\t", b" ", b"\r",
          b"\xe9", b"\xff\xfe", b"\x00", b"x", b"+3"]  # fmt: skip


def _check(data: bytes) -> None:
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "fuzz.obj"
        path.write_bytes(data)
        try:
            v, faces = read_obj(path)
        except ValueError as e:
            assert str(path) in str(e), f"the error does not name the file: {e}"
            return
    assert isinstance(v, np.ndarray) and v.dtype == np.float64 and v.ndim == 2 and v.shape[1] == 3 and len(v) > 0
    assert np.isfinite(v).all()
    for face in faces:
        assert len(face) >= 3 and all(type(i) is int and 0 <= i < len(v) for i in face), face


@given(st.binary(max_size=400))
def test_random_bytes(data):
    _check(data)


@given(st.data())
def test_mutated_valid_file(data):
    _check(mutate_text(data, VALID, TOKENS))


_line = st.lists(st.sampled_from(TOKENS), min_size=0, max_size=7).map(b" ".join)


@given(st.lists(_line, max_size=20))
def test_generated_statements(lines):
    _check(b"v 0 0 0\nv 1 0 0\nv 0 1 0\n" + b"\n".join(lines))
