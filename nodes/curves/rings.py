"""``curves.trace_rings``: an Rx family that encloses the Tx pole, so each Rx crosses most Tx lines once.

A dipole Rx loop leaves the base and returns to it, cutting the sensing region in two: it crosses
only the Tx lines whose base ends lie on its far side. Here every Rx candidate is instead a *ring*
around the Tx pole with one *leg* back to the base. The rings are level sets ``u = c`` of the
*harmonic radial function* ``u``: 0 on the far exclusion around the Tx pole, 1 on the base and its
exclusion, harmonic in between. The sensing region is an annulus between those two, and a harmonic
function with constant values on both boundaries of an annulus has no critical point, so every
level set is one closed curve around the pole, the level sets fill the whole region from the pole
to the base, and no two of them meet. ``n_rings - n_reseeded`` levels ``c_k`` are spread so that,
along the Tx lines (median over the candidates), neighbouring rings are equally far apart from the
pole to the base; the others pass through the points farthest from the rings before them, which
lie in dead ends (a second ear) where ``u`` barely changes and the level set makes a long hairpin.

The legs are Tx candidate field lines of a *corridor*: ``n_rings`` consecutive Tx candidates (in
their angular order around the pole) centred at ``corridor_turn`` of the order. Leg ``k`` gets level
``c_k``, the levels decreasing along the corridor in the rings' walking direction; ring ``k`` starts
where its leg first reaches ``u = c_k`` and walks along the level set, keeping the pole on its right,
until (past its first few mm) it comes within ``trace_width_mm + clearance_mm`` of a leg, or leaves
the sensing region. The legs it passes first exist only beyond larger levels, so a ring meets no
leg, and rings are level sets of different values, so they never cross each other. Each candidate
is oriented to start at the base: the leg reversed, then the ring; ``end_reason`` is the leg's
(``BASE`` when it is wired at the base). Tx lines inside the corridor run along legs: phase 1 never
selects a Tx line and an Rx candidate laid along each other (``layout.clearance.parallel_pairs``).

``angle`` of the CurveSet is the corridor position ``2 pi corridor_turn`` (rad), which names the
branch. Units: mm, radians.
"""
from __future__ import annotations

import numpy as np
from pydantic import Field

from ...graph.errors import UserError
from ...graph.node import NodeParams, node
from ..data.types import CurveEnd, CurveSet, Mesh
from ..geometry.harmonic import harmonic_interpolation
from ..geometry.mesh_tables import MeshTables, build_tables
from .assembly import TraceStats, reversed_rows
from .connection import DirectionField
from .rx_seeding import zero_set

STOP_MARGIN_MM = 0.5
"""A ring stops this much farther from a leg than trace width + clearance: twice the resampling step
of phase 1's conservative clearance check, so a ring's end is no conflict with the leg it meets."""

LEVEL_GRID = 257
"""Levels of ``u`` at which the Tx lines' arrival distances are measured."""


class TraceRingsParams(NodeParams):
    n_rings: int = Field(16, ge=1, description="Rx ring candidates = Tx candidates in the corridor")
    n_reseeded: int = Field(4, ge=0, description="of those, rings through the points farthest from the others (dead ends)")
    corridor_turn: float = Field(0.0, ge=0, lt=1, description="corridor centre as a fraction of the Tx candidates' angular order")
    trace_width_mm: float = Field(1.0, gt=0, description="trace width (mm), for where a ring stops")
    clearance_mm: float = Field(1.0, ge=0, description="edge-to-edge clearance (mm), for where a ring stops")


def row_values(tables: MeshTables, vertex_values: np.ndarray, faces: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Piecewise-linear vertex values at surface points (face, barycentrics)."""
    return np.einsum("kc,kc->k", vertex_values[tables.faces[faces]], bary)


def ring_walk(level_faces, p, q, start_face: int, start_point: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The level-set chain from ``start_point`` (inside face ``start_face``) along ``p -> q`` while the
    segments join, wrapping once around a closed chain: (points (n, 3), face of the segment each starts)."""
    hits = np.flatnonzero(level_faces == start_face)
    if len(hits) == 0:
        return np.empty((0, 3)), np.empty(0, dtype=np.int64)
    s = int(hits[0])
    joins = np.linalg.norm(q[:-1] - p[1:], axis=1) < 1e-9
    lo = s
    while lo > 0 and joins[lo - 1]:
        lo -= 1
    hi = s
    while hi < len(p) - 1 and joins[hi]:
        hi += 1
    closed = np.linalg.norm(q[hi] - p[lo]) < 1e-9
    order = list(range(s, hi + 1)) + (list(range(lo, s)) if closed else [])
    points = np.vstack([start_point[None], q[order]])
    faces = np.r_[level_faces[order], level_faces[order[-1]]]
    return points, faces


def stop_index(points: np.ndarray, leg_points: np.ndarray, bound_mm: float) -> int:
    """Rows of a ring walk to keep: up to the first point, beyond the first ``3 * bound_mm`` of the
    walk, within ``bound_mm`` of a leg (near its start the ring leaves its own leg and the legs of
    smaller rings beside it; phase 1's clearance conflicts decide between those)."""
    from scipy.spatial import cKDTree

    if len(points) < 2:
        return 0
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    near = (cKDTree(leg_points).query(points, distance_upper_bound=bound_mm)[0] < np.inf) & (arc > 3 * bound_mm)
    return int(np.argmax(near)) if near.any() else len(points)


def leg_joint(tx: CurveSet, values: np.ndarray, c: int, level: float) -> tuple[int, np.ndarray] | None:
    """Where Tx candidate ``c`` (with ``values`` of ``u`` per row) first reaches ``level``: (row before
    the joint, joint point in mm), or None if it never does."""
    up = np.flatnonzero((values[:-1] < level) & (values[1:] >= level))
    if len(up) == 0:
        return None
    j, lo = int(up[0]), int(tx.offsets[c])
    t = (level - values[j]) / (values[j + 1] - values[j])
    return j, tx.points[lo + j] + t * (tx.points[lo + j + 1] - tx.points[lo + j])


def corridor(tx: CurveSet, n_rings: int, turn: float) -> np.ndarray:
    """Indices of the ``n_rings`` consecutive Tx candidates centred at ``turn`` of their order (wrapping)."""
    n = min(n_rings, tx.count)
    centre = int(round(turn * tx.count))
    return (centre - n // 2 + np.arange(n)) % tx.count


def radial_function(tables: MeshTables, regions, pole: int) -> np.ndarray:
    """``(n,)`` the harmonic radial function ``u``: 0 on the far exclusion's vertices and the pole,
    1 on the vertices of the base and its exclusion, harmonic elsewhere (see the module docstring)."""
    inner = np.union1d(tables.faces[np.asarray(regions.exclusion_far, dtype=bool)].ravel(), [pole])
    outer_faces = np.asarray(regions.base_faces, dtype=bool) | np.asarray(regions.exclusion_base, dtype=bool)
    outer = np.setdiff1d(np.unique(tables.faces[outer_faces]), inner)
    fixed = np.r_[inner, outer]
    values = np.r_[np.zeros(len(inner)), np.ones(len(outer))]
    return harmonic_interpolation(tables.vertices, tables.faces, fixed, values)


def ring_levels(tx: CurveSet, u_rows: np.ndarray, n: int) -> np.ndarray:
    """``n`` levels of ``u`` in decreasing order, spread in equal steps of the distance along the Tx
    lines (where the crossings of one Tx line follow each other): the median over the Tx candidates of
    the arc length (mm) at which a line first reaches a level grows in equal steps from the pole to
    the base, half a step from either end. ``u_rows``: ``u`` at every row of ``tx``."""
    grid = np.linspace(0.0, 1.0, LEVEL_GRID)
    arrival = np.empty((tx.count, len(grid)))
    for c in range(tx.count):
        rows = tx.curve(c)
        arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(tx.points[rows], axis=0), axis=1))]
        reached, first = np.unique(np.maximum.accumulate(u_rows[rows]), return_index=True)
        arrival[c] = np.interp(grid, reached, arc[first]) if len(reached) > 1 else arc[-1]
    along = np.maximum.accumulate(np.median(arrival, axis=0))
    targets = along[0] + (np.arange(n)[::-1] + 0.5) / n * (along[-1] - along[0])
    return np.interp(targets, along, grid)


def reseeded_levels(tables: MeshTables, u: np.ndarray, sensing: np.ndarray, levels: np.ndarray, count: int) -> np.ndarray:
    """``levels`` and ``count`` more, each the level through the sensing vertex farthest (mm, to the
    level sets' polylines) from the rings so far, in decreasing order: a dead end such as an ear, where
    ``u`` barely changes, falls between two evenly spread levels and gets a ring of its own."""
    vertices = np.unique(tables.faces[sensing])
    nearest = np.full(len(vertices), np.inf)
    chosen = list(levels)
    for level in chosen:
        nearest = np.minimum(nearest, level_distance(tables, u, sensing, level, vertices))
    for _ in range(count):
        level = float(u[vertices[np.argmax(nearest)]])
        if not 0.0 < level < 1.0:
            break
        chosen.append(level)
        nearest = np.minimum(nearest, level_distance(tables, u, sensing, level, vertices))
    return np.sort(np.asarray(chosen))[::-1]


def level_distance(tables: MeshTables, u: np.ndarray, sensing: np.ndarray, level: float, vertices: np.ndarray) -> np.ndarray:
    """Distance (mm) of ``vertices`` from the level set ``u = level`` inside ``sensing`` (inf if empty)."""
    from scipy.spatial import cKDTree

    _, p, q = zero_set(tables, u - level, sensing)
    if len(p) == 0:
        return np.full(len(vertices), np.inf)
    return cKDTree(np.vstack([p, q])).query(tables.vertices[vertices])[0]


def ring_curves(params: TraceRingsParams, tables: MeshTables, regions, field: DirectionField, tx: CurveSet):
    """(rows per candidate as (faces, bary) arrays, end reasons, the levels of the rings) of the family."""
    u = radial_function(tables, regions, field.start_vertex)
    sensing = np.asarray(regions.sensing_faces, dtype=bool)
    bound = params.trace_width_mm + params.clearance_mm
    u_rows = row_values(tables, u, tx.faces, tx.bary)
    candidates = corridor(tx, params.n_rings, params.corridor_turn)
    n_even = max(len(candidates) - params.n_reseeded, 1)
    levels = reseeded_levels(tables, u, sensing, ring_levels(tx, u_rows, n_even), len(candidates) - n_even)
    joints = [leg_joint(tx, u_rows[tx.offsets[c] : tx.offsets[c + 1]], c, level) for c, level in zip(candidates, levels)]
    legs = [(c, *joint) for c, joint in zip(candidates, joints) if joint is not None]
    levels = [level for level, joint in zip(levels, joints) if joint is not None]
    portions = [np.vstack([point[None], tx.points[int(tx.offsets[c]) + j + 1 : int(tx.offsets[c + 1])]]) for c, j, point in legs]
    leg_points = np.concatenate([resample_polyline(p, 0.25) for p in portions]) if legs else np.empty((0, 3))
    rows, ends, ring_levels_kept = [], [], []
    for (c, j, point), level in zip(legs, levels):
        lo, hi = int(tx.offsets[c]), int(tx.offsets[c + 1])
        level_faces, p, q = zero_set(tables, u - level, sensing)
        ring_points, ring_faces = ring_walk(level_faces, p, q, int(tx.faces[lo + j]), point)
        keep = stop_index(ring_points, leg_points, bound + STOP_MARGIN_MM)
        if keep < 2:
            continue
        leg_faces = np.r_[tx.faces[lo + j], tx.faces[lo + j + 1 : hi]]
        leg_bary = np.vstack([tables.bary_of_points(tx.faces[lo + j : lo + j + 1], point[None]), tx.bary[lo + j + 1 : hi]])
        back_faces, back_bary = reversed_rows(tables, leg_faces, leg_bary)
        faces = np.r_[back_faces[:-1], ring_faces[:keep]]
        points = np.vstack([tables.points(back_faces[:-1], back_bary[:-1]), ring_points[:keep]])
        bary = np.clip(tables.bary_of_points(faces, points), 0.0, 1.0)
        rows.append((faces, bary / bary.sum(axis=1, keepdims=True)))
        ends.append(int(tx.end_reason[c]))
        ring_levels_kept.append(level)
    return rows, np.asarray(ends, dtype=np.int8), np.asarray(ring_levels_kept)


def resample_polyline(points: np.ndarray, step_mm: float) -> np.ndarray:
    """Points every ``step_mm`` or closer along a polyline (its rows included)."""
    if len(points) < 2:
        return points
    seg = np.diff(points, axis=0)
    pieces = np.maximum(1, np.ceil(np.linalg.norm(seg, axis=1) / step_mm).astype(np.int64))
    idx = np.repeat(np.arange(len(seg)), pieces)
    t = (np.arange(len(idx)) - (np.cumsum(pieces) - pieces)[idx]) / pieces[idx]
    return np.vstack([points[idx] + t[:, None] * seg[idx], points[-1:]])


def pack(tables: MeshTables, rows: list, ends: np.ndarray, angle: float) -> CurveSet:
    """The candidates' rows as one CurveSet (layer rx)."""
    faces = np.concatenate([f for f, _ in rows]) if rows else np.empty(0, dtype=np.int64)
    bary = np.concatenate([b for _, b in rows]) if rows else np.empty((0, 3))
    offsets = np.concatenate([[0], np.cumsum([len(f) for f, _ in rows])]).astype(np.int64)
    points = tables.points(faces, bary)
    lengths = np.array([np.linalg.norm(np.diff(points[a:b], axis=0), axis=1).sum() for a, b in zip(offsets[:-1], offsets[1:])])
    return CurveSet(layer="rx", points=points, faces=faces, bary=bary, offsets=offsets, lengths_mm=lengths,
                    end_reason=ends, angle=float(angle), family="rings")


@node("curves.trace_rings", params=TraceRingsParams, inputs=("mesh", "regions", "field", "tx"), outputs=("curves", "stats"))
def trace_rings(params: TraceRingsParams, mesh: Mesh, regions, field: DirectionField, tx: CurveSet) -> dict[str, object]:
    """Rx rings around the Tx pole with legs along a corridor of Tx candidate lines (see the module docstring)."""
    if field.layer != "tx":
        raise UserError(f"curves.trace_rings needs the tx field (distance from the Tx pole), got the {field.layer} field")
    tables = build_tables(mesh.vertices, mesh.faces)
    rows, ends, _ = ring_curves(params, tables, regions, field, tx)
    angle = 2.0 * np.pi * params.corridor_turn
    curves = pack(tables, rows, ends, angle)
    n = len(corridor(tx, params.n_rings, params.corridor_turn))
    counts = np.bincount(ends, minlength=len(CurveEnd)).astype(np.int64)
    stats = TraceStats(layer="rx", angle=angle, traced=n, kept=curves.count, dropped=n - curves.count, end_counts=counts,
                       sink_edges=int(counts[CurveEnd.SINK_EDGE]), sink_edge_rate=float(counts[CurveEnd.SINK_EDGE] / max(n, 1)),
                       sink_hits=0, sink_slides=0, reached_base_rate=float(counts[CurveEnd.BASE] / max(n, 1)), face_steps=0,
                       mean_length_mm=float(curves.lengths_mm.mean()) if curves.count else 0.0)
    return {"curves": curves, "stats": stats}
