"""Property: any TRC text gives a checked MarkerSequence or a ValueError naming the file.

Never another exception type, an infinite or far-away point, or a sequence whose shape
disagrees with its labels. Seeded and bounded (profiles in tests/conftest.py);
``--hypothesis-profile=long`` runs 1000 examples each.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from conftest import mutate_text
from unibody.mocap.trc import read_trc
from unibody.motion import MAX_DISTANCE

VALID = (
    "PathFileType\t4\t(X/Y/Z)\tt.trc\n"
    "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames\n"
    "100.0\t100.0\t3\t2\tmm\t100.0\t1\t3\n"
    "Frame#\tTime\tRASI\t\t\tSubj:LASI\t\t\n"
    "\t\tX1\tY1\tZ1\tX2\tY2\tZ2\n"
    "\n"
    "1\t0.00\t100.5\t900.0\t-20.0\t-100.5\t900.0\t-20.0\n"
    "2\t0.01\t101.5\t901.0\t-21.0\t\t\t\n"
    "3\t0.02\t102.5\t902.0\t-22.0\n"
).encode("ascii")

TOKENS = [b"\t", b"\n", b"\r\n", b"", b"mm", b"m", b"cm", b"km", b"nan", b"NaN", b"inf", b"-inf", b"1e999", b"1e308",
          b"-1e12", b"0", b"-0", b"3", b"2", b"1e-320", b"100.0", b"Frame#", b"Time", b"DataRate", b"NumFrames",
          b"NumMarkers", b"Units", b"PathFileType", b"Subj:", b"\xe9", b"\xff\xfe", b"\x00", b"x", b" ", b":",
          b"1_0"]  # fmt: skip


def _check(data: bytes) -> None:
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "fuzz.trc"
        path.write_bytes(data)
        try:
            seq = read_trc(path)
        except ValueError as e:
            assert str(path) in str(e), f"the error does not name the file: {e}"
            assert "\n" not in str(e)
            return
    t, m, three = seq.points.shape
    assert t >= 1 and m >= 1 and three == 3 and len(seq.labels) == len(seq.subjects) == m
    assert all(seq.labels), seq.labels
    finite = seq.points[~np.isnan(seq.points)]
    assert np.isfinite(finite).all() and (np.abs(finite) <= MAX_DISTANCE).all()
    assert np.isfinite(seq.rate) and seq.rate > 0


@given(st.binary(max_size=400))
def test_random_bytes(data):
    _check(b"PathFileType" + data)


@given(st.data())
def test_mutated_valid_file(data):
    _check(mutate_text(data, VALID, TOKENS, separator=b"\t"))


_name = st.text(st.characters(blacklist_categories=("Cs", "Zs"), blacklist_characters=":"), min_size=1)


@given(
    st.integers(1, 5).flatmap(
        lambda t: st.integers(1, 4).flatmap(
            lambda m: st.tuples(
                st.lists(
                    st.one_of(st.floats(-1e4, 1e4), st.just(float("nan"))), min_size=3 * t * m, max_size=3 * t * m
                ),
                st.lists(_name, min_size=m, max_size=m),
                st.lists(st.one_of(st.just(""), _name), min_size=m, max_size=m),
                st.just(t),
            )
        )
    ),
    st.floats(0.01, 1e4),
)
def test_written_files_read_back(drawn, rate):
    from unibody.mocap.c3d import MarkerSequence
    from unibody.mocap.trc import write_trc

    values, labels, subjects, t = drawn
    seq = MarkerSequence(np.asarray(values).reshape(t, len(labels), 3), tuple(labels), tuple(subjects), rate)
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "w.trc"
        try:
            write_trc(path, seq)
        except ValueError as e:  # a label holding a separator, or padded: refused, nothing written
            assert str(e).startswith("labels: a TRC label ") and not path.exists()
            parts = seq.labels + seq.subjects
            assert any("\t" in x or len(f"{x}.".splitlines()) > 1 or x != x.strip() for x in parts) or not all(
                x.strip() for x in seq.labels
            )
            return
        back = read_trc(path)
    assert back.labels == seq.labels and back.subjects == seq.subjects
    assert abs(back.rate - rate) <= 1e-11 * rate
    assert np.allclose(back.points, seq.points, rtol=0, atol=1e-9, equal_nan=True)
