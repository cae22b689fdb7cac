"""Points close in space but far apart along the surface: the two sides of a thin wall.

Two surface points less than ``radius`` apart in space are *apart* when every path along the surface
between them is longer than ``radius`` (a spoon's handle 1.6 mm thick: a strip on top and one below
never touch). The test runs on vertices and is conservative, it may call an apart pair close, never
the reverse:

* A point stands for the nearest corner of its face, at most ``reach`` away (the largest over faces of
  min(circumradius, longest edge)), so a point pair within ``radius`` along the surface maps to a vertex
  pair within ``radius + 2 reach`` along it, and in space.
* Only vertex pairs that lie behind each other's tangent plane with normals facing apart are examined
  (the two sides of a wall), among the vertices with another vertex inside the ball of that diameter
  touching the surface from inside at them (a wall's other side beneath); every other pair
  within that distance in space is close. Surfaces facing each other across air stay close: strips on
  them can touch.
* Along the surface is the shortest path over the mesh's edges, which is at most :data:`GRAPH_STRETCH`
  times the geodesic on an isotropic remesh (``tests/test_thin_walls.py`` measures it): a pair is apart
  when that path is longer than ``GRAPH_STRETCH * (radius + 2 reach)``.

:func:`wall_thickness` measures a wall the other way: along a point's inward normal to the first face
behind it.

Units: mm.
"""
from __future__ import annotations

import dataclasses
import heapq

import numba
import numpy as np
from scipy.spatial import cKDTree

from .triangles import corners, vertex_normals

GRAPH_STRETCH = 1.5  # edge-path length over geodesic length on the pipeline's isotropic remesh, at most


@dataclasses.dataclass(frozen=True)
class ThinWalls:
    """The apart vertex pairs of a mesh ``(vertices, faces)`` for one ``radius_mm``: ``keys`` sorted
    ``a * len(vertices) + b``, both orders; empty on a mesh without walls thinner than the radius."""

    vertices: np.ndarray  # (n, 3) float64, mm
    faces: np.ndarray  # (m, 3) int64
    radius_mm: float
    keys: np.ndarray  # (K,) int64, sorted

    def corners_of(self, face_ids: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(P,) the vertex each point on face ``face_ids[i]`` stands for in :meth:`apart`: its nearest corner."""
        tri = corners(self.vertices, self.faces[face_ids])
        return self.faces[face_ids, np.argmin(np.linalg.norm(tri - points[:, None, :], axis=2), axis=1)]

    def apart(self, corner_a: np.ndarray, corner_b: np.ndarray) -> np.ndarray:
        """(P,) bool: the points standing for vertices ``corner_a[i]`` and ``corner_b[i]``
        (:meth:`corners_of`), less than ``radius_mm`` apart in space, are farther apart along the surface."""
        if len(self.keys) == 0:
            return np.zeros(len(corner_a), dtype=bool)
        query = np.asarray(corner_a, dtype=np.int64) * len(self.vertices) + np.asarray(corner_b, dtype=np.int64)
        at = np.minimum(np.searchsorted(self.keys, query), len(self.keys) - 1)
        return self.keys[at] == query


def corner_reach(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Largest distance (mm) from a point of a face to the face's nearest corner, bounded above by the
    largest over faces of min(circumradius, longest edge)."""
    tri = corners(vertices, faces)
    edges = np.linalg.norm(tri - np.roll(tri, -1, axis=1), axis=2)
    double_area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    circumradius = np.divide(edges.prod(axis=1), 2.0 * double_area, out=np.full(len(tri), np.inf), where=double_area > 0)
    return float(np.minimum(circumradius, edges.max(axis=1)).max()) if len(tri) else 0.0


def thin_walls(vertices: np.ndarray, faces: np.ndarray, radius_mm: float) -> ThinWalls:
    """The vertex pairs apart along the surface of a closed mesh for point pairs ``radius_mm`` apart in
    space (module docstring)."""
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    near_mm = radius_mm + 2.0 * corner_reach(V, F)
    normal = vertex_normals(V, F)
    ball = 0.5 * near_mm  # the ball of diameter near_mm touching the surface from inside at each vertex
    thin = np.flatnonzero(cKDTree(V).query_ball_point(V - ball * normal, ball * (1.0 - 1e-9), return_length=True) > 0)
    pairs = cKDTree(V[thin]).query_pairs(near_mm, output_type="ndarray").astype(np.int64)
    a, b = thin[pairs[:, 0]], thin[pairs[:, 1]]
    gap = V[b] - V[a]
    wall = ((normal[a] * normal[b]).sum(1) < 0) & ((gap * normal[a]).sum(1) < 0) & ((gap * normal[b]).sum(1) > 0)
    a, b = a[wall], b[wall]
    if len(a) == 0:
        return ThinWalls(V, F, float(radius_mm), np.empty(0, dtype=np.int64))
    start, neighbour, length = _adjacency(V, F)
    order = np.argsort(a, kind="stable")
    a, b = a[order], b[order]
    sources, first = np.unique(a, return_index=True)
    far = _farther_than(start, neighbour, length, sources, np.append(first, len(a)), b, GRAPH_STRETCH * near_mm)
    a, b = a[far], b[far]
    keys = np.sort(np.concatenate([a * len(V) + b, b * len(V) + a]))
    return ThinWalls(V, F, float(radius_mm), keys)


def _adjacency(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """CSR vertex adjacency of a closed mesh from its halfedges (each edge once per direction):
    (start (n + 1,), neighbour (2E,), edge length (2E,) mm)."""
    tail = faces.reshape(-1)
    head = faces[:, [1, 2, 0]].reshape(-1)
    order = np.argsort(tail, kind="stable")
    tail, head = tail[order], head[order]
    start = np.searchsorted(tail, np.arange(len(vertices) + 1))
    return start, head, np.linalg.norm(vertices[head] - vertices[tail], axis=1)


@numba.njit(cache=True)
def _farther_than(start, neighbour, length, sources, first, targets, limit):
    """For every source ``sources[s]`` and its targets ``targets[first[s]:first[s + 1]]``: True where the
    shortest edge path from the source is longer than ``limit`` (Dijkstra stopped at ``limit``)."""
    n = len(start) - 1
    distance = np.full(n, np.inf)
    far = np.ones(len(targets), dtype=np.bool_)
    touched = np.empty(n, dtype=np.int64)
    for s in range(len(sources)):
        count = 0
        heap = [(0.0, sources[s])]
        distance[sources[s]] = 0.0
        touched[count] = sources[s]
        count += 1
        while heap:
            d, i = heapq.heappop(heap)
            if d > distance[i]:
                continue
            for k in range(start[i], start[i + 1]):
                j = neighbour[k]
                candidate = d + length[k]
                if candidate <= limit and candidate < distance[j]:
                    if distance[j] == np.inf:
                        touched[count] = j
                        count += 1
                    distance[j] = candidate
                    heapq.heappush(heap, (candidate, j))
        for t in range(first[s], first[s + 1]):
            far[t] = distance[targets[t]] > limit
        for t in range(count):
            distance[touched[t]] = np.inf
    return far


def wall_thickness(vertices: np.ndarray, faces: np.ndarray, face_normals: np.ndarray, areas: np.ndarray,
                   reach: float, samples: int) -> np.ndarray:
    """Wall thickness (mm) at ``samples`` face centroids spread by area (deterministic): the distance
    from each, inward along its face's outward normal, to the first face it meets, or ``inf`` when no
    face lies within ``reach`` (mm) of it (only the faces near a point are tested)."""
    cumulative = np.cumsum(areas)
    picked = np.searchsorted(cumulative, (np.arange(samples) + 0.5) / samples * cumulative[-1])
    triangles = corners(vertices, faces)
    centroids = triangles.mean(axis=1)
    origin, direction = centroids[picked], -face_normals[picked]
    spread = float(np.linalg.norm(triangles - centroids[:, None, :], axis=2).max())
    near = cKDTree(centroids).query_ball_point(origin, reach + spread)
    ray = np.repeat(np.arange(samples), [len(n) for n in near])
    face = np.concatenate([np.asarray(n, dtype=np.int64) for n in near])
    # Moller-Trumbore on every (ray, nearby face) pair
    a, b, c = triangles[face, 0], triangles[face, 1] - triangles[face, 0], triangles[face, 2] - triangles[face, 0]
    p = np.cross(direction[ray], c)
    det = np.einsum("ij,ij->i", b, p)
    ok = (np.abs(det) > 1e-12) & (face != picked[ray])
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    t_vec = origin[ray] - a
    u = np.einsum("ij,ij->i", t_vec, p) * inv
    q = np.cross(t_vec, b)
    v = np.einsum("ij,ij->i", direction[ray], q) * inv
    t = np.einsum("ij,ij->i", c, q) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    thickness = np.full(samples, np.inf)
    np.minimum.at(thickness, ray[hit], t[hit])
    return thickness
