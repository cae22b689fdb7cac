"""Layout benchmark: the 25-branch sweep of both optimisation phases on a ~20k-vertex mesh.

Preparation (untimed for the sweep): ``mesh.load`` -> ``mesh.repair`` -> ``mesh.scale`` (170 mm
diagonal) -> ``mesh.remesh`` (about ``--vertices``) -> ``regions.detect`` -> ``curves.connection``
(both layers) -> ``curves.trace_tx`` -> the default pipeline's branches: per angle -40..40 step 20
``curves.trace_rx``, per corridor position 0, 0.25, 0.5, 0.75, kind of legs and climb
``curves.trace_rings`` and per winding sense and climb ``curves.trace_helices`` (all but the grid,
which has Tx lines of its own), each with ``curves.crossings`` (``--family dipole``, ``rings`` or
``helices``: one family only), all called as plain functions.

Timed sweep (``sweep_seconds``, wall): ``layout.samples`` (K reference samples and their geodesic fields,
shared by all branches) + ``layout.bound`` for the 25 branches on ``--jobs`` processes (joblib/loky; each
process factorises the heat operators once) + ``layout.prescreen`` + ``layout.coverage`` the same way +
``layout.screen`` (default parameters; ``--no-screen`` solves and finishes every branch) +
``layout.finish`` the same way + ``layout.pick_best``; ``branches_finished`` says how many the screen
kept. The sweep is run a second time with ``secondary=false`` for the ablation
(``voronoi_cv_without_secondary``; skipped with ``--no-ablation``).
``voronoi_cv_fps_all_candidates`` is a reference for what the curve families allow: as many pads
as chosen, spread by farthest-point sampling over all candidate crossings of the chosen angle.

Reported for the chosen branch: ``cells`` of ``channel_pairs`` (n_drive x n_sense), Voronoi CV over
all crossings and over the pads, coverage radius, ``min_same_layer_clearance_mm`` (centre lines of
the selected traces in the sensing region) and the share of each layer's length closer than trace
width + clearance, ``phase1_gap`` (its worst stage on the model's objectives, radius and sum of
distance**p; ``phase1_gap_mm`` the same on the radius and the power mean in mm;
``phase1_gap_worst_branch`` over all branches)
and the notes of failed or far worse branches.

Solver comparison (``--solvers``, default both): phase 1 alone, per branch, through CP-SAT and HiGHS
on the same model, the two solvers of one branch run back to back in one process (``--jobs``
processes over the branches) so that load hits both alike. Per solver and stage: wall seconds of
the solve (model building included), final objective, bound, gap on the model's objective and
``global_gap`` (against the bounds valid without the trust region), median and worst over the
branches, and how many stages ended on the same objective (then the seconds compare time to the
same objective): ``phase1_seconds_by_solver``, ``phase1_gap_by_solver``, ``phase1_same_objective``.

Prints the per-angle table; the LAST line is one JSON object. Usage:
``python bench/layout.py [--mesh PATH] [--vertices 20000] [--jobs 2] [--up-axis +z] [--no-ablation] [--no-screen]``.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from joblib import Parallel, delayed

from retrotouch.graph.node import NodeParams
from retrotouch.nodes.curves.connection import ConnectionParams, connection
from retrotouch.nodes.curves.crossings import CrossingsParams, crossings
from retrotouch.nodes.layout.problem import candidate_crossings
from retrotouch.nodes.layout.metrics import coefficient_of_variation, voronoi_cell_areas
from retrotouch.nodes.layout.pick import PickParams, pick_best
from retrotouch.nodes.layout.selection import select_curves
from retrotouch.nodes.layout.screen import ScreenParams, prescreen, screen_branches
from retrotouch.nodes.layout.sweep import OptimizeParams, bound, branch_problem, coverage, finish
from retrotouch.nodes.mesh.loading import LoadParams, ScaleParams, load_mesh, scale_mesh
from retrotouch.nodes.mesh.repair import RemeshParams, RepairParams, remesh, repair_mesh
from retrotouch.nodes.regions.detect import RegionParams, detect_regions
from retrotouch.nodes.layout.samples import SamplesParams, geodesics_for, surface_samples
from retrotouch.nodes.regions.touch import TouchParams, touchable_surface
from retrotouch.nodes.curves.helices import TraceHelicesParams, trace_helices, winding_angle_node
from retrotouch.nodes.curves.ring_levels import RingLevelsParams, ring_levels
from retrotouch.nodes.curves.rings import TraceRingsParams, trace_rings
from retrotouch.nodes.curves.tracing import TraceRxParams, TraceTxParams, trace_rx, trace_tx

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the default pipeline's helix free end
from layout_quality import HELIX_FREE_END_MM  # noqa: E402

ANGLES = tuple(range(-40, 41, 20))
CORRIDOR_TURNS = (0.0, 0.25, 0.5, 0.75)
RING_LEGS = ("offset", "tx_lines")
WINDINGS = ("left", "right")
CLIMBS = ("median", "per_line")


def prepare(mesh_path: str, vertices: int, up_axis: str | None, family: str = "all"):
    mesh = load_mesh(LoadParams(path=mesh_path))
    mesh = repair_mesh(RepairParams(keep_largest=True), mesh)
    mesh = scale_mesh(ScaleParams(diagonal_mm=170.0, about="bbox_center"), mesh)
    touchable = touchable_surface(TouchParams(), mesh)  # as the pipeline: from the mesh before remeshing
    mesh = remesh(RemeshParams(target_vertices=vertices), mesh)
    regions = detect_regions(RegionParams(up_axis=up_axis), mesh, touchable)
    tx_field = connection(ConnectionParams(layer="tx"), mesh, regions)
    rx_field = connection(ConnectionParams(layer="rx"), mesh, regions)
    tx = trace_tx(TraceTxParams(), mesh, regions, tx_field)["curves"]
    families = []
    if family in ("dipole", "all"):
        families += [trace_rx(TraceRxParams(angle_deg=a), mesh, regions, rx_field)["curves"] for a in ANGLES]
    levels = ring_levels(RingLevelsParams(), mesh, regions, tx_field, tx) if family != "dipole" else None
    if family in ("rings", "all"):
        families += [trace_rings(TraceRingsParams(corridor_turn=t, legs=legs, climb=climb), mesh, regions, levels, tx)["curves"]
                     for t in CORRIDOR_TURNS for legs in RING_LEGS for climb in CLIMBS]
    if family in ("helices", "all"):
        theta = winding_angle_node(None, mesh, levels, tx_field)
        families += [trace_helices(TraceHelicesParams(winding=w, climb=climb), mesh, regions, levels, theta, tx, tx_field)["curves"]
                     for w in WINDINGS for climb in CLIMBS]
    branches = []
    for rx in families:
        cross = crossings(CrossingsParams(), mesh, tx, rx, tx_field, rx_field)
        branches.append((rx, cross["tx_rx"], cross["tx_tx"], cross["rx_rx"]))
    return mesh, regions, tx, branches


def branch_params(params: OptimizeParams, rx) -> OptimizeParams:
    """``params`` as the default pipeline gives them to the branch of ``rx`` (the helices' free end)."""
    return params.model_copy(update={"rx_free_end_mm": HELIX_FREE_END_MM}) if rx.family.startswith("helices") else params


def sweep(params: OptimizeParams, mesh, regions, tx, branches, jobs: int, screened: bool = True):
    start = time.perf_counter()
    samples = surface_samples(SamplesParams(), mesh, regions)
    samples_s = time.perf_counter() - start
    bounds = Parallel(n_jobs=jobs)(
        delayed(bound)(branch_params(params, rx), mesh, samples, tx, rx, tx_rx, tx_tx, rx_rx)
        for rx, tx_rx, tx_tx, rx_rx in branches
    )
    rule = ScreenParams(margin_mm=ScreenParams().margin_mm if screened else None)
    kept = prescreen(rule, bounds, [])
    starts = Parallel(n_jobs=jobs)(
        delayed(coverage)(NodeParams(), mesh, samples, tx, rx, tx_rx, tx_tx, rx_rx, branch_bound, kept)
        for (rx, tx_rx, tx_tx, rx_rx), branch_bound in zip(branches, bounds)
    )
    cut = screen_branches(rule, starts)
    candidates = Parallel(n_jobs=jobs)(
        delayed(finish)(NodeParams(), mesh, samples, tx, rx, tx_rx, tx_tx, rx_rx, branch, cut, regions)
        for (rx, tx_rx, tx_tx, rx_rx), branch in zip(branches, starts)
    )
    picked = pick_best(PickParams(), candidates)
    return picked, time.perf_counter() - start, samples_s


def phase1_branch(params: OptimizeParams, mesh, samples, tx, rx, tx_rx, tx_tx, rx_rx, solvers) -> dict:
    """Phase 1 of one branch through each solver in turn: per solver, per stage seconds and report."""
    problem = branch_problem(params, mesh, samples, tx, rx, tx_rx, tx_tx, rx_rx)
    out = {}
    for solver in solvers:
        start = time.perf_counter()
        result = select_curves(problem, params.n_drive, params.n_sense, params.relative_gap, secondary=params.secondary,
                               resolution_mm=params.resolution_mm, time_limit_s=params.time_limit_s, seed=params.seed,
                               workers=params.workers, max_memberships=params.max_model_memberships,
                               power=params.secondary_power, solver=solver, highs_max_nodes=params.highs_max_nodes)
        out[solver] = {"seconds": time.perf_counter() - start, "stage_seconds": result.stage_seconds,
                       "stages": result.report["stages"]}
    return out


def solver_comparison(mesh, regions, tx, branches, jobs: int, solvers: tuple[str, ...]) -> dict:
    """Phase 1 per branch and solver (see the module docstring): per-stage tables and summaries."""
    samples = surface_samples(SamplesParams(), mesh, regions)
    runs = Parallel(n_jobs=jobs)(delayed(phase1_branch)(branch_params(OptimizeParams(), b[0]), mesh, samples, tx, *b, solvers)
                               for b in branches)
    stats = lambda values: {"median": float(np.median(values)), "worst": float(np.max(values))}  # noqa: E731
    seconds, gaps, same = {}, {}, {}
    names = max((tuple(st["stage"] for st in r[solvers[0]]["stages"]) for r in runs), key=len)
    # a branch without a feasible radius stage has no power stage: each stage's figures are over the branches that ran it
    ran = [[r for r in runs if all(len(r[s]["stage_seconds"]) > i and len(r[s]["stages"]) > i for s in solvers)] for i in range(len(names))]
    for solver in solvers:
        seconds[solver] = {"phase1_total": round(sum(r[solver]["seconds"] for r in runs), 2)}
        gaps[solver] = {}
        for i, name in enumerate(names):
            seconds[solver][name] = {k: round(v, 2) for k, v in stats([r[solver]["stage_seconds"][i] for r in ran[i]]).items()}
            gaps[solver][name] = {"gap": stats([r[solver]["stages"][i]["gap"] for r in ran[i]]),
                                  "global_gap": stats([r[solver]["stages"][i]["global_gap"] for r in ran[i]]),
                                  "statuses": sorted({r[solver]["stages"][i]["status"] for r in ran[i]})}
    for i, name in enumerate(names):
        objectives = [[r[s]["stages"][i]["objective"] for s in solvers] for r in ran[i]]
        same[name] = sum(1 for o in objectives if max(o) - min(o) <= 1e-9 * max(abs(o[0]), 1.0))
    print(f"phase 1 per branch ({len(runs)} branches), seconds / objective / bound / gap per stage")
    for b, r in zip(branches, runs):
        cells = "  ".join(f"{s}: " + " | ".join(f"{sec:.1f}s {st['objective']:.3f}/{st['bound']:.3f} gap {st['gap']:.3f}"
                                                  for sec, st in zip(r[s]["stage_seconds"], r[s]["stages"])) for s in solvers)
        print(f"  {b[0].family:6s} {np.rad2deg(b[0].angle):+5.0f}  {cells}")
    return {"phase1_seconds_by_solver": seconds, "phase1_gap_by_solver": gaps,
            "phase1_same_objective": {"stages_with_same_objective": same, "branches": len(runs)}}


def candidate_cv_reference(mesh, sensing_faces, tx, tx_rx, count: int) -> float:
    """Voronoi CV of ``count`` pads spread by farthest-point sampling over ALL single crossings of a
    branch: what the candidate curves allow at best-effort evenness, independent of the optimiser."""
    rows, _ = candidate_crossings(tx_rx, tx.count, int(tx_rx.curve_b.max()) + 1)
    points = tx_rx.points[rows]
    chosen = [0]
    distance = np.linalg.norm(points - points[0], axis=1)
    for _ in range(count - 1):
        chosen.append(int(np.argmax(distance)))
        distance = np.minimum(distance, np.linalg.norm(points - points[chosen[-1]], axis=1))
    chosen = rows[np.array(chosen)]
    fields = geodesics_for(mesh).fields(tx_rx.faces[chosen], tx_rx.bary[chosen])
    return coefficient_of_variation(voronoi_cell_areas(fields, mesh.vertices, mesh.faces, sensing_faces))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", default="builtin:bunny", help="mesh file (default: pymeshlab's bunny)")
    parser.add_argument("--vertices", type=int, default=20000, help="remesh target vertex count")
    parser.add_argument("--jobs", type=int, default=2, help="processes for the angle branches")
    parser.add_argument("--up-axis", default=None, help='regions.detect up_axis override, e.g. "+z"')
    parser.add_argument("--no-ablation", action="store_true", help="skip the second sweep without the secondary objective")
    parser.add_argument("--no-screen", action="store_true", help="finish every branch (no layout.screen)")
    parser.add_argument("--solvers", default="cpsat,highs", help="phase-1 solvers to compare (comma list; empty: none)")
    parser.add_argument("--family", choices=("all", "dipole", "rings", "helices"), default="all",
                        help="Rx candidates: every family as in the default pipeline, dipole loops per angle (the "
                             "paper), rings around the Tx pole per corridor or helices around it per winding sense")
    args = parser.parse_args()

    start = time.perf_counter()
    mesh, regions, tx, branches = prepare(args.mesh, args.vertices, args.up_axis, args.family)
    curves_s = time.perf_counter() - start

    with_secondary, sweep_s, samples_s = sweep(OptimizeParams(), mesh, regions, tx, branches, args.jobs, not args.no_screen)
    m = with_secondary["metrics"]
    m_off, sweep_off_s = {"voronoi_cv": None, "chosen_angle_deg": None, "mean_distance_mm": None}, 0.0
    if not args.no_ablation:
        without, sweep_off_s, _ = sweep(OptimizeParams(secondary=False), mesh, regions, tx, branches, args.jobs,
                                        not args.no_screen)
        m_off = without["metrics"]
    names = [(b[0].family, round(float(np.rad2deg(b[0].angle)))) for b in branches]
    chosen_branch = branches[names.index((m["rx_family"], round(m["chosen_angle_deg"])))]
    reference_cv = candidate_cv_reference(mesh, regions.sensing_faces, tx, chosen_branch[1], m["pads"])
    solvers = tuple(s for s in args.solvers.split(",") if s)
    comparison = solver_comparison(mesh, regions, tx, branches, args.jobs, solvers) if solvers else {}
    print(f"curves (prep) {curves_s:.1f} s; samples {samples_s:.1f} s; sweep {sweep_s:.1f} s; "
          f"sweep without secondary {sweep_off_s:.1f} s")
    print(f"chosen branch {m['rx_family']} {m['chosen_angle_deg']:+.0f} deg: Voronoi CV {m['voronoi_cv']:.3f} "
          f"(without secondary {m_off['voronoi_cv']}, angle {m_off['chosen_angle_deg']}), "
          f"{m['pads']} pads of {m['cells']} cells, radius {m['coverage_radius_mm']:.1f} mm, "
          f"mean {m['mean_distance_mm']:.2f} mm, min pad spacing {m['min_pad_spacing_mm']:.1f} mm")
    print(f"reference: {m['pads']} pads by farthest-point sampling over all candidate crossings of that "
          f"angle give Voronoi CV {reference_cv:.3f}")
    print(json.dumps({
        "mesh": args.mesh,
        "family": args.family,
        "vertices": int(len(mesh.vertices)),
        "sweep_seconds": round(sweep_s, 2),
        "branches_finished": sum(not r["screened"] for r in m["angles"]),
        "samples_seconds": round(samples_s, 2),
        "curves_seconds": round(curves_s, 2),
        "jobs": args.jobs,
        "chosen_rx_family": m["rx_family"],
        "chosen_angle_deg": m["chosen_angle_deg"],
        "voronoi_cv": m["voronoi_cv"],
        "voronoi_cv_pads": m["voronoi_cv_pads"],
        "voronoi_cv_all_crossings": m["voronoi_cv_all_crossings"],
        "channel_pairs": m["channel_pairs"],
        "min_same_layer_clearance_mm": m["min_same_layer_clearance_mm"],
        "share_closer_than_bound": {layer: c["share_closer_than_bound"] for layer, c in m["same_layer_clearance"].items()},
        "phase1_gap": m["phase1_gap"],
        "phase1_gap_mm": m["phase1_gap_mm"],
        "phase1_gap_worst_branch": max((r["gap"] for r in m["angles"] if r["gap"] is not None), default=None),
        "phase1_global_gap_worst_branch": max((r["global_gap"] for r in m["angles"] if r["global_gap"] is not None),
                                              default=None),
        "branch_notes": {f"{r['rx_family']} {r['angle_deg']:+.0f}": r["note"] for r in m["angles"] if r["note"]},
        "voronoi_cv_without_secondary": m_off["voronoi_cv"],
        "pads": m["pads"],
        "cells": m["cells"],
        "channels": [m["tx_channels"], m["rx_channels"]],
        "coverage_radius_mm": m["coverage_radius_mm"],
        "coverage_radius_vertices_mm": m["coverage_radius_vertices_mm"],
        "uncovered_share": m["uncovered_share"],
        "mean_distance_mm": m["mean_distance_mm"],
        "mean_distance_mm_without_secondary": m_off["mean_distance_mm"],
        "min_pad_spacing_mm": m["min_pad_spacing_mm"],
        "voronoi_cv_fps_all_candidates": reference_cv,
        "paper_voronoi_cv_bunny": 0.374,
        "phase1_solver": OptimizeParams().solver,
        "phase1_global_gap": m["phase1_global_gap"],
        "phase1_gap_median_branch": float(np.median([r["gap"] for r in m["angles"] if r["gap"] is not None])),
        **comparison,
    }))


if __name__ == "__main__":
    main()
