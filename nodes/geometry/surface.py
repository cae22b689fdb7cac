"""Closest points on a triangle mesh: a vectorised closest-point-on-triangle test and a projector
that snaps points near the surface onto it (the runtime's touch points and simulated fingers).

Shapes follow :mod:`.triangles`: ``triangles`` are ``(n, 3, 3)`` corner arrays, points ``(n, 3)``
(mm), barycentrics ``(n, 3)`` weights of the three corners.
"""
from __future__ import annotations

import numba
import numpy as np
from scipy.spatial import cKDTree

from .triangles import corners, normals


def closest_points_on_triangles(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Barycentrics (n, 3) of the closest point on triangle ``triangles[i]`` (n, 3, 3) to
    ``points[i]`` (n, 3) (Ericson's region test, vectorised)."""
    a = triangles[:, 0]
    ab, ac = triangles[:, 1] - a, triangles[:, 2] - a
    return _closest_barycentrics(points - a, ab, ac, np.einsum("ij,ij->i", ab, ab), np.einsum("ij,ij->i", ab, ac),
                                 np.einsum("ij,ij->i", ac, ac))


def _closest_barycentrics(ap, ab, ac, ab_ab, ab_ac, ac_ac) -> np.ndarray:
    """:func:`closest_points_on_triangles` from the offsets ``ap = p - a`` (n, 3), the edges ``ab``,
    ``ac`` (n, 3) and their dot products (n,) (a projector precomputes the last five per face)."""
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    d3, d4 = d1 - ab_ab, d2 - ab_ac  # ab.(p - b), ac.(p - b)
    d5, d6 = d1 - ab_ac, d2 - ac_ac  # ab.(p - c), ac.(p - c)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        v_ab = d1 / (d1 - d3)
        w_ac = d2 / (d2 - d6)
        w_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        total = va + vb + vc
        v_in, w_in = vb / total, vc / total
    # Regions in reverse priority, so the first matching test of Ericson's order wins.
    v, w = v_in, w_in
    edge_bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
    v, w = np.where(edge_bc, 1 - w_bc, v), np.where(edge_bc, w_bc, w)
    edge_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    v, w = np.where(edge_ac, 0.0, v), np.where(edge_ac, w_ac, w)
    corner_c = (d6 >= 0) & (d5 <= d6)
    v, w = np.where(corner_c, 0.0, v), np.where(corner_c, 1.0, w)
    edge_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    v, w = np.where(edge_ab, v_ab, v), np.where(edge_ab, 0.0, w)
    corner_b = (d3 >= 0) & (d4 <= d3)
    v, w = np.where(corner_b, 1.0, v), np.where(corner_b, 0.0, w)
    corner_a = (d1 <= 0) & (d2 <= 0)
    v, w = np.where(corner_a, 0.0, v), np.where(corner_a, 0.0, w)
    return np.column_stack([1 - v - w, v, w])




class SurfaceProjector:
    """Closest point on the mesh ``(vertices (n, 3) mm, faces (m, 3))`` for query points near it
    (among the ``k`` faces nearest by centroid). ``face_normals`` (m, 3) are unit outward;
    ``face_frames`` (m, 3, 3) hold per face the rows ``t1, t2, n`` of an orthonormal frame."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, k: int = 12):
        self.vertices, self.faces = vertices, faces
        self.triangles = corners(vertices, faces)
        centroids = self.triangles.mean(axis=1)
        self.tree = cKDTree(centroids)
        self._origin = self.triangles[:, 0]
        self._ab, self._ac = self.triangles[:, 1] - self._origin, self.triangles[:, 2] - self._origin
        self._ab_ab = np.einsum("ij,ij->i", self._ab, self._ab)
        self._ab_ac = np.einsum("ij,ij->i", self._ab, self._ac)
        self._ac_ac = np.einsum("ij,ij->i", self._ac, self._ac)
        self.k = min(k, len(faces))
        self.face_normals = normals(self.triangles)[0]  # (m, 3) unit, zero for a degenerate face
        helper = np.where(np.abs(self.face_normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        t1 = np.cross(self.face_normals, helper)
        t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
        self.face_frames = np.stack([t1, np.cross(self.face_normals, t1), self.face_normals], axis=1)  # rows t1, t2, n
        # Per-face rows for the compiled single-point path (numpy's per-call overhead would dominate
        # on the k candidates of one point): origin, ab, ac, ab.ab, ab.ac, ac.ac, normal, and the
        # radius (largest vertex distance from the centroid: no point of the face is nearer a query
        # than its centroid distance minus the radius).
        radius = np.linalg.norm(self.triangles - centroids[:, None], axis=2).max(axis=1)
        self._face_rows = np.column_stack([self._origin, self._ab, self._ac, self._ab_ab, self._ab_ac, self._ac_ac,
                                           self.face_normals, radius])
        self._project_one(centroids[0], None)  # compiles the kernel now, not at the first query

    def barycentrics_in_face(self, point: np.ndarray, face: int) -> np.ndarray | None:
        """Barycentrics (3,) of ``point`` (mm, in the plane of ``face``) when it lies inside the face,
        so that it is its own closest surface point; else None."""
        ox, oy, oz, abx, aby, abz, acx, acy, acz, ab_ab, ab_ac, ac_ac = self._face_rows[face, :12].tolist()
        px, py, pz = point.tolist()
        apx, apy, apz = px - ox, py - oy, pz - oz
        d1, d2 = abx * apx + aby * apy + abz * apz, acx * apx + acy * apy + acz * apz
        determinant = ab_ab * ac_ac - ab_ac * ab_ac
        if not determinant > 0.0:
            return None
        v, w = (ac_ac * d1 - ab_ac * d2) / determinant, (ab_ab * d2 - ab_ac * d1) / determinant
        if v < 0.0 or w < 0.0 or v + w > 1.0:
            return None
        return np.array([1.0 - v - w, v, w])

    def project(self, points: np.ndarray, facing: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(n, 3) points -> closest surface points (n, 3), their faces (n,), barycentrics (n, 3).

        With ``facing`` (3,) or one per point (n, 3), faces whose normal points away from it are
        skipped when others are near: on thin parts (ears, handles) the point lands on the side
        facing that way."""
        points = np.atleast_2d(points)
        if len(points) == 1:
            single = self._project_one(points[0], None if facing is None else np.reshape(facing, (-1, 3))[0])
            if single is not None:
                return single
        _, candidates = self.tree.query(points, k=self.k)
        candidates = candidates.reshape(len(points), self.k)
        flat = candidates.ravel()
        origin, ab, ac = self._origin[flat], self._ab[flat], self._ac[flat]
        ap = (points[:, None] - origin.reshape(len(points), self.k, 3)).reshape(-1, 3)
        bary = _closest_barycentrics(ap, ab, ac, self._ab_ab[flat], self._ab_ac[flat], self._ac_ac[flat])
        closest = (origin + bary[:, 1:2] * ab + bary[:, 2:3] * ac).reshape(len(points), self.k, 3)
        distance2 = np.sum((closest - points[:, None]) ** 2, axis=2)
        if facing is not None:
            candidate_normals = self.face_normals[candidates]
            dots = (candidate_normals @ facing if np.ndim(facing) == 1
                    else np.einsum("nkc,nc->nk", candidate_normals, facing))
            away = dots <= 0.0
            distance2 = np.where(away & ~np.all(away, axis=1, keepdims=True), np.inf, distance2)
        best = np.argmin(distance2, axis=1)
        rows = np.arange(len(points))
        return closest[rows, best], candidates[rows, best], bary.reshape(len(points), self.k, 3)[rows, best]

    def _project_one(self, point: np.ndarray, facing: np.ndarray | None):
        """:meth:`project` of one point, compiled: the same region tests (Ericson's order),
        products and sums as the vectorised path. None on a degenerate candidate (division by
        zero), which the vectorised path handles with its nan/inf semantics."""
        centroid_distances, candidates = self.tree.query(point, k=self.k)
        found, face, closest, bary = _closest_among(
            np.asarray(point, dtype=np.float64), np.zeros(3) if facing is None else np.asarray(facing, dtype=np.float64),
            facing is not None, np.atleast_1d(candidates), np.atleast_1d(centroid_distances), self._face_rows)
        if not found:
            return None
        return closest[None], np.array([face], dtype=np.intp), bary[None]


@numba.njit(cache=True, error_model="numpy")  # division by zero gives inf / nan, not an exception
def _closest_among(point, facing, use_facing, candidates, centroid_distances, rows):
    """The closest point to ``point`` on the faces ``candidates`` (their centroids at
    ``centroid_distances``), skipping faces whose normal points away from ``facing`` unless all do;
    ``rows`` per face: origin, ab, ac, ab.ab, ab.ac, ac.ac, normal, radius. Returns (found, face,
    point (3,), barycentrics (3,)); not found on a degenerate candidate or when none is finite."""
    px, py, pz = point[0], point[1], point[2]
    away = np.zeros(len(candidates), dtype=np.bool_)
    if use_facing:
        for i in range(len(candidates)):
            r = rows[candidates[i]]
            away[i] = r[12] * facing[0] + r[13] * facing[1] + r[14] * facing[2] <= 0.0
        if away.all():
            away[:] = False
    best_face = -1
    best_d2 = np.inf
    best = np.zeros(6)
    for i in range(len(candidates)):
        row = rows[candidates[i]]
        reach = centroid_distances[i] - row[15]
        if reach > 0.0 and reach * reach > best_d2:  # this face cannot be nearer than the best
            continue
        ox, oy, oz, abx, aby, abz, acx, acy, acz = row[0], row[1], row[2], row[3], row[4], row[5], row[6], row[7], row[8]
        ab_ab, ab_ac, ac_ac = row[9], row[10], row[11]
        apx, apy, apz = px - ox, py - oy, pz - oz
        # Summed in the order numpy's einsum uses for rows of 3, so the two paths agree bit for bit
        # (ties between faces sharing an edge then break the same way).
        d1 = (abx * apx + abz * apz) + aby * apy
        d2 = (acx * apx + acz * apz) + acy * apy
        d3, d4 = d1 - ab_ab, d2 - ab_ac
        d5, d6 = d1 - ab_ac, d2 - ac_ac
        if d1 <= 0 and d2 <= 0:
            v = w = 0.0
        elif d3 >= 0 and d4 <= d3:
            v, w = 1.0, 0.0
        else:
            vc = d1 * d4 - d3 * d2
            if vc <= 0 and d1 >= 0 and d3 <= 0:
                v, w = d1 / (d1 - d3), 0.0
            elif d6 >= 0 and d5 <= d6:
                v, w = 0.0, 1.0
            else:
                vb = d5 * d2 - d1 * d6
                if vb <= 0 and d2 >= 0 and d6 <= 0:
                    v, w = 0.0, d2 / (d2 - d6)
                else:
                    va = d3 * d6 - d5 * d4
                    if va <= 0 and d4 - d3 >= 0 and d5 - d6 >= 0:
                        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
                        v = 1 - w
                    else:
                        total = va + vb + vc
                        v, w = vb / total, vc / total
        if not (np.isfinite(v) and np.isfinite(w)):  # a degenerate face divided by zero
            return False, -1, best[:3], best[3:]
        cx, cy, cz = ox + v * abx + w * acx, oy + v * aby + w * acy, oz + v * abz + w * acz
        ex, ey, ez = cx - px, cy - py, cz - pz
        d2_point = ex * ex + ey * ey + ez * ez
        if away[i]:
            d2_point = np.inf
        if best_face < 0 or d2_point < best_d2:
            best_face, best_d2 = candidates[i], d2_point
            best[0], best[1], best[2], best[3], best[4], best[5] = cx, cy, cz, 1 - v - w, v, w
    if best_face < 0 or not np.isfinite(best_d2):
        return False, -1, best[:3], best[3:]
    return True, best_face, best[:3], best[3:]


def farthest_point_sampling(points: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """Indices of ``count`` points chosen greedily farthest from those already chosen (Euclidean)."""
    rng = np.random.default_rng(seed)
    chosen = [int(rng.integers(len(points)))]
    distance = np.linalg.norm(points - points[chosen[0]], axis=1)
    for _ in range(count - 1):
        nxt = int(np.argmax(distance))
        chosen.append(nxt)
        distance = np.minimum(distance, np.linalg.norm(points - points[nxt], axis=1))
    return np.array(chosen)
