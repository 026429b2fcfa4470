"""Property: ``unibody view FILE --record`` records any marker take or mesh sequence, or exits with one line.

Input: a short marker take (12 columns, Z-up lab, the last one unlabelled) or a mesh sequence of a
box, mutated as files go wrong: NaN points, values 0 to 1e30, a column or a whole frame thrown
far away, frames with nothing visible, every point on one spot, one point only, a single frame,
frame rates 1e-5 to 1e5. The command must write its pictures (exit 0), or refuse in one line
naming the file or the option (exit 2 or 3) and write nothing. Never a traceback, never a hang.
Seeded and bounded (tests/conftest.py profiles).
"""

from __future__ import annotations

import contextlib
import io
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import event, example, given
from hypothesis import strategies as st

from unibody.cli import main
from unibody.mocap.c3d import MarkerSequence, write_npz

_BOX_FACES = np.array(
    [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4]]
)
_FAR = st.sampled_from([3.0, 50.0, 1e5, 1e12, 1e20, 1e30, -1e27])


def _mutate(draw, pts: np.ndarray) -> np.ndarray:
    """Damage (T, N, 3) points in place the way exports go wrong."""
    t, n = pts.shape[:2]
    for _ in range(draw(st.integers(0, 3))):
        kind = draw(st.sampled_from(["nan", "value", "far_column", "far_frame", "empty", "spot", "one"]))
        event(kind)
        f, c = draw(st.integers(0, t - 1)), draw(st.integers(0, n - 1))
        if kind == "nan":
            pts[f, c, draw(st.integers(0, 2))] = np.nan
        elif kind == "value":
            pts[f, c] = draw(st.sampled_from([0.0, 1e-30, 1e30, -1e15]))
        elif kind == "far_column":
            pts[:, c] += [draw(_FAR), 0.0, 0.0]
        elif kind == "far_frame":
            pts[f] += [0.0, draw(_FAR), 0.0]
        elif kind == "empty":
            pts[f:] = np.nan
        elif kind == "spot":
            pts[f] = pts[f, c]
        else:
            keep = pts[:, c].copy()
            pts[:] = np.nan
            pts[:, c] = keep
    return pts


@st.composite
def files(draw) -> tuple[str, dict]:
    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    t = draw(st.integers(1, 6))
    fps = draw(st.sampled_from([1e-5, 0.5, 30.0, 120.0, 1e5]))
    if draw(st.booleans()):
        pts = rng.normal(scale=0.2, size=(t, 12, 3)) + [0.0, 0.0, 1.0]
        labels = tuple(f"M{i}" for i in range(11)) + ("*1",)
        return "markers", {"points": _mutate(draw, pts), "labels": labels, "fps": fps}
    box = np.array([[x, y, z] for x in (0, 0.4) for y in (0, 1.6) for z in (0, 0.3)], float)
    verts = _mutate(draw, box[None] + rng.normal(scale=0.01, size=(t, 8, 3)))
    return "meshes", {"vertices": verts, "faces": _BOX_FACES, "topology": np.asarray("box"), "fps": np.asarray(fps)}


def _only_between() -> tuple[str, dict]:
    """A take visible only between its first, middle and last frames (found by CI's draw)."""
    pts = np.full((4, 12, 3), np.nan)
    pts[1, 0] = 0.0
    return "markers", {"points": pts, "labels": tuple(f"M{i}" for i in range(11)) + ("*1",), "fps": 0.5}


@given(case=files())
@example(case=_only_between())
def test_view_records_any_take_or_refuses_in_one_line(case):
    pytest.importorskip("PIL")
    kind, fields = case
    event(kind)
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "take.npz"
        if kind == "markers":
            pts = fields["points"]
            write_npz(path, MarkerSequence(pts, fields["labels"], ("",) * pts.shape[1], fields["fps"]))
        else:
            np.savez(path, **fields)
        out = Path(folder) / "x.png"
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            code = main(["view", str(path), "--record", str(out), "--size", "32x24", "--fps", "8"])
        event(f"exit {code}")
        written = sorted(Path(folder).glob("x*.png"))
        if code == 0:
            assert written, "exit 0 without a picture"
            return
        lines = [x for x in err.getvalue().splitlines() if x.startswith("unibody: error:")]
        assert code in (2, 3) and len(lines) == 1, err.getvalue()
        assert "take.npz" in lines[0] or "--record" in lines[0], lines[0]
        assert "Traceback" not in err.getvalue() and not written
