"""One phase-1 stage of a :class:`~retrotouch.nodes.layout.mip.LinearModel` through CP-SAT or HiGHS,
both deterministic for a fixed input: CP-SAT with a deterministic-time limit (its work units), a fixed
seed and no wall-clock limit; HiGHS on one thread with a fixed seed and a branch-and-bound node limit (its statuses mapped to
CP-SAT's names: OPTIMAL, FEASIBLE, INFEASIBLE, UNKNOWN; the raw one in the work report)
(HiGHS has no deterministic work limit; its wall-clock ``time_limit`` is only a safety net, and a stage
it stops says so in ``status``, since that result may differ between runs). Objectives and bounds are
in the model's integer units; the caller converts them."""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from .mip import LinearModel
from .problem import deterministic_solver, work_units

HIGHS_MAX_NODES = 100  # branch-and-bound nodes per HiGHS stage (deterministic)
HIGHS_SAFETY_S = 20.0  # HiGHS wall-clock safety net per stage (nondeterministic when reached)


@dataclasses.dataclass(frozen=True)
class StageSolution:
    """One stage's outcome: ``values`` (columns) is None without an incumbent."""

    status: str
    values: np.ndarray | None
    objective: float | None  # model units, without the constant
    bound: float  # model units, without the constant
    work: dict  # solver-specific reproducible effort (deterministic time; nodes and LP iterations)
    seconds: float  # wall seconds (not reproducible: kept out of the reports, for benchmarks)


def solve_stage(model: LinearModel, cost: np.ndarray, hint: np.ndarray, solver: str, settings: dict) -> StageSolution:
    """Minimise ``cost @ v`` over ``model`` from the feasible ``hint`` with ``solver`` ("cpsat" or
    "highs"); ``settings``: ``time_limit_s`` (CP-SAT deterministic time), ``seed``, ``workers``,
    ``highs_max_nodes`` and optionally ``relative_gap`` (stop once proven that close to the optimum)
    and ``cpsat_linearization`` (CP-SAT's ``linearization_level``, default 1)."""
    start = time.perf_counter()
    status, values, bound, work = (_cpsat if solver == "cpsat" else _highs)(model, cost, hint, settings)
    objective = None if values is None else float(cost @ values)
    return StageSolution(status, values, objective, bound, work, time.perf_counter() - start)


def _cpsat_variables(col_hi: np.ndarray) -> np.ndarray:
    """The CP-SAT variable of each column: binaries in column order, every fixed column (``col_hi`` 0)
    on the one constant 0, made where the first of them stands (as ``new_constant`` caches it)."""
    fixed = col_hi == 0
    opens = ~fixed
    if fixed.any():
        opens[np.argmax(fixed)] = True
    index = np.cumsum(opens) - 1
    if fixed.any():
        index[fixed] = index[np.argmax(fixed)]
    return index


def _canonical_rows(model: LinearModel, var: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rows over CP-SAT variables as CP-SAT stores a weighted sum: terms of one variable merged,
    zero coefficients dropped, variables ascending. Returns (row offsets, variables, coefficients)."""
    row = np.repeat(np.arange(len(model.row_lo)), np.diff(model.offsets))
    v = var[model.columns]
    order = np.lexsort((v, row))
    row, v, coef = row[order], v[order], model.values[order]
    first = np.concatenate([[True], (row[1:] != row[:-1]) | (v[1:] != v[:-1])]) if len(row) else np.zeros(0, bool)
    starts = np.flatnonzero(first)
    coef = np.add.reduceat(coef, starts) if len(starts) else coef
    row, v = row[starts], v[starts]
    keep = coef != 0
    row, v, coef = row[keep], v[keep], coef[keep]
    offsets = np.searchsorted(row, np.arange(len(model.row_lo) + 1))
    return offsets, v, coef


def _int_bounds(bounds: np.ndarray, infinite: int) -> list[int]:
    """Row bounds as integers, ``infinite`` for the missing ones."""
    out = np.full(len(bounds), infinite, dtype=np.int64)
    finite = np.isfinite(bounds)
    out[finite] = bounds[finite].astype(np.int64)
    return out.tolist()


def cpsat_model(model: LinearModel, cost: np.ndarray, hint: np.ndarray):
    """``min cost @ v`` over ``model`` from ``hint`` as a CP-SAT model, its proto written directly: the
    same proto as a binary (or the cached constant 0) per column, each row added through
    ``add_linear_constraint`` of a ``weighted_sum``, and ``add_hint`` per binary, built without a Python
    object per term. Returns (the CpModel, the CP-SAT variable of each column)."""
    from ortools.sat.python import cp_model

    cp = cp_model.CpModel()
    proto = cp.proto
    var = _cpsat_variables(model.col_hi)
    opens = np.flatnonzero(np.diff(np.concatenate([[-1], var])) > 0)
    for i in opens.tolist():
        entry = proto.variables.add()
        if model.col_hi[i]:
            entry.name = f"v{i}"
        entry.domain.extend([0, int(model.col_hi[i])])
    offsets, v, coef = _canonical_rows(model, var)
    lo, hi = _int_bounds(model.row_lo, cp_model.INT_MIN), _int_bounds(model.row_hi, cp_model.INT_MAX)
    v_list, coef_list, bounds = v.tolist(), coef.tolist(), offsets.tolist()
    for r in range(len(lo)):
        linear = proto.constraints.add().linear
        linear.vars.extend(v_list[bounds[r]:bounds[r + 1]])
        linear.coeffs.extend(coef_list[bounds[r]:bounds[r + 1]])
        linear.domain.extend([lo[r], hi[r]])
    used = np.flatnonzero(cost)
    terms = {}
    for i, c in zip(var[used].tolist(), cost[used].tolist()):
        terms[i] = terms.get(i, 0) + c
    cp.minimize(cp_model.LinearExpr.weighted_sum([cp.get_int_var_from_proto_index(i) for i in terms], list(terms.values())))
    hinted = np.flatnonzero(model.col_hi)
    proto.solution_hint.vars.extend(var[hinted].tolist())
    proto.solution_hint.values.extend(hint[hinted].astype(bool).astype(np.int64).tolist())
    return cp, var


def _cpsat(model: LinearModel, cost: np.ndarray, hint: np.ndarray, settings: dict) -> tuple:
    from ortools.sat.python import cp_model

    cp, var = cpsat_model(model, cost, hint)
    solver = deterministic_solver(settings["time_limit_s"], settings["seed"], settings["workers"],
                                  settings.get("relative_gap", 0.0))
    solver.parameters.linearization_level = settings.get("cpsat_linearization", 1)
    status = solver.solve(cp)
    has = status in (cp_model.OPTIMAL, cp_model.FEASIBLE)
    values = np.asarray(solver.response_proto.solution, dtype=np.int64)[var] if has else None
    return solver.status_name(status), values, solver.best_objective_bound, {"deterministic_time": work_units(solver)}


def _highs(model: LinearModel, cost: np.ndarray, hint: np.ndarray, settings: dict) -> tuple:
    import highspy  # heavy: imported when solving, not on node discovery

    h = highspy.Highs()
    for name, value in (("output_flag", bool(settings.get("log"))), ("threads", 1), ("random_seed", int(settings["seed"]) % 2**31),
                        ("mip_max_nodes", int(settings["highs_max_nodes"])), ("time_limit", HIGHS_SAFETY_S)):
        h.setOptionValue(name, value)
    if settings.get("relative_gap"):
        h.setOptionValue("mip_rel_gap", float(settings["relative_gap"]))
    lp = highspy.HighsLp()
    lp.num_col_, lp.num_row_ = model.n_cols, len(model.row_lo)
    lp.col_cost_ = cost.astype(float)
    lp.col_lower_ = np.zeros(model.n_cols)
    lp.col_upper_ = model.col_hi.astype(float)
    lp.row_lower_ = np.where(np.isfinite(model.row_lo), model.row_lo, -highspy.kHighsInf)
    lp.row_upper_ = np.where(np.isfinite(model.row_hi), model.row_hi, highspy.kHighsInf)
    lp.a_matrix_.format_ = highspy.MatrixFormat.kRowwise
    lp.a_matrix_.start_ = model.offsets.astype(np.int32)
    lp.a_matrix_.index_ = model.columns.astype(np.int32)
    lp.a_matrix_.value_ = model.values.astype(float)
    lp.integrality_ = [highspy.HighsVarType.kInteger] * model.n_cols
    h.passModel(lp)
    solution = highspy.HighsSolution()
    solution.col_value = hint.astype(float).tolist()
    h.setSolution(solution)
    h.run()
    info = h.getInfo()
    has = info.primal_solution_status == 2  # kSolutionStatusFeasible
    values = np.rint(np.asarray(h.getSolution().col_value)).astype(np.int64) if has else None
    raw = h.modelStatusToString(h.getModelStatus())
    status = "OPTIMAL" if raw == "Optimal" else "INFEASIBLE" if raw == "Infeasible" else "FEASIBLE" if has else "UNKNOWN"
    work = {"nodes": int(info.mip_node_count), "lp_iterations": int(info.simplex_iteration_count), "highs_status": raw}
    if raw == "Time limit reached":
        work["note"] = f"stopped by the {HIGHS_SAFETY_S:g} s wall-clock safety net: not reproducible"
    bound = float(info.mip_dual_bound)
    if not np.isfinite(bound):  # nothing proven (an infeasible model): the bound every 0-1 point respects
        bound = float(np.minimum(cost, 0.0) @ model.col_hi)
    return status, values, bound, work
