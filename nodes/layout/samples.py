"""Uniform surface samples on the sensing surface and batched heat-method geodesic distances.

The layout optimisation (paper section 6) measures coverage against ``K`` reference samples ``S``
spread uniformly over the sensing surface that a finger can touch (``regions.touchable``), and needs
geodesic distances sample -> candidate crossing, crossing -> crossing and pad -> surface.

Geodesics: the heat method (Crane, Weischedel, Wardetzky 2013), the algorithm of potpourri3d's
``MeshHeatMethodDistanceSolver``, re-implemented here over scipy so that (a) sources may be arbitrary
surface points given as (face, barycentrics) rather than vertices only, and (b) many sources are
solved at once with one sparse Cholesky factorisation (cholespy) and matrix right-hand sides. The operators are the
standard P1 ones: ``G`` the per-face gradient, ``L = G^T A G`` the cotan stiffness matrix (equal to
``potpourri3d.cotan_laplacian``), ``M`` the lumped (barycentric) vertex areas, time step
``t = t_coef * h^2`` with ``h`` the mean edge length. tests/test_layout_metrics.py checks the
result against exact sphere geodesics and against potpourri3d.

A mesh of more than ``PROXY_VERTICES`` vertices is solved on a copy decimated to about that many
(:mod:`..geometry.proxy`), the fields interpolated back to its vertices.

Units: mesh coordinates are millimetres, so every distance here is in millimetres.
"""
from __future__ import annotations

import dataclasses
import functools

import numpy as np
from pydantic import Field

from ...graph.errors import UserError
from ...graph.hashing import digest_fields
from ...graph.node import NodeParams, node
from ..data.types import Mesh, SurfaceRegions
from ..geometry.proxy import PROXY_VERTICES, proxy_of
from ..geometry.sparse_spd import cholesky, solve
from ..geometry.triangles import areas, corners, cross_products, mean_edge_mm, normals, random_barycentrics, zero_area

_COLUMNS_PER_BATCH = 8  # sources solved per block; bounds memory to ~(3 * faces * 8) float64 temporaries


class HeatSolver:
    """The heat method's operators on one triangle mesh, factorised once (see the module docstring)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, t_coef: float = 1.0):
        import scipy.sparse as sp  # heavy: imported when used, not on node discovery

        V = np.asarray(vertices, dtype=np.float64)
        F = np.asarray(faces, dtype=np.int64)
        n, m = len(V), len(F)
        normal2 = cross_products(corners(V, F))  # length = 2 * area
        double_area = np.linalg.norm(normal2, axis=1)
        if np.any(zero_area(double_area)):
            raise UserError("mesh has degenerate (zero-area) faces: run mesh.repair before the layout")
        unit_n = normal2 / double_area[:, None]
        area = 0.5 * double_area
        # grad(lambda_i) = N x e_i / (2A), e_i the edge opposite corner i, oriented CCW.
        rows, cols, vals = [], [], []
        for i, (a, b) in enumerate(((1, 2), (2, 0), (0, 1))):
            g = np.cross(unit_n, V[F[:, b]] - V[F[:, a]]) / double_area[:, None]
            for axis in range(3):
                rows.append(3 * np.arange(m) + axis)
                cols.append(F[:, i])
                vals.append(g[:, axis])
        self.grad = sp.csr_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(3 * m, n)
        )
        weights = sp.diags(np.repeat(area, 3))
        self.stiffness = (self.grad.T @ weights @ self.grad).tocsc()
        self.div_operator = (self.grad.T @ weights).tocsr()  # integrated divergence of a face field
        mass = np.zeros(n)
        np.add.at(mass, F.ravel(), np.repeat(area / 3.0, 3))
        h = mean_edge_mm(V, F)
        t = t_coef * h * h
        self.vertices = V
        self.faces = F
        self.heat = cholesky(sp.diags(mass) + t * self.stiffness)
        # L has the constants as null space; a tiny mass shift makes it definite, then the
        # distance is re-anchored at its source (see fields), so the shift only removes the free constant.
        self.poisson = cholesky(self.stiffness + 1e-9 * sp.diags(mass))

    def _load(self, faces: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Load vectors (n, S) of point sources at (face, barycentrics): the P1 projection of a Dirac."""
        S = len(faces)
        B = np.zeros((len(self.vertices), S))
        np.add.at(B, (self.faces[faces].ravel(), np.repeat(np.arange(S), 3)), bary.ravel())
        return B

    def fields(self, faces: np.ndarray, bary: np.ndarray, to_mesh=None) -> np.ndarray:
        """:meth:`HeatGeodesics.fields` on this solver's mesh: (n, S) float32, or ``to_mesh @`` them
        block by block for a scipy sparse ``to_mesh`` (rows, n)."""
        faces = np.asarray(faces, dtype=np.int64)
        bary = np.asarray(bary, dtype=np.float64)
        out = np.empty((len(self.vertices) if to_mesh is None else to_mesh.shape[0], len(faces)), dtype=np.float32)
        m = len(self.faces)
        for start in range(0, len(faces), _COLUMNS_PER_BATCH):
            sl = slice(start, start + _COLUMNS_PER_BATCH)
            u = solve(self.heat, self._load(faces[sl], bary[sl]))
            g = (self.grad @ u).reshape(m, 3, -1)
            del u
            # far from a source the heat underflows: scale each gradient by its largest component
            # before squaring, so that a tiny one keeps its direction instead of becoming huge
            scale = np.maximum(np.maximum(np.abs(g[:, 0]), np.abs(g[:, 1])), np.abs(g[:, 2]))
            np.maximum(scale, np.finfo(np.float64).tiny, out=scale)
            g /= scale[:, None, :]
            norm = g[:, 0] * g[:, 0]  # |g| / scale per face and source, in place (as np.linalg.norm sums)
            norm += g[:, 1] * g[:, 1]
            norm += g[:, 2] * g[:, 2]
            del scale
            np.maximum(np.sqrt(norm, out=norm), 1.0, out=norm)  # 1 <= |g| / scale <= sqrt(3) where g != 0
            np.divide(np.negative(g, out=g), norm[:, None, :], out=g)  # X = -grad u / |grad u|
            del norm
            phi = solve(self.poisson, self.div_operator @ g.reshape(3 * m, -1))
            del g
            source_corners = self.faces[faces[sl]]  # (s, 3)
            corner_points = self.vertices[source_corners]  # (s, 3, 3)
            to_corners = np.linalg.norm(corner_points - np.einsum("sc,scd->sd", bary[sl], corner_points)[:, None], axis=2)
            phi -= np.sum((phi[source_corners, np.arange(phi.shape[1])[:, None]] - to_corners) * bary[sl], axis=1)[None, :]
            np.maximum(phi, 0.0, out=phi)
            out[:, sl] = phi if to_mesh is None else to_mesh @ phi
            if not np.isfinite(out[:, sl]).all():  # never silently: phase 1 would quantise garbage
                raise FloatingPointError(f"heat-method distances from sources {start}..{start + len(source_corners) - 1} are not finite")
        return out


class HeatGeodesics:
    """Heat-method geodesic distance fields on one triangle mesh (see the module docstring), solved on the
    mesh or, above ``proxy_vertices``, on its decimated copy; the solver is built by the first :meth:`fields`
    (interpolating fields at points needs none)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, t_coef: float = 1.0, proxy_vertices: int = PROXY_VERTICES):
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)
        self.vertex_count = len(self.vertices)
        self.mean_edge_mm = mean_edge_mm(self.vertices, self.faces)
        self._t_coef = t_coef
        self._proxy_vertices = proxy_vertices

    @functools.cached_property
    def proxy(self):
        """The decimated copy (:func:`..geometry.proxy.proxy_of`), or None on a mesh small enough or
        when no copy keeps its topology."""
        if self.vertex_count <= self._proxy_vertices:
            return None
        return proxy_of(self.vertices, self.faces, self._proxy_vertices)

    @functools.cached_property
    def solver(self) -> HeatSolver:
        """The heat method's operators on the copy, else on the mesh."""
        on = self.proxy if self.proxy is not None else self
        return HeatSolver(on.vertices, on.faces, self._t_coef)

    def fields(self, faces: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Geodesic distance (mm) from each source point to every vertex: array (n, S), float32.

        Source ``s`` is the surface point ``p = bary[s] @ V[F[faces[s]]]``. The heat method's distance
        is rounded off over about an edge around its source, so the field's constant is set where it
        is exact: at the corners of the source's face, whose distances from ``p`` are straight lines,
        the field matches them on average (weighted by ``bary``; a vertex source is 0 at its vertex).
        Inside that face the field is the P1 interpolation of those distances (up to an edge length at
        ``p``, not 0); it is clipped at 0. On a copy, the sources are its closest points (on its side
        facing as the mesh does there) and the fields its interpolation at the mesh's vertices.
        """
        faces = np.asarray(faces, dtype=np.int64)
        bary = np.asarray(bary, dtype=np.float64)
        if self.proxy is None:
            return self.solver.fields(faces, bary)
        points = np.einsum("sc,scd->sd", bary, self.vertices[self.faces[faces]])
        copy_faces, copy_bary = self.proxy.locate(points, normals(corners(self.vertices, self.faces[faces]))[0])
        return self.solver.fields(copy_faces, copy_bary, self.proxy.interpolation)

    def evaluate(self, fields: np.ndarray, faces: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Interpolate vertex fields (n, S) at surface points -> (S, P) distances in mm."""
        corners = self.faces[np.asarray(faces, dtype=np.int64)]  # (P, 3)
        vals = fields[corners]  # (P, 3, S)
        return np.einsum("pcs,pc->sp", vals, np.asarray(bary, dtype=np.float64))

    def pairwise(self, faces: np.ndarray, bary: np.ndarray, fields: np.ndarray | None = None) -> np.ndarray:
        """Symmetric (P, P) geodesic distances (mm) among surface points (mean of both directions, 0 on
        the diagonal); ``fields`` the points' own :meth:`fields` when they are at hand."""
        D = self.evaluate(self.fields(faces, bary) if fields is None else fields, faces, bary)
        D = 0.5 * (D + D.T)
        np.fill_diagonal(D, 0.0)
        return D


def array_digest(*arrays: np.ndarray) -> str:
    """Content hash of arrays (each one's dtype, shape and bytes, length-prefixed: :func:`digest_fields`)."""
    return digest_fields([f for a in arrays for f in (f"{a.dtype}{a.shape}", np.ascontiguousarray(a).tobytes())])


@functools.lru_cache(maxsize=2)
def _cached_geodesics(digest: str, vertices_bytes: bytes, faces_bytes: bytes, n: int, m: int) -> HeatGeodesics:
    V = np.frombuffer(vertices_bytes, dtype=np.float64).reshape(n, 3)
    F = np.frombuffer(faces_bytes, dtype=np.int64).reshape(m, 3)
    return HeatGeodesics(V, F)


def geodesics_for(mesh: Mesh) -> HeatGeodesics:
    """The heat-method solver for ``mesh``, factorised once per process (cached by content hash)."""
    V = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    F = np.ascontiguousarray(mesh.faces, dtype=np.int64)
    return _cached_geodesics(array_digest(V, F), V.tobytes(), F.tobytes(), len(V), len(F))


def sample_surface(
    vertices: np.ndarray,
    faces: np.ndarray,
    face_mask: np.ndarray,
    keep_mask: np.ndarray,
    count: int,
    seed: int,
    spacing_factor: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """``count`` uniform samples on the faces of ``face_mask & keep_mask`` with distance-threshold
    (dart-throwing) rejection.

    Candidates are drawn uniformly by area over ``face_mask`` and those off ``keep_mask`` dropped, so
    that a small change of ``keep_mask`` leaves the other samples as they were; a candidate is kept
    when its Euclidean distance to every kept sample is at least ``r = spacing_factor * sqrt(area /
    count)``, ``area`` the kept faces' (Euclidean distance is a lower bound of the geodesic one). When
    50 consecutive batches add nothing, ``r`` shrinks by 10 %. Returns (faces (K,), bary (K, 3),
    points (K, 3), final r in mm). Deterministic for a seed.
    """
    idx = np.flatnonzero(face_mask)
    if not (face_mask & keep_mask).any():
        raise UserError("the sensing region has no faces: check the regions.detect parameters")
    face_area = areas(corners(vertices, faces[idx]))
    total = float(face_area.sum())
    cdf = np.cumsum(face_area) / total
    rng = np.random.default_rng(seed)
    radius = spacing_factor * np.sqrt(float(face_area[keep_mask[idx]].sum()) / count)
    kept_f: list[int] = []
    kept_b: list[np.ndarray] = []
    kept_p = np.empty((0, 3))
    stale = 0
    while len(kept_f) < count:
        f = idx[np.minimum(np.searchsorted(cdf, rng.random(256)), len(idx) - 1)]
        b = random_barycentrics(rng, 256)
        p = np.einsum("kc,kcd->kd", b, vertices[faces[f]])
        added = 0
        for j in range(256):
            if not keep_mask[f[j]]:
                continue
            if len(kept_p) and np.min(np.sum((kept_p - p[j]) ** 2, axis=1)) < radius * radius:
                continue
            kept_f.append(int(f[j]))
            kept_b.append(b[j])
            kept_p = np.vstack([kept_p, p[j]])
            added += 1
            if len(kept_f) == count:
                break
        stale = 0 if added else stale + 1
        if stale >= 50:
            radius *= 0.9
            stale = 0
    return np.array(kept_f, dtype=np.int64), np.array(kept_b), kept_p, float(radius)


@dataclasses.dataclass(frozen=True)
class SurfaceSamples:
    """K reference samples on the touchable part of the sensing surface with their geodesic distance fields.

    ``distances[:, k]`` is the geodesic distance (mm) from sample ``k`` to every mesh vertex; the
    distance to any surface point is its barycentric interpolation (:meth:`HeatGeodesics.evaluate`).
    """

    points: np.ndarray  # (K, 3) float64, mm
    faces: np.ndarray  # (K,) int64
    bary: np.ndarray  # (K, 3) float64
    distances: np.ndarray  # (n_vertices, K) float32, mm
    spacing_mm: float  # the rejection threshold actually used
    sensing_faces: np.ndarray  # (m,) bool, the sensing region: where curves run and their clearance counts
    touch_faces: np.ndarray  # (m,) bool, its faces a finger can touch: where samples are drawn and coverage counts
    sensing_area_mm2: float
    touch_area_mm2: float


class SamplesParams(NodeParams):
    count: int = Field(300, ge=10, le=5000, description="number K of reference samples on the sensing surface")
    seed: int = Field(0, description="random seed of the sampler")
    spacing_factor: float = Field(
        0.7, gt=0, le=1.2, description="rejection threshold as a fraction of sqrt(sensing area / K)"
    )


def sensing_face_mask(regions: object, face_count: int) -> np.ndarray:
    """Boolean (m,) mask of the sensing faces from ``regions.sensing_faces`` (mask or index array)."""
    sensing = np.asarray(regions.sensing_faces)  # type: ignore[attr-defined]
    if sensing.dtype == bool:
        if sensing.shape != (face_count,):
            raise UserError("regions.sensing_faces does not match the mesh: rerun regions.detect on this mesh")
        return sensing
    mask = np.zeros(face_count, dtype=bool)
    mask[sensing.astype(np.int64)] = True
    return mask


@node("layout.samples", params=SamplesParams, inputs=("mesh", "regions"), outputs=("samples",))
def surface_samples(params: SamplesParams, mesh: Mesh, regions: SurfaceRegions) -> SurfaceSamples:
    """K uniform reference samples on the sensing surface a finger can touch and their geodesic distance fields (mm)."""
    sensing = sensing_face_mask(regions, len(mesh.faces))
    touch = sensing & np.asarray(regions.touch_faces, dtype=bool)
    if not touch.any():
        raise UserError("a finger can touch none of the sensing region: lower regions.touchable's finger_radius_mm "
                        "or raise its finger_reach_mm")
    f, b, p, r = sample_surface(mesh.vertices, mesh.faces, sensing, touch, params.count, params.seed, params.spacing_factor)
    face_area = areas(corners(mesh.vertices, mesh.faces))
    return SurfaceSamples(
        points=p,
        faces=f,
        bary=b,
        distances=geodesics_for(mesh).fields(f, b),
        spacing_mm=r,
        sensing_faces=sensing,
        touch_faces=touch,
        sensing_area_mm2=float(face_area[sensing].sum()),
        touch_area_mm2=float(face_area[touch].sum()),
    )
