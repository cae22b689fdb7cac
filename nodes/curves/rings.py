"""``curves.trace_rings``: an Rx family that encloses the Tx pole, so each Rx crosses most Tx lines once.

A dipole Rx loop leaves the base and returns to it, cutting the sensing region in two: it crosses
only the Tx lines whose base ends lie on its far side. Here every Rx candidate is instead a *ring*
around the Tx pole with one *leg* back to the base. The rings are level sets ``u = c`` of the
*harmonic radial function* ``u``: 0 on the far exclusion around the Tx pole, 1 on the base and its
exclusion, harmonic in between. The sensing region is an annulus between those two, and a harmonic
function with constant values on both boundaries of an annulus has no critical point, so every
level set is one closed curve around the pole, the level sets fill the whole region from the pole
to the base, and no two of them meet. ``u`` and the levels ``c_k``, shared by every corridor, come
from ``curves.ring_levels`` (:mod:`retrotouch.nodes.curves.ring_levels`, which says how they are
spread); ``n_rings`` below is their count.

The legs run side by side in a *corridor* along one Tx candidate line, the *spine*: the candidate at
``corridor_turn`` of their angular order around the pole (or the nearest one that reaches the base
and every ring's level). The innermost ring's leg is the spine itself; the others, from the inside
out, go to the side of the spine with the fewer legs (the other side if it has no room), each one
``leg_spacing_mm`` farther out than the last on its side: a leg at offset ``o`` is the level set ``d
= o`` of the Euclidean distance ``d`` from the spine, from its ring ``u = c_k`` down to where the
sensing region meets the base exclusion (as the Tx lines end). Distances from one curve are
1-Lipschitz, so two legs on one side are at least their offsets' difference apart, and the corridor
is about ``n_rings * leg_spacing_mm`` wide at the base. Ring ``k`` starts where its leg meets ``u =
c_k`` and walks along the level set away from the spine (keeping the pole on its right on one side,
on its left on the other) until, past its first few mm, it comes within ``trace_width_mm +
clearance_mm`` of a leg, or leaves the sensing region: it passes the ends of the legs farther out on
its side (they belong to rings nearer the base and stop there), goes round the pole and stops at the
outermost leg on the other side that reaches its level. Rings are level sets of different values and
legs level sets of different distances, so no two candidates cross. A leg that does not run down to
the base without coming nearer the pole than its ring (a distance level set that closes around a
limb, a ring too short to reach the offset) on either side is dropped with its ring. Each candidate
is oriented to start at the base: the leg reversed, then the ring, ``end_reason`` ``BASE``. Tx lines
in the corridor run along legs: phase 1 never selects a Tx line and an Rx candidate laid along each
other (``layout.clearance.parallel_pairs``).

With ``legs="tx_lines"`` (family ``rings_tx``; ``rings`` otherwise) the legs are instead the parts
beyond their rings' levels of ``n_rings`` consecutive Tx candidates centred at ``corridor_turn``, the
levels decreasing along the corridor in the rings' walking direction (pole on the right), and
``end_reason`` is that Tx line's. Nothing keeps those legs apart (phase 1's clearance conflicts
choose among the rings whose legs come too close), but they take no room beside the Tx lines: on a
base at the end of a thin limb, where every Tx line runs down the limb, the side-by-side corridor
leaves the Tx lines no room.

With ``climb="per_line"`` (families ``rings_per_line``, ``rings_tx_per_line``) the rings are level
sets of the per-line climb of ``curves.ring_levels`` instead of ``u``: it grows along every Tx line,
hairpins through a dead end included, so a ring detours through a second ear or a limb where a level
set of ``u`` stays out of it. It is a least-squares fit, not harmonic: nothing rules out a critical
point, and a ring then follows the piece of its level set that its leg meets.

``angle`` of the CurveSet is the corridor position ``2 pi corridor_turn`` (rad), which names the
branch. Units: mm, radians.
"""
from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from ...graph.node import NodeParams, node
from ..data.types import CurveEnd, CurveSet, Mesh
from ..geometry.mesh_tables import MeshTables, build_tables
from .assembly import TraceStats, packed_rows, polyline_rows, reversed_walk
from .ring_levels import LevelSets, RingLevels, row_values

STOP_MARGIN_MM = 0.5
"""A ring stops this much farther from a leg than trace width + clearance: twice the resampling step
of phase 1's conservative clearance check, so a ring's end is no conflict with the leg it meets."""

LEG_SPACING_MM = 3.0
"""Default distance between neighbouring legs (mm): trace width + clearance + a margin for the
piecewise-linear distance field and phase 1's conservative clearance check."""

class TraceRingsParams(NodeParams):
    corridor_turn: float = Field(0.0, ge=0, lt=1, description="corridor centre as a fraction of the Tx candidates' angular order")
    legs: Literal["offset", "tx_lines"] = Field("offset", description="legs side by side along a spine Tx line, or along Tx lines")
    leg_spacing_mm: float = Field(LEG_SPACING_MM, gt=0, description="offset legs: distance between neighbouring legs (mm)")
    trace_width_mm: float = Field(1.0, gt=0, description="trace width (mm), for where a ring stops")
    clearance_mm: float = Field(1.0, ge=0, description="edge-to-edge clearance (mm), for where a ring stops")
    climb: Literal["median", "per_line"] = Field(
        "median", description="rings as level sets of the harmonic radial function, or of the per-line climb (into dead ends)")


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


def spine(tx: CurveSet, u_rows: np.ndarray, turn: float, levels: np.ndarray) -> int | None:
    """The Tx candidate nearest ``turn`` of their order (wrapping) that ends at the base and reaches
    every one of ``levels`` on its way there (on a thin object a Tx line may reach the base region
    where it borders the pole's exclusion, with ``u`` short of 1); None if none does."""
    centre = int(round(turn * tx.count))
    for step in range(tx.count):
        c = (centre + (step + 1) // 2 * (1 if step % 2 else -1)) % tx.count
        values = u_rows[tx.offsets[c] : tx.offsets[c + 1]]
        if tx.end_reason[c] == int(CurveEnd.BASE) and all(leg_joint(tx, values, c, level) for level in levels):
            return c
    return None


def ring_curves(params: TraceRingsParams, tables: MeshTables, regions, levels: RingLevels, tx: CurveSet):
    """(rows per candidate as (faces, bary) arrays, end reasons, the levels of the rings) of the family."""
    (u, at_levels), sensing = levels.function(params.climb), np.asarray(regions.sensing_faces, dtype=bool)
    u_rows = row_values(tables, u, tx.faces, tx.bary)
    u_sets = LevelSets(tables, u, sensing)
    if params.legs == "offset":
        legs = offset_legs(params, u_sets, tx, u_rows, at_levels)
    else:
        legs = tx_line_legs(params, u_sets, tx, u_rows, at_levels, levels.count)
    all_legs = np.concatenate([resample_polyline(leg[0], 0.25) for leg in legs]) if legs else np.empty((0, 3))
    rows, ends, kept = [], [], []
    for leg_points, leg_faces, ring_points, ring_faces, level, end in legs:
        keep = stop_index(ring_points, all_legs, params.trace_width_mm + params.clearance_mm + STOP_MARGIN_MM)
        if keep < 2:
            continue
        back_points, back_faces = reversed_walk(leg_points, leg_faces)
        rows.append(polyline_rows(tables, np.vstack([back_points[:-1], ring_points[:keep]]), np.r_[back_faces[:-1], ring_faces[:keep]]))
        ends.append(end)
        kept.append(level)
    return rows, np.asarray(ends, dtype=np.int8), np.asarray(kept)


def tx_line_leg(tx: CurveSet, u_rows: np.ndarray, c: int, level: float) -> tuple[np.ndarray, np.ndarray, int, np.ndarray] | None:
    """The part of Tx candidate ``c`` beyond ``u = level``: (points from the joint to the base end, the
    face of the segment each starts, the row before the joint, the joint), or None if it never gets there."""
    lo, hi = int(tx.offsets[c]), int(tx.offsets[c + 1])
    joint = leg_joint(tx, u_rows[lo:hi], c, level)
    if joint is None:
        return None
    j, point = joint
    return np.vstack([point[None], tx.points[lo + j + 1 : hi]]), np.r_[tx.faces[lo + j : hi - 1], tx.faces[hi - 1]], j, point


def tx_line_legs(params: TraceRingsParams, u_sets: LevelSets, tx: CurveSet, u_rows: np.ndarray,
                 levels: np.ndarray, n: int) -> list[tuple]:
    """Legs along consecutive Tx candidates of a corridor of ``n`` centred at ``corridor_turn`` of their
    order, the levels decreasing along it in the rings' walking direction (pole on the right):
    ``(leg points, leg faces, ring points, ring faces, level, end reason)`` each."""
    corridor = (int(round(params.corridor_turn * tx.count)) - n // 2 + np.arange(n)) % tx.count
    legs = []
    for c, level in zip(corridor, levels):
        leg = tx_line_leg(tx, u_rows, int(c), level)
        if leg is None:
            continue
        leg_points, leg_faces, j, joint = leg
        ring_points, ring_faces = ring_walk(*u_sets(level), int(tx.faces[tx.offsets[c] + j]), joint)
        legs.append((leg_points, leg_faces, ring_points, ring_faces, level, int(tx.end_reason[c])))
    return legs


def offset_legs(params: TraceRingsParams, u_sets: LevelSets, tx: CurveSet, u_rows: np.ndarray, levels: np.ndarray) -> list[tuple]:
    """Legs side by side along the spine (see the module docstring), from the innermost ring out:
    ``(leg points, leg faces, ring points, ring faces, level, end reason)`` each."""
    from scipy.spatial import cKDTree

    c = spine(tx, u_rows, params.corridor_turn, levels)
    if c is None:
        return []
    lo, hi = int(tx.offsets[c]), int(tx.offsets[c + 1])
    tables = u_sets.tables
    distance = cKDTree(resample_polyline(tx.points[lo:hi], 0.25)).query(tables.vertices)[0]
    distance_sets = LevelSets(tables, distance, u_sets.sensing)
    base = int(CurveEnd.BASE)
    legs, next_offset = [], {True: 1, False: 1}  # per side (True: the pole on the ring's right), in spacings
    for level in levels[::-1]:
        spine_points, spine_faces, j, joint = tx_line_leg(tx, u_rows, c, level)
        level_set = u_sets(level)
        if not legs:  # the innermost ring's leg is the spine
            legs.append((spine_points, spine_faces, *ring_walk(*level_set, int(tx.faces[lo + j]), joint), level, base))
            continue
        nearer = next_offset[True] <= next_offset[False]
        for side in (nearer, not nearer):
            ring_points, ring_faces = ring_walk(*either_way(level_set, side), int(tx.faces[lo + j]), joint)
            offset = next_offset[side] * params.leg_spacing_mm
            leg = offset_leg(u_sets.values, distance_sets, ring_points, ring_faces, offset, level)
            if leg is not None:
                leg_points, leg_faces, start = leg
                legs.append((leg_points, leg_faces, np.vstack([leg_points[:1], ring_points[start:]]), ring_faces[start - 1 :], level, base))
                next_offset[side] += 1
                break
    return legs


def either_way(chain: tuple[np.ndarray, np.ndarray, np.ndarray], forward: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A chained level set ``(faces, p, q)`` of :func:`zero_set` as it is (``forward``) or walked backwards."""
    faces, p, q = chain
    return (faces, p, q) if forward else (faces[::-1], q[::-1], p[::-1])


def offset_leg(u: np.ndarray, distance_sets: LevelSets, ring_points: np.ndarray, ring_faces: np.ndarray, offset: float,
               level: float) -> tuple[np.ndarray, np.ndarray, int] | None:
    """The leg at ``offset`` (mm) from the spine (``distance_sets``: level sets of the distance from it)
    for the ring walked from the spine (``ring_points``, ``ring_faces``): (leg points from the ring to
    the base, the face of the segment each starts, the first ring row past the leg's start), or None
    if the ring never gets that far from the spine or the level set ``distance = offset`` from there
    does not run down to the base without coming back nearer the pole than the ring."""
    tables, distance = distance_sets.tables, distance_sets.values
    d_ring = row_values(tables, distance, ring_faces, np.clip(tables.bary_of_points(ring_faces, ring_points), 0.0, 1.0))
    past = np.flatnonzero(d_ring >= offset)
    if len(past) == 0 or past[0] == 0:
        return None
    i = int(past[0])
    t = (offset - d_ring[i - 1]) / (d_ring[i] - d_ring[i - 1])
    start = ring_points[i - 1] + t * (ring_points[i] - ring_points[i - 1])
    chain = distance_sets(offset)
    best = None
    for forward in (True, False):
        points, faces = ring_walk(*either_way(chain, forward), int(ring_faces[i - 1]), start)
        if len(points) < 2:
            continue
        u_leg = row_values(tables, u, faces, np.clip(tables.bary_of_points(faces, points), 0.0, 1.0))
        if u_leg[-1] > 1.0 - 1e-6 and u_leg.min() > level - 1e-3 and (best is None or len(points) < len(best[0])):
            best = (points, faces)
    return None if best is None else (*best, i)


def resample_polyline(points: np.ndarray, step_mm: float) -> np.ndarray:
    """Points every ``step_mm`` or closer along a polyline (its rows included)."""
    if len(points) < 2:
        return points
    seg = np.diff(points, axis=0)
    pieces = np.maximum(1, np.ceil(np.linalg.norm(seg, axis=1) / step_mm).astype(np.int64))
    idx = np.repeat(np.arange(len(seg)), pieces)
    t = (np.arange(len(idx)) - (np.cumsum(pieces) - pieces)[idx]) / pieces[idx]
    return np.vstack([points[idx] + t[:, None] * seg[idx], points[-1:]])


def pack(tables: MeshTables, rows: list, ends: np.ndarray, angle: float, family: str) -> CurveSet:
    """The candidates' rows as one CurveSet (layer rx)."""
    return CurveSet(layer="rx", **packed_rows(tables, rows), end_reason=ends, angle=float(angle), family=family)


def packed_stats(curves: CurveSet, traced: int) -> TraceStats:
    """The TraceStats of a family :func:`pack` made out of ``traced`` level sets (no field was traced)."""
    counts = np.bincount(curves.end_reason, minlength=len(CurveEnd)).astype(np.int64)
    return TraceStats(layer="rx", angle=curves.angle, traced=traced, kept=curves.count, dropped=traced - curves.count,
                      end_counts=counts, sink_edges=int(counts[CurveEnd.SINK_EDGE]),
                      sink_edge_rate=float(counts[CurveEnd.SINK_EDGE] / max(traced, 1)), sink_hits=0, sink_slides=0,
                      reached_base_rate=float(counts[CurveEnd.BASE] / max(traced, 1)), face_steps=0,
                      mean_length_mm=float(curves.lengths_mm.mean()) if curves.count else 0.0)


@node("curves.trace_rings", params=TraceRingsParams, inputs=("mesh", "regions", "levels", "tx"), outputs=("curves", "stats"))
def trace_rings(params: TraceRingsParams, mesh: Mesh, regions, levels: RingLevels, tx: CurveSet) -> dict[str, object]:
    """Rx rings around the Tx pole at ``levels`` with legs along a corridor of Tx candidate lines (see the
    module docstring)."""
    tables = build_tables(mesh.vertices, mesh.faces)
    rows, ends, _ = ring_curves(params, tables, regions, levels, tx)
    angle = 2.0 * np.pi * params.corridor_turn
    family = ("rings" if params.legs == "offset" else "rings_tx") + ("_per_line" if params.climb == "per_line" else "")
    curves = pack(tables, rows, ends, angle, family)
    return {"curves": curves, "stats": packed_stats(curves, levels.count)}
