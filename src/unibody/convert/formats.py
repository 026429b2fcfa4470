"""The formats ``unibody convert`` reads and writes, and detection of a file's format from its content.

Readers and writers live in their own modules and are imported by dotted name only when a file
needs them (:func:`reader`, :func:`writer`), so a format whose optional dependency is missing
fails with one line ("format X is not available: ...") and the others still run. Detection
reads the file's content, never its suffix: the keys of an ``.npz``, the first words of a text.
"""

from __future__ import annotations

import functools
import importlib
import re
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ..motion import MOTION_FORMAT, Motion, check_motion, load_motion, save_motion
from ._types import Converted, ConvertOptions

__all__ = [
    "FORMATS",
    "READERS",
    "WRITERS",
    "Format",
    "NotAMotion",
    "detect",
    "output_name",
    "read_motion",
    "reader",
    "write_motion",
    "writer",
]


@dataclass(frozen=True, slots=True)
class Format:
    """One format: where its reader and writer are (``"module:function"``) and its file names.

    Attributes:
        name: the name ``--from`` / ``--to`` take.
        read: dotted ``module:function`` of the reader, None if the format is not read.
        write: dotted ``module:function`` of the writer, None if the format is not written.
        suffix: suffix of the files the writer makes (e.g. ``".motion.npz"``).
        inputs: suffixes of this format's input files, for ``--from`` on folders (files whose
            content is not recognised are taken when their suffix is one of these).
    """

    name: str
    read: str | None
    write: str | None
    suffix: str | None
    inputs: tuple[str, ...] = ()


FORMATS: dict[str, Format] = {
    f.name: f
    for f in (
        Format("motion", f"{__name__}:read_motion", f"{__name__}:write_motion", ".motion.npz", (".npz",)),
        Format("soma", "unibody.convert.soma:read_soma", "unibody.convert.soma:write_soma", ".soma.npz", (".npz",)),
        Format("amass", "unibody.convert.amass:read_amass", None, None, (".npz",)),
        Format(
            "meshes",
            "unibody.convert.meshes:read_meshes",
            "unibody.convert.export:write_meshes",
            ".meshes.npz",
            (".npz",),
        ),  # fmt: skip
        Format("bvh", "unibody.convert.skeletal:read_bvh", "unibody.convert.bvh_export:write_bvh", ".bvh", (".bvh",)),
        Format("asf", "unibody.convert.skeletal:read_amc", None, None, (".amc",)),
        Format("glb", None, "unibody.convert.export:write_glb", ".glb"),
        Format("usd", None, "unibody.convert.export:write_usd", ".usd"),
        Format("usda", None, "unibody.convert.export:write_usd", ".usda"),
    )
}
READERS = tuple(n for n, f in FORMATS.items() if f.read)
"""Formats ``--from`` takes (``asf``: CMU's ASF/AMC motions, given as the ``.amc`` files)."""
WRITERS = tuple(n for n, f in FORMATS.items() if f.write)
"""Formats ``--to`` takes (``usd`` writes the binary crate, ``usda`` the text form)."""


class NotAMotion(ValueError):
    """A file whose content is none of the formats read (the message names it and what it holds)."""


def _load(target: str, fmt: str) -> Callable:
    module, _, name = target.partition(":")
    try:
        return getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"format {fmt} is not available ({type(exc).__name__}: {exc})") from None


def reader(fmt: str) -> Callable[[Path, ConvertOptions], Converted]:
    """The reader of ``fmt``: ``(path, options) -> Converted``, its motion checked.

    The motion has at least one frame and passes :func:`unibody.motion.check_motion` (finite,
    within float32's range and :data:`~unibody.motion.MAX_DISTANCE`), or a ValueError names the file.

    Raises:
        ValueError: ``fmt`` is not read, or its module cannot be imported ("format X is not available").
    """
    spec = FORMATS.get(fmt)
    if spec is None or spec.read is None:
        raise ValueError(f"format: expected one of {', '.join(READERS)} to read, got {fmt!r}")
    read = _load(spec.read, fmt)

    @functools.wraps(read)
    def checked(path: Path, options: ConvertOptions) -> Converted:
        _check_call(path, options)
        converted = read(path, options)
        check_motion(converted.motion, f"{path}: ")  # one rule for what any reader gives
        if len(converted.motion.pose) == 0:
            raise ValueError(f"{path}: expected at least one frame, got 0")
        return converted

    return checked


def writer(fmt: str) -> Callable:
    """The writer of ``fmt``: ``(motion, path, options) -> None``, writing exactly ``path`` atomically.

    Raises:
        ValueError: ``fmt`` is not written, or its module cannot be imported.
    """
    spec = FORMATS.get(fmt)
    if spec is None or spec.write is None:
        raise ValueError(f"format: expected one of {', '.join(WRITERS)} to write, got {fmt!r}")
    write = _load(spec.write, fmt)

    @functools.wraps(write)
    def checked(motion, path: Path, options: ConvertOptions) -> None:  # noqa: ANN001 (a Motion)
        if not isinstance(motion, Motion):
            raise TypeError(f"motion: expected a unibody.motion.Motion, got {type(motion).__name__}")
        _check_call(path, options)
        write(motion, path, options)

    return checked


def _check_call(path: object, options: object) -> None:
    """TypeError naming ``path`` or ``options`` when a reader or writer is called with the wrong types."""
    if not isinstance(path, str | Path):
        raise TypeError(f"path: expected a file path, got {type(path).__name__}")
    if not isinstance(options, ConvertOptions):
        raise TypeError(f"options: expected a ConvertOptions, got {type(options).__name__}")


def read_motion(path: Path, options: ConvertOptions) -> Converted:
    """Read a ``unibody.motion/1`` file (:func:`unibody.motion.load_motion`)."""
    motion = load_motion(path)
    return Converted(motion, {"frames": len(motion.pose), "fps": motion.fps})


def write_motion(motion, path: Path, options: ConvertOptions) -> None:
    """Write a ``unibody.motion/1`` file, atomically, exactly at ``path``."""
    save_motion(path, motion)


# --------------------------------------------------------------------------- detection

_AMC_FRAME = re.compile(r"^\s*\d+\s*$")
_AMC_LINE = re.compile(r"^\s*[A-Za-z_][\w.-]*(\s+[-+0-9.eE]+)+\s*$")


def _npz_format(path: Path) -> str:
    from ..io.npz import read_npz

    with read_npz(path) as data:
        keys = set(data.files)
        if "format" in keys:
            fmt = data["format"]
            if fmt.shape == () and fmt.dtype.kind in "US" and str(fmt) == MOTION_FORMAT:
                return "motion"
        if {"poses", "identity_model_type", "rotation_repr"} <= keys:
            return "soma"
        if {"poses", "trans"} <= keys and keys & {"mocap_framerate", "mocap_frame_rate"}:
            return "amass"
        if keys & {"root_orient", "pose_body"}:
            return "amass"
        if "vertices" in keys:
            return "meshes"
        shown = ", ".join(sorted(keys)[:12]) + (", ..." if len(keys) > 12 else "")
        raise NotAMotion(f"{path}: an .npz whose fields ({shown or 'none'}) are none of the motion formats")


def _text_format(path: Path, head: bytes) -> str:
    text = head.decode("latin-1")
    lines = [ln.strip() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln and not ln.startswith("#")]
    if not lines:
        raise NotAMotion(f"{path}: empty or only comments; not a motion file")
    first = lines[0].lstrip("\ufeff\xef\xbb\xbf")
    if first.upper().startswith("HIERARCHY"):
        return "bvh"
    keywords = {ln.split()[0].lower() for ln in lines if ln.startswith(":")}
    if keywords & {":fully-specified", ":degrees", ":radians"} and not keywords & {":bonedata", ":root"}:
        return "asf"
    if keywords & {":bonedata", ":root", ":units", ":version"}:
        raise NotAMotion(f"{path}: an ASF skeleton (read with its .amc motions); give the .amc files")
    if _AMC_FRAME.match(lines[0]) and len(lines) > 1 and _AMC_LINE.match(lines[1]):
        return "asf"
    word = first.split()[0][:20] if first.split() else ""
    raise NotAMotion(f"{path}: a text file starting with {word!r}; not BVH (HIERARCHY) or AMC (:FULLY-SPECIFIED)")


def detect(path: str | Path) -> str:
    """The format of ``path`` from its content: one of :data:`READERS`.

    npz keys: ``format == "unibody.motion/1"`` -> motion; ``poses``, ``identity_model_type``
    and ``rotation_repr`` -> soma; ``poses`` + ``trans`` + a mocap frame rate, or the split
    ``root_orient`` / ``pose_body`` keys -> amass; ``vertices`` -> meshes. Text starting with
    ``HIERARCHY`` -> bvh; AMC (``:FULLY-SPECIFIED``, ``:DEGREES`` or numbered frames) -> asf.

    The suffix only tells a damaged file from another kind of file: a ``.bvh``, ``.amc`` or
    ``.npz`` that is not even a zip or text of its kind raises ValueError (it is reported as a
    failed file), any other unrecognised file NotAMotion (a folder's other files are skipped).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        NotAMotion: the content is none of these (the message says what was recognised).
        ValueError: an npz that cannot be read (truncated, pickled, a zip bomb), or a damaged
            file named as a motion.
    """
    path = Path(path)
    if path.is_dir():
        raise NotAMotion(f"{path}: is a folder")
    with open(path, "rb") as f:
        head = f.read(4096)
    if head[:4] in (b"PK\x03\x04", b"PK\x05\x06"):
        try:
            return _npz_format(path)
        except zipfile.BadZipFile:
            raise ValueError(f"{path}: not a readable .npz file") from None
    if head[:6] == b"\x93NUMPY":
        raise NotAMotion(f"{path}: a single .npy array; expected an .npz of named arrays")
    try:
        if not head:
            raise NotAMotion(f"{path}: empty file; not a motion file")
        if b"\x00" in head:
            raise NotAMotion(f"{path}: binary content (starts with {head[:8]!r}); not a motion format")
        return _text_format(path, head)
    except NotAMotion as exc:
        if path.suffix.lower() in (".bvh", ".amc", ".npz"):  # named as a motion: a damaged one, not another file
            raise ValueError(str(exc)) from None
        raise


def output_name(relative: Path, fmt: str, keep_suffix: bool = False) -> Path:
    """The output path (relative to ``--out``) of the input ``relative`` written as ``fmt``.

    The input's own suffix is replaced (``walk.npz`` -> ``walk.motion.npz``; a known compound
    suffix such as ``.soma.npz`` goes whole); ``keep_suffix`` keeps it, for two inputs that would
    otherwise meet (``02_01.bvh`` and ``02_01.amc`` -> ``02_01.bvh.motion.npz``, ``02_01.amc...``).
    """
    name = relative.name
    if not keep_suffix:
        lower = name.lower()
        compound = [f.suffix for f in FORMATS.values() if f.suffix and f.suffix.count(".") > 1]
        cut = next((s for s in compound if lower.endswith(s) and len(name) > len(s)), None)
        name = name[: -len(cut)] if cut else (relative.stem or name)
    suffix = FORMATS[fmt].suffix
    if suffix is None:
        raise ValueError(f"format: expected one of {', '.join(WRITERS)} to write, got {fmt!r}")
    return relative.with_name(name + suffix)
