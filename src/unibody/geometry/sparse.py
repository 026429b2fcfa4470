"""Constant-structure CSR matrices: built once from index arrays, values may carry gradients."""

from __future__ import annotations

import warnings

import torch

__all__ = ["crow_indices", "csr"]

# Our use (fixed structure, sparse @ dense) is the stable subset of CSR; the beta notice is noise.
warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")


def crow_indices(rows: torch.Tensor, num_rows: int) -> torch.Tensor:
    """CSR row pointers (num_rows + 1,) of row-sorted row indices."""
    counts = torch.bincount(rows, minlength=num_rows)
    return torch.cat([counts.new_zeros(1), counts.cumsum(0)])


def csr(crow: torch.Tensor, col: torch.Tensor, val: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    """A CSR matrix (structure validated by its builder, so no per-call invariant check)."""
    return torch.sparse_csr_tensor(crow, col, val, shape, check_invariants=False)
