"""Resting pose: the floor plane an object is set down on, by quasi-static analysis of its hull, on
the shape scaled to ``POSE_DIAGONAL_MM`` (:func:`at_pose_size`: the pose is the shape's, whatever its size).

A rigid object on a table rests on a plane of its convex hull. Candidate floors are convex-hull
triangle planes, one per cell of ``direction_cells`` evenly spread directions (the cell's largest
hull triangle). Each candidate gets

* its **contact area** (mm^2): the faces whose normal is within ``angle_threshold_deg`` of the floor
  normal and whose corners all lie within ``plane_tolerance_mm`` of it (connectivity not applied:
  several feet add up); on a stable floor that the object touches with ``FEET_MIN`` or more separate
  feet, at least the area of the polygon the feet span (:func:`feet_support_mm2`). A rigid body
  generically rests on three points; four or more separate patches of similar size in one plane,
  at the ends of legs (still apart ``LEG_SHARE`` of the diagonal above the floor), are what it was
  made to stand on (an animal or a figurine on its legs), and the load is carried over the whole
  polygon between them however small each rounded foot's own contact is (a flat face larger than
  that polygon still wins: a stool with a broad flat seat is set on its seat). Two feet count the
  same way on a figure that stands tall on them (a person, a bird: at least as tall as wide in that
  pose, the feet apart up to ``STRIDE_SHARE`` of its height): small soles with the body's weight
  above them, which a person sets upright rather than on its front; and
* its **tipping angle** (degrees): the support polygon is the convex hull of the hull vertices
  within ``plane_tolerance_mm`` of the floor; the angle is ``atan(margin / height)``, where
  ``margin`` is the distance from the centre of mass's projection to the polygon's nearest edge
  (negative outside: the object falls over) and ``height`` the centre of mass's height. It is the
  smallest tilt that topples the object.

A person sets a mirror-symmetric object (an animal, a figure, a boat, a teddy) down with its
mirror planes upright, not on its flank or its back: a floor keeps a mirror plane
(:func:`mirror_planes`) upright when its up direction lies within ``MIRROR_UPRIGHT_DEG`` of the
plane, and only the stable floors (tipping angle at least ``min_tipping_deg``) that keep the most
mirror planes upright are candidates (a sword or a spoon, whose stable floors all lie on one of its
planes, keeps one). Among these, the pose is the one with the largest contact area: a flat bottom
or a foot ring however small, the soles of all the feet together, and on a round object (nothing
flat anywhere) its flattest side, which is also its widest support. A pose whose contact ring
encloses a deep cavity (a bowl or a cup upside down on its rim) is passed over for the next
(``regions.detect``). If no candidate is stable the most stable one is taken.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull, QhullError, cKDTree

from ..geometry.triangles import corners, normals


MIRROR_SAMPLES = 3000
"""Surface samples of the mirror-symmetry test."""
MIRROR_TOLERANCE = 1.5
"""A plane is a mirror plane when the reflected samples lie on average within this many mean
sample spacings of the surface."""
MIRROR_UPRIGHT_DEG = 20.0
"""A floor keeps a mirror plane upright when its up direction is within this angle of the plane."""
PLANE_CHUNK = 128
"""Planes tested against all vertices at once (bounds memory)."""
FEET_MIN = 4
"""Separate contact patches from which a floor stands on feet (a rigid body generically rests on
three points; four or more separate patches in one plane are made to stand on)."""
FEET_ANGLE_DEG = 45.0
"""A foot's contact faces: normal within this angle of the floor normal (the rounded end of a leg)."""
FEET_DEPTH = 2.0
"""A foot's contact faces lie within this many plane tolerances of the floor."""
FEET_SHARE = 0.25
"""A contact patch counts as a foot with at least this share of the largest patch's area."""
LEG_SHARE = 0.05
"""Feet stand on legs: they stay separate up to this share of the object's bounding-box diagonal
above the floor (bumps of one face, or a body lying on its side, merge well below it)."""
STRIDE_SHARE = 0.2
"""A figure stands on two feet (a person, a bird) when it is at least as tall as it is wide in that
pose and its feet stay separate up to this share of its height (a person's legs part at about half
of it, a short-legged cartoon figure's at a quarter; a lying object is not tall)."""


POSE_DIAGONAL_MM = 170.0
"""The pose is found on the shape scaled to this bounding-box diagonal (the default object size), so
that it is a property of the shape: the contact band and the tipping polygon's tolerance
(``plane_tolerance_mm``) are judged at this size, whatever the object's own."""


def at_pose_size(vertices: np.ndarray) -> np.ndarray:
    """``vertices`` (mm) scaled about the origin to a ``POSE_DIAGONAL_MM`` bounding-box diagonal."""
    return vertices * (POSE_DIAGONAL_MM / float(np.linalg.norm(np.ptp(vertices, axis=0))))


@dataclasses.dataclass(frozen=True)
class Floor:
    """A candidate floor plane: outward ``down`` unit normal, contact area mm^2, tipping angle deg,
    and the number of feet whose polygon is its contact (0: the contact faces' area)."""

    down: np.ndarray
    contact_mm2: float
    tipping_deg: float
    feet: int = 0


def fibonacci_directions(count: int) -> np.ndarray:
    """``count`` unit vectors spread evenly over the sphere (Fibonacci lattice)."""
    k = np.arange(count) + 0.5
    z = 1.0 - 2.0 * k / count
    azimuth = np.pi * (1.0 + 5.0**0.5) * k
    ring = np.sqrt(1.0 - z * z)
    return np.stack([ring * np.cos(azimuth), ring * np.sin(azimuth), z], axis=1)


def centre_of_mass(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Centre of mass (mm) of the solid of uniform density bounded by a closed outward mesh."""
    return np.asarray(trimesh.Trimesh(vertices, faces, process=False).center_mass, dtype=np.float64)


def mirror_planes(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``(k, 3)`` unit normals of the object's mirror planes (k = 0 to 3). A mirror plane of a solid
    passes through its centre of mass with a principal axis of inertia as normal, so the three
    principal planes are tested: reflected surface samples must land on the surface
    (``MIRROR_TOLERANCE``)."""
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    centre = np.asarray(mesh.center_mass, dtype=np.float64)
    axes = np.linalg.eigh(mesh.moment_inertia)[1].T
    samples = np.asarray(trimesh.sample.sample_surface_even(mesh, MIRROR_SAMPLES, seed=0)[0])
    tree = cKDTree(samples)
    spacing = float(tree.query(samples, k=2)[0][:, 1].mean())
    reflected = [samples - 2.0 * ((samples - centre) @ n)[:, None] * n for n in axes]
    keep = [float(tree.query(points)[0].mean()) < MIRROR_TOLERANCE * spacing for points in reflected]
    return axes[np.asarray(keep, dtype=bool)].reshape(-1, 3)


def upright_mirrors(floor: "Floor", mirrors: np.ndarray) -> int:
    """How many mirror planes (unit normals ``mirrors``) ``floor``'s up direction lies within
    ``MIRROR_UPRIGHT_DEG`` of."""
    return int(np.count_nonzero(np.abs(mirrors @ floor.down) < np.sin(np.radians(MIRROR_UPRIGHT_DEG))))


def plane_basis(down: np.ndarray) -> np.ndarray:
    """``(3, 2)`` orthonormal basis of the plane normal to the unit vector ``down``."""
    axis_u = np.cross(down, np.eye(3)[int(np.argmin(np.abs(down)))])
    axis_u /= np.linalg.norm(axis_u)
    return np.stack([axis_u, np.cross(down, axis_u)], axis=1)


def tipping_angle_deg(points: np.ndarray, down: np.ndarray, centre: np.ndarray, tolerance_mm: float) -> float:
    """Smallest tilt (deg) that topples the object resting on ``points`` along ``down`` (module
    docstring); negative when ``centre`` projects outside the support polygon."""
    height = points @ down
    support = height.max()
    basis = plane_basis(down)
    footprint = points[height >= support - tolerance_mm] @ basis
    try:
        hull = ConvexHull(footprint)
    except (QhullError, ValueError):  # fewer than three points, or all on a line
        hull = None
    if hull is None:
        margin = -float(np.linalg.norm(footprint - centre @ basis, axis=1).min())
    else:
        margin = -float((hull.equations[:, :2] @ (centre @ basis) + hull.equations[:, 2]).max())
    return float(np.degrees(np.arctan2(margin, max(support - centre @ down, 1e-9))))


def touching_faces(
    vertices: np.ndarray,
    faces: np.ndarray,
    face_normals: np.ndarray,
    planes: np.ndarray,
    angle_deg: float,
    tolerance_mm: float,
) -> tuple[np.ndarray, np.ndarray]:
    """``(face, plane)`` index pairs: the face's normal is within ``angle_deg`` of the plane's outward
    normal and its corners lie within ``tolerance_mm`` of the plane (``planes`` rows: normal, offset)."""
    gap = np.full(len(vertices), np.inf)
    for start in range(0, len(planes), PLANE_CHUNK):
        chunk = planes[start : start + PLANE_CHUNK]
        gap = np.minimum(gap, -(vertices @ chunk[:, :3].T + chunk[:, 3]).max(axis=1))
    close = np.flatnonzero((gap[faces] <= tolerance_mm).all(axis=1))
    used, corner = np.unique(faces[close], return_inverse=True)
    corner = corner.reshape(-1, 3)
    found: list[tuple[np.ndarray, np.ndarray]] = []
    for start in range(0, len(planes), PLANE_CHUNK):
        chunk = planes[start : start + PLANE_CHUNK]
        near = vertices[used] @ chunk[:, :3].T + chunk[:, 3] >= -tolerance_mm
        face, plane = np.nonzero(near[corner].all(axis=1))
        face = close[face]
        facing = np.einsum("kj,kj->k", face_normals[face], chunk[plane, :3]) >= np.cos(np.radians(angle_deg))
        found.append((face[facing], plane[facing] + start))
    return np.concatenate([f for f, _ in found]), np.concatenate([p for _, p in found])


def groups_apart(graph, depth: np.ndarray, contact_faces: np.ndarray, height_mm: float) -> int:
    """How many groups ``contact_faces`` fall into on the surface below ``height_mm`` above the floor
    (``depth``: each vertex's height above it, mm; ``graph``: the mesh's FaceGraph)."""
    return len(np.unique(graph.components((depth[graph.faces] <= height_mm).all(axis=1))[contact_faces]))


def feet_support_mm2(
    vertices: np.ndarray, faces: np.ndarray, face_normals: np.ndarray, planes: np.ndarray, tolerance_mm: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per plane (rows: outward normal, offset), ``(area mm^2 of the polygon its feet span, number of
    feet)``, both 0 where it has no feet: faces within ``FEET_ANGLE_DEG`` of the plane and
    ``FEET_DEPTH * tolerance_mm`` of it, in edge-connected patches of at least ``FEET_SHARE`` of the
    plane's largest patch's area; ``FEET_MIN`` or more of them still apart on the surface up to
    ``LEG_SHARE`` of the object's diagonal above the floor (legs), or, when the object is at least as
    tall as wide in that pose, two legs: the patches (a sole may split into heel and toe) fall into
    exactly two groups still apart up to ``STRIDE_SHARE`` of its height."""
    from .faces import FaceGraph

    face, plane = touching_faces(vertices, faces, face_normals, planes, FEET_ANGLE_DEG, FEET_DEPTH * tolerance_mm)
    support, count = np.zeros(len(planes)), np.zeros(len(planes), dtype=np.int64)
    if len(face) == 0:
        return support, count
    keys = plane * len(faces) + face
    order = np.argsort(keys)
    graph = FaceGraph(faces, len(vertices))
    opposite = graph.opposite
    size = float(np.linalg.norm(np.ptp(vertices, axis=0)))
    node = np.repeat(np.arange(len(face)), 3)
    wanted = plane[node] * len(faces) + opposite[3 * face[:, None] + np.arange(3)].ravel() // 3
    position = np.clip(np.searchsorted(keys[order], wanted), 0, len(keys) - 1)
    found = keys[order][position] == wanted
    links = coo_matrix((np.ones(int(found.sum())), (node[found], order[position][found])), shape=(len(face),) * 2)
    label = connected_components(links, directed=False)[1]
    area = np.bincount(label, weights=normals(corners(vertices, faces[face]))[1])
    label_plane = np.zeros(len(area), dtype=np.int64)
    label_plane[label] = plane
    largest = np.zeros(len(planes))
    np.maximum.at(largest, label_plane, area)
    foot = area >= FEET_SHARE * largest[label_plane]
    legs_mm = max(LEG_SHARE * size, FEET_DEPTH * tolerance_mm)  # four feet stay apart up to this height
    for index in np.flatnonzero(np.bincount(label_plane[foot], minlength=len(planes)) >= 2):
        feet = (plane == index) & foot[label]
        depth = -(vertices @ planes[index, :3] + planes[index, 3])
        basis = plane_basis(planes[index, :3])
        patches = len(np.unique(label[feet]))
        if patches >= FEET_MIN and groups_apart(graph, depth, face[feet], legs_mm) >= FEET_MIN:
            feet_count = patches
        elif (depth.max() >= np.ptp(vertices @ basis, axis=0).max()
              and groups_apart(graph, depth, face[feet], STRIDE_SHARE * depth.max()) == 2):
            feet_count = 2
        else:
            continue
        points = vertices[np.unique(faces[face[feet]])] @ basis
        support[index], count[index] = ConvexHull(points).volume, feet_count
    return support, count


def candidate_floors(
    vertices: np.ndarray,
    faces: np.ndarray,
    direction_cells: int,
    angle_threshold_deg: float,
    plane_tolerance_mm: float,
) -> list[Floor]:
    """Every candidate floor plane with its contact area and tipping angle (module docstring)."""
    hull = ConvexHull(vertices)
    hull_areas = normals(hull.points[hull.simplices])[1]
    cell = cKDTree(fibonacci_directions(direction_cells)).query(hull.equations[:, :3])[1]
    order = np.lexsort((-hull_areas, cell))
    keep = order[np.r_[True, cell[order][1:] != cell[order][:-1]]]
    plane_normals = hull.equations[keep, :3]
    face_normals, face_areas = normals(corners(vertices, faces))
    planes = hull.equations[keep]
    face, plane = touching_faces(vertices, faces, face_normals, planes, angle_threshold_deg, plane_tolerance_mm)
    contact = np.bincount(plane, weights=face_areas[face], minlength=len(plane_normals))
    centre = centre_of_mass(vertices, faces)
    hull_points = hull.points[hull.vertices]
    tipping = np.array([tipping_angle_deg(hull_points, down, centre, plane_tolerance_mm) for down in plane_normals])
    stable = np.flatnonzero(tipping > 0.0)
    support, count = feet_support_mm2(vertices, faces, face_normals, planes[stable], plane_tolerance_mm)
    feet = np.zeros(len(plane_normals), dtype=np.int64)
    feet[stable] = np.where(support > contact[stable], count, 0)
    contact[stable] = np.maximum(contact[stable], support)
    return [
        Floor(down, float(area), float(tilt), int(n))
        for down, area, tilt, n in zip(plane_normals, contact, tipping, feet)
    ]


def ranked_floors(
    floors: list[Floor], mirrors: np.ndarray, min_tipping_deg: float, separation_deg: float, count: int
) -> list[Floor]:
    """Up to ``count`` floors at least ``separation_deg`` apart, best first: the stable ones that
    keep the most mirror planes (``mirrors``, unit normals) upright, by contact area, then (if none
    is stable) the most stable one."""
    stable = [f for f in floors if f.tipping_deg >= min_tipping_deg and f.contact_mm2 > 0.0]
    most = max((upright_mirrors(f, mirrors) for f in stable), default=0)
    stable = sorted(
        (f for f in stable if upright_mirrors(f, mirrors) == most), key=lambda f: (-f.contact_mm2, -f.tipping_deg)
    )
    cos_limit = np.cos(np.radians(separation_deg))
    picked: list[Floor] = []
    for floor in stable:
        if len(picked) == count:
            break
        if all(floor.down @ other.down < cos_limit for other in picked):
            picked.append(floor)
    return picked or [max(floors, key=lambda f: f.tipping_deg)]
