"""``curves.tx_lanes``: Tx candidates that run beside a line they would merge into.

Field lines of the Tx field gather where the surface funnels them towards the base: lines that
leave the pole apart (one of them through a second ear, say) meet further down and run on to the base
within a fraction of a millimetre of each other. Two traces there would lie on top of each other, so
the layout may select only one line of such a bundle, and what the others reached before they merged
stays far from any Tx trace.

A *lane* is a copy of a merging line that keeps its own way up to where it comes within ``offset`` of
the line it merges into (its *spine*: a line before it in the family order that it runs closer than the
smallest offset to for ``merge_run_mm``, beyond ``from_mm`` of its start) and from there follows the
spine at that offset to the base: the level set ``|x - spine| = offset`` (Euclidean, on the surface) on
the side it arrives from. With offsets above the layout's trace width + clearance (2 mm by default,
conflicts flagged from 2.25 mm: the default offsets, 3 and 5.5 mm, stay clear of that with the error of
the distance's piecewise-linear level set on the remeshed surface), the spine and lanes at different
offsets can be laid side by side down the funnel, so the selection can keep two or three lines of a
bundle. Lanes are extra candidates: the family keeps every field
line, each followed by its lanes (so the order at the pole holds), and a lane that does not reach the
base is not kept. A lane may cross other Tx lines (that merge into the spine from its side): the
crossings' Tx x Tx conflicts keep such pairs apart in the selection. Units: mm.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from pydantic import Field, PositiveFloat

from ...graph.node import NodeParams, node
from ..data.types import CurveEnd, CurveSet, Mesh, row_arcs
from ..geometry.mesh_tables import MeshTables, build_tables
from .assembly import packed_rows, polyline_rows
from .ring_levels import RingLevels, between_faces, row_values
from .rx_seeding import chain_walks, zero_set

STEP_MM = 0.25
"""Spacing of the points at which merges are found and the spine's distance is measured."""

BASE_LEVEL = 0.98
"""A lane ends on the base when the radial function (0 at the pole, 1 on the base) reaches this."""


class TxLanesParams(NodeParams):
    offsets_mm: list[PositiveFloat] = Field(
        [3.0, 5.5], description="lane offsets from the spine (mm), above trace width + clearance; [] keeps the field "
                                "lines alone")
    from_mm: float = Field(60.0, ge=0, description="merges nearer the pole than this arc length (mm) make no lane: the "
                           "lines' starts are trimmed there")
    merge_run_mm: float = Field(10.0, gt=0, description="a line merges where it stays closer than the smallest offset to "
                                "an earlier line for this length (mm)")


def dense_points(curves: CurveSet, step_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points every ``step_mm`` along every curve: (points (P, 3), curve (P,), arc (P,) mm from its start)."""
    row_arc = row_arcs(curves)
    lengths = row_arc[curves.offsets[1:] - 1]
    counts = np.floor(lengths / step_mm).astype(np.int64) + 1
    curve = np.repeat(np.arange(curves.count), counts)
    arc = (np.arange(len(curve)) - np.repeat(np.cumsum(counts) - counts, counts)) * step_mm
    lo = curves.offsets[:-1][curve]
    span = np.diff(curves.offsets)[curve]
    k = np.empty(len(curve), dtype=np.int64)
    for c in range(curves.count):  # the segment holding each point, per curve
        rows = slice(curves.offsets[c], curves.offsets[c + 1])
        own = curve == c
        k[own] = np.searchsorted(row_arc[rows], arc[own], side="right") - 1
    k = np.clip(k, 0, span - 2)
    a, b = lo + k, lo + k + 1
    t = np.clip((arc - row_arc[a]) / np.maximum(row_arc[b] - row_arc[a], 1e-12), 0.0, 1.0)
    return curves.points[a] + t[:, None] * (curves.points[b] - curves.points[a]), curve, arc


def merges(points: np.ndarray, curve: np.ndarray, arc: np.ndarray, count: int, params: TxLanesParams,
           within_mm: float) -> dict[int, tuple[int, float]]:
    """Per merging curve: (its spine, the arc (mm) where it starts running within ``within_mm`` of an
    earlier curve for ``merge_run_mm``, beyond ``from_mm``)."""
    from scipy.spatial import cKDTree

    pairs = cKDTree(points).query_pairs(within_mm, output_type="ndarray")
    pairs = pairs[curve[pairs[:, 0]] != curve[pairs[:, 1]]]
    later_first = curve[pairs[:, 0]] > curve[pairs[:, 1]]
    later = np.where(later_first, pairs[:, 0], pairs[:, 1])
    partner = np.full(len(points), -1)
    partner[later] = curve[np.where(later_first, pairs[:, 1], pairs[:, 0])]
    run = max(int(round(params.merge_run_mm / STEP_MM)), 1)
    found = {}
    for c in range(1, count):
        own = np.flatnonzero(curve == c)
        close = (partner[own] >= 0) & (arc[own] >= params.from_mm)
        sums = np.r_[0, np.cumsum(close)]
        runs = np.flatnonzero(sums[run:] - sums[:-run] == run)
        if len(runs):
            first = own[runs[0]]
            found[c] = (int(partner[first]), float(arc[first]))
    return found


def spine_distance(tables: MeshTables, spine_points: np.ndarray, reach_mm: float, vertex_tree) -> np.ndarray:
    """(n,) Euclidean distance (mm) of the vertices of every face with a corner within ``reach_mm`` of the
    spine's points from them; ``inf`` elsewhere."""
    from scipy.spatial import cKDTree

    distance = np.full(len(tables.vertices), np.inf)
    stride = max(int(reach_mm / STEP_MM / 4), 1)
    near = vertex_tree.query_ball_point(spine_points[::stride], reach_mm + stride * STEP_MM)
    within = np.zeros(len(tables.vertices), dtype=bool)
    within[np.concatenate([np.asarray(n, dtype=np.int64) for n in near])] = True
    idx = np.unique(tables.faces[within[tables.faces].any(axis=1)])
    distance[idx] = cKDTree(spine_points).query(tables.vertices[idx])[0]
    return distance


def walk_from(tables: MeshTables, chains, face: int, start: np.ndarray, u: np.ndarray):
    """The level-set walk through ``face`` from ``start`` (on its segment there) towards the larger
    ``u``: (points, face of the segment leaving each point), or None."""
    for points, faces in chain_walks(chains):
        hits = np.flatnonzero(faces[:-1] == face)
        if len(hits) == 0:
            continue
        k = int(hits[0])
        ends = [0, k, -1]
        u_ends = row_values(tables, u, faces[ends], np.clip(tables.bary_of_points(faces[ends], points[ends]), 0.0, 1.0))
        if u_ends[2] >= u_ends[0]:
            return np.vstack([start, points[k + 1:]]), np.r_[faces[k], faces[k + 1:]]
        return np.vstack([start, points[: k + 1][::-1]]), np.r_[faces[k], faces[:k][::-1], faces[0]]
    return None


def lane_rows(tables: MeshTables, curves: CurveSet, params: TxLanesParams, u: np.ndarray, region: np.ndarray
              ) -> dict[int, list[tuple[np.ndarray, np.ndarray]]]:
    """Per field line with lanes, the rows (faces, bary) of each lane that reaches the base."""
    from scipy.spatial import cKDTree

    offsets = sorted(params.offsets_mm)
    points, curve, arc = dense_points(curves, STEP_MM)
    arcs = row_arcs(curves)
    reach = offsets[-1] + 2.0
    vertex_tree = cKDTree(tables.vertices)
    distances: dict[int, np.ndarray] = {}
    lanes: dict[int, list] = {}
    for c, (spine, merge_arc) in merges(points, curve, arc, curves.count, params, offsets[0]).items():
        if spine not in distances:
            distances[spine] = spine_distance(tables, points[curve == spine], reach, vertex_tree)
        to_spine = distances[spine]
        rows = slice(curves.offsets[c], curves.offsets[c + 1])
        faces, bary, xyz = curves.faces[rows], curves.bary[rows], curves.points[rows]
        row_distance = np.sum(np.where(bary > 0, to_spine[tables.faces[faces]], 0.0) * bary, axis=1)
        before_merge = int(np.searchsorted(arcs[rows], merge_arc))
        near = region & np.isfinite(to_spine[tables.faces]).all(axis=1)
        for offset in offsets:
            outside = np.flatnonzero(row_distance[:before_merge] >= offset)
            if len(outside) == 0 or outside[-1] + 1 >= len(faces) or not row_distance[outside[-1] + 1] < offset:
                continue
            r = int(outside[-1])  # segment r, in faces[r], enters the lane's level
            t = (row_distance[r] - offset) / (row_distance[r] - row_distance[r + 1])
            start = xyz[r] + t * (xyz[r + 1] - xyz[r])
            walk = walk_from(tables, zero_set(tables, to_spine - offset, near), int(faces[r]), start, u)
            if walk is None:
                continue
            lane_points, lane_faces = np.vstack([xyz[: r + 1], walk[0]]), np.r_[faces[: r + 1], walk[1]]
            lane_faces, lane_bary = polyline_rows(tables, lane_points, lane_faces)
            if row_values(tables, u, lane_faces[-1:], lane_bary[-1:])[0] >= BASE_LEVEL:
                lanes.setdefault(c, []).append((lane_faces, lane_bary))
    return lanes


@node("curves.tx_lanes", params=TxLanesParams, inputs=("mesh", "levels", "tx"), outputs=("curves",))
def tx_lanes(params: TxLanesParams, mesh: Mesh, levels: RingLevels, tx: CurveSet) -> CurveSet:
    """The Tx field lines, each followed by its lanes (see the module docstring); ``levels`` gives the
    radial function around the Tx pole (``curves.ring_levels``), 0 there and 1 on the base."""
    if not params.offsets_mm or tx.count < 2:
        return tx
    tables = build_tables(mesh.vertices, mesh.faces)
    u = levels.values
    lanes = lane_rows(tables, tx, params, u, between_faces(tables, u))
    rows, ends, parent = [], [], []
    for c in range(tx.count):  # each field line, then its lanes: the family keeps its order at the pole
        rows.append((tx.faces[tx.offsets[c]:tx.offsets[c + 1]], tx.bary[tx.offsets[c]:tx.offsets[c + 1]]))
        ends.append(int(tx.end_reason[c]))
        parent.append(-1)
        rows += lanes.get(c, [])
        ends += [int(CurveEnd.BASE)] * len(lanes.get(c, []))
        parent += [c] * len(lanes.get(c, []))
    return dataclasses.replace(tx, **packed_rows(tables, rows), end_reason=np.asarray(ends, dtype=np.int8),
                               lane_parent=np.asarray(parent, dtype=np.int64))
