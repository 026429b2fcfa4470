"""`unibody convert`'s machinery: formats detected from content, tasks planned from files and
folders, shards that cover the set exactly once, the local pool and Ray running the same task,
and a run killed mid-folder that resumes with only what is missing."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from unibody.convert import ConvertOptions
from unibody.convert.formats import FORMATS, NotAMotion, _load, detect, output_name, reader, writer
from unibody.convert.run import plan, run
from unibody.convert.soma import read_soma, write_soma
from unibody.motion import Motion, load_motion, save_motion

OPTS = ConvertOptions()


def _motion(seed: int = 0, frames: int = 4, fps: float = 25.0) -> Motion:
    gen = np.random.default_rng(seed)
    return Motion(
        (0.3 * gen.standard_normal((frames, 77, 3))).astype(np.float32),
        gen.standard_normal((frames, 3)).astype(np.float32),
        fps,
    )


def _folder(root: Path, n: int = 4) -> list[Path]:
    paths = []
    for i in range(n):
        path = root / f"s{i % 2}" / f"take{i}.npz"
        path.parent.mkdir(parents=True, exist_ok=True)
        save_motion(path, _motion(i, frames=3 + i))
        paths.append(path)
    return paths


# --------------------------------------------------------------------------- detection


BVH = "HIERARCHY\nROOT Hips\n{\n  OFFSET 0 0 0\n  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation\n"
AMC = "# AMC from the CMU database\n:FULLY-SPECIFIED\n:DEGREES\n1\nroot 0 17 0 0 0 0\nlowerback 1 2 3\n"
ASF = "# AST/ASF file\n:version 1.10\n:name VICON\n:units\n  mass 1.0\n:root\n  order TX TY TZ RX RY RZ\n:bonedata\n"


def test_formats_are_detected_from_content_not_suffix(tmp_path):
    made = {}
    save_motion(tmp_path / "a.data", _motion())
    made["a.data"] = "motion"
    write_soma(_motion(), tmp_path / "b.bin", OPTS)
    made["b.bin"] = "soma"
    np.savez(tmp_path / "h.npz", poses=np.zeros((2, 156)), trans=np.zeros((2, 3)), betas=np.zeros(16),
             gender=np.asarray("male"), mocap_framerate=np.asarray(120.0))  # fmt: skip
    made["h.npz"] = "amass"
    np.savez(tmp_path / "x.npz", root_orient=np.zeros((2, 3)), pose_body=np.zeros((2, 63)), trans=np.zeros((2, 3)),
             mocap_frame_rate=np.asarray(60.0), surface_model_type=np.asarray("smplx"))  # fmt: skip
    made["x.npz"] = "amass"
    np.savez(tmp_path / "m.npz", vertices=np.zeros((2, 5, 3), np.float32), topology=np.asarray("canonical"))
    made["m.npz"] = "meshes"
    (tmp_path / "walk.txt").write_text(BVH)
    made["walk.txt"] = "bvh"
    (tmp_path / "run.motion").write_text(AMC)
    made["run.motion"] = "asf"
    (tmp_path / "bare.amc").write_text("1\nroot 0 17 0 0 0 0\nlowerback 1 2 3\n2\nroot 0 17 0 0 0 0\n")
    made["bare.amc"] = "asf"
    for name, fmt in made.items():
        assert detect(tmp_path / name) == fmt, name

    (tmp_path / "09.asf").write_text(ASF)
    np.savez(tmp_path / "shape.npz", betas=np.zeros(16), gender=np.asarray("female"))
    (tmp_path / "noise.dat").write_bytes(bytes(range(256)))
    (tmp_path / "notes.txt").write_text("hello world\n")
    for name, message in [
        ("09.asf", "an ASF skeleton"),
        ("shape.npz", r"an .npz whose fields \(betas, gender\) are none of the motion formats"),
        ("noise.dat", "binary content"),
        ("notes.txt", "a text file starting with 'hello'"),
    ]:
        with pytest.raises(NotAMotion, match=f"{name}: {message}"):
            detect(tmp_path / name)
    # Named as a motion but unreadable: damaged, not another kind of file (reported, not skipped).
    (tmp_path / "broken.npz").write_bytes(b"PK\x03\x04 cut short")
    (tmp_path / "noise.npz").write_bytes(bytes(range(256)))
    (tmp_path / "bad.bvh").write_text("hello\n")
    for name in ("broken.npz", "noise.npz", "bad.bvh"):
        with pytest.raises(ValueError, match=name) as info:
            detect(tmp_path / name)
        assert not isinstance(info.value, NotAMotion), name


def test_registry_and_output_names():
    assert {f.suffix for f in FORMATS.values() if f.write} == {
        ".motion.npz", ".soma.npz", ".bvh", ".glb", ".usd", ".usda", ".meshes.npz"
    }  # fmt: skip
    assert reader("motion").__name__ == "read_motion" and writer("soma").__name__ == "write_soma"
    with pytest.raises(ValueError, match="format nope is not available .*ModuleNotFoundError"):
        _load("unibody.convert.nope:read_nope", "nope")
    with pytest.raises(ValueError, match="expected one of .* to read, got 'glb'"):
        reader("glb")
    assert output_name(Path("a/walk.npz"), "motion") == Path("a/walk.motion.npz")
    assert output_name(Path("walk.soma.npz"), "motion") == Path("walk.motion.npz")
    assert output_name(Path("02_01.bvh"), "usda") == Path("02_01.usda")
    assert output_name(Path("02_01.bvh"), "motion", keep_suffix=True) == Path("02_01.bvh.motion.npz")


# --------------------------------------------------------------------------- planning


def test_plan_mirrors_folders_skips_other_files_and_splits_into_shards(tmp_path):
    src, out = tmp_path / "in", tmp_path / "out"
    takes = _folder(src, 5)
    (src / "s0" / "09.asf").write_text(ASF)
    (src / "README.txt").write_text("CMU takes\n")
    (src / "s1" / "take1.bvh").write_text(BVH)  # meets take1.npz: both keep their suffix
    tasks, skipped = plan([src], ["motion", "soma"], out)
    assert sorted(Path(s["input"]).name for s in skipped) == ["09.asf", "README.txt"]
    by_name = {Path(t.input).name: t for t in tasks}
    assert set(by_name) == {p.name for p in takes} | {"take1.bvh"}
    assert by_name["take0.npz"].outputs == (
        ("motion", os.path.realpath(out / "s0" / "take0.motion.npz")),
        ("soma", os.path.realpath(out / "s0" / "take0.soma.npz")),
    )
    assert by_name["take1.bvh"].outputs[0][1].endswith("s1/take1.bvh.motion.npz")
    assert by_name["take1.npz"].outputs[0][1].endswith("s1/take1.npz.motion.npz")
    assert by_name["take1.bvh"].format == "bvh" and all(t.error is None for t in tasks)
    shards = [plan([src], ["motion"], out, shard=(i, 3))[0] for i in range(3)]
    inputs = [t.input for s in shards for t in s]
    assert sorted(inputs) == sorted(t.input for t in tasks) and len(set(inputs)) == len(inputs)
    # --from: only files of that format (or unrecognised ones with its suffix) from folders.
    tasks, skipped = plan([src], ["motion"], out, source="bvh")
    assert [Path(t.input).name for t in tasks] == ["take1.bvh"]


def test_a_broken_link_is_named_by_itself(tmp_path):
    """A link to nowhere in an input folder: before, its task was named by the missing target
    ("/nonexistent: /in/take.bvh: No such file or directory"); now by the link, saying so. A link
    to a real take is one task with it (the take converts once)."""
    src, out = tmp_path / "in", tmp_path / "out"
    takes = _folder(src, 1)
    (src / "gone.npz").symlink_to(tmp_path / "nowhere.npz")
    (src / "again.npz").symlink_to(takes[0])
    tasks, _ = plan([src], ["motion"], out)
    by_name = {Path(t.input).name: t for t in tasks}
    assert set(by_name) == {"gone.npz", takes[0].name}
    assert by_name["gone.npz"].error == f"{src / 'gone.npz'}: a broken link (to {tmp_path / 'nowhere.npz'})"
    assert by_name[takes[0].name].error is None


# --------------------------------------------------------------------------- executors


def _check_outputs(out: Path, takes: list[Path], src: Path, soma: bool = True) -> None:
    for take in takes:
        rel = take.relative_to(src)
        expected = load_motion(take)
        got = load_motion(out / rel.parent / (take.stem + ".motion.npz"))
        np.testing.assert_array_equal(got.pose, expected.pose)
        np.testing.assert_array_equal(got.transl, expected.transl)
        assert got.fps == pytest.approx(expected.fps)
        if soma:
            np.testing.assert_array_equal(read_soma(out / rel.parent / (take.stem + ".soma.npz"), OPTS).motion.pose,
                                          expected.pose)  # fmt: skip


def test_shards_cover_the_set_exactly_once(tmp_path):
    src, out = tmp_path / "in", tmp_path / "out"
    takes = _folder(src, 5)
    s0 = run([src], ["motion", "soma"], out, shard=(0, 2), progress=False)
    s1 = run([src], ["motion", "soma"], out, shard=(1, 2), progress=False)
    assert (s0.converted, s1.converted, s0.failed + s1.failed) == (3, 2, 0)
    _check_outputs(out, takes, src)
    reports = [json.loads((out / f"convert_report.{i}of2.json").read_text()) for i in range(2)]
    inputs = [r["input"] for rep in reports for r in rep["files"]]
    assert sorted(inputs) == sorted(os.path.realpath(t) for t in takes)
    assert not list(out.glob("*.journal"))
    whole = run([src], ["motion", "soma"], out, progress=False)  # the shards' work counts for an unsharded rerun
    assert (whole.done_before, whole.converted, whole.failed) == (5, 0, 0)


def test_jobs_2_runs_the_same_task_in_spawned_workers(tmp_path):
    src, out = tmp_path / "in", tmp_path / "out"
    takes = _folder(src, 4)
    summary = run([src], ["motion"], out, jobs=2, progress=False)  # motion only: the workers need no rig
    assert (summary.converted, summary.failed, summary.frames) == (4, 0, 3 + 4 + 5 + 6)
    _check_outputs(out, takes, src, soma=False)


def test_ray_executor_on_a_local_ray_with_2_cpus(tmp_path, monkeypatch):
    pytest.importorskip("ray")
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    src, out = tmp_path / "in", tmp_path / "out"
    takes = _folder(src, 3)
    summary = run([src], ["motion"], out, jobs=2, executor="ray", progress=False)
    assert (summary.converted, summary.failed) == (3, 0)
    _check_outputs(out, takes, src, soma=False)
    report = json.loads((out / "convert_report.json").read_text())
    assert report["summary"]["executor"] == "ray" and all(r["status"] == "ok" for r in report["files"])


# --------------------------------------------------------------------------- resume after a kill

SLOW = """
import sys, time
import unibody.convert.formats as formats
fast = formats.read_motion
def slow(path, options):
    time.sleep(0.4)
    return fast(path, options)
formats.read_motion = slow
from unibody.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_killed_run_resumes_with_only_what_is_missing(tmp_path):
    src, out = tmp_path / "in", tmp_path / "out"
    takes = _folder(src, 8)
    args = [str(src), "--to", "motion,soma", "--out", str(out)]
    proc = subprocess.Popen([sys.executable, "-c", SLOW, "convert", *args],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    journal = out / "convert_report.journal"
    deadline = time.monotonic() + 120
    done: list[dict] = []
    while time.monotonic() < deadline and proc.poll() is None:
        if journal.exists():
            lines = [json.loads(x) for x in journal.read_text().splitlines() if x.endswith("}")]
            done = [r for r in lines if r["status"] == "ok"]
            if len(done) >= 2:
                break
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL and 2 <= len(done) < 8
    assert not [p for p in out.rglob(".*") if p.is_file()]  # no temporary file left: outputs are atomic
    finished = {r["input"] for r in done}
    stamps = {o["path"]: os.stat(o["path"]).st_mtime_ns for r in done for o in r["outputs"]}

    summary = run([src], ["motion", "soma"], out, progress=False)
    assert summary.failed == 0 and summary.done_before >= len(finished)
    assert summary.done_before + summary.converted == 8
    assert all(os.stat(p).st_mtime_ns == t for p, t in stamps.items())  # finished work was not redone
    _check_outputs(out, takes, src)
    report = json.loads((out / "convert_report.json").read_text())
    assert len(report["files"]) == 8 and all(r["status"] == "ok" for r in report["files"])
    assert not journal.exists()
    again = run([src], ["motion", "soma"], out, progress=False)  # a third run has nothing to do
    assert (again.converted, again.done_before) == (0, 8)


def test_output_folder_inside_the_inputs_never_replaces_a_users_file(tmp_path):
    data = tmp_path / "data"
    a = _folder(data, 1)[0]  # data/s0/take0.npz
    mine = data / "s0" / "take1.npz"
    save_motion(mine, _motion(5))
    users = data / "s0" / "take1.motion.npz"  # the user's own file where take1's output would go
    save_motion(users, _motion(6))
    before = users.read_bytes()
    first = run([data], ["motion"], data, force=True, progress=False)
    # The user's file is an input: the two inputs that meet keep their suffixes, nothing is replaced.
    assert users.read_bytes() == before and (first.converted, first.failed) == (3, 0)
    names = sorted(p.name for p in (data / "s0").iterdir())
    assert names == sorted(["take0.npz", "take0.motion.npz", "take1.npz", "take1.npz.motion.npz", users.name,
                            "take1.motion.npz.motion.npz"])  # fmt: skip
    second = run([data], ["motion"], data, progress=False)  # our outputs are known as outputs now, not inputs
    assert (second.done_before, second.converted, second.failed, second.skipped) == (3, 0, 0, 3)
    assert users.read_bytes() == before
    report = {Path(r["input"]).name: r for r in json.loads((data / "convert_report.json").read_text())["files"]}
    assert report["take0.motion.npz"]["status"] == "skipped" and report[a.name]["status"] == "ok"
    assert report[users.name]["status"] == "ok" and report[mine.name]["status"] == "ok"
    # Two files of one name given directly would write the same output: both refused, nothing written.
    other = tmp_path / "other" / "take0.npz"
    save_motion(other.parent.mkdir() or other, _motion(7))
    tasks, _ = plan([a, other], ["motion"], tmp_path / "o")
    assert tasks[0].error is None and "would write the same outputs" in tasks[1].error


def test_ctrl_c_writes_the_report_and_the_rerun_finishes(tmp_path):
    src, out = tmp_path / "in", tmp_path / "out"
    _folder(src, 6)
    # SIGINT as a terminal delivers it, whatever the runner's disposition (a shell's background job
    # starts with SIGINT ignored, and Python then never raises KeyboardInterrupt)
    proc = subprocess.Popen([sys.executable, "-c", SLOW, "convert", str(src), "--to", "motion", "--out", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # fmt: skip
    journal = out / "convert_report.journal"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if journal.exists() and '"status": "ok"' in journal.read_text():
            break
        time.sleep(0.02)
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "unibody: interrupted" in stderr and "Traceback" not in stderr, stderr
    report = json.loads((out / "convert_report.json").read_text())
    status = [r["status"] for r in report["files"]]
    assert 1 <= status.count("ok") < 6 and set(status) <= {"ok", "running"} and not journal.exists()
    summary = run([src], ["motion"], out, progress=False)
    assert summary.done_before == status.count("ok") and summary.done_before + summary.converted == 6
