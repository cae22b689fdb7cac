"""Sparse symmetric positive definite systems, the Laplacian-like ones every stage solves: one
Cholesky factorisation (cholespy: CHOLMOD's simplicial LL' factor on a nested-dissection ordering)
reused for any number of right-hand sides."""
from __future__ import annotations

import numpy as np


def cholesky(matrix):
    """The Cholesky factor of the SPD scipy sparse ``matrix`` (both triangles stored), for :func:`solve`."""
    import scipy.sparse as sp
    from cholespy import CholeskySolverD, MatrixType

    coo = sp.coo_matrix(matrix)
    return CholeskySolverD(
        coo.shape[0], coo.row.astype(np.int32), coo.col.astype(np.int32), coo.data.astype(np.float64), MatrixType.COO
    )


def solve(factor, rhs: np.ndarray) -> np.ndarray:
    """``matrix^-1 rhs`` for a factor of :func:`cholesky`; ``rhs`` (n,) or (n, k)."""
    rhs = np.ascontiguousarray(rhs, dtype=np.float64)
    out = np.zeros_like(rhs)
    factor.solve(rhs, out)
    return out


def spd_solve(matrix, rhs: np.ndarray) -> np.ndarray:
    """``matrix^-1 rhs`` for one SPD scipy sparse ``matrix``."""
    return solve(cholesky(matrix), rhs)
