"""Geodesic distance from vertices by the heat method (potpourri3d's ``MeshHeatMethodDistanceSolver``),
set up once per process and mesh: regions, connections and the Tx seeding measure distances on the
same remeshed surface, and the set-up (a sparse factorisation) costs far more than a distance."""
from __future__ import annotations

import functools

import numpy as np

from ...graph.hashing import digest_fields


def array_digest(*arrays: np.ndarray) -> str:
    """Content hash of arrays (each one's dtype, shape and bytes, length-prefixed: :func:`digest_fields`)."""
    return digest_fields([f for a in arrays for f in (f"{a.dtype}{a.shape}", np.ascontiguousarray(a).tobytes())])


@functools.lru_cache(maxsize=2)
def _cached_solver(digest: str, vertices_bytes: bytes, faces_bytes: bytes, n: int, m: int):
    import potpourri3d as pp3d  # heavy: imported when used, not on node discovery

    V = np.frombuffer(vertices_bytes, dtype=np.float64).reshape(n, 3)
    F = np.frombuffer(faces_bytes, dtype=np.int64).reshape(m, 3)
    return pp3d.MeshHeatMethodDistanceSolver(V, F)


def heat_distance_solver(vertices: np.ndarray, faces: np.ndarray):
    """potpourri3d's heat-method distance solver for ``(V, F)`` (mm in, mm out), cached by content."""
    V = np.ascontiguousarray(vertices, dtype=np.float64)
    F = np.ascontiguousarray(faces, dtype=np.int64)
    return _cached_solver(array_digest(V, F), V.tobytes(), F.tobytes(), len(V), len(F))
