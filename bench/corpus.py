"""Corpus benchmark: the default pipeline, with no overrides, on every object a user may bring.

Runs ``retrotouch run pipelines/retrofit.yaml -S mesh=PATH -S diagonal_mm=D -S vertices=N`` (one
fresh process per mesh, a shared cache folder) on every mesh or point cloud in ``--meshes`` (default
``../shared/meshes``) and on one generated shape per class of ``tests/shapes.py`` (a plate, a bowl
with a foot ring, a four-legged figurine, a figure standing on two legs and one with its arms stretched
out, a lying spoon-like object, a thin metal spoon, a bust with a cut base, a box, a phone-sized slab, a
lying starfish, a narrow-necked vase, a point-cloud scan with holes and fragments; written at their
natural size).
``--sizes FILE.json`` maps a mesh file's stem to its bounding-box diagonal in mm (default 170 mm; the
generated shapes keep their own size). The pose, base and sensing region are read from the run's ``metrics.json``.

Prints one row per mesh (mesh, ok, pose and base kind, tipping angle, base and sensing area % of the
surface, the % of the sensing area a finger can touch, cells, pads, Voronoi CV over the pads and over
all crossings, coverage radius mm, the % of the touchable sensing area farther than 10 mm from every
cell (``uncovered_share`` of metrics.json) and the same over the whole sensing region, touchable or
not (``sensing_region``), phase 1's gap, the chosen Rx family and Tx pole, whether the pipeline's
fallback ran its second sweep (``manifest.json``), sheets, joints, the limbs (``limbs`` of metrics.json) and how
many of them hold no cell, seconds) and, as the LAST line,
one JSON object with ``meshes``, ``succeeded``, ``failures`` (list of ``{mesh, node, message}``),
``median_voronoi_cv``, ``median_cells``, the worst cases, ``fallback_runs``, ``chosen_tx_poles``,
``limbs`` and ``limbs_without_cells`` (totals)
and per-row details. Usage::

    python bench/corpus.py [--meshes DIR] [--sizes FILE.json] [--vertices N] [--angles -20,0,20]
                           [--set KEY=VALUE ...] [--only STEM ...] [--no-shapes] [--cache-dir DIR] [--timeout S]
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))  # the generated shapes are test fixtures, shared with the e2e tests

import shapes  # noqa: E402

from retrotouch.nodes.mesh.loading import SUPPORTED_SUFFIXES  # noqa: E402  (every file the pipeline reads)

DEFAULT_DIAGONAL_MM = 170.0
ERROR_LINE = re.compile(r"error: node (?P<node>[\w.\-]+)(?:\[[^\]]*\])?: (?P<message>.*)")


def run_pipeline(mesh_path: Path, diagonal_mm: float, args: argparse.Namespace, out: Path) -> tuple[int, str, float]:
    """``(exit code, stderr, seconds)`` of one default-pipeline run into ``out``."""
    command = [
        sys.executable, "-m", "retrotouch.nodes", "run", str(REPO / "pipelines" / "retrofit.yaml"),
        "--out", str(out), "--cache-dir", str(args.cache_dir),
        "-S", f"mesh={mesh_path}", "-S", f"diagonal_mm={diagonal_mm}", "-S", f"vertices={args.vertices}",
    ]
    if args.angles:
        command += ["-S", f"rx_angles_deg=[{args.angles}]"]
    for override in args.set:
        command += ["-S", override]
    start = time.perf_counter()
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=args.timeout, cwd=out.parent)
        code, stderr = done.returncode, done.stderr
    except subprocess.TimeoutExpired:
        code, stderr = -1, f"error: node timeout: no result within {args.timeout} s"
    return code, stderr, time.perf_counter() - start


def failure(stem: str, stderr: str) -> dict[str, str]:
    """``{mesh, node, message}`` from a failed run's stderr (its last error line)."""
    for line in reversed(stderr.strip().splitlines()):
        match = ERROR_LINE.search(line)
        if match:
            return {"mesh": stem, "node": match["node"], "message": match["message"][:300]}
    tail = stderr.strip().splitlines()[-1] if stderr.strip() else "no output"
    return {"mesh": stem, "node": "?", "message": tail[:300]}


def measured(stem: str, out: Path) -> dict[str, object]:
    """The row of a successful run: layout metrics, sheet count, pose, base and sensing region, the
    chosen layout's Tx pole and whether the pipeline's fallback (a second sweep) ran."""
    metrics = json.loads((out / "metrics.json").read_text())
    manifest = json.loads((out / "manifest.json").read_text())
    report = json.loads((out / "sheets" / "report.json").read_text())
    sheet_count = report.get("sheet", {}).get("count")
    pose = metrics["pose"]
    return {
        "pose": pose["kind"],
        "up": [round(float(v), 3) for v in pose["up"]],
        "tipping_deg": round(pose["tipping_angle_deg"], 1),
        "base_percent": round(100 * pose["base_area_fraction"], 2),
        "sensing_percent": round(100 * pose["sensing_area_fraction"], 2),
        "touchable_percent": round(100 * metrics["touchable_share"], 2),
        "rx_family": metrics.get("rx_family"),
        "tx_pole": pose.get("tx_pole"),
        "fallback_ran": bool((manifest.get("fallback") or {}).get("ran_again")),
        "cells": metrics.get("cells"),
        "pads": metrics.get("pads"),
        "voronoi_cv": metrics.get("voronoi_cv"),
        "voronoi_cv_all_crossings": metrics.get("voronoi_cv_all_crossings"),
        "coverage_radius_mm": metrics.get("coverage_radius_mm"),
        "uncovered_percent": round(100 * metrics["uncovered_share"], 2),
        "uncovered_percent_sensing": round(100 * metrics["sensing_region"]["uncovered_share"], 2),
        "coverage_radius_vertices_mm": metrics["coverage_radius_vertices_mm"],
        "coverage_radius_vertices_sensing_mm": metrics["sensing_region"]["coverage_radius_vertices_mm"],
        "phase1_gap": metrics.get("phase1_gap"),
        "sheets": sheet_count,
        "joints": report.get("joints"),
        "limbs": len(metrics["limbs"]),
        "limbs_without_cells": sum(limb["cells"] == 0 for limb in metrics["limbs"]),
    }


def corpus(args: argparse.Namespace, work: Path) -> list[tuple[str, Path, float]]:
    """``(stem, path, diagonal mm)`` of every mesh to run."""
    sizes = json.loads(Path(args.sizes).read_text()) if args.sizes else {}
    items = []
    folder = Path(args.meshes)
    if folder.is_dir():
        for path in sorted(p for p in folder.iterdir() if p.suffix.lower() in SUPPORTED_SUFFIXES):
            items.append((path.stem, path, float(sizes.get(path.stem, DEFAULT_DIAGONAL_MM))))
    if not args.no_shapes:
        for name in shapes.CLASSES:
            path = shapes.write_shape(name, work)
            items.append((f"shape:{name}", path, float(sizes.get(name, shapes.diagonal_mm(name)))))
    if args.only:
        items = [item for item in items if item[0] in args.only or item[0].removeprefix("shape:") in args.only]
    return items


def fmt(value: object, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--meshes", default=str(REPO.parent / "shared" / "meshes"))
    parser.add_argument("--sizes", default=None, help="JSON file: mesh stem -> bounding-box diagonal (mm)")
    parser.add_argument("--vertices", type=int, default=20000)
    parser.add_argument("--angles", default="", help="Rx angles (deg, comma-separated); default: the pipeline's")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a further -S override for every run (repeatable), e.g. --set 'tx_poles=[far, centre]'")
    parser.add_argument("--only", nargs="*", default=None, help="run only these stems / shape classes")
    parser.add_argument("--no-shapes", action="store_true", help="skip the generated shapes")
    parser.add_argument("--cache-dir", default=None, help="cache folder (default: a fresh temporary one)")
    parser.add_argument("--timeout", type=float, default=3600.0, help="seconds per mesh")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="retrotouch-corpus-") as tmp:
        work = Path(tmp)
        args.cache_dir = args.cache_dir or str(work / "cache")
        os.environ.setdefault("PYTHONHASHSEED", "0")
        rows, failures = [], []
        print(
            f"{'mesh':32s} {'ok':3s} {'pose':10s} {'tip':>5s} {'base%':>6s} {'sens%':>6s} {'touch%':>6s} {'cells':>6s} {'pads':>5s} "
            f"{'CV':>6s} {'CV all':>6s} {'cov mm':>7s} {'unc%':>5s} {'all%':>5s} {'gap':>6s} {'Rx family':16s} {'Tx':6s} "
            f"{'fallback':8s} {'sheets':>6s} {'joints':>6s} {'limbs':>5s} {'bare':>4s} {'s':>7s}",
            flush=True,
        )
        for stem, path, diagonal in corpus(args, work):
            out = work / "out" / re.sub(r"\W", "_", stem)
            out.parent.mkdir(parents=True, exist_ok=True)
            code, stderr, seconds = run_pipeline(path, diagonal, args, out)
            row: dict[str, object] = {
                "mesh": stem, "ok": code == 0, "seconds": round(seconds, 1), "diagonal_mm": diagonal,
            }
            if code == 0:
                row.update(measured(stem, out))
            else:
                failures.append(failure(stem, stderr))
            rows.append(row)
            print(
                f"{stem:32s} {'yes' if row['ok'] else 'NO':3s} {row.get('pose', '-'):10s} "
                f"{fmt(row.get('tipping_deg'), '5.0f')} "
                f"{fmt(row.get('base_percent'), '6.1f')} {fmt(row.get('sensing_percent'), '6.1f')} "
                f"{fmt(row.get('touchable_percent'), '6.1f')} "
                f"{fmt(row.get('cells'), '6d')} {fmt(row.get('pads'), '5d')} "
                f"{fmt(row.get('voronoi_cv'), '6.3f')} {fmt(row.get('voronoi_cv_all_crossings'), '6.3f')} "
                f"{fmt(row.get('coverage_radius_mm'), '7.1f')} {fmt(row.get('uncovered_percent'), '5.1f')} "
                f"{fmt(row.get('uncovered_percent_sensing'), '5.1f')} "
                f"{fmt(row.get('phase1_gap'), '6.3f')} "
                f"{row.get('rx_family') or '-':16s} {row.get('tx_pole') or '-':6s} "
                f"{'yes' if row.get('fallback_ran') else 'no':8s} "
                f"{fmt(row.get('sheets'), '6d')} {fmt(row.get('joints'), '6d')} {fmt(row.get('limbs'), '5d')} "
                f"{fmt(row.get('limbs_without_cells'), '4d')} {seconds:7.1f}",
                flush=True,
            )
            if code != 0:
                print(f"    {failures[-1]['node']}: {failures[-1]['message']}", flush=True)
    good = [r for r in rows if r["ok"]]
    cvs = [r["voronoi_cv"] for r in good if r.get("voronoi_cv") is not None]
    cells = [r["cells"] for r in good if r.get("cells") is not None]
    radii = [r["coverage_radius_mm"] for r in good if r.get("coverage_radius_mm") is not None]
    uncovered = [r["uncovered_percent"] for r in good]
    summary = {
        "meshes": len(rows),
        "succeeded": len(good),
        "failures": failures,
        "median_voronoi_cv": float(np.median(cvs)) if cvs else None,
        "worst_voronoi_cv": max(cvs) if cvs else None,
        "median_cells": float(np.median(cells)) if cells else None,
        "fewest_cells": min(cells) if cells else None,
        "median_coverage_radius_mm": float(np.median(radii)) if radii else None,
        "worst_coverage_radius_mm": max(radii) if radii else None,
        "median_uncovered_percent": float(np.median(uncovered)) if uncovered else None,
        "worst_uncovered_percent": max(uncovered) if uncovered else None,
        "worst_phase1_gap": max((r["phase1_gap"] for r in good if r.get("phase1_gap") is not None), default=None),
        "most_sheets": max((r["sheets"] for r in good if r.get("sheets") is not None), default=None),
        "median_seconds": float(np.median([r["seconds"] for r in rows])) if rows else None,
        "slowest_seconds": max((r["seconds"] for r in rows), default=None),
        "fallback_runs": sum(bool(r.get("fallback_ran")) for r in good),
        "chosen_tx_poles": {pole: sum(r.get("tx_pole") == pole for r in good) for pole in sorted({r.get("tx_pole") for r in good})},
        "limbs": sum(r["limbs"] for r in good),
        "limbs_without_cells": sum(r["limbs_without_cells"] for r in good),
        "vertices": args.vertices,
        "rows": rows,
    }
    print(json.dumps(summary, separators=(",", ":")))


if __name__ == "__main__":
    main()
