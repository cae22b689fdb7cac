"""Fabrication benchmark: unfolding + outlining + nesting + writing the cut sheets for the bunny.

Layout (``--layout auto`` tries them in this order):

* ``real``: the pipeline's (``layout.pick_best`` in ``pipelines/retrofit.yaml``, run through the
  engine with its cache), when the pipeline has it and it runs;
* ``traced``: the curve helpers' real Tx/Rx tracing on the bunny (``tests/curves_fixture.py``
  preparation, 170 mm), 21 Tx / 12 Rx picked evenly (not optimised), crossings from
  ``curves.crossings``, pads greedily >= 15 mm apart;
* ``synthetic``: 21 Tx x 12 Rx plane sections (Tx: meridians, Rx: horizontal sections opened into
  arcs) on the bunny loaded, scaled to a 170 mm diagonal, repaired and remeshed by the pipeline's
  own mesh nodes.

The written SVGs are parsed back and checked with shapely (overlaps, smallest gap, fit on the mat),
independently of the nester's own verification. Prints a table, then as its LAST line one JSON
object: seconds (unfold + outline + nest + write), sheets, material_use (parts area / area of the
sheets used), min_gap_mm, overlaps, plus details.

Usage: python bench/fabrication.py [--layout auto|real|traced|synthetic] [--seconds 10] [--mat 12x12] [--guide] [--out DIR]
"""
from __future__ import annotations

import argparse
import json
import re
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import shapely
from shapely.geometry import Polygon

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from fab_layouts import greedy_pads, section_layout  # noqa: E402

from retrotouch.nodes import mesh_io, mesh_repair  # noqa: E402
from retrotouch.nodes.fab.assembly_guide import Params as GuideParams  # noqa: E402
from retrotouch.nodes.fab.assembly_guide import assembly_guide  # noqa: E402
from retrotouch.nodes.fab.cut_sheets import Params as SheetParams  # noqa: E402
from retrotouch.nodes.fab.cut_sheets import cut_sheets  # noqa: E402
from retrotouch.nodes.data.types import Mesh  # noqa: E402
from retrotouch.nodes.fab.nesting import Params as NestParams  # noqa: E402
from retrotouch.nodes.fab.nesting import nest  # noqa: E402
from retrotouch.nodes.fab.outline import Params as OutlineParams  # noqa: E402
from retrotouch.nodes.fab.outline import outline  # noqa: E402
from retrotouch.nodes.fab.unfold import Params as UnfoldParams  # noqa: E402
from retrotouch.nodes.fab.unfold import unfold  # noqa: E402


def real_layout():
    """(mesh, layout) from the repo pipeline's layout.pick_best, or None when it has none."""
    pipeline = REPO / "pipelines" / "retrofit.yaml"
    if "layout.pick_best" not in pipeline.read_text():
        return None
    from retrotouch.graph.app import configure
    from retrotouch.graph.runner import run_pipeline
    from retrotouch.nodes.app import APP

    configure(APP)
    with tempfile.TemporaryDirectory() as out:
        result = run_pipeline(str(pipeline), out_dir=out, scheduler="sync")
    store = result.plan.store

    def value(instance, output):
        loaded = store.load(store.lookup(instance.key))
        return loaded[output] if len(instance.decl.spec.outputs) > 1 else loaded

    pick = next(i for i in result.plan.instances if i.decl.spec.name == "layout.pick_best")
    consumer = next(i for i in result.plan.instances if "mesh" in i.inputs and "layout" in i.inputs)
    upstream, output = consumer.inputs["mesh"][0]
    return value(upstream, output), value(pick, "layout")


def traced_layout():
    """(mesh, layout): real traced curves on the bunny, an even (not optimised) 21 x 12 choice."""
    import dataclasses

    from curves_fixture import bunny

    from retrotouch.nodes.curves.crossings import find_crossings
    from retrotouch.nodes.data.types import CurveEnd, CurveSet, Layout
    from retrotouch.nodes.curves.tracing import TraceRxParams, TraceTxParams, trace_rx, trace_tx

    mesh, regions, _, tx_field, rx_field = bunny()
    families = (trace_tx(TraceTxParams(), mesh, regions, tx_field)["curves"],
                trace_rx(TraceRxParams(angle_deg=0.0), mesh, regions, rx_field)["curves"])

    def pick(curves: CurveSet, count: int) -> CurveSet:
        usable = np.nonzero(curves.end_reason == CurveEnd.BASE)[0] if curves.layer == "tx" else np.arange(curves.count)
        chosen = usable[np.linspace(0, len(usable) - 1, count).astype(int)]
        rows = np.concatenate([np.arange(curves.offsets[c], curves.offsets[c + 1]) for c in chosen])
        offsets = np.concatenate([[0], np.cumsum(np.diff(curves.offsets)[chosen])]).astype(np.int64)
        return dataclasses.replace(curves, points=curves.points[rows], faces=curves.faces[rows],
                                   bary=curves.bary[rows], offsets=offsets, lengths_mm=curves.lengths_mm[chosen],
                                   end_reason=curves.end_reason[chosen])

    tx, rx = pick(families[0], 21), pick(families[1], 12)
    cells = find_crossings(tx, rx, mesh.faces)
    _, first = np.unique(cells.curve_a * rx.count + cells.curve_b, return_index=True)  # one per channel pair
    cells = dataclasses.replace(cells, **{f.name: getattr(cells, f.name)[first] for f in dataclasses.fields(cells)
                                          if f.name not in ("layer_a", "layer_b")})
    layout = Layout(tx, rx, cells, greedy_pads(cells.points, 15.0), np.arange(21), np.arange(12))
    return mesh, layout


def synthetic_layout():
    """(mesh, layout): the bunny as the pipeline prepares it (y-up turned z-up), 21 x 12 sections."""
    mesh = mesh_io.load_mesh(mesh_io.LoadParams(path="builtin:bunny", units="unitless"))
    mesh = mesh_io.scale_mesh(mesh_io.ScaleParams(diagonal_mm=170, about="bbox_center"), mesh)
    mesh = mesh_repair.repair_mesh(mesh_repair.RepairParams(), mesh)
    mesh = mesh_repair.remesh(mesh_repair.RemeshParams(target_edge_mm=2.0), mesh)
    y_up_to_z_up = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    mesh = Mesh(mesh.vertices @ y_up_to_z_up.T, mesh.faces, mesh.source)
    return mesh, section_layout(mesh, 21, 12, pad_distance_mm=15.0, keep=0.8)


def svg_parts(svg: bytes) -> tuple[float, float, list[Polygon]]:
    """Sheet size (mm) and cut polygons (y up) read back from a written sheet."""
    root = ET.fromstring(svg)
    width, height = (float(root.get(k)[:-2]) for k in ("width", "height"))
    path = root.find("{http://www.w3.org/2000/svg}g[@id='cut']/{http://www.w3.org/2000/svg}path")
    polygons = []
    for sub in re.findall(r"M([^MZ]*)Z", path.get("d")):
        xy = np.array([float(v) for v in re.findall(r"-?\d+\.?\d*", sub)]).reshape(-1, 2)
        polygons.append(Polygon(np.stack([xy[:, 0], height - xy[:, 1]], axis=1)))
    return width, height, polygons


def check_sheets(files: dict[str, bytes], sheet_count: int) -> dict:
    overlaps, min_gap, off_mat, area, sheet_area = 0, np.inf, 0, 0.0, 0.0
    for k in range(1, sheet_count + 1):
        width, height, polygons = svg_parts(files[f"sheets/sheet_{k}.svg"])
        mat = shapely.box(0, 0, width, height)
        off_mat += sum(not mat.contains(p) for p in polygons)
        area += sum(p.area for p in polygons)
        sheet_area += width * height
        for i in range(len(polygons)):
            for j in range(i):
                overlaps += polygons[i].intersects(polygons[j])
                min_gap = min(min_gap, polygons[i].distance(polygons[j]))
    return {"overlaps": overlaps, "min_gap_mm": min_gap, "off_mat": off_mat, "material_use": area / sheet_area}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--layout", choices=["auto", "real", "traced", "synthetic"], default="auto")
    parser.add_argument("--seconds", type=int, default=10, help="spyrrow budget per sheet (s)")
    parser.add_argument("--mat", default="12x12", choices=["12x12", "12x24"])
    parser.add_argument("--guide", action="store_true", help="also time the assembly guide PDF")
    parser.add_argument("--out", type=Path, help="write the sheets (and guide) into this folder")
    args = parser.parse_args()

    t0 = time.perf_counter()
    source = None
    builders = {"real": real_layout, "traced": traced_layout, "synthetic": synthetic_layout}
    for name in (["real", "traced", "synthetic"] if args.layout == "auto" else [args.layout]):
        try:
            found = builders[name]()
        except Exception as error:  # noqa: BLE001 - upstream stages may not run yet: say so, try the next
            if args.layout != "auto":
                raise
            print(f"{name} layout unavailable ({type(error).__name__}: {error})", file=sys.stderr)
            continue
        if found is not None:
            (mesh, layout), source = found, name
            break
        print(f"{name} layout unavailable (pipelines/retrofit.yaml has no layout.pick_best yet)", file=sys.stderr)
    if source is None:
        raise SystemExit(f"no {args.layout} layout available")
    t_layout = time.perf_counter() - t0

    timings = {}
    t = time.perf_counter()
    unfolded = unfold(UnfoldParams(), mesh, layout)
    timings["unfold"] = time.perf_counter() - t
    t = time.perf_counter()
    outlines = outline(OutlineParams(), unfolded)
    timings["outline"] = time.perf_counter() - t
    t = time.perf_counter()
    nested = nest(NestParams(mat=args.mat, seconds=args.seconds, workers=2), outlines)
    timings["nest (spyrrow)"] = time.perf_counter() - t
    t = time.perf_counter()
    files = cut_sheets(SheetParams(), outlines, nested).contents
    timings["write SVG/PDF/DXF/PNG"] = time.perf_counter() - t
    seconds = sum(timings.values())
    t = time.perf_counter()
    shelf = nest(NestParams(mat=args.mat, nester="shelf"), outlines)
    shelf_seconds = time.perf_counter() - t
    if args.guide:
        t = time.perf_counter()
        guide = assembly_guide(GuideParams(), mesh, layout, outlines).contents["assembly_guide.pdf"]
        timings["assembly guide (not in seconds)"] = time.perf_counter() - t
    checked = check_sheets(files, nested.sheet_count)
    if args.out:
        for name, content in {**files, **({"assembly_guide.pdf": guide} if args.guide else {})}.items():
            (args.out / name).parent.mkdir(parents=True, exist_ok=True)
            (args.out / name).write_bytes(content)

    lengths = unfolded.arc[unfolded.offsets[1:] - 1]
    rel_error = np.abs(lengths - unfolded.length_3d) / unfolded.length_3d
    print(f"layout: {source} on {mesh.source} ({len(mesh.faces)} faces), {layout.tx.count} Tx x {layout.rx.count} Rx, "
          f"{len(layout.cells.curve_a)} crossings, {int(layout.pad.sum())} pads  [{t_layout:.1f} s to build]")
    print(f"traces: {unfolded.count}, parts: {outlines.count}, split: {list(outlines.split_traces) or 'none'}, "
          f"length {lengths.min():.0f}-{lengths.max():.0f} mm (total {lengths.sum():.0f} mm), "
          f"max |2D-3D|/3D length {rel_error.max():.1e}")
    print(f"{'step':<34}{'seconds':>9}")
    for name, value in timings.items():
        print(f"{name:<34}{value:>9.2f}")
    print(f"{'total (unfold..write)':<34}{seconds:>9.2f}")
    print(f"nesting on {args.mat}: spyrrow {nested.sheet_count} sheet(s), last sheet used length "
          f"{nested.used_length_mm:.0f} mm, material use {nested.material_use:.3f}"
          f"{' (fallback: ' + nested.fallback_reason + ')' if nested.fallback_reason else ''}; "
          f"shelf fallback {shelf.sheet_count} sheet(s), used length {shelf.used_length_mm:.0f} mm [{shelf_seconds:.2f} s]")
    print(f"written sheets re-read: overlaps {checked['overlaps']}, min gap {checked['min_gap_mm']:.3f} mm, "
          f"parts off the mat {checked['off_mat']}")
    summary = {
        "seconds": round(seconds, 3),
        "sheets": nested.sheet_count,
        "material_use": round(checked["material_use"], 5),
        "material_use_used_length": round(nested.parts_area_mm2 / (
            (nested.sheet_count - 1) * nested.sheet_width_mm * nested.sheet_height_mm
            + nested.used_length_mm * min(nested.sheet_width_mm, nested.sheet_height_mm)), 5),
        "used_length_mm": round(nested.used_length_mm, 2),
        "min_gap_mm": round(checked["min_gap_mm"], 4),
        "overlaps": checked["overlaps"],
        "off_mat": checked["off_mat"],
        "nester": nested.nester,
        "shelf_used_length_mm": round(shelf.used_length_mm, 2),
        "parts": outlines.count,
        "split_traces": len(outlines.split_traces),
        "trace_length_total_mm": round(float(lengths.sum()), 1),
        "max_length_rel_error": float(rel_error.max()),
        "layout": source,
        "timings": {k: round(v, 3) for k, v in timings.items()},
    }
    if args.guide:
        summary["guide_pdf_bytes"] = len(guide)
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
