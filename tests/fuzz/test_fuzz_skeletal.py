"""The BVH and ASF/AMC readers on mutated files.

Property: :func:`unibody.io.bvh.read_bvh` and :func:`unibody.io.asfamc.read_asf_amc` of a valid file
with lines deleted, repeated or cut, tokens swapped for odd ones (NaN, inf, 1e400, braces,
keywords) or a byte flipped give a :class:`~unibody.io.skeletal.SkeletalMotion` whose arrays are
finite and consistent (parents before children), or a ``ValueError`` naming the file. Never
another exception type. Default run: seeded, bounded; ``--hypothesis-profile=long``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from hypothesis import event, given
from hypothesis import strategies as st

from test_io_asfamc import AMC, ASF  # the hand-made skeleton and motion of the reader's tests
from test_io_bvh import UNUSUAL  # unusual channel orders, six channels off the root, tabs
from unibody.io.asfamc import read_asf_amc
from unibody.io.bvh import read_bvh
from unibody.io.skeletal import SkeletalMotion

ODD = ["nan", "inf", "-inf", "1e400", "-1e400", "1e-400", "", "{", "}", "0", "-1", "99999999999", "x", "End",
       "JOINT", "CHANNELS", "3", "begin", "end", ":root", "dof", "rx", "2.5.1", "0x10", "1_000"]  # fmt: skip


@st.composite
def mutated(draw, text: str) -> bytes:
    lines = text.split("\n")
    for _ in range(draw(st.integers(1, 4))):
        k = draw(st.integers(0, len(lines) - 1))
        op = draw(st.sampled_from(["delete", "repeat", "token", "token", "cut"]))
        if op == "delete":
            del lines[k]
        elif op == "repeat":
            lines.insert(k, lines[k])
        elif op == "cut":
            lines = lines[: k + 1]
            lines[k] = lines[k][: draw(st.integers(0, len(lines[k])))]
        else:
            tokens = lines[k].split()
            if tokens:
                tokens[draw(st.integers(0, len(tokens) - 1))] = draw(st.sampled_from(ODD))
                lines[k] = " ".join(tokens)
        if not lines:
            lines = [""]
    raw = bytearray("\n".join(lines).encode())
    if raw and draw(st.booleans()):
        raw[draw(st.integers(0, len(raw) - 1))] ^= 1 << draw(st.integers(0, 7))
    return bytes(raw)


def _check(motion: SkeletalMotion) -> None:
    j, t = len(motion.names), motion.num_frames
    assert motion.parents.shape == (j,) and motion.parents[0] == -1
    assert all(0 <= p < k for k, p in enumerate(motion.parents.tolist()) if k)
    assert motion.offsets.shape == (j, 3) and np.isfinite(motion.offsets).all()
    assert motion.rotations.shape == (t, j, 3, 3) and np.isfinite(motion.rotations).all()
    assert motion.translations.shape == (t, j, 3) and np.isfinite(motion.translations).all()
    assert np.isfinite(motion.fps) and motion.fps > 0


def _read(reader, *paths: Path) -> None:  # noqa: ANN001
    try:
        motion = reader(*paths)
    except ValueError as exc:
        assert any(str(p) in str(exc) for p in paths), repr(exc)
        event("refused")
        return
    event("read")
    _check(motion)


@given(data=mutated(UNUSUAL))
def test_bvh(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("bvh") / "m.bvh"
    path.write_bytes(data)
    _read(read_bvh, path)


@given(which=st.sampled_from(["asf", "amc"]), data=st.data())
def test_asf_amc(tmp_path_factory, which, data):
    """One of the two files mutated, the other as valid."""
    folder = tmp_path_factory.mktemp("asfamc")
    files = {"asf": (folder / "s.asf", ASF), "amc": (folder / "s.amc", AMC)}
    for name, (path, text) in files.items():
        path.write_bytes(data.draw(mutated(text), label=name) if name == which else text.encode())
    _read(read_asf_amc, files["asf"][0], files["amc"][0])
