"""The layout optimisation per branch: ``layout.bound``, ``layout.coverage`` and ``layout.finish`` (all
mapped; between them the prescreen and the screen, :mod:`retrotouch.nodes.layout.screen`; the pick is
:mod:`retrotouch.nodes.layout.pick`).

A branch is one Rx candidate family (one initial angle). ``layout.bound`` sets up its phase-1 problem
(:mod:`retrotouch.nodes.layout.candidates`), its heuristic start and a lower bound;
``layout.coverage`` solves the radius stage (:mod:`retrotouch.nodes.layout.selection`) and
``layout.finish``, with the same parameters, the power-mean stage, geodesic distances among the
active crossings, phase 2 pad placement (:mod:`retrotouch.nodes.layout.pads`) with the relaxation
ladder, and the metrics (:mod:`retrotouch.nodes.layout.metrics`,
:mod:`retrotouch.nodes.layout.clearance`). With
``enforce_clearance`` (default) two curves of one layer whose centre lines come closer than
``trace_width_mm + clearance_mm`` in the sensing region are a phase-1 conflict, like two that cross;
Tx curves may come closer within the first ``tx_free_start_mm`` of their free start near the pole,
and Rx curves (wired at their start, see ``fab.unfold``) within the last ``rx_free_end_mm`` of their
free end (off by default); the selected ones are then trimmed there until they have room, and
crossings on the cut parts are not cells (phase 1 still counts them).

Relaxation ladder, applied only when phase 2 is infeasible (some selected curve cannot carry
``min_pads_per_curve`` pads at spacing ``d_min``): (1) smaller pads, each radius of
``relax_pad_radii_mm`` in turn (``d_min`` scales with the pad diameter); (2) fewer curves: drop
the curves that get no pad in an unconstrained maximum pad set. Every step is logged as a warning
and recorded in ``metrics["relaxations"]``; a branch where nothing works is reported infeasible
with the reason, and ``layout.pick_best`` raises a UserError naming what to change if no branch is
feasible. Units: mm, degrees in Params and in the reports.
"""
from __future__ import annotations

import dataclasses
import functools
import logging
import math
from typing import Literal

import numpy as np
from pydantic import Field

from ...graph.errors import UserError
from ...graph.node import NodeParams, node
from .candidates import selection_problem
from .problem import (PHASE1_MAX_MEMBERSHIPS, PHASE1_POWER, PHASE1_RELATIVE_GAP, PHASE1_RESOLUTION_MM, PHASE1_TIME_LIMIT_S,
                      SelectionProblem)
from .clearance import free_end_trims, trim_free_ends, walls_for
from .screen import BranchBound, BranchStart, PreScreen, Screen
from .selection import finish_selection, radius_proven_above, solve_radius_stage, start_and_bound
from .solvers import HIGHS_MAX_NODES
from ..data.board import NUM_RX, NUM_TX
from ..geometry.thin_walls import ThinWalls
from ..data.types import (CLEARANCE_MM, PAD_RADIUS_MM, TRACE_WIDTH_MM, Crossings, CurveSet, Layout, Mesh,
                          SurfaceRegions)
from .metrics import layout_metrics
from .pads import PAD_TIME_LIMIT_S, PadResult, place_pads, sparseness
from .samples import SurfaceSamples, geodesics_for

log = logging.getLogger(__name__)


class OptimizeParams(NodeParams):
    n_drive: int = Field(NUM_TX, ge=1, le=NUM_TX, description="Tx channels available (N_drive; at most the Muca board's 21)")
    n_sense: int = Field(NUM_RX, ge=1, le=NUM_RX, description="Rx channels available (N_sense; at most the Muca board's 12)")
    secondary: bool = Field(True, description="also minimise the sample distances (off: ablation)")
    secondary_power: int = Field(
        PHASE1_POWER, ge=1, le=8, description="secondary objective: power mean of sample distances (1 = plain mean)"
    )
    resolution_mm: float = Field(PHASE1_RESOLUTION_MM, gt=0, le=5, description="distance quantisation of the phase-1 model (mm)")
    solver: Literal["cpsat", "highs"] = Field(
        "cpsat", description="phase-1 solver of the same 0-1 model: CP-SAT or HiGHS (both reproducible)"
    )
    time_limit_s: float = Field(PHASE1_TIME_LIMIT_S, gt=0, description="per CP-SAT solve, deterministic time (CP-SAT work units, no wall-clock limit)")
    relative_gap: float = Field(PHASE1_RELATIVE_GAP, ge=0, lt=1, description="the secondary stage stops once proven within this share of its optimum (0: prove optimality)")
    highs_max_nodes: int = Field(
        HIGHS_MAX_NODES, ge=1, description="per HiGHS solve, branch-and-bound nodes (its deterministic limit)"
    )
    pad_time_limit_s: float = Field(PAD_TIME_LIMIT_S, gt=0, description="phase-2 CP-SAT limit, deterministic time")
    max_model_memberships: int = Field(
        PHASE1_MAX_MEMBERSHIPS, ge=100, description="phase-1 model size cap in (sample, crossing) pairs; beyond it a trust region"
    )
    workers: int = Field(1, ge=1, le=16, description="CP-SAT workers per solve (more than 1: interleaved search, still reproducible)")
    seed: int = Field(0, description="CP-SAT random seed")
    require_base_end: bool = Field(True, description="only curves that reach the base can be wired")
    pad_radius_mm: float = Field(PAD_RADIUS_MM, gt=0, description="electrode pad radius (mm)")
    d_min_mm: float | None = Field(
        None, gt=0, description="minimum geodesic pad spacing (mm); default twice the pad diameter"
    )
    min_pads_per_curve: int = Field(1, ge=0, description="pads every selected curve must carry")
    trace_width_mm: float = Field(TRACE_WIDTH_MM, gt=0, description="conductive trace width (mm)")
    clearance_mm: float = Field(CLEARANCE_MM, ge=0, description="edge-to-edge gap between two traces of one layer (mm)")
    enforce_clearance: bool = Field(
        True, description="phase 1 never selects two curves of one layer closer than trace width + clearance"
    )
    tx_free_start_mm: float = Field(
        60.0, ge=0, description="Tx curves may come closer within this arc length of their free start (near the "
        "pole); the selected ones are trimmed there until they have room (mm)"
    )
    rx_free_end_mm: float = Field(
        0.0, ge=0, description="Rx curves may come closer within this arc length of their free end (the end "
        "not wired); the selected ones are trimmed there until they have room (mm; 0 = off: phase 1 counts "
        "the crossings there, which trimming may take away)"
    )
    relax_pad_radii_mm: tuple[float, ...] = Field(
        (1.5, 1.0), description="smaller pad radii tried in order when phase 2 is infeasible"
    )


def d_min_for(params: OptimizeParams, pad_radius_mm: float) -> float:
    """Pad spacing for a pad radius: ``d_min_mm`` scaled with the radius, or twice the diameter."""
    if params.d_min_mm is None:
        return 4.0 * pad_radius_mm
    return params.d_min_mm * pad_radius_mm / params.pad_radius_mm


@dataclasses.dataclass(frozen=True)
class AngleLayout:
    """One branch of the sweep (an Rx family at one angle, around one Tx pole): its layout (None if
    infeasible), metrics, and the regions it was laid out on (their ``tx_pole``)."""

    family: str  # the Rx family (CurveSet.family), "grid" or "grid_plan" with Tx lines of its own
    angle_deg: float  # the dipole's angle offset, the rings' corridor position around the Tx pole, 0 / 180 for left- / right-handed helices, or 0 / 90 for the grid's lines across / along as Tx
    feasible: bool
    message: str
    layout: Layout | None
    metrics: dict
    regions: SurfaceRegions | None = None


def subset_curves(curves: CurveSet, ids: np.ndarray) -> CurveSet:
    """The curves ``ids`` of a family, in that order, as a new flat CurveSet."""
    ids = np.asarray(ids, dtype=np.int64)
    rows = [np.arange(curves.offsets[i], curves.offsets[i + 1]) for i in ids]
    rows_all = np.concatenate(rows) if rows else np.zeros(0, dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum([len(r) for r in rows])]).astype(np.int64)
    return CurveSet(
        layer=curves.layer,
        points=curves.points[rows_all],
        faces=curves.faces[rows_all],
        bary=curves.bary[rows_all],
        offsets=offsets,
        lengths_mm=curves.lengths_mm[ids],
        end_reason=curves.end_reason[ids],
        angle=curves.angle,
        family=curves.family,
        lane_parent=None if curves.lane_parent is None else curves.lane_parent[ids],
        limb=None if curves.limb is None else curves.limb[ids],
    )


def _pads_with_ladder(
    params: OptimizeParams, distance: np.ndarray, ctx: np.ndarray, crx: np.ndarray
) -> tuple[PadResult, np.ndarray, float, list[dict]]:
    """Phase 2 with the relaxation ladder -> (result, kept crossings mask, pad radius, steps)."""
    relaxations: list[dict] = []
    radii = [params.pad_radius_mm] + [r for r in params.relax_pad_radii_mm if r < params.pad_radius_mm]
    keep = np.ones(len(distance), dtype=bool)
    kwargs = dict(time_limit_s=params.pad_time_limit_s, seed=params.seed, workers=params.workers,
                  tie_break=sparseness(distance))
    for i, radius in enumerate(radii):
        d_min = d_min_for(params, radius)
        result = place_pads(distance, ctx, crx, d_min, params.min_pads_per_curve, **kwargs)
        if result.feasible:
            return result, keep, radius, relaxations
        step = {
            "step": "smaller_pads" if i + 1 < len(radii) else "fewer_curves",
            "failed": f"pad radius {radius:g} mm (d_min {d_min:g} mm): {result.report['status']}, "
            f"not every curve can carry {params.min_pads_per_curve} pad(s)",
        }
        relaxations.append(step)
        log.warning("phase 2 relaxation: %s -> %s", step["failed"], step["step"])
    radius = radii[-1]
    d_min = d_min_for(params, radius)
    free = place_pads(distance, ctx, crx, d_min, 0, **kwargs)
    padded_tx, padded_rx = np.unique(ctx[free.pad]), np.unique(crx[free.pad])
    keep = np.isin(ctx, padded_tx) & np.isin(crx, padded_rx)
    relaxations[-1]["dropped_tx"] = sorted(int(a) for a in set(ctx.tolist()) - set(padded_tx.tolist()))
    relaxations[-1]["dropped_rx"] = sorted(int(b) for b in set(crx.tolist()) - set(padded_rx.tolist()))
    kwargs["tie_break"] = sparseness(distance[np.ix_(keep, keep)])
    result = place_pads(distance[np.ix_(keep, keep)], ctx[keep], crx[keep], d_min, params.min_pads_per_curve, **kwargs)
    return result, keep, radius, relaxations


def _branch_report(params: OptimizeParams, angle_deg: float, tx: CurveSet, rx: CurveSet, problem: SelectionProblem) -> dict:
    """The part of a branch's metrics known before solving: angle, objective settings, candidate counts."""
    return {
        "rx_family": rx.family,
        "angle_deg": angle_deg,
        "secondary": params.secondary,
        "secondary_power": params.secondary_power,
        "candidates": {"tx": tx.count, "rx": rx.count, "tx_usable": int(problem.tx_usable.sum()),
                       "rx_usable": int(problem.rx_usable.sum()), "single_crossings": len(problem.cross_rows),
                       "multi_crossing_pairs": len(problem.multi_pairs), "tx_conflicts": len(problem.tx_conflicts),
                       "rx_conflicts": len(problem.rx_conflicts), "tx_clearance_conflicts": problem.clearance_pairs[0],
                       "rx_clearance_conflicts": problem.clearance_pairs[1]},
    }


def _layout_of(tx: CurveSet, rx: CurveSet, tx_rx: Crossings, cells_rows: np.ndarray, pad: np.ndarray,
               design: dict, tx_first: np.ndarray, rx_last: np.ndarray) -> tuple[Layout, np.ndarray]:
    """The layout of the kept crossings ``cells_rows`` (rows of ``tx_rx``) and their pad flags: channels
    are the curves with at least one kept crossing, Tx curves without their first ``tx_first`` rows and
    Rx curves without their last ``rx_last`` rows,
    cells sorted by (Tx channel, Rx channel); ``design`` holds the Layout's design values (mm).
    Returns the layout and the order applied to ``cells_rows``."""
    tx_sel, rx_sel = np.unique(tx_rx.curve_a[cells_rows]), np.unique(tx_rx.curve_b[cells_rows])
    tx_curves, tx_cut = trim_free_ends(subset_curves(tx, tx_sel), tx_first[tx_sel], "start")
    rx_curves, _ = trim_free_ends(subset_curves(rx, rx_sel), rx_last[rx_sel], "end")
    order = np.lexsort((np.searchsorted(rx_sel, tx_rx.curve_b[cells_rows]),
                        np.searchsorted(tx_sel, tx_rx.curve_a[cells_rows])))
    cells_rows = cells_rows[order]
    channel_a = np.searchsorted(tx_sel, tx_rx.curve_a[cells_rows]).astype(np.int64)
    cells = Crossings(
        layer_a="tx", layer_b="rx",
        curve_a=channel_a,
        curve_b=np.searchsorted(rx_sel, tx_rx.curve_b[cells_rows]).astype(np.int64),
        seg_a=tx_rx.seg_a[cells_rows] - tx_first[tx_rx.curve_a[cells_rows]], seg_b=tx_rx.seg_b[cells_rows],
        arc_a=tx_rx.arc_a[cells_rows] - tx_cut[channel_a], arc_b=tx_rx.arc_b[cells_rows],
        points=tx_rx.points[cells_rows], faces=tx_rx.faces[cells_rows], bary=tx_rx.bary[cells_rows],
    )
    layout = Layout(tx=tx_curves, rx=rx_curves, cells=cells, pad=pad[order],
                    tx_source=tx_sel, rx_source=rx_sel, **design)
    return layout, order


def _free_end_trims(params: OptimizeParams, samples: SurfaceSamples, curves: CurveSet, selected: np.ndarray,
                    bound_mm: float, walls: ThinWalls) -> np.ndarray:
    """Rows to drop from the free end of each candidate of ``curves`` (Tx: the start, the first
    ``tx_free_start_mm``; Rx: the end, the last ``rx_free_end_mm``): the ``selected`` ones where there
    they come closer than ``bound_mm`` to another selected one; 0 elsewhere."""
    free_mm, free_end = (params.tx_free_start_mm, "start") if curves.layer == "tx" else (params.rx_free_end_mm, "end")
    drop = np.zeros(curves.count, dtype=np.int64)
    if free_mm > 0:
        drop[selected] = free_end_trims(subset_curves(curves, selected), samples.sensing_faces, bound_mm, free_mm, free_end,
                                        walls=walls)
    return drop


def branch_problem(params: OptimizeParams, mesh: Mesh, samples: SurfaceSamples, tx: CurveSet, rx: CurveSet, tx_rx: Crossings,
             tx_tx: Crossings, rx_rx: Crossings) -> SelectionProblem:
    """The branch's phase-1 problem under ``params`` (see :func:`selection_problem`)."""
    bound = params.trace_width_mm + params.clearance_mm if params.enforce_clearance else None
    walls = None if bound is None else walls_for(mesh, bound)
    return selection_problem(geodesics_for(mesh), samples, tx, rx, tx_rx, tx_tx, rx_rx, params.require_base_end, bound,
                             params.tx_free_start_mm, params.rx_free_end_mm, params.trace_width_mm, walls)


def _failed(family: str, angle_deg: float, base: dict, message: str, **report) -> AngleLayout:
    """A branch without a layout: ``message`` says why; ``base`` and ``report`` go into its metrics."""
    return AngleLayout(family, angle_deg, False, message, None, {**base, "feasible": False, "message": message, **report})


@node("layout.bound", params=OptimizeParams, inputs=("mesh", "samples", "tx", "rx", "tx_rx", "tx_tx", "rx_rx"),
      outputs=("bound",))
def bound(params: OptimizeParams, mesh: Mesh, samples: SurfaceSamples, tx: CurveSet, rx: CurveSet, tx_rx: Crossings,
          tx_tx: Crossings, rx_rx: Crossings) -> BranchBound:
    """One branch's phase-1 problem, its heuristic start's radius and a lower bound on its layouts' (what
    ``layout.prescreen`` compares); ``layout.coverage`` and ``layout.finish`` solve it with these parameters."""
    angle_deg = float(np.rad2deg(rx.angle))
    problem = branch_problem(params, mesh, samples, tx, rx, tx_rx, tx_tx, rx_rx)
    base = _branch_report(params, angle_deg, tx, rx, problem)
    try:
        start, radius, low = start_and_bound(problem, params.n_drive, params.n_sense, params.secondary, params.resolution_mm,
                                             params.secondary_power, params.time_limit_s, params.seed, params.workers)
    except UserError as exc:
        return BranchBound(params.model_dump(), rx.family, angle_deg, base, None, None, None, str(exc))
    return BranchBound(params.model_dump(), rx.family, angle_deg, base, start, radius, low, "ok")


@node("layout.coverage", inputs=("mesh", "samples", "tx", "rx", "tx_rx", "tx_tx", "rx_rx", "bound", "prescreen"),
      outputs=("branch",))
def coverage(params: NodeParams, mesh: Mesh, samples: SurfaceSamples, tx: CurveSet, rx: CurveSet, tx_rx: Crossings,
             tx_tx: Crossings, rx_rx: Crossings, bound: BranchBound, prescreen: PreScreen) -> BranchStart:
    """Phase 1's radius stage for a branch the ``prescreen`` keeps (see the module docstring), with the
    parameters of its ``layout.bound``; ``layout.finish`` completes it with them too."""
    p = OptimizeParams.model_validate(bound.params)
    branch_start = functools.partial(BranchStart, bound.params, bound.family, bound.angle_deg, bound.base)
    if bound.lower_bound_mm is None:
        return branch_start(None, bound.message)
    if prescreen.repeated(bound):
        return branch_start(None, "not solved: an earlier Tx pole's branch had its phase-1 start (the two poles on one vertex)",
                            repeated=True)
    if not prescreen.keeps(bound):
        return branch_start(None, f"screened out before its radius stage: its coverage radius is at least "
                                  f"{bound.lower_bound_mm:.1f} mm, above {prescreen.threshold_mm:.1f} mm",
                            prescreened_bound_mm=bound.lower_bound_mm)
    problem = branch_problem(p, mesh, samples, tx, rx, tx_rx, tx_tx, rx_rx)
    try:
        stage = solve_radius_stage(problem, p.n_drive, p.n_sense, p.secondary, p.resolution_mm, p.time_limit_s, p.seed,
                                   p.workers, p.max_model_memberships, p.secondary_power, p.solver, p.highs_max_nodes,
                                   start=bound.start)
    except UserError as exc:
        return branch_start(None, str(exc))
    return branch_start(stage, "ok")


@node("layout.finish", inputs=("mesh", "samples", "tx", "rx", "tx_rx", "tx_tx", "rx_rx", "branch", "screen", "regions"),
      outputs=("candidate",))
def finish(params: NodeParams, mesh: Mesh, samples: SurfaceSamples, tx: CurveSet, rx: CurveSet, tx_rx: Crossings,
           tx_tx: Crossings, rx_rx: Crossings, branch: BranchStart, screen: Screen, regions: SurfaceRegions) -> AngleLayout:
    """:func:`finish_branch` as a node; the candidate carries ``regions`` (``layout.pick_best`` hands the chosen
    branch's to the sinks)."""
    return dataclasses.replace(finish_branch(mesh, samples, tx, rx, tx_rx, tx_tx, rx_rx, branch, screen), regions=regions)


def finish_branch(mesh: Mesh, samples: SurfaceSamples, tx: CurveSet, rx: CurveSet, tx_rx: Crossings, tx_tx: Crossings,
                  rx_rx: Crossings, branch: BranchStart, screen: Screen | None) -> AngleLayout:
    """Phase 1's power-mean stage + phase 2 (pads) + metrics for a branch the ``screen`` keeps (all
    when None), with the parameters of its ``layout.bound``; a branch it drops is reported as
    screened out with its radius stage."""
    params, angle_deg, base = OptimizeParams.model_validate(branch.params), branch.angle_deg, branch.base
    if branch.repeated:
        return _failed(branch.family, angle_deg, base, branch.message, screened=True, repeated=True)
    if branch.prescreened_bound_mm is not None:
        return _failed(branch.family, angle_deg, base, branch.message, screened=True,
                       coverage_radius_lower_bound_mm=branch.prescreened_bound_mm)
    if branch.stage is None:
        return _failed(branch.family, angle_deg, base, branch.message)
    if screen is not None and not screen.keeps(branch):
        message = (f"screened out: its coverage radius is at least {branch.stage.lower_bound_mm:.1f} mm, above "
                   f"{screen.threshold_mm:.1f} mm")
        return _failed(branch.family, angle_deg, base, message, screened=True,
                       coverage_radius_lower_bound_mm=branch.stage.lower_bound_mm, phase1=branch.stage.report)
    problem = branch_problem(params, mesh, samples, tx, rx, tx_rx, tx_tx, rx_rx)  # as layout.bound's, rebuilt: not cached
    if screen is not None and screen.needs_proof(branch) and radius_proven_above(problem, branch.stage, screen.threshold_mm):
        message = f"screened out: no selection of it covers the surface within {screen.threshold_mm:.1f} mm (proven)"
        return _failed(branch.family, angle_deg, base, message, screened=True,
                       coverage_radius_lower_bound_mm=screen.threshold_mm, phase1=branch.stage.report)
    selection = finish_selection(problem, branch.stage, params.relative_gap)
    geo = geodesics_for(mesh)
    bound = params.trace_width_mm + params.clearance_mm if params.enforce_clearance else None
    active = selection.active
    tx_first = np.zeros(tx.count, dtype=np.int64)  # rows trimmed from each Tx candidate's start
    rx_last = np.zeros(rx.count, dtype=np.int64)  # rows trimmed from each Rx candidate's end
    if bound is not None:
        walls = walls_for(mesh, bound)
        tx_first = _free_end_trims(params, samples, tx, selection.tx, bound, walls)
        rx_last = _free_end_trims(params, samples, rx, selection.rx, bound, walls)
        rows = problem.cross_rows[active]
        rx_segments = np.diff(rx.offsets)[problem.cross_rx[active]] - 1  # segments per Rx candidate
        active = active[(tx_rx.seg_a[rows] >= tx_first[problem.cross_tx[active]])
                        & (tx_rx.seg_b[rows] < rx_segments - rx_last[problem.cross_rx[active]])]
    if len(active) == 0:
        message = ("no Tx/Rx crossing is left once the selected curves are trimmed where they come closer "
                   "than trace width + clearance: this branch has no layout (the other branches still count)")
        return _failed(branch.family, angle_deg, base, message, phase1=selection.report)
    active_rows = problem.cross_rows[active]
    fields = geo.fields(tx_rx.faces[active_rows], tx_rx.bary[active_rows])
    distance = geo.pairwise(tx_rx.faces[active_rows], tx_rx.bary[active_rows], fields)
    pads, keep, pad_radius, relaxations = _pads_with_ladder(params, distance, tx_rx.curve_a[active_rows], tx_rx.curve_b[active_rows])
    if not pads.feasible:
        message = (f"no pad placement even with pad radius {pad_radius:g} mm and fewer curves: lower "
                   f"min_pads_per_curve or d_min_mm, or add smaller relax_pad_radii_mm")
        return _failed(branch.family, angle_deg, base, message, relaxations=relaxations, phase1=selection.report,
                       phase2=pads.report)

    design = {"pad_radius_mm": float(pad_radius), "d_min_mm": float(d_min_for(params, pad_radius)),
              "trace_width_mm": params.trace_width_mm, "clearance_mm": params.clearance_mm}
    layout, order = _layout_of(tx, rx, tx_rx, active_rows[keep], pads.pad, design, tx_first, rx_last)
    kept = np.flatnonzero(keep)[order]
    pad_distance = distance[np.ix_(kept[layout.pad], kept[layout.pad])]
    cell_fields = fields[:, kept]
    del fields  # (vertices, active crossings) float32: not kept beside its cells' copy
    quality = layout_metrics(mesh, samples, problem, selection, layout, cell_fields, pad_distance, active[kept],
                             params.n_drive * params.n_sense, params.secondary_power)
    idle = quality.pop("unwired_selected_curves")
    metrics = {**base, "feasible": True, **quality, "phase1": selection.report, "phase2": pads.report,
               "relaxations": relaxations, "unwired_selected_curves": idle}
    return AngleLayout(branch.family, angle_deg, True, "ok" if not relaxations else "relaxed", layout, metrics)


def optimize(params: OptimizeParams, mesh: Mesh, samples: SurfaceSamples, tx: CurveSet, rx: CurveSet, tx_rx: Crossings,
             tx_tx: Crossings, rx_rx: Crossings) -> AngleLayout:
    """One branch start to end, unscreened: ``layout.bound``, ``layout.coverage`` and ``layout.finish`` (plain
    functions)."""
    every = PreScreen(math.inf, math.inf, {}, "")
    branch = coverage(NodeParams(), mesh, samples, tx, rx, tx_rx, tx_tx, rx_rx,
                      bound(params, mesh, samples, tx, rx, tx_rx, tx_tx, rx_rx), every)
    return finish_branch(mesh, samples, tx, rx, tx_rx, tx_tx, rx_rx, branch, None)
