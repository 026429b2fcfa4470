"""Input validation at public boundaries: one helper per concern, one message style.

Every message names the argument, what was expected and what was given, e.g.
``pose: expected shape (B, 77, 3) or (B, 77, 3, 3), got (2, 76, 3)``.
"""

from __future__ import annotations

import math
import numbers

import torch

__all__ = [
    "check_count",
    "check_device",
    "check_grad_mode",
    "check_shape",
    "check_finite",
    "check_like",
    "check_number",
    "check_tensor",
]


def _fmt(spec: str) -> str:
    return "(" + ", ".join(spec.split()) + ")"


def _matches(shape: tuple[int, ...], spec: str, sizes: dict[str, int]) -> bool:
    dims = spec.split()
    if len(dims) != len(shape):
        return False
    bound = dict(sizes)
    for d, n in zip(dims, shape, strict=True):
        if d.isdigit():
            if int(d) != n:
                return False
        elif d in bound:
            if bound[d] != n:
                return False
        else:
            bound[d] = n
    sizes.update(bound)
    return True


def check_tensor(x: object, name: str) -> torch.Tensor:
    """Raise TypeError unless ``x`` is a tensor."""
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    return x


def check_shape(x: torch.Tensor, *specs: str, name: str, sizes: dict[str, int] | None = None) -> int:
    """Check ``x`` against one or more shape specs such as ``"B 77 3"``.

    Letters bind to sizes (shared through ``sizes`` across calls); digits are exact.
    Returns the index of the spec that matched.
    """
    check_tensor(x, name)
    sizes = {} if sizes is None else sizes
    for i, spec in enumerate(specs):
        trial = dict(sizes)
        if _matches(tuple(x.shape), spec, trial):
            sizes.update(trial)
            return i
    expected = " or ".join(_fmt(s) for s in specs)
    bound = {k: v for k, v in sizes.items() if any(k in s.split() for s in specs)}
    hint = f" with {', '.join(f'{k}={v}' for k, v in bound.items())}" if bound else ""
    raise ValueError(f"{name}: expected shape {expected}{hint}, got {tuple(x.shape)}")


def check_finite(x: torch.Tensor, name: str) -> None:
    """Raise ValueError if ``x`` holds NaN or infinite values."""
    # One reduction first (NaN/inf propagate through a sum); the elementwise test runs only
    # when the sum is not finite, which also covers a sum that merely overflowed.
    if x.is_floating_point() and not bool(torch.isfinite(x.sum())):
        bad = int((~torch.isfinite(x)).sum())
        if bad:
            raise ValueError(f"{name}: expected finite values, got {bad} NaN/inf entries")


def check_like(x: torch.Tensor, ref: torch.Tensor, name: str, owner: str = "the layer") -> None:
    """Require ``x`` to share dtype and device with ``ref``; never cast silently."""
    if x.dtype != ref.dtype or x.device != ref.device:
        raise TypeError(
            f"{name}: is {str(x.dtype).removeprefix('torch.')} on {x.device} but {owner} is "
            f"{str(ref.dtype).removeprefix('torch.')} on {ref.device}; "
            f"convert the input or call .to(...) on {owner}"
        )


def check_device(name: str, arg: str = "device") -> torch.device:
    """The torch device ``name`` ("cpu", "cuda", "cuda:1"); ValueError unless this machine has it."""
    try:
        dev = torch.device(name)
    except (RuntimeError, TypeError):
        raise ValueError(f"{arg}: expected cpu, cuda or cuda:N, got {name!r}") from None
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"{arg}: expected cpu, cuda or cuda:N, got {name!r}")
    if dev.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if (dev.index or 0) >= count:
            raise ValueError(f"{arg}: {name!r} is not on this machine ({count} CUDA devices)")
    return dev


def check_grad_mode(what: str) -> None:
    """RuntimeError under ``torch.inference_mode()`` for ``what``, an optimiser that descends a
    gradient (it enables gradients itself under ``torch.no_grad()``, but inference tensors cannot
    be differentiated)."""
    if torch.is_inference_mode_enabled():
        raise RuntimeError(f"{what} descends a gradient: call it outside torch.inference_mode() (no_grad is fine)")


def check_count(value: object, name: str, low: int = 0) -> None:
    """ValueError unless ``value`` is an integer (not a bool) >= ``low`` (a settings field)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < low:
        raise ValueError(f"{name}: expected an integer >= {low}, got {value!r}")


def check_number(value: object, name: str, *, positive: bool = False) -> None:
    """ValueError unless ``value`` is a finite real number (not a bool) >= 0, or > 0 when ``positive``."""
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or value < 0 or (positive and value == 0):
        raise ValueError(f"{name}: expected a finite number {'>' if positive else '>='} 0, got {value!r}")
