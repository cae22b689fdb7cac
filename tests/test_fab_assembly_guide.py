"""fab.assembly_guide: renderer visibility, readable upright views, one PDF page per trace between an
overview and the wiring table, the wiring table as CSV, split pieces laid out apart with their joint."""
from __future__ import annotations

import csv
import io
import re

import numpy as np
import pytest
import trimesh
from fab_layouts import mesh_from_trimesh, section_layout

from retrotouch.nodes.fab.assembly_guide import Params, _TracePages, assembly_guide, object_frame, wiring_rows
from retrotouch.nodes.fab.guide_views import ObjectFrame, render
from retrotouch.nodes.fab.outline import Params as OutlineParams
from retrotouch.nodes.fab.outline import outline
from retrotouch.nodes.fab.unfold import Params as UnfoldParams
from retrotouch.nodes.fab.unfold import unfold

SPHERE = mesh_from_trimesh(trimesh.creation.icosphere(subdivisions=3, radius=40.0), "icosphere r40")


def test_render_sees_the_near_side_only():
    view = render(SPHERE, np.array([0.0, 0.0, 1.0]), 120)
    points = np.array([[0, 0, 40.0], [0, 0, -40.0], [28.0, 0, 28.0], [28.0, 0, -28.0]])
    np.testing.assert_array_equal(view.visible(points, 0.4), [True, False, True, False])
    px, depth = view.project(points[:1])
    np.testing.assert_allclose(px[0], [60, 60], atol=1.0)  # centred
    covered = np.isfinite(view.depth)
    disc = np.pi * (40.0 * view.scale) ** 2
    assert abs(covered.sum() - disc) < 0.05 * disc  # silhouette of the sphere


@pytest.mark.parametrize("up", [(0, 0, 1.0), (0, 1.0, 0), (1.0, 0, 0)])
def test_views_are_upright_and_named_in_the_object_frame(up):
    frame = ObjectFrame.from_up(np.array(up))
    assert frame.name(np.array(up)) == "top view" and frame.name(-np.array(up)) == "bottom view"
    assert frame.name(frame.front) == "front view" and frame.name(frame.right) == "right view"
    assert frame.name(frame.front + frame.up) == "front view from above"
    side = next(d for d in np.eye(3) if abs(d @ np.array(up)) < 0.5)
    view = render(SPHERE, side, 100, frame)
    np.testing.assert_allclose(view.up, up, atol=1e-12)  # image up = the object's up
    z_up = ObjectFrame.from_up(np.array([0, 0, 1.0]))
    np.testing.assert_allclose(z_up.front, [0, -1, 0]) and np.testing.assert_allclose(z_up.right, [1, 0, 0])


def test_object_frame_points_away_from_the_base_ends():
    layout = section_layout(SPHERE, 3, 2)  # meridians run top -> bottom: the base is at -z
    assert object_frame(SPHERE, layout).up @ np.array([0, 0, 1.0]) > 0.9


def test_guide_pages_and_wiring_table():
    layout = section_layout(SPHERE, 3, 2)
    outlines = outline(OutlineParams(), unfold(UnfoldParams(), SPHERE, layout))
    files = assembly_guide(Params(image_px=100, views_per_trace=2), SPHERE, layout, outlines)
    pdf = files.contents["assembly_guide.pdf"]
    assert pdf.startswith(b"%PDF")
    assert len(re.findall(rb"/Type\s*/Page\b", pdf)) == 1 + 5 + 1  # overview, 5 traces, wiring table
    rows = list(csv.DictReader(io.StringIO(files.contents["wiring.csv"].decode())))
    assert [r["tab"] for r in rows] == list(outlines.names)
    assert [r["muca_pin"] for r in rows] == ["TX0", "TX1", "TX2", "RX0", "RX1"]
    assert [r["layer_order"] for r in rows] == ["1"] * 3 + ["2"] * 2


def test_split_pieces_are_laid_out_apart_with_their_joint_drawn():
    from matplotlib.figure import Figure
    from test_fab_outline import long_arc, unfolded_from_polylines

    outlines = outline(OutlineParams(), unfolded_from_polylines([long_arc()], [(0, 30.0, True)]))
    assert outlines.count >= 2
    rows = wiring_rows(section_layout(SPHERE, 1, 1), outlines)
    assert rows[0]["wire"] == "to the Muca pin" and rows[1]["wire"] == "soldered onto Tx00.1's end"
    pages = _TracePages(Figure, [render(SPHERE, np.array([0, 0, 1.0]), 100)], 1)
    from retrotouch.nodes.fab.assembly_guide import _draw_pieces

    _draw_pieces(pages.fig, pages.flat, outlines, np.arange(outlines.count))
    fills = [p for p in pages.flat.patches]
    assert len(fills) == outlines.count
    boxes = [p.get_path().get_extents() for p in fills]
    for a, b in zip(boxes, boxes[1:]):
        assert a.x1 < b.x0  # side by side, not on top of each other
    assert any("joint" in t.get_text() for t in pages.flat.texts)
    labels = [t for t in pages.flat.texts if t.get_text().startswith("Rx")]
    assert labels == [] or len(labels) == len(outlines.landmark_xy)


def test_crossing_labels_do_not_overlap_where_crossings_cluster():
    from retrotouch.nodes.fab.assembly_guide import _label_offsets

    anchors = np.array([[100.0, 100.0]] * 6 + [[104.0, 101.0]] * 4)  # ten labels on two nearby points
    sizes = np.full((10, 2), [22.0, 8.0])
    taken = [(90.0, 110.0, 140.0, 124.0)]  # the part's name label above
    offsets = np.array(_label_offsets(anchors, sizes, taken))
    boxes = np.hstack([anchors + offsets - sizes / 2, anchors + offsets + sizes / 2])
    for i in range(len(boxes)):
        for j in range(i):
            a, b = boxes[i], boxes[j]
            assert a[2] <= b[0] or b[2] <= a[0] or a[3] <= b[1] or b[3] <= a[1], (i, j)
        c = taken[0]
        assert boxes[i][2] <= c[0] or c[2] <= boxes[i][0] or boxes[i][3] <= c[1] or c[3] <= boxes[i][1]


def test_attached_traces_are_drawn_in_later_views_where_visible():
    from matplotlib.figure import Figure

    view = render(SPHERE, np.array([0, 0, 1.0]), 100)
    pages = _TracePages(Figure, [view], 1)
    arc = np.stack([40 * np.sin(np.linspace(0.2, 1.2, 30)), np.zeros(30), 40 * np.cos(np.linspace(0.2, 1.2, 30))], 1)
    hidden = arc * [1, 1, -1]  # the same arc on the far side
    pages.attach(hidden, [view], 0.4)
    assert np.isnan(np.vstack(pages.attached[0])).all()  # nothing visible: nothing drawn
    pages.attach(arc, [view], 0.4)
    trail = np.vstack(pages.attached[0])
    px, _ = view.project(arc)
    seen = view.visible(arc, 0.4)
    assert seen.sum() > 20
    np.testing.assert_allclose(trail[np.isfinite(trail[:, 0])], px[seen])  # the visible part, in the view's pixels


def test_a_view_shown_on_many_pages_is_one_pdf_image():
    from matplotlib.backends.backend_pdf import PdfPages
    from matplotlib.figure import Figure

    pages = _TracePages(Figure, [render(SPHERE, np.array([0, 0, 1.0]), 100)], 1)
    buffer = io.BytesIO()
    with PdfPages(buffer) as pdf:
        for _ in range(3):
            pdf.savefig(pages.fig)
    assert len(re.findall(rb"/Subtype\s*/Image", buffer.getvalue())) == 1
