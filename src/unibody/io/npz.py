"""Reading ``.npz`` files from users: never a pickle, never a zip bomb, one ValueError naming the file."""

from __future__ import annotations

import contextlib
import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

__all__ = ["check_npz_members", "read_npz", "reason"]


@contextlib.contextmanager
def read_npz(path: str | Path) -> Iterator[np.lib.npyio.NpzFile]:
    """Open an ``.npz`` without pickles; anything that is not one raises ``ValueError`` naming ``path``.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: ``path`` is a folder, empty, truncated, not a zip of arrays, or holds pickled objects.
    """
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path}: is a folder, expected an .npz file")
    check_npz_members(path)
    try:
        data = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise ValueError(f"{path}: not a readable .npz file ({reason(exc)})") from None
    if not isinstance(data, np.lib.npyio.NpzFile):  # a bare .npy array
        raise ValueError(f"{path}: expected an .npz file of named arrays, got a single .npy array")
    with data:
        yield data


_BOMB_BYTES = 1 << 28  # members may expand past 256 MiB only at a plausible compression ratio
_BOMB_RATIO = 50  # float arrays deflate 1-3x; a run of zeros ~1000x


def check_npz_members(path: str | Path) -> None:
    """Refuse an ``.npz`` whose members would expand to far more memory than the file holds (a zip bomb).

    Also refuses, before any member is read, what ``zipfile`` cannot open (encrypted members, an
    unknown compression method, a newer zip version): reading them raised ``NotImplementedError``
    or ``RuntimeError`` rather than an error naming the file. Does nothing for files that are not
    zips (the reader reports those).

    Raises:
        ValueError: such a member, or one larger than 256 MiB compressed more than 50 times.
    """
    try:
        with zipfile.ZipFile(path) as z:
            infos = z.infolist()
    except NotImplementedError as exc:  # a zip feature zipfile lacks (a newer zip version)
        raise ValueError(f"{path}: not an .npz of arrays numpy can read ({exc})") from None
    except (OSError, zipfile.BadZipFile, ValueError):
        return
    for info in infos:
        why = _unopenable(info)
        if why:
            raise ValueError(f"{path}: member {info.filename!r} is {why}; not an .npz of arrays numpy can read")
        if info.file_size > _BOMB_BYTES and info.file_size > _BOMB_RATIO * max(info.compress_size, 1):
            raise ValueError(
                f"{path}: member {info.filename!r} would expand from {info.compress_size:,} to {info.file_size:,} "
                "bytes; refusing a likely zip bomb"
            )


_METHODS = (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED, zipfile.ZIP_BZIP2, zipfile.ZIP_LZMA)


def _unopenable(info: zipfile.ZipInfo) -> str | None:
    """Why ``zipfile`` would refuse to open this member (the checks of ``ZipFile.open``), or None."""
    if info.flag_bits & 0x40:  # before bit 0, which strong encryption sets too
        return "strongly encrypted"
    if info.flag_bits & 0x1:
        return "encrypted"
    if info.flag_bits & 0x20:
        return "compressed patched data"
    if info.compress_type not in _METHODS:
        return f"compressed with an unknown method ({info.compress_type})"
    return None


def reason(exc: BaseException) -> str:
    """A short reason for a failed ``np.load``."""
    if isinstance(exc, EOFError) or "No data left" in str(exc):
        return "empty or truncated"
    if "pickled" in str(exc):
        return "not a zip of arrays; pickled objects are never loaded"
    return str(exc) or type(exc).__name__
