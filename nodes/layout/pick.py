"""``layout.pick_best``: the best branch of the layout sweep and the per-branch table.

A branch is one curve family (dipole loops, rings, helices or the grid) at one angle, around one Tx pole; branches
of several families (and poles) arrive as one list (``candidates: ["finish[*]", "ring_finish[*]", ...]``)
and are taken in order; the chosen branch's regions go to the sinks with its layout. The best has
the smallest coverage radius (within ``radius_tolerance_mm``), then the smallest power mean of the
sample distances when the secondary objective is on (within ``mean_tolerance`` of it, relative),
then the most cells, then the smallest Voronoi CV of the pads. Every branch gets a row in
``metrics["angles"]`` and the printed table, with its notes: a failed branch with its reason, a
branch ``layout.screen`` left unfinished with its lower bound, one ``layout.prescreen`` left unsolved
as an earlier Tx pole's repeat (status REPEATED), and a feasible branch whose coverage
radius exceeds ``outlier_factor`` times the median of the feasible branches as far worse. A screened
branch whose lower bound is within ``radius_tolerance_mm`` of the chosen radius could have tied it:
that is warned about, with the fix. Units: mm, deg.
"""
from __future__ import annotations

import logging

import numpy as np
from pydantic import Field

from ...graph.errors import UserError
from ...graph.node import NodeParams, node
from .sweep import AngleLayout

log = logging.getLogger(__name__)


class PickParams(NodeParams):
    print_table: bool = Field(True, description="print the per-angle table to the console")
    radius_tolerance_mm: float = Field(
        1.0, ge=0, description="coverage radii within this of the best count as equal (then mean, then CV)"
    )
    mean_tolerance: float = Field(
        0.05, ge=0, description="power means within this share of the best count as equal (then most cells, then CV)"
    )
    outlier_factor: float = Field(
        1.5, gt=1, description="a branch whose coverage radius exceeds this times the median is noted as far worse"
    )


def best_branch(candidates: list[AngleLayout], radius_tolerance_mm: float, mean_tolerance: float = 0.0) -> int:
    """Index of the best feasible branch: smallest coverage radius (ties within the tolerance, since
    the K samples resolve no finer), then the secondary objective when it is on (power mean of the
    sample distances; ties within ``mean_tolerance`` of the best, relative), then the most cells (the
    sensor's resolution), then the Voronoi CV."""
    feasible = [i for i, c in enumerate(candidates) if c.feasible]
    best_radius = min(candidates[i].metrics["coverage_radius_mm"] for i in feasible)
    tied = [i for i in feasible if candidates[i].metrics["coverage_radius_mm"] <= best_radius + radius_tolerance_mm]
    mean = {i: candidates[i].metrics["power_mean_distance_mm"] if candidates[i].metrics["secondary"] else 0.0 for i in tied}
    best_mean = min(mean.values())
    tied = [i for i in tied if mean[i] <= best_mean * (1.0 + mean_tolerance)]

    def key(i: int) -> tuple:
        m = candidates[i].metrics
        cv = m["voronoi_cv"] if m["voronoi_cv"] is not None else float("inf")
        return (-(m.get("cells") or 0), cv, mean[i], m["coverage_radius_mm"])

    return min(tied, key=key)


def branch_notes(candidates: list[AngleLayout], outlier_factor: float) -> list[str]:
    """Per branch: its failure or screening reason, a 'far worse' note when its coverage radius exceeds
    ``outlier_factor`` times the median of the feasible branches, or ''."""
    radii = [c.metrics["coverage_radius_mm"] for c in candidates if c.feasible]
    median = float(np.median(radii)) if radii else float("nan")
    notes = []
    for c in candidates:
        if c.metrics.get("screened"):
            notes.append(c.message)
        elif not c.feasible:
            notes.append(f"failed: {c.message}")
        elif c.metrics["coverage_radius_mm"] > outlier_factor * median:
            notes.append(f"far worse: coverage radius {c.metrics['coverage_radius_mm']:.1f} mm > "
                         f"{outlier_factor:g} x median {median:.1f} mm")
        else:
            notes.append("")
    return notes


def _deterministic_time(metrics: dict) -> float | None:
    """CP-SAT's deterministic time of a branch (phase-1 stages plus phase 2; a reproducible measure of
    the solver's work, unlike wall seconds), or None for a branch that did not solve."""
    stages = metrics.get("phase1", {}).get("stages", [])
    if not stages:
        return None
    phase1 = sum(st.get("deterministic_time", 0.0) for st in stages)  # HiGHS stages report nodes instead
    return phase1 + metrics.get("phase2", {}).get("deterministic_time", 0.0)


def angle_table(candidates: list[AngleLayout], outlier_factor: float = 1.5) -> list[dict]:
    """One row per branch: Rx family, angle, stage-1 radius, coverage, Voronoi CV (all crossings, pads),
    cells, clearance, phase-1 gap, CP-SAT deterministic time, status and notes."""
    rows = []
    for c, note in zip(candidates, branch_notes(candidates, outlier_factor)):
        m = c.metrics
        stages = m.get("phase1", {}).get("stages", [])
        rows.append({
            "rx_family": c.family,
            "angle_deg": c.angle_deg,
            "tx_pole": c.regions.tx_pole if c.regions is not None else None,
            "feasible": c.feasible,
            "screened": bool(m.get("screened")),
            "stage1_radius_mm": stages[0]["objective"] if stages else None,
            "coverage_radius_mm": m.get("coverage_radius_mm"),
            "mean_distance_mm": m.get("mean_distance_mm"),
            "voronoi_cv": m.get("voronoi_cv"),
            "voronoi_cv_all_crossings": m.get("voronoi_cv_all_crossings"),
            "pads": m.get("pads"),
            "cells": m.get("cells"),
            "channel_pairs": m.get("channel_pairs"),
            "min_same_layer_clearance_mm": m.get("min_same_layer_clearance_mm"),
            "channels": f"{m.get('tx_channels', 0)}x{m.get('rx_channels', 0)}",
            "deterministic_time": _deterministic_time(m),
            "status": "/".join(s["status"] for s in stages) or (
                "REPEATED" if m.get("repeated") else "PRESCREENED" if m.get("screened") else c.message),
            "gap": None if not stages or any(s["gap"] is None for s in stages) else max(s["gap"] for s in stages),
            "global_gap": None if not stages or any(s.get("global_gap") is None for s in stages)
            else max(s["global_gap"] for s in stages),
            "bound": [s.get("bound") for s in stages],
            "relaxations": len(m.get("relaxations", [])),
            "note": note,
        })
    return rows


def print_angle_table(rows: list[dict], best: int) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title="layout per branch: Rx family and angle (* = chosen; r1 = radius after phase 1's first stage)")
    columns = ("family", "angle", "pole", "r1 mm", "radius mm", "mean mm", "CV all", "CV pads", "cells", "pads", "clear mm", "channels", "det t",
               "status", "gap", "relax", "note")
    for name in columns:
        table.add_column(name, justify="right")
    fmt = lambda v, f: "-" if v is None else format(v, f)  # noqa: E731
    for i, r in enumerate(rows):
        cells = "-" if r["cells"] is None else f"{r['cells']}/{r['channel_pairs']}"
        table.add_row(("*" if i == best else "") + r["rx_family"], fmt(r["angle_deg"], "+.0f"), r["tx_pole"] or "-",
                      fmt(r["stage1_radius_mm"], ".1f"),
                      fmt(r["coverage_radius_mm"], ".2f"),
                      fmt(r["mean_distance_mm"], ".2f"), fmt(r["voronoi_cv_all_crossings"], ".3f"),
                      fmt(r["voronoi_cv"], ".3f"), cells, fmt(r["pads"], "d"), fmt(r["min_same_layer_clearance_mm"], ".2f"),
                      r["channels"], fmt(r["deterministic_time"], ".1f"), r["status"], fmt(r["gap"], ".3f"), str(r["relaxations"]),
                      r["note"])
    Console(stderr=True, width=200).print(table)


def best_note(outputs: dict[str, object]) -> str:
    """The run summary's line on the chosen layout: family, cells, coverage radius and where it is thin."""
    m, regions = outputs["metrics"], outputs["regions"]  # type: ignore[assignment]
    line = (f"chosen {m['rx_family']} at {m['chosen_angle_deg']:+.0f} deg around the {regions.tx_pole} Tx pole: "
            f"{m['cells']} of {m['channel_pairs']} channel pairs as cells, coverage radius {m['coverage_radius_mm']:.1f} mm "
            f"({m['coverage_radius_vertices_mm']:.1f} over every touchable vertex); {100 * m['uncovered_share']:.1f}% of the "
            f"touchable sensing area is farther than {m['uncovered_threshold_mm']:g} mm from every cell")
    if m["uncovered_spots"]:
        spot = m["uncovered_spots"][0]
        line += (f", the largest spot {spot['area_mm2']:.0f} mm2 up to {spot['max_distance_mm']:.1f} mm at "
                 f"({', '.join(f'{x:.0f}' for x in spot['point'])}) mm")
    return line


@node("layout.pick_best", params=PickParams, inputs=("candidates",), outputs=("layout", "metrics", "regions"), note=best_note)
def pick_best(params: PickParams, candidates: list[AngleLayout]) -> dict[str, object]:
    """Keep the best branch (radius, secondary, cells, Voronoi CV), its regions, and the per-branch table."""
    if not candidates:
        raise UserError("no layout branch to pick from: the Tx poles' list, or every Rx family's, is empty ([]); give "
                        "them at least one value (e.g. -S tx_poles=[far] -S helix_windings=[left])")
    feasible = [i for i, c in enumerate(candidates) if c.feasible]
    screened = [c for c in candidates if c.metrics.get("screened")]
    if not feasible:
        reasons = "; ".join(f"{c.family} {c.angle_deg:+.0f} deg: {c.message}" for c in candidates)
        fix = " (rerun with -S prescreen.margin_mm=null to solve and finish the screened ones)" if screened else ""
        raise UserError(f"no branch gives a feasible layout{fix} ({reasons})")
    best = best_branch(candidates, params.radius_tolerance_mm, params.mean_tolerance)
    reach = candidates[best].metrics["coverage_radius_mm"] + params.radius_tolerance_mm
    missed = [c for c in screened if not c.metrics.get("repeated") and c.metrics["coverage_radius_lower_bound_mm"] <= reach]
    if missed:
        log.warning("%d screened branch(es) could have tied the chosen one (coverage radius %.1f mm): rerun with a larger "
                    "-S prescreen.margin_mm, or null to solve and finish every branch", len(missed),
                    reach - params.radius_tolerance_mm)
    rows = angle_table(candidates, params.outlier_factor)
    if params.print_table:
        print_angle_table(rows, best)
    chosen = candidates[best]
    metrics = {**chosen.metrics, "chosen_angle_deg": chosen.angle_deg, "angles": rows}
    return {"layout": chosen.layout, "metrics": metrics, "regions": chosen.regions}
