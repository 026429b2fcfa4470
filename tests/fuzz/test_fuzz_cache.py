"""Fuzz the canonical asset cache: any mutation of the file is either harmless or refused and rebuilt.

One real build (~5 s) gives the reference file; each example mutates its bytes (flips, truncation,
overwritten runs, appended junk, biased towards the zip headers at both ends) and checks that

- :func:`unibody.assets.read_cache` never raises: it returns arrays equal to the reference or a reason;
- :func:`unibody.assets.canonical_assets` returns the reference arrays, with an AssetWarning exactly
  when the file was refused, and leaves an intact file behind.

The rebuild is the reference's arrays (``assets._build`` replaced), so an example costs milliseconds.
Seeded and bounded by the hypothesis profiles of ``tests/conftest.py`` (``--hypothesis-profile=long``).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from unibody import assets
from unibody.assets import AssetWarning


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fuzz-cache")
    mp = pytest.MonkeyPatch()
    mp.setenv("UNIBODY_CACHE_DIR", str(folder))
    assets.canonical_assets.cache_clear()
    reference = assets.canonical_assets()
    path = assets.canonical_cache_path()
    data = path.read_bytes()
    mp.setattr(assets, "_build", lambda source: {k: v.copy() for k, v in reference.items()})
    yield reference, path, data
    assets.canonical_assets.cache_clear()
    mp.undo()


def _equal(a, b) -> bool:
    return a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


@st.composite
def mutations(draw, size: int):
    """(kind, args) of a mutation of a file of ``size`` bytes."""
    # Half the positions in the first/last 4 KiB: the local header of the first member and the central directory.
    position = st.one_of(st.integers(0, size - 1), st.integers(0, 4095), st.integers(size - 4096, size - 1))
    kind = draw(st.sampled_from(["flip", "truncate", "overwrite", "append"]))
    if kind == "flip":
        return kind, draw(st.lists(st.tuples(position, st.integers(1, 255)), min_size=1, max_size=8))
    if kind == "truncate":
        return kind, draw(position)
    if kind == "overwrite":
        return kind, (draw(position), draw(st.binary(min_size=1, max_size=64)))
    return kind, draw(st.binary(min_size=1, max_size=256))


def _mutate(data: bytes, mutation) -> bytes:
    kind, args = mutation
    b = bytearray(data)
    if kind == "flip":
        for pos, mask in args:
            b[pos] ^= mask
    elif kind == "truncate":
        del b[args:]
    elif kind == "overwrite":
        pos, junk = args
        b[pos : pos + len(junk)] = junk
    else:
        b += args
    return bytes(b)


SIZE = 5_301_448  # the reference file's size when the test was written; the strategy clamps to the real one


@given(mutation=mutations(SIZE))
def test_a_mutated_cache_file_is_harmless_or_rebuilt(setup, mutation):
    reference, path, data = setup
    kind, args = mutation
    if kind == "flip":  # clamp positions to this build's file size
        mutation = (kind, [(p % len(data), m) for p, m in args])
    elif kind in ("truncate", "overwrite"):
        mutation = (kind, args % len(data) if kind == "truncate" else (args[0] % len(data), args[1]))
    path.write_bytes(_mutate(data, mutation))
    arrays, problem = assets.read_cache(path, assets._check_canonical)
    assert (arrays is None) != (problem is None)
    if arrays is not None:  # e.g. a flipped timestamp or zip comment: the same arrays
        assert _equal(arrays, reference)
    assets.canonical_assets.cache_clear()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        loaded = assets.canonical_assets()
    refused = [w for w in caught if issubclass(w.category, AssetWarning)]
    assert _equal(loaded, reference)
    assert len(refused) == (problem is not None)
    again, problem = assets.read_cache(path, assets._check_canonical)
    assert problem is None and _equal(again, reference)
