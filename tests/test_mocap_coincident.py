"""Coincident points (issue 38 item 6): copies found, labelled as their original, reported."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from unibody.mocap.coincident import COINCIDENT_TOL, find_coincident

EVAL = Path(__file__).resolve().parents[2] / "shared/evaldata/c3d/cmu_85_02.c3d"


def _cloud(t=50, n=6, seed=0):
    rng = np.random.default_rng(seed)
    base = rng.uniform(-0.5, 0.5, (n, 3))  # markers >= several cm apart
    walk = np.cumsum(rng.normal(0, 0.002, (t, 1, 3)), axis=0)
    return base[None] + walk + rng.normal(0, 0.003, (t, n, 3))


def test_copy_columns_exact_and_near():
    pts = _cloud()
    rng = np.random.default_rng(1)
    exact = pts[:, 1]
    near = pts[:, 3] + rng.uniform(-1, 1, (len(pts), 3)) * 0.4e-3 / np.sqrt(3)  # within 0.4 mm
    far = pts[:, 4] + np.array([0.005, 0.0, 0.0])  # 5 mm: two markers, not a copy
    x = np.concatenate([pts, exact[:, None], near[:, None], far[:, None]], axis=1)  # columns 6, 7, 8
    co = find_coincident(x)
    assert co.columns == ((6, 1), (7, 3))
    assert co.copy[:, 6].all() and co.copy[:, 7].all() and not co.copy[:, 8].any()
    assert not co.copy[:, :6].any() and co.frame_copies == 0
    assert (co.original[:, 6] == 1).all() and (co.original[:, 8] == 8).all()
    labels = np.tile(np.arange(9), (len(x), 1))
    assert (co.spread(labels)[:, 6] == 1).all() and (co.spread(labels)[:, 8] == 8).all()
    assert "merged 2 columns" in co.describe([f"m{i}" for i in range(9)]) and "m6=m1" in co.describe(
        [f"m{i}" for i in range(9)]
    )


def test_copy_without_original_is_its_own_point_and_isolated_coincidences():
    pts = _cloud()
    x = np.concatenate([pts, pts[:, 2:3]], axis=1)  # column 6 copies column 2
    x[10:20, 2] = np.nan  # original absent: the copy is an ordinary point there
    x[30, 5] = x[30, 0] + 0.0002  # one frame: column 5 lands on column 0
    co = find_coincident(x)
    assert co.columns == ((6, 2),)
    assert not co.copy[10:20, 6].any() and co.copy[:10, 6].all()
    assert co.copy[30, 5] and co.original[30, 5] == 0 and co.copy[:, 5].sum() == 1
    assert co.frame_copies == 1
    # a copy of a copy goes to the first column
    y = np.concatenate([pts, pts[:, :1], pts[:, :1]], axis=1)
    assert find_coincident(y).columns == ((6, 0), (7, 0))


def test_rarely_coincident_column_is_not_a_copy_column():
    pts = _cloud()
    x = np.concatenate([pts, pts[:, 1:2] + 0.03], axis=1)
    x[:3, 6] = pts[:3, 1]  # coincides in 3 of 50 frames: per-frame coincidences, not a copy column
    co = find_coincident(x)
    assert co.columns == () and co.frame_copies == 3


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [({"tol": 0.0}, "tol: expected"), ({"tol": 0.01}, "tol: expected"), ({"share": 0.0}, "share: expected")],
)
def test_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        find_coincident(_cloud(), **kwargs)
    with pytest.raises(ValueError, match="points: expected shape"):
        find_coincident(np.zeros((3, 4)))


@pytest.mark.skipif(not EVAL.is_file(), reason="needs ../shared/evaldata")
def test_copied_columns_on_a_real_file_label_like_their_originals():
    from unibody.mocap.c3d import MarkerSequence, read_markers
    from unibody.mocap.pipeline import label_sequence, load_labeler

    seq = read_markers(EVAL)
    seq = replace(seq, points=seq.points[200:260])
    idx = [seq.labels.index(x) for x in ("LFWT", "CLAV", "LFHD")]
    pts = np.concatenate([seq.points, seq.points[:, idx]], axis=1)
    pts[5:9, -1] = np.nan  # a copy column with gaps
    copies = MarkerSequence(pts, (*seq.labels, "C1", "C2", "C3"), ("",) * (len(seq.labels) + 3), seq.rate)
    model = load_labeler("cmu41")
    lines: list[str] = []
    plain = label_sequence(seq, model)
    dup = label_sequence(copies, model, progress=lines.append)
    assert dup.report.copies == (("C1", "LFWT"), ("C2", "CLAV"), ("C3", "LFHD"))
    assert any("merged 3 columns" in x and "C3=LFHD" in x for x in lines)
    n = seq.num_markers
    np.testing.assert_array_equal(dup.point_labels[:, :n], plain.point_labels)  # as if the copies were not there
    vis = copies.visible[:, n:]
    np.testing.assert_array_equal(dup.point_labels[:, n:][vis], plain.point_labels[:, idx][vis])
    assert dup.labels == plain.labels  # no extra '*' columns for the copies
    np.testing.assert_array_equal(dup.points, plain.points)
    truth = np.array([model.label_names.index(x) for x in seq.labels])
    assert (plain.point_labels == truth)[seq.visible].mean() > 0.95
    assert COINCIDENT_TOL == 1e-3
