"""Fabrication benchmark: unfolding + outlining + nesting + writing the cut sheets (and the guide).

Layouts (``--layout``, ``auto`` tries the first three in this order):

* ``real``: the pipeline's (``layout.pick_best`` in ``pipelines/retrofit.yaml``, run through the
  engine with its cache), when the pipeline has it and it runs;
* ``traced``: the curve helpers' real Tx/Rx tracing on the bunny (``tests/curves_fixture.py``
  preparation, 170 mm), 21 Tx / 12 Rx picked evenly (not optimised), crossings from
  ``curves.crossings``, pads greedily >= 15 mm apart;
* ``synthetic``: 21 Tx x 12 Rx plane sections (Tx: meridians, Rx: horizontal sections opened into
  arcs) on the bunny loaded, scaled to a 170 mm diagonal, repaired and remeshed by the pipeline's
  own mesh nodes;
* one or more output folders (``--out`` of ``retrotouch run``): each run's ``layout.pick_best``
  layout and mesh, loaded from the cache it recorded in ``manifest.json`` (same pipeline and ``-S``
  overrides, nothing recomputed when the run is cached); one row per folder;
* one or more mesh files (``.ply``, ``.obj``, ...; or a folder of them, or ``builtin:bunny``): the
  default pipeline's ``layout.pick_best`` layout of each, run only up to that node (``-S mesh=...
  -S diagonal_mm=... -S vertices=...``; ``--sizes FILE.json`` maps a file's stem to its diagonal in
  mm, default ``--diagonal-mm``); ``shapes`` adds one generated shape per class of
  ``tests/shapes.py`` at its natural size; one row per mesh (a mesh the pipeline or a fab node fails on
  is listed under ``failed``).

The written SVGs are parsed back and checked with shapely (overlaps, smallest gap, fit on the mat),
independently of the nester's own verification. Prints a table, then as its LAST line one JSON
object: sheets, nest_seconds, material_use (parts area / area of the sheets used), joints,
min_gap_mm, overlaps for the worst object (most sheets, slowest nest, lowest use, most joints,
smallest gap), with per-object rows under ``objects`` and the medians. ``--profile`` prints the top
cProfile entries of fab.nest and fab.assembly_guide.

Usage: python bench/fabrication.py [--layout auto|real|traced|synthetic|DIR|MESH...] [--mat auto] [--guide]
       [--profile] [--out DIR] [--cache-dir DIR] [--vertices N] [--diagonal-mm D] [--sizes FILE.json]
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

from retrotouch.graph.errors import UserError  # noqa: E402
from retrotouch.nodes.mesh import loading as mesh_io  # noqa: E402
from retrotouch.nodes.mesh import repair as mesh_repair  # noqa: E402
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


def run_layout(pipeline: str, overrides: list[str], cache_dir: str | None, out_dir: str | None = None):
    """(mesh, layout) of a pipeline's ``layout.pick_best`` and the mesh its consumers read: from the
    cache when the run is there, else run up to ``layout.pick_best`` (into ``out_dir``, a temporary
    folder when None)."""
    from retrotouch.graph.app import configure
    from retrotouch.graph.runner import make_plan, run_pipeline
    from retrotouch.nodes.app import APP

    configure(APP)
    plan = make_plan(pipeline, overrides, cache_dir)
    store = plan.store
    pick = next(i for i in plan.instances if i.decl.spec.name == "layout.pick_best")
    consumer = next(i for i in plan.instances if "mesh" in i.inputs and "layout" in i.inputs)
    upstream, output = consumer.inputs["mesh"][0]
    if store.lookup(pick.key) is None or store.lookup(upstream.key) is None:
        with tempfile.TemporaryDirectory() as scratch:
            run_pipeline(pipeline, overrides, out_dir=out_dir or scratch, scheduler="sync", cache_dir=cache_dir,
                         targets=[pick.node])

    def value(instance, name):
        loaded = store.load(store.lookup(instance.key))
        return loaded[name] if len(instance.decl.spec.outputs) > 1 else loaded

    return value(upstream, output), value(pick, "layout")


def real_layout(cache_dir: str | None = None):
    """(mesh, layout) from the repo pipeline's layout.pick_best, or None when it has none."""
    pipeline = REPO / "pipelines" / "retrofit.yaml"
    if "layout.pick_best" not in pipeline.read_text():
        return None
    return run_layout(str(pipeline), [], cache_dir)


def folder_layout(folder: Path, cache_dir: str | None = None):
    """(mesh, layout) of the run that wrote the output folder ``folder`` (from ``cache_dir`` instead
    of the run's own cache when given)."""
    manifest = json.loads((folder / "manifest.json").read_text())
    return run_layout(manifest["pipeline"]["path"], manifest["overrides"], cache_dir or manifest["cache_dir"])


MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off", ".glb")


def mesh_layout(mesh: str, args, diagonal: float | None = None):
    """(mesh, layout) of the default pipeline on a mesh file (or builtin mesh) at its size."""
    sizes = json.loads(Path(args.sizes).read_text()) if args.sizes else {}
    diagonal = diagonal or float(sizes.get(Path(mesh).stem, args.diagonal_mm))
    overrides = [f"mesh={mesh}", f"diagonal_mm={diagonal:g}"] + ([f"vertices={args.vertices}"] if args.vertices else [])
    return run_layout(str(REPO / "pipelines" / "retrofit.yaml"), overrides, args.cache_dir)


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


def profiled(function, *args, top: int = 12):
    """(result, seconds, cProfile's top entries by internal time as text)."""
    import cProfile
    import io
    import pstats

    profile = cProfile.Profile()
    t = time.perf_counter()
    result = profile.runcall(function, *args)
    seconds = time.perf_counter() - t
    text = io.StringIO()
    pstats.Stats(profile, stream=text).sort_stats("tottime").print_stats(top)
    lines = [line for line in text.getvalue().splitlines() if line.strip()]
    start = next(k for k, line in enumerate(lines) if line.lstrip().startswith("ncalls"))
    return result, seconds, "\n".join(lines[start:])


def measure(name: str, mesh, layout, args) -> dict:
    """One object: timings, sheets, checks (see the module docstring)."""
    timings = {}
    t = time.perf_counter()
    unfolded = unfold(UnfoldParams(), mesh, layout)
    timings["unfold"] = time.perf_counter() - t
    t = time.perf_counter()
    outlines = outline(OutlineParams(), unfolded)
    timings["outline"] = time.perf_counter() - t
    nested, timings["nest"], nest_profile = profiled(nest, NestParams(mat=args.mat), outlines)
    t = time.perf_counter()
    files = cut_sheets(SheetParams(), outlines, nested).contents
    timings["write SVG/PDF/DXF/PNG"] = time.perf_counter() - t
    row = {"object": name, "faces": len(mesh.faces), "traces": unfolded.count, "parts": outlines.count,
           "joints": outlines.joints, "mat": nested.mat, "sheets": nested.sheet_count,
           "nest_seconds": round(timings["nest"], 3), "rotations": nested.rotations,
           "used_length_mm": round(nested.used_length_mm, 1), "nester": nested.nester,
           "longest_trace_mm": round(float(unfolded.arc[unfolded.offsets[1:] - 1].max()), 1)}
    checked = check_sheets(files, nested.sheet_count)
    row.update(material_use=round(checked["material_use"], 5), min_gap_mm=round(checked["min_gap_mm"], 4),
               overlaps=checked["overlaps"], off_mat=checked["off_mat"])
    if args.guide:
        guide, timings["guide"], guide_profile = profiled(assembly_guide, GuideParams(), mesh, layout, outlines)
        files = {**files, **guide.contents}
        row["guide_seconds"] = round(timings["guide"], 3)
    row["seconds"] = round(sum(timings.values()), 3)
    if args.profile:
        print(f"--- {name}: fab.nest profile ({timings['nest']:.1f} s)\n{nest_profile}")
        if args.guide:
            print(f"--- {name}: fab.assembly_guide profile ({timings['guide']:.1f} s)\n{guide_profile}")
    if args.out:
        for file, content in files.items():
            target = args.out / (name if len(args.layout) > 1 or Path(args.layout[0]).is_dir() else "") / file
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(content)
    return row


def layouts(choice: list[str], args):
    """(name, mesh, layout) for each requested layout (module docstring)."""
    cache_dir = args.cache_dir
    builders = {"real": lambda: real_layout(cache_dir), "traced": traced_layout, "synthetic": synthetic_layout}
    if choice == ["auto"]:
        for name in ("real", "traced", "synthetic"):
            try:
                found = builders[name]()
            except Exception as error:  # noqa: BLE001 - upstream stages may not run yet: say so, try the next
                print(f"{name} layout unavailable ({type(error).__name__}: {error})", file=sys.stderr)
                continue
            if found is not None:
                yield name, *found
                return
        raise SystemExit("no layout available")
    meshes = []  # (name, mesh file, diagonal or None)
    for item in choice:
        path = Path(item)
        if item in builders:
            yield item, *builders[item]()
        elif item == "shapes":
            import shapes

            folder = Path(tempfile.gettempdir()) / "retrotouch-fab-shapes"  # one path: cached layouts are reused
            folder.mkdir(exist_ok=True)
            meshes += [(f"shape:{name}", str(shapes.write_shape(name, folder)), shapes.diagonal_mm(name))
                       for name in shapes.CLASSES]
        elif item.startswith("builtin:") or path.suffix.lower() in MESH_SUFFIXES:
            meshes.append((path.stem.removeprefix("builtin:"), item, None))
        elif path.is_dir() and not (path / "manifest.json").exists():
            meshes += [(p.stem, str(p), None) for p in sorted(path.iterdir()) if p.suffix.lower() in MESH_SUFFIXES]
        else:
            yield path.name, *folder_layout(path, cache_dir)
    for name, mesh, diagonal in meshes:
        try:
            found = mesh_layout(mesh, args, diagonal)
        except Exception as error:  # noqa: BLE001 - the pipeline fails on some meshes: list them, go on
            print(f"{name}: no layout ({type(error).__name__}: {str(error)[:200]})", file=sys.stderr, flush=True)
            args.failed.append(name)
            continue
        yield name, *found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--layout", nargs="+", default=["auto"],
                        help="auto, real, traced, synthetic, output folders, mesh files or folders of meshes")
    parser.add_argument("--mat", default="auto", choices=["auto", "12x12", "12x24"])
    parser.add_argument("--guide", action="store_true", help="also time the assembly guide PDF")
    parser.add_argument("--profile", action="store_true", help="print the top profile entries of nest (and guide)")
    parser.add_argument("--out", type=Path, help="write the sheets (and guide) into this folder")
    parser.add_argument("--cache-dir", help="engine cache for real / folder / mesh layouts (default: the run's own)")
    parser.add_argument("--vertices", type=int, help="mesh layouts: remeshing target (default: the pipeline's)")
    parser.add_argument("--diagonal-mm", type=float, default=170.0, help="mesh layouts: bounding-box diagonal (mm)")
    parser.add_argument("--sizes", help="mesh layouts: JSON file, mesh stem -> bounding-box diagonal (mm)")
    args = parser.parse_args()
    args.failed = []

    rows = []
    for name, mesh, layout in layouts(args.layout, args):
        try:
            rows.append(measure(name, mesh, layout, args))
        except UserError as error:  # a fab node refuses this layout: a failure of the object, listed
            print(f"{name}: {error}", file=sys.stderr, flush=True)
            args.failed.append(name)
            continue
        print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    columns = ["object", "faces", "parts", "joints", "mat", "sheets", "nest_seconds", "rotations", "used_length_mm",
               "material_use", "min_gap_mm", "overlaps", "off_mat", "longest_trace_mm"] + (
        ["guide_seconds"] if args.guide else [])
    print("  ".join(f"{c:>14}" for c in columns))
    for row in rows:
        print("  ".join(f"{row[c]:>14}" for c in columns))

    def median(key):
        return float(np.median([row[key] for row in rows]))

    summary = {
        "sheets": max(row["sheets"] for row in rows),
        "nest_seconds": max(row["nest_seconds"] for row in rows),
        "material_use": min(row["material_use"] for row in rows),
        "joints": max(row["joints"] for row in rows),
        "min_gap_mm": min(row["min_gap_mm"] for row in rows),
        "overlaps": sum(row["overlaps"] for row in rows),
        "off_mat": sum(row["off_mat"] for row in rows),
        "failed": args.failed,
        "median": {k: median(k) for k in ("sheets", "nest_seconds", "material_use", "joints")},
        "objects": rows,
    }
    if args.guide:
        summary["guide_seconds"] = max(row["guide_seconds"] for row in rows)
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
