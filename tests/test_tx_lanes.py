"""curves.tx_lanes: copies of merging Tx lines that run beside the line they merge into."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from curves_fixture import bunny
from retrotouch.nodes.curves.lanes import (BASE_LEVEL, STEP_MM, TxLanesParams, dense_points, merges, spine_distance,
                                           tx_lanes)
from retrotouch.nodes.curves.ring_levels import RingLevelsParams, radial_function, ring_levels, row_values
from retrotouch.nodes.curves.tracing import TraceTxParams, trace_tx
from retrotouch.nodes.data.types import CurveEnd


@pytest.fixture(scope="module")
def families():
    mesh, regions, tables, tx_field, _ = bunny()
    tx = trace_tx(TraceTxParams(), mesh, regions, tx_field)["curves"]
    levels = ring_levels(RingLevelsParams(), mesh, regions, tx_field, tx)
    return tx, tx_lanes(TxLanesParams(), mesh, levels, tx), levels


def rows_of(curves, c):
    return curves.faces[curves.curve(c)], curves.bary[curves.curve(c)]


def test_field_lines_are_kept_in_order_each_followed_by_its_lanes(families):
    tx, out, _ = families
    field = np.flatnonzero(out.lane_parent < 0)
    assert len(field) == tx.count and out.count > tx.count  # the bunny's second ear: lines merge down its flank
    for k, c in enumerate(field):
        assert np.array_equal(rows_of(out, c)[0], rows_of(tx, k)[0])
        assert np.array_equal(rows_of(out, c)[1], rows_of(tx, k)[1])
    owner = np.cumsum(out.lane_parent < 0) - 1  # the field line each curve follows in the family
    assert np.array_equal(out.lane_parent[out.lane_parent >= 0], owner[out.lane_parent >= 0])


def test_a_lane_leaves_its_line_and_keeps_one_offset_from_the_spine(families):
    """Beyond its branch a lane lies on the level set of the piecewise-linear distance from its spine
    (exactly), and in space within half the mesh's longest edge of that offset (the interpolation error)."""
    mesh, regions, tables, *_ = bunny()
    tx, out, _ = families
    params = TxLanesParams()
    points, curve, arc = dense_points(tx, STEP_MM)
    spine_of = merges(points, curve, arc, tx.count, params, min(params.offsets_mm))
    vertex_tree = cKDTree(mesh.vertices)
    longest_edge = np.linalg.norm(np.diff(mesh.vertices[mesh.faces[:, [0, 1, 2, 0]]], axis=1), axis=2).max()
    for lane in np.flatnonzero(out.lane_parent >= 0):
        parent = int(out.lane_parent[lane])
        own, parents = rows_of(out, lane)[0], rows_of(tx, parent)[0]
        shared = int(np.argmin(np.r_[own[: len(parents)] == parents[: len(own)], False]))
        assert shared >= 2  # the lane starts as its line
        spine_points = points[curve == spine_of[parent][0]]
        to_spine = spine_distance(tables, spine_points, max(params.offsets_mm) + 2.0, vertex_tree)
        rows = np.arange(out.offsets[lane] + shared + 1, out.offsets[lane + 1])
        on_level = row_values(tables, to_spine, out.faces[rows], out.bary[rows])
        offset = min(params.offsets_mm, key=lambda o: abs(o - np.median(on_level)))
        assert np.abs(on_level - offset).max() < 1e-6
        in_space = cKDTree(spine_points).query(out.points[rows])[0]
        assert np.abs(in_space - offset).max() < 0.5 * longest_edge


def test_lanes_end_on_the_base(families):
    mesh, regions, tables, *_ = bunny()
    _, out, _ = families
    u = radial_function(tables, regions, int(regions.far_vertex))
    lanes = np.flatnonzero(out.lane_parent >= 0)
    last = out.offsets[lanes + 1] - 1
    assert (row_values(tables, u, out.faces[last], out.bary[last]) >= BASE_LEVEL).all()
    assert (out.end_reason[lanes] == int(CurveEnd.BASE)).all()


def test_no_offsets_keep_the_field_lines_alone(families):
    mesh, *_ = bunny()
    tx, _, levels = families
    assert tx_lanes(TxLanesParams(offsets_mm=[]), mesh, levels, tx) is tx


@pytest.mark.parametrize("offsets", [[3.0, 0.0], [-2.0]])
def test_an_offset_that_is_not_positive_is_refused(offsets):
    with pytest.raises(ValueError, match="greater than 0"):
        TxLanesParams(offsets_mm=offsets)
