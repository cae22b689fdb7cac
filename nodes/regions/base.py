"""The base: the non-sensing region the object rests on, given the resting direction ``down``.

1. **Contact patches**: faces whose normal deviates less than ``angle_threshold_deg`` from ``down``
   and whose corners all lie within ``plane_tolerance_mm`` of the support plane (of the seed's
   height when a seed is given), in edge-connected patches.
2. **The patch**: the seed's, or the largest by area. With several contact patches of at least
   ``PATCH_SHARE`` of the largest's area (the feet of a figurine, the legs of an animal, the two
   ends of a lying spoon) the base is the largest patch alone; the other patches stay sensing, as
   part of the one sensing region (a foot cannot join the base without covering the leg between).
3. **Room for the Rx dipole**: the patch grows ring by ring (faces sharing a vertex with it) until
   some interior vertex is ``min_base_radius_mm`` from the nearest boundary vertex and two
   adjacent vertices are interior. A round or curved bottom gets a contact cap this way, a tiny
   flat foot a disc around it. A patch whose vertices lie on average more than ``CURVED_DEPTH`` of
   the plane tolerance above the plane is a round bottom's contact cap.
4. **Thin objects** (height along ``up`` below ``THIN_RATIO`` of the narrowest horizontal extent:
   plates, dishes, lids, a lying blade; or a sheet, :func:`is_sheet`, resting on a curved bottom or
   on several patches with at least ``SHEET_BOTTOM_SHARE`` of its surface on its bottom side: a lying
   spoon, whose bowl makes it tall): before step 3, the patch takes the whole bottom side, the faces
   connected to it whose normal is within ``THIN_SIDE_ANGLE_DEG`` of ``down``, so the dipole goes
   where the bottom side is widest, and it grows only for an interior edge if the bottom side is
   narrower than ``min_base_radius_mm`` (a band over the rim would cut the top in two); top and rim
   stay sensing. A thin or lying object's base (under ``LYING_RATIO`` as high as long) also takes the
   underside beside it that no fingertip reaches above the table (:func:`with_the_table_side`).
5. **Enclosed islands**: non-base components other than the largest join the base, so the rest is
   one piece: a foot ring takes the faces it encloses. Enclosed faces deeper than ``CAVITY_SHARE``
   of the object's height are a cavity opening downward.
6. **Room for the wiring** (:func:`grow_through_necks`, after the pose is chosen): every trace ends on
   the base's boundary, so a base behind a narrow neck (one foot of a figurine, an animal's leg, the
   foot of a penguin) lets only as many traces through as the neck's girth holds. The base grows by
   geodesic distance from it, level by level (``levels`` steps up to the farthest point), each level's
   base taking the islands it cuts off (a second foot, the other leg); the level kept maximises the
   free area the wiring reaches: each later level's area weighted by ``min(1, narrowest boundary on
   the way / wiring_room_mm)``. The base stays within ``max_share`` of the surface, and grows only
   for ``MIN_NECK_GAIN`` of it or more: where no neck narrows the way (a foot ring, a flat bottom
   with a long rim) it does not grow.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree

from ..geometry.thin_walls import wall_thickness
from .faces import FaceGraph
from .pose import plane_basis

PATCH_SHARE = 0.25
"""A contact patch with at least this share of the largest patch's area counts as another one."""
THIN_RATIO = 0.25
"""Height / narrowest horizontal extent below which an object is thin (a plate, a lid)."""
LYING_RATIO = 0.5
"""Height / longest horizontal extent below which an object lies (a spoon, an airplane, a bone, a boat on its keel)."""
SHEET_SHARE = 0.03
"""A sheet: three quarters of its surface lie on walls thinner than this share of its bounding-box diagonal
(measured: 0.5-2.9 % for a spoon, a blade, plates, a bowl, a vase, a tray, a tube; 3.5-3.9 % for CAD parts,
a plate with holes, pins, a turbine; 6.5 % and more for figures, animals and an airplane)."""
SHEET_BOTTOM_SHARE = 0.25
"""A sheet lies on its bottom side (a thin object) when that side holds at least this share of its surface
(about half when it lies flat; a sheet standing on an edge rests on a strip)."""
SHEET_SAMPLES = 400
"""Surface points whose wall thickness :func:`is_sheet` measures."""
THIN_SIDE_ANGLE_DEG = 60.0
"""On a thin object, the bottom side: faces whose normal is within this angle of ``down``."""
CAVITY_SHARE = 0.25
"""Enclosed faces deeper than this share of the object's height make a cavity opening downward."""
ISLAND_SHARE = 0.05
"""Enclosed faces worth this share of the base area make it a foot ring."""
CURVED_DEPTH = 0.25
"""A patch whose vertices lie on average deeper than this share of the plane tolerance is curved."""
MIN_NECK_GAIN = 0.01
"""The base grows through a neck only if the wiring then reaches at least this share more of the surface."""
MAX_GROWTH_RINGS = 200
"""Ring growth gives up after this many rings (the base is then what it reached)."""


@dataclasses.dataclass(frozen=True)
class Base:
    """The base faces and how they were found: ``kind`` is one of ``flat``, ``foot_ring``,
    ``patches``, ``round`` or ``thin``; ``patches`` the number of contact patches counted;
    ``cavity`` whether the base encloses a cavity opening downward (a bowl upside down);
    ``contacts`` the contact patches of any size (:func:`find_base`'s ``rank`` chooses among them)."""

    faces: np.ndarray
    kind: str
    patches: int
    cavity: bool
    contacts: int = 1  # contact patches on the support plane, of any size
    table_side: bool = False  # it took the underside beside it that no fingertip reaches (:func:`with_the_table_side`)


def contact_patches(
    vertices: np.ndarray,
    graph: FaceGraph,
    face_normals: np.ndarray,
    down: np.ndarray,
    angle_threshold_deg: float,
    tolerance_mm: float,
    seed: int | None,
) -> np.ndarray:
    """Patch label per face (-1 off the support plane), step 1 of the module docstring."""
    height = vertices @ down
    reference = height[graph.faces[seed]].mean() if seed is not None else height.max()
    near = (np.abs(reference - height[graph.faces]) <= tolerance_mm).all(axis=1)
    candidates = near & (face_normals @ down >= np.cos(np.radians(angle_threshold_deg)))
    if seed is not None:
        candidates[seed] = True
    return graph.components(candidates)


def inradius_mm(vertices: np.ndarray, graph: FaceGraph, base: np.ndarray) -> float:
    """Largest distance (mm) from an interior base vertex to the nearest base boundary vertex."""
    inside, outside = graph.vertex_masks(base)
    interior, boundary = np.flatnonzero(inside & ~outside), np.flatnonzero(inside & outside)
    if len(interior) == 0 or len(boundary) == 0:
        return 0.0 if len(interior) == 0 else np.inf
    return float(cKDTree(vertices[boundary]).query(vertices[interior])[0].max())


def grow_for_dipole(vertices: np.ndarray, graph: FaceGraph, base: np.ndarray, radius_mm: float) -> np.ndarray:
    """Step 3: ``base`` grown ring by ring until it gives the dipole room."""
    for _ in range(MAX_GROWTH_RINGS):
        if graph.has_interior_edge(base) and inradius_mm(vertices, graph, base) >= radius_mm:
            break
        grown = graph.ring(base)
        if grown.all():
            break
        base = grown
    return base


def horizontal_extents(vertices: np.ndarray, down: np.ndarray) -> tuple[float, float]:
    """``(longest, narrowest)`` extent (mm) across ``down``: along the principal axes of the vertices
    projected onto the horizontal plane."""
    flat = vertices @ plane_basis(down)
    flat = flat - flat.mean(axis=0)
    axes = np.linalg.svd(flat, full_matrices=False)[2]
    return float(np.ptp(flat @ axes[0])), float(np.ptp(flat @ axes[-1]))


def is_thin(vertices: np.ndarray, down: np.ndarray) -> bool:
    """Whether the height along ``down`` is below ``THIN_RATIO`` of the narrowest horizontal extent."""
    return float(np.ptp(vertices @ down)) < THIN_RATIO * horizontal_extents(vertices, down)[1]


def is_lying(vertices: np.ndarray, down: np.ndarray) -> bool:
    """Whether the height along ``down`` is below ``LYING_RATIO`` of the longest horizontal extent."""
    return float(np.ptp(vertices @ down)) < LYING_RATIO * horizontal_extents(vertices, down)[0]


def is_sheet(vertices: np.ndarray, faces: np.ndarray, face_normals: np.ndarray, areas: np.ndarray) -> bool:
    """Whether the object is a sheet (a spoon, a plate, a lid, a leaf; not a solid with thin limbs):
    three quarters of :func:`wall_thickness` below ``SHEET_SHARE`` of the bounding-box diagonal."""
    limit = SHEET_SHARE * float(np.linalg.norm(np.ptp(vertices, axis=0)))
    return bool(np.mean(wall_thickness(vertices, faces, face_normals, areas, limit, SHEET_SAMPLES) < limit) >= 0.75)


def absorb_islands(graph: FaceGraph, base: np.ndarray, areas: np.ndarray) -> np.ndarray:
    """Base plus every non-base component except the largest (by area), so the rest is one piece."""
    labels = graph.components(~base)
    rest = labels >= 0
    if not rest.any():
        return base
    largest = int(np.argmax(np.bincount(labels[rest], weights=areas[rest])))
    return base | (rest & (labels != largest))


def with_the_table_side(graph: FaceGraph, base: Base, below_reach: np.ndarray, areas: np.ndarray, lying: bool) -> Base:
    """A thin or ``lying`` object's base with the faces joined to it that a fingertip cannot reach above the
    table (``below_reach``: a rounded underside, a sword's grip) and the islands they cut off. Others unchanged."""
    if base.kind != "thin" and not lying:
        return base
    labels = graph.components(below_reach | base.faces)
    joined = absorb_islands(graph, base.faces | np.isin(labels, np.unique(labels[base.faces])), areas)
    return dataclasses.replace(base, faces=joined, table_side=bool((joined & ~base.faces).any()))


def find_base(
    vertices: np.ndarray,
    graph: FaceGraph,
    face_normals: np.ndarray,
    areas: np.ndarray,
    down: np.ndarray,
    params,
    seed: int | None,
    sheet: bool,
    rank: int = 0,
) -> Base:
    """The base for resting direction ``down`` (module docstring) on the seed's contact patch, else on
    the ``rank``-th largest; ``params`` is a ``RegionParams``, ``sheet`` :func:`is_sheet` of the object."""
    labels = contact_patches(
        vertices, graph, face_normals, down, params.angle_threshold_deg, params.plane_tolerance_mm, seed
    )
    on_plane = labels >= 0
    if not on_plane.any():  # no face is flat enough: start from the faces at the lowest vertex
        lowest = int(np.argmax(vertices @ down))
        patch = (graph.faces == lowest).any(axis=1)
        patch_area = np.zeros(1)
    else:
        patch_area = np.bincount(labels[on_plane], weights=areas[on_plane])
        chosen = labels[seed] if seed is not None else int(np.argsort(-patch_area, kind="stable")[rank])
        patch = labels == chosen
    patches = int(np.count_nonzero(patch_area >= PATCH_SHARE * patch_area.max())) if patch_area.max() > 0 else 1
    height = vertices @ down
    depth = height.max() - height[np.unique(graph.faces[patch])]
    curved = depth.mean() > CURVED_DEPTH * params.plane_tolerance_mm
    thin = is_thin(vertices, down)
    if thin or (sheet and (curved or patches > 1)):
        side = face_normals @ down >= np.cos(np.radians(THIN_SIDE_ANGLE_DEG))
        side_labels = graph.components(side | patch)
        bottom = patch | np.isin(side_labels, np.unique(side_labels[patch]))
        if thin or areas[bottom].sum() >= SHEET_BOTTOM_SHARE * areas.sum():
            patch, thin = bottom, True
    radius = params.min_base_radius_mm
    if thin:  # a band over the rim would cut the top in two: the bottom side's own room is enough
        radius = min(radius, inradius_mm(vertices, graph, patch))
    base = grow_for_dipole(vertices, graph, patch, radius)
    islands = absorb_islands(graph, base, areas) & ~base
    cavity = bool(islands.any()) and height.max() - height[graph.faces[islands]].min() > CAVITY_SHARE * np.ptp(height)
    ring = float(areas[islands].sum()) > ISLAND_SHARE * float(areas[base].sum())
    base = base | islands
    kind = "thin" if thin else "foot_ring" if ring else "round" if curved else "patches" if patches > 1 else "flat"
    contacts = int(np.count_nonzero(patch_area > 0))
    return Base(faces=base, kind=kind, patches=patches, cavity=cavity, contacts=max(contacts, 1))


def boundary_length_mm(vertices: np.ndarray, graph: FaceGraph, base: np.ndarray) -> float:
    """Length (mm) of the edges between ``base`` and the rest."""
    edge = graph.halfedges[graph.halfedges_between(base, ~base)]
    return float(np.linalg.norm(vertices[edge[:, 0]] - vertices[edge[:, 1]], axis=1).sum())


def grow_through_necks(
    vertices: np.ndarray, graph: FaceGraph, base: np.ndarray, areas: np.ndarray, from_base: np.ndarray,
    wiring_room_mm: float, max_share: float, levels: int = 60,
) -> tuple[np.ndarray, float, float]:
    """Step 6: ``(base, its boundary length mm, free area reached mm^2)``, the base grown through the
    narrow necks next to it; ``from_base`` is the geodesic distance (mm) per vertex from ``base``."""
    face_distance = from_base[graph.faces].mean(axis=1)
    levels_mm = np.linspace(0.0, float(from_base.max()), levels, endpoint=False)
    grown = [base] + [absorb_islands(graph, base | (face_distance <= level), areas) for level in levels_mm[1:]]
    lengths = np.array([boundary_length_mm(vertices, graph, g) for g in grown])
    grown_area = np.array([areas[g].sum() for g in grown])
    gained = np.diff(np.append(grown_area, areas.sum()))  # area that leaves the free side after each level
    reach = np.minimum(1.0, lengths / wiring_room_mm)
    scores = np.array([float(gained[k:] @ np.minimum.accumulate(reach[k:])) for k in range(levels)])
    scores[1:][grown_area[1:] > max_share * areas.sum()] = -np.inf
    best = int(np.argmax(scores))
    if scores[best] < scores[0] + MIN_NECK_GAIN * areas.sum():
        best = 0
    return grown[best], float(lengths[best]), float(scores[best])
