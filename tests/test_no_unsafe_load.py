"""Every ``torch.load`` in the package, scripts and benchmarks passes ``weights_only=True``.

``torch.load(weights_only=False)`` (or an older torch's default) unpickles arbitrary objects,
so a crafted checkpoint runs code. The check walks the syntax tree, so comments and strings
do not count and a new call without the flag fails here.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("src", "scripts", "benchmarks")


def _is_torch_load(func: ast.expr) -> bool:
    return isinstance(func, ast.Attribute) and func.attr == "load" and ast.unparse(func.value) == "torch"


def unsafe_loads(source: str, name: str = "<source>") -> list[str]:
    """``file:line`` of each ``torch.load(...)`` call without a literal ``weights_only=True``."""
    found = []
    for node in ast.walk(ast.parse(source, name)):
        if isinstance(node, ast.Call) and _is_torch_load(node.func):
            flag = next((k.value for k in node.keywords if k.arg == "weights_only"), None)
            if not (isinstance(flag, ast.Constant) and flag.value is True):
                found.append(f"{name}:{node.lineno}")
    return found


def test_the_checker_finds_unsafe_calls():
    bad = "import torch\na = torch.load(p)\nb = torch.load(p, weights_only=False)\nc = torch.load(p, **kw)\n"
    assert unsafe_loads(bad) == ["<source>:2", "<source>:3", "<source>:4"]
    good = "import torch\na = torch.load(p, map_location='cpu', weights_only=True)\n# torch.load(p)\n"
    assert unsafe_loads(good) == []


def _sources() -> list[Path]:
    return sorted(p for folder in FOLDERS if (ROOT / folder).is_dir() for p in (ROOT / folder).rglob("*.py"))


def test_sources_are_found():
    names = {p.relative_to(ROOT).as_posix() for p in _sources()}
    assert {"src/unibody/occupancy/train.py", "scripts/train_occupancy.py", "scripts/build_panoman.py"} <= names


@pytest.mark.parametrize("folder", FOLDERS)
def test_every_torch_load_is_weights_only(folder):
    found = []
    for path in _sources():
        if path.relative_to(ROOT).parts[0] == folder:
            found += unsafe_loads(path.read_text(encoding="utf-8"), str(path.relative_to(ROOT)))
    assert not found, f"torch.load without weights_only=True (a crafted file would run code): {found}"
