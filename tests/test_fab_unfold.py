"""fab.unfold: isometric strip unfolding keeps lengths, distances on developable strips, and crossings."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh
from fab_layouts import curve_set, mesh_from_trimesh, section_layout

from retrotouch.graph.errors import UserError
from retrotouch.nodes.data.types import Crossings, Layout, Mesh
from retrotouch.nodes.fab.unfold import Params, UnfoldedTraces, unfold


@pytest.fixture(scope="module")
def sphere() -> Mesh:
    return mesh_from_trimesh(trimesh.creation.icosphere(subdivisions=3, radius=40.0), "icosphere r40")


@pytest.fixture(scope="module")
def cylinder() -> Mesh:
    return mesh_from_trimesh(trimesh.creation.cylinder(radius=30.0, height=100.0, sections=40), "cylinder r30 h100")


def _traces(unfolded: UnfoldedTraces):
    for c in range(unfolded.count):
        yield c, unfolded.points[unfolded.trace(c)], unfolded.arc[unfolded.trace(c)]


def test_unfolded_length_equals_3d_length(sphere):
    layout = section_layout(sphere, 6, 4)
    unfolded = unfold(Params(), sphere, layout)
    assert unfolded.count == 10
    assert unfolded.names[:2] == ("Tx00", "Tx01") and unfolded.names[6] == "Rx00"
    lengths_3d = np.concatenate([layout.tx.lengths_mm, layout.rx.lengths_mm])
    for c, points, arc in _traces(unfolded):
        length_2d = np.linalg.norm(np.diff(points, axis=0), axis=1).sum()
        assert abs(length_2d - lengths_3d[c]) <= 1e-9 * lengths_3d[c]
        assert abs(arc[-1] - length_2d) <= 1e-9 * length_2d
    # every single segment keeps its length too
    rows = np.concatenate([layout.tx.points, layout.rx.points])
    seg3 = np.linalg.norm(np.diff(rows, axis=0), axis=1)
    seg2 = np.linalg.norm(np.diff(unfolded.points, axis=0), axis=1)
    inner = np.ones(len(seg2), dtype=bool)
    inner[unfolded.offsets[1:-1] - 1] = False  # pairs spanning two traces
    np.testing.assert_allclose(seg2[inner], seg3[inner], rtol=1e-9, atol=1e-12)


def test_base_end_at_origin_far_end_on_x_axis(sphere):
    unfolded = unfold(Params(), sphere, section_layout(sphere, 3, 2))
    for c, points, _ in _traces(unfolded):
        base, far = (points[-1], points[0]) if unfolded.base_at_end[c] else (points[0], points[-1])
        np.testing.assert_allclose(base, 0.0, atol=1e-9)
        assert far[0] > 0 and abs(far[1]) < 1e-9


def test_sections_of_a_prism_unfold_to_straight_lines(cylinder):
    """A prism's side wall is developable: a horizontal section unfolds to a straight segment, so every
    pair of rows is as far apart in 2D as along the curve."""
    layout = section_layout(cylinder, 4, 3, keep=0.9)
    unfolded = unfold(Params(), cylinder, layout)
    for c, points, arc in _traces(unfolded):
        if unfolded.layers[c] == "tx":
            continue  # meridians cross the cap rims at an angle: not straight
        assert arc[-1] > 150  # most of the 2 pi 30 mm circumference
        pairwise_2d = np.linalg.norm(points[:, None] - points[None], axis=2)
        np.testing.assert_allclose(pairwise_2d, np.abs(arc[:, None] - arc[None]), atol=1e-8)


def test_crossings_and_pads_map_to_their_arc_positions(sphere):
    layout = section_layout(sphere, 6, 4)
    unfolded = unfold(Params(pad_offset_mm=3.0), sphere, layout)
    cells = layout.cells
    assert len(unfolded.mark_trace) == 2 * len(cells.curve_a)
    for m in range(len(unfolded.mark_trace)):
        k = unfolded.mark_cell[m]
        is_tx = unfolded.layers[unfolded.mark_trace[m]] == "tx"
        expected_arc = cells.arc_a[k] if is_tx else cells.arc_b[k]
        assert unfolded.mark_arc[m] == pytest.approx(expected_arc, abs=1e-9)
        rows = unfolded.trace(unfolded.mark_trace[m])
        points, arc = unfolded.points[rows], unfolded.arc[rows]
        on_polyline = [np.interp(unfolded.mark_arc[m], arc, points[:, i]) for i in range(2)]
        np.testing.assert_allclose(unfolded.mark_xy[m], on_polyline, atol=1e-9)
        length = arc[-1]
        assert unfolded.pad_arc[m] == pytest.approx(min(unfolded.mark_arc[m] + 3.0, length), abs=1e-12)
        on_polyline = [np.interp(unfolded.pad_arc[m], arc, points[:, i]) for i in range(2)]
        np.testing.assert_allclose(unfolded.pad_xy[m], on_polyline, atol=1e-9)
        assert np.linalg.norm(unfolded.mark_tangent[m]) == pytest.approx(1.0)
        assert unfolded.mark_pad[m] == layout.pad[k]
    # the two marks of a cell point at each other's traces
    tx_marks = unfolded.mark_trace[::2]
    np.testing.assert_array_equal(unfolded.mark_other[1::2], tx_marks)


def test_curve_through_a_vertex_unfolds_around_the_fan():
    """Flat hexagonal fan; the curve goes from face 0 through the centre vertex into face 3. On a
    flat mesh every unfolding is a rigid motion, so all 2D distances equal the 3D ones."""
    angles = np.arange(6) * np.pi / 3
    vertices = np.vstack([[0, 0, 0], np.stack([10 * np.cos(angles), 10 * np.sin(angles), np.zeros(6)], axis=1)])
    faces = np.array([[0, 1 + i, 1 + (i + 1) % 6] for i in range(6)], dtype=np.int64)
    mesh = Mesh(vertices, faces, "fan")
    rows_faces = np.array([0, 3, 3], dtype=np.int64)
    bary = np.array([[0.2, 0.4, 0.4], [1.0, 0.0, 0.0], [0.1, 0.5, 0.4]])
    points = np.einsum("rk,rkd->rd", bary, vertices[faces[rows_faces]])
    curves = curve_set("tx", [(points, rows_faces, bary)])
    empty = Crossings("tx", "rx", *(np.zeros(0, np.int64),) * 4, *(np.zeros(0),) * 2, np.zeros((0, 3)),
                      np.zeros(0, np.int64), np.zeros((0, 3)))
    layout = Layout(curves, curve_set("rx", [(points[::-1], rows_faces, bary[::-1])]), empty,
                    np.zeros(0, bool), np.zeros(1, np.int64), np.zeros(1, np.int64))
    unfolded = unfold(Params(), mesh, layout)
    p2 = unfolded.points[unfolded.trace(0)]
    np.testing.assert_allclose(np.linalg.norm(p2[:, None] - p2[None], axis=2),
                               np.linalg.norm(points[:, None] - points[None], axis=2), atol=1e-9)


def test_disconnected_rows_are_a_user_error(sphere):
    layout = section_layout(sphere, 2, 1)
    faces = layout.tx.faces.copy()
    far_face = int(np.argmin(sphere.vertices[sphere.faces].mean(axis=1) @ sphere.vertices[sphere.faces[faces[3]]].mean(axis=0)))
    faces[3] = far_face
    broken = Layout(dataclasses.replace(layout.tx, faces=faces), layout.rx, layout.cells, layout.pad,
                    layout.tx_source, layout.rx_source)
    with pytest.raises(UserError, match="Tx00: rows .* share no vertex"):
        unfold(Params(), sphere, broken)

