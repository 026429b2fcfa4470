"""Property: a damaged marker layout file loads as a usable layout, or a ValueError names the file.

Input: a shipped layout's JSON (``cmu41``; what ``unibody mocap layout`` writes and users edit),
with one to three values anywhere in it replaced (by -1, 2**40, 1.5, NaN, inf, 1e30, a string,
null, true, a list, an object), keys dropped or added, or the text cut short.
:meth:`unibody.mocap.layout.MarkerLayout.load` must give a layout whose vertices are canonical
vertex ids, whose distances are finite and within ``MAX_MARKER_DISTANCE`` and whose labels are
names (not empty, not ``*``-prefixed), which places finite markers on a body; or raise a one-line
``ValueError`` starting with the file's path. Seeded and bounded (tests/conftest.py profiles).
"""

from __future__ import annotations

import json
import tempfile
from functools import lru_cache
from pathlib import Path

import torch
from hypothesis import event, given
from hypothesis import strategies as st

from conftest import change_json
from unibody.mocap.layout import MAX_MARKER_DISTANCE, MarkerLayout, place_markers
from unibody.topology import CANONICAL_VERTICES

GOOD = MarkerLayout.load("cmu41").to_json()
_VALUES = st.sampled_from(
    [-1, 0, 2**40, 1.5, float("nan"), float("inf"), 1e30, -0.3, "x", "", "*", None, True, [], {}, {"vertex": 3}]
)


@st.composite
def damaged(draw) -> str:
    data = json.loads(json.dumps(GOOD))
    kind = draw(st.sampled_from(["value", "value", "drop", "add", "cut"]))
    event(kind)
    if kind == "cut":
        text = json.dumps(data)
        return text[: draw(st.integers(0, len(text) - 1))]
    for _ in range(draw(st.integers(1, 3))):
        change_json(draw, data, kind, _VALUES, st.sampled_from(["", "*9", "extra", "vertex", "distance"]))
    return json.dumps(data, allow_nan=True)


@given(text=damaged())
def test_a_damaged_layout_loads_as_a_usable_layout_or_names_the_file(text):
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "session.json"
        path.write_text(text)
        try:
            layout = MarkerLayout.load(path)
        except ValueError as exc:
            event("refused")
            assert str(exc).startswith(str(path)) and "\n" not in str(exc), exc
            return
    event("loaded")
    assert len(layout) >= 1
    assert int(layout.vertices.min()) >= 0 and int(layout.vertices.max()) < CANONICAL_VERTICES
    assert bool(torch.isfinite(layout.distance).all()) and float(layout.distance.abs().max()) <= MAX_MARKER_DISTANCE
    assert all(isinstance(x, str) and x and not x.startswith("*") for x in layout.labels)
    verts, faces = _body()
    markers = place_markers(verts, faces, layout.vertices, layout.distance)
    assert markers.shape == (1, len(layout), 3) and bool(torch.isfinite(markers).all())


@lru_cache(maxsize=1)
def _body() -> tuple[torch.Tensor, torch.Tensor]:
    """The canonical mean body at rest: (1, V, 3) vertices and its faces."""
    from unibody.body import BodyLayer

    layer = BodyLayer.from_pca(num_components=10)
    with torch.no_grad():
        rest = layer.prepare_identity(torch.zeros(1, 10)).rest_vertices
    return rest, layer.faces
