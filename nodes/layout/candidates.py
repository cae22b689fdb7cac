"""A branch's phase-1 problem from its curve families: the candidate crossings, the C1/C2 and
clearance conflicts among the curves, and the samples' distances to the crossings
(:class:`retrotouch.nodes.layout.problem.SelectionProblem`). Units: mm."""
from __future__ import annotations

import numpy as np

from ..data.types import TRACE_WIDTH_MM, Crossings, CurveEnd, CurveSet
from ..geometry.thin_walls import ThinWalls
from .clearance import PARALLEL_RUN_MM, close_pairs, parallel_pairs
from .problem import SelectionProblem, candidate_crossings, merge_pairs, same_layer_conflicts
from .samples import HeatGeodesics, SurfaceSamples


def _usable(curves: CurveSet, require_base_end: bool) -> np.ndarray:
    if not require_base_end:
        return np.ones(curves.count, dtype=bool)
    return curves.end_reason == int(CurveEnd.BASE)


def selection_problem(
    geo: HeatGeodesics,
    samples: SurfaceSamples,
    tx: CurveSet,
    rx: CurveSet,
    tx_rx: Crossings,
    tx_tx: Crossings,
    rx_rx: Crossings,
    require_base_end: bool,
    clearance_bound_mm: float | None = None,
    tx_free_start_mm: float = 0.0,
    rx_free_end_mm: float = 0.0,
    trace_width_mm: float = TRACE_WIDTH_MM,
    walls: ThinWalls | None = None,
) -> SelectionProblem:
    """Phase-1 input from the curve families: single crossings, C1/C2 conflicts (a Tx/Rx pair laid
    along each other, closer than a trace width over more than ``PARALLEL_RUN_MM``, conflicts like a
    pair crossing twice), sample distances;
    with ``clearance_bound_mm``, same-layer pairs closer than it in the sensing region conflict too
    (not counting the first ``tx_free_start_mm`` of each Tx curve and the last ``rx_free_end_mm`` of
    each Rx curve, which the selected ones may lose, and pairs close only across one of the ``walls``)."""
    rows, multi = candidate_crossings(tx_rx, tx.count, rx.count)
    multi = np.unique(np.concatenate([multi, parallel_pairs(tx, rx, samples.sensing_faces, trace_width_mm, PARALLEL_RUN_MM)]), axis=0)
    tx_conflicts, rx_conflicts = same_layer_conflicts(tx_tx), same_layer_conflicts(rx_rx)
    clearance_pairs = (0, 0)
    if clearance_bound_mm is not None:
        tx_close = close_pairs(tx, samples.sensing_faces, clearance_bound_mm, tx_free_start_mm, "start", walls=walls)
        rx_close = close_pairs(rx, samples.sensing_faces, clearance_bound_mm, rx_free_end_mm, "end", walls=walls)
        merged_tx, merged_rx = merge_pairs(tx_conflicts, tx_close), merge_pairs(rx_conflicts, rx_close)
        clearance_pairs = (len(merged_tx) - len(tx_conflicts), len(merged_rx) - len(rx_conflicts))
        tx_conflicts, rx_conflicts = merged_tx, merged_rx
    return SelectionProblem(
        tx_usable=_usable(tx, require_base_end),
        rx_usable=_usable(rx, require_base_end),
        cross_tx=tx_rx.curve_a[rows].astype(np.int64),
        cross_rx=tx_rx.curve_b[rows].astype(np.int64),
        cross_rows=rows,
        distance=geo.evaluate(samples.distances, tx_rx.faces[rows], tx_rx.bary[rows]),
        multi_pairs=multi,
        tx_conflicts=tx_conflicts,
        rx_conflicts=rx_conflicts,
        clearance_pairs=clearance_pairs,
        tx_lanes=None if tx.lane_parent is None else tx.lane_parent >= 0,
        limb_curves=None if tx.limb is None or rx.limb is None else (tx.limb >= 0, rx.limb >= 0),
    )
