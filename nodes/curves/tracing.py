"""``curves.trace_tx`` / ``curves.trace_rx``: integral curves of a trivial-connection field.

Tracing is barycentric and exact for the piecewise-constant field (like geometry-central's
``traceInFaceBarycentric``): in face ``f`` a curve moves along the unit direction ``u_f`` so its
barycentrics change at the constant rate ``dl = G_f u_f`` per mm (``G_f`` = gradients of the
barycentrics). It leaves through the edge whose barycentric reaches 0 first, and the barycentrics of
the exit point carry over to the neighbour. Exit points within ``1e-7`` (barycentric) of a vertex
are nudged along the edge, so a traced curve never passes through a vertex (only sink-edge slides
and the Tx start do). All curves of one family are
stepped together (numpy arrays over the active curves).

Stops (``CurveEnd``):

* ``BASE`` when the curve enters a face of the base region (``base_faces | exclusion_base``) after
  having been outside it;
* ``SINK_EDGE`` when the field of the face across the exit edge points back at that edge (both faces
  point at their shared edge);
* ``SINGULARITY`` when it enters a face with a vertex within ``singularity_stop_mm`` (geodesic) of
  a singularity it ends at (Tx: the base centre; Rx: the dipole), after leaving its start region;
* ``LOOP`` when it enters the same face more than ``max_face_visits`` times;
* ``MAX_STEPS`` when the step budget runs out.

Families:

* **Tx** (field with +1 at the far vertex and the base centre, pointing away from the far vertex):
  with ``angle_sampling="uniform"`` (the paper), ``n_curves`` start directions at uniform intervals
  of the intrinsic angle around the far vertex (``(k + 1/2) / n`` of the cone angle, measured in the
  unfolded one-ring). Each curve goes straight from the vertex across its first face and then
  follows the field, so Tx curves are field lines and do not cross each other. The part inside
  ``exclusion_far`` is trimmed off. Uniform angles leave narrow protrusions away from the far vertex
  empty (measured on the bunny, 170 mm, 19k vertices: the other ear is up to 32 mm from any Tx
  curve, and the layout's coverage radius is 33 mm). ``angle_sampling="adaptive"`` (default)
  starts ``uniform_share * n_curves`` curves at uniform angles and then reseeds, up to ``n_curves``,
  field lines through the sensing points farthest (geodesic) from the family, a few holes per round
  (see :func:`adaptive_tx_traces`); on that bunny every sensing vertex is then within 5 mm
  (Euclidean) of a Tx curve, and the coverage radius of the optimised layouts drops to about 14 mm.
  A reseeded line is traced back against the field without sliding: it starts where it enters the
  far exclusion or, when the seed lies in the shadow of a vertex where the discrete field diverges
  (no line from the far vertex reaches it), on that diverging edge (about 10 % of the curves on the
  bunny). Reseeded lines are field lines too, so the family still has no Tx x Tx crossings; the
  curves are ordered by their angle at the far vertex. Sensing points whose field line comes out of
  the base cannot be reached by Tx curves and stay uncovered.
* **Rx** (dipole field, pointing away from ``base_dipole[0]``): its field lines are loops that leave
  the base, run over the object and return to the base. Seeds lie on the loops' apex line, where the
  field is tangent to the geodesic circles around the dipole (zero set of ``u . grad d``, ``d`` the
  heat-method distance from ``base_dipole[0]``), inside the sensing faces, at equal arc length; the
  same seeds serve every angle. (Seeding on a geodesic ring around the dipole, as the paper
  describes, was measured on the bunny: the dipole's loops are nested, so ring seeds gave mostly
  short loops near the base, mean 45 mm, and 30 % sink-edge stops.) The traced direction in every
  face is the field rotated by ``angle_deg`` about the outward normal (counter-clockwise positive):
  the offset is relative to the field direction, and transport by the trivial connection keeps it
  constant along the curve, so the curves of one angle do not cross each other (except where
  sink-edge slides merge them). Each seed is traced both ways to the base and the halves are joined;
  the curve is oriented to start at the base, and ``end_reason`` tells how its other end stopped.

Sink edges: with ``slide_sink_edges`` (default) a curve meeting a sink edge slides along it, and
along further sink edges, to a vertex it can leave (Filippov sliding; such rows sit on vertices);
without it the curve stops there, as in the paper.

Curves that never leave their start region are dropped (counted in the stats).
"""
from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np
from pydantic import Field

from ...graph.errors import UserError
from ...graph.node import NodeParams, node
from .connection import DirectionField
from ..data.types import CurveEnd, CurveSet, Mesh
from ..geometry.mesh_tables import MeshTables, build_tables

VERTEX_NUDGE = 1e-7  # barycentric distance kept from a vertex at edge crossings


@dataclasses.dataclass(frozen=True)
class TraceStats:
    """What happened while tracing one family (rates are fractions of the traced curves)."""

    layer: str
    angle: float  # radians (Rx offset; 0 for Tx)
    traced: int  # curves started
    kept: int  # curves in the CurveSet (those that left their start region)
    dropped: int  # curves that never left their start region
    end_counts: np.ndarray  # (5,) int64, traced curves per CurveEnd code
    sink_edges: int  # traces stopped at a sink edge
    sink_edge_rate: float  # sink_edges / traced (the paper reports about 3 %)
    sink_hits: int  # sink edges met, including those escaped by sliding
    sink_slides: int
    reached_base_rate: float  # end_reason BASE / traced (Rx: both ends at the base)
    face_steps: int  # total face-to-face steps
    mean_length_mm: float  # over kept curves


@dataclasses.dataclass(frozen=True)
class Traces:
    """Raw traced rows of a family before trimming (flat, grouped by curve)."""

    curve: np.ndarray  # (P,) int64
    faces: np.ndarray  # (P,) int64
    bary: np.ndarray  # (P, 3) float64
    end_reason: np.ndarray  # (C,) int8
    face_steps: int
    sink_hits: int  # sink edges met (slid along or stopped at)
    sink_slides: int  # sink edges escaped by sliding to a vertex


def field_direction(field: DirectionField, tables: MeshTables, angle: float) -> np.ndarray:
    """Unit direction per face: the field rotated by ``angle`` (rad) counter-clockwise about the normal."""
    a = field.face_angle + angle
    return np.cos(a)[:, None] * tables.frame_e1 + np.sin(a)[:, None] * tables.frame_e2


def faces_near(tables: MeshTables, vertex_distance: np.ndarray, radius_mm: float) -> np.ndarray:
    """Faces with a vertex whose (geodesic) ``vertex_distance`` is below ``radius_mm``."""
    return np.any(vertex_distance[tables.faces] < radius_mm, axis=1)


def vertex_face_table(tables: MeshTables) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """CSR-style incidence: faces (and the vertex's corner in them) of vertex v are rows ``ptr[v]:ptr[v+1]``."""
    flat = tables.faces.reshape(-1)
    order = np.argsort(flat, kind="stable")
    ptr = np.searchsorted(flat[order], np.arange(len(tables.vertices) + 1))
    return ptr, order // 3, order % 3


MAX_SLIDE_EDGES = 64  # edges one sink-edge slide may follow before the curve is stopped


def vertex_exit(tables: MeshTables, rate: np.ndarray, vertex_faces, v: int, avoid: tuple[int, ...]):
    """A face incident to ``v`` whose direction points strictly into it from ``v``: ``(face, corner)`` or ``None``."""
    ptr, vf, vc = vertex_faces
    for h, k in zip(vf[ptr[v] : ptr[v + 1]], vc[ptr[v] : ptr[v + 1]]):
        if h not in avoid and rate[h, (k + 1) % 3] > 0.0 and rate[h, (k + 2) % 3] > 0.0:
            return int(h), int(k)
    return None


def next_sink_edge(tables: MeshTables, rate: np.ndarray, direction: np.ndarray, vertex_faces, v: int, came_from: int):
    """The edge ``(v, w)`` both of whose faces point at it and whose directions lean from ``v`` to ``w``.

    Returns ``(w, face, corner of v in face)`` for the steepest such edge, or ``None``.
    """
    ptr, vf, vc = vertex_faces
    best, best_along = None, 0.0
    for h, k in zip(vf[ptr[v] : ptr[v + 1]], vc[ptr[v] : ptr[v + 1]]):
        w = int(tables.faces[h, (k + 1) % 3])  # edge (v, w) is opposite corner k + 2 of h
        if w == came_from:
            continue
        opp = (k + 2) % 3
        h2, c2 = tables.opposite_face[h, opp], tables.opposite_corner[h, opp]
        if rate[h, opp] < 0.0 and rate[h2, c2] < 0.0:
            along = float((direction[h] + direction[h2]) @ (tables.vertices[w] - tables.vertices[v]))
            if along > best_along:
                best, best_along = (w, int(h), int(k)), along
    return best


def slide(
    tables: MeshTables, rate: np.ndarray, direction: np.ndarray, vertex_faces, f: int, exit_corner: int, g: int, base: np.ndarray | None
):
    """Escape from sink edge (f, g) by sliding along sink edges (Filippov sliding).

    The curve slides along the edge to the end both face directions lean toward, then either leaves
    that vertex into an incident face whose direction points strictly into it, or follows the next
    sink edge leaning away from it (at most ``MAX_SLIDE_EDGES`` edges). Returns the rows to record
    for the slid edges after the first (``[(face, bary)]``, each the start of an edge segment), the
    escape state ``(face, bary at the vertex)`` and the vertex restated in the face of the last slid
    edge (the curve's end row if it stops right there); ``None`` when the curve is stuck. A slide
    that would continue along an edge between two ``base`` faces ends there instead (escape ``None``):
    the curve has reached the base.
    """
    a = int(tables.faces[f, (exit_corner + 1) % 3])
    b = int(tables.faces[f, (exit_corner + 2) % 3])
    along = float((direction[f] + direction[g]) @ (tables.vertices[b] - tables.vertices[a]))
    if along == 0.0:
        return None
    v, came_from = (b, a) if along > 0 else (a, b)
    rows: list[tuple[int, np.ndarray]] = []
    seen = {a, b}
    last_face = f
    for _ in range(MAX_SLIDE_EDGES):
        exit_face = vertex_exit(tables, rate, vertex_faces, v, (f, g) if not rows else ())
        if exit_face is not None:
            h, k = exit_face
            at_vertex = np.asarray(tables.faces[last_face] == v, dtype=np.float64)
            return rows, (h, np.eye(3)[k]), (last_face, at_vertex)
        nxt = next_sink_edge(tables, rate, direction, vertex_faces, v, came_from)
        if nxt is None or nxt[0] in seen:
            return None
        w, h, k = nxt
        if base is not None and base[h] and base[tables.opposite_face[h, (k + 2) % 3]]:
            at_vertex = np.asarray(tables.faces[last_face] == v, dtype=np.float64)
            return rows, None, (last_face, at_vertex)
        rows.append((h, np.eye(3)[k]))
        seen.add(w)
        last_face = h
        v, came_from = w, v
    return None


def trace(
    tables: MeshTables,
    direction: np.ndarray,
    start_faces: np.ndarray,
    start_bary: np.ndarray,
    start_region: np.ndarray,
    base_region: np.ndarray,
    singular_region: np.ndarray,
    max_steps: int,
    max_face_visits: int,
    prefix: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    slide_sink_edges: bool = True,
) -> Traces:
    """Trace all curves of a family at once through the per-face unit ``direction`` (m, 3).

    ``start_region``: faces the curves start in (a curve has "left" once it enters a face outside
    it); ``base_region`` / ``singular_region`` stop a curve that has left. ``prefix`` optionally
    gives rows (curve, face, bary) recorded before the start rows. With ``slide_sink_edges`` a
    curve reaching a sink edge slides along sink edges until it can leave a vertex (see :func:`slide`).
    """
    n = len(start_faces)
    rate = np.einsum("fij,fj->fi", tables.bary_gradients, direction)  # d(bary)/d(mm) per face
    opposite_face, opposite_corner = tables.opposite_face, tables.opposite_corner
    visits = np.zeros((n, len(tables.faces)), dtype=np.uint8)
    end_reason = np.full(n, CurveEnd.MAX_STEPS, dtype=np.int8)

    cid = np.arange(n)
    face = np.asarray(start_faces, dtype=np.int64).copy()
    bary = np.asarray(start_bary, dtype=np.float64).copy()
    left = ~start_region[face]
    visits[cid, face] = 1
    rec_curve, rec_face, rec_bary = ([prefix[0]], [prefix[1]], [prefix[2]]) if prefix else ([], [], [])
    rec_curve.append(cid.copy())
    rec_face.append(face.copy())
    rec_bary.append(bary.copy())
    steps = sinks = slides = 0
    vertex_faces = vertex_face_table(tables) if slide_sink_edges else None
    for _ in range(max_steps):
        if len(cid) == 0:
            break
        k = len(cid)
        rows = np.arange(k)
        dl = rate[face]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(dl < 0.0, bary / -dl, np.inf)
        exit_corner = np.argmin(t, axis=1)
        tt = t[rows, exit_corner]
        out = bary + tt[:, None] * dl
        out[rows, exit_corner] = 0.0
        np.maximum(out, VERTEX_NUDGE, out=out)
        out[rows, exit_corner] = 0.0
        out /= out.sum(axis=1, keepdims=True)

        nxt = opposite_face[face, exit_corner]
        c = opposite_corner[face, exit_corner]
        nb = np.empty_like(out)
        nb[rows, c] = 0.0
        nb[rows, (c + 1) % 3] = out[rows, (exit_corner + 2) % 3]
        nb[rows, (c + 2) % 3] = out[rows, (exit_corner + 1) % 3]
        steps += k

        sink = rate[nxt, c] <= 0.0
        sinks += int(np.count_nonzero(sink))
        extra = []
        slid_to_base = np.zeros(k, dtype=bool)
        if slide_sink_edges:
            for r in np.flatnonzero(sink):
                escape = slide(
                    tables, rate, direction, vertex_faces, int(face[r]), int(exit_corner[r]), int(nxt[r]), base_region if left[r] else None
                )
                if escape is not None:
                    extra.append((cid[r], face[r], out[r].copy()))
                    extra.extend((cid[r], h, bary) for h, bary in escape[0])
                    if escape[1] is None:
                        slid_to_base[r] = True
                    else:
                        nxt[r], nb[r] = escape[1]
                    face[r], out[r] = escape[2]
                    sink[r] = False
                    slides += 1
        visits[cid, nxt] += 1
        base = (left & base_region[nxt]) | slid_to_base
        singular = left & singular_region[nxt] & ~base
        loop = visits[cid, nxt] > max_face_visits
        reason = np.full(k, -1, dtype=np.int8)
        reason[loop] = CurveEnd.LOOP
        reason[singular] = CurveEnd.SINGULARITY
        reason[sink] = CurveEnd.SINK_EDGE
        reason[base] = CurveEnd.BASE
        stop = reason >= 0
        go = ~stop

        end_reason[cid[stop]] = reason[stop]
        if extra:
            rec_curve.append(np.array([e[0] for e in extra]))
            rec_face.append(np.array([e[1] for e in extra]))
            rec_bary.append(np.array([e[2] for e in extra]))
        rec_curve.append(cid[stop])
        rec_face.append(face[stop])
        rec_bary.append(out[stop])
        rec_curve.append(cid[go])
        rec_face.append(nxt[go])
        rec_bary.append(nb[go])

        cid, face, bary = cid[go], nxt[go], nb[go]
        left = left[go] | ~start_region[face]
    curve = np.concatenate(rec_curve)
    order = np.argsort(curve, kind="stable")
    faces = np.concatenate(rec_face)[order]
    barys = np.concatenate(rec_bary)[order]
    curve = curve[order]
    if len(cid):
        # curves out of steps end on an edge stored in the next face: restate it in the last segment's face
        last = np.searchsorted(curve, cid, side="right") - 1
        points = tables.points(faces[last], barys[last])
        faces[last] = faces[last - 1]
        barys[last] = tables.bary_of_points(faces[last], points)
    return Traces(curve=curve, faces=faces, bary=barys, end_reason=end_reason, face_steps=steps, sink_hits=sinks, sink_slides=slides)


def assemble(
    tables: MeshTables, traces: Traces, start_region: np.ndarray, layer: str, angle: float
) -> tuple[CurveSet, TraceStats]:
    """Trim each curve's leading rows inside ``start_region`` and pack the kept curves into a ``CurveSet``."""
    n = len(traces.end_reason)
    bounds = np.searchsorted(traces.curve, np.arange(n + 1))
    outside = ~start_region[traces.faces]
    # first row outside the start region, per curve
    first = np.full(n, -1, dtype=np.int64)
    idx = np.flatnonzero(outside)
    cur = traces.curve[idx]
    uniq, pos = np.unique(cur, return_index=True)
    first[uniq] = idx[pos]
    keep_curve = (first >= 0) & (first < bounds[1:] - 1)  # at least one segment left
    keep_row = np.zeros(len(traces.curve), dtype=bool)
    for c in np.flatnonzero(keep_curve):
        keep_row[first[c] : bounds[c + 1]] = True
    kept = np.flatnonzero(keep_curve)
    faces = traces.faces[keep_row]
    bary = traces.bary[keep_row]
    counts = np.bincount(traces.curve[keep_row], minlength=n)[kept]
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    points = tables.points(faces, bary)
    row_curve = np.repeat(np.arange(len(kept)), counts)
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    within = row_curve[1:] == row_curve[:-1]
    lengths = np.bincount(row_curve[:-1][within], weights=seg[within], minlength=len(kept))
    curves = CurveSet(
        layer=layer,
        points=points,
        faces=faces,
        bary=bary,
        offsets=offsets,
        lengths_mm=lengths,
        end_reason=traces.end_reason[kept],
        angle=float(angle),
    )
    end_counts = np.bincount(traces.end_reason, minlength=len(CurveEnd)).astype(np.int64)
    stats = TraceStats(
        layer=layer,
        angle=float(angle),
        traced=n,
        kept=len(kept),
        dropped=n - len(kept),
        end_counts=end_counts,
        sink_edges=int(end_counts[CurveEnd.SINK_EDGE]),
        sink_edge_rate=float(end_counts[CurveEnd.SINK_EDGE] / max(n, 1)),
        sink_hits=traces.sink_hits,
        sink_slides=traces.sink_slides,
        reached_base_rate=float(end_counts[CurveEnd.BASE] / max(n, 1)),
        face_steps=traces.face_steps,
        mean_length_mm=float(lengths.mean()) if len(kept) else 0.0,
    )
    return curves, stats


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
    out[rows, k] = 0.0
    np.maximum(out, VERTEX_NUDGE, out=out)
    out[rows, k] = 0.0
    out /= out.sum(axis=1, keepdims=True)
    g = tables.opposite_face[f, k]
    c = tables.opposite_corner[f, k]
    gb = np.zeros_like(out)
    gb[rows, (c + 1) % 3] = out[rows, (k + 2) % 3]
    gb[rows, (c + 2) % 3] = out[rows, (k + 1) % 3]
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


def zero_set(tables: MeshTables, values: np.ndarray, faces_allowed: np.ndarray):
    """Zero level set of piecewise-linear vertex ``values`` inside ``faces_allowed``, as chained segments.

    Returns per segment (in chain order): face (s,), end points ``p``, ``q`` (s, 3).
    """
    faces = tables.faces
    d = values[faces]
    fidx = np.flatnonzero((d.min(axis=1) < 0.0) & (d.max(axis=1) > 0.0) & faces_allowed)
    dd = d[fidx]
    pts, eids = [], []
    for i in range(3):
        a, b = (i + 1) % 3, (i + 2) % 3
        da, db = dd[:, a], dd[:, b]
        hit = (da < 0.0) != (db < 0.0)
        t = np.where(hit, -da / np.where(hit, db - da, 1.0), 0.0)
        pa = tables.vertices[faces[fidx, a]]
        pb = tables.vertices[faces[fidx, b]]
        pts.append(pa + t[:, None] * (pb - pa))
        eids.append(np.where(hit, tables.face_edges[fidx, (i + 1) % 3], -1))
    pts = np.stack(pts, axis=1)
    eids = np.stack(eids, axis=1)
    two = np.argsort(eids < 0, axis=1, kind="stable")[:, :2]
    rows = np.arange(len(fidx))
    p, q = pts[rows, two[:, 0]], pts[rows, two[:, 1]]
    ep, eq = eids[rows, two[:, 0]], eids[rows, two[:, 1]]
    # orient every segment so that values increase to its left (N x (q - p) . grad > 0)
    grad = np.einsum("kij,ki->kj", tables.bary_gradients[fidx], dd)
    flip = np.einsum("kj,kj->k", np.cross(tables.normals[fidx], q - p), grad) < 0
    p, q = np.where(flip[:, None], q, p), np.where(flip[:, None], p, q)
    ep, eq = np.where(flip, eq, ep), np.where(flip, ep, eq)
    # chains: the segment starting on edge eq follows; start chains at segments nothing leads into
    by_start = {int(e): s for s, e in enumerate(ep)}
    has_pred = np.isin(ep, eq)
    order, seen = [], np.zeros(len(fidx), dtype=bool)
    for s0 in np.r_[np.flatnonzero(~has_pred), np.flatnonzero(has_pred)]:
        s = int(s0)
        while not seen[s]:
            seen[s] = True
            order.append(s)
            s = by_start.get(int(eq[s]), s)
    order = np.asarray(order, dtype=np.int64)
    return fidx[order], p[order], q[order]


def rx_seeds(tables: MeshTables, field: DirectionField, sensing: np.ndarray, n_curves: int):
    """Seeds on the apex line of the dipole loops: where the field is tangent to the geodesic circles
    around the dipole source (``u . grad d = 0``), inside the sensing faces, at equal arc length."""
    grad = np.einsum("fij,fi->fj", tables.bary_gradients, field.start_distance[tables.faces])
    radial = np.einsum("fj,fj->f", field.face_direction, grad)
    weights = np.zeros(len(tables.vertices))
    np.add.at(weights, tables.faces.reshape(-1), np.repeat(tables.areas, 3))
    vertex_value = np.zeros(len(tables.vertices))
    np.add.at(vertex_value, tables.faces.reshape(-1), np.repeat(radial * tables.areas, 3))
    vertex_value /= weights
    seg_face, p, q = zero_set(tables, vertex_value, sensing)
    if len(seg_face) == 0:
        raise UserError("the Rx dipole field has no loop apex inside the sensing region: check the base region and dipole")
    length = np.linalg.norm(q - p, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(length)])
    target = (np.arange(n_curves) + 0.5) / n_curves * cum[-1]
    j = np.clip(np.searchsorted(cum, target, side="right") - 1, 0, len(length) - 1)
    frac = np.clip((target - cum[j]) / np.where(length[j] > 0, length[j], 1.0), 0.0, 1.0)
    points = p[j] + frac[:, None] * (q[j] - p[j])
    faces = seg_face[j]
    bary = np.maximum(tables.bary_of_points(faces, points), 1e-6)
    return faces, bary / bary.sum(axis=1, keepdims=True)


def reversed_rows(tables: MeshTables, faces: np.ndarray, bary: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rows of one curve in reverse order, each restated in the face of the segment it now starts."""
    points = tables.points(faces, bary)[::-1]
    rev_faces = np.r_[faces[:-1][::-1], faces[:1]]
    rev_bary = np.clip(tables.bary_of_points(rev_faces, points), 0.0, 1.0)
    return rev_faces, rev_bary / rev_bary.sum(axis=1, keepdims=True)


def join_both_ways(tables: MeshTables, backward: Traces, forward: Traces, orient_to_base: bool = True) -> Traces:
    """Curves through their seeds: ``reversed(backward) + forward``, oriented to start at the base.

    With ``orient_to_base``, a curve whose backward half stopped elsewhere but whose forward half
    reached the base is reversed as a whole; ``end_reason`` then describes the end away from the start.
    """
    n = len(forward.end_reason)
    bb = np.searchsorted(backward.curve, np.arange(n + 1))
    fb = np.searchsorted(forward.curve, np.arange(n + 1))
    parts_curve, parts_face, parts_bary = [], [], []
    end_reason = np.empty(n, dtype=np.int8)
    for c in range(n):
        rev_faces, rev_bary = reversed_rows(tables, backward.faces[bb[c] : bb[c + 1]], backward.bary[bb[c] : bb[c + 1]])
        faces = np.r_[rev_faces[:-1], forward.faces[fb[c] : fb[c + 1]]]
        bary = np.r_[rev_bary[:-1], forward.bary[fb[c] : fb[c + 1]]]
        back_end, fwd_end = backward.end_reason[c], forward.end_reason[c]
        if orient_to_base and back_end != CurveEnd.BASE and fwd_end == CurveEnd.BASE:
            faces, bary = reversed_rows(tables, faces, bary)
            fwd_end = back_end
        end_reason[c] = fwd_end
        parts_curve.append(np.full(len(faces), c, dtype=np.int64))
        parts_face.append(faces)
        parts_bary.append(bary)
    return Traces(
        curve=np.concatenate(parts_curve),
        faces=np.concatenate(parts_face),
        bary=np.concatenate(parts_bary),
        end_reason=end_reason,
        face_steps=backward.face_steps + forward.face_steps,
        sink_hits=backward.sink_hits + forward.sink_hits,
        sink_slides=backward.sink_slides + forward.sink_slides,
    )


class TraceTxParams(NodeParams):
    n_curves: int = Field(100, ge=1, description="Tx curves (at most this many with adaptive angle sampling)")
    angle_sampling: Literal["uniform", "adaptive"] = Field(
        "adaptive", description="start angles at the far vertex: uniform, or uniform then reseeded through the largest gaps"
    )
    uniform_share: float = Field(0.5, gt=0, le=1, description="adaptive: share of n_curves started at uniform angles (1: uniform)")
    singularity_stop_mm: float = Field(3.0, gt=0, description="stop within this geodesic distance (mm) of the base centre")
    max_steps: int = Field(20000, ge=1, description="face steps per family before giving up")
    max_face_visits: int = Field(3, ge=1, description="loop guard: a curve may enter a face this many times")
    slide_sink_edges: bool = Field(True, description="slide along sink edges instead of stopping there (the paper stops)")


class TraceRxParams(NodeParams):
    angle_deg: float = Field(0.0, ge=-90, le=90, description="offset of the traced direction from the field (deg, CCW)")
    n_curves: int = Field(100, ge=1, description="Rx curves per angle")
    singularity_stop_mm: float = Field(3.0, gt=0, description="stop within this geodesic distance (mm) of the dipole")
    max_steps: int = Field(20000, ge=1, description="face steps per family before giving up")
    max_face_visits: int = Field(3, ge=1, description="loop guard: a curve may enter a face this many times")
    slide_sink_edges: bool = Field(True, description="slide along sink edges instead of stopping there (the paper stops)")


def base_region_of(regions) -> np.ndarray:
    return np.asarray(regions.base_faces, dtype=bool) | np.asarray(regions.exclusion_base, dtype=bool)


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


def concat_traces(parts: list[Traces]) -> Traces:
    """One family from several, curves renumbered consecutively in the order given."""
    counts = np.cumsum([0] + [len(p.end_reason) for p in parts])
    return Traces(
        curve=np.concatenate([p.curve + c for p, c in zip(parts, counts)]),
        faces=np.concatenate([p.faces for p in parts]),
        bary=np.concatenate([p.bary for p in parts]),
        end_reason=np.concatenate([p.end_reason for p in parts]),
        face_steps=sum(p.face_steps for p in parts),
        sink_hits=sum(p.sink_hits for p in parts),
        sink_slides=sum(p.sink_slides for p in parts),
    )


def pick_curves(traces: Traces, order: np.ndarray) -> Traces:
    """The curves ``order`` (indices, a subset in any order) of a family; curve ``order[i]`` becomes ``i``."""
    rank = np.full(len(traces.end_reason), -1, dtype=np.int64)
    rank[order] = np.arange(len(order))
    curve = rank[traces.curve]
    rows = np.flatnonzero(curve >= 0)
    rows = rows[np.argsort(curve[rows], kind="stable")]
    return dataclasses.replace(
        traces, curve=curve[rows], faces=traces.faces[rows], bary=traces.bary[rows], end_reason=traces.end_reason[order]
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


def gap_distances(solver, tables: MeshTables, curves: CurveSet, vertices: np.ndarray) -> np.ndarray:
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

    ``uniform_share`` measured on the bunny (170 mm, 19k vertices, bench/layout.py sweep): 0.25 / 0.5
    / 0.75 give Voronoi CV 0.270 / 0.285 / 0.263 at the chosen Rx angle and 0.317 / 0.318 / 0.304
    averaged over the ten angles other than -10 deg (uniform sampling: 0.378 and 0.369); small next to
    the spread of the chosen CV between reseeding variants of equal coverage (0.25 to 0.30), so not
    tuned further. The largest Euclidean gap is 6.1 / 4.9 / 5.3 mm.
    """
    import potpourri3d as pp3d  # heavy: imported when used, not on node discovery

    _, _, cum = fan_sectors(tables, field.start_vertex)
    phi = uniform_angles(cum[-1], max(1, round(params.uniform_share * params.n_curves)))
    parts = [tx_traces(params, tables, field, phi, start_region, base, singular)]
    solver = pp3d.MeshHeatMethodDistanceSolver(tables.vertices, tables.faces)
    sensing = np.asarray(regions.sensing_faces, dtype=bool)
    vertices = np.unique(tables.faces[sensing])
    points = tables.vertices[vertices]
    blocked = np.zeros(len(vertices), dtype=bool)
    edges = tables.vertices[tables.faces] - tables.vertices[np.roll(tables.faces, 1, axis=1)]
    resolution = float(np.mean(np.linalg.norm(edges, axis=2)))
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


def trace_tx_curves(params: TraceTxParams, tables: MeshTables, regions, field: DirectionField) -> tuple[CurveSet, TraceStats]:
    if field.layer != "tx":
        raise UserError(f"curves.trace_tx needs the tx field, got the {field.layer} field: wire curves.connection with layer: tx")
    base = base_region_of(regions)
    start_region = np.asarray(regions.exclusion_far, dtype=bool) & ~base
    singular = faces_near(tables, field.stop_distance, params.singularity_stop_mm)
    if params.angle_sampling == "uniform":
        _, _, cum = fan_sectors(tables, field.start_vertex)
        traces = tx_traces(params, tables, field, uniform_angles(cum[-1], params.n_curves), start_region, base, singular)
    else:
        traces = adaptive_tx_traces(params, tables, regions, field, start_region, base, singular)
    return assemble(tables, traces, start_region, "tx", 0.0)


def trace_rx_curves(params: TraceRxParams, tables: MeshTables, regions, field: DirectionField) -> tuple[CurveSet, TraceStats]:
    if field.layer != "rx":
        raise UserError(f"curves.trace_rx needs the rx field, got the {field.layer} field: wire curves.connection with layer: rx")
    base = base_region_of(regions)
    sensing = ~base & ~np.asarray(regions.exclusion_far, dtype=bool)
    faces, bary = rx_seeds(tables, field, sensing, params.n_curves)
    angle = float(np.radians(params.angle_deg))
    direction = field_direction(field, tables, angle)
    singular = faces_near(tables, field.stop_distance, params.singularity_stop_mm)
    nothing = np.zeros(len(tables.faces), dtype=bool)
    halves = [
        trace(
            tables, sign * direction, faces, bary, nothing, base, singular, params.max_steps, params.max_face_visits, None, params.slide_sink_edges
        )
        for sign in (-1.0, 1.0)
    ]
    return assemble(tables, join_both_ways(tables, *halves), nothing, "rx", angle)


@node("curves.trace_tx", params=TraceTxParams, inputs=("mesh", "regions", "field"), outputs=("curves", "stats"))
def trace_tx(params: TraceTxParams, mesh: Mesh, regions, field: DirectionField) -> dict[str, object]:
    """Tx curves: field lines from the far vertex (uniform angles, then reseeded into the largest gaps
    with the default ``angle_sampling="adaptive"``), trimmed at the far exclusion, ending at the base."""
    curves, stats = trace_tx_curves(params, build_tables(mesh.vertices, mesh.faces), regions, field)
    return {"curves": curves, "stats": stats}


@node("curves.trace_rx", params=TraceRxParams, inputs=("mesh", "regions", "field"), outputs=("curves", "stats"))
def trace_rx(params: TraceRxParams, mesh: Mesh, regions, field: DirectionField) -> dict[str, object]:
    """Rx curves of one angle offset: dipole loops through seeds on their apex line, from the base to the base."""
    curves, stats = trace_rx_curves(params, build_tables(mesh.vertices, mesh.faces), regions, field)
    return {"curves": curves, "stats": stats}
