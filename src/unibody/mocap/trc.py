"""Read TRC marker files (OpenSim's text format for labelled marker trajectories).

A TRC file is tab-separated text::

    PathFileType  4  (X/Y/Z)  name.trc
    DataRate  CameraRate  NumFrames  NumMarkers  Units  OrigDataRate  OrigDataStartFrame  OrigNumFrames
    60        60          600        41          mm     60            1                   600
    Frame#  Time  R.ASIS        L.ASIS        ...
                  X1  Y1  Z1    X2  Y2  Z2    ...
    (an optional blank line)
    1       0.0   809.0 1034.5 -64.6  797.3 ...

The header's names and values are matched by position among the non-empty tokens (exporters
pad them with extra tabs), the marker names come from line 4, every data row holds the frame
number, the time and three coordinates per marker; an empty coordinate (or a row cut short,
as some exporters write trailing missing markers) is a missing sample. Points are returned in
metres in the file's own frame (OpenSim's files are Y up: ``--up y``), as a
:class:`~unibody.mocap.c3d.MarkerSequence`.

Written by hand: the format is a few lines of text, and no maintained package reads it without
OpenSim itself.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..motion import MAX_DISTANCE
from .c3d import MarkerSequence, _split_label

__all__ = ["read_trc", "write_trc"]

_UNITS = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}
MAX_TRC_BYTES = 2**30
"""A TRC file larger than this (1 GiB: about 2 hours of 40 markers at 120 Hz) is refused before it is read."""


def read_trc(path: str | Path) -> MarkerSequence:
    """The labelled marker trajectories of a ``.trc`` file, in metres.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a TRC file, or a malformed one; the message names the file, the line and
            what was expected.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such marker file")
    if path.stat().st_size > MAX_TRC_BYTES:
        raise ValueError(f"{path}: {path.stat().st_size} bytes, more than a TRC file holds (at most {MAX_TRC_BYTES})")
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")  # older exporters write marker names in the system code page
    lines = text.splitlines()
    if not lines or not lines[0].startswith("PathFileType"):
        raise ValueError(f"{path}: not a TRC file (expected a first line starting with 'PathFileType')")
    if len(lines) < 5:
        raise ValueError(f"{path}: truncated TRC header: {len(lines)} line(s), expected at least 5")
    header = _header(path, lines[1], lines[2])
    rate = _number(path, header, "DataRate")
    if not (math.isfinite(rate) and rate > 0):
        raise ValueError(f"{path}: line 3: DataRate: expected a positive frame rate in Hz, got {header['DataRate']!r}")
    unit = header.get("Units", "")
    if unit.lower() not in _UNITS:
        raise ValueError(f"{path}: line 3: Units: expected one of mm, cm, m, got {unit!r}")
    names = [x.strip() for x in lines[3].split("\t")[2:]]
    names = [x for x in names if x]
    if not lines[3].startswith("Frame#") or not names:
        raise ValueError(f"{path}: line 4: expected 'Frame#', 'Time' and the marker names, got {lines[3][:60]!r}")
    if "NumMarkers" in header and _number(path, header, "NumMarkers") != len(names):
        raise ValueError(f"{path}: line 3: NumMarkers {header['NumMarkers']} but line 4 names {len(names)} markers")
    points = _rows(path, lines, len(names)) * _UNITS[unit.lower()]
    with np.errstate(invalid="ignore"):
        far = np.abs(points) > MAX_DISTANCE
    if far.any():
        t, m, _ = np.argwhere(far)[0]
        raise ValueError(
            f"{path}: frame {t + 1}, marker {names[m]!r}: a coordinate {np.abs(points[t, m]).max():.3g} m from the "
            f"origin, expected within {MAX_DISTANCE:g} m"
        )
    if "NumFrames" in header and _number(path, header, "NumFrames") != len(points):
        raise ValueError(f"{path}: line 3: NumFrames {header['NumFrames']} but the file holds {len(points)} frames")
    labels, subjects = zip(*(_split_label(x) for x in names), strict=True)
    if not all(labels):
        raise ValueError(f"{path}: line 4: marker {names[labels.index('')]!r} has no name after its subject")
    return MarkerSequence(points, labels, subjects, rate)


def write_trc(path: str | Path, seq: MarkerSequence) -> None:
    """Write ``seq`` as a TRC file in millimetres, as OpenSim writes them (missing samples: empty cells).

    Labels get a ``Subject:`` prefix where a subject is set, so :func:`read_trc` gives back the
    same labels, subjects and rate; coordinates keep 6 decimals of a millimetre. Written
    atomically at exactly ``path`` (:func:`unibody.io.atomic.atomic_path`).

    Raises:
        ValueError: no frame or no marker; a label holding a tab or a line break (the format's
            separators), or one that is empty or padded with spaces (readers strip them).
    """
    from ..io.atomic import atomic_path

    if seq.num_frames == 0 or seq.num_markers == 0:  # a TRC file holds at least one of each
        raise ValueError(f"seq: expected at least one frame and one marker, got {seq.points.shape}")
    names = seq.qualified_labels
    for name, label, subject in zip(names, seq.labels, seq.subjects, strict=True):
        if "\t" in name or len(f"{name}.".splitlines()) > 1:  # splitlines also breaks at \v, \x85, \u2028, ...
            raise ValueError(f"labels: a TRC label cannot hold a tab or a line break, got {name!r}")
        if not label.strip() or label != label.strip() or subject != subject.strip():
            raise ValueError(
                f"labels: a TRC label is read back stripped, so it cannot be empty or padded, got {name!r}"
            )
    t, m = seq.num_frames, seq.num_markers
    rate = f"{seq.rate:.12g}"
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{Path(path).name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        f"{rate}\t{rate}\t{t}\t{m}\tmm\t{rate}\t1\t{t}",
        "Frame#\tTime\t" + "".join(f"{x}\t\t\t" for x in names),
        "\t\t" + "\t".join(f"{a}{i + 1}" for i in range(m) for a in "XYZ"),
        "",
    ]
    mm = seq.points * 1e3
    for k in range(t):
        cells = ["" if math.isnan(x) else f"{x:.6f}" for x in mm[k].ravel()]
        lines.append(f"{k + 1}\t{k / seq.rate:.6f}\t" + "\t".join(cells))
    with atomic_path(path) as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n", encoding="utf-8")


def _header(path: Path, names: str, values: str) -> dict[str, str]:
    keys, vals = names.split(), values.split()
    if not keys or keys[0] != "DataRate":
        raise ValueError(f"{path}: line 2: expected the header names (DataRate, ..., Units, ...), got {names[:60]!r}")
    return dict(zip(keys, vals, strict=False))


def _number(path: Path, header: dict[str, str], key: str) -> float:
    if key not in header:
        raise ValueError(f"{path}: line 3: no value for {key}")
    try:
        return float(header[key])
    except ValueError:
        raise ValueError(f"{path}: line 3: {key}: expected a number, got {header[key]!r}") from None


def _rows(path: Path, lines: list[str], markers: int) -> np.ndarray:
    """(T, M, 3) coordinates in the file's unit, NaN where missing (rows from line 6; blank lines skipped)."""
    width = 3 * markers
    data = [k for k in range(5, len(lines)) if lines[k].strip()]
    if not data:
        raise ValueError(f"{path}: no data rows after the header")
    out = np.full((len(data), width), np.nan)
    for t, k in enumerate(data):
        fields = lines[k].split("\t") if "\t" in lines[k] else lines[k].split()
        coords = [x.strip() for x in fields[2:]]
        while coords and not coords[-1]:
            coords.pop()
        if len(coords) > width:
            raise ValueError(f"{path}: line {k + 1}: {len(coords)} coordinates, expected {width} ({markers} markers)")
        try:
            out[t, : len(coords)] = [float(x) if x else math.nan for x in coords]
        except ValueError:
            bad = next(x for x in coords if x and not _is_float(x))
            raise ValueError(f"{path}: line {k + 1}: expected numbers, got {bad[:30]!r}") from None
        if np.isinf(out[t]).any():
            raise ValueError(f"{path}: line {k + 1}: a coordinate is infinite (expected a number; empty: missing)")
    return out.reshape(len(data), markers, 3)


def _is_float(x: str) -> bool:
    try:
        float(x)
    except ValueError:
        return False
    return True
