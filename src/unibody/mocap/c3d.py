"""Read and write labelled optical-marker trajectories: C3D (through ezc3d) and our npz.

Conventions: points are float64 metres in the file's own lab frame (most C3D labs are Z up;
nothing is rotated here), shape (T, M, 3), NaN for a missing sample. A C3D sample is missing
when its residual is negative (ezc3d already turns those into NaN) or when all three
coordinates are exactly zero (the old "zero means missing" convention, also used by SOMA).

Labels are bare: ``"Derrick:C7"`` becomes label ``"C7"`` with subject ``"Derrick"``, so two
subjects wearing the same marker set stay distinguishable through ``subjects``. Subjects come
from label prefixes only; an unprefixed label has subject ``""``. Unlabelled reconstructions
keep their slot name (``"*12"``).

Vicon Nexus stores Plug-in Gait model outputs as points too: joint angles, forces, moments,
powers, the centre of mass and the segment axes (``PELO/PELA/PELL/PELP``: origin, anterior,
lateral and proximal points of a segment). ``read_markers(..., markers_only=True)`` drops them,
see :func:`model_output_labels`.

The npz format holds ``format="unibody.markers/1"``, ``points`` (T, M, 3) float32 m,
``labels`` (M,) str, ``subjects`` (M,) str and ``rate`` (Hz); it loads without pickle.
"""

from __future__ import annotations

import math
import struct
import zipfile
import zlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = [
    "NPZ_FORMAT",
    "MarkerSequence",
    "model_output_labels",
    "read_markers",
    "write_c3d",
    "write_npz",
]

NPZ_FORMAT = "unibody.markers/1"

_UNIT_TO_M = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}
# POINT groups whose labels name model outputs rather than markers (Vicon Nexus, C3D.org).
_OUTPUT_GROUPS = ("ANGLES", "FORCES", "MOMENTS", "POWERS", "SCALARS", "REACTIONS", "MODELED_MARKERS")
# Plug-in Gait modelled markers that older Nexus files list in no group.
_OUTPUT_NAMES = frozenset({"CentreOfMass", "CentreOfMassFloor"})
_AXIS_POINTS = "OALP"  # origin, anterior, lateral, proximal point of a PiG segment frame


@dataclass(frozen=True)
class MarkerSequence:
    """T frames of M labelled marker trajectories.

    Attributes:
        points: (T, M, 3) float64 m, NaN for a missing sample.
        labels: M bare labels (no subject prefix); unlabelled slots keep their name (``"*12"``).
        subjects: M subject names, ``""`` for a label without a ``Subject:`` prefix.
        rate: frames per second (Hz).
    """

    points: np.ndarray
    labels: tuple[str, ...]
    subjects: tuple[str, ...]
    rate: float

    def __post_init__(self) -> None:
        pts = np.asarray(self.points, dtype=np.float64)
        if pts.ndim != 3 or pts.shape[2] != 3:
            raise ValueError(f"points: expected shape (T, M, 3), got {pts.shape}")
        m = pts.shape[1]
        labels, subjects = tuple(map(str, self.labels)), tuple(map(str, self.subjects))
        if len(labels) != m or len(subjects) != m:
            raise ValueError(f"labels/subjects: expected {m} entries each, got {len(labels)} and {len(subjects)}")
        if np.isinf(pts).any():
            raise ValueError("points: infinite values; use NaN for missing samples")
        if not (np.isfinite(self.rate) and self.rate > 0):
            raise ValueError(f"rate: expected a positive frame rate in Hz, got {self.rate}")
        object.__setattr__(self, "points", pts)
        object.__setattr__(self, "labels", labels)
        object.__setattr__(self, "subjects", subjects)
        object.__setattr__(self, "rate", float(self.rate))

    @property
    def num_frames(self) -> int:
        """T."""
        return self.points.shape[0]

    @property
    def num_markers(self) -> int:
        """M."""
        return self.points.shape[1]

    @property
    def visible(self) -> np.ndarray:
        """(T, M) bool, True where a sample is present."""
        return ~np.isnan(self.points).any(axis=2)

    @property
    def qualified_labels(self) -> tuple[str, ...]:
        """M labels with their subject prefix (``"Derrick:C7"``), bare where there is no subject."""
        return tuple(f"{s}:{x}" if s else x for x, s in zip(self.labels, self.subjects, strict=True))

    def _columns(self, idx: Sequence[int]) -> MarkerSequence:
        idx = list(idx)
        return MarkerSequence(
            self.points[:, idx],
            tuple(self.labels[i] for i in idx),
            tuple(self.subjects[i] for i in idx),
            self.rate,
        )

    def select(self, labels: Iterable[str]) -> MarkerSequence:
        """Only the columns ``labels``, in that order.

        A label is bare (``"C7"``) or qualified (``"Derrick:C7"``). Raises ValueError for a
        label that is absent, or that is bare and held by more than one subject.
        """
        qualified = self.qualified_labels
        idx = []
        for want in labels:
            hits = [i for i, q in enumerate(qualified) if q == want]
            if not hits and ":" not in want:
                hits = [i for i, x in enumerate(self.labels) if x == want]
            if not hits:
                raise ValueError(f"select: label {want!r} is not in the sequence ({', '.join(qualified)})")
            if len(hits) > 1:
                who = sorted({self.subjects[i] or "''" for i in hits})
                raise ValueError(
                    f"select: label {want!r} is held by {len(hits)} columns (subjects {', '.join(who)}); "
                    f"qualify it as 'Subject:{want}' or call .subject(name) first"
                )
            idx.append(hits[0])
        return self._columns(idx)

    def subject(self, name: str) -> MarkerSequence:
        """Only the columns of subject ``name`` (``""``: columns without a subject)."""
        idx = [i for i, s in enumerate(self.subjects) if s == name]
        if not idx:
            have = sorted(set(self.subjects))
            raise ValueError(f"subject: no columns for {name!r}; subjects: {have}")
        return self._columns(idx)

    def drop_empty(self) -> MarkerSequence:
        """Without the columns that are never visible."""
        return self._columns(np.flatnonzero(self.visible.any(axis=0)).tolist())


def model_output_labels(labels: Sequence[str], groups: dict[str, Sequence[str]] | None = None) -> set[str]:
    """The labels among ``labels`` that are model outputs, not markers.

    A label is an output when it is listed in one of the POINT groups ANGLES, FORCES,
    MOMENTS, POWERS, SCALARS, REACTIONS or MODELED_MARKERS (``groups`` maps a group name to
    its labels), when it is ``CentreOfMass``/``CentreOfMassFloor``, or when it is a segment
    axis: four characters ``XYZ`` + one of O/A/L/P with **all four** siblings ``XYZO``,
    ``XYZA``, ``XYZL``, ``XYZP`` present (a marker set never holds such a quadruple, while
    Plug-in Gait always writes the four together).

    Args:
        labels: bare labels.
        groups: POINT group name -> labels, as stored in the file.
    """
    groups = groups or {}
    out = {x for g in _OUTPUT_GROUPS for x in groups.get(g, ())}
    out |= _OUTPUT_NAMES
    present = set(labels)
    for x in present:
        if len(x) == 4 and x[3] in _AXIS_POINTS and all(x[:3] + c in present for c in _AXIS_POINTS):
            out.add(x)
    return out & present


def read_markers(path: str | Path, *, markers_only: bool = True) -> MarkerSequence:
    """Read a ``.c3d``, ``.trc`` (:mod:`unibody.mocap.trc`) or ``.npz`` marker file.

    Args:
        path: the file; the suffix picks the format.
        markers_only: C3D only; drop model outputs stored as points
            (:func:`model_output_labels`). Unlabelled ``*n`` slots are kept.

    Returns:
        The sequence, in metres.

    Raises:
        FileNotFoundError: no such file.
        ValueError: unknown suffix, or a malformed, truncated or unsupported file; the
            message names the file and the problem.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such marker file")
    suffix = path.suffix.lower()
    if suffix == ".c3d":
        return _read_c3d(path, markers_only)
    if suffix == ".npz":
        return _read_npz(path)
    if suffix == ".trc":
        from .trc import read_trc

        return read_trc(path)
    raise ValueError(f"{path}: unknown marker file type {suffix!r}; expected .c3d, .trc or .npz")


def write_npz(path: str | Path, seq: MarkerSequence) -> None:
    """Write ``seq`` in the npz format of this module (points stored as float32 m).

    Exactly at ``path`` (no ``.npz`` is appended), atomically: a reader sees the old file or the
    new one, and a failed write leaves the old one (:func:`unibody.io.atomic.save_npz`).
    """
    from ..io.atomic import save_npz

    save_npz(
        Path(path),
        format=np.array(NPZ_FORMAT),
        points=seq.points.astype(np.float32),
        labels=np.array(seq.labels, dtype=str).reshape(-1),
        subjects=np.array(seq.subjects, dtype=str).reshape(-1),
        rate=np.array(seq.rate, dtype=np.float64),
    )


def write_c3d(path: str | Path, seq: MarkerSequence) -> None:
    """Write ``seq`` as a C3D file in millimetres (float32).

    Missing samples are written as NaN with residual -1. Labels get a ``Subject:`` prefix
    where a subject is set, so :func:`read_markers` gives back the same labels and subjects.
    Written atomically at exactly ``path`` (:func:`unibody.io.atomic.atomic_path`).
    """
    import ezc3d

    from ..io.atomic import atomic_path

    t, m = seq.num_frames, seq.num_markers
    data = np.ones((4, m, t))
    data[:3] = seq.points.transpose(2, 1, 0) * 1e3
    missing = np.isnan(data[:3]).any(axis=0)
    data[:3, missing] = np.nan
    residuals = np.where(missing, -1.0, 0.0)[None]
    c = ezc3d.c3d()
    point = c["parameters"]["POINT"]
    point["RATE"]["value"] = [seq.rate]
    point["UNITS"]["value"] = ["mm"]
    point["LABELS"]["value"] = list(seq.qualified_labels)
    point["DESCRIPTIONS"]["value"] = [""] * m
    c["data"]["points"] = data
    c["data"]["meta_points"] = {"residuals": residuals, "camera_masks": np.zeros((7, m, t), dtype=bool)}
    with atomic_path(path) as tmp:
        c.write(str(tmp))


# --------------------------------------------------------------------------------------- npz


def _read_npz(path: Path) -> MarkerSequence:
    if not zipfile.is_zipfile(path):
        raise ValueError(f"{path}: not a readable npz file (not a zip archive)")
    try:
        with np.load(path, allow_pickle=False) as z:
            fmt = str(z["format"]) if "format" in z.files else None
            if fmt != NPZ_FORMAT:
                raise ValueError(f"{path}: expected an npz with format={NPZ_FORMAT!r}, got {fmt!r}")
            missing = [k for k in ("points", "labels", "subjects", "rate") if k not in z.files]
            if missing:
                raise ValueError(f"{path}: npz lacks the arrays {missing}")
            return MarkerSequence(
                z["points"].astype(np.float64),
                tuple(str(x) for x in z["labels"].reshape(-1)),
                tuple(str(x) for x in z["subjects"].reshape(-1)),
                float(z["rate"]),
            )
    except ValueError as e:
        msg = str(e)
        raise ValueError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from e
    except (OSError, EOFError, KeyError, zipfile.BadZipFile, zlib.error, struct.error, NotImplementedError) as e:
        # zip damage: a bad CRC, a corrupt deflate stream, a bad header, an unknown compression method
        raise ValueError(f"{path}: not a readable npz file ({e})") from e


# --------------------------------------------------------------------------------------- c3d


def _check_c3d_structure(path: Path) -> int:
    """Walk the header and parameter section before ezc3d sees the file.

    ezc3d segfaults on some corrupted parameter sections; this pure-Python walk of the
    C3D layout (c3d.org user guide: 512-byte header, then parameter blocks holding a
    chain of group/parameter records) turns those into ValueErrors. Returns the frame
    count that the header announces (ezc3d silently shortens truncated data and rewrites
    its header copy to match, so truncation is detected against this number).
    """
    size = path.stat().st_size
    with path.open("rb") as f:
        head = f.read(512)
        if len(head) < 512:
            raise ValueError(f"{path}: not a C3D file (only {size} bytes, shorter than the 512-byte header)")
        if head[1] != 0x50:
            raise ValueError(f"{path}: not a C3D file (header byte 2 is {head[1]:#04x}, expected 0x50)")
        start = (head[0] - 1) * 512
        if head[0] < 2 or start + 4 > size:
            raise ValueError(f"{path}: malformed C3D header (parameter block {head[0]} outside the file)")
        f.seek(start)
        lead = f.read(4)
        nblocks, proc = lead[2], lead[3]
        if proc not in (84, 85, 86):
            raise ValueError(f"{path}: malformed C3D parameter section (processor type {proc}, expected 84-86)")
        end = start + nblocks * 512
        if nblocks == 0 or end > size:
            raise ValueError(f"{path}: truncated C3D file (parameter section ends at byte {end}, file has {size})")
        f.seek(start)
        section = f.read(nblocks * 512)
    endian = ">" if proc == 86 else "<"
    _walk_parameters(path, section, endian)
    first, last = struct.unpack_from(endian + "HH", head, 6)
    return last - first + 1


def _walk_parameters(path: Path, sec: bytes, endian: str) -> None:
    def bad(pos: int, what: str) -> ValueError:
        return ValueError(f"{path}: malformed C3D parameter section at byte {pos}: {what}")

    groups: set[int] = set()
    used: set[int] = set()
    pos = 4
    while pos + 2 <= len(sec):
        nlen, gid = struct.unpack_from("bb", sec, pos)
        if nlen == 0 or gid == 0:
            break
        name_end = pos + 2 + abs(nlen)
        if name_end + 2 > len(sec):
            raise bad(pos, "record runs past the section")
        name = sec[pos + 2 : name_end]
        if not all(32 < c < 127 for c in name):
            raise bad(pos, f"non-ASCII name {name!r}")
        (offset,) = struct.unpack_from(endian + "h", sec, name_end)
        nxt = name_end + offset if offset else len(sec)
        if nxt <= name_end or nxt > len(sec):
            raise bad(pos, f"record {name.decode()} points to byte {nxt}")
        body = name_end + 2
        if gid < 0:
            groups.add(-gid)  # a group may be defined twice (BTKData PiG files do); ezc3d copes
        else:
            used.add(gid)
            try:
                body = _skip_parameter_data(sec, body, nxt)
            except ValueError as e:
                raise bad(pos, f"{name.decode()}: {e}") from None
        # ezc3d reads the description length as a signed byte and crashes on >= 128.
        if body >= nxt or sec[body] >= 128 or body + 1 + sec[body] > nxt:
            raise bad(pos, f"description of {name.decode()} has a bad length or runs past the record")
        if not offset:
            break
        pos = nxt
    if not groups or not used <= groups:
        raise bad(4, f"parameters refer to undefined groups {sorted(used - groups)}")


def _skip_parameter_data(sec: bytes, body: int, nxt: int) -> int:
    """Position just past a parameter's data; ValueError when the record cannot hold it."""
    if body + 2 > nxt:
        raise ValueError("header runs past the record")
    dtype, ndim = struct.unpack_from("bB", sec, body)
    if dtype not in (-1, 1, 2, 4):
        raise ValueError(f"unknown data type {dtype}")
    if ndim > 7:
        raise ValueError(f"{ndim} dimensions (at most 7)")
    count = math.prod(sec[body + 2 : body + 2 + ndim])
    data_end = body + 2 + ndim + abs(dtype) * count
    if data_end > nxt:
        raise ValueError(f"data ({count} values) runs past the record")
    return data_end


def _param(params: dict, group: str, name: str):
    g = params.get(group, {})
    return g[name]["value"] if name in g else None


def _group_labels(point: dict, base: str) -> list[str]:
    """``base`` + ``base2`` + ``base3`` ... (C3D splits long label lists at 255)."""
    out, k = [], 1
    while True:
        key = base if k == 1 else f"{base}{k}"
        if key not in point:
            return out
        out += [str(x) for x in point[key]["value"]]
        k += 1


def _split_label(raw: str) -> tuple[str, str]:
    """``"Derrick:C7 "`` -> (``"C7"``, ``"Derrick"``)."""
    subject, sep, label = raw.strip().partition(":")
    return (label.strip(), subject.strip()) if sep else (subject, "")


def _read_c3d(path: Path, markers_only: bool) -> MarkerSequence:
    import ezc3d

    frames = _check_c3d_structure(path)
    try:
        c = ezc3d.c3d(str(path))
    except (OSError, RuntimeError, ValueError, IndexError, MemoryError) as e:
        raise ValueError(f"{path}: not a readable C3D file ({e})") from e
    t = c["data"]["points"].shape[2]
    # The 16-bit header count wraps for files longer than 65535 frames: only a shortfall is an error.
    if t < frames:
        raise ValueError(f"{path}: truncated C3D file (the header announces {frames} frames, the data holds {t})")
    try:
        return _c3d_to_sequence(c, markers_only)
    except (ValueError, TypeError, KeyError, IndexError) as e:
        raise ValueError(f"{path}: {e}") from e


def _c3d_to_sequence(c, markers_only: bool) -> MarkerSequence:
    """Convert a loaded ``ezc3d.c3d`` to metres, NaN gaps, bare labels and subjects."""
    params, header = c["parameters"], c["header"]["points"]
    point = params.get("POINT", {})
    xyz = np.asarray(c["data"]["points"], dtype=np.float64)[:3]  # (3, M, T)
    m, t = xyz.shape[1], xyz.shape[2]
    units = _param(params, "POINT", "UNITS")
    unit = str(units[0]).strip().lower() if units is not None and len(units) else ""
    if m and unit not in _UNIT_TO_M:
        raise ValueError(f"unknown POINT:UNITS {unit!r}; expected one of {', '.join(_UNIT_TO_M)}")
    rate = _param(params, "POINT", "RATE")
    rate = float(rate[0]) if rate is not None and len(rate) else float(header["frame_rate"])
    raw = _group_labels(point, "LABELS")
    # Slots without a label get an unlabelled name, as moshpp does.
    raw = (raw + [f"*{i}" for i in range(len(raw), m)])[:m]
    labels, subjects = zip(*map(_split_label, raw), strict=True) if m else ((), ())
    pts = xyz.transpose(2, 1, 0) * _UNIT_TO_M.get(unit, 1.0)
    residuals = c["data"].get("meta_points", {}).get("residuals")
    missing = (pts == 0).all(axis=2)
    if residuals is not None and np.shape(residuals) == (1, m, t):
        missing |= residuals[0].T < 0
    pts[missing] = np.nan
    seq = MarkerSequence(pts, tuple(labels), tuple(subjects), rate)
    if markers_only:
        groups = {g: [_split_label(x)[0] for x in _group_labels(point, g)] for g in _OUTPUT_GROUPS}
        drop = model_output_labels(seq.labels, groups)
        seq = seq._columns([i for i, x in enumerate(seq.labels) if x not in drop])
    return seq
