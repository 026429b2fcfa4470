"""Seeded pools of synthetic identities: native PCA bodies, newborns to adults, for every companion."""

from __future__ import annotations

import math

import torch

from .poses import keyed_generator

__all__ = ["NUM_SHAPE", "identity_pool"]

NUM_SHAPE = 10  # PCA components per identity
_TRUNCATE = 2.0  # identity coefficients are N(0, 1) truncated to [-2, 2]


def identity_pool(size: int, *, seed: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """(size, 10) PCA coefficients of the identities 0..size-1 of pool ``seed``.

    Each row is N(0, 1) truncated to [-2, 2] (inverse-CDF of a uniform), drawn from a stream
    keyed by ``(seed, k)``, so ``identity_pool(m, seed=s)`` is a prefix of any larger pool.
    """
    for value, name in ((size, "size"), (seed, "seed")):
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(f"{name}: expected an int >= 0, got {value!r}")
    lo = 0.5 * math.erfc(_TRUNCATE / math.sqrt(2.0))  # Phi(-2)
    u = torch.stack([torch.rand(NUM_SHAPE, generator=keyed_generator("identity", seed, k), dtype=torch.float64)
                     for k in range(size)]) if size else torch.zeros(0, NUM_SHAPE, dtype=torch.float64)  # fmt: skip
    return torch.special.ndtri(lo + (1.0 - 2.0 * lo) * u).to(dtype)
