"""Harmonic interpolation over ``(V, F)``: the function with given values on fixed vertices whose
cotan Laplacian vanishes at every other vertex (conventions: :mod:`.triangles`)."""
from __future__ import annotations

import numpy as np

from .sparse_spd import spd_solve
from .triangles import corners


def cotan_laplacian(vertices: np.ndarray, faces: np.ndarray):
    """The ``(n, n)`` cotan stiffness matrix (positive semi-definite, rows sum to 0), scipy CSR:
    ``L_ij = -(cot a_ij + cot b_ij) / 2`` for an edge ``ij`` with opposite angles ``a_ij, b_ij``."""
    import scipy.sparse as sp

    tri = corners(vertices, faces)
    F = np.asarray(faces, dtype=np.int64)
    rows, cols, vals = [], [], []
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        u, v = tri[:, j] - tri[:, i], tri[:, k] - tri[:, i]
        cot = np.einsum("ij,ij->i", u, v) / np.maximum(np.linalg.norm(np.cross(u, v), axis=1), 1e-300)
        rows += [F[:, j], F[:, k]]
        cols += [F[:, k], F[:, j]]
        vals += [-0.5 * cot, -0.5 * cot]
    n = len(vertices)
    off = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    return (off - sp.diags(np.asarray(off.sum(axis=1)).ravel())).tocsr()


def harmonic_interpolation(vertices: np.ndarray, faces: np.ndarray, fixed: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``(n,)`` values equal to ``values`` at the vertex indices ``fixed`` and harmonic (``(L u)_i = 0``)
    at every other vertex. Every connected component must hold a fixed vertex."""
    L = cotan_laplacian(vertices, faces)
    n = len(vertices)
    fixed = np.asarray(fixed, dtype=np.int64)
    u = np.zeros(n)
    u[fixed] = values
    free = np.ones(n, dtype=bool)
    free[fixed] = False
    if free.any():
        u[free] = spd_solve(L[free][:, free], -(L[free][:, fixed] @ u[fixed]))
    return u
