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

Formulation: distances are quantised to ``resolution_mm``; per sample, the distinct distance levels
of the candidate crossings within its cap form a chain of "still uncovered at level j" columns, and
one radius chain is shared by all samples (the p-center and p-median radius formulations; rows and
columns in :mod:`retrotouch.nodes.layout.mip`). The model is one 0-1 linear program that either
solver takes unchanged (``solver``: CP-SAT or HiGHS, :mod:`retrotouch.nodes.layout.solvers`).

Start, caps and hints: a heuristic selection (:mod:`retrotouch.nodes.layout.heuristic`) (the better of a greedy construction and an evenly
spread pick over the candidate order, improved by a best-improvement swap local search on
(radius, sum of distance^p)) gives the global cap (its radius: no sample of an optimal solution is
farther). When the model would exceed ``max_memberships`` (sample, crossing) pairs, each sample's
cap is tightened to its distance in the start plus the largest common slack that fits: a trust
region around the start, reported in ``report["model"]["trust_region_slack_mm"]`` (bounds and gaps
are then those of the restricted model). The start is hinted to stage 1 and, after a local search
from the stage-1 solution, to stage 2. Without the secondary objective the local search scores the
radius alone, so nothing in the ablation optimises the mean distance.

Both solvers are deterministic for a fixed input (CP-SAT: deterministic time, fixed seed, in the
secondary stage with every row in its LP, ``POWER_STAGE_LINEARIZATION``; HiGHS: one thread, fixed
seed, a node limit). The secondary stage also stops once its incumbent is proven within
``relative_gap`` of the optimum (status FEASIBLE, ``stopped_at_relative_gap`` in its report); the
radius stage has no gap limit. Every stage reports status, objective, bound, gap and the solver's
reproducible work (CP-SAT's deterministic time, HiGHS's nodes and LP iterations; no wall seconds: they
would make the report differ between runs). Objectives are integers in the model, so a bound is
rounded up to the next integer before the gap is taken. Beside the model's bound, each stage reports
``global_bound`` (mm) and ``global_gap``, valid for the problem without the trust region: the model's
bound when no trust region was needed, else for stage 1 the layer relaxation of
:mod:`retrotouch.nodes.layout.bounds` (the radius no set of Rx, or Tx, curves alone can beat) and for
stage 2 the power mean of each sample's distance to its nearest usable crossing.
If the solver returns no incumbent the heuristic selection is used and ``report["source"]`` says so.
When the layer relaxation already proves that no selection covers every sample a level nearer than
the start does, stage 1 is the start without a solver call (``proven_by: "layer_bound"``).

:func:`select_curves` is :func:`solve_radius_stage` (start, caps, stage 1) then
:func:`finish_selection` (stage 2): the sweep screens its branches between the two
(:mod:`retrotouch.nodes.layout.screen`), and :func:`radius_proven_above` asks, without a trust region,
whether any selection covers every sample within a radius. Units: mm.
"""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from .heuristic import heuristic_selection, local_search
from .bounds import layer_radius_bound
from .mip import LinearModel, build_model
from .problem import (
    PHASE1_MAX_MEMBERSHIPS,
    PHASE1_POWER,
    PHASE1_RELATIVE_GAP,
    PHASE1_RESOLUTION_MM,
    PHASE1_TIME_LIMIT_S,
    POWER_STAGE_LINEARIZATION,
    UNREACHABLE_LEVEL,
    SelectionProblem,
    evaluate_selection,
    nearest_levels,
    quantised_distances,
    start_key,
    without_added,
)
from .solvers import HIGHS_MAX_NODES, StageSolution, solve_stage


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
    stage_seconds: tuple[float, ...] = ()  # wall seconds per stage (not reproducible: not in the report)


def _gap(objective: float, bound: float) -> float:
    return 0.0 if objective <= bound + 1e-9 else (objective - bound) / max(abs(objective), 1e-12)


def _stage_report(name: str, solved: StageSolution, objective: float, bound: float) -> dict:
    """A stage's status, objective and bound (model units with the constant) and their gap."""
    return {"stage": name, "status": solved.status, "objective": objective, "bound": bound,
            "gap": _gap(objective, bound), **solved.work}


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


def _selection(model: LinearModel, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return (np.flatnonzero(values[:model.n_tx]).astype(np.int64),
            np.flatnonzero(values[model.n_tx:model.n_tx + model.n_rx]).astype(np.int64))


def _radius_stage(model: LinearModel, problem: SelectionProblem, start: tuple, settings: dict) -> tuple[dict, tuple | None, float]:
    """Stage 1: minimise the radius from ``start``. Returns the report (mm), the selection (None
    without an incumbent) and the solver's wall seconds."""
    res = settings["resolution_mm"]
    hint = model.column_values(*start, nearest_levels(problem, *start, res))
    solved = solve_stage(model, model.radius_objective(), hint, settings["solver"], {**settings, "relative_gap": 0.0})
    bound = model.r_low + np.ceil(solved.bound - 1e-6)
    objective = model.r_low + (solved.objective if solved.values is not None else float(hint @ model.radius_objective()))
    report = _stage_report("coverage_radius", solved, float(objective * res), float(bound * res))
    return report, None if solved.values is None else _selection(model, solved.values), solved.seconds


def _power_mean_stage(model: LinearModel, problem: SelectionProblem, start: tuple, settings: dict) -> tuple[dict, tuple, float]:
    """Stage 2: with the radius fixed at stage 1's, minimise the sum of level**power from a local
    search of stage 1's selection. The report's ``gap`` is on the mean of level**p (the model's
    objective), ``gap_power_mean_mm`` on the power mean in mm; objective and bound are in mm."""
    power, res = settings["power"], settings["resolution_mm"]
    radius = int(nearest_levels(problem, *start, res).max())
    tx_sel, rx_sel, moves = local_search(problem, *start, settings["n_drive"], settings["n_sense"], True, res, power=power)
    fixed = model.radius_fixed(radius)
    cost = fixed.power_objective()
    hint = fixed.column_values(tx_sel, rx_sel, nearest_levels(problem, tx_sel, rx_sel, res))
    # the solvers take the gap on the cost without the constant (samples fixed at the radius): a limit
    # scaled by (hint + constant) / hint, the hint's cost bounding the solution's, keeps the gap with it
    hinted = max(float(hint @ cost), 1.0)
    limit = settings["relative_gap"] * (hinted + fixed.constant_power_sum) / hinted
    solved = solve_stage(fixed, cost, hint, settings["solver"],
                         {**settings, "relative_gap": limit, "cpsat_linearization": POWER_STAGE_LINEARIZATION})
    k = len(problem.distance)
    if solved.values is not None:
        tx_sel, rx_sel = _selection(fixed, solved.values)
        total = solved.objective
    else:  # keep the hinted local-search selection, scored like the model scores it
        total = float(hint @ cost)
    mean_objective = (fixed.constant_power_sum + total) / k
    mean_bound = (fixed.constant_power_sum + float(np.ceil(solved.bound - 1e-6))) / k
    report = _stage_report(f"power_mean_distance_p{power}", solved, mean_objective, mean_bound)
    if report["status"] == "OPTIMAL" and report["gap"] > 0:  # the solver stopped at the gap limit
        report["status"], report["stopped_at_relative_gap"] = "FEASIBLE", settings["relative_gap"]
    if solved.values is None:
        report["note"] = "no incumbent within the limit: the local search's selection is kept (objective and gap are its)"
    for key in ("objective", "bound"):  # (mean of level**p) -> power mean in mm
        report[key] = res * max(report[key], 0.0) ** (1.0 / power)
    report["gap_power_mean_mm"] = _gap(report["objective"], report["bound"])
    # a trust region's bound holds inside it only; outside, no sample gets nearer than its nearest crossing
    global_mean = mean_bound if not settings["restricted"] else fixed.constant_power_sum / k
    report["global_bound"] = res * max(global_mean, 0.0) ** (1.0 / power)
    report["global_gap"] = _gap(mean_objective, global_mean)
    report["local_search_moves_before"] = moves
    return report, (tx_sel, rx_sel), solved.seconds


@dataclasses.dataclass(frozen=True)
class RadiusStage:
    """Phase 1 after its radius stage: what finishing it needs besides the problem, and what screening a
    branch reads. ``selection`` is stage 1's (Tx ids, Rx ids), or the heuristic start when the solver
    found none; ``sample_cap`` the model's caps (levels), from which :func:`stage_model` rebuilds it."""

    sample_cap: np.ndarray
    selection: tuple[np.ndarray, np.ndarray]
    solved: bool  # stage 1 returned an incumbent
    report: dict  # heuristic, stage 1, model size, solver, resolution
    settings: dict
    seconds: float  # stage 1's wall seconds (not reproducible: not in the report)
    without_limbs: bool = False  # the limbs' curves did not lower the radius: stage 2 leaves them out too

    @property
    def radius_mm(self) -> float:
        """Stage 1's coverage radius (mm, quantised up to the resolution)."""
        return self.report["stages"][0]["objective"]

    @property
    def lower_bound_mm(self) -> float:
        """No layout of this branch has a smaller coverage radius (mm): below stage 1's global bound by
        one resolution step, since a distance at level j lies in ((j - 1) res, j res]."""
        return self.report["stages"][0]["global_bound"] - self.settings["resolution_mm"]


def solve_radius_stage(
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
    solver: str = "cpsat",
    highs_max_nodes: int = HIGHS_MAX_NODES,
    bound_apart: bool = True,
    start: tuple[np.ndarray, np.ndarray, dict] | None = None,
) -> RadiusStage:
    """Phase 1's start and radius stage (see the module docstring) with ``solver`` ("cpsat" or "highs");
    ``secondary`` says whether a power-mean stage follows (the start's local search scores it too).
    With the limbs' curves among the candidates, the stage is first solved without them, and with Tx lanes
    but no limbs' curves, over the field lines alone (:func:`.problem.without_added`); that selection starts
    the whole problem when it is the better start, so added candidates never leave a branch's radius worse
    than without them. When the limbs' curves give neither a better start nor a smaller radius, the stage
    without them is the branch's (``without_limbs``: :func:`finish_selection` leaves them out too). Without
    ``bound_apart`` a trust region's stage
    reports the model's lowest level as its global bound instead of the layer relaxation's (that first
    solve only hands on its selection). ``start`` is the heuristic start (Tx ids, Rx ids, its report) when
    already known (:func:`start_and_bound`)."""
    args = (n_drive, n_sense, secondary, resolution_mm, time_limit_s, seed, workers, max_memberships, power, solver,
            highs_max_nodes)
    if start is None:
        start = heuristic_selection(problem, n_drive, n_sense, secondary, resolution_mm, power)
    start_tx, start_rx, heuristic = start[0], start[1], dict(start[2])
    reduced_seconds = 0.0
    reduced = without_added(problem)
    if reduced is not None:
        name, smaller = reduced
        first = solve_radius_stage(smaller, *args, bound_apart=bound_apart and name == "without_limbs")
        reduced_seconds = first.seconds
        key = start_key(problem, start_tx, start_rx, resolution_mm, power)
        better = start_key(problem, *first.selection, resolution_mm, power) < key
        if name == "without_limbs" and better:  # the limbs' curves do not even give a better start
            return _without_limbs(first, key[0] * resolution_mm, reduced_seconds)
        heuristic[name] = {"radius_mm": first.radius_mm, "starts_the_stage": bool(better)}
        if better:
            start_tx, start_rx = first.selection
    q = quantised_distances(problem, resolution_mm)
    q_start = nearest_levels(problem, start_tx, start_rx, resolution_mm)
    sample_cap, slack = _sample_caps(q, q_start, max_memberships)
    model = build_model(problem, n_drive, n_sense, q, sample_cap, power)
    restricted = slack < int(q_start.max())
    size = {"columns": model.n_cols, "rows": len(model.row_lo), "nonzeros": len(model.values),
            "candidate_crossings": int((problem.tx_usable[problem.cross_tx] & problem.rx_usable[problem.cross_rx]).sum()),
            "crossings_in_model": len(model.act_crossings),
            "trust_region_slack_mm": slack * resolution_mm if restricted else None,
            "memberships": len(model.u_sample) + len(q)}
    settings = {"n_drive": n_drive, "n_sense": n_sense, "power": power, "resolution_mm": resolution_mm,
                "solver": solver, "time_limit_s": time_limit_s, "seed": seed, "workers": workers,
                "highs_max_nodes": highs_max_nodes, "restricted": restricted, "secondary": secondary}
    level = int(q_start.max())
    started = time.perf_counter()
    if level < UNREACHABLE_LEVEL and layer_radius_bound(problem, q, (n_drive, n_sense), level - 1, level, settings) >= level:
        radius = float(level * resolution_mm)  # no set of curves of one layer reaches every sample a level nearer
        stage1 = {"stage": "coverage_radius", "status": "OPTIMAL", "objective": radius, "bound": radius, "gap": 0.0,
                  "proven_by": "layer_bound", "deterministic_time": 0.0, "global_bound": radius}
        found, seconds = (start_tx, start_rx), time.perf_counter() - started
    else:
        stage1, found, seconds = _radius_stage(model, problem, (start_tx, start_rx), settings)
        if restricted:  # the model's bound holds inside the trust region only: bound the problem apart
            low = (layer_radius_bound(problem, q, (n_drive, n_sense), model.r_low, level, settings) if bound_apart
                   else model.r_low)
            stage1["global_bound"] = float(low * resolution_mm)
        else:
            stage1["global_bound"] = stage1["bound"]
    stage1["global_gap"] = _gap(stage1["objective"], stage1["global_bound"])
    report = {"heuristic": heuristic, "stages": [stage1], "model": size, "solver": solver, "resolution_mm": resolution_mm}
    if reduced is not None and name == "without_limbs" and stage1["objective"] >= first.radius_mm:
        return _without_limbs(first, stage1["objective"], seconds + reduced_seconds)
    return RadiusStage(sample_cap, found if found is not None else (start_tx, start_rx), found is not None, report, settings,
                       seconds + reduced_seconds)


def start_and_bound(problem: SelectionProblem, n_drive: int, n_sense: int, secondary: bool, resolution_mm: float,
                    power: int, time_limit_s: float, seed: int, workers: int) -> tuple[tuple, float, float]:
    """Phase 1's heuristic start (Tx ids, Rx ids, its report), its coverage radius (quantised up as
    stage 1's) and a lower bound on any selection's (the layer relaxation), in mm: what
    ``layout.prescreen`` compares across branches before their radius stages."""
    start = heuristic_selection(problem, n_drive, n_sense, secondary, resolution_mm, power)
    level = int(nearest_levels(problem, start[0], start[1], resolution_mm).max())
    if level >= UNREACHABLE_LEVEL:
        return start, math.inf, 0.0
    settings = {"time_limit_s": time_limit_s, "seed": seed, "workers": workers}
    low = layer_radius_bound(problem, quantised_distances(problem, resolution_mm), (n_drive, n_sense), 0, level, settings)
    return start, level * resolution_mm, max(low - 1, 0) * resolution_mm  # a level-j distance lies in ((j - 1) res, j res]


def _without_limbs(first: RadiusStage, radius_mm: float, seconds: float) -> RadiusStage:
    """The stage without the limbs' curves (``first``) as the branch's, stage 2 too: with them, nothing
    better than ``radius_mm`` was found."""
    return dataclasses.replace(first, report={**first.report, "limbs": {"radius_mm": radius_mm, "kept": False}},
                               seconds=seconds, without_limbs=True)


def stage_model(problem: SelectionProblem, stage: RadiusStage) -> LinearModel:
    """The model the radius stage solved (the same function of the problem and its caps)."""
    settings = stage.settings
    return build_model(problem, settings["n_drive"], settings["n_sense"], quantised_distances(problem, settings["resolution_mm"]),
                       stage.sample_cap, settings["power"])


def radius_proven_above(problem: SelectionProblem, stage: RadiusStage, radius_mm: float) -> bool:
    """True when no selection covers every sample within ``radius_mm``: the model with every sample's
    cap at that radius (no trust region) is proven infeasible within the stage's limits; False when a
    selection may (feasible, or not proven)."""
    settings = stage.settings
    q = quantised_distances(problem, settings["resolution_mm"])
    level = int(np.ceil(radius_mm / settings["resolution_mm"] - 1e-9))
    if np.any(q.min(axis=1) > level):  # a sample with no crossing that near
        return True
    model = build_model(problem, settings["n_drive"], settings["n_sense"], q, np.full(len(q), level), settings["power"])
    nothing = np.zeros(model.n_cols, dtype=np.int64)  # a feasibility question: any selection stops it
    solved = solve_stage(model, nothing, nothing, settings["solver"], {**settings, "relative_gap": 0.0})
    return solved.status == "INFEASIBLE"


def finish_selection(problem: SelectionProblem, stage: RadiusStage, relative_gap: float = PHASE1_RELATIVE_GAP) -> SelectionResult:
    """Phase 1 from its radius stage: the power-mean stage when the stage was solved with
    ``secondary`` (stopped within ``relative_gap`` of its optimum; without the limbs' curves when they
    did not lower the radius) and every stage's report."""
    if stage.without_limbs:
        problem = without_added(problem)[1]
    solver = stage.settings["solver"]
    tx_sel, rx_sel = stage.selection
    stages, stage_seconds = list(stage.report["stages"]), [stage.seconds]
    if not stage.solved:
        # The heuristic start is feasible, so no incumbent means the solver could not even load it in
        # time: keep the heuristic selection and say so in the report.
        source = f"heuristic ({solver} found no incumbent)"
    else:
        source = solver
        if stage.settings["secondary"]:
            settings = {**stage.settings, "relative_gap": relative_gap}
            report, (tx_sel, rx_sel), seconds = _power_mean_stage(stage_model(problem, stage), problem, (tx_sel, rx_sel),
                                                                  settings)
            stages.append(report)
            stage_seconds.append(seconds)
    active, nearest = evaluate_selection(problem, tx_sel, rx_sel)
    report = {**stage.report, "stages": stages, "source": source}
    return SelectionResult(tx=tx_sel, rx=rx_sel, active=active, nearest_mm=nearest, coverage_radius_mm=float(nearest.max()),
                           mean_distance_mm=float(nearest.mean()), report=report, stage_seconds=tuple(stage_seconds))


def select_curves(problem: SelectionProblem, n_drive: int, n_sense: int, relative_gap: float = PHASE1_RELATIVE_GAP,
                  **options) -> SelectionResult:
    """Solve phase 1 (see the module docstring): :func:`solve_radius_stage` with ``options`` (its keyword
    arguments), then :func:`finish_selection` within ``relative_gap``."""
    return finish_selection(problem, solve_radius_stage(problem, n_drive, n_sense, **options), relative_gap)
