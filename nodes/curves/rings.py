"""``curves.trace_rings``: an Rx family that encloses the Tx pole, so each Rx crosses most Tx lines once.

A dipole Rx loop leaves the base and returns to it, cutting the sensing region in two: it crosses
only the Tx lines whose base ends lie on its far side. Here every Rx candidate is instead a *ring*
around the Tx pole (a level set ``d = r`` of the geodesic distance ``d`` from the pole, the Tx
field's ``start_distance``) with one *leg* back to the base. The legs are Tx candidate field lines
of a *corridor*: ``n_rings`` consecutive Tx candidates (in their angular order around the pole)
centred at ``corridor_turn`` of the order. Leg ``k`` of the corridor gets the radius ``r_k``, spread
evenly over ``[r_min, r_max]`` so that the radius grows against the walking direction of the rings;
ring ``k`` starts where its leg first reaches ``d = r_k`` and walks along the level set, keeping
the pole on its right, until (past its first few mm) it comes within ``trace_width_mm +
clearance_mm`` of a leg, or leaves the sensing region. The legs it passes first exist only
beyond larger radii, so a ring meets no leg, and rings are level sets of different values, so they
never cross each other. Each candidate is oriented to start at the base: the leg reversed, then the
ring; ``end_reason`` is the leg's (``BASE`` when it is wired at the base). Tx lines inside the
corridor run along legs; phase 1's clearance conflicts and C2 keep them apart.

``angle`` of the CurveSet is the corridor position ``2 pi corridor_turn`` (rad), which names the
branch. Units: mm, radians.
"""
from __future__ import annotations

import numpy as np
from pydantic import Field

from ...graph.errors import UserError
from ...graph.node import NodeParams, node
from ..data.types import CurveEnd, CurveSet, Mesh
from ..geometry.mesh_tables import MeshTables, build_tables
from .assembly import TraceStats, reversed_rows
from .connection import DirectionField
from .rx_seeding import zero_set


class TraceRingsParams(NodeParams):
    n_rings: int = Field(40, ge=1, description="Rx ring candidates = Tx candidates in the corridor")
    corridor_turn: float = Field(0.0, ge=0, lt=1, description="corridor centre as a fraction of the Tx candidates' angular order")
    r_min_mm: float | None = Field(None, gt=0, description="smallest ring radius (mm); default: where the first leg starts plus the bound")
    r_max_share: float = Field(0.85, gt=0, le=1, description="largest ring radius as a share of the shortest leg's pole distance at the base")
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


def corridor(tx: CurveSet, n_rings: int, turn: float) -> np.ndarray:
    """Indices of the ``n_rings`` consecutive Tx candidates centred at ``turn`` of their order (wrapping)."""
    n = min(n_rings, tx.count)
    centre = int(round(turn * tx.count))
    return (centre - n // 2 + np.arange(n)) % tx.count


def ring_curves(params: TraceRingsParams, tables: MeshTables, regions, field: DirectionField, tx: CurveSet):
    """(rows per candidate as (faces, bary) arrays, end reasons, the radii) of the ring family."""
    d = field.start_distance
    sensing = np.asarray(regions.sensing_faces, dtype=bool)
    bound = params.trace_width_mm + params.clearance_mm
    legs = corridor(tx, params.n_rings, params.corridor_turn)
    values = [row_values(tables, d, tx.faces[tx.offsets[c] : tx.offsets[c + 1]], tx.bary[tx.offsets[c] : tx.offsets[c + 1]])
              for c in legs]
    r_lo = params.r_min_mm or min(float(v[0]) for v in values) + bound
    r_hi = params.r_max_share * min(float(v.max()) for v in values)
    if r_hi <= r_lo:
        raise UserError(f"the corridor's legs end within {r_hi:.1f} mm of the Tx pole, below the smallest ring "
                        f"({r_lo:.1f} mm): move corridor_turn or lower r_min_mm")
    radii = np.linspace(r_hi, r_lo, len(legs))  # grows against the rings' walking direction
    joints, portions = [], []
    for c, v, r in zip(legs, values, radii):
        lo = int(tx.offsets[c])
        up = np.flatnonzero((v[:-1] < r) & (v[1:] >= r))
        if len(up) == 0:
            joints.append(None)
            portions.append(np.empty((0, 3)))
            continue
        j = int(up[0])
        t = (r - v[j]) / (v[j + 1] - v[j])
        point = tx.points[lo + j] + t * (tx.points[lo + j + 1] - tx.points[lo + j])
        joints.append((j, point))
        portions.append(np.vstack([point[None], tx.points[lo + j + 1 : int(tx.offsets[c + 1])]]))
    leg_points = np.concatenate([resample_polyline(p, 0.25) for p in portions])
    rows, ends = [], []
    for k, (c, r) in enumerate(zip(legs, radii)):
        if joints[k] is None:
            continue
        j, point = joints[k]
        lo, hi = int(tx.offsets[c]), int(tx.offsets[c + 1])
        level_faces, p, q = zero_set(tables, d - r, sensing)
        ring_points, ring_faces = ring_walk(level_faces, p, q, int(tx.faces[lo + j]), point)
        keep = stop_index(ring_points, leg_points, bound)
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
    return rows, np.asarray(ends, dtype=np.int8), radii


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
                    end_reason=ends, angle=float(angle))


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
