"""Isometric unfolding of each selected curve's triangle strip into the plane (paper section 7.1).

Conventions (in addition to :mod:`retrotouch.nodes.data.types`):

* Traces are ordered Tx channels first, then Rx channels (the attachment order); trace ``c`` owns
  rows ``offsets[c]:offsets[c + 1]`` of the flat 2D arrays, one row per row of its 3D curve.
* 2D coordinates are in mm and show the surface **seen from outside**: every unfolded face keeps its
  counter-clockwise corner order (positive signed area), so a cut trace laid face-up matches the
  object seen from outside. Each trace is moved so its base end (where the wire is soldered) sits
  at the origin and its far end lies on the +x axis.
* The base end is the curve's last row for Tx (Tx curves run from the far singularity to the base)
  and its first row for Rx (Rx curves start at the base boundary).
* Arc lengths are measured from the curve's start (its first row), as in ``Crossings.arc_a``.
* A *mark* is one crossing seen from one of its two curves: every cell of the layout gives two marks
  (one on its Tx trace, one on its Rx trace). An electrode pad at a pad cell is centred on the trace
  ``pad_offset_mm`` further along the curve's orientation (the routing direction), or at the curve's
  end when the crossing is closer than that to the end.

Unfolding (verified in ``shared/notes/geometry-trivial-connections.md``): the curve's first face is
laid in the plane from its edge lengths, every next face is placed across the edge it shares with
the previous one by the law of cosines, on the side that keeps it counter-clockwise; curve rows map
by their barycentrics. The unfolded polyline therefore has the 3D polyline's length, which is
checked for every trace.
"""
from __future__ import annotations

import dataclasses
from collections import deque

import numpy as np
from pydantic import Field

from ...graph.errors import UserError
from ...graph.node import NodeParams, node
from ..data.types import PAD_RADIUS_MM, TRACE_WIDTH_MM, CurveSet, Layout, Mesh


class Params(NodeParams):
    pad_offset_mm: float = Field(
        3.0, ge=0, description="electrode pad centre offset from the crossing along the routing direction (mm)"
    )
    length_rtol: float = Field(
        1e-6, gt=0, description="largest allowed relative difference between unfolded and 3D trace length"
    )


@dataclasses.dataclass(frozen=True)
class UnfoldedTraces:
    """The selected curves unfolded into the plane (module conventions)."""

    names: tuple[str, ...]  # (C,) "Tx00", ..., "Rx00", ...
    layers: tuple[str, ...]  # (C,) "tx" or "rx"
    channels: np.ndarray  # (C,) int64 channel number within the layer
    points: np.ndarray  # (P, 2) float64, mm
    arc: np.ndarray  # (P,) float64, arc length of each row from the curve's start (mm)
    offsets: np.ndarray  # (C + 1,) int64
    length_3d: np.ndarray  # (C,) float64, 3D polyline length (mm)
    base_at_end: np.ndarray  # (C,) bool, True when the base end is the last row
    mark_trace: np.ndarray  # (K2,) int64 trace carrying the mark
    mark_other: np.ndarray  # (K2,) int64 trace of the other layer crossing there
    mark_cell: np.ndarray  # (K2,) int64 row of ``layout.cells``
    mark_arc: np.ndarray  # (K2,) float64 arc length of the crossing on its trace (mm)
    mark_xy: np.ndarray  # (K2, 2) float64 unfolded crossing position (mm)
    mark_tangent: np.ndarray  # (K2, 2) float64 unit routing direction at the crossing
    mark_pad: np.ndarray  # (K2,) bool electrode pad placed at this crossing
    pad_arc: np.ndarray  # (K2,) float64 arc length of the pad centre (mm)
    pad_xy: np.ndarray  # (K2, 2) float64 pad centre (mm), defined for every mark
    pad_radius_mm: float = PAD_RADIUS_MM  # the layout's pad radius
    trace_width_mm: float = TRACE_WIDTH_MM  # the layout's trace width

    @property
    def count(self) -> int:
        return len(self.names)

    def trace(self, c: int) -> slice:
        """Row slice of trace ``c``."""
        return slice(int(self.offsets[c]), int(self.offsets[c + 1]))


def _edge_faces(faces: np.ndarray) -> dict[tuple[int, int], list[int]]:
    """Undirected edge (lo, hi) -> faces holding it."""
    table: dict[tuple[int, int], list[int]] = {}
    for f, tri in enumerate(faces.tolist()):
        for i in range(3):
            a, b = tri[i], tri[(i + 1) % 3]
            table.setdefault((min(a, b), max(a, b)), []).append(f)
    return table


def _fan_path(faces: np.ndarray, edge_faces: dict, start: int, goal: int, vertex: int) -> list[int]:
    """Shortest chain of faces around ``vertex`` from ``start`` to ``goal`` (both excluded)."""
    previous = {start: start}
    queue = deque([start])
    while queue:
        f = queue.popleft()
        if f == goal:
            break
        for other in faces[f].tolist():
            if other == vertex:
                continue
            for g in edge_faces[(min(vertex, other), max(vertex, other))]:
                if g not in previous:
                    previous[g] = f
                    queue.append(g)
    if goal not in previous:
        return []
    chain = []
    f = previous[goal]
    while f != start:
        chain.append(f)
        f = previous[f]
    return chain[::-1]


def _place_across(vertices, face, known: dict[int, np.ndarray]) -> np.ndarray:
    """2D corners of ``face`` given two of its vertices' 2D positions in ``known`` (law of cosines).

    The third corner goes on the side that keeps the face counter-clockwise in the plane.
    """
    corners = face.tolist()
    free = [i for i in range(3) if corners[i] not in known]
    k = free[0]
    i, j = (k + 1) % 3, (k + 2) % 3  # CCW order: i -> j -> k
    pi, pj = known[corners[i]], known[corners[j]]
    vi, vj, vk = vertices[corners[i]], vertices[corners[j]], vertices[corners[k]]
    edge = pj - pi
    length = np.hypot(*edge)
    di2 = float(np.dot(vk - vi, vk - vi))
    dj2 = float(np.dot(vk - vj, vk - vj))
    along = (di2 - dj2 + length * length) / (2 * length)
    across = np.sqrt(max(di2 - along * along, 0.0))
    unit = edge / length
    normal = np.array([-unit[1], unit[0]])  # left of i -> j: CCW side
    out = np.empty((3, 2))
    out[i], out[j] = pi, pj
    out[k] = pi + along * unit + across * normal
    return out


def _first_face(vertices, face) -> np.ndarray:
    """2D corners of a face with corner 0 at the origin and corner 1 on +x, counter-clockwise."""
    p = vertices[face]
    e1, e2 = p[1] - p[0], p[2] - p[0]
    l1 = np.linalg.norm(e1)
    x2 = float(np.dot(e2, e1) / l1)
    y2 = float(np.linalg.norm(np.cross(e1, e2)) / l1)
    return np.array([[0.0, 0.0], [l1, 0.0], [x2, y2]])


def unfold_curve(mesh: Mesh, curves: CurveSet, c: int, edge_faces: dict, name: str) -> np.ndarray:
    """Unfolded 2D positions (mm) of the rows of curve ``c`` (frame of its first face)."""
    rows = curves.curve(c)
    faces_of_rows = curves.faces[rows]
    bary = curves.bary[rows]
    V, F = mesh.vertices, mesh.faces
    out = np.empty((len(faces_of_rows), 2))
    current = int(faces_of_rows[0])
    corners2d = _first_face(V, F[current])
    for r, f in enumerate(faces_of_rows.tolist()):
        if f != current:
            shared = set(F[current].tolist()) & set(F[f].tolist())
            if len(shared) == 1:
                chain = _fan_path(F, edge_faces, current, f, shared.pop()) + [f]
            elif len(shared) == 2:
                chain = [f]
            else:
                raise UserError(
                    f"{name}: rows {r - 1} and {r} lie in faces {current} and {f} that share no vertex; "
                    "the curve is not a connected face strip — re-run curve tracing"
                )
            for g in chain:
                known = dict(zip(F[current].tolist(), corners2d))
                corners2d = _place_across(V, F[g], known)
                current = g
        out[r] = bary[r] @ corners2d
    return out


def _polyline_length(points: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())


def _normalise(points2d: np.ndarray, base_at_end: bool) -> np.ndarray:
    """Rigidly move a trace so its base end is at the origin and its far end on +x."""
    base, far = (points2d[-1], points2d[0]) if base_at_end else (points2d[0], points2d[-1])
    direction = far - base
    norm = np.hypot(*direction)
    cos, sin = (direction / norm) if norm > 0 else (1.0, 0.0)
    rotation = np.array([[cos, sin], [-sin, cos]])  # rotates `direction` onto +x
    return (points2d - base) @ rotation.T


def point_at_arc(points2d: np.ndarray, arc: np.ndarray, s: float) -> tuple[np.ndarray, np.ndarray]:
    """Point and unit tangent at arc length ``s`` of a polyline; past either end along the end tangent."""
    seg = int(np.clip(np.searchsorted(arc, s, side="right") - 1, 0, len(arc) - 2))
    # skip zero-length segments so the tangent is defined
    lo, hi = seg, seg + 1
    while arc[hi] - arc[lo] <= 0 and hi < len(arc) - 1:
        hi += 1
    while arc[hi] - arc[lo] <= 0 and lo > 0:
        lo -= 1
    d = points2d[hi] - points2d[lo]
    tangent = d / np.hypot(*d)
    return points2d[lo] + (s - arc[lo]) * tangent, tangent


def _segment_fraction(p0: np.ndarray, p1: np.ndarray, q: np.ndarray) -> float:
    """Fraction along the 3D segment p0 -> p1 of the projection of q, clamped to [0, 1]."""
    d = p1 - p0
    dd = float(np.dot(d, d))
    return 0.0 if dd == 0 else float(np.clip(np.dot(q - p0, d) / dd, 0.0, 1.0))


def _unfold_traces(params: Params, mesh: Mesh, layout: Layout):
    """(names, layers, channels, base_at_end, 2D points per trace, arc lengths per trace, 3D lengths)."""
    edge_faces = _edge_faces(mesh.faces)
    traces: dict[str, list] = {k: [] for k in ("name", "layer", "channel", "at_end", "points", "arc", "length3d")}
    for layer, curves, at_end in (("tx", layout.tx, True), ("rx", layout.rx, False)):
        for c in range(curves.count):
            name = f"{layer.capitalize()}{c:02d}"
            rows = curves.curve(c)
            if rows.stop - rows.start < 2:
                raise UserError(f"{name} has fewer than 2 points; drop it from the layout or re-run tracing")
            p3 = np.einsum("rk,rkd->rd", curves.bary[rows], mesh.vertices[mesh.faces[curves.faces[rows]]])
            p2 = _normalise(unfold_curve(mesh, curves, c, edge_faces, name), at_end)
            length2d, length3d = _polyline_length(p2), _polyline_length(p3)
            if abs(length2d - length3d) > params.length_rtol * max(length3d, 1e-12):
                raise UserError(
                    f"{name}: unfolded length {length2d:.6f} mm differs from its 3D length {length3d:.6f} mm "
                    f"(more than length_rtol={params.length_rtol:g}); its rows are not on the edges shared by "
                    "consecutive faces — re-run curve tracing"
                )
            seg_lengths = np.linalg.norm(np.diff(p2, axis=0), axis=1)
            for key, value in zip(traces, (name, layer, c, at_end, p2, np.concatenate([[0.0], np.cumsum(seg_lengths)]),
                                           length3d)):
                traces[key].append(value)
    return traces


def _marks(params: Params, layout: Layout, points: np.ndarray, arcs: np.ndarray, offsets: np.ndarray) -> dict:
    """Per crossing and per curve through it (Tx mark, then Rx mark): the mark fields as lists."""
    cells = layout.cells
    marks: dict[str, list] = {k: [] for k in ("trace", "other", "cell", "arc", "xy", "tangent", "pad", "pad_arc", "pad_xy")}
    for k in range(len(cells.curve_a)):
        tx_trace = int(cells.curve_a[k])
        rx_trace = layout.tx.count + int(cells.curve_b[k])
        for trace, other, curves, channel, seg in (
            (tx_trace, rx_trace, layout.tx, int(cells.curve_a[k]), int(cells.seg_a[k])),
            (rx_trace, tx_trace, layout.rx, int(cells.curve_b[k]), int(cells.seg_b[k])),
        ):
            rows = curves.curve(channel)
            last = rows.stop - rows.start - 1
            seg = min(max(seg, 0), last - 1)
            t = _segment_fraction(curves.points[rows.start + seg], curves.points[rows.start + seg + 1], cells.points[k])
            p2 = points[int(offsets[trace]) : int(offsets[trace + 1])]
            a2 = arcs[int(offsets[trace]) : int(offsets[trace + 1])]
            arc = a2[seg] + t * (a2[seg + 1] - a2[seg])
            xy, tangent = point_at_arc(p2, a2, arc)
            pad_arc = min(arc + params.pad_offset_mm, float(a2[-1]))
            pad_xy, _ = point_at_arc(p2, a2, pad_arc)
            for key, value in zip(marks, (trace, other, k, arc, xy, tangent, bool(layout.pad[k]), pad_arc, pad_xy)):
                marks[key].append(value)
    return marks


@node("fab.unfold", params=Params, inputs=("mesh", "layout"), outputs=("unfolded",))
def unfold(params: Params, mesh: Mesh, layout: Layout) -> UnfoldedTraces:
    """Unfold every selected Tx and Rx curve isometrically into the plane and map its crossings and
    electrode pads to 2D; fails when a trace's unfolded length differs from its 3D length."""
    traces = _unfold_traces(params, mesh, layout)
    points = np.concatenate(traces["points"])
    arcs = np.concatenate(traces["arc"])
    offsets = np.concatenate([[0], np.cumsum([len(p) for p in traces["points"]])]).astype(np.int64)
    marks = _marks(params, layout, points, arcs, offsets)

    def arr(key, dtype, shape):
        return np.asarray(marks[key], dtype=dtype).reshape(shape)

    return UnfoldedTraces(
        names=tuple(traces["name"]),
        layers=tuple(traces["layer"]),
        channels=np.asarray(traces["channel"], dtype=np.int64),
        points=points,
        arc=arcs,
        offsets=offsets,
        length_3d=np.asarray(traces["length3d"]),
        base_at_end=np.asarray(traces["at_end"], dtype=bool),
        mark_trace=arr("trace", np.int64, (-1,)),
        mark_other=arr("other", np.int64, (-1,)),
        mark_cell=arr("cell", np.int64, (-1,)),
        mark_arc=arr("arc", np.float64, (-1,)),
        mark_xy=arr("xy", np.float64, (-1, 2)),
        mark_tangent=arr("tangent", np.float64, (-1, 2)),
        mark_pad=arr("pad", bool, (-1,)),
        pad_arc=arr("pad_arc", np.float64, (-1,)),
        pad_xy=arr("pad_xy", np.float64, (-1, 2)),
        pad_radius_mm=float(layout.pad_radius_mm),
        trace_width_mm=float(layout.trace_width_mm),
    )
