"""Weights files (``torch.save`` of plain data and tensors), read back safely, with one error naming the file.

Every model this library trains (the labelers, the correctives, the occupancy field, PanoMan)
is saved as a dict of tensors and plain data and loaded with ``torch.load(weights_only=True)``.
A user may pass any file in their place (``--model FILE``): bytes of another kind, a truncated
download, another model's weights, or weights a diverged training run filled with NaN. The
loaders read through :func:`read_weights` (which also refuses NaN/inf anywhere in the file) and
rebuild inside :func:`rebuilding`, so each of these is one ``ValueError`` that names the file and
says what it is not, never a traceback from deep inside torch nor results computed from NaN.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import torch

__all__ = ["read_weights", "rebuilding"]


def _reason(exc: BaseException, loading: bool = False) -> str:
    """One short line about ``exc``: its first sentence (with the line after a heading ending in ':')."""
    if isinstance(exc, KeyError) and not loading:
        return f"no entry {exc.args[0]!r}" if exc.args else "an entry is missing"
    lines = [x.strip() for x in str(exc).strip().splitlines() if x.strip()]
    text = " ".join(lines[:2]) if len(lines) > 1 and lines[0].endswith(":") else (lines[0] if lines else "")
    text = text.split(". ")[0]
    text = f"{type(exc).__name__}: {text}" if loading or not text else text
    return text if len(text) <= 160 else text[:157] + "..."


def read_weights(path: str | Path, what: str, *, map_location: str | torch.device = "cpu") -> dict:
    """The dict saved at ``path``, read with ``torch.load(weights_only=True)``.

    Args:
        path: the file.
        what: what it should be, for the message (``"a labeler written by Labeler.save"``).
        map_location: where the tensors go.

    Raises:
        ValueError: ``path`` is not such a file (its bytes are no ``torch.save`` archive of plain
            data, or it holds no dict), or a floating-point tensor in it holds NaN/inf (a corrupted
            file or a diverged run; the message names the entry); the message names the file.
    """
    try:
        payload = torch.load(Path(path), map_location=map_location, weights_only=True)
    except FileNotFoundError:
        raise
    except Exception as exc:  # torch.load on foreign bytes: KeyError, RuntimeError, UnpicklingError, EOFError, ...
        raise ValueError(f"{path}: not {what} (unreadable: {_reason(exc, loading=True)})") from None
    if not isinstance(payload, dict):
        raise ValueError(f"{path}: not {what} (it holds a {type(payload).__name__})")
    if (bad := _non_finite(payload, "")) is not None:
        raise ValueError(f"{path}: {bad} holds NaN/inf: corrupted weights")
    return payload


def _non_finite(x: object, key: str) -> str | None:
    """The key path (``state_dict.bin_score``, ``decompositions[0].mean``) of the first floating-point
    tensor in ``x`` with a NaN or inf, or None."""
    if isinstance(x, torch.Tensor):
        return key if x.is_floating_point() and not bool(torch.isfinite(x).all()) else None
    items = x.items() if isinstance(x, dict) else enumerate(x) if isinstance(x, list | tuple) else ()
    for k, v in items:
        found = _non_finite(v, f"{key}[{k}]" if isinstance(k, int) else f"{key}.{k}" if key else str(k))
        if found is not None:
            return found
    return None


@contextmanager
def rebuilding(path: str | Path, what: str) -> Iterator[None]:
    """Errors while a model is rebuilt from a read file (an entry missing, of the wrong type or
    shape) become one ``ValueError`` naming the file."""
    try:
        yield
    except (KeyError, TypeError, ValueError, RuntimeError, IndexError, AttributeError) as exc:
        raise ValueError(f"{path}: not {what} ({_reason(exc)})") from None
