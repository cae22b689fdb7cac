"""fab.nest: parts on their mats, no overlaps, gaps >= spacing, more sheets when needed, clear error
for a trace longer than any mat, reproducible placement."""
from __future__ import annotations

import numpy as np
import pydantic
import pytest
import shapely
import shapely.affinity
from shapely.geometry import Polygon
from test_fab_outline import straight, unfolded_from_polylines

from retrotouch.graph.errors import UserError
from retrotouch.nodes.fab.mats import MARGIN_MM, MATS_MM, fit_angles, usable_sides
from retrotouch.nodes.fab.nesting import Params, nest, placed_polygons
from retrotouch.nodes.fab.outline import Params as OutlineParams
from retrotouch.nodes.fab.outline import outline
from retrotouch.nodes.fab.raster_nest import Part, raster_nest


def traces(lengths, bend: float = 0.0, fit_mat: str = "12x12"):
    """Straight (or bent) traces with a few pads each (split to fit ``fit_mat``)."""
    polylines = []
    for k, length in enumerate(lengths):
        line = straight(length, 80)
        line[:, 1] += bend * np.sin(np.linspace(0, np.pi * (1 + k % 3), 80))
        polylines.append(line - line[-1])
    marks = [(c, s, True) for c, length in enumerate(lengths) for s in np.arange(10.0, length - 5, 25.0)]
    return outline(OutlineParams(fit_mat=fit_mat), unfolded_from_polylines(polylines, marks))


def check_layout(outlines, nested, params):
    width, height = nested.sheet_width_mm, nested.sheet_height_mm
    placed = placed_polygons(outlines, nested)
    usable = shapely.box(params.margin_mm, params.margin_mm, width - params.margin_mm, height - params.margin_mm)
    for polygon in placed:
        assert usable.buffer(1e-6).contains(polygon)  # fits its mat inside the margin
    for i in range(len(placed)):
        for j in range(i):
            if nested.part_sheet[i] == nested.part_sheet[j]:
                assert not placed[i].intersects(placed[j])
                assert placed[i].distance(placed[j]) >= params.spacing_mm - 1e-6
    # placements are rigid: areas unchanged
    np.testing.assert_allclose([p.area for p in placed], outlines.area_mm2, rtol=1e-9)
    assert nested.overlaps == 0
    assert nested.min_gap_mm >= params.spacing_mm - 1e-6
    assert nested.material_use == pytest.approx(outlines.area_mm2.sum() / (nested.sheet_count * width * height))
    assert set(np.unique(nested.part_sheet)) == set(range(nested.sheet_count))


def test_shelf_fallback_packs_a_sheet():
    outlines = traces([250, 200, 180, 150, 120, 100, 90, 60], bend=6.0)
    params = Params(nester="shelf", spacing_mm=1.5)
    nested = nest(params, outlines)
    assert nested.nester == "shelf" and nested.sheet_count == 1
    check_layout(outlines, nested, params)


def test_raster_packs_densely_with_spacing():
    outlines = traces([250, 200, 180, 120, 100, 60], bend=10.0)
    params = Params(spacing_mm=1.0)
    nested = nest(params, outlines)
    assert nested.nester == "raster", nested.fallback_reason
    check_layout(outlines, nested, params)
    shelf = nest(Params(nester="shelf", spacing_mm=1.0), outlines)
    assert nested.used_length_mm < shelf.used_length_mm  # denser than the fallback


def test_raster_placement_is_reproducible():
    outlines = traces([250, 200, 180, 120, 100, 60], bend=10.0)
    first, second = nest(Params(), outlines), nest(Params(), outlines)
    assert first.rotation_deg.tobytes() == second.rotation_deg.tobytes()
    assert first.translation.tobytes() == second.translation.tobytes()
    assert first.part_sheet.tobytes() == second.part_sheet.tobytes()


@pytest.mark.parametrize("spacing", [0.5, 2.0])
def test_raster_gap_is_at_least_the_spacing(spacing):
    outlines = traces([150, 140, 130, 120, 110, 100, 90, 80], bend=8.0)
    params = Params(mat="custom", sheet_width_mm=160, sheet_height_mm=60, spacing_mm=spacing, pixel_mm=0.7)
    nested = nest(params, outlines)
    assert nested.nester == "raster", nested.fallback_reason
    check_layout(outlines, nested, params)


@pytest.mark.parametrize("nester", ["shelf", "raster"])
def test_more_sheets_when_needed(nester):
    outlines = traces([100] * 5)
    params = Params(mat="custom", sheet_width_mm=130, sheet_height_mm=20, nester=nester)
    nested = nest(params, outlines)
    assert nested.nester == nester, nested.fallback_reason
    assert nested.sheet_count >= 2
    check_layout(outlines, nested, params)


def test_auto_mat_takes_12x24_for_a_trace_too_long_for_12x12():
    outlines = traces([400, 150], fit_mat="12x24")
    with pytest.raises(UserError, match=r"Tx00 is 4\d\d x \d+ mm flat and does not fit .* at any rotation; .*12x24"):
        nest(Params(mat="12x12", nester="shelf"), outlines)
    params = Params(nester="shelf")
    nested = nest(params, outlines)
    assert nested.mat == "12x24" and "Tx00 does not fit the 12x12 mat" in nested.mat_reason
    assert (nested.sheet_width_mm, nested.sheet_height_mm) == MATS_MM["12x24"]
    check_layout(outlines, nested, params)
    small = nest(Params(nester="shelf"), traces([150, 100]))
    assert small.mat == "12x12"


def test_custom_sheet_needs_both_sizes():
    with pytest.raises(pydantic.ValidationError, match="sheet_width_mm and sheet_height_mm"):
        Params(mat="custom", sheet_width_mm=200)
    with pytest.raises(pydantic.ValidationError):
        Params(sheet_width_mm=200, sheet_height_mm=100)


def test_part_fitting_only_diagonally_gets_its_own_sheet():
    outlines = traces([112, 40])  # 112 mm + 9 mm tab: longer than the 118 mm sheet side, fits diagonally
    for nester in ("raster", "shelf"):
        params = Params(mat="custom", sheet_width_mm=120, sheet_height_mm=40, nester=nester)
        check_layout(outlines, nest(params, outlines), params)


TIGHT_ARC = [(0.0, 3.2), (207.2, 162.8), (241.2, 196.9), (260.5, 224.8), (274.7, 242.0), (293.0, 253.7), (306.3, 258.9),
             (309.9, 258.6), (293.4, 252.8), (275.3, 241.2), (234.9, 188.1), (194.1, 150.4), (72.9, 57.8), (9.6, 5.3),
             (2.3, 0.0)]
"""A piece of a 1.5 m object's trace (simplified to 2 mm), split to fit the 12 x 12 in mat: about 400 mm
along its arc, it fits the usable area only within about 1.5 deg of one angle."""


def test_a_piece_that_fits_the_mat_only_tightly_is_placed_by_the_raster_nester():
    """On its coarse grid the ranking places the piece at none of the 96 angles, so its finalists were the
    first four angles, none of which fits: the raster nester raised and the whole nest fell back to
    shelves (a 1.5 m bunny: 114 sheets, 18 with the raster nester)."""
    long_side, short_side = usable_sides(*MATS_MM["12x12"], MARGIN_MM)
    piece = Polygon(TIGHT_ARC)
    assert 0 < len(fit_angles(piece, long_side, short_side)) <= 8  # 4 angles 0.5 deg apart, either way round the square
    [(sheet, angle, shift)] = raster_nest([Part(piece, 1.0, 0.5, long_side, short_side)], long_side, short_side,
                                          1.0, 0.5, 96, 4, [0])
    placed = shapely.affinity.translate(shapely.affinity.rotate(piece, angle, origin=(0, 0)), *shift)
    assert sheet == 0 and shapely.box(0, 0, long_side, short_side).buffer(1e-6).contains(placed)


def test_a_trace_longer_than_any_mat_never_fails_late():
    """Issue 12: a 664 x 118 mm unfolded trace (a cup's Rx) is split to fit the 12 x 12 mat and nested."""
    import json

    from test_fab_outline import long_arc, unfolded_from_polylines

    from retrotouch.nodes.fab.cut_sheets import Params as SheetParams
    from retrotouch.nodes.fab.cut_sheets import cut_sheets

    polylines = [long_arc(), straight(120.0) + [0.0, 0.0]]
    outlines = outline(OutlineParams(), unfolded_from_polylines(polylines, [(0, 30.0, True), (1, 50.0, True)]))
    params = Params()
    nested = nest(params, outlines)
    assert nested.mat == "12x12" and nested.sheet_count == 1
    check_layout(outlines, nested, params)
    report = json.loads(cut_sheets(SheetParams(), outlines, nested).contents["sheets/report.json"])
    assert report["mat"] == "12x12" and report["joints"] == outlines.count - 2 >= 1
    assert report["split_traces"] == [{"trace": "Tx00", "reason": "longer than the 12x12 mat"}]
    whole = outline(OutlineParams(fit_mat="none"), unfolded_from_polylines(polylines))
    with pytest.raises(UserError, match="Tx00 is 6\\d\\d x \\d+ mm flat and does not fit the 292.1 x 596.9 mm sheet"):
        nest(params, whole)  # without splitting even the 12 x 24 mat is too short: said before any nesting


def ring_layout(scale: float = 1.0):
    """What the rings layout unfolds to: 12 wide Rx arcs (circles of 30-129 mm radius, 300 to 190
    degrees, times ``scale``) and 21 straight Tx of 120-220 mm (times ``scale``), pads every 30 mm;
    outlined and split to fit the 12 x 12 mat."""
    def arc(radius: float, turn_deg: float) -> np.ndarray:
        t = np.radians(np.linspace(0.0, turn_deg, 200))
        points = radius * np.stack([np.cos(t), np.sin(t)], axis=1)
        return points - points[-1]

    polylines = [arc(scale * (30 + 9 * k), 300 - 10 * k) for k in range(12)]
    polylines += [straight(scale * (120 + 5 * k), 60) for k in range(21)]
    lengths = [np.linalg.norm(np.diff(p, axis=0), axis=1).sum() for p in polylines]
    marks = [(c, s, True) for c, length in enumerate(lengths) for s in np.arange(10.0, length - 5, 30.0)]
    return outline(OutlineParams(), unfolded_from_polylines(polylines, marks))


def test_long_arcs_of_a_rings_layout_pack_on_two_sheets():
    """Issue 16: wide arcs (up to 1.2 m of a 290-degree ring) and 330 mm Tx fit two 12 x 12 sheets."""
    outlines = ring_layout(scale=1.5)
    assert outlines.joints == outlines.count - 33 >= 1  # the longest rings were split to fit the mat
    params = Params(mat="12x12")
    nested = nest(params, outlines)
    assert nested.nester == "raster", nested.fallback_reason
    assert nested.sheet_count <= 2
    check_layout(outlines, nested, params)


def test_a_pass_stops_once_worse_than_the_best_and_only_then():
    from retrotouch.nodes.fab.mats import usable_sides
    from retrotouch.nodes.fab.nesting import _strip_score
    from retrotouch.nodes.fab.raster_nest import Part, raster_nest

    outlines = ring_layout(scale=0.8)
    polygons = [outlines.polygon(i) for i in range(outlines.count)]
    long_side, short_side = usable_sides(292.1, 160.0, 1.0)
    parts = [Part(p, 1.0, 0.5, long_side, short_side) for p in polygons]
    order = sorted(range(len(parts)), key=lambda i: -polygons[i].minimum_rotated_rectangle.area)

    def run(beaten_by):
        return raster_nest(parts, long_side, short_side, 1.0, 0.5, 72, 4, order, beaten_by)

    full = run(None)
    sheets, length = _strip_score(full, polygons)
    assert sheets == 2  # the bound below is then checked on the sheet count and on the last strip
    assert run((sheets, length)) == full  # not worse than the bound: the same placement
    assert run((sheets, length * 0.99)) is None
    assert run((sheets - 1, np.inf)) is None


def test_a_placement_on_one_sheet_ends_the_passes(monkeypatch):
    """No pass can save a sheet when the first one used one: the raster nester runs once."""
    from retrotouch.nodes.fab import nesting

    passes = []
    monkeypatch.setattr(nesting, "raster_nest", lambda *args: passes.append(args[5]) or raster_nest(*args))
    nested = nest(Params(), traces([250, 200, 180, 120, 100, 60], bend=10.0))
    assert nested.sheet_count == 1 and passes == [3 * nesting.ROTATION_STEP] and nested.rotations == passes[0]
    passes.clear()
    nested = nest(Params(mat="custom", sheet_width_mm=130, sheet_height_mm=20), traces([100] * 5))
    assert nested.sheet_count >= 2 and len(passes) >= 2  # more angles may save a sheet: a second pass runs
