"""fab.outline: trace width, pads at the unfolded pad positions, landmarks, named solder tab,
self-overlapping traces split into pieces that do not overlap."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import shapely
import trimesh
from fab_layouts import mesh_from_trimesh, section_layout
from shapely.geometry import LineString, Point, Polygon

from retrotouch.graph.errors import UserError
from retrotouch.nodes.data.types import TRACE_WIDTH_MM
from retrotouch.nodes.fab.outline import Params, outline
from retrotouch.nodes.fab.unfold import Params as UnfoldParams
from retrotouch.nodes.fab.unfold import UnfoldedTraces, unfold


def unfolded_from_polylines(polylines: list[np.ndarray], marks: list[tuple[int, float, bool]] = (),
                            pad_offset: float = 3.0) -> UnfoldedTraces:
    """Hand-made unfolded traces (all Tx, base at the end); marks = (trace, arc, pad)."""
    arcs = [np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))]) for p in polylines]

    def at(c, s):
        return np.array([np.interp(s, arcs[c], polylines[c][:, i]) for i in range(2)])

    mark_xy, tangent, pad_arc, pad_xy = [], [], [], []
    for c, s, _ in marks:
        mark_xy.append(at(c, s))
        d = at(c, s + 1e-6) - at(c, s - 1e-6)
        tangent.append(d / np.linalg.norm(d))
        pad_arc.append(min(s + pad_offset, arcs[c][-1]))
        pad_xy.append(at(c, pad_arc[-1]))
    n = len(polylines)
    return UnfoldedTraces(
        names=tuple(f"Tx{c:02d}" for c in range(n)),
        layers=("tx",) * n,
        channels=np.arange(n),
        points=np.concatenate(polylines),
        arc=np.concatenate(arcs),
        offsets=np.concatenate([[0], np.cumsum([len(p) for p in polylines])]),
        length_3d=np.array([a[-1] for a in arcs]),
        base_at_end=np.ones(n, dtype=bool),
        mark_trace=np.array([m[0] for m in marks], dtype=np.int64),
        mark_other=np.zeros(len(marks), dtype=np.int64),
        mark_cell=np.arange(len(marks)),
        mark_arc=np.array([m[1] for m in marks], dtype=np.float64),
        mark_xy=np.array(mark_xy).reshape(-1, 2),
        mark_tangent=np.array(tangent).reshape(-1, 2),
        mark_pad=np.array([m[2] for m in marks], dtype=bool),
        pad_arc=np.array(pad_arc, dtype=np.float64),
        pad_xy=np.array(pad_xy).reshape(-1, 2),
    )


def straight(length: float, n: int = 50) -> np.ndarray:
    """From x = -length to the base end at the origin."""
    return np.stack([np.linspace(-length, 0.0, n), np.zeros(n)], axis=1)


@pytest.mark.parametrize("width", [1.0, 0.6])
def test_trace_width(width):
    outlines = outline(Params(landmark_radius_mm=0), dataclasses.replace(unfolded_from_polylines([straight(120.0)]), trace_width_mm=width))
    assert outlines.count == 1
    body = outlines.polygon(0).difference(Polygon(outlines.tab[0]).buffer(0.01))
    # rectangle width x length plus the far round cap (a half disc)
    expected = width * 120.0 + np.pi * width**2 / 8
    assert body.area == pytest.approx(expected, rel=2e-3)
    assert not body.buffer(-width / 2 + 0.02).is_empty
    assert body.buffer(-width / 2 - 0.02).is_empty


def test_pads_landmarks_and_tab_positions():
    curve = np.stack([np.linspace(-100, 0, 200), 8 * np.sin(np.linspace(0, 2, 200))], axis=1)
    curve -= curve[-1]  # base end at the origin, as fab.unfold leaves it
    unfolded = unfolded_from_polylines([curve], [(0, 20.0, True), (0, 50.0, False), (0, 80.0, True)])
    params = Params()
    outlines = outline(params, unfolded)
    polygon = outlines.polygon(0)
    # pads exactly at the unfolded pad positions (3 mm further along the trace) and inside the outline
    np.testing.assert_allclose(outlines.pad_xy, unfolded.pad_xy[[0, 2]], atol=1e-12)
    arc = unfolded.arc
    for pad, mark in zip(outlines.pad_xy, [0, 2]):
        along = [np.interp(unfolded.mark_arc[mark] + 3.0, arc, curve[:, i]) for i in range(2)]
        np.testing.assert_allclose(pad, along, atol=1e-9)
        assert polygon.contains(Point(pad).buffer(unfolded.pad_radius_mm - 0.05, quad_segs=8))
        assert not polygon.contains(Point(pad).buffer(unfolded.pad_radius_mm + 0.05))
    # a landmark at every crossing
    np.testing.assert_allclose(outlines.landmark_xy, unfolded.mark_xy, atol=1e-12)
    for xy in outlines.landmark_xy:
        assert polygon.contains(Point(xy).buffer(params.landmark_radius_mm - 0.05, quad_segs=8))
    # the solder tab starts at the base end (origin), continues the end tangent, holds the label
    tab = outlines.tab[0]
    np.testing.assert_allclose((tab[0] + tab[1]) / 2, [0.0, 0.0], atol=1e-9)
    end_tangent = (curve[-1] - curve[-2]) / np.linalg.norm(curve[-1] - curve[-2])
    axis = (tab[2] + tab[3]) / 2 - (tab[0] + tab[1]) / 2
    np.testing.assert_allclose(axis, params.solder_tab_length_mm * end_tangent, atol=1e-6)
    tab_polygon = Polygon(tab)
    assert polygon.contains(tab_polygon.buffer(-1e-6))
    glyphs = outlines.label_polylines(0)
    assert len(glyphs) >= 4  # "Tx00": at least one outline per glyph
    for glyph in glyphs:
        assert tab_polygon.buffer(-params.label_margin_mm + 1e-6).contains(LineString(glyph))
    assert outlines.names == ("Tx00",) and outlines.split_traces == ()


def test_outlines_of_a_sphere_layout_are_single_polygons():
    mesh = mesh_from_trimesh(trimesh.creation.icosphere(subdivisions=3, radius=40.0), "icosphere")
    layout = section_layout(mesh, 6, 4)
    unfolded = unfold(UnfoldParams(), mesh, layout)
    outlines = outline(Params(), unfolded)
    assert outlines.count == unfolded.count
    assert len(outlines.pad_xy) == 2 * int(layout.pad.sum())
    assert len(outlines.landmark_xy) == 2 * len(layout.cells.curve_a)
    for part, other in zip(outlines.landmark_part, outlines.landmark_other):
        assert outlines.names[part][:2] != outlines.trace_names[other][:2]  # crossed by the other layer
    for i in range(outlines.count):
        polygon = outlines.polygon(i)
        assert polygon.is_valid and len(polygon.interiors) == 0
        assert polygon.area == pytest.approx(outlines.area_mm2[i])
        centre = outlines.centre[outlines.centre_offsets[i] : outlines.centre_offsets[i + 1]]
        assert polygon.contains(LineString(centre).buffer(0.49))


def _self_overlapping_pairs(centre: np.ndarray, contact: float) -> int:
    """Pairs of centreline samples closer than ``contact`` while > pi/2 * contact apart along it."""
    line = LineString(centre)
    s = np.arange(0.0, line.length, 0.1)
    pts = np.array([line.interpolate(x).coords[0] for x in s])
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    far = np.abs(s[:, None] - s[None]) > np.pi / 2 * contact
    return int(np.count_nonzero((d < contact) & far))


def test_spiral_is_split_into_pieces_that_do_not_overlap():
    t = np.linspace(0, 3 * np.pi, 600)  # 1.5 turns of a circle of radius 10 mm
    spiral = np.stack([10 * np.cos(t), 10 * np.sin(t) + 0.3 * t], axis=1)
    spiral -= spiral[-1]
    params = Params()
    contact = TRACE_WIDTH_MM + params.self_clearance_mm
    assert _self_overlapping_pairs(spiral, contact) > 0
    unfolded = unfolded_from_polylines([spiral], [(0, 30.0, True)])
    with pytest.raises(UserError, match="Tx00 overlaps itself"):
        outline(params.model_copy(update={"on_self_overlap": "error"}), unfolded)
    outlines = outline(params, unfolded)
    assert outlines.split_traces == ("Tx00",)
    assert outlines.count >= 2 and outlines.names[:2] == ("Tx00.1", "Tx00.2")
    covered = sorted(map(tuple, outlines.arc_range))
    assert covered[0][0] == 0.0 and covered[-1][1] == pytest.approx(unfolded.arc[-1])
    for (_, hi), (lo, _) in zip(covered[:-1], covered[1:]):
        assert hi == pytest.approx(lo)  # pieces are contiguous along the trace
    for i in range(outlines.count):
        centre = outlines.centre[outlines.centre_offsets[i] : outlines.centre_offsets[i + 1]]
        assert _self_overlapping_pairs(centre, contact) == 0
        polygon = outlines.polygon(i)
        assert polygon.is_valid and polygon.geom_type == "Polygon"
        assert len(outlines.label_polylines(i)) >= 6  # "Tx00.1": five glyphs, "0" has two outlines


def long_arc(width: float = 664.0, height: float = 118.0, n: int = 400) -> np.ndarray:
    """A parabolic arc ``width`` x ``height`` mm (centreline bounds), base end at the origin."""
    x = np.linspace(-width, 0.0, n)
    return np.stack([x, height * (1 - ((x + width / 2) / (width / 2)) ** 2)], axis=1)


@pytest.mark.parametrize("fit_mat", ["12x12", "12x24"])
def test_trace_longer_than_the_mat_is_split_into_pieces_that_fit(fit_mat):
    from retrotouch.nodes.fab.mats import MARGIN_MM, MATS_MM, fit_angles, usable_sides

    line = long_arc()
    marks = [(0, s, True) for s in np.arange(20.0, 700.0, 40.0)]
    outlines = outline(Params(fit_mat=fit_mat), unfolded_from_polylines([line], marks))
    long_side, short_side = usable_sides(*MATS_MM[fit_mat], MARGIN_MM)
    assert outlines.count >= 2 and outlines.joints == outlines.count - 1
    assert outlines.split_traces == ("Tx00",) and outlines.split_reasons == (f"longer than the {fit_mat} mat",)
    for i in range(outlines.count):
        assert len(fit_angles(outlines.polygon(i), long_side, short_side)) > 0
    # the pieces cover the trace end to end; each next piece starts where the previous ends
    ranges = outlines.arc_range[np.argsort(outlines.arc_range[:, 0])]
    np.testing.assert_allclose(ranges[0, 0], 0.0, atol=1e-9)
    np.testing.assert_allclose(ranges[-1, 1], np.linalg.norm(np.diff(line, axis=0), axis=1).sum(), rtol=1e-9)
    np.testing.assert_allclose(ranges[1:, 0], ranges[:-1, 1], atol=1e-9)
    # the 12x12 pieces are as long as the mat allows: two neighbours together would not fit
    if fit_mat == "12x12":
        assert outlines.count <= 4
    # pads are all kept, each in exactly one piece
    assert len(outlines.pad_xy) == len(marks)


def test_a_trace_curled_over_the_mat_is_split_into_pieces_that_leave_room():
    """A helix on a plate unfolds to a spiral as large as the sheet: whole, nothing else fits beside it."""
    from retrotouch.nodes.fab.mats import MARGIN_MM, MATS_MM, usable_sides

    turn = np.linspace(0.0, 2 * np.pi, 600)
    spiral = np.stack([(125 - 12 * turn) * np.cos(turn), (125 - 12 * turn) * np.sin(turn)], axis=1)  # fits the mat whole
    straight = np.stack([np.linspace(-250.0, 0.0, 200), np.zeros(200)], axis=1)
    params = Params()
    outlines = outline(params, unfolded_from_polylines([spiral - spiral[-1], straight]))
    long_side, short_side = usable_sides(*MATS_MM[params.fit_mat], MARGIN_MM)
    assert outlines.split_traces == ("Tx00",)
    assert outlines.split_reasons == (f"curls over more than {params.max_hull_share:g} of the mat",)
    spiral_parts = np.flatnonzero(outlines.trace == 0)
    assert 2 <= len(spiral_parts) <= 4  # as few as the limit allows: about 45,000 mm2 of hull, 12,600 per piece
    for i in spiral_parts:
        centre = outlines.centre[outlines.centre_offsets[i] : outlines.centre_offsets[i + 1]]
        assert shapely.MultiPoint(centre).convex_hull.area <= params.max_hull_share * long_side * short_side
    assert np.sum(outlines.trace == 1) == 1  # the straight trace of about the same length stays whole
    whole = outline(Params(max_hull_share=1.0), unfolded_from_polylines([spiral - spiral[-1]]))
    assert whole.count == 1


def test_fit_mat_none_keeps_the_trace_whole():
    outlines = outline(Params(fit_mat="none"), unfolded_from_polylines([long_arc()]))
    assert outlines.count == 1 and outlines.joints == 0


def test_small_pocket_between_tab_bend_and_pad_is_filled():
    """The cat's first ring (170 mm, 8000 vertices) leaves its base downwards and turns right within
    1.5 mm: the tab, that bend and a pad enclose a 0.4 mm2 pocket, which failed the run."""
    bend = np.array([[4.60, -2.49], [4.61, -1.94], [4.13, -1.76], [3.80, -2.08], [3.03, -2.11], [2.83, -2.04],
                     [1.51, -1.75], [1.36, -1.69], [-0.02, -1.42], [-0.14, -1.37], [-0.18, -1.36], [-0.16, -1.27],
                     [-0.12, -1.08], [0.0, 0.0]])
    line = np.vstack([np.stack([np.linspace(60, 5, 30), np.full(30, -4.0)], axis=1), bend])
    unfolded = unfolded_from_polylines([line], [(0, 58.8, True)], pad_offset=1.0)
    with pytest.raises(UserError, match="not one closed polygon without holes"):
        outline(Params(fill_hole_mm2=1e-6), unfolded)
    outlines = outline(Params(), unfolded)
    polygon = outlines.polygon(0)
    assert outlines.count == 1 and polygon.is_valid and len(polygon.interiors) == 0
    pieces = shapely.unary_union([Polygon(outlines.tab[0]), LineString(line).buffer(0.5, quad_segs=8),
                                  Point(outlines.pad_xy[0]).buffer(unfolded.pad_radius_mm, quad_segs=8),
                                  Point(outlines.landmark_xy[0]).buffer(1.0, quad_segs=8)])
    assert len(pieces.interiors) == 1 and polygon.buffer(Params().simplify_mm + 1e-6).contains(pieces)
    assert 0 < polygon.area - pieces.area <= 8.0  # only the pocket was added


def test_the_outline_drops_only_vertices_it_does_not_need():
    """``simplify_mm``: the cut outline lies within that distance of the exact one, with far fewer
    vertices (a dense centreline's buffer repeats points a few micrometres apart)."""
    unfolded = unfolded_from_polylines([long_arc()])
    exact = outline(Params(simplify_mm=0.0), unfolded).polygon(0)
    simplified = outline(Params(), unfolded).polygon(0)
    assert exact.hausdorff_distance(simplified) <= Params().simplify_mm + 1e-9
    assert len(simplified.exterior.coords) < 0.8 * len(exact.exterior.coords)
    assert abs(simplified.area - exact.area) < 1e-3 * exact.area
