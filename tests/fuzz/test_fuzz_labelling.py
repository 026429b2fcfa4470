"""Property: any marker sequence given to ``label_sequence`` gives a consistent labelling or a ValueError naming it.

Input: a short take of the cmu41 markers on a moving body (labels hidden, columns shuffled),
mutated the way lab exports go wrong: NaN in one coordinate, values far off (0, 1e-300, 1e30),
copied columns at and around the 1 mm coincidence tolerance, empty frames, frames with one to
three points, many ghosts, every point of a frame on one spot, whole frames far away, a scale
(units), a cut to a few frames, dropped columns and an odd frame rate. Labelled per frame, by
tracklets, and (fewer examples: it solves a body) with the body check.

The answer must be a :class:`LabelledSequence` where: every point is finite or NaN; the first L
columns are the model's labels; each input point's label is in [0, L] and null where it is
absent; a labelled point sits in its label's column in its frame, and no two input points that
are not copies of one another share a label in a frame; or a ValueError whose message names
``seq``. Seeded and bounded (tests/conftest.py profiles).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import example, given, settings
from hypothesis import strategies as st

from unibody.body import BodyLayer
from unibody.mocap.c3d import MarkerSequence
from unibody.mocap.coincident import find_coincident
from unibody.mocap.layout import MarkerLayout, place_markers
from unibody.mocap.pipeline import label_sequence, load_labeler
from unibody.mocap.solve import unibody_to_lab
from unibody.rig import joint_index

FRAMES = 6


@pytest.fixture(scope="module")
def setup():
    layout = MarkerLayout.load("cmu41")
    layer = BodyLayer.from_pca(num_components=8, dtype=torch.float64)
    t = torch.linspace(0, 1, FRAMES, dtype=torch.float64)
    pose = torch.zeros(FRAMES, 77, 3, dtype=torch.float64)
    pose[:, joint_index("LeftArm") - 1, 2] = -1.2 + 0.8 * torch.sin(3 * t)
    pose[:, joint_index("RightLeg") - 1, 0] = -0.5 * t
    pose[:, 0, 1] = 1.5 * t
    out = layer(torch.zeros(1, 8, dtype=torch.float64), pose, transl=torch.stack([t, 0.9 + 0 * t, 0 * t], -1))
    markers = place_markers(out.vertices, layer.faces, layout.vertices, layout.distance)
    lab = unibody_to_lab(markers.numpy(), up="z")
    perm = np.random.default_rng(1).permutation(len(layout))
    return load_labeler("cmu41"), layout, lab[:, perm]


_INDEX = st.integers(0, 10**6)
_VALUE = st.sampled_from([0.0, -0.0, 1e-300, 1e30, -1e30, 3.0, -50.0, 1e6])
_OPS = st.one_of(
    st.tuples(st.just("nan"), _INDEX, _INDEX, st.integers(0, 2)),
    st.tuples(st.just("value"), _INDEX, _INDEX, st.integers(0, 2), _VALUE),
    st.tuples(st.just("copy"), _INDEX, st.sampled_from([0.0, 1e-4, 9e-4, 1.1e-3, 5e-3]), st.booleans()),
    st.tuples(st.just("empty"), _INDEX),
    st.tuples(st.just("few"), _INDEX, st.integers(1, 3)),
    st.tuples(st.just("ghosts"), st.integers(1, 60), st.floats(0.05, 3.0)),
    st.tuples(st.just("stack"), _INDEX),
    st.tuples(st.just("away"), _INDEX, st.sampled_from([2.5, 40.0, 1e5])),
    st.tuples(st.just("scale"), st.sampled_from([1e-3, 0.1, 10.0, 100.0, 1000.0])),
    st.tuples(st.just("cut"), st.integers(1, FRAMES)),
    st.tuples(st.just("drop"), st.integers(0, 41)),
)


def _mutate(points: np.ndarray, ops: list, seed: int) -> np.ndarray:
    p = points.copy()
    g = np.random.default_rng(seed)
    for op in ops:
        t, m = p.shape[:2]
        kind = op[0]
        if kind == "nan" and m:
            p[op[1] % t, op[2] % m, op[3]] = np.nan
        elif kind == "value" and m:
            p[op[1] % t, op[2] % m, op[3]] = op[4]
        elif kind == "copy" and m:
            col = p[:, op[1] % m] + op[2] * np.array([1.0, 0.0, 0.0])
            if op[3]:  # a copy seen in half of the frames only
                col[::2] = np.nan
            p = np.concatenate([p, col[:, None]], 1)
        elif kind == "empty":
            p[op[1] % t] = np.nan
        elif kind == "few" and m:
            keep = g.permutation(m)[: op[2]]
            drop = np.setdiff1d(np.arange(m), keep)
            p[op[1] % t, drop] = np.nan
        elif kind == "ghosts":
            centre = np.nan_to_num(np.nanmedian(p.reshape(-1, 3), axis=0)) if np.isfinite(p).any() else np.zeros(3)
            p = np.concatenate([p, centre + g.uniform(-op[2], op[2], size=(t, op[1], 3))], 1)
        elif kind == "stack" and m:
            p[op[1] % t] = p[op[1] % t, :1]
        elif kind == "away":
            p[op[1] % t] += op[2]
        elif kind == "scale":
            p = p * op[1]
        elif kind == "cut":
            p = p[: op[1]]
        elif kind == "drop":
            p = p[:, g.permutation(m)[: max(m - op[1], 0)]]
    return p


def _check(seq: MarkerSequence, model, **kwargs) -> None:
    try:
        out = label_sequence(seq, model, **kwargs)
    except ValueError as e:
        assert str(e).startswith("seq"), e
        return
    t, n = seq.points.shape[:2]
    big = model.num_labels
    assert out.labels[:big] == model.label_names and out.points.shape[0] == t
    assert not np.isinf(out.points).any()
    lab = out.point_labels
    assert lab.shape == (t, n) and lab.min(initial=0) >= 0 and lab.max(initial=0) <= big
    assert (lab[~seq.visible] == big).all()
    original = find_coincident(seq.points).original
    for f, i in zip(*np.nonzero(lab < big), strict=True):
        assert np.array_equal(out.points[f, lab[f, i]], seq.points[f, original[f, i]]), (f, i)
    for f in range(t):
        named = lab[f] < big
        owners = {}
        for i in np.flatnonzero(named):
            assert owners.setdefault(int(lab[f, i]), original[f, i]) == original[f, i], (f, i)
    # every visible point is somewhere in the output: in its label's column or an unlabelled one
    assert int(np.isfinite(out.points).all(-1).sum()) == int((seq.visible & (original == np.arange(n))).sum())


_MUTATIONS = st.lists(_OPS, max_size=5)


@given(ops=_MUTATIONS, seed=st.integers(0, 3), tracklets=st.booleans())
@example(ops=[("drop", 41)], seed=0, tracklets=False)  # found: no column at all raised a RuntimeError
def test_label_sequence_on_mutated_takes(setup, ops, seed, tracklets):
    model, _, lab = setup
    pts = _mutate(lab, ops, seed)
    names = tuple(f"*{i}" for i in range(pts.shape[1]))
    _check(MarkerSequence(pts, names, ("",) * len(names), 60.0), model, tracklets=tracklets)


@settings(max_examples=max(8, settings.default.max_examples // 4))  # each example solves a body
# Found by this test: labelling kept a frame with the whole subject 40 m away, then the body
# check's solve refused the sequence ("points: coordinates span 82 units; millimetres?").
@example(ops=[("away", 0, 40.0)], seed=0, tracklets=False, rate=0.5)
# Found: labels naming two markers or none made the body check's solve refuse the sequence (it
# now skips the check and says why).
@example(ops=[("drop", 39)], seed=0, tracklets=True, rate=60.0)
@example(ops=[("drop", 41)], seed=0, tracklets=False, rate=60.0)
# Found by CI: one frame at 10 kHz (a static trial) interpolated its strided solve 0 / 0 into NaN markers.
@example(ops=[("cut", 1)], seed=0, tracklets=True, rate=10000.0)
@given(ops=_MUTATIONS, seed=st.integers(0, 3), tracklets=st.booleans(), rate=st.sampled_from([0.5, 60.0, 1e4]))
def test_label_sequence_with_the_body_check_on_mutated_takes(setup, ops, seed, tracklets, rate):
    model, layout, lab = setup
    pts = _mutate(lab, ops, seed)
    names = tuple(f"*{i}" for i in range(pts.shape[1]))
    _check(MarkerSequence(pts, names, ("",) * len(names), rate), model, tracklets=tracklets, layout=layout)
