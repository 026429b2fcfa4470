"""Architecture rules that keep the package's seams public (design.md §4).

No module under ``src/unibody`` but ``body.py`` reads a private member of :class:`BodyLayer`:
solvers go through ``BodyLayer.skinning``, ``BodyLayer.local_rotations`` and the other public
members, so the layer's internal layout can change without breaking them.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
from torch import nn

from unibody import BodyLayer

SRC = Path(__file__).resolve().parents[1] / "src" / "unibody"
OWNER = SRC / "body.py"


def bodylayer_private_names(layer: BodyLayer) -> set[str]:
    """Single-underscore names that BodyLayer defines (class) or registers (instance), not nn.Module's."""
    names = {n for cls in type(layer).__mro__ if issubclass(cls, BodyLayer) for n in vars(cls)}
    names |= set(vars(layer)) | set(layer._buffers) | set(layer._modules) | set(layer._parameters)
    inherited = set(dir(nn.Module)) | set(vars(nn.Module()))
    return {n for n in names - inherited if n.startswith("_") and not n.startswith("__")}


def private_reads(source: str, names: set[str]) -> list[tuple[int, str]]:
    """(line, name) of every ``x.<name>`` and every string literal ``"<name>"`` (getattr) in ``source``."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Attribute) and node.attr in names:
            found.append((node.lineno, node.attr))
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in names:
            found.append((node.lineno, node.value))
    return sorted(found)


@pytest.fixture(scope="module")
def private(small_rig) -> set[str]:
    return bodylayer_private_names(BodyLayer(small_rig))


def test_private_names_are_bodylayers_own(private):
    # Registered buffers, private methods and the transitional alias are all found ...
    assert {"_skin_vertex", "_skin_joint", "_skin_w_crow", "_check_extent"} <= private
    # ... and nn.Module's own private machinery is not.
    assert not private & {"_buffers", "_modules", "_parameters", "_apply", "_call_impl", "_version"}


def test_no_private_bodylayer_member_outside_body(private):
    offenders = []
    for path in sorted(SRC.rglob("*.py")):
        if path == OWNER:
            continue
        for line, name in private_reads(path.read_text(encoding="utf-8"), private):
            offenders.append(f"{path.relative_to(SRC.parent)}:{line}: {name}")
    assert not offenders, "private BodyLayer members used outside body.py:\n" + "\n".join(offenders)


@pytest.mark.parametrize(
    ("source", "expected"),
    [
        ("w = layer._skin_vertex\n", [(1, "_skin_vertex")]),
        ("x = 1\nok = body.layer._check_extent(rest)\n", [(2, "_check_extent")]),
        ("v = getattr(layer, '_skin_w_crow')\n", [(1, "_skin_w_crow")]),
        ("s = layer.skinning\nr = layer.local_rotations(pose)\n", []),
        ("m._buffers\nself._levels = 1\n", []),  # nn.Module's or another class's private names
    ],
)
def test_checker_flags_private_reads(private, source, expected):
    assert private_reads(source, private) == expected


def test_checker_fails_on_an_offending_file(private, tmp_path):
    bad = tmp_path / "solver.py"
    bad.write_text("def f(layer):\n    return layer._skin_joint.cpu()\n", encoding="utf-8")
    assert private_reads(bad.read_text(encoding="utf-8"), private) == [(2, "_skin_joint")]
