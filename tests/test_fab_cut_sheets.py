"""fab.cut_sheets: exact physical size of SVG and PDF, one compound cut path, no transforms, DXF in mm
with closed polylines, geometry written = geometry nested."""
from __future__ import annotations

import io
import json
import re
import xml.etree.ElementTree as ET

import cv2
import ezdxf
import numpy as np
import pytest
import shapely
from shapely.geometry import LineString, Polygon
from test_fab_nesting import traces

from retrotouch.graph.node import Files
from retrotouch.nodes.fab.cut_sheets import Params, cut_sheets
from retrotouch.nodes.fab.nesting import Params as NestParams
from retrotouch.nodes.fab.nesting import nest, place, placed_polygons

SVG = "{http://www.w3.org/2000/svg}"
MM_PER_PT = 25.4 / 72


@pytest.fixture(scope="module", params=["12x12", "12x24", "custom"])
def written(request):
    if request.param == "custom":
        nest_params = NestParams(mat="custom", sheet_width_mm=150.5, sheet_height_mm=35.25, nester="shelf")
        outlines = traces([120, 110, 90, 60])
    else:
        nest_params = NestParams(mat=request.param, nester="shelf")
        outlines = traces([250, 200, 150, 90], bend=8.0)
    nested = nest(nest_params, outlines)
    files = cut_sheets(Params(), outlines, nested)
    assert isinstance(files, Files)
    return (nested.sheet_width_mm, nested.sheet_height_mm), outlines, nested, files.contents


def _subpaths(d: str) -> list[np.ndarray]:
    out = []
    for sub in re.findall(r"M([^MZ]*)Z", d):
        numbers = np.array([float(v) for v in re.findall(r"-?\d+\.?\d*", sub)])
        out.append(numbers.reshape(-1, 2))
    return out


def test_svg_exact_size_single_cut_path_no_transform(written):
    (width, height), outlines, nested, contents = written
    placed = placed_polygons(outlines, nested)
    assert nested.sheet_count >= 1
    for k in range(1, nested.sheet_count + 1):
        text = contents[f"sheets/sheet_{k}.svg"].decode()
        assert "transform" not in text
        root = ET.fromstring(text)
        assert root.get("width") == f"{width:g}mm" and root.get("height") == f"{height:g}mm"
        assert float(root.get("width")[:-2]) == pytest.approx(width, abs=0.01)
        assert [float(v) for v in root.get("viewBox").split()] == pytest.approx([0, 0, width, height], abs=0.01)
        cut = root.find(f"{SVG}g[@id='cut']")
        labels = root.find(f"{SVG}g[@id='labels']")
        assert len(cut.findall(f"{SVG}path")) == 1 and len(root.findall(f".//{SVG}path")) == 2
        assert labels.find(f"{SVG}path").get("fill") == "none"
        assert root.find(f".//{SVG}text") is None
        d = cut.find(f"{SVG}path").get("d")
        assert d.count("M") == d.count("Z")  # every subpath closed
        rings = _subpaths(d)
        on_sheet = np.nonzero(nested.part_sheet == k - 1)[0]
        assert len(rings) == len(on_sheet)
        for ring, i in zip(rings, on_sheet):
            assert ring[:, 0].min() >= 0 and ring[:, 0].max() <= width
            assert ring[:, 1].min() >= 0 and ring[:, 1].max() <= height
            written_polygon = Polygon(np.stack([ring[:, 0], height - ring[:, 1]], axis=1))  # back to y up
            assert written_polygon.symmetric_difference(placed[i]).area < 1e-3 * placed[i].area


def test_pdf_page_is_the_sheet_size(written):
    (width, height), _, nested, contents = written
    for k in range(1, nested.sheet_count + 1):
        pdf = contents[f"sheets/sheet_{k}.pdf"]
        assert pdf.startswith(b"%PDF")
        box = re.search(rb"/MediaBox\s*\[\s*([\d.]+)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)\s*\]", pdf)
        x0, y0, x1, y1 = (float(v) for v in box.groups())
        assert (x1 - x0) * MM_PER_PT == pytest.approx(width, abs=0.01)
        assert (y1 - y0) * MM_PER_PT == pytest.approx(height, abs=0.01)


def test_dxf_in_mm_with_closed_cut_polylines(written):
    (width, height), outlines, nested, contents = written
    placed = placed_polygons(outlines, nested)
    for k in range(1, nested.sheet_count + 1):
        doc = ezdxf.read(io.StringIO(contents[f"sheets/sheet_{k}.dxf"].decode()))
        assert doc.units == ezdxf.units.MM and doc.header["$INSUNITS"] == 4
        msp = doc.modelspace()
        cut = [e for e in msp if e.dxf.layer == "CUT"]
        labels = [e for e in msp if e.dxf.layer == "LABELS"]
        on_sheet = np.nonzero(nested.part_sheet == k - 1)[0]
        assert len(cut) == len(on_sheet) and all(e.dxftype() == "LWPOLYLINE" and e.closed for e in cut)
        assert len(labels) >= 4 * len(on_sheet)
        written_polygons = [Polygon([p[:2] for p in e.get_points()]) for e in cut]
        for polygon, i in zip(written_polygons, on_sheet):
            assert polygon.symmetric_difference(placed[i]).area < 1e-3 * placed[i].area
            assert shapely.box(0, 0, width, height).contains(polygon)


def test_preview_and_report(written):
    (width, height), outlines, nested, contents = written
    image = cv2.imdecode(np.frombuffer(contents["sheets/preview.png"], np.uint8), cv2.IMREAD_COLOR)
    px = Params().preview_px_per_mm
    assert image.shape[0] >= height * px and image.shape[1] >= nested.sheet_count * width * px
    report = json.loads(contents["sheets/report.json"])
    assert report["sheet"] == {"width": width, "height": height, "count": nested.sheet_count}
    assert [p["name"] for p in report["parts"]] == list(outlines.names)
    assert report["overlaps"] == 0 and report["min_gap_mm"] >= nested.spacing_mm - 1e-6


def test_svg_tells_how_to_import_it(written):
    _, _, nested, contents = written
    root = ET.fromstring(contents["sheets/sheet_1.svg"].decode())
    desc = root.find(f"{SVG}desc").text
    assert "Design Space" in desc and "Pen" in desc and "Attach" in desc and "Silhouette" in desc


def test_labels_read_upright_on_the_sheet(written):
    _, outlines, nested, _ = written
    for i in range(outlines.count):
        glyphs = outlines.label_polylines(i, float(nested.rotation_deg[i]))
        placed = [place(LineString(g), float(nested.rotation_deg[i]), nested.translation[i]) for g in glyphs]
        first, last = (np.asarray(p.centroid.coords)[0] for p in (placed[0], placed[-1]))  # first / last glyph
        reading = np.degrees(np.arctan2(*(last - first)[::-1]))
        assert -90.0 < reading <= 90.0 + 1e-6, (outlines.names[i], reading)


@pytest.mark.parametrize("version", ["R2010", "R12"])
def test_dxf_header_extents_limits_and_audit(written, version):
    (width, height), outlines, nested, _ = written
    contents = cut_sheets(Params(dxf_version=version), outlines, nested).contents
    for k in range(1, nested.sheet_count + 1):
        doc = ezdxf.read(io.StringIO(contents[f"sheets/sheet_{k}.dxf"].decode()))
        assert doc.dxfversion == {"R2010": "AC1024", "R12": "AC1009"}[version]
        auditor = doc.audit()
        assert not auditor.has_errors and not auditor.has_fixes
        entities = list(doc.modelspace())
        assert {e.dxftype() for e in entities} == {"LWPOLYLINE" if version == "R2010" else "POLYLINE"}
        points = np.array([(p[0], p[1]) for e in entities for p in (e.get_points() if version == "R2010" else
                                                                     [v.dxf.location for v in e.vertices])])
        np.testing.assert_allclose(doc.header["$EXTMIN"][:2], points.min(axis=0), atol=1e-9)
        np.testing.assert_allclose(doc.header["$EXTMAX"][:2], points.max(axis=0), atol=1e-9)
        assert tuple(doc.header["$LIMMIN"][:2]) == (0, 0) and tuple(doc.header["$LIMMAX"][:2]) == (width, height)
        assert 0 <= points.min() and points[:, 0].max() <= width and points[:, 1].max() <= height


def test_pdf_page_size_by_pdfinfo_and_svg_renders(written, tmp_path):
    import shutil
    import subprocess

    (width, height), _, nested, contents = written
    if shutil.which("pdfinfo") is None and shutil.which("rsvg-convert") is None:
        pytest.skip("neither pdfinfo (poppler-utils) nor rsvg-convert (librsvg2-bin) installed")
    for name in ("sheet_1.pdf", "sheet_1.svg"):
        (tmp_path / name).write_bytes(contents[f"sheets/{name}"])
    if shutil.which("pdfinfo"):
        info = subprocess.run(["pdfinfo", str(tmp_path / "sheet_1.pdf")], capture_output=True, text=True, check=True)
        w_pt, h_pt = (float(v) for v in re.search(r"Page size:\s+([\d.]+) x ([\d.]+) pts", info.stdout).groups())
        assert w_pt * MM_PER_PT == pytest.approx(width, abs=0.05) and h_pt * MM_PER_PT == pytest.approx(height, abs=0.05)
    if shutil.which("rsvg-convert"):
        png = tmp_path / "sheet_1.png"
        subprocess.run(["rsvg-convert", "--dpi-x", "25.4", "--dpi-y", "25.4", "-o", str(png),
                        str(tmp_path / "sheet_1.svg")], check=True)
        image = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
        assert abs(image.shape[1] - width) <= 1 and abs(image.shape[0] - height) <= 1  # 1 px per mm
        assert image[..., 3].any()  # something drawn
