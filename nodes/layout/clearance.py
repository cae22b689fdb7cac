"""Same-layer clearance of traces on the object, measured on their centre lines.

Two traces of one layer of width ``w`` with an edge-to-edge clearance ``c`` need their centre lines
at least ``w + c`` apart. Distances are Euclidean between points of the centre-line polylines (a
lower bound of the geodesic distance, and what shorts two strips), counted only on segments that
run through ``face_mask`` (the sensing region). Polylines are resampled at the midpoints of pieces
at most ``step_mm`` long; a sampled distance exceeds the true one by at most ``step_mm``, so
:func:`close_pairs` widens its radius by one step (conservative: it may flag a pair up to one step
beyond the bound, never miss one). Units: mm.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..data.types import CurveSet

CONFLICT_STEP_MM = 0.25  # resampling of candidate curves for the conflict pairs
MEASURE_STEP_MM = 0.1  # resampling of selected traces for the reported clearance


def row_arcs(curves: CurveSet) -> np.ndarray:
    """(P,) arc length (mm) of every row from its curve's first row."""
    seg = np.linalg.norm(np.diff(curves.points, axis=0), axis=1)
    row_curve = np.repeat(np.arange(curves.count), np.diff(curves.offsets))
    seg = np.where(row_curve[1:] == row_curve[:-1], seg, 0.0)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    return cum - cum[curves.offsets[:-1]][row_curve]


def resample(curves: CurveSet, face_mask: np.ndarray, step_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Midpoints of pieces at most ``step_mm`` long of every segment inside ``face_mask``.

    Returns ``(points (P, 3), curve (P,) int64, length (P,) mm each point stands for, arc (P,) mm
    from the curve's start)``. Segment ``j`` of a curve runs from row ``j`` to row ``j + 1`` in face
    ``faces[j]``.
    """
    arcs = row_arcs(curves)
    row_curve = np.repeat(np.arange(curves.count), np.diff(curves.offsets))
    last = np.zeros(len(row_curve), dtype=bool)
    last[curves.offsets[1:] - 1] = True
    inside = ~last & np.asarray(face_mask, dtype=bool)[curves.faces]
    rows = np.flatnonzero(inside)
    if len(rows) == 0:
        return np.empty((0, 3)), np.empty(0, dtype=np.int64), np.empty(0), np.empty(0)
    p, q = curves.points[rows], curves.points[rows + 1]
    length = np.linalg.norm(q - p, axis=1)
    pieces = np.maximum(1, np.ceil(length / step_mm).astype(np.int64))
    seg = np.repeat(np.arange(len(p)), pieces)
    first = np.cumsum(pieces) - pieces
    t = (np.arange(len(seg)) - first[seg] + 0.5) / pieces[seg]
    points = p[seg] + t[:, None] * (q[seg] - p[seg])
    return points, row_curve[rows][seg], (length / pieces)[seg], arcs[rows][seg] + t * length[seg]


def close_pairs(
    curves: CurveSet, face_mask: np.ndarray, bound_mm: float, free_start_mm: float = 0.0, step_mm: float = CONFLICT_STEP_MM
) -> np.ndarray:
    """Distinct ``(P, 2)`` curve pairs (ascending) whose centre lines come closer than ``bound_mm``
    inside ``face_mask`` (conservatively: sampled distance below ``bound_mm + step_mm``), except where
    both points lie in the first ``free_start_mm`` of their curves (free ends, which
    :func:`start_trims` shortens until they have room)."""
    from scipy.spatial import cKDTree  # heavy: imported when used, not on node discovery

    points, curve, _, arc = resample(curves, face_mask, step_mm)
    if len(points) < 2:
        return np.empty((0, 2), dtype=np.int64)
    pairs = cKDTree(points).query_pairs(bound_mm + step_mm, output_type="ndarray")
    a, b = curve[pairs[:, 0]], curve[pairs[:, 1]]
    free = (arc < free_start_mm)[pairs]
    counted = (a != b) & ~(free[:, 0] & free[:, 1])
    key = np.unique(np.minimum(a, b)[counted] * curves.count + np.maximum(a, b)[counted])
    return np.stack([key // curves.count, key % curves.count], axis=1).astype(np.int64)


def clearance_profile(curves: CurveSet, face_mask: np.ndarray, bound_mm: float, step_mm: float = MEASURE_STEP_MM) -> dict:
    """Smallest centre-line distance (mm) between two curves of the family inside ``face_mask``, and
    the length (mm and share of the family's length there) lying closer than ``bound_mm`` to another
    curve. ``None`` distances when fewer than two curves run there."""
    from scipy.spatial import cKDTree

    points, curve, length, _ = resample(curves, face_mask, step_mm)
    nearest = np.full(len(points), np.inf)
    for c in np.unique(curve):
        own = curve == c
        if own.all():
            break
        nearest[own] = cKDTree(points[~own]).query(points[own])[0]
    close = nearest < bound_mm
    total = float(length.sum())
    finite = np.isfinite(nearest)
    return {
        "min_centre_distance_mm": float(nearest[finite].min()) if finite.any() else None,
        "length_closer_than_bound_mm": float(length[close].sum()),
        "share_closer_than_bound": float(length[close].sum() / total) if total > 0 else 0.0,
        "length_in_region_mm": total,
        "bound_mm": float(bound_mm),
    }


def spread_order(n: int) -> np.ndarray:
    """0..n-1 in van der Corput order (0, n/2, n/4, 3n/4, ...): every prefix is spread over the range."""
    bits = max(1, int(np.ceil(np.log2(max(n, 2)))))
    reversed_bits = np.array([int(format(i, f"0{bits}b")[::-1], 2) for i in range(2**bits)])
    return reversed_bits[reversed_bits < n]


def start_trims(curves: CurveSet, face_mask: np.ndarray, bound_mm: float, free_start_mm: float,
                step_mm: float = CONFLICT_STEP_MM) -> np.ndarray:
    """Per curve, the row from which it keeps ``bound_mm`` from the curves kept before it inside
    ``face_mask``: curves are taken in :func:`spread_order` of their index (their angular order at the
    pole), and each is cut after the last point of its first ``free_start_mm`` that comes closer
    (conservatively, below ``bound_mm + step_mm``) to an earlier one, as trimmed. So one curve of each
    converging bundle reaches the pole and the others stop where they have room; 0 = untouched."""
    from scipy.spatial import cKDTree

    points, curve, length, arc = resample(curves, face_mask, step_mm)
    arcs = row_arcs(curves)
    first = np.zeros(curves.count, dtype=np.int64)
    kept = np.zeros(len(points), dtype=bool)
    for c in spread_order(curves.count):
        own = curve == c
        if kept.any():
            zone = own & (arc < free_start_mm)
            near = cKDTree(points[kept]).query(points[zone], distance_upper_bound=bound_mm + step_mm)[0] < np.inf
            if near.any():
                cut = float((arc[zone][near] + 0.5 * length[zone][near]).max())
                lo, hi = int(curves.offsets[c]), int(curves.offsets[c + 1])
                first[c] = min(int(np.searchsorted(arcs[lo:hi], cut)), hi - lo - 2)
        kept |= own & (arc >= arcs[int(curves.offsets[c]) + first[c]])
    return first


def trim_starts(curves: CurveSet, first: np.ndarray) -> tuple[CurveSet, np.ndarray]:
    """The family without the rows before ``first[c]`` of each curve c; returns it and the arc (mm)
    cut from each curve's start (subtract it from crossing arcs; subtract ``first`` from segments)."""
    arcs = row_arcs(curves)
    keep = np.ones(len(curves.faces), dtype=bool)
    cut = np.zeros(curves.count)
    for c in np.flatnonzero(first):
        lo = int(curves.offsets[c])
        keep[lo : lo + int(first[c])] = False
        cut[c] = arcs[lo + int(first[c])]
    counts = np.bincount(np.repeat(np.arange(curves.count), np.diff(curves.offsets))[keep], minlength=curves.count)
    trimmed = dataclasses.replace(
        curves, points=curves.points[keep], faces=curves.faces[keep], bary=curves.bary[keep],
        offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64), lengths_mm=curves.lengths_mm - cut,
    )
    return trimmed, cut
