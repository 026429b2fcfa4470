"""`unibody convert` on the command line: motion and SOMA files end to end, a broken file among
good ones, outputs that are inputs or someone else's files, and one line per bad argument."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from unibody.cli import main
from unibody.convert import ConvertOptions
from unibody.convert.soma import read_soma, write_soma
from unibody.motion import Motion, load_motion, save_motion

UNIBODY = [sys.executable, "-c", "import sys; from unibody.cli import main; sys.exit(main())"]


def _motion(path: Path, seed: int = 0, frames: int = 4, fps: float = 50.0) -> Path:
    gen = np.random.default_rng(seed)
    m = Motion(
        (0.3 * gen.standard_normal((frames, 77, 3))).astype(np.float32),
        gen.standard_normal((frames, 3)).astype(np.float32),
        fps,
        np.zeros(10, np.float32),
        "pca",
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    save_motion(path, m)
    return path


def _run(capsys, *args) -> tuple[int, str, str]:
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


def _error_lines(err: str) -> list[str]:
    assert "Traceback" not in err, err
    return [ln for ln in err.splitlines() if ln.startswith("unibody: error:")]


def test_motion_and_soma_end_to_end(tmp_path, capsys):
    src = tmp_path / "in"
    a = _motion(src / "a.npz", 1, fps=120.0)
    soma = src / "sub" / "b.npz"
    soma.parent.mkdir(parents=True)
    write_soma(load_motion(_motion(tmp_path / "b0.npz", 2, fps=24.0)), soma, ConvertOptions())
    code, out, err = _run(capsys, "convert", src, "--to", "soma,motion", "--out", tmp_path / "out")
    assert code == 0, err
    assert "converted 2 file(s), 8 frames" in out and "100%" in err
    m = load_motion(tmp_path / "out" / "a.motion.npz")
    s = read_soma(tmp_path / "out" / "a.soma.npz", ConvertOptions()).motion
    np.testing.assert_array_equal(m.pose, load_motion(a).pose)
    np.testing.assert_array_equal(s.pose, m.pose)
    assert m.fps == s.fps == 120.0  # the frame rate is kept end to end
    b = load_motion(tmp_path / "out" / "sub" / "b.motion.npz")
    np.testing.assert_array_equal(b.pose, load_motion(tmp_path / "b0.npz").pose)
    assert b.fps == 24.0 and b.source == "soma: b.npz"
    rows = list(csv.DictReader(open(tmp_path / "out" / "convert_report.csv")))
    assert sorted((Path(r["input"]).name, r["format"], r["status"], r["frames"]) for r in rows) == [
        ("a.npz", "motion", "ok", "4"),
        ("b.npz", "soma", "ok", "4"),
    ]
    code, out, err = _run(capsys, "convert", src, "--to", "soma,motion", "--out", tmp_path / "out")
    assert code == 0 and "converted 0 file(s)" in out and "2 done before" in out


def test_subprocess_run_and_frame_rate(tmp_path):
    take = _motion(tmp_path / "take.npz", 3, fps=59.94)
    run = subprocess.run([*UNIBODY, "convert", str(take), "--to", "soma", "--out", str(tmp_path / "o")],
                         capture_output=True, text=True, timeout=300)  # fmt: skip
    assert run.returncode == 0, run.stderr
    assert "converted 1 file(s)" in run.stdout and "file/s" in run.stderr and "Traceback" not in run.stderr
    got = read_soma(tmp_path / "o" / "take.soma.npz", ConvertOptions()).motion
    assert got.fps == pytest.approx(59.94) and got.pose.shape == (4, 77, 3)


def test_a_broken_file_is_reported_and_the_rest_go_on(tmp_path, capsys):
    src = tmp_path / "in"
    good = [_motion(src / f"g{i}.npz", i) for i in range(3)]
    bad = _motion(src / "nan.npz", 9)
    data = dict(np.load(bad))
    data["pose"][2, 5, 1] = np.nan
    np.savez(bad, **data)
    (src / "cut.npz").write_bytes(b"PK\x03\x04 truncated")
    (src / "shape.npz").write_bytes(b"")  # empty: not even a zip
    np.savez(src / "notes.npz", betas=np.zeros(3))  # another kind of npz: skipped, listed
    code, out, err = _run(capsys, "convert", src, "--to", "motion", "--out", tmp_path / "out")
    assert code == 3
    lines = _error_lines(err)
    assert any("nan.npz: pose: expected finite values" in ln for ln in lines)
    assert any("cut.npz" in ln for ln in lines) and any("shape.npz" in ln for ln in lines)
    assert lines[-1] == f"unibody: error: 3 of 6 file(s) failed; see {tmp_path / 'out' / 'convert_report.json'}"
    for g in good:
        np.testing.assert_array_equal(load_motion(tmp_path / "out" / f"{g.stem}.motion.npz").pose, load_motion(g).pose)
    assert not (tmp_path / "out" / "nan.motion.npz").exists()
    report = {
        Path(r["input"]).name: r for r in json.loads((tmp_path / "out" / "convert_report.json").read_text())["files"]
    }
    assert report["nan.npz"]["status"] == "failed" and "expected finite values" in report["nan.npz"]["error"]
    assert report["notes.npz"]["status"] == "skipped" and report["g0.npz"]["status"] == "ok"
    # The broken file fixed: the rerun converts it alone.
    _motion(bad, 9)
    (src / "cut.npz").unlink()
    (src / "shape.npz").unlink()
    code, out, err = _run(capsys, "convert", src, "--to", "motion", "--out", tmp_path / "out")
    assert code == 0 and "converted 1 file(s)" in out and "3 done before" in out, err


def test_inputs_and_unknown_files_in_the_output_folder_are_never_overwritten(tmp_path, capsys):
    out = tmp_path / "out"
    inside = _motion(out / "a.motion.npz", 1)
    before = inside.read_bytes()
    for force in ([], ["--force"]):
        code, _, err = _run(capsys, "convert", inside, "--to", "motion", "--out", out, *force)
        assert code == 3 and inside.read_bytes() == before
        assert "is an input file" in _error_lines(err)[0]
    theirs = tmp_path / "out2" / "b.soma.npz"
    theirs.parent.mkdir()
    theirs.write_bytes(b"someone's file")
    src = _motion(tmp_path / "b.npz", 2)
    code, _, err = _run(capsys, "convert", src, "--to", "soma", "--out", theirs.parent)
    assert code == 3 and theirs.read_bytes() == b"someone's file"
    assert "b.soma.npz exists; pass --force to replace it" in _error_lines(err)[0]
    code, _, err = _run(capsys, "convert", src, "--to", "soma", "--out", theirs.parent, "--force")
    assert code == 0 and read_soma(theirs, ConvertOptions()).motion.pose.shape == (4, 77, 3)


def test_argument_errors_are_one_line(tmp_path, capsys):
    take = _motion(tmp_path / "t.npz")
    (tmp_path / "file").write_text("x")
    out = tmp_path / "o"
    cases = [
        (["--to", "fbx"], 2, "--to: expected one or more of motion, soma"),
        (["--to", ""], 2, "--to: expected one or more of"),
        (["--to", "motion", "--from", "c3d"], 2, "--from: expected one of motion, soma, amass"),
        (["--to", "motion", "--jobs", "0"], 2, "--jobs: expected a positive number of worker processes, got '0'"),
        (["--to", "motion", "--jobs", "two"], 2, "--jobs: expected a positive number"),
        (["--to", "motion", "--shard", "2/2"], 2, "--shard: expected i/N with 0 <= i < N (e.g. 0/4), got '2/2'"),
        (["--to", "motion", "--shard", "1"], 2, "--shard: expected i/N"),
        (["--to", "motion", "--executor", "dask"], 2, "--executor: expected local or ray, got 'dask'"),
        (["--to", "motion", "--preset", "best"], 2, "--preset: expected one of"),
        (["--to", "motion", "--units", "km"], 2, "--units: expected one of m, cm, mm, in, ft, got 'km'"),
        (["--to", "motion", "--batch", "0"], 2, "--batch: expected a positive number of frames"),
        (["--to", "motion", "--template", tmp_path / "none.obj"], 2, "--template: expected an existing"),
        (["--to", "motion", "--models", tmp_path / "nomodels"], 2, "--models: expected an existing"),
    ]
    for args, expected, needle in cases:
        code, stdout, err = _run(capsys, "convert", take, "--out", out, *args)
        lines = _error_lines(err)
        assert code == expected and len(lines) == 1 and needle in lines[0], (args, code, err)
    code, _, err = _run(capsys, "convert", tmp_path / "missing.npz", "--to", "motion", "--out", out)
    assert code == 3 and "missing.npz: no such file or folder" in _error_lines(err)[0]
    code, _, err = _run(capsys, "convert", take, "--to", "motion", "--out", tmp_path / "file")
    assert code == 4 and "is a file; name a folder" in _error_lines(err)[0]
    assert not out.exists()


def test_ray_missing_says_how_to_install(tmp_path, capsys, monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "ray" else real(name, *a))
    code, _, err = _run(capsys, "convert", _motion(tmp_path / "t.npz"), "--to", "motion", "--out", tmp_path / "o",
                        "--executor", "ray")  # fmt: skip
    assert code == 2 and "pip install 'unibody[ray]'" in _error_lines(err)[0]
