"""Phase 2 of the layout optimisation (paper section 6.3): where electrode pads go.

Among the active crossings ``I'`` of the selected curves, choose ``z_k`` maximising ``sum z_k``
subject to ``dist_M(i_k, i_l) >= d_min`` for every chosen pair: a maximum independent set in the
conflict graph whose edges join crossings closer than ``d_min`` (geodesic, mm), solved with CP-SAT.
Optionally every selected curve must carry at least ``min_pads_per_curve`` pads (a wired channel
without a pad only senses through its bare crossings); that requirement is what can make the
problem infeasible, and the caller's relaxation ladder (smaller pads, then fewer curves) answers it.
"""
from __future__ import annotations

import dataclasses

import numpy as np


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
    time_limit_s: float = 2.0,
    seed: int = 0,
    workers: int = 1,
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
    model.maximize(sum(z))
    solver = cp_model.CpSolver()
    solver.parameters.num_workers = workers
    solver.parameters.random_seed = seed
    solver.parameters.max_deterministic_time = time_limit_s
    solver.parameters.max_time_in_seconds = 4.0 * time_limit_s
    status = solver.solve(model)
    feasible = status in (cp_model.OPTIMAL, cp_model.FEASIBLE)
    pad = np.array([solver.boolean_value(v) for v in z], dtype=bool) if feasible else np.zeros(A, dtype=bool)
    objective = float(solver.objective_value) if feasible else None
    bound = float(solver.best_objective_bound)
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
        "seconds": solver.wall_time,
    }
    return PadResult(pad=pad, feasible=feasible, report=report)
