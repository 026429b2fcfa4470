"""The shipped procedural twist sidecar, mutated (issue 35, item 11).

Property: :func:`unibody.procedural.load` of a mutated file raises
:class:`~unibody.procedural.ProceduralFormatError` (a ``ValueError``) whose message starts with
the JSON path it carries, or gives a definition that compiles onto the canonical rig (or is
refused there with the same error) and poses to finite meshes in float32 and float64, even for
extreme poses. Never NaN/inf, never another exception type.
Default run: seeded, bounded (building a twist layer takes ~1 s); ``--hypothesis-profile=long``.
"""

from __future__ import annotations

import copy
import json
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from unibody import BodyLayer
from unibody.procedural import ProceduralFormatError, load, parse

_PROFILE_EXAMPLES = settings().max_examples  # 30 by default, 1000 with --hypothesis-profile=long


def examples(n: int) -> settings:
    """``n`` examples in the default run; the long profile's count otherwise."""
    return settings(max_examples=n if _PROFILE_EXAMPLES <= 30 else _PROFILE_EXAMPLES)


SHIPPED: dict[str, Any] = json.loads(
    resources.files("unibody.procedural").joinpath("data", "canonical_twist.json").read_text(encoding="utf-8")
)
NUMBERS = st.sampled_from(
    [0.0, -0.0, 1.0, -1.0, 0.5, 1.5, -0.5, 10.0, 10.5, 1e-30, 1e20, -1e20, 1e40, -1e40, 1e300, 2**70, 10**400]
) | st.floats(allow_nan=False, allow_infinity=False)
JSON_VALUES = st.none() | st.booleans() | st.integers() | st.text(max_size=6) | st.lists(st.integers(), max_size=2)


def _paths(node: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    out = []
    for key, child in items:
        out.append((*prefix, key))
        out.extend(_paths(child, (*prefix, key)))
    return out


ALL_PATHS = _paths(SHIPPED)
NUMBER_PATHS = [p for p in ALL_PATHS if len(p) == 4 and p[0] == "parameter_matrices" and p[2] == "values"]


def _set(d: dict[str, Any], path: tuple[Any, ...], value: Any) -> None:
    for step in path[:-1]:
        d = d[step]
    d[path[-1]] = value


def _write(tmp_path: Path, d: dict[str, Any], name: str = "sidecar.json") -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(d), encoding="utf-8")  # huge ints and 1e40 are valid JSON numbers
    return path


@pytest.fixture(scope="module")
def rig():
    from unibody.rig import Rig

    return Rig.canonical()


def _load_or_error(path: Path):
    try:
        return load(path)
    except ProceduralFormatError as err:
        assert isinstance(err, ValueError) and str(err).startswith(f"{err.path}: "), str(err)
        return None


def _pose_finite(rig, definition) -> None:
    """Compile ``definition`` (or get its documented refusal) and pose it, checking finiteness."""
    try:
        layer = BodyLayer(rig, procedural=definition)
    except ProceduralFormatError as err:
        assert str(err).startswith(f"{err.path}: ")
        return
    gen = torch.Generator().manual_seed(0)
    for dtype in (torch.float32, torch.float64):
        lay = layer.to(dtype)
        prepared = lay.prepare_rest(rig.bind_vertices[None].to(dtype))
        for scale in (0.0, 0.5, 3.0, 1e20):
            pose = (scale * torch.randn(2, 77, 3, generator=gen, dtype=torch.float64)).to(dtype)
            out = lay.pose(prepared, pose)
            assert torch.isfinite(out.vertices).all() and torch.isfinite(out.joints).all(), (dtype, scale)


@examples(60)
@given(st.data(), st.sampled_from(["delete", "replace", "duplicate", "rename"]))
def test_mutated_structure_raises_path_error_or_loads(tmp_path_factory, data, op):
    """Keys and types: cheap, parse only (a layer is built for the rare valid outcome)."""
    d = copy.deepcopy(SHIPPED)
    path = data.draw(st.sampled_from(ALL_PATHS))
    parent = d
    for step in path[:-1]:
        parent = parent[step]
    key = path[-1]
    if op == "delete":
        del parent[key]
    elif op == "duplicate" and isinstance(parent, list):
        parent.insert(key, copy.deepcopy(parent[key]))
    elif op == "rename" and isinstance(parent, dict):
        parent[key + "_x"] = parent.pop(key)
    else:
        parent[key] = data.draw(JSON_VALUES | NUMBERS)
    definition = _load_or_error(_write(tmp_path_factory.mktemp("s"), d))
    if definition is not None:  # valid: it round-trips (numbers are posed in the test below)
        assert parse(definition.to_dict()) == definition


@examples(12)
@given(st.data(), st.integers(1, 3))
def test_mutated_numbers_raise_path_error_or_pose_finite(tmp_path_factory, rig, data, count):
    """Matrix values (1e40: finite in float64, inf in float32): refused by path, or finite posing."""
    d = copy.deepcopy(SHIPPED)
    for _ in range(count):
        _set(d, data.draw(st.sampled_from(NUMBER_PATHS)), data.draw(NUMBERS))
    definition = _load_or_error(_write(tmp_path_factory.mktemp("s"), d))
    if definition is not None:
        _pose_finite(rig, definition)


@pytest.mark.parametrize("value", [1e40, -1e40, 10.5, float(np.float32(3.4e38)), 10**400])
def test_overflowing_rotation_value_is_refused_by_path(tmp_path, value):
    d = copy.deepcopy(SHIPPED)
    d["parameter_matrices"]["rotation"]["values"][4] = value
    with pytest.raises(ProceduralFormatError, match=r"^parameter_matrices\.rotation\.values\[4\]: expected") as info:
        load(_write(tmp_path, d))
    assert info.value.path == "parameter_matrices.rotation.values[4]"


def test_extreme_valid_values_pose_finite(tmp_path, rig):
    d = copy.deepcopy(SHIPPED)
    n = len(d["parameter_matrices"]["rotation"]["values"])
    d["parameter_matrices"]["rotation"]["values"] = [10.0, -10.0] * (n // 2)
    _pose_finite(rig, load(_write(tmp_path, d)))
