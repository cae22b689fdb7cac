"""``regions.detect``: the base (non-sensing) region, the two exclusion regions and the anchors of
the singularities (paper section 5).

Conventions: ``down`` is the resting direction (unit vector pointing from the object into the
support plane), ``up = -down``. The height below the object of a vertex along ``down`` is
``s = v . down``; the support plane touches the vertex with the largest ``s``.

Base detection:

1. Resting direction. With ``up_axis`` given, ``down = -up_axis``. With only a seed, ``down`` is the
   seed face's outward normal. Otherwise convex-hull triangle planes (per direction cell, the
   largest triangle's) are candidate floors, scored
   by the area of faces facing it within ``angle_threshold_deg`` and lying within
   ``plane_tolerance_mm`` of it; of the best few, the largest connected contact region on which the
   centre of mass rests stably wins (a flat base, not the most probable tumble, is what the object
   stands on).
2. Contact region: faces whose normal deviates less than ``angle_threshold_deg`` from ``down`` and
   whose three vertices lie within ``plane_tolerance_mm`` of the support plane (of the seed's height
   when a seed is given), connected across edges; the component holding the seed, or the largest
   by area. Without overrides it must cover at least ``min_base_area_fraction`` of the surface
   (a sphere's best contact cap is < 1.8 % at 15 degrees), otherwise the node fails and asks for
   ``up_axis`` or a seed. With ``up_axis`` or a seed the base is the component at the lowest point
   (or the seed) and always found: when it is too small to hold two adjacent interior vertices
   (the Rx dipole; a round bottom, e.g. a sphere), the plane tolerance doubles until it does, so a sphere gets the
   lowest point's neighbourhood, a polar cap bounded by the angle threshold.
3. Islands of non-base faces enclosed by the base join the base, so the rest is one piece.

Then, with heat-method geodesic distances (potpourri3d):

* ``base_centre``: the interior base vertex farthest from the base boundary; ``base_dipole`` adds
  its interior neighbour farthest from the boundary.
* ``exclusion_base``: faces grown outward from the base, across edges, while their mean vertex
  distance from the base is below ``exclusion_base_mm`` and their normal deviates from ``down`` by
  less than ``exclusion_base_angle_deg`` (growth stops at whichever threshold is reached first).
* ``far_vertex``: the vertex outside base and first exclusion farthest from the base;
  ``exclusion_far``: faces with mean vertex distance from it below ``exclusion_far_mm`` plus the
  faces around it.
"""
from __future__ import annotations

import numpy as np
import potpourri3d as pp3d
import trimesh
from pydantic import Field, field_validator, model_validator
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull, QhullError, cKDTree

from ...graph.errors import UserError
from ...graph.node import NodeParams, node
from ..data.types import Mesh, SurfaceRegions

MAX_TOLERANCE_DOUBLINGS = 8
"""With an explicit up axis or seed, how often the plane tolerance may double to find a base."""

AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


def parse_axis(spec: str | tuple[float, float, float]) -> np.ndarray:
    """Unit vector of an axis spec: ``"+z"``, ``"-y"``, ``"x"`` or three numbers."""
    if isinstance(spec, str):
        text = spec.strip().lower()
        sign = -1.0 if text.startswith("-") else 1.0
        name = text.lstrip("+-")
        if name not in AXES:
            raise ValueError(f"up_axis {spec!r} is not one of +x, -x, +y, -y, +z, -z or [x, y, z]")
        return sign * np.array(AXES[name])
    vector = np.asarray(spec, dtype=np.float64)
    norm = float(np.linalg.norm(vector))
    if vector.shape != (3,) or not np.isfinite(norm) or norm == 0.0:
        raise ValueError(f"up_axis {spec!r} must be a non-zero 3-vector")
    return vector / norm


class RegionParams(NodeParams):
    """Base detection overrides and exclusion radii (lengths mm, angles degrees)."""

    up_axis: str | tuple[float, float, float] | None = Field(
        None, description='up direction of the object as it rests: "+z", "-y", ... or [x, y, z]'
    )
    seed_face: int | None = Field(None, ge=0, description="a face index on the base")
    seed_point: tuple[float, float, float] | None = Field(
        None, description="a point (mm) on or near the base; its nearest face seeds the base"
    )
    angle_threshold_deg: float = Field(
        15.0, gt=0, lt=90, description="max normal deviation from the resting direction on the base"
    )
    plane_tolerance_mm: float = Field(1.0, gt=0, description="max base height above the support plane")
    min_base_area_fraction: float = Field(
        0.02, gt=0, lt=1, description="automatic detection: smallest flat base, share of the surface"
    )
    exclusion_base_mm: float = Field(10.0, ge=0, description="first exclusion: geodesic width from base")
    exclusion_base_angle_deg: float = Field(
        60.0, gt=0, le=180, description="first exclusion: max normal deviation from resting direction"
    )
    exclusion_far_mm: float = Field(10.0, ge=0, description="second exclusion: geodesic radius at far point")
    direction_cells: int = Field(2000, ge=20, description="automatic detection: direction cells (one hull plane each)")
    candidate_directions: int = Field(6, ge=1, description="automatic detection: best floor planes compared")

    @field_validator("up_axis")
    @classmethod
    def _valid_axis(cls, value: str | tuple[float, float, float] | None) -> str | tuple[float, float, float] | None:
        if value is not None:
            parse_axis(value)
        return value

    @model_validator(mode="after")
    def _one_seed(self) -> "RegionParams":
        if self.seed_face is not None and self.seed_point is not None:
            raise ValueError("set seed_face or seed_point, not both")
        return self


class FaceGraph:
    """Halfedge adjacency of a closed triangle mesh.

    Halfedge ``h = 3 f + k`` runs ``faces[f, k] -> faces[f, (k + 1) % 3]``; ``opposite[h]`` is the
    halfedge running the other way (-1 on a boundary).
    """

    def __init__(self, faces: np.ndarray, vertex_count: int) -> None:
        self.faces = faces
        self.halfedges = np.stack([faces, np.roll(faces, -1, axis=1)], axis=2).reshape(-1, 2)
        keys = self.halfedges[:, 0] * vertex_count + self.halfedges[:, 1]
        order = np.argsort(keys)
        wanted = self.halfedges[:, 1] * vertex_count + self.halfedges[:, 0]
        position = np.clip(np.searchsorted(keys[order], wanted), 0, len(keys) - 1)
        found = keys[order][position] == wanted
        self.opposite = np.where(found, order[position], -1)
        inner = np.flatnonzero(self.opposite >= 0)
        self.pairs = np.stack([inner // 3, self.opposite[inner] // 3], axis=1)

    def components(self, mask: np.ndarray) -> np.ndarray:
        """Edge-connected component label of each face in ``mask`` (-1 outside)."""
        m = len(self.faces)
        pairs = self.pairs[mask[self.pairs].all(axis=1)]
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(m, m))
        labels = connected_components(graph, directed=False)[1]
        return np.where(mask, labels, -1)


def face_normals_areas(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit outward face normals (m, 3) and areas (m,) in mm^2."""
    p0, p1, p2 = (vertices[faces[:, k]] for k in range(3))
    cross = np.cross(p1 - p0, p2 - p0)
    length = np.linalg.norm(cross, axis=1)
    return cross / np.maximum(length, 1e-300)[:, None], 0.5 * length


def contact_region(
    vertices: np.ndarray,
    graph: FaceGraph,
    normals: np.ndarray,
    areas: np.ndarray,
    down: np.ndarray,
    params: RegionParams,
    seed: int | None,
    tolerance_mm: float | None = None,
) -> np.ndarray:
    """Face mask of the flat region resting on the plane normal to ``down`` (module docstring);
    ``tolerance_mm`` replaces ``params.plane_tolerance_mm`` when given."""
    tolerance = params.plane_tolerance_mm if tolerance_mm is None else tolerance_mm
    height = vertices @ down
    reference = height[graph.faces[seed]].mean() if seed is not None else height.max()
    near = (np.abs(reference - height[graph.faces]) <= tolerance).all(axis=1)
    flat = normals @ down >= np.cos(np.radians(params.angle_threshold_deg))
    candidates = near & flat
    if seed is not None:
        candidates[seed] = True
    labels = graph.components(candidates)
    if not candidates.any():
        return candidates
    if seed is not None:
        return labels == labels[seed]
    area_per_label = np.bincount(labels[candidates], weights=areas[candidates])
    return labels == int(np.argmax(area_per_label))


def fibonacci_directions(count: int) -> np.ndarray:
    """``count`` unit vectors spread evenly over the sphere (Fibonacci lattice)."""
    k = np.arange(count) + 0.5
    z = 1.0 - 2.0 * k / count
    azimuth = np.pi * (1.0 + 5.0**0.5) * k
    ring = np.sqrt(1.0 - z * z)
    return np.stack([ring * np.cos(azimuth), ring * np.sin(azimuth), z], axis=1)


def hull_plane_contact(
    vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray, areas: np.ndarray, params: RegionParams
) -> tuple[np.ndarray, np.ndarray]:
    """``(outward normals (h, 3), contact area (h,) mm^2)`` of candidate floor planes: per cell of
    ``direction_cells`` directions, the plane of the largest convex-hull triangle facing into it.

    The contact area of a plane sums the faces whose normal is within ``angle_threshold_deg`` of it
    and whose corners all lie within ``plane_tolerance_mm`` of it: the flat part of the surface the
    object would stand on if that plane were the floor (connectivity not yet applied).
    """
    hull = ConvexHull(vertices)
    corners = hull.points[hull.simplices]
    hull_areas = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    # one plane per direction cell: the largest hull triangle whose normal falls in it
    cell = cKDTree(fibonacci_directions(params.direction_cells)).query(hull.equations[:, :3])[1]
    order = np.lexsort((-hull_areas, cell))
    keep = order[np.r_[True, cell[order][1:] != cell[order][:-1]]]
    plane_normals, offsets = hull.equations[keep, :3], hull.equations[keep, 3]
    chord = 2.0 * np.sin(np.radians(params.angle_threshold_deg) / 2.0)
    pairs = cKDTree(normals).sparse_distance_matrix(cKDTree(plane_normals), chord, output_type="ndarray")
    face, plane = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
    depth = -(np.einsum("kcj,kj->kc", vertices[faces[face]], plane_normals[plane]) + offsets[plane, None])
    touching = depth.max(axis=1) <= params.plane_tolerance_mm
    contact = np.bincount(plane[touching], weights=areas[face[touching]], minlength=len(plane_normals))
    return plane_normals, contact


def centre_of_mass(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Centre of mass (mm) of the solid bounded by a closed, outward-oriented mesh."""
    p0, p1, p2 = (vertices[faces[:, k]] for k in range(3))
    volume = np.einsum("ij,ij->i", p0, np.cross(p1, p2))
    return ((p0 + p1 + p2) * volume[:, None]).sum(axis=0) / (4.0 * volume.sum())


def rests_stably(vertices: np.ndarray, down: np.ndarray, centre: np.ndarray, tolerance_mm: float) -> bool:
    """Whether ``centre`` projects along ``down`` inside the support polygon: the convex hull of the
    vertices within ``tolerance_mm`` of the support plane."""
    axis_u = np.cross(down, np.eye(3)[int(np.argmin(np.abs(down)))])
    axis_u /= np.linalg.norm(axis_u)
    axis_v = np.cross(down, axis_u)
    basis = np.stack([axis_u, axis_v], axis=1)
    height = vertices @ down
    footprint = vertices[height >= height.max() - tolerance_mm] @ basis
    try:
        hull = ConvexHull(footprint)
    except QhullError:  # fewer than three points or all on a line
        return False
    return bool((hull.equations[:, :2] @ (centre @ basis) + hull.equations[:, 2] <= 1e-9).all())


def automatic_base(
    vertices: np.ndarray, graph: FaceGraph, normals: np.ndarray, areas: np.ndarray, params: RegionParams
) -> tuple[np.ndarray, np.ndarray]:
    """``(base mask, down)``: the largest stable flat contact region over all resting directions.

    Convex-hull triangle planes are possible floors; the few with the largest flat contact area
    (at least ``angle_threshold_deg`` apart) are tried, and the largest connected contact region on
    which the centre of mass rests stably wins (the largest one if none does).
    """
    faces = graph.faces
    plane_normals, contact = hull_plane_contact(vertices, faces, normals, areas, params)
    cos_limit = np.cos(np.radians(params.angle_threshold_deg))
    picked: list[np.ndarray] = []
    for index in np.argsort(-contact):
        if contact[index] <= 0 or len(picked) == params.candidate_directions:
            break
        if all(plane_normals[index] @ other < cos_limit for other in picked):
            picked.append(plane_normals[index])
    centre = centre_of_mass(vertices, graph.faces)
    results = []
    for down in picked:
        region = contact_region(vertices, graph, normals, areas, down, params, None)
        if region.any():
            stable = rests_stably(vertices, down, centre, params.plane_tolerance_mm)
            results.append((stable, float(areas[region].sum()), region, down))
    total = float(areas.sum())
    best_area = max((r[1] for r in results), default=0.0)
    if best_area < params.min_base_area_fraction * total:
        raise UserError(
            f"no flat resting region found (largest {100 * best_area / total:.1f}% of the surface, "
            f"need {100 * params.min_base_area_fraction:.1f}%): set up_axis (e.g. \"+z\") or "
            "seed_point/seed_face on the base, or raise angle_threshold_deg/plane_tolerance_mm"
        )
    large = [r for r in results if r[1] >= params.min_base_area_fraction * total]
    _, _, region, down = max(large, key=lambda r: (r[0], r[1]))
    return region, down


def nearest_face(vertices: np.ndarray, faces: np.ndarray, point: np.ndarray) -> int:
    """Index of the face closest to ``point`` (mm)."""
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    return int(trimesh.proximity.closest_point(mesh, point[None, :])[2][0])


def detect_base(
    vertices: np.ndarray, graph: FaceGraph, normals: np.ndarray, areas: np.ndarray, params: RegionParams
) -> tuple[np.ndarray, np.ndarray]:
    """``(base face mask, down unit vector)`` following the module docstring."""
    seed = params.seed_face
    if seed is not None and seed >= len(graph.faces):
        raise UserError(f"seed_face {seed} does not exist: the mesh has {len(graph.faces)} faces")
    if params.seed_point is not None:
        seed = nearest_face(vertices, graph.faces, np.asarray(params.seed_point, dtype=np.float64))
    if params.up_axis is not None:
        down = -parse_axis(params.up_axis)
    elif seed is not None:
        down = normals[seed].copy()
    else:
        return automatic_base(vertices, graph, normals, areas, params)
    # an explicit override always yields a base: on a round bottom the plane tolerance doubles
    # until the region around the lowest point (or the seed) has an interior edge
    tolerance = params.plane_tolerance_mm
    for _ in range(MAX_TOLERANCE_DOUBLINGS):
        base = contact_region(vertices, graph, normals, areas, down, params, seed, tolerance)
        on_base, off_base = vertex_masks(graph.faces, base, len(vertices))
        interior = on_base & ~off_base
        if interior[graph.halfedges].all(axis=1).any():  # room for the Rx dipole
            break
        tolerance *= 2.0
    if not base.any():
        raise UserError(
            f"no base faces face the resting direction {np.round(-down, 3).tolist()} within "
            f"{params.angle_threshold_deg} deg: check up_axis or raise angle_threshold_deg"
        )
    return base, down


def absorb_islands(graph: FaceGraph, base: np.ndarray, areas: np.ndarray) -> np.ndarray:
    """Base plus every non-base component except the largest, so the rest is one piece."""
    labels = graph.components(~base)
    rest = labels >= 0
    if not rest.any():
        raise UserError("the base covers the whole surface: lower angle_threshold_deg or plane_tolerance_mm")
    largest = int(np.argmax(np.bincount(labels[rest], weights=areas[rest])))
    return base | (rest & (labels != largest))


def vertex_masks(faces: np.ndarray, face_mask: np.ndarray, vertex_count: int) -> tuple[np.ndarray, np.ndarray]:
    """``(touched by a face in mask, touched by a face outside mask)`` per vertex."""
    inside = np.zeros(vertex_count, dtype=bool)
    outside = np.zeros(vertex_count, dtype=bool)
    inside[faces[face_mask].ravel()] = True
    outside[faces[~face_mask].ravel()] = True
    return inside, outside


def grow_exclusion(
    graph: FaceGraph,
    base: np.ndarray,
    face_distance: np.ndarray,
    normals: np.ndarray,
    down: np.ndarray,
    params: RegionParams,
) -> np.ndarray:
    """First exclusion region: faces reachable from the base within both thresholds."""
    within = (face_distance < params.exclusion_base_mm) & (
        normals @ down > np.cos(np.radians(params.exclusion_base_angle_deg))
    )
    labels = graph.components(base | within)
    return np.isin(labels, np.unique(labels[base])) & ~base


@node("regions.detect", params=RegionParams, inputs=("mesh",), outputs=("regions",))
def detect_regions(params: RegionParams, mesh: Mesh) -> SurfaceRegions:
    """Find the base the object rests on, the two exclusion regions and the singularity anchors."""
    vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.int64)
    n = len(vertices)
    graph = FaceGraph(faces, n)
    if (graph.opposite < 0).any():
        raise UserError("regions.detect needs a closed mesh: run mesh.repair and mesh.check_topology first")
    normals, areas = face_normals_areas(vertices, faces)
    base, down = detect_base(vertices, graph, normals, areas, params)
    base = absorb_islands(graph, base, areas)

    on_base, off_base = vertex_masks(faces, base, n)
    interior = np.flatnonzero(on_base & ~off_base)
    if len(interior) == 0:
        raise UserError(
            f"the base ({int(base.sum())} faces) has no interior vertex: raise angle_threshold_deg or "
            "plane_tolerance_mm, or remesh finer"
        )
    solver = pp3d.MeshHeatMethodDistanceSolver(vertices, faces)
    from_boundary = solver.compute_distance_multisource(np.flatnonzero(on_base & off_base))
    centre = int(interior[np.argmax(from_boundary[interior])])
    edges = graph.halfedges
    neighbours = edges[edges[:, 0] == centre, 1]
    neighbours = neighbours[on_base[neighbours] & ~off_base[neighbours]]
    if len(neighbours) == 0:
        raise UserError("the base is too narrow for the Rx dipole: raise angle_threshold_deg or remesh finer")
    partner = int(neighbours[np.argmax(from_boundary[neighbours])])

    # distance from the base = distance from its boundary outside it, 0 on it (the heat method
    # smooths many-source distances, so the boundary is the better source set)
    from_base = np.where(on_base, 0.0, np.maximum(from_boundary, 0.0))
    exclusion_base = grow_exclusion(graph, base, from_base[faces].mean(axis=1), normals, down, params)
    blocked = base | exclusion_base
    touches_blocked, _ = vertex_masks(faces, blocked, n)
    free = np.flatnonzero(~touches_blocked)
    if len(free) == 0:
        raise UserError("base and first exclusion cover the whole surface: lower exclusion_base_mm")
    far_vertex = int(free[np.argmax(from_base[free])])
    from_far = solver.compute_distance(far_vertex)
    exclusion_far = (from_far[faces].mean(axis=1) < params.exclusion_far_mm) | (faces == far_vertex).any(axis=1)
    exclusion_far &= ~blocked
    sensing = ~(blocked | exclusion_far)
    if not sensing.any():
        raise UserError("no sensing surface is left: lower exclusion_base_mm or exclusion_far_mm")

    halfedge_face = np.arange(len(edges)) // 3
    toward_base = sensing[halfedge_face] & blocked[graph.opposite // 3]
    return SurfaceRegions(
        base_faces=base,
        exclusion_base=exclusion_base,
        exclusion_far=exclusion_far,
        sensing_faces=sensing,
        base_centre=centre,
        base_dipole=np.array([centre, partner], dtype=np.int64),
        far_vertex=far_vertex,
        up=-down,
        base_boundary_edges=np.ascontiguousarray(edges[toward_base], dtype=np.int64),
        base_distance_mm=np.asarray(from_base, dtype=np.float64),
    )
