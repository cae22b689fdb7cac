"""Per-triangle quantities over ``(V, F)`` arrays, in the manner of trimesh's ``triangles.py``.

Conventions, stated once for the whole project: lengths in millimetres; ``vertices`` is ``(n, 3)``
float, ``faces`` is ``(m, 3)`` int with corners counter-clockwise seen from outside, so
``cross(p1 - p0, p2 - p0)`` points outward and has length twice the triangle's area.
"""
from __future__ import annotations

import numpy as np


def corners(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``(m, 3, 3)`` corner positions of every face."""
    return np.asarray(vertices, dtype=float)[np.asarray(faces)]


def mean_edge_mm(vertices: np.ndarray, faces: np.ndarray) -> float:
    """The mean length (mm) of the faces' edges, each counted once per face it bounds."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return float(np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1).mean())


def random_barycentrics(rng: np.random.Generator, count: int) -> np.ndarray:
    """``(count, 3)`` barycentrics of points drawn uniformly by area inside a triangle."""
    r1, r2 = np.sqrt(rng.random(count)), rng.random(count)
    return np.stack([1 - r1, r1 * (1 - r2), r1 * r2], axis=1)


def cross_products(triangles: np.ndarray) -> np.ndarray:
    """``(m, 3)`` ``cross(p1 - p0, p2 - p0)`` of ``(m, 3, 3)`` triangles: outward, length 2 x area."""
    return np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])


def areas(triangles: np.ndarray) -> np.ndarray:
    """``(m,)`` areas (mm^2) of ``(m, 3, 3)`` triangles."""
    return 0.5 * np.linalg.norm(cross_products(triangles), axis=1)


def zero_area(double_areas: np.ndarray) -> np.ndarray:
    """Mask of the degenerate triangles among ``(m,)`` doubled areas (mm^2): at most 1e-14 of the
    largest (or of 1 mm^2), where the geometry's divisions by the area stop being meaningful."""
    return double_areas <= 1e-14 * max(1.0, float(np.max(double_areas, initial=0.0)))


def normals(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``((m, 3) unit outward normals, (m,) areas)`` of ``(m, 3, 3)`` triangles; a degenerate
    triangle gets the zero vector."""
    cross = cross_products(triangles)
    double_area = np.linalg.norm(cross, axis=1)
    unit = np.divide(cross, double_area[:, None], out=np.zeros_like(cross), where=double_area[:, None] > 0)
    return unit, 0.5 * double_area


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``(n, 3)`` unit area-weighted vertex normals (zero for a vertex in no non-degenerate face)."""
    cross = cross_products(corners(vertices, faces))
    summed = np.zeros((len(vertices), 3))
    for corner in range(3):
        np.add.at(summed, np.asarray(faces)[:, corner], cross)
    length = np.linalg.norm(summed, axis=1, keepdims=True)
    return np.divide(summed, length, out=np.zeros_like(summed), where=length > 0)


def vertex_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``(n,)`` barycentric vertex areas (mm^2): a third of each incident face's area."""
    face_area = areas(corners(vertices, faces))
    out = np.zeros(len(vertices))
    for corner in range(3):
        np.add.at(out, np.asarray(faces)[:, corner], face_area / 3.0)
    return out


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Enclosed volume (mm^3) of a closed mesh, positive when faces are CCW seen from outside."""
    tri = corners(vertices, faces)
    return float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0)


def surface_normals(vertices: np.ndarray, faces: np.ndarray, face_ids: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """``(k, 3)`` unit normals at surface points ``(face_ids (k,), bary (k, 3))``: the barycentric
    interpolation of :func:`vertex_normals`, normalised (smooth across faces, outward)."""
    corner_normals = vertex_normals(vertices, faces)[np.asarray(faces)[face_ids]]
    n = np.einsum("kc,kcd->kd", bary, corner_normals)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
