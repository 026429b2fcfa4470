"""Output files that never lose data: checked paths, atomic writes, one writer per output.

A file is written to a unique temporary file in its own folder (created exclusively, so a
link planted there is never followed), flushed to disk, then renamed over the target: a
reader sees the old file or the new one, never half of one, and a full disk or a kill
leaves the previous output intact. :func:`check_output` refuses an output that is the
input, a folder, in a missing folder, of the wrong suffix, or that exists (unless
``force``); :func:`output_lock` refuses a second process writing the same output, and
:func:`waiting_lock` makes it wait its turn instead (a cache that one process builds and the
others then read).
"""

from __future__ import annotations

import contextlib
import errno
import os
import tempfile
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import IO

import numpy as np

__all__ = [
    "OutputError",
    "atomic_path",
    "atomic_write",
    "check_output",
    "file_sha256",
    "output_lock",
    "save_npz",
    "waiting_lock",
]


class OutputError(ValueError):
    """An output path that would lose data or cannot be written (the message names it)."""


def check_output(
    out: str | os.PathLike[str],
    *,
    inputs: Iterable[str | os.PathLike[str]] = (),
    suffixes: Iterable[str] = (),
    force: bool = False,
    name: str = "--out",
) -> Path:
    """Check that ``out`` may be written and return it as a Path.

    Args:
        out: the output file.
        inputs: files the same run reads; ``out`` may be none of them.
        suffixes: accepted suffixes (``".npz"``, ...), case-insensitive; empty accepts any.
        force: whether an existing output may be replaced.
        name: the argument's name in messages.

    Raises:
        OutputError: ``out`` is an input, a folder, lies in a missing folder, has another
            suffix, or exists and ``force`` is false.
    """
    path = Path(out)
    allowed = tuple(s.lower() for s in suffixes)
    if allowed and path.suffix.lower() not in allowed:
        raise OutputError(f"{name}: expected a {' or '.join(allowed)} file, got {str(path)!r}")
    if path.is_dir():
        raise OutputError(f"{name}: {path} is a folder; name a file")
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise OutputError(f"{name}: folder {parent} does not exist")
    for src in inputs:
        if _same_file(path, Path(src)):
            raise OutputError(f"{name}: {path} is the input file {src}; name another output")
    if path.exists() and not force:
        raise OutputError(f"{name}: {path} exists; pass --force to replace it")
    return path


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist
        return a.resolve() == b.resolve()


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a fresh temporary path beside ``path`` (same suffix); on success it replaces ``path``.

    For writers that take a file name (ezc3d, torch.save, PIL). The temporary file is created
    exclusively with a unique name; it is fsynced and renamed over ``path`` when the block
    ends without an exception, and removed otherwise.
    """
    path = Path(path)
    if path.is_dir():  # else the temporary file lands beside the folder and the rename fails
        raise OutputError(f"{path}: is a folder; expected the path of a file to write")
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{path.suffix}", dir=path.parent or ".")
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            if os.fstat(f.fileno()).st_size == 0:  # a writer that failed without raising (seen with C3D writers)
                raise OutputError(f"{path}: the writer produced an empty file; nothing was replaced")
            os.fsync(f.fileno())
        os.chmod(tmp, _mode(path))
        os.replace(tmp, path)
        _fsync_dir(path.parent)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _mode(path: Path) -> int:
    """The permissions a plain ``open(path, "w")`` would give (mkstemp makes 0600): kept if ``path`` exists."""
    try:
        return os.stat(path).st_mode & 0o777
    except OSError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike[str], mode: str = "wb") -> Iterator[IO]:
    """Open a temporary file beside ``path`` for writing; on success it replaces ``path`` (see :func:`atomic_path`)."""
    with atomic_path(path) as tmp, open(tmp, mode) as f:
        yield f


def file_sha256(path: str | os.PathLike[str]) -> str:
    """Hex sha256 of a file's bytes (read in 1 MiB blocks): the key of resumable work and of checksummed sources."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def save_npz(path: str | os.PathLike[str], **arrays: np.ndarray) -> None:
    """Write an ``.npz`` atomically, exactly at ``path`` (numpy would append ``.npz`` to a name)."""
    with atomic_write(path) as f:
        np.savez(f, **arrays)


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder or ".", os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:  # some file systems cannot sync a folder; the rename is still atomic
        pass
    finally:
        os.close(fd)


def output_lock(path: str | os.PathLike[str], name: str = "--out") -> contextlib.AbstractContextManager[None]:
    """Hold ``<path>.lock`` for the block; raise OutputError if another process holds it.

    The lock is an advisory ``flock``: the system releases it when its holder dies, so a
    killed run never leaves a lock that blocks the next one.
    """
    import fcntl

    def refuse(fd: int, lock: Path) -> None:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno in _BUSY:
                raise OutputError(f"{name}: another process is writing {path} (lock {lock})") from None
            raise

    return _held(path, refuse)


def waiting_lock(
    path: str | os.PathLike[str], timeout: float | None = None, poll: float = 0.05
) -> contextlib.AbstractContextManager[None]:
    """Hold ``<path>.lock`` for the block, waiting for another process that holds it.

    The waiting twin of :func:`output_lock` (same advisory ``flock``, released by the system
    when its holder dies, so a killed holder never blocks the next process for good).

    Args:
        path: the file the lock protects.
        timeout: the most seconds to wait; None waits as long as the holder runs.
        poll: seconds between two tries while waiting with a timeout.

    Raises:
        TimeoutError: another process still held the lock after ``timeout`` seconds.
        OSError: the lock file cannot be created (e.g. the folder is not writable).
    """
    import fcntl
    import time

    def wait(fd: int, lock: Path) -> None:
        if timeout is None:
            fcntl.flock(fd, fcntl.LOCK_EX)
            return
        deadline = time.monotonic() + timeout
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return
            except OSError as exc:
                if exc.errno not in _BUSY:
                    raise
                if time.monotonic() >= deadline:
                    raise TimeoutError(f"another process held {lock} for over {timeout:g} s") from None
                time.sleep(poll)

    return _held(path, wait)


_BUSY = (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES)


@contextlib.contextmanager
def _held(path: str | os.PathLike[str], acquire: Callable[[int, Path], None]) -> Iterator[None]:
    """Lock ``<path>.lock`` with ``acquire(fd, lock)`` for the block; remove the lock file after."""
    lock = Path(f"{path}.lock")
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            acquire(fd, lock)
        except BaseException:
            os.close(fd)
            raise
        # The previous holder removes the file when it is done: lock the file now at that path.
        try:
            same = os.stat(lock).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        yield
    finally:
        lock.unlink(missing_ok=True)
        os.close(fd)
