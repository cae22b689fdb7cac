"""``regions.detect``: the resting pose, the base (non-sensing) region, the two exclusion regions
and the anchors of the singularities (paper section 5).

Conventions: ``down`` is the resting direction (unit vector pointing from the object into the
support plane), ``up = -down``. The height below the object of a vertex along ``down`` is
``s = v . down``; the support plane touches the vertex with the largest ``s``.

1. Resting direction (:mod:`.pose`): with ``up_axis`` given, ``down = -up_axis``; with only a seed,
   ``down`` is the seed face's outward normal; otherwise the pose a person would set the object
   down in, from a quasi-static analysis of its convex hull.
2. Base (:mod:`.base`): the contact patch on the support plane (the seed's, or the largest), grown
   until it gives the Rx dipole room, or a thin object's whole bottom side; a thin or lying object's
   with the underside beside it no fingertip reaches above the table (:func:`.base.with_the_table_side`);
   plus the faces it encloses, so the rest is one piece; then grown through a narrow neck next to it
   (a leg above a foot) so every trace has room to reach it, or, where a neck blocks the wiring (a
   contact at the end of a thin handle), started on another contact patch (:func:`room_for_wiring`).

Then, with heat-method geodesic distances (:mod:`..geometry.vertex_distance`):

* ``base_centre``: the interior base vertex farthest from the base boundary; ``base_dipole`` adds
  its interior neighbour farthest from the boundary.
* ``exclusion_base``: faces grown outward from the base, across edges, while their mean vertex
  distance from the base is below ``exclusion_base_mm`` and their normal deviates from ``down`` by
  less than ``exclusion_base_angle_deg`` (growth stops at whichever threshold is reached first);
  then also every piece of the rest that no trace can reach from the Tx pole
  (:func:`unreachable_faces`: a second foot, legs that the base and its exclusion cut off). The run
  note gives their area when it matters.
* ``far_vertex`` (the Tx pole): with ``tx_pole="far"`` (the paper's) the vertex outside base and
  first exclusion farthest from the base before its growth for the wiring (a grown base leaves a
  second foot beside it, which is no pole), on a thin object, whose top is everywhere close to the
  base's rim, farthest from the base centre, so the Tx lines run the object's length; of near ties
  a much higher one (:func:`.poles.farthest_pole`); with ``tx_pole="top"`` the highest peak of that
  distance (:func:`.poles.top_pole`: a standing figure's head, where the far pole may be a stretched
  hand); with ``tx_pole="centre"`` the geodesic centre of that free region: the free vertex whose largest
  distance to the region's ``CENTRE_SAMPLES`` farthest-point samples is smallest, so Tx lines fan
  out to every side of the object;
  ``exclusion_far``: faces with mean vertex distance from it below ``exclusion_far_mm`` plus the
  faces around it, plus the faces beyond a finger's reach joined to those but not to the base
  (:mod:`.touch`: the inside of a vessel, when the pole lies at its bottom).
* ``touch_faces``: the sensing faces a finger can touch (``regions.touchable``) with the table below.
"""
from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np
import trimesh
from pydantic import Field, field_validator, model_validator

from ...graph.errors import UserError
from ...graph.node import NodeParams, node
from ..data.types import Mesh, SurfaceRegions, TouchField
from ..geometry.triangles import corners, normals
from ..geometry.vertex_distance import VertexDistances
from .base import MIN_NECK_GAIN, Base, find_base, grow_through_necks, is_lying, is_sheet, with_the_table_side
from .faces import FaceGraph
from .poles import tx_pole
from .pose import at_pose_size, candidate_floors, centre_of_mass, mirror_planes, ranked_floors, tipping_angle_deg
from .touch import clear_of_table, pocket_of, touch_summary, touchable_faces_of

CANDIDATE_POSES = 6
"""Automatic pose: how many of the best floors (at least angle_threshold_deg apart) are tried."""

AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}

KIND_WORDS = {
    "flat": "a flat bottom",
    "foot_ring": "a foot ring and the faces it encloses",
    "patches": "{which} of {patches} contact patches (the others stay sensing)",
    "round": "a contact cap on its curved bottom",
    "thin": "the bottom side of a thin object",
}


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
    """Resting pose and base overrides, base shape and exclusion radii (lengths mm, angles degrees)."""

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
    min_base_radius_mm: float = Field(
        5.0, gt=0, description="the base grows until its centre is this far from its boundary (dipole room)"
    )
    min_tipping_deg: float = Field(
        2.0, ge=0, lt=90, description="automatic pose: smallest tilt that must not topple the object"
    )
    exclusion_base_mm: float = Field(10.0, ge=0, description="first exclusion: geodesic width from base")
    exclusion_base_angle_deg: float = Field(
        60.0, gt=0, le=180, description="first exclusion: max normal deviation from resting direction"
    )
    exclusion_far_mm: float = Field(10.0, ge=0, description="second exclusion: geodesic radius at far point")
    tx_pole: Literal["far", "top", "centre"] = Field(
        "far", description="the Tx pole: the point farthest from the base, the highest peak of that distance, or the "
        "free region's geodesic centre"
    )
    direction_cells: int = Field(2000, ge=20, description="automatic pose: direction cells (one hull plane each)")
    wiring_room_mm: float = Field(
        99.0, ge=0, description="the base grows through a narrow neck (a leg, an ankle) toward this boundary "
        "length, room for every trace to reach it: 33 channels x 3 mm; 0 keeps the contact base"
    )
    max_base_share: float = Field(0.4, gt=0, le=1, description="the neck growth's largest base, share of the surface")

    @field_validator("up_axis")
    @classmethod
    def _valid_axis(cls, value: str | tuple[float, float, float] | None) -> str | tuple[float, float, float] | None:
        if value is not None:
            parse_axis(value)
        return value

    @model_validator(mode="after")
    def _one_seed(self) -> "RegionParams":
        if self.seed_face is not None and self.seed_point is not None:
            raise ValueError("seed_face and seed_point are both set: set one of them, not both")
        return self


def nearest_face(vertices: np.ndarray, faces: np.ndarray, point: np.ndarray) -> int:
    """Index of the face closest to ``point`` (mm)."""
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    return int(trimesh.proximity.closest_point(mesh, point[None, :])[2][0])


def automatic_pose(
    vertices: np.ndarray, graph: FaceGraph, face_normals: np.ndarray, areas: np.ndarray, params: RegionParams,
    sheet: bool,
) -> tuple[Base, np.ndarray, str]:
    """``(base, down, why)`` of the pose a person would set the object down in (:mod:`.pose`):
    the best ranked floor whose base does not enclose a downward cavity (else the best)."""
    shape = at_pose_size(vertices)
    floors = candidate_floors(
        shape, graph.faces, params.direction_cells, params.angle_threshold_deg, params.plane_tolerance_mm
    )
    mirrors = mirror_planes(shape, graph.faces)
    ranked = ranked_floors(floors, mirrors, params.min_tipping_deg, params.angle_threshold_deg, CANDIDATE_POSES)
    stable = sum(f.tipping_deg >= params.min_tipping_deg for f in floors)
    why = f"the stable pose with the most flat contact of {stable} stable hull planes"
    if len(mirrors):
        why += f", keeping the most of its {len(mirrors)} mirror plane(s) upright"
    first = None
    for rank, floor in enumerate(ranked):
        base = find_base(vertices, graph, face_normals, areas, floor.down, params, None, sheet)
        if not base.cavity:
            skipped = f", {rank} upside-down pose(s) passed over" if rank else ""
            if floor.feet and base.kind in ("flat", "round"):  # one foot is the base, the others sense
                base = dataclasses.replace(base, kind="patches", patches=floor.feet)
            feet = f", standing on {floor.feet} feet (the polygon they span is its contact)" if floor.feet else ""
            return base, floor.down, why + feet + skipped
        first = first or (base, floor.down)
    return first[0], first[1], why + " (every candidate encloses a cavity)"


def resting_base(
    vertices: np.ndarray, graph: FaceGraph, face_normals: np.ndarray, areas: np.ndarray, params: RegionParams,
    sheet: bool,
) -> tuple[Base, np.ndarray, float, str]:
    """``(base, down, tipping angle deg, why this pose)``: steps 1 and 2 of the module docstring; ``sheet``
    is :func:`.base.is_sheet` of the object."""
    seed = params.seed_face
    if seed is not None and seed >= len(graph.faces):
        raise UserError(f"seed_face {seed} does not exist: the mesh has {len(graph.faces)} faces")
    if params.seed_point is not None:
        seed = nearest_face(vertices, graph.faces, np.asarray(params.seed_point, dtype=np.float64))
    if params.up_axis is None and seed is None:
        base, down, why = automatic_pose(vertices, graph, face_normals, areas, params, sheet)
    else:
        if params.up_axis is not None:
            down, why = -parse_axis(params.up_axis), f"up_axis {params.up_axis} given"
        else:
            down, why = face_normals[seed].copy(), f"seed face {seed} given"
        base = find_base(vertices, graph, face_normals, areas, down, params, seed, sheet)
    shape = at_pose_size(vertices)
    tipping = tipping_angle_deg(shape, down, centre_of_mass(shape, graph.faces), params.plane_tolerance_mm)
    return base, down, tipping, why


def base_distance(solver: VertexDistances, graph: FaceGraph, base: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(from boundary, from base)`` per vertex (mm): the heat-method distance from the base's boundary
    vertices, and the same set to 0 on the base (many-source distances are smoothed, so the boundary is
    the better source set)."""
    on_base, off_base = graph.vertex_masks(base)
    from_boundary = solver.compute_distance_multisource(np.flatnonzero(on_base & off_base))
    return from_boundary, np.where(on_base, 0.0, np.maximum(from_boundary, 0.0))


WIRING_CONTACTS = 4
"""Room for the wiring: how many of the largest contact patches are tried as the base's start."""
WIRING_REACH = 0.8
"""The other contact patches are tried only if, from the largest, the wiring reaches less than this
share of the free surface (a neck it cannot grow through)."""


def room_for_wiring(
    vertices: np.ndarray, graph: FaceGraph, face_normals: np.ndarray, areas: np.ndarray, down: np.ndarray,
    base: Base, from_base: np.ndarray, solver, params: RegionParams, seeded: bool, sheet: bool,
) -> tuple[Base, np.ndarray, float | None, int]:
    """``(base, distance mm from its contact patch, rim mm or None if it did not grow, the patch's rank
    by size)``: the base grown through the necks next to it (:func:`.base.grow_through_necks`), started
    on the largest contact patch or, if a neck blocks the wiring there (``WIRING_REACH``), on whichever
    of the ``WIRING_CONTACTS`` largest lets it reach the most (the seed's if one is given; a thin
    object's whole bottom side; a base that took the table side, which joins the contacts beneath)."""
    ranks = range(1 if seeded or base.kind == "thin" or base.table_side else min(base.contacts, WIRING_CONTACTS))
    best = None
    for rank in ranks:
        start = base if rank == 0 else find_base(vertices, graph, face_normals, areas, down, params, None, sheet, rank)
        if rank and (start.cavity or start.faces.all()):
            continue
        distance = from_base if rank == 0 else base_distance(solver, graph, start.faces)[1]
        grown, rim, reached = grow_through_necks(
            vertices, graph, start.faces, areas, distance, params.wiring_room_mm, params.max_base_share
        )
        if best is None or reached > best[3] + MIN_NECK_GAIN * areas.sum():
            best = (start, grown, rim, reached, distance, rank)
        if rank == 0 and reached >= WIRING_REACH * areas[~start.faces].sum():
            break  # the largest patch leaves the wiring room enough: the others are not tried
    start, grown, rim, _, distance, rank = best
    grew = bool(grown.sum() > start.faces.sum())
    return dataclasses.replace(start, faces=grown), distance, rim if grew else None, rank


def reason_text(base: Base, share: float, tipping: float, why: str, rim_mm: float | None, rank: int) -> str:
    """The pose note's sentence: the base, its share of the surface, the stability, why; ``rank`` is its
    contact patch's by size (0: the largest)."""
    words = KIND_WORDS[base.kind].format(patches=base.patches, which="one" if rank else "the largest")
    if rank:
        words += f" (contact patch {rank + 1} by size: the wiring reaches more)"
    if base.table_side:
        words += " and the underside beside it that no fingertip reaches above the table"
    grown = f", grown until its rim has room for the wiring ({rim_mm:.0f} mm)" if rim_mm is not None else ""
    return (
        f"rests on {words}{grown} ({100 * share:.1f}% of the surface), "
        f"tips over at {tipping:.0f} deg; {why}"
    )


def grow_exclusion(
    graph: FaceGraph,
    base: np.ndarray,
    face_distance: np.ndarray,
    face_normals: np.ndarray,
    down: np.ndarray,
    params: RegionParams,
) -> np.ndarray:
    """First exclusion region: faces reachable from the base within both thresholds."""
    within = (face_distance < params.exclusion_base_mm) & (
        face_normals @ down > np.cos(np.radians(params.exclusion_base_angle_deg))
    )
    labels = graph.components(base | within)
    return np.isin(labels, np.unique(labels[base])) & ~base


def unreachable_faces(graph: FaceGraph, candidate: np.ndarray, blocked: np.ndarray, pole: np.ndarray) -> np.ndarray:
    """Faces of ``candidate`` (the sensing region before this check) that no trace from the Tx pole
    (around the faces ``pole``) reaches: the edge-connected pieces that share no edge with ``pole``
    once slivers, faces whose three corners touch ``blocked`` faces, are taken out (no trace passes a
    sliver without touching the base); slivers left beside the pole's piece stay."""
    touches_blocked, _ = graph.vertex_masks(blocked)
    sliver = candidate & touches_blocked[graph.faces].all(axis=1)
    labels = graph.components((candidate & ~sliver) | pole)
    reached = np.isin(labels, np.unique(labels[pole]))
    labels = graph.components(reached | sliver)
    return candidate & ~np.isin(labels, np.unique(labels[pole]))


def dipole(graph: FaceGraph, base: np.ndarray, from_boundary: np.ndarray) -> np.ndarray:
    """``(centre, partner)``: the interior base vertex farthest from the base boundary and its
    interior neighbour farthest from it."""
    on_base, off_base = graph.vertex_masks(base)
    interior = np.flatnonzero(on_base & ~off_base)
    if len(interior) == 0:
        raise UserError(
            f"the base ({int(base.sum())} faces) has no interior vertex: raise min_base_radius_mm or "
            "remesh finer (raise vertices)"
        )
    centre = int(interior[np.argmax(from_boundary[interior])])
    neighbours = graph.halfedges[graph.halfedges[:, 0] == centre, 1]
    neighbours = neighbours[on_base[neighbours] & ~off_base[neighbours]]
    if len(neighbours) == 0:
        raise UserError("the base is too narrow for the Rx dipole: raise min_base_radius_mm or remesh finer")
    return np.array([centre, int(neighbours[np.argmax(from_boundary[neighbours])])], dtype=np.int64)


CUT_OFF_NOTE_SHARE = 0.005
"""The run note names the faces no trace reaches once they are this share of the surface or more."""


def pose_note(regions: SurfaceRegions) -> str:
    """The run summary's line: the resting pose, its kind and why it was chosen."""
    return f"resting pose {regions.pose_kind}: {regions.pose_reason}"


@node("regions.detect", params=RegionParams, inputs=("mesh", "touchable"), outputs=("regions",), note=pose_note)
def detect_regions(params: RegionParams, mesh: Mesh, touchable: TouchField) -> SurfaceRegions:
    """Find the resting pose and base, the two exclusion regions, the singularity anchors and the
    touchable sensing faces."""
    vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.int64)
    graph = FaceGraph(faces, len(vertices))
    if (graph.opposite < 0).any():
        raise UserError(f"regions.detect needs a closed mesh, {int((graph.opposite < 0).sum())} edges are open: "
                        "put mesh.check_topology before regions.detect")
    face_normals, areas = normals(corners(vertices, faces))
    sheet = is_sheet(vertices, faces, face_normals, areas)
    base, down, tipping, why = resting_base(vertices, graph, face_normals, areas, params, sheet)
    above_table = clear_of_table(vertices, faces, face_normals, down, touchable.finger_radius_mm)
    base = with_the_table_side(graph, base, ~above_table, areas, is_lying(vertices, down))
    if base.faces.all():
        raise UserError("the base covers the whole surface: lower min_base_radius_mm or angle_threshold_deg")
    solver = VertexDistances(vertices, faces)
    from_boundary, from_base = base_distance(solver, graph, base.faces)
    from_contact, rim_mm, rank = from_base, None, 0
    if params.wiring_room_mm > 0:
        seeded = params.seed_face is not None or params.seed_point is not None
        contact = base.faces
        base, from_contact, rim_mm, rank = room_for_wiring(
            vertices, graph, face_normals, areas, down, base, from_base, solver, params, seeded, sheet
        )
        if not np.array_equal(base.faces, contact):
            from_boundary, from_base = base_distance(solver, graph, base.faces)
    share = float(areas[base.faces].sum() / areas.sum())
    reason = reason_text(base, share, tipping, why, rim_mm, rank)
    anchors = dipole(graph, base.faces, from_boundary)
    exclusion_base = grow_exclusion(graph, base.faces, from_base[faces].mean(axis=1), face_normals, down, params)
    blocked = base.faces | exclusion_base
    touches_blocked, _ = graph.vertex_masks(blocked)
    free = np.flatnonzero(~touches_blocked)
    if len(free) == 0:
        raise UserError("base and first exclusion cover the whole surface: lower exclusion_base_mm")
    from_centre = solver.compute_distance(int(anchors[0]))
    reach = from_centre if base.kind == "thin" else from_contact
    far_vertex, from_far = tx_pole(params.tx_pole, graph, reach, free, vertices @ -down, solver)
    exclusion_far = (from_far[faces].mean(axis=1) < params.exclusion_far_mm) | (faces == far_vertex).any(axis=1)
    exclusion_far &= ~blocked
    within_reach = touchable_faces_of(touchable, vertices, faces)
    exclusion_far |= pocket_of(graph, exclusion_far, ~within_reach & ~blocked, blocked)
    touch = within_reach & above_table
    cut_off = unreachable_faces(graph, ~(blocked | exclusion_far), blocked, exclusion_far)
    exclusion_base |= cut_off
    blocked |= cut_off
    sensing = ~(blocked | exclusion_far)
    if not sensing.any():
        raise UserError("no sensing surface is left: lower exclusion_base_mm or exclusion_far_mm")
    cut_share = float(areas[cut_off].sum() / areas.sum())
    if cut_share >= CUT_OFF_NOTE_SHARE:
        reason += f"; {100 * cut_share:.1f}% of the surface is cut off from the Tx pole by the base and is not sensing"
    return SurfaceRegions(
        base_faces=base.faces,
        exclusion_base=exclusion_base,
        exclusion_far=exclusion_far,
        sensing_faces=sensing,
        touch_faces=sensing & touch,
        base_centre=int(anchors[0]),
        base_dipole=anchors,
        far_vertex=far_vertex,
        up=-down,
        base_boundary_edges=graph.halfedges[graph.halfedges_between(sensing, blocked)].astype(np.int64),
        base_distance_mm=np.asarray(from_base, dtype=np.float64),
        far_distance_mm=np.asarray(from_far, dtype=np.float64),
        centre_distance_mm=np.asarray(from_centre, dtype=np.float64),
        dipole_distance_mm=np.asarray(solver.compute_distance_multisource(anchors.tolist()), dtype=np.float64),
        pose_kind=base.kind,
        pose_reason=reason,
        tipping_angle_deg=float(tipping),
        base_area_fraction=share,
        sensing_area_fraction=float(areas[sensing].sum() / areas.sum()),
        tx_pole=params.tx_pole,
        touch=touch_summary(touchable, float(areas[touch].sum() / areas.sum())),
    )
