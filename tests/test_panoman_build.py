"""The PanoMan build script end to end on a tiny recipe: it runs, writes a loadable model, resumes."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest
import torch

from unibody.panoman.model import PanoMan

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "build_panoman.py"


def _script():
    spec = importlib.util.spec_from_file_location("build_panoman", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_build_script_tiny_recipe_and_resume(tmp_path, capsys):
    work, out = tmp_path / "work", tmp_path / "model.pt"
    argv = ["--work", str(work), "--out", str(out), "--samples", "6", "4", "4", "--components", "2", "1", "1",
            "--iterations", "1", "--net-steps", "3", "--correction-rank", "2"]  # fmt: skip
    build = _script()
    build.main(argv)
    model = PanoMan.load(out)
    assert model.num_beta == 2 * (2 + 1 + 1)
    assert model.metadata["recipe"]["components"] == {"body": 2, "face": 1, "hands": 1}
    beta = model.beta_from_pose(torch.zeros(1, 77, 3, dtype=torch.float64))
    rl, ra = model.rla(beta)
    assert torch.isfinite(rl).all() and torch.isfinite(ra).all()
    first = capsys.readouterr().out
    assert "resume" not in first and "wrote" in first
    build.main(argv)  # every stage is cached now
    second = capsys.readouterr().out
    assert second.count("resume:") >= 9
    again = PanoMan.load(out)
    assert torch.equal(again.decompositions[0].value, model.decompositions[0].value)
