"""The package's floors: every import points down (or sideways within a floor), and companions
never import each other. The floors are the architecture of docs/architecture.md."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import unibody

ROOT = Path(unibody.__file__).parent

# Bottom first. A module may import from its own floor and the floors below it.
FLOORS: tuple[tuple[str, ...], ...] = (
    ("_checks", "io"),
    ("geometry",),
    ("viz",),
    ("assets", "rig", "joint_limits", "regions", "symmetry"),
    ("identity", "topology", "registration"),
    ("skeleton", "procedural", "body", "motion", "correctives"),
    ("fitting", "synth"),
    ("convert",),
    ("mocap", "occupancy", "panoman"),
    ("cli",),
)
COMPANIONS = ("mocap", "occupancy", "panoman")
FLOOR = {name: i for i, names in enumerate(FLOORS) for name in names}


def _top(module: str) -> str:
    """``unibody.a.b`` -> ``a``; the package root itself -> ``""``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def _module(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_edges(root: Path = ROOT) -> list[tuple[str, str, int]]:
    """``(importer, imported, line)`` for every import of a unibody module, functions' too."""
    edges = []
    for path in sorted(root.rglob("*.py")):
        module = _module(path)
        package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")[: len(package.split(".")) - node.level + 1]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                if target.split(".")[0] == "unibody":
                    edges += [(module, f"{target}.{a.name}" if target == "unibody" else target, node.lineno)
                              for a in node.names]  # fmt: skip
            elif isinstance(node, ast.Import):
                edges += [(module, a.name, node.lineno) for a in node.names if a.name.split(".")[0] == "unibody"]
    return edges


def wrong_way(edges: list[tuple[str, str, int]]) -> list[str]:
    """Edges that point up a floor, cross between companions, or leave a module off the floors."""
    bad = []
    for importer, imported, line in edges:
        a, b = _top(importer), _top(imported)
        if not a or a == b:
            continue  # the root package re-exports; a subpackage may import itself
        where = f"{importer}:{line} imports {imported}"
        if a not in FLOOR or b not in FLOOR:
            bad.append(f"{where}: {a if a not in FLOOR else b!r} is on no floor (add it to FLOORS)")
        elif FLOOR[b] > FLOOR[a]:
            bad.append(f"{where}: floor {FLOOR[a]} ({a}) imports floor {FLOOR[b]} ({b})")
        elif a in COMPANIONS and b in COMPANIONS:
            bad.append(f"{where}: companions never import each other")
    return bad


def test_every_import_points_down():
    assert wrong_way(import_edges()) == []


def test_every_module_is_on_a_floor():
    modules = {p.stem for p in ROOT.glob("*.py") if p.name != "__init__.py"}
    packages = {p.name for p in ROOT.iterdir() if (p / "__init__.py").is_file()}
    assert sorted((modules | packages) - set(FLOOR)) == []


@pytest.mark.parametrize(
    "edge, reason",
    [
        (("unibody.geometry.kinematics", "unibody.rig", 3), "floor 1 (geometry) imports floor 3 (rig)"),
        (("unibody.occupancy.data", "unibody.panoman.dataset", 9), "companions never import each other"),
        (("unibody.mocap.x", "unibody.cli", 1), "floor 8 (mocap) imports floor 9 (cli)"),
        (("unibody.newthing", "unibody.body", 1), "'newthing' is on no floor"),
    ],
)
def test_the_check_can_fail(edge, reason):
    (found,) = wrong_way([edge])
    assert reason in found
