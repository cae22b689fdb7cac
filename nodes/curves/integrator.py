"""Barycentric integration of a piecewise-constant direction field (the tracing core of ``curves.trace_*``).

In face ``f`` a curve moves along the unit direction ``u_f`` so its barycentrics change at the
constant rate ``dl = G_f u_f`` per mm (``G_f`` = gradients of the barycentrics). It leaves through
the edge whose barycentric reaches 0 first, and the barycentrics of the exit point carry over to
the neighbour (like geometry-central's ``traceInFaceBarycentric``). Exit points within ``1e-7``
(barycentric) of a vertex are nudged along the edge, so a traced curve never passes through a
vertex (only sink-edge slides and the Tx start do). All curves of one family are stepped together
(numpy arrays over the active curves). Stop rules: :mod:`retrotouch.nodes.curves.tracing`.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..data.types import CurveEnd
from ..geometry.mesh_tables import MeshTables
from .connection import DirectionField

VERTEX_NUDGE = 1e-7  # barycentric distance kept from a vertex at edge crossings


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
    the curve has reached the base; an edge between a base face and another is recorded in the other.
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
        across = int(tables.opposite_face[h, (k + 2) % 3])
        if base is not None and base[h]:
            if base[across]:
                at_vertex = np.asarray(tables.faces[last_face] == v, dtype=np.float64)
                return rows, None, (last_face, at_vertex)
            h, k = across, int(np.flatnonzero(tables.faces[across] == v)[0])
        rows.append((h, np.eye(3)[k]))
        seen.add(w)
        last_face = h
        v, came_from = w, v
    return None


def exit_step(rate: np.ndarray, tables: MeshTables, face: np.ndarray, bary: np.ndarray):
    """One face step of every active curve along its face's constant barycentric ``rate`` (per mm).

    Returns the exit corner (the corner opposite the exit edge), the exit barycentrics in ``face``
    (nudged off vertices), the face across the exit edge, the exit edge's corner there and the exit
    barycentrics restated in that face.
    """
    rows = np.arange(len(face))
    dl = rate[face]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(dl < 0.0, bary / -dl, np.inf)
    exit_corner = np.argmin(t, axis=1)
    tt = t[rows, exit_corner]
    out = bary + tt[:, None] * dl
    nxt, c, nb = across_exit_edge(tables, face, exit_corner, out)
    return exit_corner, out, nxt, c, nb


def across_exit_edge(tables: MeshTables, face: np.ndarray, exit_corner: np.ndarray, out: np.ndarray):
    """Exit barycentrics ``out`` (k, 3) in ``face`` on the edge opposite ``exit_corner``: nudged off
    vertices and renormalised in place, then restated in the face across that edge. Returns that
    face, the exit edge's corner there and the barycentrics there."""
    rows = np.arange(len(face))
    out[rows, exit_corner] = 0.0
    np.maximum(out, VERTEX_NUDGE, out=out)
    out[rows, exit_corner] = 0.0
    out /= out.sum(axis=1, keepdims=True)
    nxt = tables.opposite_face[face, exit_corner]
    c = tables.opposite_corner[face, exit_corner]
    nb = np.zeros_like(out)
    nb[rows, (c + 1) % 3] = out[rows, (exit_corner + 2) % 3]
    nb[rows, (c + 2) % 3] = out[rows, (exit_corner + 1) % 3]
    return nxt, c, nb


def slide_sinks(tables, rate, direction, vertex_faces, base_region, state, sink, left):
    """Let the curves at a sink edge (``sink``, per active curve) slide (:func:`slide`), in place.

    ``state`` is ``(cid, face, out, exit_corner, nxt, nb)`` of the step; a curve that escapes gets
    its new face/barycentrics in ``nxt``/``nb`` and its slid end in ``face``/``out``, and ``sink``
    is cleared for it. Returns the extra rows ``[(curve, face, bary)]``, the curves that slid into
    the base and the number of slides.
    """
    cid, face, out, exit_corner, nxt, nb = state
    extra = []
    slid_to_base = np.zeros(len(cid), dtype=bool)
    slides = 0
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
    return extra, slid_to_base, slides


def stop_reasons(base: np.ndarray, singular: np.ndarray, looped: np.ndarray, sink: np.ndarray) -> np.ndarray:
    """``CurveEnd`` code per active curve from its stop masks, -1 for those that go on (base wins,
    then sink edge, then singularity, then loop)."""
    reason = np.full(len(base), -1, dtype=np.int8)
    reason[looped] = CurveEnd.LOOP
    reason[singular] = CurveEnd.SINGULARITY
    reason[sink] = CurveEnd.SINK_EDGE
    reason[base] = CurveEnd.BASE
    return reason


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
    visits = np.zeros((n, len(tables.faces)), dtype=np.uint8)
    end_reason = np.full(n, CurveEnd.MAX_STEPS, dtype=np.int8)

    cid = np.arange(n)
    face = np.asarray(start_faces, dtype=np.int64).copy()
    bary = np.asarray(start_bary, dtype=np.float64).copy()
    left = ~start_region[face]
    visits[cid, face] = 1
    rows = RowRecorder(prefix)
    rows.add(cid.copy(), face.copy(), bary.copy())
    steps = sinks = slides = 0
    vertex_faces = vertex_face_table(tables) if slide_sink_edges else None
    for _ in range(max_steps):
        if len(cid) == 0:
            break
        exit_corner, out, nxt, c, nb = exit_step(rate, tables, face, bary)
        steps += len(cid)
        sink = rate[nxt, c] <= 0.0
        sinks += int(np.count_nonzero(sink))
        extra, slid_to_base = [], np.zeros(len(cid), dtype=bool)
        if slide_sink_edges:
            state = (cid, face, out, exit_corner, nxt, nb)
            extra, slid_to_base, slid = slide_sinks(tables, rate, direction, vertex_faces, base_region, state, sink, left)
            slides += slid
        visits[cid, nxt] += 1
        base = (left & base_region[nxt]) | slid_to_base
        reason = stop_reasons(base, left & singular_region[nxt] & ~base, visits[cid, nxt] > max_face_visits, sink)
        stop = reason >= 0
        go = ~stop
        end_reason[cid[stop]] = reason[stop]
        if extra:
            rows.add(np.array([e[0] for e in extra]), np.array([e[1] for e in extra]), np.array([e[2] for e in extra]))
        rows.add(cid[stop], face[stop], out[stop])
        rows.add(cid[go], nxt[go], nb[go])
        cid, face, bary = cid[go], nxt[go], nb[go]
        left = left[go] | ~start_region[face]
    curve, faces, barys = rows.by_curve(tables, unfinished=cid)
    return Traces(curve=curve, faces=faces, bary=barys, end_reason=end_reason, face_steps=steps, sink_hits=sinks, sink_slides=slides)


class RowRecorder:
    """Rows (curve, face, bary) recorded while tracing, in recording order."""

    def __init__(self, prefix: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None):
        self.curve, self.face, self.bary = ([prefix[0]], [prefix[1]], [prefix[2]]) if prefix else ([], [], [])

    def add(self, curve: np.ndarray, face: np.ndarray, bary: np.ndarray) -> None:
        self.curve.append(curve)
        self.face.append(face)
        self.bary.append(bary)

    def by_curve(self, tables: MeshTables, unfinished: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The rows grouped by curve (stable); the ``unfinished`` curves (out of steps) end on an edge
        stored in the next face, which is restated in the face of their last segment."""
        curve = np.concatenate(self.curve)
        order = np.argsort(curve, kind="stable")
        faces = np.concatenate(self.face)[order]
        barys = np.concatenate(self.bary)[order]
        curve = curve[order]
        if len(unfinished):
            last = np.searchsorted(curve, unfinished, side="right") - 1
            points = tables.points(faces[last], barys[last])
            faces[last] = faces[last - 1]
            barys[last] = tables.bary_of_points(faces[last], points)
        return curve, faces, barys
