"""Lower bounds on the phase-1 coverage radius that hold for the whole problem, without the trust
region the model may be restricted to. Units: levels (distances in units of the model's resolution).

Layer relaxation: a sample covered within radius ``r`` by an active crossing ``(a, b)`` is also within
``r`` of a crossing on the selected Rx curve ``b`` (and on the selected Tx curve ``a``). So no selection
has a radius below the smallest ``r`` at which at most ``N_sense`` pairwise non-conflicting Rx curves
(C1) put a usable crossing within ``r`` of every sample, and likewise for Tx with ``N_drive``. Each
``r`` is a small set-cover feasibility question, found by bisection between a known lower and upper
value. A greedy cover within the limit is a selection, which settles about half of them (coverable);
the rest go to a CP-SAT model (deterministic time, fixed seed), where an undecided ``r`` counts as
coverable, so the bound stays valid whatever the limit.
"""
from __future__ import annotations

import numpy as np

from .problem import UNREACHABLE_LEVEL, SelectionProblem, deterministic_solver


def _layer_levels(problem: SelectionProblem, q: np.ndarray, layer: str) -> np.ndarray:
    """(K, curves) level of each sample's nearest usable crossing on each curve of ``layer``."""
    curve_of = problem.cross_tx if layer == "tx" else problem.cross_rx
    usable = problem.tx_usable if layer == "tx" else problem.rx_usable
    nearest = np.full((len(q), len(usable)), UNREACHABLE_LEVEL)
    np.minimum.at(nearest.T, curve_of, q.T)
    nearest[:, ~usable] = UNREACHABLE_LEVEL
    return nearest


def _greedy_cover(reach: np.ndarray, conflicting: np.ndarray, limit: int) -> bool:
    """True when at most ``limit`` greedy picks, each the curve (column) that reaches the most samples
    (rows) not yet reached among those conflicting with no pick (``conflicting`` (C, C) bool), reach
    every sample."""
    gain = reach.sum(axis=0)
    allowed = np.ones(reach.shape[1], dtype=bool)
    unreached = np.ones(reach.shape[0], dtype=bool)
    for _ in range(limit):
        pick = int(np.argmax(np.where(allowed, gain, -1)))
        if not allowed[pick] or gain[pick] == 0:
            return False
        newly = unreached & reach[:, pick]
        gain -= reach[newly].sum(axis=0)
        unreached &= ~newly
        if not unreached.any():
            return True
        allowed &= ~conflicting[pick]
        allowed[pick] = False
    return False


def _coverable(nearest: np.ndarray, conflicts: np.ndarray, limit: int, radius: int, settings: dict) -> bool:
    """Whether at most ``limit`` non-conflicting curves reach every sample within ``radius``
    (True when the solver cannot decide within its limit)."""
    from ortools.sat.python import cp_model  # heavy: imported when solving, not on node discovery

    reach = nearest <= radius
    if not reach.any(axis=1).all():
        return False
    conflicting = np.zeros((reach.shape[1], reach.shape[1]), dtype=bool)
    conflicting[conflicts[:, 0], conflicts[:, 1]] = conflicting[conflicts[:, 1], conflicts[:, 0]] = True
    if _greedy_cover(reach, conflicting, limit):
        return True
    model = cp_model.CpModel()
    pick = [model.new_bool_var(f"p{i}") for i in range(nearest.shape[1])]
    model.add(sum(pick) <= limit)
    for a, b in conflicts.tolist():
        model.add_bool_or([pick[a].Not(), pick[b].Not()])
    for row in reach:
        model.add_bool_or([pick[i] for i in np.flatnonzero(row).tolist()])
    solver = deterministic_solver(settings["time_limit_s"], settings["seed"], settings["workers"])
    return solver.solve(model) != cp_model.INFEASIBLE


def layer_radius_bound(problem: SelectionProblem, q: np.ndarray, limits: tuple[int, int], low: int, high: int,
                       settings: dict) -> int:
    """The larger of the two layers' smallest coverable radius (see the module docstring), searched in
    ``[low, high]`` levels: ``low`` a valid bound, ``high`` the radius of a feasible selection."""
    best = low
    for layer, limit, conflicts in (("tx", limits[0], problem.tx_conflicts), ("rx", limits[1], problem.rx_conflicts)):
        nearest = _layer_levels(problem, q, layer)
        lo, hi = best, high
        while lo < hi:
            mid = (lo + hi) // 2
            if _coverable(nearest, conflicts, limit, mid, settings):
                hi = mid
            else:
                lo = mid + 1
        best = max(best, lo)
    return best
