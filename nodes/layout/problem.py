"""The phase-1 problem (candidate curves, crossings, conflicts, sample distances), its evaluation,
the phase-1 defaults shared by the solver and the ``layout.bound`` params, and the CP-SAT solver
settings both phases use. Units: mm."""
from __future__ import annotations

import dataclasses

import numpy as np

from ..data.types import Crossings

PHASE1_TIME_LIMIT_S = 1.0  # per CP-SAT solve, deterministic seconds
PHASE1_RESOLUTION_MM = 0.5  # distance quantisation of the model
PHASE1_MAX_MEMBERSHIPS = 15000  # (sample, crossing) pairs before a trust region
PHASE1_POWER = 6  # secondary objective: power mean of the sample distances
PHASE1_RELATIVE_GAP = 0.02  # the secondary stage stops once proven within this share of its optimum
# CP-SAT's LP in the secondary stage holds every row and its cuts (linearization level 2, not the
# default 1): the covering chains' LP bound is what proves that stage's gap in its budget (the
# bunny: 0.135 -> 0.042); the radius stage keeps level 1, whose budget goes to the search.
POWER_STAGE_LINEARIZATION = 2
UNREACHABLE_LEVEL = np.iinfo(np.int64).max // 4  # the quantised distance of a crossing no selection may use


def deterministic_solver(time_limit_s: float, seed: int, workers: int, relative_gap: float = 0.0):
    """A CP-SAT solver whose result is a function of the model only: a deterministic-time limit
    (``time_limit_s``, CP-SAT's work units, not wall seconds) and no wall-clock limit, a fixed seed, and
    with more than one worker the interleaved search (deterministic for any ``workers``); it stops
    early once its incumbent is proven within ``relative_gap`` of the optimum (0: prove optimality)."""
    from ortools.sat.python import cp_model  # heavy: imported when solving, not on node discovery

    solver = cp_model.CpSolver()
    solver.parameters.num_workers = workers
    solver.parameters.interleave_search = workers > 1
    solver.parameters.random_seed = seed
    solver.parameters.max_deterministic_time = time_limit_s
    solver.parameters.relative_gap_limit = relative_gap
    return solver


def work_units(solver) -> float:
    """The deterministic time (CP-SAT work units) a solve used, to 1e-9 units: the last bits of
    CP-SAT's float sum differ between identical solves in one process, the 9 decimals do not."""
    return round(float(solver.deterministic_time), 9)


@dataclasses.dataclass(frozen=True)
class SelectionProblem:
    """Phase-1 input: candidate curves, their valid crossings and the C1/C2 conflicts.

    ``tx_conflicts``/``rx_conflicts`` are the pairs of one layer that cannot both be selected: those
    that cross (C1) and, when clearance is enforced, those whose centre lines come closer than
    ``trace_width + clearance`` in the sensing region (``clearance_pairs`` counts the latter per layer).
    """

    tx_usable: np.ndarray  # (Ntx,) bool, candidate may be selected (e.g. connected to the base)
    rx_usable: np.ndarray  # (Nrx,) bool
    cross_tx: np.ndarray  # (C,) int64, Tx curve of candidate crossing c (pairs crossing exactly once)
    cross_rx: np.ndarray  # (C,) int64
    cross_rows: np.ndarray  # (C,) int64, row of c in the Tx x Rx Crossings
    distance: np.ndarray  # (K, C) float, geodesic sample -> crossing distance in mm
    multi_pairs: np.ndarray  # (P, 2) int64, Tx/Rx pairs crossing more than once (C2)
    tx_conflicts: np.ndarray  # (Q, 2) int64, crossing Tx pairs (C1)
    rx_conflicts: np.ndarray  # (R, 2) int64, crossing Rx pairs (C1)
    clearance_pairs: tuple[int, int] = (0, 0)  # (Tx, Rx) pairs in the conflicts for clearance alone
    tx_lanes: np.ndarray | None = None  # (Ntx,) bool, Tx candidates that are lanes (curves.tx_lanes), or None
    limb_curves: tuple[np.ndarray, np.ndarray] | None = None  # (Ntx,), (Nrx,) bool, the curves.trace_limbs candidates, or None


def merge_pairs(*pairs: np.ndarray) -> np.ndarray:
    """Distinct ``(P, 2)`` int64 rows of several pair lists, each row ascending."""
    rows = np.concatenate([np.sort(np.asarray(p, dtype=np.int64).reshape(-1, 2), axis=1) for p in pairs])
    return np.unique(rows, axis=0) if len(rows) else np.empty((0, 2), dtype=np.int64)


def candidate_crossings(tx_rx: Crossings, tx_count: int, rx_count: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows of ``tx_rx`` whose Tx/Rx pair crosses exactly once, and the (P, 2) pairs crossing more often."""
    key = tx_rx.curve_a.astype(np.int64) * rx_count + tx_rx.curve_b.astype(np.int64)
    multiplicity = np.bincount(key, minlength=tx_count * rx_count)
    single_rows = np.flatnonzero(multiplicity[key] == 1)
    multi = np.flatnonzero(multiplicity > 1)
    return single_rows, np.stack([multi // rx_count, multi % rx_count], axis=1).astype(np.int64)


def same_layer_conflicts(crossings: Crossings) -> np.ndarray:
    """Distinct (P, 2) curve pairs of one layer that cross (C1)."""
    pairs = np.stack([crossings.curve_a, crossings.curve_b], axis=1).astype(np.int64)
    pairs = np.sort(pairs, axis=1)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    return np.unique(pairs, axis=0) if len(pairs) else np.empty((0, 2), dtype=np.int64)


def evaluate_selection(problem: SelectionProblem, tx: np.ndarray, rx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Active candidate crossings of a selection and each sample's nearest active distance (inf if none)."""
    tx_sel = np.zeros(len(problem.tx_usable), dtype=bool)
    rx_sel = np.zeros(len(problem.rx_usable), dtype=bool)
    tx_sel[tx] = True
    rx_sel[rx] = True
    active = np.flatnonzero(tx_sel[problem.cross_tx] & rx_sel[problem.cross_rx])
    if len(active) == 0:
        return active, np.full(problem.distance.shape[0], np.inf)
    return active, problem.distance[:, active].min(axis=1)


def without_added(problem: SelectionProblem) -> tuple[str, SelectionProblem] | None:
    """The problem without the candidates added beside the family, the outermost first, and its name in
    the report: without the limbs' curves (``"without_limbs"``) if it has any, else without the Tx lanes
    (``"field_lines"``); None if it has neither."""
    if problem.limb_curves is not None and (problem.limb_curves[0].any() or problem.limb_curves[1].any()):
        tx_limb, rx_limb = problem.limb_curves
        return "without_limbs", dataclasses.replace(problem, tx_usable=problem.tx_usable & ~tx_limb,
                                                    rx_usable=problem.rx_usable & ~rx_limb, limb_curves=None)
    if problem.tx_lanes is not None and problem.tx_lanes.any():
        return "field_lines", dataclasses.replace(problem, tx_usable=problem.tx_usable & ~problem.tx_lanes, tx_lanes=None)
    return None


def quantised_distances(problem: SelectionProblem, resolution_mm: float) -> np.ndarray:
    """(K, C) sample -> crossing distances in units of ``resolution_mm`` (rounded up); crossings of
    unusable curves get a value beyond any cap."""
    usable_c = problem.tx_usable[problem.cross_tx] & problem.rx_usable[problem.cross_rx]
    q = np.ceil(problem.distance / resolution_mm - 1e-9).astype(np.int64)
    q[:, ~usable_c] = UNREACHABLE_LEVEL
    return q


def nearest_levels(problem: SelectionProblem, tx: np.ndarray, rx: np.ndarray, resolution_mm: float) -> np.ndarray:
    """(K,) each sample's distance to the selection's nearest active crossing in units of ``resolution_mm``
    (rounded up)."""
    _, nearest = evaluate_selection(problem, tx, rx)
    return np.ceil(nearest / resolution_mm - 1e-9).astype(np.int64)


def start_key(problem: SelectionProblem, tx: np.ndarray, rx: np.ndarray, resolution_mm: float, power: int) -> tuple:
    """A start's (radius level, sum of level ** power): smaller is better."""
    levels = nearest_levels(problem, tx, rx, resolution_mm)
    return int(levels.max()), float(np.sum(levels.astype(np.float64) ** power))
