"""The layout optimisation per Rx angle (``layout.optimize``, mapped) and the pick (``layout.pick_best``).

``layout.optimize`` runs, for one Rx candidate family (one initial angle): phase 1 curve selection
(:mod:`retrotouch.nodes.layout.selection`), geodesic distances among the active crossings, phase 2
pad placement (:mod:`retrotouch.nodes.layout.pads`) with the relaxation ladder, and the metrics
(:mod:`retrotouch.nodes.layout.metrics`). ``layout.pick_best`` takes the branches in order and
keeps the best by (coverage radius within ``radius_tolerance_mm`` of the best, then mean distance
when the secondary objective is on, then Voronoi CV), and returns the per-angle table.

Relaxation ladder, applied only when phase 2 is infeasible (some selected curve cannot carry
``min_pads_per_curve`` pads at spacing ``d_min``): (1) smaller pads, each radius of
``relax_pad_radii_mm`` in turn (``d_min`` scales with the pad diameter); (2) fewer curves: drop
the curves that get no pad in an unconstrained maximum pad set. Every step is logged as a warning
and recorded in ``metrics["relaxations"]``; a branch where nothing works is reported infeasible
with the reason, and :func:`pick_best` raises a UserError naming what to change if no branch is
feasible. Units: mm, degrees in Params and in the reports.
"""
from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np
from pydantic import Field

from ...graph.errors import UserError
from ...graph.node import NodeParams, node
from .problem import (
    PHASE1_MAX_MEMBERSHIPS,
    PHASE1_POWER,
    PHASE1_RESOLUTION_MM,
    PHASE1_TIME_LIMIT_S,
    SelectionProblem,
    candidate_crossings,
    evaluate_selection,
    same_layer_conflicts,
)
from .selection import select_curves
from ..data.types import Crossings, CurveEnd, CurveSet, Layout, Mesh
from .metrics import coefficient_of_variation, min_pairwise, voronoi_cell_areas
from .pads import PAD_TIME_LIMIT_S, PadResult, place_pads, sparseness
from .samples import HeatGeodesics, SurfaceSamples, geodesics_for

log = logging.getLogger(__name__)


class OptimizeParams(NodeParams):
    n_drive: int = Field(21, ge=1, le=128, description="Tx channels available (N_drive; 21 on the Muca board)")
    n_sense: int = Field(12, ge=1, le=128, description="Rx channels available (N_sense; 12 on the Muca board)")
    secondary: bool = Field(True, description="also minimise the sample distances (off: ablation)")
    secondary_power: int = Field(
        PHASE1_POWER, ge=1, le=8, description="secondary objective: power mean of sample distances (1 = plain mean)"
    )
    resolution_mm: float = Field(PHASE1_RESOLUTION_MM, gt=0, le=5, description="distance quantisation of the phase-1 model (mm)")
    time_limit_s: float = Field(PHASE1_TIME_LIMIT_S, gt=0, description="per CP-SAT solve, deterministic seconds (wall guard 4x)")
    pad_time_limit_s: float = Field(PAD_TIME_LIMIT_S, gt=0, description="phase-2 CP-SAT limit, deterministic seconds")
    max_model_memberships: int = Field(
        PHASE1_MAX_MEMBERSHIPS, ge=100, description="phase-1 model size cap in (sample, crossing) pairs; beyond it a trust region"
    )
    workers: int = Field(1, ge=1, le=16, description="CP-SAT workers per solve (1 = reproducible)")
    seed: int = Field(0, description="CP-SAT random seed")
    require_base_end: bool = Field(True, description="only curves that reach the base can be wired")
    pad_radius_mm: float = Field(2.0, gt=0, description="electrode pad radius (mm)")
    d_min_mm: float | None = Field(
        None, gt=0, description="minimum geodesic pad spacing (mm); default twice the pad diameter"
    )
    min_pads_per_curve: int = Field(1, ge=0, description="pads every selected curve must carry")
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
    """One Rx-angle branch: its layout (None when infeasible) and its metrics/report."""

    angle_deg: float
    feasible: bool
    message: str
    layout: Layout | None
    metrics: dict


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
    )


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
) -> SelectionProblem:
    """Phase-1 input from the curve families: single crossings, C1/C2 conflicts, sample distances."""
    rows, multi = candidate_crossings(tx_rx, tx.count, rx.count)
    return SelectionProblem(
        tx_usable=_usable(tx, require_base_end),
        rx_usable=_usable(rx, require_base_end),
        cross_tx=tx_rx.curve_a[rows].astype(np.int64),
        cross_rx=tx_rx.curve_b[rows].astype(np.int64),
        cross_rows=rows,
        distance=geo.evaluate(samples.distances, tx_rx.faces[rows], tx_rx.bary[rows]),
        multi_pairs=multi,
        tx_conflicts=same_layer_conflicts(tx_tx),
        rx_conflicts=same_layer_conflicts(rx_rx),
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
        "angle_deg": angle_deg,
        "secondary": params.secondary,
        "secondary_power": params.secondary_power,
        "candidates": {"tx": tx.count, "rx": rx.count, "tx_usable": int(problem.tx_usable.sum()),
                       "rx_usable": int(problem.rx_usable.sum()), "single_crossings": len(problem.cross_rows),
                       "multi_crossing_pairs": len(problem.multi_pairs), "tx_conflicts": len(problem.tx_conflicts),
                       "rx_conflicts": len(problem.rx_conflicts)},
    }


def _layout_of(tx: CurveSet, rx: CurveSet, tx_rx: Crossings, cells_rows: np.ndarray, pad: np.ndarray) -> tuple[Layout, np.ndarray]:
    """The layout of the kept crossings ``cells_rows`` (rows of ``tx_rx``) and their pad flags: channels
    are the curves with at least one kept crossing, cells sorted by (Tx channel, Rx channel). Returns
    the layout and the order applied to ``cells_rows``."""
    tx_sel, rx_sel = np.unique(tx_rx.curve_a[cells_rows]), np.unique(tx_rx.curve_b[cells_rows])
    order = np.lexsort((np.searchsorted(rx_sel, tx_rx.curve_b[cells_rows]),
                        np.searchsorted(tx_sel, tx_rx.curve_a[cells_rows])))
    cells_rows = cells_rows[order]
    cells = Crossings(
        layer_a="tx", layer_b="rx",
        curve_a=np.searchsorted(tx_sel, tx_rx.curve_a[cells_rows]).astype(np.int64),
        curve_b=np.searchsorted(rx_sel, tx_rx.curve_b[cells_rows]).astype(np.int64),
        seg_a=tx_rx.seg_a[cells_rows], seg_b=tx_rx.seg_b[cells_rows],
        arc_a=tx_rx.arc_a[cells_rows], arc_b=tx_rx.arc_b[cells_rows],
        points=tx_rx.points[cells_rows], faces=tx_rx.faces[cells_rows], bary=tx_rx.bary[cells_rows],
    )
    layout = Layout(tx=subset_curves(tx, tx_sel), rx=subset_curves(rx, rx_sel), cells=cells, pad=pad[order],
                    tx_source=tx_sel, rx_source=rx_sel)
    return layout, order


def _layout_metrics(params, mesh, samples, problem, selection, layout, cell_fields, pad_distance, pad_radius) -> dict:
    """Quality figures of a branch's layout (coverage, Voronoi CV of the pads, counts, lengths)."""
    tx_sel, rx_sel, pad = layout.tx_source, layout.rx_source, layout.pad
    _, nearest = evaluate_selection(problem, tx_sel, rx_sel)
    cell_area = voronoi_cell_areas(cell_fields[:, pad], mesh.vertices, mesh.faces, samples.sensing_faces)
    tx_lengths, rx_lengths = layout.tx.lengths_mm, layout.rx.lengths_mm
    return {
        "coverage_radius_mm": float(nearest.max()),
        "mean_distance_mm": float(nearest.mean()),
        "power_mean_distance_mm": float(np.mean(nearest**params.secondary_power) ** (1.0 / params.secondary_power)),
        "voronoi_cv": coefficient_of_variation(cell_area) if pad.sum() else None,
        "voronoi_cell_area_mm2": {"mean": float(cell_area.mean()), "min": float(cell_area.min()),
                                  "max": float(cell_area.max())} if pad.sum() else None,
        "pads": int(pad.sum()),
        "cells": int(len(pad)),
        "tx_channels": int(len(tx_sel)),
        "rx_channels": int(len(rx_sel)),
        "pad_radius_mm": float(pad_radius),
        "d_min_mm": float(d_min_for(params, pad_radius)),
        "min_pad_spacing_mm": min_pairwise(pad_distance) if pad.sum() > 1 else None,
        "curve_lengths_mm": {"tx": [float(v) for v in tx_lengths], "rx": [float(v) for v in rx_lengths],
                             "total": float(tx_lengths.sum() + rx_lengths.sum())},
        "unwired_selected_curves": {"tx": [int(a) for a in np.setdiff1d(selection.tx, tx_sel)],
                                    "rx": [int(b) for b in np.setdiff1d(selection.rx, rx_sel)]},
    }


@node(
    "layout.optimize",
    params=OptimizeParams,
    inputs=("mesh", "samples", "tx", "rx", "tx_rx", "tx_tx", "rx_rx"),
    outputs=("candidate",),
)
def optimize(
    params: OptimizeParams,
    mesh: Mesh,
    samples: SurfaceSamples,
    tx: CurveSet,
    rx: CurveSet,
    tx_rx: Crossings,
    tx_tx: Crossings,
    rx_rx: Crossings,
) -> AngleLayout:
    """Phase 1 (curve selection) + phase 2 (pads) + metrics for one Rx-angle branch (see the module docstring)."""
    t0 = time.perf_counter()
    angle_deg = float(np.rad2deg(rx.angle))
    geo = geodesics_for(mesh)
    problem = selection_problem(geo, samples, tx, rx, tx_rx, tx_tx, rx_rx, params.require_base_end)
    base = _branch_report(params, angle_deg, tx, rx, problem)
    try:
        selection = select_curves(problem, params.n_drive, params.n_sense, params.secondary,
                                  params.resolution_mm, params.time_limit_s, params.seed, params.workers,
                                  params.max_model_memberships, params.secondary_power)
    except UserError as exc:
        return AngleLayout(angle_deg, False, str(exc), None, {**base, "feasible": False, "message": str(exc)})
    t1 = time.perf_counter()

    active_rows = problem.cross_rows[selection.active]
    fields = geo.fields(tx_rx.faces[active_rows], tx_rx.bary[active_rows])
    distance = geo.evaluate(fields, tx_rx.faces[active_rows], tx_rx.bary[active_rows])
    distance = 0.5 * (distance + distance.T)
    t2 = time.perf_counter()
    pads, keep, pad_radius, relaxations = _pads_with_ladder(params, distance, tx_rx.curve_a[active_rows], tx_rx.curve_b[active_rows])
    if not pads.feasible:
        message = (f"no pad placement even with pad radius {pad_radius:g} mm and fewer curves: lower "
                   f"min_pads_per_curve or d_min_mm, or add smaller relax_pad_radii_mm")
        return AngleLayout(angle_deg, False, message, None,
                           {**base, "feasible": False, "message": message, "relaxations": relaxations,
                            "phase1": selection.report, "phase2": pads.report})
    t3 = time.perf_counter()

    layout, order = _layout_of(tx, rx, tx_rx, active_rows[keep], pads.pad)
    kept = np.flatnonzero(keep)[order]
    pad_distance = distance[np.ix_(kept[layout.pad], kept[layout.pad])]
    quality = _layout_metrics(params, mesh, samples, problem, selection, layout, fields[:, kept], pad_distance, pad_radius)
    t4 = time.perf_counter()
    idle = quality.pop("unwired_selected_curves")
    metrics = {**base, "feasible": True, **quality, "phase1": selection.report, "phase2": pads.report,
               "relaxations": relaxations, "unwired_selected_curves": idle,
               "seconds": {"phase1": t1 - t0, "crossing_geodesics": t2 - t1, "phase2": t3 - t2, "metrics": t4 - t3,
                           "total": t4 - t0}}
    return AngleLayout(angle_deg, True, "ok" if not relaxations else "relaxed", layout, metrics)


class PickParams(NodeParams):
    print_table: bool = Field(True, description="print the per-angle table to the console")
    radius_tolerance_mm: float = Field(
        1.0, ge=0, description="coverage radii within this of the best count as equal (then mean, then CV)"
    )


def best_branch(candidates: list[AngleLayout], radius_tolerance_mm: float) -> int:
    """Index of the best feasible branch: smallest coverage radius (ties within the tolerance, since
    the K samples resolve no finer), then the secondary objective when it is on (power mean of the
    sample distances), then the Voronoi CV."""
    feasible = [i for i, c in enumerate(candidates) if c.feasible]
    best_radius = min(candidates[i].metrics["coverage_radius_mm"] for i in feasible)
    tied = [i for i in feasible if candidates[i].metrics["coverage_radius_mm"] <= best_radius + radius_tolerance_mm]

    def key(i: int) -> tuple:
        m = candidates[i].metrics
        mean = m["power_mean_distance_mm"] if m["secondary"] else 0.0
        cv = m["voronoi_cv"] if m["voronoi_cv"] is not None else float("inf")
        return (mean, cv, m["coverage_radius_mm"])

    return min(tied, key=key)


def angle_table(candidates: list[AngleLayout]) -> list[dict]:
    """One row per branch: angle, objective, CV, pads, seconds, status."""
    rows = []
    for c in candidates:
        m = c.metrics
        stages = m.get("phase1", {}).get("stages", [])
        rows.append({
            "angle_deg": c.angle_deg,
            "feasible": c.feasible,
            "coverage_radius_mm": m.get("coverage_radius_mm"),
            "mean_distance_mm": m.get("mean_distance_mm"),
            "voronoi_cv": m.get("voronoi_cv"),
            "pads": m.get("pads"),
            "channels": f"{m.get('tx_channels', 0)}x{m.get('rx_channels', 0)}",
            "seconds": m.get("seconds", {}).get("total"),
            "status": "/".join(s["status"] for s in stages) or c.message,
            "gap": None if not stages or any(s["gap"] is None for s in stages) else max(s["gap"] for s in stages),
            "relaxations": len(m.get("relaxations", [])),
        })
    return rows


def print_angle_table(rows: list[dict], best: int) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title="layout per Rx angle (* = chosen)")
    for name in ("angle", "radius mm", "mean mm", "Voronoi CV", "pads", "channels", "s", "status", "gap", "relax"):
        table.add_column(name, justify="right")
    fmt = lambda v, f: "-" if v is None else format(v, f)  # noqa: E731
    for i, r in enumerate(rows):
        table.add_row(("*" if i == best else "") + fmt(r["angle_deg"], "+.0f"), fmt(r["coverage_radius_mm"], ".2f"),
                      fmt(r["mean_distance_mm"], ".2f"), fmt(r["voronoi_cv"], ".3f"), fmt(r["pads"], "d"),
                      r["channels"], fmt(r["seconds"], ".1f"), r["status"], fmt(r["gap"], ".3f"),
                      str(r["relaxations"]))
    Console(stderr=True, width=140).print(table)


@node("layout.pick_best", params=PickParams, inputs=("candidates",), outputs=("layout", "metrics"))
def pick_best(params: PickParams, candidates: list[AngleLayout]) -> dict[str, object]:
    """Keep the best Rx-angle branch (radius, secondary, Voronoi CV) and the per-angle table."""
    feasible = [i for i, c in enumerate(candidates) if c.feasible]
    if not feasible:
        reasons = "; ".join(f"{c.angle_deg:+.0f} deg: {c.message}" for c in candidates)
        raise UserError(f"no Rx angle gives a feasible layout ({reasons})")
    best = best_branch(candidates, params.radius_tolerance_mm)
    rows = angle_table(candidates)
    if params.print_table:
        print_angle_table(rows, best)
    chosen = candidates[best]
    metrics = {**chosen.metrics, "chosen_angle_deg": chosen.angle_deg, "angles": rows}
    return {"layout": chosen.layout, "metrics": metrics}
