"""C3D / npz marker I/O: real evaluation files, a generated C3D, round trips and bad files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

ezc3d = pytest.importorskip("ezc3d")

from unibody.mocap.c3d import (  # noqa: E402
    NPZ_FORMAT,
    MarkerSequence,
    model_output_labels,
    read_markers,
    write_c3d,
    write_npz,
)

EVAL = Path("/work/shared/evaldata")
MANIFEST = EVAL / "manifest.json"
C3D_ENTRIES = [e for e in json.loads(MANIFEST.read_text()) if e["format"] == "c3d"] if MANIFEST.is_file() else []
needs_evaldata = pytest.mark.skipif(not C3D_ENTRIES, reason="no /work/shared/evaldata (evaluation data absent)")


def _bare(label: str) -> str:
    return label.split(":", 1)[-1]


_CACHE: dict[tuple[str, bool], MarkerSequence] = {}


def _read(rel: str, markers_only: bool = True) -> MarkerSequence:
    key = (rel, markers_only)
    if key not in _CACHE:
        _CACHE[key] = read_markers(EVAL / rel, markers_only=markers_only)
    return _CACHE[key]


# ------------------------------------------------------------------------ real evaluation data


@needs_evaldata
@pytest.mark.parametrize("entry", C3D_ENTRIES, ids=lambda e: Path(e["path"]).stem)
def test_evaldata_labels_frames_rate(entry):
    seq = _read(entry["path"])
    physical = [_bare(x) for x in entry["physical_labels"]]
    unlabeled = entry["unlabeled_labels"]
    # markers_only keeps exactly the physical markers and the unlabelled '*n' slots.
    assert sorted(seq.labels) == sorted(physical + unlabeled)
    full = _read(entry["path"], markers_only=False)
    assert set(full.labels) >= set(physical)
    assert full.num_markers == entry["n_points_in_file"]
    assert seq.num_frames == full.num_frames == entry["n_frames"]
    assert seq.rate == pytest.approx(entry["rate_hz"])
    assert seq.points.shape == (entry["n_frames"], len(physical) + len(unlabeled), 3)


@needs_evaldata
@pytest.mark.parametrize("entry", C3D_ENTRIES, ids=lambda e: Path(e["path"]).stem)
def test_evaldata_units_and_missing_samples(entry):
    seq = _read(entry["path"])
    z = seq.points[..., 2]  # every file here is Z up
    floor = np.nanmin(z, axis=1)
    for subject in sorted(set(seq.subjects)):
        sub = seq.subject(subject)
        c7 = sub.points[:, sub.labels.index("C7"), 2]
        # A mm file read as m (or the reverse) would be off by 1000x.
        assert 1.0 < np.nanmedian(c7 - floor) < 1.8
    # NaN pattern against the manifest's independent visibility statistics.
    phys = np.array([not x.startswith("*") for x in seq.labels])
    assert seq.visible[:, phys].mean() == pytest.approx(entry["physical_visible_fraction"], abs=1e-4)
    assert int((~seq.visible[:, phys]).any(axis=1).sum()) == entry["frames_with_any_physical_missing"]
    ghosts_per_frame = seq.visible[:, ~phys].sum(axis=1).mean() if (~phys).any() else 0.0
    assert ghosts_per_frame == pytest.approx(entry["unlabeled_visible_per_frame_mean"], abs=0.01)


@needs_evaldata
def test_evaldata_subject_prefixes():
    by_name = {Path(e["path"]).name: e for e in C3D_ENTRIES}
    for name, entry in by_name.items():
        seq = _read(entry["path"])
        prefixes = {x.split(":", 1)[0] for x in entry["physical_labels"] if ":" in x}
        assert set(seq.subjects) == (prefixes or {""}), name
        assert set(seq.qualified_labels) >= set(entry["physical_labels"]), name


@needs_evaldata
def test_evaldata_two_subjects_match_the_single_recording():
    """The composite file is the single serve twice: cross-check subjects and values."""
    two = _read("c3d/ktk_kinematics_tennis_serve_2players.c3d")
    with pytest.raises(ValueError, match="held by 2 columns"):
        two.select(["C7"])
    derrick = two.subject("Derrick")
    viktor = two.subject("Viktor").select(derrick.labels)
    np.testing.assert_array_equal(two.select(["Viktor:C7"]).points, viktor.select(["C7"]).points)
    one = _read("c3d/ktk_kinematics_tennis_serve.c3d").select(derrick.labels)
    t = two.num_frames
    # Measured offsets: Derrick = frames 51.., Viktor = frames 251.. moved by (+2, -2, 0) m.
    np.testing.assert_allclose(derrick.points, one.points[51 : 51 + t], atol=1e-6)
    np.testing.assert_allclose(viktor.points, one.points[251 : 251 + t] + [2.0, -2.0, 0.0], atol=1e-5)


@needs_evaldata
def test_evaldata_py_c3d_failure_files_read():
    # py-c3d fails on these two (duplicate BODYMASS parameter); we must not.
    for name in ("btkdata_PiG_Calibration-FlatFoot-Full.c3d", "btkdata_PiG_Motion-FlatFoot-One.c3d"):
        assert read_markers(EVAL / "c3d" / name).num_markers == 35


# --------------------------------------------------------------------------- generated C3D


MARKERS = ["Ann:LFHD", "Ann:C7", "Bob:LFHD", "Bob:C7", "*3"]
OUTPUTS = ["PELO", "PELA", "PELL", "PELP", "LHipAngles", "CentreOfMass"]


def _make_c3d(path: Path, *, unit: str = "mm", frames: int = 30, seed: int = 0) -> dict:
    """Write a C3D with ezc3d directly (independent of write_c3d); return the truth in metres."""
    rng = np.random.default_rng(seed)
    labels = MARKERS + OUTPUTS
    m = len(labels)
    scale = {"mm": 1e3, "cm": 1e2, "m": 1.0}.get(unit, 1e3)
    truth = rng.uniform(-2.0, 2.0, size=(frames, m, 3))
    truth[..., 2] += 3.0
    residual = np.zeros((frames, m))
    residual[rng.random((frames, m)) < 0.1] = -1.0  # coordinates kept: the residual alone marks them
    zero = rng.random((frames, m)) < 0.05
    data = np.ones((4, m, frames))
    data[:3] = (truth * scale).transpose(2, 1, 0)
    data[:3, zero.T] = 0.0
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [120.0]
    c["parameters"]["POINT"]["UNITS"]["value"] = [unit]
    c["parameters"]["POINT"]["LABELS"]["value"] = labels
    c["parameters"]["POINT"]["DESCRIPTIONS"]["value"] = [""] * m
    c.add_parameter("POINT", "ANGLES", ["LHipAngles"])
    c["data"]["points"] = data
    c["data"]["meta_points"] = {
        "residuals": residual.T[None],
        "camera_masks": np.zeros((7, m, frames), dtype=bool),
    }
    c.write(str(path))
    missing = (residual < 0) | zero
    return {"points": np.where(missing[..., None], np.nan, truth), "labels": labels}


def test_generated_c3d_read(tmp_path):
    path = tmp_path / "gen.c3d"
    truth = _make_c3d(path)
    seq = read_markers(path)
    assert seq.labels == ("LFHD", "C7", "LFHD", "C7", "*3")
    assert seq.subjects == ("Ann", "Ann", "Bob", "Bob", "")
    assert seq.rate == 120.0
    want = truth["points"][:, : len(MARKERS)]
    np.testing.assert_array_equal(np.isnan(seq.points), np.isnan(want))
    np.testing.assert_allclose(seq.points, want, atol=1e-4)
    full = read_markers(path, markers_only=False)
    assert full.labels[len(MARKERS) :] == tuple(OUTPUTS)
    np.testing.assert_allclose(full.points, truth["points"], atol=1e-4)
    bob = seq.subject("Bob")
    assert bob.labels == ("LFHD", "C7")
    np.testing.assert_array_equal(seq.select(["Bob:C7", "Ann:LFHD"]).points, seq.points[:, [3, 0]], strict=True)


@pytest.mark.parametrize("unit", ["mm", "cm", "m"])
def test_units_to_metres(tmp_path, unit):
    truth = _make_c3d(tmp_path / "u.c3d", unit=unit)
    seq = read_markers(tmp_path / "u.c3d", markers_only=False)
    np.testing.assert_allclose(seq.points, truth["points"], atol=1e-4)


def test_unknown_unit_raises(tmp_path):
    _make_c3d(tmp_path / "in.c3d", unit="in")
    with pytest.raises(ValueError, match=r"in\.c3d: unknown POINT:UNITS 'in'"):
        read_markers(tmp_path / "in.c3d")


@pytest.mark.parametrize("fmt", ["c3d", "npz"])
def test_write_read_round_trip(tmp_path, fmt):
    _make_c3d(tmp_path / "gen.c3d")
    seq = read_markers(tmp_path / "gen.c3d")
    out = tmp_path / f"out.{fmt}"
    (write_c3d if fmt == "c3d" else write_npz)(out, seq)
    back = read_markers(out)
    assert back.labels == seq.labels and back.subjects == seq.subjects
    assert back.rate == seq.rate and back.points.dtype == np.float64
    np.testing.assert_array_equal(np.isnan(back.points), np.isnan(seq.points))
    np.testing.assert_allclose(back.points, seq.points, atol=1e-4)
    if fmt == "npz":
        with np.load(out, allow_pickle=False) as z:
            assert str(z["format"]) == NPZ_FORMAT and z["points"].dtype == np.float32


def test_round_trip_more_than_255_labels(tmp_path):
    # C3D stores labels past 255 in LABELS2; all must come back, in order.
    rng = np.random.default_rng(1)
    m = 300
    pts = rng.normal(size=(4, m, 3))
    pts[1, 7] = np.nan
    seq = MarkerSequence(pts, tuple(f"M{i}" for i in range(m)), ("",) * m, 60.0)
    write_c3d(tmp_path / "big.c3d", seq)
    back = read_markers(tmp_path / "big.c3d")
    assert back.labels == seq.labels
    np.testing.assert_allclose(back.points, seq.points, atol=1e-4)


# ------------------------------------------------------------------------------ bad files


def _param_record(raw: bytes, name: bytes) -> int:
    """Byte position of the record named ``name`` in the parameter section (name-length byte)."""
    start = (raw[0] - 1) * 512
    pos = raw.index(name, start)
    return pos - 2


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda raw: b"", "shorter than the 512-byte header"),
        (lambda raw: b"hello world\n" * 100, "not a C3D file"),
        (lambda raw: bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8)), "not a C3D file"),
        (lambda raw: raw[:600], "truncated C3D file"),
        (lambda raw: raw[: len(raw) - 700], "truncated C3D file"),
    ],
    ids=["empty", "text", "random", "cut-in-parameters", "cut-in-data"],
)
def test_garbage_raises_value_error(tmp_path, make, match):
    _make_c3d(tmp_path / "ok.c3d", frames=60)
    bad = tmp_path / "bad.c3d"
    bad.write_bytes(make((tmp_path / "ok.c3d").read_bytes()))
    with pytest.raises(ValueError, match=match) as err:
        read_markers(bad)
    assert str(bad) in str(err.value)


def test_corrupt_parameter_record_raises_instead_of_crashing(tmp_path):
    """A parameter turned into a group record with a 255-byte description crashes ezc3d 1.7.2."""
    _make_c3d(tmp_path / "ok.c3d")
    raw = bytearray((tmp_path / "ok.c3d").read_bytes())
    at = _param_record(bytes(raw), b"LABELS")
    raw[at + 1] = 256 - 9  # group id 9, negative: now a group record
    raw[at + 2 + 6 + 2] = 255  # its "description length" (was the data-type byte)
    (tmp_path / "bad.c3d").write_bytes(bytes(raw))
    with pytest.raises(ValueError, match="malformed C3D parameter section"):
        read_markers(tmp_path / "bad.c3d")


def test_impossible_dimensions_raise(tmp_path):
    _make_c3d(tmp_path / "ok.c3d")
    raw = bytearray((tmp_path / "ok.c3d").read_bytes())
    at = _param_record(bytes(raw), b"LABELS")
    raw[at + 2 + 6 + 3] = 40  # number of dimensions
    (tmp_path / "bad.c3d").write_bytes(bytes(raw))
    with pytest.raises(ValueError, match="40 dimensions"):
        read_markers(tmp_path / "bad.c3d")


def test_missing_file_and_suffix_and_bad_npz(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.c3d"):
        read_markers(tmp_path / "nope.c3d")
    (tmp_path / "x.tsv").write_text("x")
    with pytest.raises(ValueError, match=r"x.tsv: unknown marker file type '.tsv'; expected \.c3d, \.trc or \.npz"):
        read_markers(tmp_path / "x.tsv")
    (tmp_path / "x.trc").write_text("x")
    with pytest.raises(ValueError, match=r"x.trc: not a TRC file"):
        read_markers(tmp_path / "x.trc")
    np.savez(tmp_path / "other.npz", points=np.zeros((1, 1, 3)))
    with pytest.raises(ValueError, match="other.npz: expected an npz with format"):
        read_markers(tmp_path / "other.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="junk.npz: not a readable npz"):
        read_markers(tmp_path / "junk.npz")
    np.savez(tmp_path / "short.npz", format=NPZ_FORMAT, points=np.zeros((2, 1, 3)), labels=np.array(["A"]))
    with pytest.raises(ValueError, match=r"short.npz: npz lacks the arrays \['subjects', 'rate'\]"):
        read_markers(tmp_path / "short.npz")


# ---------------------------------------------------------------------------- MarkerSequence


def _seq() -> MarkerSequence:
    pts = np.arange(4 * 4 * 3, dtype=float).reshape(4, 4, 3)
    pts[:, 3] = np.nan
    pts[2, 0] = np.nan
    return MarkerSequence(pts, ("A", "B", "A", "*1"), ("S", "S", "T", ""), 100)


def test_sequence_helpers():
    seq = _seq()
    assert seq.num_frames == 4 and seq.num_markers == 4
    assert seq.visible[:, 3].sum() == 0 and not seq.visible[2, 0] and seq.visible[2, 1]
    sel = seq.select(["B", "T:A", "S:A"])
    np.testing.assert_array_equal(sel.points, seq.points[:, [1, 2, 0]])
    assert sel.subjects == ("S", "T", "S")
    assert seq.subject("T").labels == ("A",)
    assert seq.drop_empty().labels == ("A", "B", "A")
    assert seq.qualified_labels == ("S:A", "S:B", "T:A", "*1")


def test_sequence_errors():
    seq = _seq()
    with pytest.raises(ValueError, match="label 'RFHD' is not in the sequence"):
        seq.select(["B", "RFHD"])
    with pytest.raises(ValueError, match="'A' is held by 2 columns"):
        seq.select(["A"])
    with pytest.raises(ValueError, match="no columns for 'U'"):
        seq.subject("U")
    with pytest.raises(ValueError, match=r"expected shape \(T, M, 3\)"):
        MarkerSequence(np.zeros((2, 3)), ("A",), ("",), 10)
    with pytest.raises(ValueError, match="expected 2 entries each"):
        MarkerSequence(np.zeros((1, 2, 3)), ("A",), ("", ""), 10)
    with pytest.raises(ValueError, match="positive frame rate"):
        MarkerSequence(np.zeros((1, 1, 3)), ("A",), ("",), 0)
    with pytest.raises(ValueError, match="infinite"):
        MarkerSequence(np.full((1, 1, 3), np.inf), ("A",), ("",), 10)


def test_model_output_rule():
    labels = ["PELO", "PELA", "PELL", "PELP", "LKNO", "LTOE", "RTOE", "RBAK", "CentreOfMass", "LHipAngles", "*1"]
    out = model_output_labels(labels, {"ANGLES": ["LHipAngles"]})
    # A lone xxxO label is not a segment axis; the full O/A/L/P quadruple is.
    assert out == {"PELO", "PELA", "PELL", "PELP", "CentreOfMass", "LHipAngles"}


def test_damaged_npz_raises_value_error_naming_the_file(tmp_path):
    """A flipped byte inside a stored array (bad CRC: zipfile.BadZipFile) or in its compression
    method field (NotImplementedError) used to escape as those types (found by tests/fuzz)."""
    seq = MarkerSequence(np.ones((4, 3, 3)), ("A", "B", "C"), ("", "", ""), 100.0)
    write_npz(tmp_path / "ok.npz", seq)
    data = (tmp_path / "ok.npz").read_bytes()
    for where, value in ((len(data) // 2, 0), (int(0.8057 * len(data)), 1)):
        bad = bytearray(data)
        bad[where] = value
        (tmp_path / "bad.npz").write_bytes(bytes(bad))
        try:
            read_markers(tmp_path / "bad.npz")
        except ValueError as e:
            assert str(tmp_path / "bad.npz") in str(e)
