"""TRC marker files (unibody.mocap.trc): real OpenSim files against numpy's own parse, the
format's variations, hostile files, and the commands that read markers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from smpl_format import evaldata_dir
from unibody.cli import main
from unibody.mocap.c3d import MarkerSequence, read_markers
from unibody.mocap.trc import read_trc, write_trc

REAL = sorted((evaldata_dir() / "trc").glob("*.trc"))


def _trc(names, rows, *, units="mm", rate="60", eol="\n", header_gap="\t", num_frames=None) -> str:
    """A TRC text: ``rows`` are lists of coordinate strings ('' = missing), frame and time added."""
    n = len(rows) if num_frames is None else num_frames
    keys = ["DataRate", "CameraRate", "NumFrames", "NumMarkers", "Units", "OrigDataRate", "OrigDataStartFrame"]
    vals = [rate, rate, str(n), str(len(names)), units, rate, "1"]
    lines = [
        "PathFileType\t4\t(X/Y/Z)\tsynthetic.trc",
        "\t".join(keys),
        header_gap.join(vals),
        "Frame#\tTime\t" + "\t\t\t".join(names) + "\t\t",
        "\t\t" + "\t".join(f"{a}{i + 1}" for i in range(len(names)) for a in "XYZ"),
        "",
    ]
    lines += [f"{t + 1}\t{t / 60:.5f}\t" + "\t".join(r) for t, r in enumerate(rows)]
    return eol.join(lines) + eol


@pytest.mark.skipif(not REAL, reason="no TRC files under the evaluation data")
@pytest.mark.parametrize("path", REAL, ids=lambda p: p.stem)
def test_real_opensim_files_match_numpys_parse(path):
    seq = read_trc(path)
    header = path.read_text().splitlines()[3].split("\t")[2:]
    names = [x for x in header if x.strip()]
    assert seq.labels == tuple(names) and seq.subjects == ("",) * len(names)
    ref = np.genfromtxt(path, delimiter="\t", skip_header=5, usecols=range(2, 2 + 3 * len(names)))
    assert seq.points.shape == (len(ref), len(names), 3) and seq.rate in (60.0, 100.0)
    assert np.allclose(seq.points, ref.reshape(len(ref), -1, 3) / 1000, rtol=1e-15, atol=0, equal_nan=True)  # mm -> m
    assert 1.0 < np.nanmax(seq.points[..., 1]) < 2.0  # Y up: the head marker 1-2 m above the floor
    assert read_markers(path).points.shape == seq.points.shape


def test_variations_exporters_write(tmp_path):
    rows = [["1000", "2000", "3000", "", "", "", "7", "8", "9"], ["1100", "2000", "3000"]]
    rows.append(["nan", "1", "2", "4", "5", "6"])
    path = tmp_path / "take.trc"
    text = _trc(["Derrick:C7", "LFHD", "Rücken"], rows, units="cm", eol="\r\n", header_gap="\t\t")
    path.write_bytes(text.encode("latin-1"))  # CRLF, doubled header tabs, a latin-1 name
    seq = read_trc(path)
    assert seq.labels == ("C7", "LFHD", "Rücken") and seq.subjects == ("Derrick", "", "")
    assert seq.rate == 60.0 and seq.points.shape == (3, 3, 3)
    assert np.allclose(seq.points[0, 0], [10.0, 20.0, 30.0]) and np.allclose(seq.points[0, 2], [0.07, 0.08, 0.09])
    vis = seq.visible
    assert vis.tolist() == [[True, False, True], [True, False, False], [False, True, False]]  # empty, cut short, NaN


def test_written_files_read_back_and_parse_as_opensim_writes_them(tmp_path):
    g = np.random.default_rng(1)
    points = g.normal(0, 0.8, (7, 4, 3))
    points[2, 1] = np.nan
    points[6, 3] = np.nan  # a trailing missing marker: empty cells at the end of the row
    seq = MarkerSequence(points, ("C7", "LFHD", "*3", "RFHD"), ("Derrick", "", "", "Viktor"), 120.0)
    path = tmp_path / "out.trc"
    write_trc(path, seq)
    back = read_trc(path)
    assert back.labels == seq.labels and back.subjects == seq.subjects and back.rate == 120.0
    assert np.allclose(back.points, points, atol=1e-9, equal_nan=True)  # 6 decimals of a millimetre
    ref = np.genfromtxt(path, delimiter="\t", skip_header=5)  # numpy's parse: frame, time, 12 coordinates
    assert ref.shape == (7, 14) and np.allclose(ref[:, 1], np.arange(7) / 120.0, atol=1e-6)
    assert np.allclose(ref[:, 2:].reshape(7, 4, 3) / 1000, points, atol=1e-9, equal_nan=True)
    lines = path.read_text().splitlines()
    assert lines[0] == "PathFileType\t4\t(X/Y/Z)\tout.trc" and lines[2].split("\t")[2:5] == ["7", "4", "mm"]
    with pytest.raises(ValueError, match="labels: a TRC label cannot hold a tab or a line break, got .a.tb."):
        write_trc(tmp_path / "x.trc", MarkerSequence(points[:, :1], ("a\tb",), ("",), 120.0))
    with pytest.raises(ValueError, match=r"seq: expected at least one frame and one marker, got \(0, 1, 3\)"):
        write_trc(tmp_path / "x.trc", MarkerSequence(points[:0, :1], ("a",), ("",), 120.0))
    assert not (tmp_path / "x.trc").exists()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda t: "PathFile\n" + t, "not a TRC file"),
        (lambda t: "\n".join(t.splitlines()[:3]), "truncated TRC header: 3 line(s)"),
        (lambda t: t.replace("\tmm\t", "\tinch\t"), "line 3: Units: expected one of mm, cm, m, got 'inch'"),
        (lambda t: t.replace("60\t60\t2", "-60\t60\t2"), "line 3: DataRate: expected a positive frame rate"),
        (lambda t: t.replace("60\t60\t2", "fast\t60\t2"), "line 3: DataRate: expected a number, got 'fast'"),
        (lambda t: t.replace("\t2\t2\tmm", "\t5\t2\tmm"), "line 3: NumFrames 5 but the file holds 2 frames"),
        (lambda t: t.replace("\t2\t2\tmm", "\t2\t3\tmm"), "line 3: NumMarkers 3 but line 4 names 2 markers"),
        (lambda t: t.replace("\t4\t5\t6", "\t4\t5\tabc"), "line 7: expected numbers, got 'abc'"),
        (lambda t: t.replace("\t4\t5\t6", "\t4\t5\t1e999"), "line 7: a coordinate is infinite"),
        (lambda t: t.replace("\t4\t5\t6", "\t4\t5\t6\t7"), "line 7: 7 coordinates, expected 6 (2 markers)"),
        (lambda t: t.replace("\t4\t5\t6", "\t4\t5\t1e12"), "frame 1, marker 'B': a coordinate 1e+09 m from the origin"),
        (lambda t: t.replace("Frame#", "Frames"), "line 4: expected 'Frame#', 'Time' and the marker names"),
        (lambda t: "\n".join(t.splitlines()[:6]), "no data rows after the header"),
        (lambda t: t.replace("\tB\t", "\tSubj:\t"), "line 4: marker 'Subj:' has no name after its subject"),
    ],
)
def test_hostile_files_are_refused_in_one_line_naming_the_file(tmp_path, change, message):
    path = tmp_path / "bad.trc"
    path.write_text(change(_trc(["A", "B"], [["1", "2", "3", "4", "5", "6"], ["1", "2", "3", "4", "5", "6"]])))
    with pytest.raises(ValueError, match="bad.trc: ") as err:
        read_trc(path)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_commands_read_trc(tmp_path, capsys):
    g = np.random.default_rng(0)
    rows = [[f"{x:.3f}" for x in 1000 * (g.random(3 * 8) + [0, 1, 0] * 8)] for _ in range(6)]
    path = tmp_path / "take.trc"
    path.write_text(_trc([f"M{i}" for i in range(8)], rows))
    assert main(["view", str(path), "--up", "y", "--record", str(tmp_path / "x.png"), "--size", "64x48"]) == 0
    assert (tmp_path / "x_0000.png").is_file() or (tmp_path / "x.png").is_file()
    assert main(["mocap", "label", str(path), "--up", "y", "--out", str(tmp_path / "l.npz")]) == 0
    labelled = read_markers(tmp_path / "l.npz")
    assert labelled.num_frames == 6 and math.isclose(labelled.rate, 60.0)
    assert main(["mocap", "label", str(path), "--up", "y", "--out", str(tmp_path / "l.trc")]) == 0
    same = read_markers(tmp_path / "l.trc")
    assert same.labels == labelled.labels and np.allclose(same.points, labelled.points, atol=1e-6, equal_nan=True)
    capsys.readouterr()
    bad = tmp_path / "bad.trc"
    bad.write_text("PathFileType\t4\n")
    assert main(["view", str(bad), "--record", str(tmp_path / "y.png")]) == 3
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "bad.trc: truncated TRC header" in err


def test_a_take_recorded_with_the_other_vertical_axis_gets_a_note(tmp_path, capsys):
    from unibody.mocap.frames import vertical_note

    g = np.random.default_rng(2)
    standing = g.uniform(0, 1, (20, 30, 3)) * [0.5, 1.6, 0.3]  # metres, Y up
    standing[3, :25] = np.nan  # a frame with too few points is skipped
    assert vertical_note(standing, "y") is None
    note = vertical_note(standing, "z")
    assert note.startswith("the markers span 1.") and note.endswith("if the lab is Y up, pass --up y")
    z_up = standing[..., [0, 2, 1]]
    assert vertical_note(z_up, "z") is None and "pass --up z" in vertical_note(z_up, "y")
    assert vertical_note(np.full((4, 3, 3), np.nan), "z") is None
    for path in REAL:  # OpenSim's files are Y up; the C3D files Z up
        seq = read_trc(path)
        assert vertical_note(seq.points, "y") is None and "pass --up y" in vertical_note(seq.points, "z")
    for path in sorted((evaldata_dir() / "c3d").glob("*.c3d")):
        assert vertical_note(read_markers(path).points, "z") is None, path.name
    rows = [[f"{x:.3f}" for x in 1000 * p.ravel()] for p in standing[:6]]
    take = tmp_path / "take.trc"
    take.write_text(_trc([f"M{i}" for i in range(30)], rows))
    assert main(["mocap", "label", str(take), "--out", str(tmp_path / "l.npz")]) == 0
    assert f"unibody: note: {take}: the markers span" in capsys.readouterr().err
    assert main(["mocap", "label", str(take), "--up", "y", "--out", str(tmp_path / "m.npz")]) == 0
    assert "note" not in capsys.readouterr().err
