"""Curve benchmark: trivial connections, Tx/Rx families and crossings on a ~20k-vertex mesh.

Pipeline: ``mesh.load`` -> ``mesh.repair`` (keep largest) -> ``mesh.scale`` (170 mm diagonal) ->
``mesh.remesh`` (about ``--vertices`` vertices) -> ``regions.detect``; then timed: ``curves.connection``
for both layers, ``curves.trace_tx`` (100 curves), ``curves.trace_rx`` for the 11 angles -50..50 step 10
(100 curves each) and ``curves.crossings`` per angle. ``seconds`` is the serial sum of the timed work;
``parallel2_seconds`` estimates the wall time when the engine runs the 11 angle branches (trace_rx +
crossings) on 2 processes: connection + Tx + the longer of the two greedy per-process sums.
The sink-edge rate (traces stopped at a sink edge) is reported with sliding along sink edges (the
default) and without it (the paper's rule, ~3 % reported there).

Prints a table; the LAST line is one JSON object. Usage:
``python bench/curves.py [--mesh PATH] [--vertices 20000] [--up-axis +z]``.
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from retrotouch.nodes.curves.connection import ConnectionParams, connection
from retrotouch.nodes.curves.crossings import CrossingsParams, crossings, pair_multiplicity
from retrotouch.nodes.data.types import CurveEnd
from retrotouch.nodes.mesh.loading import LoadParams, ScaleParams, load_mesh, scale_mesh
from retrotouch.nodes.mesh.repair import RemeshParams, RepairParams, remesh, repair_mesh
from retrotouch.nodes.regions.detect import RegionParams, detect_regions
from retrotouch.nodes.regions.touch import TouchParams, touchable_surface
from retrotouch.nodes.curves.tracing import TraceRxParams, TraceTxParams, trace_rx, trace_tx

ANGLES = tuple(range(-50, 51, 10))


def timed(func, *args):
    start = time.perf_counter()
    out = func(*args)
    return out, time.perf_counter() - start


def two_process_makespan(durations: list[float]) -> float:
    """Longest per-process sum when branches go, in order, to the process that frees up first."""
    loads = [0.0, 0.0]
    for d in durations:
        loads[int(np.argmin(loads))] += d
    return max(loads)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", default="builtin:bunny", help="mesh file (default: pymeshlab's bunny)")
    parser.add_argument("--vertices", type=int, default=20000, help="remesh target vertex count")
    parser.add_argument("--up-axis", default=None, help='regions.detect up_axis override, e.g. "+z"')
    args = parser.parse_args()

    mesh = load_mesh(LoadParams(path=args.mesh))
    mesh = repair_mesh(RepairParams(keep_largest=True), mesh)
    mesh = scale_mesh(ScaleParams(diagonal_mm=170.0, about="bbox_center"), mesh)
    touchable = touchable_surface(TouchParams(), mesh)  # as the pipeline: from the mesh before remeshing
    mesh, remesh_s = timed(remesh, RemeshParams(target_vertices=args.vertices), mesh)
    regions = detect_regions(RegionParams(up_axis=args.up_axis), mesh, touchable)

    rows: list[tuple[str, float, str]] = []
    tx_field, t_ctx = timed(connection, ConnectionParams(layer="tx"), mesh, regions)
    rows.append(("connection tx", t_ctx, f"indices ok {tx_field.indices_ok}"))
    rx_field, t_crx = timed(connection, ConnectionParams(layer="rx"), mesh, regions)
    rows.append(("connection rx", t_crx, f"indices ok {rx_field.indices_ok}"))
    tx_out, t_tx = timed(trace_tx, TraceTxParams(), mesh, regions, tx_field)
    tx, tx_stats = tx_out["curves"], tx_out["stats"]
    rows.append(("trace tx", t_tx, f"{tx.count} curves, {tx_stats.face_steps} face steps, base {tx_stats.reached_base_rate:.2f}"))

    branch_s, rx_stats, tx_rx_counts, multi_pairs, rx_rx_counts = [], [], [], [], []
    for angle in ANGLES:
        rx_out, t_rx = timed(trace_rx, TraceRxParams(angle_deg=angle), mesh, regions, rx_field)
        rx = rx_out["curves"]
        cross, t_x = timed(crossings, CrossingsParams(), mesh, tx, rx, tx_field, rx_field)
        mult = pair_multiplicity(cross["tx_rx"], tx.count, rx.count)
        branch_s.append(t_rx + t_x)
        rx_stats.append(rx_out["stats"])
        tx_rx_counts.append(len(cross["tx_rx"].curve_a))
        multi_pairs.append(int(np.count_nonzero(mult > 1)))
        rx_rx_counts.append(len(cross["rx_rx"].curve_a))
        rows.append(
            (
                f"rx {angle:+d} deg + crossings",
                t_rx + t_x,
                f"trace {t_rx:.3f} s, crossings {t_x:.3f} s, base both ends {rx_out['stats'].reached_base_rate:.2f}, "
                f"tx x rx {len(cross['tx_rx'].curve_a)} ({np.count_nonzero(mult == 1)} pairs once, {multi_pairs[-1]} more), "
                f"rx x rx {rx_rx_counts[-1]}, tx x tx {len(cross['tx_tx'].curve_a)}",
            )
        )
    tx_tx = len(cross["tx_tx"].curve_a)

    no_slide_tx = trace_tx(TraceTxParams(slide_sink_edges=False), mesh, regions, tx_field)["stats"]
    no_slide_rx = [trace_rx(TraceRxParams(angle_deg=a, slide_sink_edges=False), mesh, regions, rx_field)["stats"] for a in ANGLES]

    def sink_rate(stats) -> float:
        return float(sum(s.sink_edges for s in stats) / sum(s.traced for s in stats))

    all_stats = [tx_stats] + rx_stats
    seconds = t_ctx + t_crx + t_tx + sum(branch_s)
    result = {
        "mesh": args.mesh,
        "vertices": int(len(mesh.vertices)),
        "faces": int(len(mesh.faces)),
        "seconds": round(seconds, 3),
        "parallel2_seconds": round(t_ctx + t_crx + t_tx + two_process_makespan(branch_s), 3),
        "connection_seconds": round(t_ctx + t_crx, 3),
        "tx_seconds": round(t_tx, 3),
        "rx_branch_seconds_mean": round(float(np.mean(branch_s)), 3),
        "tx_curves": int(tx.count),
        "rx_curves": int(sum(s.kept for s in rx_stats)),
        "rx_angles": len(ANGLES),
        "sink_edge_rate": round(sink_rate(all_stats), 4),
        "sink_edge_rate_without_sliding": round(sink_rate([no_slide_tx] + no_slide_rx), 4),
        "sink_edges_met_per_curve": round(sum(s.sink_hits for s in all_stats) / sum(s.traced for s in all_stats), 3),
        "reached_base_rate": round(float(sum(s.end_counts[CurveEnd.BASE] for s in all_stats) / sum(s.traced for s in all_stats)), 4),
        "tx_reached_base_rate": round(tx_stats.reached_base_rate, 4),
        "rx_both_ends_base_rate": round(float(np.mean([s.reached_base_rate for s in rx_stats])), 4),
        "tx_rx_crossings_per_angle": tx_rx_counts,
        "tx_rx_pairs_crossing_more_than_once_per_angle": multi_pairs,
        "tx_tx_crossings": tx_tx,
        "rx_rx_crossings_per_angle": rx_rx_counts,
        "indices_ok": bool(tx_field.indices_ok and rx_field.indices_ok),
        "remesh_seconds_untimed": round(remesh_s, 3),
    }
    width = max(len(r[0]) for r in rows)
    print(f"{'step':<{width}}  seconds  notes")
    for name, sec, note in rows:
        print(f"{name:<{width}}  {sec:7.3f}  {note}")
    print(f"{'total (serial)':<{width}}  {seconds:7.3f}")
    print(f"{'wall on 2 processes (est.)':<{width}}  {result['parallel2_seconds']:7.3f}")
    print(
        f"sink-edge rate {result['sink_edge_rate']:.2%} with sliding, {result['sink_edge_rate_without_sliding']:.2%} without "
        "(paper: about 3 %)"
    )
    print(json.dumps(result))


if __name__ == "__main__":
    main()
