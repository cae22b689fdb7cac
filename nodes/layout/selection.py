"""Phase 1 of the layout optimisation (paper section 6.2): choose the Tx and Rx curves.

Decision variables: ``x_a`` (Tx candidate ``a`` selected), ``y_b`` (Rx candidate ``b`` selected) and,
per candidate crossing ``c = (a, b)``, ``act_c <= x_a, act_c <= y_b`` (the crossing is active when
both its curves are selected; the objective only rewards active crossings, so ``act_c`` reaching
``x_a AND y_b`` exactly is never worse and the reported active set is recomputed as that AND).

Constraints:

* C1: two selected curves of one layer never cross: ``x_a + x_a' <= 1`` per crossing Tx pair (the
  crossing node already drops crossings inside the singularity neighbourhoods), same for Rx.
* C2: a Tx/Rx pair crossing more than once is never selected together: ``x_a + y_b <= 1``; those
  crossings are no candidates.
* C3: ``sum x <= N_drive``, ``sum y <= N_sense`` (21 x 12 on the Muca/FT5316 board).

Objective, and why it differs from the paper's printed formula: the paper prints
``d_max = max over active i of min over samples dist(i, s)``, which is degenerate (with K = 300
samples nearly every crossing lies next to some sample, so it barely depends on the selection and
an empty selection would be optimal), while its text says the objective "ensures that every region
of the surface lies within a bounded distance of at least one sensing location". We implement
that stated intent, the p-center/p-median pair over the K uniform samples:

1. primary: the coverage radius ``R = max_k min_{c active} dist(s_k, c)``, minimised;
2. secondary (``secondary=True``): with ``R`` fixed at the best radius found, the power mean of
   the sample-to-nearest-active-crossing distances ``((1/K) sum_k d_k^p)^(1/p)`` with
   ``d_k = min_{c active} dist(s_k, c)``, minimised (``power=1`` is the plain mean distance). This
   is the surface-uniform version of the paper's eq. 6 (whose per-intersection mean would reward
   selecting few crossings). Powers between the mean (p = 1) and the radius (p -> inf) weigh the
   large gaps more: p = 2 is the centroidal-Voronoi energy. The default power is ``PHASE1_POWER``.

Formulation (chosen for speed over a big-M assignment model): distances are quantised to
``resolution_mm`` and, per sample, the distinct distance levels ``l_1 < ... < l_J`` of the
candidate crossings within its cap form a chain of "still uncovered at level j" literals ``u_kj``:
``u_k1 + sum_{c at l_1} act_c >= 1``, ``u_kj >= u_k(j-1) - sum_{c at l_j} act_c``, the last level
must be covered, ``u_kj => R >= l_(j+1)`` and ``dist_k = l_1 + sum_j (l_(j+1) - l_j) u_kj`` (the
radius formulation of the p-median problem, Elloumi 2010). Stage 1 minimises ``R``; stage 2 adds
``R <= R*`` and minimises ``sum_k dist_k^p = sum_k (l_1^p + sum_j (l_(j+1)^p - l_j^p) u_kj)``
(exact in the level chain; levels in units of ``resolution_mm``).

Start, caps and hints: a heuristic selection (:mod:`retrotouch.nodes.layout.heuristic`) (the better of a greedy construction and an evenly
spread pick over the candidate order, improved by a best-improvement swap local search on
(radius, sum of distance^p)) gives the global cap (its radius: no sample of an optimal solution is
farther). When the model would exceed ``max_memberships`` (sample, crossing) pairs, each sample's
cap is tightened to its distance in the start plus the largest common slack that fits: a trust
region around the start, reported in ``report["model"]["trust_region_slack_mm"]`` (bounds and gaps
are then those of the restricted model). The start is hinted to stage 1 and, after a local search
from the stage-1 solution, to stage 2. Without the secondary objective the local search scores the
radius alone, so nothing in the ablation optimises the mean distance.

CP-SAT runs with ``workers`` workers, a fixed seed and ``max_deterministic_time`` equal to the time
limit and no wall-clock limit, so the result is a function of the problem only; every stage reports
status, objective, bound, gap and CP-SAT's deterministic time (no wall seconds: they would make the
report differ between runs). If CP-SAT returns no incumbent the heuristic selection is used and
``report["source"]`` says so. Units: mm.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .heuristic import heuristic_selection, local_search
from .problem import (
    PHASE1_MAX_MEMBERSHIPS,
    PHASE1_POWER,
    PHASE1_RESOLUTION_MM,
    PHASE1_TIME_LIMIT_S,
    SelectionProblem,
    deterministic_solver,
    evaluate_selection,
)


@dataclasses.dataclass(frozen=True)
class SelectionResult:
    """Phase-1 output. ``active`` indexes the problem's candidate crossings."""

    tx: np.ndarray  # selected Tx candidate ids, ascending
    rx: np.ndarray  # selected Rx candidate ids, ascending
    active: np.ndarray  # candidate crossings whose two curves are selected
    nearest_mm: np.ndarray  # (K,) distance of each sample to its nearest active crossing
    coverage_radius_mm: float
    mean_distance_mm: float
    report: dict


def _stage_report(name: str, solver, status: int, scale: float) -> dict:
    from ortools.sat.python import cp_model

    has = status in (cp_model.OPTIMAL, cp_model.FEASIBLE)
    objective = solver.objective_value * scale if has else None
    bound = solver.best_objective_bound * scale
    gap = None
    if has:
        gap = 0.0 if objective <= bound + 1e-12 else (objective - bound) / max(abs(objective), 1e-12)
    return {
        "stage": name,
        "status": solver.status_name(status),
        "objective": objective,
        "bound": bound,
        "gap": gap,
        "deterministic_time": solver.deterministic_time,
    }


def _quantised_distances(problem: SelectionProblem, resolution_mm: float) -> np.ndarray:
    """(K, C) sample -> crossing distances in units of ``resolution_mm`` (rounded up); crossings of
    unusable curves get a value beyond any cap."""
    usable_c = problem.tx_usable[problem.cross_tx] & problem.rx_usable[problem.cross_rx]
    q = np.ceil(problem.distance / resolution_mm - 1e-9).astype(np.int64)
    q[:, ~usable_c] = np.iinfo(np.int64).max // 4
    return q


def _sample_caps(q: np.ndarray, q_start: np.ndarray, max_memberships: int) -> tuple[np.ndarray, int]:
    """Per-sample level caps (quantised) and the trust-region slack (``cap`` = none).

    Without a restriction every sample's cap is the start's radius; when that would put more than
    ``max_memberships`` (sample, crossing) pairs in the model, each cap is the sample's start distance
    plus the largest common slack that fits.
    """
    cap = int(q_start.max())
    sorted_q = np.sort(q, axis=1, kind="stable")

    def caps_for(slack: int) -> tuple[np.ndarray, int]:
        caps = np.minimum(cap, q_start + slack)
        counts = [int(np.searchsorted(sorted_q[k], caps[k], side="right")) for k in range(len(q))]
        return caps, int(sum(counts))

    slack = cap
    sample_cap, size_needed = caps_for(slack)
    if size_needed > max_memberships:
        low, high = 0, cap
        while low < high:
            mid = (low + high + 1) // 2
            if caps_for(mid)[1] <= max_memberships:
                low = mid
            else:
                high = mid - 1
        slack = low
        sample_cap, _ = caps_for(slack)
    return sample_cap, slack


class Phase1Model:
    """The CP-SAT model of phase 1 (see the module docstring): selection literals ``x``/``y``, C1-C3,
    the lazily created crossing literals ``act``, the radius and the per-sample level chains."""

    def __init__(self, problem: SelectionProblem, n_drive: int, n_sense: int, q: np.ndarray, cap: int):
        from ortools.sat.python import cp_model  # heavy: imported when solving, not on node discovery

        self.problem = problem
        self.model = model = cp_model.CpModel()
        self.x = [model.new_bool_var(f"x{a}") for a in range(len(problem.tx_usable))]
        self.y = [model.new_bool_var(f"y{b}") for b in range(len(problem.rx_usable))]
        x, y = self.x, self.y
        for a in np.flatnonzero(~problem.tx_usable):
            model.add(x[a] == 0)
        for b in np.flatnonzero(~problem.rx_usable):
            model.add(y[b] == 0)
        model.add(sum(x) <= n_drive)
        model.add(sum(y) <= n_sense)
        for a, b in problem.tx_conflicts:
            model.add_bool_or([x[a].Not(), x[b].Not()])
        for a, b in problem.rx_conflicts:
            model.add_bool_or([y[a].Not(), y[b].Not()])
        for a, b in problem.multi_pairs:
            model.add_bool_or([x[a].Not(), y[b].Not()])
        self.act: dict = {}
        self.radius = model.new_int_var(int(q.min()), cap, "radius")
        self.cap = cap
        self.sample_terms: list = []
        self.hint_u: list = []
        self.memberships = 0

    def active_var(self, c: int):
        """The literal of candidate crossing ``c`` (``act_c <=> x_a AND y_b``), created on first use."""
        if c not in self.act:
            x, y = self.x[self.problem.cross_tx[c]], self.y[self.problem.cross_rx[c]]
            v = self.model.new_bool_var(f"act{c}")
            self.model.add_implication(v, x)
            self.model.add_implication(v, y)
            self.model.add_bool_or([x.Not(), y.Not(), v])
            self.act[c] = v
        return self.act[c]

    def add_sample_chain(self, k: int, levels: np.ndarray, shells: list[np.ndarray], power: int) -> None:
        """Covering chain of sample ``k``: distinct quantised ``levels`` and the crossings at each."""
        model = self.model
        model.add(self.radius >= int(levels[0]))
        prev = None
        terms = [int(levels[0]) ** power]
        for j, level in enumerate(levels):
            shell = [self.active_var(int(c)) for c in shells[j]]
            if j == len(levels) - 1:
                model.add(sum(shell) >= (1 if prev is None else prev))
                break
            u = model.new_bool_var(f"u{k}_{j}")
            model.add(u + sum(shell) >= (1 if prev is None else prev))
            if prev is not None:
                model.add_implication(u, prev)
            model.add(self.radius >= int(levels[j + 1])).only_enforce_if(u)
            terms.append((int(levels[j + 1]) ** power - int(level) ** power) * u)
            self.hint_u.append((u, k, int(level)))
            prev = u
        self.sample_terms.append(sum(terms))

    def add_samples(self, q: np.ndarray, sample_cap: np.ndarray, power: int) -> None:
        """One covering chain per sample over the crossings within its cap."""
        order = np.argsort(q, axis=1, kind="stable")
        for k in range(q.shape[0]):
            within = order[k, : int(np.searchsorted(q[k, order[k]], sample_cap[k], side="right"))]
            self.memberships += len(within)
            levels, shell_of = np.unique(q[k, within], return_inverse=True)
            self.add_sample_chain(k, levels, [within[shell_of == j] for j in range(len(levels))], power)

    def hint(self, tx_sel: np.ndarray, rx_sel: np.ndarray, resolution_mm: float) -> None:
        """Hint a selection with every derived literal at its tight value."""
        problem, model = self.problem, self.model
        model.clear_hints()
        tx_mask = np.zeros(len(self.x), dtype=bool)
        tx_mask[tx_sel] = True
        rx_mask = np.zeros(len(self.y), dtype=bool)
        rx_mask[rx_sel] = True
        _, nearest = evaluate_selection(problem, tx_sel, rx_sel)
        q_near = np.ceil(nearest / resolution_mm - 1e-9)
        for a, v in enumerate(self.x):
            model.add_hint(v, bool(tx_mask[a]))
        for b, v in enumerate(self.y):
            model.add_hint(v, bool(rx_mask[b]))
        for c, v in self.act.items():
            model.add_hint(v, bool(tx_mask[problem.cross_tx[c]] and rx_mask[problem.cross_rx[c]]))
        for u, k, level in self.hint_u:
            model.add_hint(u, bool(q_near[k] > level))
        model.add_hint(self.radius, int(min(q_near.max(), self.cap)))

    def selection(self, solver) -> tuple[np.ndarray, np.ndarray]:
        """The selected Tx and Rx candidates of the solver's incumbent."""
        tx = np.array([a for a, v in enumerate(self.x) if solver.boolean_value(v)], dtype=np.int64)
        rx = np.array([b for b, v in enumerate(self.y) if solver.boolean_value(v)], dtype=np.int64)
        return tx, rx


def _power_mean_stage(m: Phase1Model, solver, start: tuple[np.ndarray, np.ndarray], settings: dict) -> tuple[dict, tuple | None]:
    """Stage 2: with the radius fixed at stage 1's, minimise the sum of distance**power, from a local
    search of stage 1's selection. Returns the stage report (``gap`` on the sum of level**p, the
    model's objective; ``gap_power_mean_mm`` on the power mean in mm) and the selection."""
    from ortools.sat.python import cp_model

    problem, power, resolution_mm = m.problem, settings["power"], settings["resolution_mm"]
    best_radius = int(solver.value(m.radius))
    tx_sel, rx_sel, moves = local_search(problem, *start, settings["n_drive"], settings["n_sense"], True, resolution_mm,
                                         power=power)
    m.hint(tx_sel, rx_sel, resolution_mm)
    m.model.add(m.radius <= best_radius)
    m.model.minimize(sum(m.sample_terms))
    status = solver.solve(m.model)
    report = _stage_report(f"power_mean_distance_p{power}", solver, status, 1.0 / len(problem.distance))
    found = status in (cp_model.OPTIMAL, cp_model.FEASIBLE)
    if found:
        tx_sel, rx_sel = m.selection(solver)
    else:  # keep the hinted local-search selection, scored like the model scores it
        _, nearest = evaluate_selection(problem, tx_sel, rx_sel)
        report["objective"] = float(np.mean(np.ceil(nearest / resolution_mm - 1e-9) ** power))
        report["gap"] = max(0.0, report["objective"] - report["bound"]) / max(report["objective"], 1e-12)
        report["note"] = "no incumbent within the limit: the local search's selection is kept (objective and gap are its)"
    for key in ("objective", "bound"):  # (mean of level**p) -> power mean in mm
        report[key] = resolution_mm * max(report[key], 0.0) ** (1.0 / power)
    report["gap_power_mean_mm"] = max(0.0, report["objective"] - report["bound"]) / max(report["objective"], 1e-12)
    report["local_search_moves_before"] = moves
    return report, (tx_sel, rx_sel)


def select_curves(
    problem: SelectionProblem,
    n_drive: int,
    n_sense: int,
    secondary: bool = True,
    resolution_mm: float = PHASE1_RESOLUTION_MM,
    time_limit_s: float = PHASE1_TIME_LIMIT_S,
    seed: int = 0,
    workers: int = 1,
    max_memberships: int = PHASE1_MAX_MEMBERSHIPS,
    power: int = PHASE1_POWER,
) -> SelectionResult:
    """Solve phase 1 (see the module docstring) and report every stage."""
    from ortools.sat.python import cp_model  # heavy: imported when solving, not on node discovery

    start_tx, start_rx, heuristic = heuristic_selection(problem, n_drive, n_sense, secondary, resolution_mm, power)
    _, h_nearest = evaluate_selection(problem, start_tx, start_rx)

    q = _quantised_distances(problem, resolution_mm)
    q_start = np.ceil(h_nearest / resolution_mm - 1e-9).astype(np.int64)
    m = Phase1Model(problem, n_drive, n_sense, q, int(q_start.max()))
    sample_cap, slack = _sample_caps(q, q_start, max_memberships)
    m.add_samples(q, sample_cap, power)
    solver = deterministic_solver(time_limit_s, seed, workers)
    size = {"variables": len(m.model.proto.variables), "constraints": len(m.model.proto.constraints),
            "candidate_crossings": int((problem.tx_usable[problem.cross_tx] & problem.rx_usable[problem.cross_rx]).sum()),
            "crossings_in_model": len(m.act),
            "trust_region_slack_mm": None if slack >= m.cap else slack * resolution_mm,
            "memberships": m.memberships}
    m.hint(start_tx, start_rx, resolution_mm)
    m.model.minimize(m.radius)
    status = solver.solve(m.model)
    stages = [_stage_report("coverage_radius", solver, status, resolution_mm)]
    if status not in (cp_model.OPTIMAL, cp_model.FEASIBLE):
        # The greedy hint is feasible, so no incumbent means the solver could not even load it in
        # time: keep the greedy selection and say so in the report.
        tx_sel, rx_sel, source = start_tx, start_rx, "heuristic (CP-SAT found no incumbent)"
    else:
        (tx_sel, rx_sel), source = m.selection(solver), "cp-sat"
        if secondary:
            settings = {"n_drive": n_drive, "n_sense": n_sense, "power": power, "resolution_mm": resolution_mm}
            report, (tx_sel, rx_sel) = _power_mean_stage(m, solver, (tx_sel, rx_sel), settings)
            stages.append(report)
    active, nearest = evaluate_selection(problem, tx_sel, rx_sel)
    report = {"heuristic": heuristic, "stages": stages, "model": size, "source": source,
              "resolution_mm": resolution_mm}
    return SelectionResult(tx=tx_sel, rx=rx_sel, active=active, nearest_mm=nearest, coverage_radius_mm=float(nearest.max()),
                           mean_distance_mm=float(nearest.mean()), report=report)
