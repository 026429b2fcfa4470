"""Motion in and out at dataset scale: readers to the canonical motion, writers from it.

The contract every format module follows (``unibody convert`` dispatches on it):

- a **reader** ``read_<format>(path: Path, options: ConvertOptions) -> Converted`` returns the
  canonical :class:`~unibody.motion.Motion` (fps kept, ``source`` set, identity when known)
  and per-file statistics; bad input raises ``ValueError`` with one line naming the file.
- a **writer** ``write_<format>(motion: Motion, path: Path, options: ConvertOptions) -> None``
  writes exactly ``path``, atomically (:mod:`unibody.io.atomic`).

The whole command is :func:`unibody.convert.run.run`; docs/convert.md describes the formats.
"""

from ._types import Converted, ConvertOptions
from .formats import FORMATS, detect, reader, writer

__all__ = ["FORMATS", "ConvertOptions", "Converted", "detect", "reader", "writer"]
