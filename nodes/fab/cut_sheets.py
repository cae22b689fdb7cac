"""Cut-sheet files for the vinyl cutter (paper section 7.2; rules in shared/notes/projection-fabrication.md).

Per sheet ``n`` (1-based) the sink writes

* ``sheets/sheet_<n>.svg``: root ``width``/``height`` in mm and a ``viewBox`` in mm, so one user unit is
  1 mm; no ``transform`` anywhere; the import steps (:data:`IMPORT_STEPS`) in its ``<desc>``. Group
  ``id="cut"`` holds ONE compound ``<path>`` with every part as a closed subpath (Cricut Design Space
  keeps the nesting of a single path; separate paths would be rearranged). Group ``id="labels"``
  holds ONE stroke-only ``<path>`` with the channel names as glyph outlines, upright on the sheet
  (Design Space ignores ``<text>`` and imports every path as a cut, whatever its stroke or fill: the
  user sets this layer to *Pen*, or hides it, and *Attaches* both layers).
* ``sheets/sheet_<n>.pdf``: the same drawing through cairosvg, page exactly the sheet size.
* ``sheets/sheet_<n>.dxf``: DXF in mm, R2010 (``$INSUNITS`` = 4, LWPOLYLINE) or, with
  ``dxf_version: R12``, R12 (POLYLINE; no units header) for Silhouette Studio Basic and older
  readers; closed polylines on layer ``CUT`` (red) and the label glyphs on layer ``LABELS`` (blue),
  so Silhouette's "action by line color" tells them apart; ``$EXTMIN/$EXTMAX`` = the drawing's
  bounds, ``$LIMMIN/$LIMMAX`` = the sheet.
* ``sheets/preview.png``: all sheets side by side on white, mat border in grey.
* ``sheets/report.json``: mat (and why), sheet size, nester, material use, gaps, split traces (and
  why), joints, and where every part went.

PDF and DXF creation times come from :mod:`.timestamps` (SOURCE_DATE_EPOCH, else fixed), so two runs
write the same bytes. SVG y grows downwards; the sheet frame of :mod:`retrotouch.nodes.fab.nesting`
has y up, so the writer maps ``(x, y) -> (x, H - y)`` (the drawing stays "seen from outside"; no
mirroring).
"""
from __future__ import annotations

import io
import json
from xml.sax.saxutils import escape
import re
from typing import Literal

import numpy as np
from pydantic import Field

from ...graph.node import Files, NodeParams, node
from .nesting import NestedSheets, place, placed_polygons
from .outline import TraceOutlines
from .timestamps import source_date, with_pdf_creation_date
from shapely.geometry import LineString


IMPORT_STEPS = (
    "Cut sheets (sheets/sheet_<n>.svg, .dxf, .pdf; every file is the mat at its real size, labels upright):",
    "  Cricut Design Space: Upload > sheet_<n>.svg > Add to canvas. It arrives as two layers: 'cut' (the traces) and",
    "  'labels' (the names). Set the labels layer's Operation to Pen (Draw), select both and Attach, then Make it.",
    "  Without a pen: hide the labels layer. Do not resize: the sheet is at 100 %.",
    "  Silhouette Studio (Basic reads DXF): Open sheet_<n>.dxf (R12 with dxf_version: R12). Send > Action by Line",
    "  Color: red (layer CUT) = Cut, blue (layer LABELS) = Sketch with a pen, or off.",
)
"""How to import the sheets (each SVG's ``<desc>``, the assembly guide's page 1)."""

class Params(NodeParams):
    preview_px_per_mm: float = Field(2.0, gt=0, le=20, description="preview.png resolution (pixels per mm)")
    decimals: int = Field(3, ge=1, le=6, description="coordinate decimals in SVG/DXF (3 = 1 micrometre)")
    dxf_version: Literal["R2010", "R12"] = Field(
        "R2010", description="DXF version: R2010 (LWPOLYLINE, units in the header) or R12 (POLYLINE, the oldest "
        "and most widely read; Silhouette Studio)")


def _sheet_geometry(outlines: TraceOutlines, nested: NestedSheets):
    """Per sheet: (placed outline rings, placed label polylines, part names), sheet frame, y up."""
    placed = placed_polygons(outlines, nested)
    sheets = []
    for sheet in range(nested.sheet_count):
        rings, labels, names = [], [], []
        for i in np.nonzero(nested.part_sheet == sheet)[0]:
            rings.append(np.asarray(placed[i].exterior.coords)[:-1])
            names.append(outlines.names[i])
            for glyph in outlines.label_polylines(int(i), float(nested.rotation_deg[i])):
                line = place(LineString(glyph), float(nested.rotation_deg[i]), nested.translation[i])
                labels.append(np.asarray(line.coords))
        sheets.append((rings, labels, names))
    return sheets


def _path_data(polylines: list[np.ndarray], height: float, decimals: int) -> str:
    """SVG path data of closed polylines (mm, sheet frame y up -> SVG y down), one format per polyline."""
    point = f"%.{decimals}f %.{decimals}f"
    parts = []
    for poly in polylines:
        xy = np.column_stack([poly[:, 0], height - poly[:, 1]])
        parts.append("M" + " L".join([point] * len(xy)) % tuple(xy.ravel().tolist()) + " Z")
    return " ".join(parts)


def sheet_svg(rings, labels, names, width: float, height: float, number: int, decimals: int) -> str:
    """One sheet as an SVG document at exact physical size (module conventions)."""
    return (
        '<?xml version="1.0" encoding="UTF-8" standalone="no"?>\n'
        f'<svg xmlns="http://www.w3.org/2000/svg" version="1.1" width="{width:g}mm" height="{height:g}mm" '
        f'viewBox="0 0 {width:g} {height:g}">\n'
        f"  <title>retrotouch cut sheet {number}: {', '.join(names)}</title>\n"
        f"  <desc>{escape(chr(10).join(IMPORT_STEPS))}</desc>\n"
        '  <g id="cut">\n'
        f'    <path id="cut-sheet-{number}" fill="#c87533" fill-rule="evenodd" stroke="#000000" stroke-width="0.1" '
        f'd="{_path_data(rings, height, decimals)}"/>\n'
        "  </g>\n"
        '  <g id="labels">\n'
        f'    <path id="labels-sheet-{number}" fill="none" stroke="#0000ff" stroke-width="0.15" '
        f'd="{_path_data(labels, height, decimals)}"/>\n'
        "  </g>\n"
        "</svg>\n"
    )


def sheet_dxf(rings, labels, width: float, height: float, decimals: int, version: str = "R2010") -> bytes:
    """One sheet as DXF in mm: closed polylines on layers CUT and LABELS (LWPOLYLINE in R2010,
    POLYLINE in R12); header extents = the drawing's bounds, limits = the sheet; creation and
    update times from :func:`.timestamps.source_date`, fixed GUIDs."""
    import ezdxf  # heavy: imported when used
    from ezdxf.tools import juliandate

    fixed = ezdxf.options.write_fixed_meta_data_for_testing
    ezdxf.options.write_fixed_meta_data_for_testing = True  # fixed GUIDs, marker and times (replaced below)
    try:
        doc = ezdxf.new(version, setup=False, units=ezdxf.units.MM)  # R12 keeps no units (ezdxf warns): mm by convention
        text = _dxf_text(doc, rings, labels, width, height, decimals)
    finally:
        ezdxf.options.write_fixed_meta_data_for_testing = fixed
    when = juliandate(source_date().replace(tzinfo=None))
    text = re.sub(r"(\$TDU?(?:CREATE|UPDATE)\n 40\n)[^\n]*", lambda m: f"{m.group(1)}{when}", text)
    return text.encode("utf-8")


def _dxf_text(doc, rings, labels, width: float, height: float, decimals: int) -> str:
    """The document text with the polylines, extents and limits (see :func:`sheet_dxf`)."""
    if doc.dxfversion != "AC1009":
        doc.header["$MEASUREMENT"] = 1
    doc.layers.add("CUT", color=1)
    doc.layers.add("LABELS", color=5)
    msp = doc.modelspace()
    for layer, polylines in (("CUT", rings), ("LABELS", labels)):
        for poly in polylines:
            points = np.round(poly, decimals).tolist()
            if doc.dxfversion == "AC1009":  # R12
                msp.add_polyline2d(points, close=True, dxfattribs={"layer": layer})
            else:
                msp.add_lwpolyline(points, close=True, dxfattribs={"layer": layer})
    everything = np.round(np.concatenate(list(rings) + list(labels)), decimals) if len(rings) else np.zeros((1, 2))
    msp.reset_extents((*everything.min(axis=0).tolist(), 0.0), (*everything.max(axis=0).tolist(), 0.0))
    msp.reset_limits((0.0, 0.0), (float(width), float(height)))  # the write copies both into the header
    if doc.dxfversion != "AC1009":  # ezdxf adds the CLASS entries of the types in use in set order (string
        for dxftype in sorted(doc.entitydb.dxf_types_in_use()):  # hashes differ between processes): sorted first
            doc.classes.add_class(dxftype)
    stream = io.StringIO()
    doc.write(stream)
    return stream.getvalue()


def preview_png(svgs: list[str], width: float, height: float, px_per_mm: float) -> bytes:
    """All sheets side by side (grey border = cut area), white background."""
    import cairosvg
    import cv2

    w, h = int(round(width * px_per_mm)), int(round(height * px_per_mm))
    gap = max(4, int(round(5 * px_per_mm)))
    canvas = np.full((h + 2 * gap, len(svgs) * (w + gap) + gap, 3), 255, dtype=np.uint8)
    for k, svg in enumerate(svgs):
        png = cairosvg.svg2png(bytestring=svg.encode(), output_width=w, output_height=h, background_color="white")
        image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        x = gap + k * (w + gap)
        canvas[gap : gap + h, x : x + w] = image
        cv2.rectangle(canvas, (x - 1, gap - 1), (x + w, gap + h), (160, 160, 160), 1)
    ok, encoded = cv2.imencode(".png", canvas)
    return encoded.tobytes()


@node("fab.cut_sheets", params=Params, inputs=("outlines", "nesting"), outputs=("files",), sink=True)
def cut_sheets(params: Params, outlines: TraceOutlines, nesting: NestedSheets) -> Files:
    """Write every nested sheet as SVG (one compound cut path + pen labels), PDF and DXF at exact
    physical size, a PNG preview and a JSON report."""
    import cairosvg  # heavy: imported when used

    width, height = nesting.sheet_width_mm, nesting.sheet_height_mm
    contents: dict[str, bytes] = {}
    svgs = []
    for k, (rings, labels, names) in enumerate(_sheet_geometry(outlines, nesting), start=1):
        svg = sheet_svg(rings, labels, names, width, height, k, params.decimals)
        svgs.append(svg)
        contents[f"sheets/sheet_{k}.svg"] = svg.encode("utf-8")
        pdf = cairosvg.svg2pdf(bytestring=svg.encode("utf-8"))
        contents[f"sheets/sheet_{k}.pdf"] = with_pdf_creation_date(pdf, source_date())
        contents[f"sheets/sheet_{k}.dxf"] = sheet_dxf(rings, labels, width, height, params.decimals, params.dxf_version)
    contents["sheets/preview.png"] = preview_png(svgs, width, height, params.preview_px_per_mm)
    report = {
        "units": "mm",
        "sheet": {"width": width, "height": height, "count": nesting.sheet_count},
        "mat": nesting.mat,
        "mat_reason": nesting.mat_reason,
        "nester": nesting.nester,
        "rotations": nesting.rotations,
        "fallback_reason": nesting.fallback_reason,
        "spacing_mm": nesting.spacing_mm,
        "min_gap_mm": nesting.min_gap_mm if np.isfinite(nesting.min_gap_mm) else None,
        "overlaps": nesting.overlaps,
        "parts_area_mm2": round(nesting.parts_area_mm2, 3),
        "material_use": round(nesting.material_use, 5),
        "used_length_mm_last_sheet": round(nesting.used_length_mm, 3),
        "split_traces": [{"trace": t, "reason": r} for t, r in zip(outlines.split_traces, outlines.split_reasons)],
        "joints": outlines.joints,
        "parts": [
            {
                "name": outlines.names[i],
                "sheet": int(nesting.part_sheet[i]) + 1,
                "rotation_deg": round(float(nesting.rotation_deg[i]), 4),
                "translation_mm": [round(float(v), 4) for v in nesting.translation[i]],
                "area_mm2": round(float(outlines.area_mm2[i]), 3),
            }
            for i in range(outlines.count)
        ],
    }
    contents["sheets/report.json"] = (json.dumps(report, indent=1) + "\n").encode("utf-8")
    return Files(contents=contents)
