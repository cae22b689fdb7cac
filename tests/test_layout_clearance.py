"""Same-layer clearance on centre lines: close pairs (phase-1 conflicts) and the reported profile."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from retrotouch.nodes.data.types import CurveSet
from retrotouch.nodes.layout.clearance import (clearance_profile, close_pairs, free_end_trims, parallel_pairs, resample,
                                                trim_free_ends)


def lines(offsets_mm: list[float], length_mm: float = 50.0, rows: int = 26, face_of_row=None) -> CurveSet:
    """Straight parallel curves along x at the given y offsets (mm); row j of every curve in face
    ``face_of_row(j)`` (default 0)."""
    x = np.linspace(0.0, length_mm, rows)
    points = np.concatenate([np.stack([x, np.full(rows, y), np.zeros(rows)], axis=1) for y in offsets_mm])
    faces = np.tile([face_of_row(j) if face_of_row else 0 for j in range(rows)], len(offsets_mm)).astype(np.int64)
    n = len(offsets_mm)
    return CurveSet(layer="tx", points=points, faces=faces, bary=np.full((len(points), 3), 1 / 3),
                    offsets=np.arange(n + 1, dtype=np.int64) * rows, lengths_mm=np.full(n, length_mm),
                    end_reason=np.zeros(n, dtype=np.int8), angle=0.0)


EVERYWHERE = np.array([True])


def test_resampled_points_cover_the_length_in_short_pieces():
    points, curve, length, arc, _ = resample(lines([0.0, 5.0]), EVERYWHERE, 0.25)
    assert length.sum() == pytest.approx(100.0)
    np.testing.assert_allclose(arc, points[:, 0], atol=1e-9)  # straight lines from x = 0
    assert length.max() <= 0.25 + 1e-12 and np.array_equal(np.unique(curve), [0, 1])
    assert np.all((points[:, 0] > 0) & (points[:, 0] < 50))


@pytest.mark.parametrize("gap,close", [(1.5, True), (1.99, True), (2.3, False), (5.0, False)])
def test_close_pairs_flag_exactly_the_pairs_below_the_bound_plus_one_step(gap, close):
    pairs = close_pairs(lines([0.0, gap, gap + 10.0]), EVERYWHERE, 2.0, step_mm=0.25)
    assert (pairs.tolist() == [[0, 1]]) is close
    assert len(pairs) == int(close)


def test_close_pairs_are_kept_per_content_and_recomputed_when_it_changes():
    """Every branch of one Tx pole asks for the same Tx pairs: the second ask is the kept result."""
    first = close_pairs(lines([0.0, 1.5, 20.0]), EVERYWHERE, 2.0)
    again = close_pairs(lines([0.0, 1.5, 20.0]), EVERYWHERE, 2.0)
    assert again is first and not first.flags.writeable
    assert close_pairs(lines([0.0, 1.5, 20.0]), EVERYWHERE, 1.0).tolist() == []  # another bound
    assert close_pairs(lines([0.0, 20.0, 21.5]), EVERYWHERE, 2.0).tolist() == [[1, 2]]  # other curves


def test_only_segments_in_the_region_count():
    # curves 1.0 mm apart, but only segments 0..9 (the first 20 mm) lie in region face 1
    curves = lines([0.0, 1.0], face_of_row=lambda j: 1 if j < 10 else 0)
    region = np.array([False, True])
    assert close_pairs(curves, region, 2.0).tolist() == [[0, 1]]
    assert close_pairs(curves, np.array([True, False]), 0.5).tolist() == []
    profile = clearance_profile(curves, region, 2.0)
    assert profile["length_in_region_mm"] == pytest.approx(2 * 20.0)
    assert profile["share_closer_than_bound"] == pytest.approx(1.0)


def test_profile_measures_the_closest_centre_lines_and_the_close_length():
    profile = clearance_profile(lines([0.0, 1.2, 6.0]), EVERYWHERE, 2.0, step_mm=0.1)
    assert profile["min_centre_distance_mm"] == pytest.approx(1.2, abs=1e-9)
    assert profile["length_closer_than_bound_mm"] == pytest.approx(100.0)
    assert profile["share_closer_than_bound"] == pytest.approx(100.0 / 150.0)
    alone = clearance_profile(lines([0.0]), EVERYWHERE, 2.0)
    assert alone["min_centre_distance_mm"] is None and alone["share_closer_than_bound"] == 0.0


def fan(angles_deg: list[float], length_mm: float = 40.0, rows: int = 81) -> CurveSet:
    """Straight curves from a common start at the origin (a pole), one per angle."""
    s = np.linspace(0.0, length_mm, rows)
    a = np.radians(angles_deg)
    points = np.concatenate([np.stack([s * np.cos(t), s * np.sin(t), np.zeros(rows)], axis=1) for t in a])
    n = len(a)
    return CurveSet(layer="tx", points=points, faces=np.zeros(len(points), dtype=np.int64),
                    bary=np.full((len(points), 3), 1 / 3), offsets=np.arange(n + 1, dtype=np.int64) * rows,
                    lengths_mm=np.full(n, length_mm), end_reason=np.zeros(n, dtype=np.int8), angle=0.0)


def test_curves_from_a_common_start_are_trimmed_where_they_have_room():
    curves = fan([-10.0, 10.0])  # 2 s sin(10 deg) apart at arc s: 2 mm at s = 5.76 mm
    assert close_pairs(curves, EVERYWHERE, 2.0).tolist() == [[0, 1]]
    assert close_pairs(curves, EVERYWHERE, 2.0, free_mm=20.0).tolist() == []
    first = free_end_trims(curves, EVERYWHERE, 2.0, free_mm=20.0)
    trimmed, cut = trim_free_ends(curves, first)
    np.testing.assert_allclose(cut, first * 0.5)  # rows every 0.5 mm
    assert cut[0] == 0.0  # the first curve in spread order reaches the pole
    assert 5.76 <= cut[1] <= 5.76 + 0.25 + 0.5 + 1e-9  # conservative by one step, then one row
    np.testing.assert_allclose(trimmed.lengths_mm, 40.0 - cut)
    assert clearance_profile(trimmed, EVERYWHERE, 2.0)["min_centre_distance_mm"] >= 2.0
    assert trimmed.offsets[-1] == len(trimmed.points) == 2 * 81 - first.sum()


def test_curves_into_a_common_end_are_trimmed_there_and_keep_their_start():
    """The fan reversed: the curves meet at their ends; trimming the free end keeps every row from the
    start (its arcs and segment indices unchanged) and cuts as much as the free start does in the fan."""
    forward = fan([-10.0, 10.0])
    rows = np.diff(forward.offsets)[0]
    order = np.concatenate([np.arange(forward.offsets[c + 1] - 1, forward.offsets[c] - 1, -1) for c in range(2)])
    curves = dataclasses.replace(forward, points=forward.points[order])
    assert close_pairs(curves, EVERYWHERE, 2.0, free_mm=20.0).tolist() == [[0, 1]]  # the start is not free
    assert close_pairs(curves, EVERYWHERE, 2.0, free_mm=20.0, free_end="end").tolist() == []
    drop = free_end_trims(curves, EVERYWHERE, 2.0, free_mm=20.0, free_end="end")
    np.testing.assert_array_equal(drop, free_end_trims(forward, EVERYWHERE, 2.0, free_mm=20.0))
    trimmed, cut = trim_free_ends(curves, drop, free_end="end")
    assert drop[0] == 0 and drop[1] > 0 and np.all(cut == 0.0)
    np.testing.assert_array_equal(trimmed.points[trimmed.offsets[1]:], curves.points[rows : 2 * rows - drop[1]])
    np.testing.assert_allclose(trimmed.lengths_mm, 40.0 - drop * 0.5)
    assert clearance_profile(trimmed, EVERYWHERE, 2.0)["min_centre_distance_mm"] >= 2.0


def test_spread_order_covers_the_range_evenly():
    from retrotouch.nodes.layout.clearance import spread_order

    assert spread_order(8).tolist() == [0, 4, 2, 6, 1, 5, 3, 7]
    assert sorted(spread_order(21).tolist()) == list(range(21))


def test_a_free_start_next_to_the_middle_of_another_curve_still_conflicts():
    x = np.linspace(0.0, 50.0, 101)
    a = np.stack([x, np.zeros_like(x), np.zeros_like(x)], axis=1)  # its first 10 mm run beside b's last 10 mm
    b = np.stack([x - 40.0, np.ones_like(x), np.zeros_like(x)], axis=1)
    curves = CurveSet(layer="tx", points=np.vstack([a, b]), faces=np.zeros(202, dtype=np.int64),
                      bary=np.full((202, 3), 1 / 3), offsets=np.array([0, 101, 202]), lengths_mm=np.full(2, 50.0),
                      end_reason=np.zeros(2, dtype=np.int8), angle=0.0)
    assert close_pairs(curves, EVERYWHERE, 2.0, free_mm=20.0).tolist() == [[0, 1]]
    # b's last 10 mm lie in its far half, which is never free however long the free start
    assert close_pairs(curves, EVERYWHERE, 2.0, free_mm=60.0).tolist() == [[0, 1]]
    assert close_pairs(curves, EVERYWHERE, 2.0, free_mm=60.0, free_end="end").tolist() == [[0, 1]]
    assert close_pairs(curves, EVERYWHERE, 2.0, free_mm=20.0, free_end="end").tolist() == [[0, 1]]


def test_two_short_curves_side_by_side_conflict_whatever_the_free_length():
    """Curves shorter than the free length: only their halves at the free end are free, so two that
    run side by side all along still conflict (a free zone never reaches the wired half)."""
    curves = lines([0.0, 1.0], length_mm=10.0)
    for free_end in ("start", "end"):
        assert close_pairs(curves, EVERYWHERE, 2.0, free_mm=60.0, free_end=free_end).tolist() == [[0, 1]]


def test_a_tx_laid_along_an_rx_conflicts_and_a_crossing_does_not():
    tx = lines([0.0, 20.0])  # two Tx lines along x, 50 mm long
    along = dataclasses.replace(lines([0.4], length_mm=30.0), layer="rx")  # 30 mm along Tx 0, 0.4 mm off
    across_points = np.stack([np.full(26, 25.0), np.linspace(-5.0, 25.0, 26), np.zeros(26)], axis=1)  # crosses both at 90 deg
    steep_points = np.stack([np.linspace(20.0, 30.0, 26), np.linspace(-5.0, 25.0, 26), np.zeros(26)], axis=1)  # about 18 deg off y
    rx = CurveSet(layer="rx", points=np.vstack([along.points, across_points, steep_points]), faces=np.zeros(78, dtype=np.int64),
                  bary=np.full((78, 3), 1 / 3), offsets=np.array([0, 26, 52, 78]), lengths_mm=np.array([30.0, 30.0, 31.6]),
                  end_reason=np.zeros(3, dtype=np.int8), angle=0.0)
    assert parallel_pairs(tx, rx, EVERYWHERE, 1.0, 10.0).tolist() == [[0, 0]]
    # the same Rx only 8 mm long along Tx 0 stays below a 10 mm run
    short = dataclasses.replace(lines([0.4], length_mm=8.0), layer="rx")
    assert len(parallel_pairs(tx, short, EVERYWHERE, 1.0, 10.0)) == 0


def test_close_pairs_match_every_point_pair_on_wandering_curves():
    """Random walks that meet, cross, leave the region and come back: the pairs from runs of points
    are those of comparing every resampled point pair (the rule's definition)."""
    rng = np.random.default_rng(3)
    n, rows = 12, 60
    steps = rng.normal(size=(n, rows, 3)) * [0.6, 0.6, 0.1]
    points = (np.cumsum(steps, axis=1) + rng.uniform(-6, 6, size=(n, 1, 3))).reshape(-1, 3)
    faces = rng.integers(0, 2, size=n * rows)  # face 1 is outside the region: curves leave it and come back
    arcs = np.linalg.norm(np.diff(points.reshape(n, rows, 3), axis=1), axis=2).sum(axis=1)
    curves = CurveSet(layer="rx", points=points, faces=faces, bary=np.full((len(points), 3), 1 / 3),
                      offsets=np.arange(n + 1, dtype=np.int64) * rows, lengths_mm=arcs,
                      end_reason=np.zeros(n, dtype=np.int8), angle=0.0)
    region = np.array([True, False])
    for free_mm, free_end in ((0.0, "start"), (15.0, "start"), (15.0, "end")):
        got = close_pairs(curves, region, 2.0, free_mm, free_end)
        sampled, curve, _, arc, _ = resample(curves, region, 0.25)
        from_end = arc if free_end == "start" else curves.lengths_mm[curve] - arc
        free = from_end < np.minimum(free_mm, 0.5 * curves.lengths_mm[curve])
        d2 = ((sampled[:, None, :] - sampled[None, :, :]) ** 2).sum(axis=2)
        hit = (d2 <= 2.25**2) & (curve[:, None] < curve[None, :]) & ~(free[:, None] & free[None, :])
        expected = np.unique(np.stack([curve[np.nonzero(hit)[0]], curve[np.nonzero(hit)[1]]], axis=1), axis=0)
        assert len(expected) > 3 and got.tolist() == expected.tolist()
