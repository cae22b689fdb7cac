"""curves.crossings: exact crossings of hand-made curves, and consistency on the bunny."""
from __future__ import annotations

import numpy as np
import pytest

from curves_fixture import bunny
from retrotouch.nodes.curves.crossings import CrossingsParams, crossings, drop_near, find_crossings, pair_multiplicity
from retrotouch.nodes.data.types import CurveEnd, CurveSet
from retrotouch.nodes.curves.tracing import TraceRxParams, TraceTxParams, trace_rx_curves, trace_tx_curves

# unit square (mm) split along its diagonal: face 0 = lower right, face 1 = upper left
SQUARE_V = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
SQUARE_F = np.array([[0, 1, 2], [0, 2, 3]])


def bary_in(face: int, xy) -> np.ndarray:
    p = SQUARE_V[SQUARE_F[face]][:, :2]
    m = np.vstack([p.T, np.ones(3)])
    return np.linalg.solve(m, [xy[0], xy[1], 1.0])


def square_curves(layer: str, polylines: list[list[tuple[int, tuple[float, float]]]]) -> CurveSet:
    """Curves from rows ``(face of the segment starting here, (x, y))``."""
    faces = np.array([f for line in polylines for f, _ in line])
    bary = np.array([bary_in(f, xy) for line in polylines for f, xy in line])
    points = np.array([[x, y, 0.0] for line in polylines for _, (x, y) in line])
    offsets = np.cumsum([0] + [len(line) for line in polylines])
    lengths = np.array([np.linalg.norm(np.diff([xy for _, xy in line], axis=0), axis=1).sum() for line in polylines])
    return CurveSet(layer, points, faces, bary, offsets, lengths, np.zeros(len(polylines), dtype=np.int8), 0.0)


def test_crossing_in_a_face_is_exact():
    # a: y = 0.25 from x = 0 (upper-left face until the diagonal at x = 0.25) to x = 1
    a = square_curves("tx", [[(1, (0.0, 0.25)), (0, (0.25, 0.25)), (0, (1.0, 0.25))]])
    # b: x = 0.75 from y = 0 to the diagonal at y = 0.75, then up to y = 1
    b = square_curves("rx", [[(0, (0.75, 0.0)), (1, (0.75, 0.75)), (1, (0.75, 1.0))]])
    c = find_crossings(a, b, SQUARE_F)
    assert len(c.curve_a) == 1
    np.testing.assert_allclose(c.points[0], [0.75, 0.25, 0.0], atol=1e-15)
    assert c.faces[0] == 0
    np.testing.assert_allclose(c.bary[0], bary_in(0, (0.75, 0.25)), atol=1e-15)
    assert c.arc_a[0] == pytest.approx(0.75) and c.arc_b[0] == pytest.approx(0.25)
    assert (c.seg_a[0], c.seg_b[0]) == (1, 0)
    assert pair_multiplicity(c, 1, 1).tolist() == [[1]]


def test_crossing_on_a_shared_edge_counts_once_and_multiplicity():
    # a crosses the diagonal at (0.5, 0.5); b zigzags through that same point and crosses a again later
    a = square_curves("tx", [[(1, (0.0, 1.0)), (0, (0.5, 0.5)), (0, (1.0, 0.0))]])
    b = square_curves(
        "rx",
        [[(1, (0.1, 0.3)), (0, (0.5, 0.5)), (0, (0.9, 0.7)), (0, (0.9, 0.05))], [(1, (0.0, 0.9)), (1, (0.05, 0.95))]],
    )
    c = find_crossings(a, b, SQUARE_F)
    mult = pair_multiplicity(c, a.count, b.count)
    assert mult.tolist() == [[2, 0]]
    np.testing.assert_allclose(c.points[0], [0.5, 0.5, 0.0], atol=1e-12)
    assert c.arc_a[0] < c.arc_a[1]


def test_same_layer_pairs_once_and_exclusion():
    lines = square_curves("rx", [[(0, (0.2, 0.0)), (0, (1.0, 0.8))], [(0, (1.0, 0.0)), (1, (0.5, 0.5)), (1, (0.3, 0.7))]])
    c = find_crossings(lines, lines, SQUARE_F)
    assert c.curve_a.tolist() == [0] and c.curve_b.tolist() == [1]
    np.testing.assert_allclose(c.points[0], [0.6, 0.4, 0.0], atol=1e-12)
    # vertex distances from vertex 1, interpolated linearly: 0.4 * 1 + 0.2 * 0 + 0.4 * 1 = 0.8 at the crossing
    distance = np.linalg.norm(SQUARE_V - SQUARE_V[1], axis=1)
    assert len(drop_near(c, SQUARE_F, distance, 0.81).curve_a) == 0
    assert len(drop_near(c, SQUARE_F, distance, 0.79).curve_a) == 1


@pytest.fixture(scope="module")
def bunny_crossings():
    mesh, regions, tables, tx_field, rx_field = bunny()
    tx, _ = trace_tx_curves(TraceTxParams(), tables, regions, tx_field)
    rx, _ = trace_rx_curves(TraceRxParams(angle_deg=20.0), tables, regions, rx_field)
    out = crossings(CrossingsParams(), mesh, tx, rx, tx_field, rx_field)
    return mesh, tx, rx, out


def point_at_arc(curves: CurveSet, curve: int, arc: float) -> np.ndarray:
    pts = curves.points[curves.curve(curve)]
    cum = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))]
    return np.array([np.interp(arc, cum, pts[:, k]) for k in range(3)])


def test_bunny_tx_rx_crossings_are_on_both_curves(bunny_crossings):
    mesh, tx, rx, out = bunny_crossings
    c = out["tx_rx"]
    assert len(c.curve_a) > tx.count  # the layers interleave
    corners = mesh.vertices[mesh.faces[c.faces]]
    assert np.abs(np.einsum("kij,ki->kj", corners, c.bary) - c.points).max() < 1e-9
    for k in range(0, len(c.curve_a), max(1, len(c.curve_a) // 200)):
        assert np.linalg.norm(point_at_arc(tx, c.curve_a[k], c.arc_a[k]) - c.points[k]) < 1e-6
        assert np.linalg.norm(point_at_arc(rx, c.curve_b[k], c.arc_b[k]) - c.points[k]) < 1e-6
        assert tx.faces[tx.offsets[c.curve_a[k]] + c.seg_a[k]] == c.faces[k]
        assert rx.faces[rx.offsets[c.curve_b[k]] + c.seg_b[k]] == c.faces[k]


def test_bunny_tx_rx_crossing_counts_per_pair(bunny_crossings):
    _, tx, rx, out = bunny_crossings
    mult = pair_multiplicity(out["tx_rx"], tx.count, rx.count)
    assert mult.sum() == len(out["tx_rx"].curve_a)
    # Rx loops start and end at the base, Tx curves run from the top to the base: most pairs that
    # meet do so once; report-level property rather than a hard law of the discrete field
    meeting = mult[mult > 0]
    assert np.mean(meeting == 1) > 0.8
    # every Tx curve reaching the base crosses some Rx curve
    reached = np.flatnonzero(tx.end_reason == CurveEnd.BASE)
    assert np.all(mult[reached].sum(axis=1) > 0)


def test_bunny_same_layer_crossings(bunny_crossings):
    mesh, tx, rx, out = bunny_crossings
    assert len(out["tx_tx"].curve_a) == 0
    rr = out["rx_rx"]
    assert np.all(rr.curve_a < rr.curve_b)


def test_identical_output_for_identical_input(bunny_crossings):
    mesh, tx, rx, out = bunny_crossings
    mesh_, regions, tables, tx_field, rx_field = bunny()
    again = crossings(CrossingsParams(), mesh, tx, rx, tx_field, rx_field)
    for key in ("tx_rx", "tx_tx", "rx_rx"):
        for name in ("curve_a", "curve_b", "seg_a", "seg_b", "arc_a", "arc_b", "points", "faces", "bary"):
            assert getattr(again[key], name).tobytes() == getattr(out[key], name).tobytes()
