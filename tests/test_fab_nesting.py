"""fab.nest: parts on their mats, no overlaps, gaps >= spacing, more sheets when needed, clear error
for a trace longer than any mat."""
from __future__ import annotations

import numpy as np
import pydantic
import pytest
import shapely
from test_fab_outline import straight, unfolded_from_polylines

from retrotouch.graph.errors import UserError
from retrotouch.nodes.fab.nesting import Params, nest, placed_polygons
from retrotouch.nodes.fab.outline import Params as OutlineParams
from retrotouch.nodes.fab.outline import outline


def traces(lengths, bend: float = 0.0):
    """Straight (or bent) traces with a few pads each."""
    polylines = []
    for k, length in enumerate(lengths):
        line = straight(length, 80)
        line[:, 1] += bend * np.sin(np.linspace(0, np.pi * (1 + k % 3), 80))
        polylines.append(line - line[-1])
    marks = [(c, s, True) for c, length in enumerate(lengths) for s in np.arange(10.0, length - 5, 25.0)]
    return outline(OutlineParams(), unfolded_from_polylines(polylines, marks))


def check_layout(outlines, nested, params):
    width, height = params.sheet_size()
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


def test_spyrrow_packs_densely_with_spacing():
    outlines = traces([250, 200, 180, 120, 100, 60], bend=10.0)
    params = Params(seconds=1, spacing_mm=1.0)
    nested = nest(params, outlines)
    assert nested.nester == "spyrrow", nested.fallback_reason
    check_layout(outlines, nested, params)
    shelf = nest(Params(nester="shelf", spacing_mm=1.0), outlines)
    assert nested.used_length_mm < shelf.used_length_mm  # denser than the fallback


@pytest.mark.parametrize("nester", ["shelf", "spyrrow"])
def test_more_sheets_when_needed(nester):
    outlines = traces([100] * 5)
    params = Params(mat="custom", sheet_width_mm=130, sheet_height_mm=20, nester=nester, seconds=1, retry_seconds=1)
    nested = nest(params, outlines)
    assert nested.nester == nester, nested.fallback_reason
    assert nested.sheet_count >= 2
    check_layout(outlines, nested, params)


def test_portrait_12x24_mat_holds_a_trace_too_long_for_12x12():
    outlines = traces([400, 150])
    with pytest.raises(UserError, match=r"Tx00 is 4\d\d x \d+ mm flat .*mat: 12x24"):
        nest(Params(nester="shelf"), outlines)
    params = Params(mat="12x24", nester="shelf")
    nested = nest(params, outlines)
    assert (nested.sheet_width_mm, nested.sheet_height_mm) == (290.0, 600.0)
    check_layout(outlines, nested, params)


def test_custom_sheet_needs_both_sizes():
    with pytest.raises(pydantic.ValidationError, match="sheet_width_mm and sheet_height_mm"):
        Params(mat="custom", sheet_width_mm=200)
    with pytest.raises(pydantic.ValidationError):
        Params(sheet_width_mm=200, sheet_height_mm=100)


def test_part_fitting_only_diagonally_gets_its_own_sheet():
    outlines = traces([112, 40])  # 112 mm + 9 mm tab: longer than the 118 mm sheet side, fits diagonally
    params = Params(mat="custom", sheet_width_mm=120, sheet_height_mm=40, seconds=1, retry_seconds=1)
    nested = nest(params, outlines)
    check_layout(outlines, nested, params)
    shelf = Params(mat="custom", sheet_width_mm=120, sheet_height_mm=40, nester="shelf")
    check_layout(outlines, nest(shelf, outlines), shelf)


def test_spyrrow_failure_falls_back_to_shelves(monkeypatch):
    import spyrrow

    class Crashing:
        def __init__(self, *args, **kwargs):
            pass

        def solve(self, config, progress=None):
            raise RuntimeError("solver crashed")

    monkeypatch.setattr(spyrrow, "StripPackingInstance", Crashing)
    outlines = traces([150, 100, 80])
    params = Params(seconds=1)
    nested = nest(params, outlines)
    assert nested.nester == "shelf" and "solver crashed" in nested.fallback_reason
    check_layout(outlines, nested, params)
