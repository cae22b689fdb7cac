"""Traced rows -> curves: joining halves, picking and concatenating families, trimming and packing
into a ``CurveSet`` with its ``TraceStats``. Units: mm, radians."""
from __future__ import annotations

import dataclasses

import numpy as np

from ..data.types import CurveEnd, CurveSet, curve_lengths
from ..geometry.mesh_tables import MeshTables
from .integrator import Traces


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
    lengths = curve_lengths(points, offsets)
    curves = CurveSet(
        layer=layer,
        points=points,
        faces=faces,
        bary=bary,
        offsets=offsets,
        lengths_mm=lengths,
        end_reason=traces.end_reason[kept],
        angle=float(angle),
        family="dipole" if layer == "rx" else "field",
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


def packed_rows(tables: MeshTables, rows: list[tuple[np.ndarray, np.ndarray]]) -> dict[str, np.ndarray]:
    """The curves' rows ``(faces, bary)`` packed as the ``CurveSet`` fields ``points`` (mm), ``faces``,
    ``bary``, ``offsets`` and ``lengths_mm``."""
    faces = np.concatenate([f for f, _ in rows]) if rows else np.empty(0, dtype=np.int64)
    bary = np.concatenate([b for _, b in rows]) if rows else np.empty((0, 3))
    offsets = np.concatenate([[0], np.cumsum([len(f) for f, _ in rows])]).astype(np.int64)
    points = tables.points(faces, bary)
    return {"points": points, "faces": faces, "bary": bary, "offsets": offsets,
            "lengths_mm": curve_lengths(points, offsets)}


def joined(own: CurveSet, extra: CurveSet, extra_limb: np.ndarray) -> CurveSet:
    """``own``'s curves, then ``extra``'s (one layer), with ``limb`` (-1 for ``own``'s curves that had
    none, ``extra_limb`` for the others); ``own``'s Tx lanes keep their parents, the extra curves are none."""
    lane_parent = None if own.lane_parent is None else np.r_[own.lane_parent, np.full(extra.count, -1, dtype=np.int64)]
    limb = np.full(own.count, -1, dtype=np.int64) if own.limb is None else own.limb
    return dataclasses.replace(
        own, points=np.vstack([own.points, extra.points]), faces=np.r_[own.faces, extra.faces],
        bary=np.vstack([own.bary, extra.bary]), offsets=np.r_[own.offsets[:-1], extra.offsets + len(own.points)],
        lengths_mm=np.r_[own.lengths_mm, extra.lengths_mm], end_reason=np.r_[own.end_reason, extra.end_reason],
        lane_parent=lane_parent, limb=np.r_[limb, extra_limb].astype(np.int64))


def reversed_walk(points: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A polyline on the mesh (points, and the face of the segment leaving each; the last point its
    segment's face) walked backwards, in the same convention."""
    return points[::-1], np.r_[faces[:-1][::-1], faces[:1]]


def polyline_rows(tables: MeshTables, points: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rows ``(faces, bary)`` of a polyline in the convention of :func:`reversed_walk`."""
    bary = np.clip(tables.bary_of_points(faces, points), 0.0, 1.0)
    return faces, bary / bary.sum(axis=1, keepdims=True)


def reversed_rows(tables: MeshTables, faces: np.ndarray, bary: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rows of one curve in reverse order, each restated in the face of the segment it now starts."""
    return polyline_rows(tables, *reversed_walk(tables.points(faces, bary), faces))


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
