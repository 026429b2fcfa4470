"""One sparse Cholesky for the PanoMan solvers: CHOLMOD through ``cholespy`` (a declared dependency)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.sparse as sp
from cholespy import CholeskySolverD, MatrixType

__all__ = ["cholesky"]


def cholesky(matrix: sp.spmatrix) -> Callable[[np.ndarray], np.ndarray]:
    """Factorise a symmetric positive definite (n, n) matrix; return ``solve(b)`` for b of shape (n,) or (n, k)."""
    csr = sp.csr_matrix(matrix, dtype=np.float64)
    n = csr.shape[0]
    solver = CholeskySolverD(n, csr.indptr.astype(np.int32), csr.indices.astype(np.int32), csr.data, MatrixType.CSR)

    def solve(b: np.ndarray) -> np.ndarray:
        rhs = np.ascontiguousarray(b, dtype=np.float64).reshape(n, -1)
        out = np.zeros_like(rhs)
        solver.solve(rhs, out)
        return out.reshape(np.shape(b))

    return solve
