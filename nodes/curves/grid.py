"""``curves.trace_grid``, ``curves.grid_layers``: a Tx and an Rx family that cross like the grid of a
touch panel, with no pole.

The surface where curves may run, everything but the base and its exclusion, is a disc on a genus-0
object, and its rim is the base's. The grid's lines are the level sets of two functions on the disc,
its coordinates, ``across`` (its level sets run across the disc's principal axis) and ``along``
(they run along it), each from 0 to 1, in one of two kinds (``coordinates``):

* ``geodesic``: two ends and two sides split the rim as a rectangle's corners would: each end is the
  ``end_share`` of the rim's length around the rim point farthest along the principal axis
  (area-weighted, one end at either extreme), the sides are what lies between. Each coordinate is the
  share of the way from one arc to the opposite one, ``d0 / (d0 + d1)`` with ``d0``, ``d1`` the
  geodesic distances within the disc (heat method) from the two arcs: ``across`` is 0 on one end and
  1 on the other, ``along`` 0 on one side and 1 on the other. Evenly spread levels are evenly spread
  on the surface along the shortest way between the two arcs (where ``d0 + d1`` is constant the share
  grows with ``d0``), where the disc narrows as where it is wide (the coordinates of a conformal map
  crowd their lines where it narrows). The lines follow a slender disc that bends (a curved blade).
* ``plan``: the position in the table's plane, as the object is seen from above in its resting pose:
  ``across`` along the horizontal principal axis of the disc, ``along`` across it, each scaled to
  [0, 1] over the disc. On a top seen once from above (an airplane's, a starfish's: a top whose arms
  point several ways, which no two rim arcs span) a level set of each meets one of the other at most
  once wherever the two lie on the disc, and evenly spread levels are evenly spread lines in plan;
  where the disc folds under itself (a round object's sides) a pair may meet twice, which phase 1
  never selects together.

Level sets of one function never meet, and on a slender or flat object (a sword, a plate's top, a
spoon's bowl, a boat's deck) a level set of each meets one of the other once: a touch panel's grid,
with no pole where the lines of one layer crowd. A few more levels pass through the points farthest
from the lines before them; every curve has an end on the rim, both where it can, and runs the way
the other function grows. A level set that the disc's boundary breaks into pieces (the other arms of
a plan's top, holes where the base encloses a cut-off region) keeps each piece with an end on the
rim, starting there; each piece is a candidate of its own. ``curves.trace_grid`` computes both
families once; ``curves.grid_layers`` (one branch per choice) makes one of them the Tx lines, walked
backwards so that they end on the rim, and the other the Rx lines, which start on it, as
``fab.unfold`` expects. The family is ``grid`` with geodesic coordinates, ``grid_plan`` with plan
ones. Units: mm.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Literal

import numpy as np
from pydantic import Field

from ...graph.errors import UserError
from ...graph.node import NodeParams, node
from ..data.types import CurveEnd, CurveSet, Mesh
from ..geometry.mesh_tables import MeshTables, build_tables
from .assembly import polyline_rows, reversed_rows, reversed_walk
from .ring_levels import LevelSets, reseeded_levels
from .rings import pack
from .rx_seeding import chain_walks

MIN_LENGTH_MM = 4.0
"""A level set's piece shorter than this is no candidate: it cannot hold a pad (2 mm radius by default). A line
across a strip a little wider than that (a blade lying flat) holds one crossing, which is what covers it."""


class TraceGridParams(NodeParams):
    n_across: int = Field(40, ge=1, description="evenly spread lines across the principal axis (level sets of 'across')")
    n_along: int = Field(24, ge=1, description="evenly spread lines along the principal axis (level sets of 'along')")
    n_reseeded: int = Field(8, ge=0, description="more lines of each family, each through the point farthest from the lines before it")
    end_share: float = Field(0.1, gt=0.0, lt=0.5, description="geodesic coordinates: each end's share of the rim's length")
    coordinates: Literal["geodesic", "plan"] = Field(
        "geodesic", description="the grid's coordinates: shares of geodesic distance between rim arcs, or the position "
        "in the table's plane seen from above")


class GridLayersParams(NodeParams):
    tx: Literal["across", "along"] = Field("across", description="which family drives: the lines across the disc's principal axis or along it")


def boundary_loops(tables: MeshTables, domain: np.ndarray) -> list[np.ndarray]:
    """The closed vertex loops bounding the faces ``domain`` (m,) bool, each with the domain on its
    left (counter-clockwise seen from outside), longest first (mm). Where the boundary passes a vertex
    twice (two loops touching there), one of the two ways on is followed."""
    f, k = np.divmod(np.arange(tables.faces.size), 3)  # every halfedge (f, k): corner k -> corner k + 1
    e = tables.face_edges[f, k]
    other = np.where(tables.edge_faces[e, 0] == f, tables.edge_faces[e, 1], tables.edge_faces[e, 0])
    rim = domain[f] & ~domain[other]
    start, end = tables.faces[f[rim], k[rim]], tables.faces[f[rim], (k[rim] + 1) % 3]
    following = dict(zip(start.tolist(), end.tolist()))
    loops, seen = [], set()
    for v0 in start.tolist():
        if v0 in seen:
            continue
        loop, v = [], v0
        while v not in seen and v in following:
            seen.add(v)
            loop.append(v)
            v = following[v]
        loops.append(np.asarray(loop, dtype=np.int64))
    length = [np.linalg.norm(np.diff(tables.vertices[np.r_[loop, loop[:1]]], axis=0), axis=1).sum() for loop in loops]
    return [loops[i] for i in np.argsort(length)[::-1]]


def rim_arcs(tables: MeshTables, domain: np.ndarray, rim: np.ndarray, end_share: float) -> tuple[np.ndarray, ...]:
    """The rim's ``(end_a, end_b, side_c, side_d)`` vertex arcs: the ends centred on the rim vertices
    lowest and highest along the domain's principal axis, each ``end_share`` of the rim's length;
    ``side_c`` follows ``end_a`` along the rim (domain on the left), ``side_d`` follows ``end_b``."""
    centre, axis = principal_axis(tables, domain)
    step = np.linalg.norm(tables.vertices[np.roll(rim, -1)] - tables.vertices[rim], axis=1)
    arc = np.r_[0.0, np.cumsum(step)[:-1]]
    length = step.sum()
    x = (tables.vertices[rim] - centre) @ axis
    a = int(np.argmin(x))
    from_a = np.mod(arc - arc[a], length)  # mm along the rim from end a's middle
    apart = np.minimum(from_a, length - from_a) >= end_share * length  # where end b would not overlap end a
    b = int(np.flatnonzero(apart)[np.argmax(x[apart])])
    from_b = np.mod(arc - arc[b], length)
    half = 0.5 * end_share * length
    end_a = np.minimum(from_a, length - from_a) <= half
    end_b = np.minimum(from_b, length - from_b) <= half
    side_c = ~end_a & ~end_b & (from_a < from_a[b])
    side_d = ~end_a & ~end_b & ~side_c
    return rim[end_a], rim[end_b], rim[side_c], rim[side_d]


def principal_axis(
    tables: MeshTables, domain: np.ndarray, normal: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``(centre, axis)``: the area-weighted centre (mm) of the faces ``domain``'s centroids and the unit
    axis along which they spread most, both within the plane perpendicular to the unit ``normal`` when
    one is given."""
    centroids = tables.vertices[tables.faces[domain]].mean(axis=1)
    if normal is not None:
        centroids = centroids - np.outer(centroids @ normal, normal)
    weights = tables.areas[domain] / tables.areas[domain].sum()
    centre = weights @ centroids
    spread = (centroids - centre).T @ ((centroids - centre) * weights[:, None])
    return centre, np.linalg.eigh(spread)[1][:, -1]


def plan_coordinates(tables: MeshTables, domain: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(across, along)`` per vertex: the position along the horizontal principal axis of the faces
    ``domain`` (``up``: the unit vertical) and across it, seen from above, each scaled to [0, 1] over the
    domain's vertices; NaN off the domain."""
    _, axis = principal_axis(tables, domain, up)
    used = np.unique(tables.faces[domain])
    coordinates = []
    for direction in (axis, np.cross(up, axis)):
        x = tables.vertices[used] @ direction
        u = np.full(len(tables.vertices), np.nan)
        u[used] = (x - x.min()) / max(float(np.ptp(x)), 1e-12)
        coordinates.append(u)
    return coordinates[0], coordinates[1]


def disc_distances(tables: MeshTables, domain: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """A function of vertex ids: the ``(n,)`` geodesic distances (heat method, mm) from them within the
    faces ``domain`` alone; NaN off the domain. One factorisation serves every call."""
    import potpourri3d as pp3d  # heavy: imported when used, not on node discovery

    used, local = np.unique(tables.faces[domain], return_inverse=True)
    index = np.full(len(tables.vertices), -1, dtype=np.int64)
    index[used] = np.arange(len(used))
    solver = pp3d.MeshHeatMethodDistanceSolver(tables.vertices[used], local.reshape(-1, 3))

    def distances(sources: np.ndarray) -> np.ndarray:
        d = np.full(len(tables.vertices), np.nan)
        d[used] = np.maximum(solver.compute_distance_multisource(index[sources]), 0.0)
        d[sources] = 0.0
        return d

    return distances


def distance_share(distances: Callable[[np.ndarray], np.ndarray], zero: np.ndarray, one: np.ndarray) -> np.ndarray:
    """``(n,)`` ``d0 / (d0 + d1)`` of the :func:`disc_distances` from the vertices ``zero`` and from
    ``one``: 0 on ``zero``, 1 on ``one``, in [0, 1]; NaN off the domain."""
    d0, d1 = distances(zero), distances(one)
    total = d0 + d1
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(total > 0.0, d0 / total, np.nan)


def level_curves(tables: MeshTables, sets: LevelSets, other: np.ndarray, on_rim: np.ndarray, levels: np.ndarray) -> list:
    """Rows ``(faces, bary)`` of the level sets at ``levels``: each joined piece with an end on the rim
    (``on_rim`` per vertex) and at least ``MIN_LENGTH_MM`` long, running the way ``other`` grows when
    both ends are on the rim, else from its rim end."""
    rows = []
    for level in levels:
        for points, point_faces in chain_walks(sets(level)):
            if np.linalg.norm(np.diff(points, axis=0), axis=1).sum() < MIN_LENGTH_MM:
                continue
            bary = np.clip(tables.bary_of_points(point_faces[[0, -1]], points[[0, -1]]), 0.0, 1.0)
            corners = tables.faces[point_faces[[0, -1]]]
            rim_end = (on_rim[corners] | (bary < 1e-9)).all(axis=1)  # on an edge between rim vertices
            if not rim_end.any():
                continue
            if rim_end.all():
                ends = (other[corners] * bary).sum(axis=1)
                forward = ends[0] <= ends[1]
            else:
                forward = bool(rim_end[0])
            rows.append(polyline_rows(tables, *((points, point_faces) if forward else reversed_walk(points, point_faces))))
    return rows


NO_GRID = ("remove the grid nodes (grid, grid_layers, grid_crossings, grid_select, grid_radius, grid_finish) and their "
           "entries in prescreen, screen and best from the pipeline")


@node("curves.trace_grid", params=TraceGridParams, inputs=("mesh", "regions"), outputs=("across", "along"))
def trace_grid(params: TraceGridParams, mesh: Mesh, regions) -> dict[str, object]:
    """The grid's two families (see the module docstring), each curve starting on the rim."""
    tables = build_tables(mesh.vertices, mesh.faces)
    domain = ~(np.asarray(regions.base_faces, dtype=bool) | np.asarray(regions.exclusion_base, dtype=bool))
    loops = boundary_loops(tables, domain)
    if not loops or len(loops[0]) < 8:
        raise UserError(f"curves.trace_grid: the surface around the base has no rim to wire a grid to; {NO_GRID}")
    rim = loops[0]
    if params.coordinates == "plan":
        across, along = plan_coordinates(tables, domain, np.asarray(regions.up, dtype=np.float64))
    else:
        end_a, end_b, side_c, side_d = rim_arcs(tables, domain, rim, params.end_share)
        distances = disc_distances(tables, domain)
        across = distance_share(distances, end_a, end_b)
        along = distance_share(distances, side_c, side_d)
    family = "grid_plan" if params.coordinates == "plan" else "grid"
    on_rim = np.zeros(len(tables.vertices), dtype=bool)
    on_rim[rim] = True
    families = {}
    for name, u, other, n in (("across", across, along, params.n_across), ("along", along, across, params.n_along)):
        sets = LevelSets(tables, u, domain)
        levels = np.sort(reseeded_levels(sets, (np.arange(n) + 0.5) / n, params.n_reseeded))
        rows = level_curves(tables, sets, other, on_rim, levels)
        if not rows:
            raise UserError(f"curves.trace_grid: no line {name} the surface reaches the rim; {NO_GRID}")
        families[name] = pack(tables, rows, np.full(len(rows), int(CurveEnd.BASE), dtype=np.int8), 0.0, family)
    return families


@node("curves.grid_layers", params=GridLayersParams, inputs=("mesh", "across", "along"), outputs=("tx", "rx"))
def grid_layers(params: GridLayersParams, mesh: Mesh, across: CurveSet, along: CurveSet) -> dict[str, object]:
    """The grid's ``tx`` family as Tx lines, walked backwards to end on the rim where they are wired,
    and the other as Rx lines as they are; the angle 0 when the lines across drive, 90 deg otherwise."""
    tables = build_tables(mesh.vertices, mesh.faces)
    tx, rx = (across, along) if params.tx == "across" else (along, across)
    rows = [reversed_rows(tables, tx.faces[tx.curve(c)], tx.bary[tx.curve(c)]) for c in range(tx.count)]
    angle = 0.0 if params.tx == "across" else 0.5 * np.pi
    tx = dataclasses.replace(pack(tables, rows, tx.end_reason, angle, tx.family), layer="tx")
    return {"tx": tx, "rx": dataclasses.replace(rx, angle=angle)}
