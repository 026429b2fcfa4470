"""The ``unibody`` command under careless and hostile use: one clear line, an exit code per
error class, no traceback unless --debug, and no input or earlier output ever lost."""

from __future__ import annotations

import os
import re
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from unibody.cli import main
from unibody.io.atomic import OutputError, atomic_path, check_output, output_lock, save_npz
from unibody.motion import Motion, load_motion, save_motion

UNIBODY = [sys.executable, "-c", "import sys; from unibody.cli import main; sys.exit(main())"]


def _motion(path: Path, frames: int = 3, **changes) -> Path:
    """A PCA motion (replays fast): small random poses, seeded."""
    gen = np.random.default_rng(frames)
    fields = dict(
        pose=(0.2 * gen.standard_normal((frames, 77, 3))).astype(np.float32),
        transl=np.zeros((frames, 3), np.float32),
        fps=30.0,
        identity=np.zeros(10, np.float32),
        identity_backend="pca",
    )
    fields.update(changes)
    save_motion(path, Motion(**fields))
    return path


def _run(capsys, *args: str) -> tuple[int, str, str]:
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


def _one_line_error(err: str, *needles: str) -> None:
    lines = [ln for ln in err.splitlines() if ln.startswith("unibody: error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file()}


# --------------------------------------------------------------------------- io.atomic


def test_check_output_refusals(tmp_path):
    src = tmp_path / "in.npz"
    src.write_bytes(b"x")
    with pytest.raises(OutputError, match=r"--out: .*in\.npz is the input file"):
        check_output(tmp_path / "." / "in.npz", inputs=[src], force=True)
    link = tmp_path / "link.npz"
    link.symlink_to(src)
    with pytest.raises(OutputError, match="is the input file"):
        check_output(link, inputs=[src], force=True)
    with pytest.raises(OutputError, match=r"exists; pass --force"):
        check_output(src)
    with pytest.raises(OutputError, match=r"expected a \.npz file, got '.*\.txt'"):
        check_output(tmp_path / "a.txt", suffixes=[".npz"])
    with pytest.raises(OutputError, match=r"folder .*missing does not exist"):
        check_output(tmp_path / "missing" / "a.npz")
    with pytest.raises(OutputError, match=r"is a folder"):
        check_output(tmp_path)
    assert check_output(tmp_path / "new.NPZ", suffixes=[".npz"]) == tmp_path / "new.NPZ"


def test_atomic_write_failure_keeps_the_old_file(tmp_path):
    out = tmp_path / "out.npz"
    save_npz(out, a=np.arange(3))
    before = out.read_bytes()
    with pytest.raises(RuntimeError), atomic_path(out) as tmp:
        tmp.write_bytes(b"half")
        raise RuntimeError("writer died")
    assert out.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["out.npz"]
    with pytest.raises(OutputError, match="empty file"), atomic_path(out):
        pass  # a writer that wrote nothing
    assert out.read_bytes() == before


def test_atomic_write_replaces_a_link_not_its_target(tmp_path):
    victim, link = tmp_path / "victim", tmp_path / "out.npz"
    victim.write_bytes(b"precious")
    link.symlink_to(victim)
    save_npz(link, a=np.zeros(2))
    assert victim.read_bytes() == b"precious" and not link.is_symlink()
    assert np.load(link)["a"].shape == (2,)


def test_save_npz_writes_exactly_the_path_and_keeps_umask(tmp_path):
    out = tmp_path / "motion"  # numpy's savez would write motion.npz
    save_npz(out, a=np.zeros(1))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["motion"]
    umask = os.umask(0)
    os.umask(umask)
    assert out.stat().st_mode & 0o777 == 0o666 & ~umask


def test_output_lock_refuses_a_second_writer(tmp_path):
    out = tmp_path / "out.npz"
    with output_lock(out):
        with pytest.raises(OutputError, match="another process is writing"), output_lock(out):
            pass
    with output_lock(out):  # released: free again, and no lock file left behind
        pass
    assert not (tmp_path / "out.npz.lock").exists()


# --------------------------------------------------------------------------- readers


@pytest.mark.parametrize(
    "content, message",
    [
        (b"", "empty or truncated"),
        (b"\x80\x04K\x01.", "pickled objects are never loaded"),
        (bytes(range(256)) * 4, "not a readable .npz file"),
    ],
)
def test_pose_refuses_non_npz_files(tmp_path, capsys, content, message):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(content)
    code, out, err = _run(capsys, "pose", bad, "--out", tmp_path / "out.npz")
    assert code == 3 and out == ""
    _one_line_error(err, "bad.npz", message)


def test_motion_reader_checks_fields(tmp_path):
    good = _motion(tmp_path / "good.npz")
    data = dict(np.load(good))
    for key, value, message in [
        ("fps", np.asarray(np.nan, np.float32), "fps: expected a positive number"),
        ("fps", np.asarray(-30.0, np.float32), "fps: expected a positive number"),
        ("pose", np.zeros((3, 76, 3), np.float32), r"pose: expected shape \(T, 77, 3\)"),
        ("pose", np.full((3, 77, 3), np.inf, np.float32), "pose: expected finite values"),
        ("pose", np.zeros((3, 77, 3), np.int64), "pose: expected floating-point numbers"),
        ("transl", np.zeros((2, 3), np.float32), r"transl: expected shape \(3, 3\)"),
        ("transl", np.full((3, 3), 2e5, np.float32), r"transl: expected the root within 100000 m .* 2e\+05 m at frame"),
        ("identity", np.full(10, np.nan, np.float32), "identity: expected finite values"),
        ("identity_backend", np.zeros(3), "identity_backend: expected a string"),
    ]:
        bad = tmp_path / f"bad_{key}.npz"
        np.savez(bad, **{**data, key: value})
        with pytest.raises(ValueError, match=f"bad_{key}.npz: {message}"):
            load_motion(bad)
    np.savez(tmp_path / "nokey.npz", **{k: v for k, v in data.items() if k != "transl"})
    with pytest.raises(ValueError, match="missing field 'transl'"):
        load_motion(tmp_path / "nokey.npz")
    with pytest.raises(ValueError, match="fps: expected a positive number"):
        save_motion(tmp_path / "x.npz", Motion(data["pose"], data["transl"], 0.0))
    # float64 values past float32's range were written as inf (the file then refused on reading)
    huge = data["pose"].astype(np.float64)
    huge[1, 5, 2] = 1e300
    expected = r"^pose: expected values within float32's range \(\+-3.4e\+38\), got 1 beyond it \(up to 1e\+300\)$"
    with pytest.raises(ValueError, match=expected):
        save_motion(tmp_path / "x.npz", Motion(huge, data["transl"], 30.0))
    assert not (tmp_path / "x.npz").exists()


# --------------------------------------------------------------------------- errors and exit codes


def test_errors_are_one_line_with_their_exit_code(tmp_path, capsys):
    motion = _motion(tmp_path / "m.npz")
    out = tmp_path / "meshes.npz"
    cases = [
        (("pose", tmp_path / "missing.npz", "--out", out), 3, ["missing.npz: no such file"]),
        (("pose", motion, "--out", tmp_path / "meshes"), 4, ["--out: expected a .npz file"]),
        (("pose", motion, "--out", tmp_path / "no" / "m.npz"), 4, ["does not exist"]),
        (("invert", motion, "--out", out, "--batch", "0"), 2, ["--batch: expected a positive number", "got 0"]),
        (("invert", motion, "--out", out, "--batch", "-3"), 2, ["--batch"]),
        (("invert", motion, "--out", out, "--preset", "best"), 2, ["--preset: expected one of"]),
        (("invert", motion, "--out", out), 3, ["m.npz: missing field(s) topology, vertices"]),
        (("mocap", "label", motion, "--out", tmp_path / "l.txt"), 4, ["expected a .c3d or .npz or .trc file"]),
        (("mocap", "solve", motion, "--out", tmp_path / "x.c3d"), 4, ["expected a .npz file"]),
        (("demo", "--backends", "smpl2"), 2, ["--backends: unknown backend 'smpl2'"]),
        (("demo", "--backends", "pca=3"), 2, ["--backends: pca ships with unibody and takes no path, got 'pca=3'"]),
    ]
    for args, expected, needles in cases:
        code, stdout, err = _run(capsys, *args)
        assert code == expected, (args, code, err)
        _one_line_error(err, *needles)
    assert not out.exists()


def test_pose_checks_motion_metadata(tmp_path, capsys):
    smpl = _motion(tmp_path / "smpl.npz", identity_backend="smpl")
    code, _, err = _run(capsys, "pose", smpl, "--out", tmp_path / "o.npz")
    assert code == 3
    _one_line_error(err, "smpl.npz: identity_backend", "'smpl'")
    empty = _motion(tmp_path / "empty.npz", frames=0)
    code, _, err = _run(capsys, "pose", empty, "--out", tmp_path / "o.npz")
    assert code == 3
    _one_line_error(err, "empty.npz: pose: expected at least one frame")
    anny10 = _motion(tmp_path / "anny10.npz", identity_backend="anny")  # 10 numbers are not 6 phenotypes
    code, _, err = _run(capsys, "pose", anny10, "--out", tmp_path / "o.npz")
    assert code == 3
    _one_line_error(err, "anny10.npz", "identity params")
    assert not (tmp_path / "o.npz").exists()


def test_debug_prints_the_traceback(tmp_path, capsys):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"")
    code, _, err = _run(capsys, "pose", bad, "--out", tmp_path / "o.npz", "--debug")
    assert code == 3 and "Traceback" in err and "unibody: error:" in err


def test_internal_errors_say_so(tmp_path, capsys, monkeypatch):
    import unibody.cli as cli

    def broken(*args, **kwargs):
        raise ZeroDivisionError("oops")

    monkeypatch.setattr(cli, "run_pose", broken)
    code, _, err = _run(capsys, "pose", "x.npz", "--out", tmp_path / "o.npz")
    assert code == 1
    _one_line_error(err, "internal error (ZeroDivisionError: oops)", "--debug")


# --------------------------------------------------------------------------- no data lost


def test_output_is_never_the_input_nor_silently_replaced(tmp_path, capsys):
    motion = _motion(tmp_path / "m.npz")
    before = motion.read_bytes()
    code, _, err = _run(capsys, "pose", motion, "--out", motion, "--force")
    assert code == 4 and motion.read_bytes() == before
    _one_line_error(err, "is the input file")
    out = tmp_path / "meshes.npz"
    assert _run(capsys, "pose", motion, "--out", out)[0] == 0
    first = out.read_bytes()
    code, _, err = _run(capsys, "pose", motion, "--out", out)
    assert code == 4 and out.read_bytes() == first
    _one_line_error(err, "exists; pass --force")
    other = _motion(tmp_path / "m2.npz", frames=2)
    assert _run(capsys, "pose", other, "--out", out, "--force")[0] == 0
    assert np.load(out)["vertices"].shape[0] == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.npz", "m2.npz", "meshes.npz"]


def test_second_writer_is_refused(tmp_path, capsys):
    motion, out = _motion(tmp_path / "m.npz"), tmp_path / "meshes.npz"
    with output_lock(out):  # another unibody process writing the same output
        code, _, err = _run(capsys, "pose", motion, "--out", out)
    assert code == 4 and not out.exists()
    _one_line_error(err, "another process is writing")


def _limit_file_size():
    resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000))  # `ulimit -f`: a full disk after 200 kB


def test_full_disk_keeps_the_previous_output(tmp_path, capsys):
    motion, out = _motion(tmp_path / "m.npz"), tmp_path / "meshes.npz"
    assert _run(capsys, "pose", motion, "--out", out)[0] == 0
    before = _snapshot(tmp_path)
    run = subprocess.run(
        [*UNIBODY, "pose", str(motion), "--out", str(out), "--force"],
        capture_output=True, text=True, preexec_fn=_limit_file_size, timeout=300,
    )  # fmt: skip
    assert run.returncode == 4, run.stderr
    _one_line_error(run.stderr, "cannot write")
    assert _snapshot(tmp_path) == before  # the old output intact, no temporary or lock file left


def test_kill_during_write_leaves_old_output(tmp_path, capsys):
    motion, out = _motion(tmp_path / "m.npz", frames=400), tmp_path / "meshes.npz"
    out.write_bytes(b"previous good output")
    proc = subprocess.Popen(
        [*UNIBODY, "pose", str(motion), "--out", str(out), "--force"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    deadline = time.monotonic() + 240
    while proc.poll() is None and time.monotonic() < deadline:
        if any(p.name.startswith(".meshes.npz.") for p in tmp_path.iterdir()):
            break  # the temporary output exists: the write is under way
        time.sleep(0.005)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=60)
    if out.read_bytes() != b"previous good output":  # only a run that finished before the kill may replace it
        assert proc.returncode == 0 and np.load(out)["vertices"].shape[0] == 400


def _seq(path: Path, frames: int) -> Path:
    from unibody import BodyLayer

    layer = BodyLayer.from_pca(num_components=10)
    gen = torch.Generator().manual_seed(frames)
    with torch.no_grad():
        prepared = layer.prepare_identity(torch.zeros(1, 10))
        verts = layer.pose(prepared, 0.15 * torch.randn(frames, 77, 3, generator=gen)).vertices
    np.savez(path, vertices=verts.numpy(), topology=np.asarray("canonical"))
    return path


def test_ctrl_c_exits_130_and_resumes(tmp_path):
    seq, out = _seq(tmp_path / "seq.npz", 12), tmp_path / "motion.npz"
    partial = tmp_path / "motion.npz.partial.npz"
    args = [*UNIBODY, "invert", str(seq), "--out", str(out), "--batch", "2", "--preset", "fast"]
    proc = subprocess.Popen(  # SIGINT as a terminal delivers it, even under a runner that ignores it
        args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip
    deadline = time.monotonic() + 240
    while not partial.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=120)
    if proc.returncode == 0:  # finished before the signal arrived: nothing to resume
        pytest.skip("the run finished before Ctrl-C")
    assert proc.returncode == 130 and "Traceback" not in stderr, stderr
    assert "rerun the same command to resume" in stderr and partial.is_file() and not out.exists()
    saved = len(np.load(partial)["pose"])
    rerun = subprocess.run(args, capture_output=True, text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stderr
    assert f"{saved}/12 frames already inverted" in rerun.stderr and not partial.exists()
    assert load_motion(out).pose.shape == (12, 77, 3)


@pytest.mark.parametrize("content", [b"", b"PK\x03\x04 truncated", None])
def test_broken_partial_file_starts_over(tmp_path, capsys, content):
    seq, out = _seq(tmp_path / "seq.npz", 3), tmp_path / "motion.npz"
    partial = tmp_path / "motion.npz.partial.npz"
    if content is None:  # a partial file of another input
        save_npz(partial, key=np.asarray("other"), pose=np.zeros((2, 77, 3)), transl=np.zeros((2, 3)),
                 error=np.zeros(2))  # fmt: skip
    else:
        partial.write_bytes(content)
    code, stdout, err = _run(capsys, "invert", seq, "--out", out, "--preset", "fast")
    assert code == 0, err
    assert "warning: starting over" in err and "wrote" in stdout and not partial.exists()
    assert load_motion(out).pose.shape == (3, 77, 3)


def test_demo_backend_files_are_named(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("UNIBODY_SMPL_FILE", raising=False)
    bad = tmp_path / "bad.pkl"
    bad.write_bytes(b"garbage")
    for spec, code, needle in [
        (f"smpl={bad}", 3, "bad.pkl: not a loadable pickle"),
        (f"smpl={tmp_path / 'none.pkl'}", 3, "no SMPL-family model file at"),
        ("smpl", 2, "--backends: smpl needs its model files"),
        (f"mhr={tmp_path}", 3, "rig.npz is missing"),
    ]:
        got, _, err = _run(capsys, "demo", "--backends", spec, "--out", tmp_path / "d")
        assert got == code, err
        _one_line_error(err, needle)
    assert not (tmp_path / "d").exists()


def test_npz_zip_bomb_is_refused(tmp_path, capsys):
    """A 1 GiB array of zeros deflates to ~1 MB: refused before numpy allocates it."""
    import zipfile

    bomb = tmp_path / "bomb.npz"
    header = b"\x93NUMPY\x01\x00v\x00{'descr': '<f4', 'fortran_order': False, 'shape': (1398101, 77, 3), }"
    header = header + b" " * (127 - len(header)) + b"\n"
    with (
        zipfile.ZipFile(bomb, "w", compression=zipfile.ZIP_DEFLATED) as z,
        z.open("pose.npy", "w", force_zip64=True) as f,
    ):
        f.write(header)
        zeros = bytes(1 << 24)
        for _ in range(64):
            f.write(zeros)
    assert bomb.stat().st_size < 3 << 20
    code, _, err = _run(capsys, "pose", bomb, "--out", tmp_path / "o.npz")
    assert code == 3
    _one_line_error(err, "bomb.npz: member 'pose.npy' would expand", "zip bomb")


@pytest.mark.parametrize(
    ("offset", "value", "why"),
    [
        (8, 0x01, "is encrypted"),
        (8, 0x40, "is strongly encrypted"),
        (10, 77, "unknown method (77)"),
        (6, 109, "zip file version 10.9"),
    ],
    ids=["encrypted", "strong-encryption", "method", "version"],
)
def test_npz_members_zipfile_cannot_open_are_refused(tmp_path, capsys, offset, value, why):
    """A motion whose central directory says its pose member is encrypted, compressed by an unknown
    method or of a newer zip version (found by the long fuzz run: NotImplementedError /
    RuntimeError from zipfile before): one line naming the file, exit 3; load_motion too."""
    path = _motion(tmp_path / "m.npz")
    raw = bytearray(path.read_bytes())
    entry = raw.index(b"PK\x01\x02")  # the central directory's entries; the name starts at byte 46
    while raw[entry + 46 : entry + 54] != b"pose.npy":
        entry = raw.index(b"PK\x01\x02", entry + 4)
    raw[entry + offset : entry + offset + 2] = value.to_bytes(2, "little")
    path.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match=re.escape(why)):
        load_motion(path)
    code, _, err = _run(capsys, "pose", path, "--out", tmp_path / "o.npz")
    assert code == 3
    _one_line_error(err, "m.npz", why)


def test_warnings_are_one_line(tmp_path, capsys, monkeypatch):
    import warnings

    import unibody.cli.body_commands as cli

    seq, out = _seq(tmp_path / "seq.npz", 2), tmp_path / "motion.npz"
    original = cli._load_partial

    def warn_once(*args, **kwargs):
        warnings.warn("something to know", UserWarning, stacklevel=1)
        return original(*args, **kwargs)

    monkeypatch.setattr(cli, "_load_partial", warn_once)
    code, _, err = _run(capsys, "invert", seq, "--out", out, "--preset", "fast")
    assert code == 0 and "unibody: warning: something to know\n" in err and "warnings.warn" not in err


def _markers(path: Path, points: np.ndarray) -> Path:
    from unibody.mocap.c3d import MarkerSequence, write_npz

    n = points.shape[1]
    write_npz(path, MarkerSequence(points, tuple(f"*{i}" for i in range(n)), ("",) * n, 100.0))
    return path


def test_mocap_label_refuses_wrong_units_and_unlabellable_files(tmp_path, capsys):
    from test_mocap_pipeline import smooth_sequence
    from unibody.mocap.layout import MarkerLayout
    from unibody.mocap.solve import unibody_to_lab

    markers, _ = smooth_sequence(MarkerLayout.load("cmu41"), frames=4)
    lab = unibody_to_lab(markers.numpy(), up="z")
    mm = _markers(tmp_path / "mm.npz", 1000 * lab)
    code, out, err = _run(capsys, "mocap", "label", mm, "--out", tmp_path / "o.npz", "--per-frame")
    assert code == 3 and out == ""
    _one_line_error(err, "mm.npz: the points are not in metres", "divide by 1000")
    apart = np.zeros((4, 2, 3))
    apart[:, 1, 0] = 5.0  # two points 5 m apart per frame: nothing to label
    sparse = _markers(tmp_path / "apart.npz", apart)
    code, out, err = _run(capsys, "mocap", "label", sparse, "--out", tmp_path / "o.npz", "--per-frame")
    assert code == 3 and out == ""
    _one_line_error(err, "apart.npz: no frame could be labelled", "4 of 4 frames")
    assert not (tmp_path / "o.npz").exists()


def test_invert_keeps_the_frame_rate(tmp_path, capsys):
    seq, out = _seq(tmp_path / "seq.npz", 3), tmp_path / "motion.npz"
    data = dict(np.load(seq))
    np.savez(seq, **data, fps=np.asarray(120.0))
    code, _, err = _run(capsys, "invert", seq, "--out", out, "--preset", "fast")
    assert code == 0, err
    motion = load_motion(out)
    assert motion.fps == 120.0 and motion.source == "meshes: seq.npz"
    np.savez(seq, **data, fps=np.asarray(-5.0))
    code, _, err = _run(capsys, "invert", seq, "--out", out, "--preset", "fast", "--force")
    assert code == 3
    _one_line_error(err, "seq.npz: fps: expected a positive number")


def test_pose_writes_the_motion_frame_rate(tmp_path, capsys):
    motion = _motion(tmp_path / "m.npz", fps=48.0)
    code, _, err = _run(capsys, "pose", motion, "--out", tmp_path / "meshes.npz")
    assert code == 0, err
    from unibody.motion import load_mesh_sequence

    assert load_mesh_sequence(tmp_path / "meshes.npz").fps == 48.0


def test_writing_onto_a_folder_is_refused_by_name(tmp_path):
    """A folder given as the file to write: the temporary file was made beside the folder and
    the rename failed as `IsADirectoryError: ... '.tmp.x.tmp' -> 'out'`; now one line, nothing
    left beside it."""
    folder = tmp_path / "out"
    folder.mkdir()
    motion = Motion(pose=np.zeros((2, 77, 3), np.float32), transl=np.zeros((2, 3), np.float32), fps=30.0)
    with pytest.raises(OutputError, match=r"out: is a folder; expected the path of a file to write"):
        save_motion(folder, motion)
    with pytest.raises(OutputError, match=r"is a folder"):
        save_npz(folder, x=np.zeros(3))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"] and not any(folder.iterdir())
    with pytest.raises(TypeError, match=r"motion: expected a unibody.motion.Motion, got str"):
        save_motion(tmp_path / "m.npz", "walk.npz")
