"""Phase 2 of the layout optimisation (paper section 6.3): where electrode pads go.

Among the active crossings ``I'`` of the selected curves, choose ``z_k`` maximising ``sum z_k``
subject to ``dist_M(i_k, i_l) >= d_min`` for every chosen pair: a maximum independent set in the
conflict graph whose edges join crossings closer than ``d_min`` (geodesic, mm), solved with CP-SAT.
Optionally every selected curve must carry at least ``min_pads_per_curve`` pads (a wired channel
without a pad only senses through its bare crossings); that requirement is what can make the
problem infeasible, and the caller's relaxation ladder (smaller pads, then fewer curves) answers it.

Among the maximum pad sets, ``tie_break`` weights (larger = preferred) pick one: the layout uses
the mean geodesic distance of each crossing to its three nearest active neighbours (see
:func:`sparseness`), so inside a cluster the pads go to the crossings bordering sparse areas,
which evens out the pad spacing.
The count keeps priority: the count weight exceeds the sum of all tie-break weights.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .problem import deterministic_solver, work_units

PAD_TIME_LIMIT_S = 2.0  # phase-2 CP-SAT limit, deterministic seconds


def sparseness(distance_mm: np.ndarray, neighbours: int = 3) -> np.ndarray:
    """Mean distance (mm) of each point to its ``neighbours`` nearest others (inf-free, >= 0)."""
    if len(distance_mm) < 2:
        return np.zeros(len(distance_mm))
    k = min(neighbours, len(distance_mm) - 1)
    return np.sort(distance_mm, axis=1)[:, 1 : k + 1].mean(axis=1)


@dataclasses.dataclass(frozen=True)
class PadResult:
    pad: np.ndarray  # (A,) bool over the active crossings
    feasible: bool
    report: dict


def place_pads(
    distance_mm: np.ndarray,
    curve_tx: np.ndarray,
    curve_rx: np.ndarray,
    d_min_mm: float,
    min_pads_per_curve: int = 0,
    time_limit_s: float = PAD_TIME_LIMIT_S,
    seed: int = 0,
    workers: int = 1,
    tie_break: np.ndarray | None = None,
) -> PadResult:
    """Maximum set of crossings pairwise >= ``d_min_mm`` apart (``distance_mm`` symmetric (A, A))."""
    from ortools.sat.python import cp_model  # heavy: imported when solving, not on node discovery

    A = len(distance_mm)
    model = cp_model.CpModel()
    z = [model.new_bool_var(f"z{k}") for k in range(A)]
    close_i, close_j = np.nonzero(np.triu(distance_mm < d_min_mm, k=1))
    for i, j in zip(close_i, close_j):
        model.add_bool_or([z[i].Not(), z[j].Not()])
    if min_pads_per_curve > 0:
        for curves in (curve_tx, curve_rx):
            for c in np.unique(curves):
                model.add(sum(z[k] for k in np.flatnonzero(curves == c)) >= min_pads_per_curve)
    if tie_break is None:
        model.maximize(sum(z))
    else:
        # integer tie-break weights in [0, 100]; the count weight exceeds their total, so the pad
        # count stays the primary objective
        w = np.round(100 * np.asarray(tie_break, dtype=float) / max(float(np.max(tie_break)), 1e-12)).astype(int)
        big = int(w.sum()) + 1
        model.maximize(sum((big + int(w[k])) * z[k] for k in range(A)))
    solver = deterministic_solver(time_limit_s, seed, workers)
    status = solver.solve(model)
    feasible = status in (cp_model.OPTIMAL, cp_model.FEASIBLE)
    pad = np.array([solver.boolean_value(v) for v in z], dtype=bool) if feasible else np.zeros(A, dtype=bool)
    scale = 1.0 if tie_break is None else float(big)
    objective = float(pad.sum()) if feasible else None
    bound = float(np.floor(solver.best_objective_bound / scale + 1e-9))
    report = {
        "status": solver.status_name(status),
        "d_min_mm": float(d_min_mm),
        "min_pads_per_curve": int(min_pads_per_curve),
        "candidates": int(A),
        "conflicts": int(len(close_i)),
        "pads": int(pad.sum()),
        "objective": objective,
        "bound": bound,
        "gap": None if objective is None else (bound - objective) / max(objective, 1.0),
        "deterministic_time": work_units(solver),
    }
    return PadResult(pad=pad, feasible=feasible, report=report)
