"""Property: retargeting a skeleton motion gives a finite canonical motion or a ValueError naming the file.

Input: six frames of a real CMU BVH (cgspeed/DAZ skeleton, ``../shared/motions/cmu``), read by
:func:`unibody.io.bvh.read_bvh`, then changed in ways the reader lets through: offsets scaled
(other units), zeroed (a joint on its parent) or made huge, joints renamed beyond the name rules,
rotations random, half turns, or one frame turned against the next, the root thrown far, one
frame only, an odd frame rate, a NaN (as a hand-made ``SkeletalMotion`` may carry).
:func:`unibody.convert.skeletal.skeletal_to_motion` must return a motion whose pose, translation
and identity are finite, with the input's frames and rate, and finite statistics; or refuse with
a ValueError whose message starts with the file's name. Seeded and bounded (tests/conftest.py
profiles).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import event, given
from hypothesis import strategies as st

from unibody.convert import ConvertOptions
from unibody.convert.skeletal import skeletal_to_motion
from unibody.io.bvh import read_bvh

CLIP = Path(__file__).resolve().parents[3] / "shared" / "motions" / "cmu" / "bvh" / "002" / "02_01.bvh"
WHERE = "02_01.bvh: "

pytestmark = pytest.mark.skipif(not CLIP.is_file(), reason="../shared/motions/cmu is not here")


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    lines = CLIP.read_text().splitlines()
    at = next(i for i, s in enumerate(lines) if s.startswith("Frames:"))
    path = tmp_path_factory.mktemp("clip") / "02_01.bvh"
    path.write_text("\n".join(lines[:at] + ["Frames: 6"] + lines[at + 1 : at + 8]) + "\n")
    return read_bvh(path)


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    k = axis / np.linalg.norm(axis)
    x = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * x + (1 - math.cos(angle)) * x @ x


_J = st.integers(0, 10**6)
_OPS = st.one_of(
    st.tuples(st.just("scale"), st.sampled_from([1e-4, 1e-3, 0.0254, 0.1, 10.0, 1000.0, 1e6])),
    st.tuples(st.just("zero"), _J),
    st.tuples(st.just("huge"), _J, st.sampled_from([1e3, 1e8])),
    st.tuples(st.just("rename"), _J),
    st.tuples(st.just("random"), _J, st.integers(0, 3)),
    st.tuples(st.just("half"), _J),
    st.tuples(st.just("flip"), st.integers(0, 4)),
    st.tuples(st.just("far"), st.sampled_from([1e3, 1e7, -1e9])),
    st.tuples(st.just("one")),
    st.tuples(st.just("nan"), _J, st.booleans()),
    st.tuples(st.just("fps"), st.sampled_from([1e-3, 0.5, 1e5])),
)


def _mutate(sk, ops):  # noqa: ANN001, ANN202
    names, offsets = list(sk.names), sk.offsets.copy()
    rot, trans, fps = sk.rotations.copy(), sk.translations.copy(), sk.fps
    g = np.random.default_rng(len(ops))
    for op in ops:
        j = len(names)
        if op[0] == "scale":
            offsets *= op[1]
            trans *= op[1]
        elif op[0] == "zero":
            k = 1 + op[1] % (j - 1)
            offsets[k] = 0.0
            trans[:, k] = 0.0
        elif op[0] == "huge":
            k = op[1] % j
            offsets[k] *= op[2]
            trans[:, k] *= op[2]
        elif op[0] == "rename":
            names[op[1] % j] = f"joint{op[1]}"
        elif op[0] == "random":
            k = op[1] % j
            rot[:, k] = [_rotation(g.normal(size=3), g.uniform(0, math.pi)) for _ in range(len(rot))]
        elif op[0] == "half":
            rot[:, op[1] % j] = rot[:, op[1] % j] @ _rotation(np.array([0.0, 0.0, 1.0]), math.pi)
        elif op[0] == "flip" and len(rot) > 1:
            t = op[1] % len(rot)
            rot[t] = rot[t] @ _rotation(np.array([1.0, 0.0, 0.0]), math.pi)
        elif op[0] == "far":
            trans[:, 0] += op[1]
        elif op[0] == "one":
            rot, trans = rot[:1], trans[:1]
        elif op[0] == "nan":  # a reader bug or a hand-made SkeletalMotion
            (rot if op[2] else trans)[-1, op[1] % j, 0] = np.nan
        elif op[0] == "fps":
            fps = op[1]
    names = tuple(n if names.count(n) == 1 else f"{n}{i}" for i, n in enumerate(names))  # the reader's names are unique
    return dataclasses.replace(sk, names=names, offsets=offsets, rotations=rot, translations=trans, fps=fps)


@given(ops=st.lists(_OPS, max_size=4))
def test_retarget_gives_finite_motion_or_names_the_file(clip, ops):
    sk = _mutate(clip, ops)
    try:
        conv = skeletal_to_motion(sk, ConvertOptions(), "bvh: 02_01.bvh", WHERE)
    except ValueError as exc:
        assert str(exc).startswith(WHERE), exc
        event(f"refused: {str(exc)[len(WHERE) :][:40]}")
        return
    event("converted")
    m = conv.motion
    assert m.pose.shape == (sk.num_frames, 77, 3) and m.transl.shape == (sk.num_frames, 3) and m.fps == sk.fps
    assert np.isfinite(m.pose).all() and np.isfinite(m.transl).all() and np.isfinite(m.identity).all()
    assert all(np.isfinite(v) for v in conv.stats.values() if isinstance(v, float)), conv.stats
