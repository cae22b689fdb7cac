"""Tx seeding: start angles in the fan of the far vertex and the adaptive reseeding of field lines
through the largest gaps of the family (``angle_sampling="adaptive"``). Angles in radians, lengths in mm."""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..data.types import CurveEnd, CurveSet
from ..geometry.mesh_tables import MeshTables
from ..geometry.triangles import mean_edge_mm
from ..geometry.vertex_distance import VertexDistances
from .assembly import assemble, concat_traces, join_both_ways, pick_curves
from .connection import DirectionField
from .integrator import Traces, across_exit_edge, trace, vertex_face_table

if TYPE_CHECKING:
    from .tracing import TraceTxParams


def vertex_fan(tables: MeshTables, vertex: int) -> tuple[np.ndarray, np.ndarray]:
    """Faces around ``vertex`` in counter-clockwise order and the corner of ``vertex`` in each."""
    faces = tables.faces
    f = int(np.flatnonzero(np.any(faces == vertex, axis=1))[0])
    fan_faces, fan_corners = [], []
    while True:
        k = int(np.flatnonzero(faces[f] == vertex)[0])
        fan_faces.append(f)
        fan_corners.append(k)
        f = int(tables.opposite_face[f, (k + 1) % 3])
        if f == fan_faces[0]:
            break
    return np.asarray(fan_faces), np.asarray(fan_corners)


def fan_sectors(tables: MeshTables, vertex: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The fan of ``vertex`` (:func:`vertex_fan`) and the cumulative corner angles bounding its
    sectors: face ``fan_faces[j]`` spans the intrinsic angles ``cum[j]..cum[j + 1]`` (rad), measured
    counter-clockwise from the edge ``vertex -> faces[fan_faces[0], corner + 1]``; ``cum[-1]`` is the cone angle."""
    fan_faces, fan_corners = vertex_fan(tables, vertex)
    sector = tables.corner_angles[fan_faces, fan_corners]
    return fan_faces, fan_corners, np.concatenate([[0.0], np.cumsum(sector)])


def uniform_angles(cone_angle: float, n_curves: int) -> np.ndarray:
    """``n_curves`` intrinsic angles (rad) at uniform intervals ``(k + 1/2) / n`` of the cone angle."""
    return (np.arange(n_curves) + 0.5) / n_curves * cone_angle


def tx_starts(tables: MeshTables, vertex: int, phi: np.ndarray):
    """First straight segment of each Tx curve from ``vertex`` at the intrinsic angles ``phi`` (rad,
    see :func:`fan_sectors`): prefix rows and the start (face, bary) after it."""
    fan_faces, fan_corners, cum = fan_sectors(tables, vertex)
    phi = np.asarray(phi, dtype=np.float64)
    n_curves = len(phi)
    j = np.clip(np.searchsorted(cum, phi, side="right") - 1, 0, len(fan_faces) - 1)
    f, k = fan_faces[j], fan_corners[j]
    psi = phi - cum[j]
    p_v = tables.vertices[tables.faces[f, k]]
    edge = tables.vertices[tables.faces[f, (k + 1) % 3]] - p_v
    edge /= np.linalg.norm(edge, axis=1)[:, None]
    d = np.cos(psi)[:, None] * edge + np.sin(psi)[:, None] * np.cross(tables.normals[f], edge)
    rows = np.arange(n_curves)
    rate = np.einsum("kij,kj->ki", tables.bary_gradients[f], d)
    start = np.zeros((n_curves, 3))
    start[rows, k] = 1.0
    out = start + (1.0 / -rate[rows, k])[:, None] * rate
    g, _, gb = across_exit_edge(tables, f, k, out)
    return (rows, f, start), g, gb


def fan_angles(tables: MeshTables, vertex: int, points: np.ndarray) -> np.ndarray:
    """Intrinsic angle (rad, :func:`fan_sectors`) of ``points`` (k, 3) lying on faces of the fan of
    ``vertex``, measured in the fan face that holds each point; NaN for points off the fan."""
    fan_faces, fan_corners, cum = fan_sectors(tables, vertex)
    n, s = len(points), len(fan_faces)
    bary = tables.bary_of_points(np.tile(fan_faces, n), np.repeat(points, s, axis=0)).reshape(n, s, 3)
    j = np.argmax(bary.min(axis=2), axis=1)
    phi = np.full(n, np.nan)
    ok = bary.min(axis=2)[np.arange(n), j] > -1e-6
    j = j[ok]
    f, k = fan_faces[j], fan_corners[j]
    p_v = tables.vertices[vertex]
    edge = tables.vertices[tables.faces[f, (k + 1) % 3]] - p_v
    d = points[ok] - p_v
    psi = np.arctan2(np.einsum("kj,kj->k", np.cross(edge, d), tables.normals[f]), np.einsum("kj,kj->k", edge, d))
    phi[ok] = cum[j] + np.clip(psi, 0.0, cum[j + 1] - cum[j])
    return phi


def gap_seeds(points: np.ndarray, gap: np.ndarray, budget: int) -> np.ndarray:
    """Indices of at most ``budget`` seed points for the largest gaps: in decreasing ``gap`` (mm), only
    those with at least half the largest gap, each farther (Euclidean, mm) than its own gap from the
    seeds picked before it, so one seed goes into each hole per round."""
    picked: list[int] = []
    floor = 0.5 * gap.max()
    for i in np.argsort(-gap, kind="stable"):
        if len(picked) == budget or gap[i] < floor or gap[i] <= 0.0:
            break
        if not picked or np.min(np.linalg.norm(points[picked] - points[i], axis=1)) > gap[i]:
            picked.append(int(i))
    return np.asarray(picked, dtype=np.int64)


def tx_traces(params: TraceTxParams, tables: MeshTables, field: DirectionField, phi: np.ndarray, start_region, base, singular) -> Traces:
    """Tx curves from the far vertex at the intrinsic start angles ``phi`` (rad, :func:`fan_sectors`)."""
    prefix, faces, bary = tx_starts(tables, field.start_vertex, phi)
    return trace(
        tables,
        field.face_direction,
        faces,
        bary,
        start_region,
        base,
        singular,
        params.max_steps,
        params.max_face_visits,
        prefix,
        params.slide_sink_edges,
    )


def field_lines_through(
    params: TraceTxParams, tables: MeshTables, field: DirectionField, seed_faces: np.ndarray, seed_bary: np.ndarray, base, singular
) -> tuple[Traces, np.ndarray, np.ndarray]:
    """Tx field lines through seed points, traced against the field and along it to the base, joined
    so that they run along the field (``reversed(backward) + forward``).

    The backward half never slides along sink edges (in the reversed field those are the edges
    where the field diverges, where lines traced forward from the far vertex split): it ends where it
    enters the fan of the far vertex or, for a seed in the shadow of such a split, on the edge where
    the field diverges (a free end; the line does not merge with any other there). Its angle
    (rad, :func:`fan_angles`) is where the same backward line with sliding enters the fan: the order
    of the line among the curves from the far vertex. Returns the lines of the seeds (``ok``, per
    seed) whose sliding backward line reaches the fan without entering the base and whose backward
    half ends in the fan or on a sink edge, and their angles.
    """
    fan_faces, _, _ = fan_sectors(tables, field.start_vertex)
    fan = np.zeros(len(tables.faces), dtype=bool)
    fan[fan_faces] = True
    nothing = np.zeros(len(tables.faces), dtype=bool)
    back = [
        trace(tables, -field.face_direction, seed_faces, seed_bary, nothing, fan, base, params.max_steps, params.max_face_visits, None, s)
        for s in (False, True)
    ]
    last = np.searchsorted(back[1].curve, np.arange(len(seed_faces)), side="right") - 1
    phi = fan_angles(tables, field.start_vertex, tables.points(back[1].faces[last], back[1].bary[last]))
    ok = np.isin(back[0].end_reason, (CurveEnd.BASE, CurveEnd.SINK_EDGE)) & (back[1].end_reason == CurveEnd.BASE) & ~np.isnan(phi)
    if not ok.any():
        return pick_curves(back[0], np.flatnonzero(ok)), phi[ok], ok
    forward = trace(
        tables, field.face_direction, seed_faces[ok], seed_bary[ok], nothing, base, singular, params.max_steps, params.max_face_visits,
        None, params.slide_sink_edges,
    )
    return join_both_ways(tables, pick_curves(back[0], np.flatnonzero(ok)), forward, orient_to_base=False), phi[ok], ok


def gap_distances(solver: VertexDistances, tables: MeshTables, curves: CurveSet, vertices: np.ndarray) -> np.ndarray:
    """Geodesic (heat method) distance in mm from each of ``vertices`` to the nearest vertex of a face
    that ``curves`` run through: the distance to the nearest curve, low by at most about one edge."""
    return solver.compute_distance_multisource(np.unique(tables.faces[curves.faces]))[vertices]


def sensing_face_at(tables: MeshTables, sensing: np.ndarray, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A seed point next to each vertex: in a sensing face incident to it, barycentrics 1/2 at the vertex."""
    ptr, vertex_faces, vertex_corners = vertex_face_table(tables)
    faces, bary = np.empty(len(vertices), dtype=np.int64), np.full((len(vertices), 3), 0.25)
    for i, v in enumerate(vertices):
        around = np.arange(ptr[v], ptr[v + 1])
        r = around[np.argmax(sensing[vertex_faces[around]])]
        faces[i] = vertex_faces[r]
        bary[i, vertex_corners[r]] = 0.5
    return faces, bary


def adaptive_tx_traces(params: TraceTxParams, tables: MeshTables, regions, field: DirectionField, start_region, base, singular) -> Traces:
    """The adaptive Tx family (``angle_sampling="adaptive"``), in the order of its start angles.

    ``round(uniform_share * n_curves)`` curves from the far vertex at uniform angles; then rounds of
    reseeding until ``n_curves`` curves: measure each sensing vertex's geodesic distance to the family
    (:func:`gap_distances`), pick seeds in the largest gaps (:func:`gap_seeds`) and add the field line
    through each (:func:`field_lines_through`). Seeds without a line (traced backwards it enters the
    base, loops or runs out of steps) block their neighbourhood (Euclidean, within half their gap)
    from later seeding, so every round adds a curve or blocks a seed. Stops early when no unblocked
    sensing vertex is farther than the mean edge length from the family.
    """
    _, _, cum = fan_sectors(tables, field.start_vertex)
    phi = uniform_angles(cum[-1], max(1, round(params.uniform_share * params.n_curves)))
    parts = [tx_traces(params, tables, field, phi, start_region, base, singular)]
    solver = VertexDistances(tables.vertices, tables.faces)
    sensing = np.asarray(regions.sensing_faces, dtype=bool)
    vertices = np.unique(tables.faces[sensing])
    points = tables.vertices[vertices]
    blocked = np.zeros(len(vertices), dtype=bool)
    resolution = mean_edge_mm(tables.vertices, tables.faces)
    while len(phi) < params.n_curves:
        curves, _ = assemble(tables, concat_traces(parts), start_region, "tx", 0.0)
        gap = np.where(blocked, 0.0, gap_distances(solver, tables, curves, vertices))
        if gap.max() <= resolution:
            break
        seeds = gap_seeds(points, gap, params.n_curves - len(phi))
        lines, found, ok = field_lines_through(params, tables, field, *sensing_face_at(tables, sensing, vertices[seeds]), base, singular)
        for i in seeds[~ok]:
            blocked |= np.linalg.norm(points - points[i], axis=1) <= 0.5 * gap[i]
        parts.append(lines)
        phi = np.r_[phi, found]
    return pick_curves(concat_traces(parts), np.argsort(phi, kind="stable"))
