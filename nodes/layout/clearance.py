"""Same-layer clearance of traces on the object, measured on their centre lines.

Two traces of one layer of width ``w`` with an edge-to-edge clearance ``c`` need their centre lines
at least ``w + c`` apart. Distances are Euclidean between points of the centre-line polylines (a
lower bound of the geodesic distance, and what shorts two strips), counted only on segments that
run through ``face_mask`` (the sensing region). Polylines are resampled at the midpoints of pieces
at most ``step_mm`` long; a sampled distance exceeds the true one by at most ``step_mm``, so
:func:`close_pairs` widens its radius by one step (conservative: it may flag a pair up to one step
beyond the bound, never miss one). With a mesh's :class:`ThinWalls`, point pairs on the two sides of a
wall thinner than the bound (apart along the surface: strips on them cannot touch) are not close.
Units: mm.
"""
from __future__ import annotations

import collections
import dataclasses
import threading
from typing import Literal

import numpy as np

from ..data.types import CurveSet, Mesh, row_arcs
from ..geometry.thin_walls import ThinWalls, thin_walls
from .samples import array_digest

CONFLICT_STEP_MM = 0.25  # resampling of candidate curves for the conflict pairs
MEASURE_STEP_MM = 0.1  # resampling of selected traces for the reported clearance
PARALLEL_RUN_MM = 10.0  # a Tx/Rx pair closer than a trace width along more of the Tx line is laid along, not across
FreeEnd = Literal["start", "end"]  # the end of a curve that may be cut back (the other one is wired)
CLOSE_PAIRS_MEMO = 8  # close_pairs results kept per process: every branch of one Tx pole asks for the same Tx pairs
_close_pairs_memo: collections.OrderedDict[str, np.ndarray] = collections.OrderedDict()
_memo_lock = threading.Lock()
_walls_memo: collections.OrderedDict[str, ThinWalls] = collections.OrderedDict()


def walls_for(mesh: Mesh, bound_mm: float) -> ThinWalls:
    """The mesh's :class:`ThinWalls` for the clearance ``bound_mm``: made for pairs up to one conflict
    step further apart (:func:`close_pairs`' radius), kept per process by content (the last two)."""
    radius_mm = bound_mm + CONFLICT_STEP_MM
    key = repr(float(radius_mm)) + array_digest(mesh.vertices, mesh.faces)
    with _memo_lock:
        if key in _walls_memo:
            _walls_memo.move_to_end(key)
            return _walls_memo[key]
    walls = thin_walls(mesh.vertices, mesh.faces, radius_mm)
    with _memo_lock:
        _walls_memo[key] = walls
        while len(_walls_memo) > 2:
            _walls_memo.popitem(last=False)
    return walls


def resample(curves: CurveSet, face_mask: np.ndarray, step_mm: float
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Midpoints of pieces at most ``step_mm`` long of every segment inside ``face_mask``.

    Returns ``(points (P, 3), curve (P,) int64, length (P,) mm each point stands for, arc (P,) mm
    from the curve's start, face (P,) int64)``. Segment ``j`` of a curve runs from row ``j`` to row
    ``j + 1`` in face ``faces[j]``.
    """
    arcs = row_arcs(curves)
    row_curve = np.repeat(np.arange(curves.count), np.diff(curves.offsets))
    last = np.zeros(len(row_curve), dtype=bool)
    last[curves.offsets[1:] - 1] = True
    inside = ~last & np.asarray(face_mask, dtype=bool)[curves.faces]
    rows = np.flatnonzero(inside)
    if len(rows) == 0:
        return np.empty((0, 3)), np.empty(0, dtype=np.int64), np.empty(0), np.empty(0), np.empty(0, dtype=np.int64)
    p, q = curves.points[rows], curves.points[rows + 1]
    length = np.linalg.norm(q - p, axis=1)
    pieces = np.maximum(1, np.ceil(length / step_mm).astype(np.int64))
    seg = np.repeat(np.arange(len(p)), pieces)
    first = np.cumsum(pieces) - pieces
    t = (np.arange(len(seg)) - first[seg] + 0.5) / pieces[seg]
    points = p[seg] + t[:, None] * (q[seg] - p[seg])
    arc = arcs[rows][seg] + t * length[seg]
    return points, row_curve[rows][seg], (length / pieces)[seg], arc, curves.faces[rows][seg].astype(np.int64)


def close_pairs(
    curves: CurveSet, face_mask: np.ndarray, bound_mm: float, free_mm: float = 0.0, free_end: FreeEnd = "start",
    step_mm: float = CONFLICT_STEP_MM, walls: ThinWalls | None = None,
) -> np.ndarray:
    """Distinct ``(P, 2)`` curve pairs (ascending) whose centre lines come closer than ``bound_mm``
    inside ``face_mask`` (conservatively: sampled distance at most ``bound_mm + step_mm``), except where
    both points lie in their curves' free zones: within ``free_mm`` of the ``free_end`` (``"start"`` or
    ``"end"``) and in that half of the curve, which :func:`free_end_trims` shortens until they have room,
    or on the two sides of one of the ``walls`` (made for a radius of at least ``bound_mm + step_mm``).
    Kept per process by content (:data:`CLOSE_PAIRS_MEMO` results), read-only."""
    walls_key = "" if walls is None else repr(walls.radius_mm) + array_digest(walls.vertices, walls.keys)
    memo_key = repr((bound_mm, free_mm, free_end, step_mm)) + walls_key + array_digest(
        curves.points, curves.faces, curves.offsets, np.asarray(face_mask, dtype=bool))
    with _memo_lock:
        if memo_key in _close_pairs_memo:
            _close_pairs_memo.move_to_end(memo_key)
            return _close_pairs_memo[memo_key]
    points, curve, _, arc, face = resample(curves, face_mask, step_mm)
    if len(points) < 2:
        return np.empty((0, 2), dtype=np.int64)
    free = _in_free_zone(curves, curve, arc, free_mm, free_end)
    sides = None if walls is None else (walls, _checked(walls, bound_mm + step_mm).corners_of(face, points))
    key = _close_keys(points, curve, free, bound_mm + step_mm, curves.count, step_mm, sides)
    pairs = np.stack([key // curves.count, key % curves.count], axis=1).astype(np.int64)
    pairs.flags.writeable = False
    with _memo_lock:
        _close_pairs_memo[memo_key] = pairs
        while len(_close_pairs_memo) > CLOSE_PAIRS_MEMO:
            _close_pairs_memo.popitem(last=False)
    return pairs


def _chunks(points: np.ndarray, curve: np.ndarray, size: int, step_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Runs of at most ``size`` consecutive points of one curve without a jump of more than ``step_mm``
    (where the curve leaves the region): (start of each run, its centre (mean), its bounding radius
    about the centre)."""
    jump = np.linalg.norm(np.diff(points, axis=0), axis=1) > step_mm * (1 + 1e-9)
    new_piece = np.concatenate([[True], (curve[1:] != curve[:-1]) | jump])
    piece = np.cumsum(new_piece) - 1
    position = np.arange(len(curve)) - np.flatnonzero(new_piece)[piece]
    starts = np.flatnonzero(new_piece | (position % size == 0))
    counts = np.diff(np.append(starts, len(points)))
    centres = np.add.reduceat(points, starts, axis=0) / counts[:, None]
    offsets = np.linalg.norm(points - np.repeat(centres, counts, axis=0), axis=1)
    return starts, centres, np.maximum.reduceat(offsets, starts)


def _checked(walls: ThinWalls, radius_mm: float) -> ThinWalls:
    if walls.radius_mm < radius_mm - 1e-9:
        raise ValueError(f"thin walls made for {walls.radius_mm} mm cannot judge pairs {radius_mm} mm apart")
    return walls


def _close_keys(points: np.ndarray, curve: np.ndarray, free: np.ndarray, radius: float, count: int,
                step_mm: float, sides: tuple[ThinWalls, np.ndarray] | None, size: int = 16, batch: int = 4096) -> np.ndarray:
    """Sorted keys ``a * count + b`` (a < b) of the curve pairs with two points at most ``radius`` apart
    (Euclidean), not both ``free`` nor apart along the surface by ``sides`` (the walls and every point's
    corner); ``step_mm`` the points' spacing along a curve. Exact: runs of points whose bounding spheres
    come within ``radius`` (and not both wholly free) are compared point by point, nearest runs first,
    skipping curve pairs already found."""
    from scipy.spatial import cKDTree  # heavy: imported when used, not on node discovery

    starts, centres, reach = _chunks(points, curve, size, step_mm)
    all_free = np.logical_and.reduceat(free, starts)
    pairs = cKDTree(centres).query_pairs(radius + 2.0 * float(reach.max()), output_type="ndarray")
    i, j = pairs[:, 0], pairs[:, 1]
    a, b = curve[starts[i]], curve[starts[j]]
    gap = np.linalg.norm(centres[i] - centres[j], axis=1) - reach[i] - reach[j]
    near = (a != b) & (gap <= radius) & ~(all_free[i] & all_free[j])
    i, j, gap = i[near], j[near], gap[near]
    keys = np.minimum(a, b)[near] * count + np.maximum(a, b)[near]
    order = np.lexsort((j, i, gap))
    i, j, keys = i[order], j[order], keys[order]
    members = starts[:, None] + np.arange(size)  # point rows of each run, -1 past its end
    ends = np.append(starts[1:], len(points))
    members = np.where(members < ends[:, None], members, -1)
    padded = np.vstack([points, np.full((1, 3), 1e18)])  # padding: far away, and free
    padded_free = np.append(free, True)
    padded_corner = None if sides is None else np.append(sides[1], 0)
    found: set[int] = set()
    for lo in range(0, len(keys), batch):
        todo = np.flatnonzero(~np.isin(keys[lo:lo + batch], list(found))) + lo
        if len(todo) == 0:
            continue
        p, q = members[i[todo]], members[j[todo]]
        d2 = np.zeros((len(todo), size, size))
        for axis in range(3):
            d2 += (padded[p, axis][:, :, None] - padded[q, axis][:, None, :]) ** 2
        hit = (d2 <= radius * radius) & ~(padded_free[p][:, :, None] & padded_free[q][:, None, :])
        if sides is not None:
            pair, row, column = np.nonzero(hit)
            hit[pair, row, column] = ~sides[0].apart(padded_corner[p[pair, row]], padded_corner[q[pair, column]])
        found.update(keys[todo][hit.any(axis=(1, 2))].tolist())
    return np.array(sorted(found), dtype=np.int64)


def parallel_pairs(tx: CurveSet, rx: CurveSet, face_mask: np.ndarray, within_mm: float, run_mm: float,
                   step_mm: float = CONFLICT_STEP_MM) -> np.ndarray:
    """Distinct ``(P, 2)`` (Tx, Rx) pairs whose centre lines lie within ``within_mm`` of each other
    (conservatively: sampled distance below ``within_mm + step_mm``) along more than ``run_mm`` of the Tx
    line inside ``face_mask``: strips laid along each other, not across. A crossing at angle ``a``
    keeps them that close along ``2 within / sin a``, so only glancing crossings count too."""
    from scipy.spatial import cKDTree

    tx_points, tx_curve, tx_length, _, _ = resample(tx, face_mask, step_mm)
    rx_points, rx_curve, _, _, _ = resample(rx, face_mask, step_mm)
    if len(tx_points) == 0 or len(rx_points) == 0:
        return np.empty((0, 2), dtype=np.int64)
    near = cKDTree(tx_points).sparse_distance_matrix(cKDTree(rx_points), within_mm + step_mm, output_type="ndarray")
    point_near_curve = np.zeros(len(tx_points) * rx.count, dtype=bool)  # each Tx point counted once per Rx curve
    point_near_curve[near["i"].astype(np.int64) * rx.count + rx_curve[near["j"]]] = True
    point, rx_of = np.divmod(np.flatnonzero(point_near_curve), rx.count)
    pair_key = tx_curve[point] * rx.count + rx_of
    run = np.bincount(pair_key, weights=tx_length[point], minlength=tx.count * rx.count)
    long = np.flatnonzero(run > run_mm)
    return np.stack([long // rx.count, long % rx.count], axis=1).astype(np.int64)


def _from_free_end(curves: CurveSet, curve: np.ndarray, arc: np.ndarray, free_end: FreeEnd) -> np.ndarray:
    """Arc length (mm) of resampled points from their curve's ``free_end``."""
    return arc if free_end == "start" else curves.lengths_mm[curve] - arc


def _in_free_zone(curves: CurveSet, curve: np.ndarray, arc: np.ndarray, free_mm: float, free_end: FreeEnd) -> np.ndarray:
    """Resampled points within ``free_mm`` of their curve's ``free_end`` and in its half on that side
    (a curve is never cut back beyond its middle, so a short one keeps its wired half clear)."""
    return _from_free_end(curves, curve, arc, free_end) < np.minimum(free_mm, 0.5 * curves.lengths_mm[curve])


def spread_order(n: int) -> np.ndarray:
    """0..n-1 in van der Corput order (0, n/2, n/4, 3n/4, ...): every prefix is spread over the range."""
    bits = max(1, int(np.ceil(np.log2(max(n, 2)))))
    reversed_bits = np.array([int(format(i, f"0{bits}b")[::-1], 2) for i in range(2**bits)])
    return reversed_bits[reversed_bits < n]


def _within(points: np.ndarray, corner: np.ndarray | None, others: np.ndarray, others_corner: np.ndarray | None,
            radius: float, walls: ThinWalls | None) -> np.ndarray:
    """(P,) bool: a point of ``others`` lies within ``radius`` of ``points[i]`` in space and is not apart
    from it along the surface by ``walls`` (``corner``s as :meth:`ThinWalls.corners_of` gives them)."""
    from scipy.spatial import cKDTree

    near = np.zeros(len(points), dtype=bool)
    if len(points) == 0 or len(others) == 0:
        return near
    pairs = cKDTree(points).sparse_distance_matrix(cKDTree(others), radius, output_type="ndarray")
    i, j = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
    if walls is not None:
        keep = ~walls.apart(corner[i], others_corner[j])
        i = i[keep]
    near[i] = True
    return near


def free_end_trims(curves: CurveSet, face_mask: np.ndarray, bound_mm: float, free_mm: float, free_end: FreeEnd = "start",
                   step_mm: float = CONFLICT_STEP_MM, walls: ThinWalls | None = None) -> np.ndarray:
    """Per curve, how many rows to drop from its ``free_end`` so that it keeps ``bound_mm`` from the
    curves kept before it inside ``face_mask``: curves are taken in :func:`spread_order` of their index
    (their order at the pole or along the seed line), and each is cut beyond the last point of its free
    zone (:func:`close_pairs`) that comes closer (conservatively, below ``bound_mm + step_mm``) to an
    earlier one, as trimmed. So one curve of each converging bundle reaches the end and the others stop
    where they have room (points on the two sides of one of the ``walls`` are not close); 0 = untouched."""
    points, curve, length, arc, face = resample(curves, face_mask, step_mm)
    corner = None if walls is None else _checked(walls, bound_mm + step_mm).corners_of(face, points)
    from_end = _from_free_end(curves, curve, arc, free_end)
    in_zone = _in_free_zone(curves, curve, arc, free_mm, free_end)
    arcs = row_arcs(curves)
    drop = np.zeros(curves.count, dtype=np.int64)
    kept = np.zeros(len(points), dtype=bool)
    for c in spread_order(curves.count):
        own = curve == c
        lo, hi = int(curves.offsets[c]), int(curves.offsets[c + 1])
        keep_from = 0.0  # arc from the free end (mm) where the kept part begins
        if kept.any():
            zone = own & in_zone
            near = _within(points[zone], None if corner is None else corner[zone], points[kept],
                           None if corner is None else corner[kept], bound_mm + step_mm, walls)
            if near.any():
                cut = float((from_end[zone][near] + 0.5 * length[zone][near]).max())
                if free_end == "start":
                    drop[c] = min(int(np.searchsorted(arcs[lo:hi], cut)), hi - lo - 2)
                    keep_from = arcs[lo + drop[c]]
                else:
                    last = max(int(np.searchsorted(arcs[lo:hi], curves.lengths_mm[c] - cut, side="right")) - 1, 1)
                    drop[c] = hi - lo - 1 - last
                    keep_from = curves.lengths_mm[c] - arcs[lo + last]
        kept |= own & (from_end >= keep_from)
    return drop


def trim_free_ends(curves: CurveSet, drop: np.ndarray, free_end: FreeEnd = "start") -> tuple[CurveSet, np.ndarray]:
    """The family without the ``drop[c]`` rows at the ``free_end`` of each curve c; returns it and the
    arc (mm) cut from each curve's start (subtract it from crossing arcs, and ``drop`` from segments,
    when the start is cut; nothing changes for the rows kept when the end is cut)."""
    arcs = row_arcs(curves)
    keep = np.ones(len(curves.faces), dtype=bool)
    cut = np.zeros(curves.count)
    shortened = np.zeros(curves.count)
    for c in np.flatnonzero(drop):
        lo, hi, k = int(curves.offsets[c]), int(curves.offsets[c + 1]), int(drop[c])
        if free_end == "start":
            keep[lo : lo + k] = False
            cut[c] = shortened[c] = arcs[lo + k]
        else:
            keep[hi - k : hi] = False
            shortened[c] = curves.lengths_mm[c] - arcs[hi - k - 1]
    counts = np.bincount(np.repeat(np.arange(curves.count), np.diff(curves.offsets))[keep], minlength=curves.count)
    trimmed = dataclasses.replace(
        curves, points=curves.points[keep], faces=curves.faces[keep], bary=curves.bary[keep],
        offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64), lengths_mm=curves.lengths_mm - shortened,
    )
    return trimmed, cut


def clearance_profile(curves: CurveSet, face_mask: np.ndarray, bound_mm: float, step_mm: float = MEASURE_STEP_MM,
                      walls: ThinWalls | None = None) -> dict:
    """Smallest centre-line distance (mm) between two curves of the family inside ``face_mask``, and
    the length (mm and share of the family's length there) lying closer than ``bound_mm`` to another
    curve. With ``walls``, points on the two sides of a wall are not close: the smallest distance
    counts the others (at least ``walls.radius_mm`` where every closer point is across a wall), and
    ``min_distance_in_space_mm`` all. ``None`` distances when fewer than two curves run there."""
    from scipy.spatial import cKDTree

    points, curve, length, _, face = resample(curves, face_mask, step_mm)
    corner = None if walls is None else _checked(walls, bound_mm).corners_of(face, points)
    in_space = np.full(len(points), np.inf)
    nearest = np.full(len(points), np.inf)
    for c in np.unique(curve):
        own = curve == c
        if own.all():
            break
        others = np.flatnonzero(~own)
        tree = cKDTree(points[others])
        in_space[own] = nearest[own] = tree.query(points[own])[0]
        if walls is None:
            continue
        rows = np.flatnonzero(own & (in_space < walls.radius_mm))  # their nearest point not across a wall,
        pairs = cKDTree(points[rows]).sparse_distance_matrix(tree, walls.radius_mm, output_type="ndarray")
        i, j = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
        keep = ~walls.apart(corner[rows[i]], corner[others[j]])
        closest = np.full(len(rows), walls.radius_mm)  # or at least the walls' radius away
        np.minimum.at(closest, i[keep], pairs["v"][keep])
        nearest[rows] = closest
    close = nearest < bound_mm
    total = float(length.sum())
    finite = np.isfinite(nearest)
    return {
        "min_centre_distance_mm": float(nearest[finite].min()) if finite.any() else None,
        "min_distance_in_space_mm": float(in_space[finite].min()) if finite.any() else None,
        "length_closer_than_bound_mm": float(length[close].sum()),
        "share_closer_than_bound": float(length[close].sum() / total) if total > 0 else 0.0,
        "length_in_region_mm": total,
        "bound_mm": float(bound_mm),
    }
