"""Phase 2 (pad placement) and the relaxation ladder."""
from __future__ import annotations

import numpy as np
import pytest

from retrotouch.nodes.layout.sweep import OptimizeParams, _pads_with_ladder, d_min_for
from retrotouch.nodes.layout.pads import place_pads, sparseness


def sphere_points(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(n, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    return p, 50.0 * np.arccos(np.clip(p @ p.T, -1, 1))  # exact geodesics on a 50 mm sphere


def test_pads_are_a_maximal_set_at_least_d_min_apart():
    _, D = sphere_points(120, 0)
    result = place_pads(D, np.arange(120) % 7, np.arange(120) % 5, d_min_mm=15.0)
    chosen = np.flatnonzero(result.pad)
    assert result.feasible and result.report["status"] == "OPTIMAL"
    sub = D[np.ix_(chosen, chosen)]
    assert sub[np.triu_indices(len(chosen), 1)].min() >= 15.0
    for k in np.flatnonzero(~result.pad):  # maximal: every skipped crossing is too close to a pad
        assert D[k, chosen].min() < 15.0
    assert result.report["pads"] == len(chosen) < 120


def test_every_curve_carries_the_required_pads():
    _, D = sphere_points(80, 1)
    tx, rx = np.arange(80) % 8, np.arange(80) // 8
    result = place_pads(D, tx, rx, d_min_mm=10.0, min_pads_per_curve=1)
    assert result.feasible
    assert set(tx[result.pad]) == set(tx) and set(rx[result.pad]) == set(rx)


def two_close_crossings(gap_mm: float):
    """Tx0 x Rx0 and Tx1 x Rx1, each the only crossing of its curves, ``gap_mm`` apart."""
    D = np.array([[0.0, gap_mm], [gap_mm, 0.0]])
    return D, np.array([0, 1]), np.array([0, 1])


def test_ladder_shrinks_pads_when_curves_cannot_carry_one():
    D, tx, rx = two_close_crossings(7.0)  # d_min 8 mm (radius 2) fails, 6 mm (radius 1.5) works
    params = OptimizeParams()
    result, keep, radius, steps = _pads_with_ladder(params, D, tx, rx)
    assert result.feasible and keep.all() and result.pad.all()
    assert radius == 1.5 and d_min_for(params, radius) == 6.0
    assert [s["step"] for s in steps] == ["smaller_pads"]
    assert "pad radius 2 mm (d_min 8 mm)" in steps[0]["failed"]


def test_ladder_drops_curves_when_smaller_pads_do_not_help():
    D, tx, rx = two_close_crossings(2.0)  # even radius 1 mm (d_min 4 mm) fails
    result, keep, radius, steps = _pads_with_ladder(OptimizeParams(), D, tx, rx)
    assert [s["step"] for s in steps] == ["smaller_pads", "smaller_pads", "fewer_curves"]
    assert result.feasible and keep.sum() == 1 and result.pad.sum() == 1
    assert len(steps[-1]["dropped_tx"]) == 1 and len(steps[-1]["dropped_rx"]) == 1
    assert radius == 1.0


def test_explicit_d_min_scales_with_the_pad_radius():
    params = OptimizeParams(d_min_mm=10.0)
    assert d_min_for(params, 2.0) == pytest.approx(10.0)
    assert d_min_for(params, 1.0) == pytest.approx(5.0)


def line_distances(positions: list[float]) -> np.ndarray:
    p = np.asarray(positions, dtype=float)
    return np.abs(p[:, None] - p[None, :])


def test_tie_break_keeps_the_crossing_in_the_sparser_neighbourhood():
    D = line_distances([0.0, 5.0, 20.0, 100.0])  # {0, 20, 100} and {5, 20, 100} are both maximum
    ids = np.arange(4)
    result = place_pads(D, ids, ids, d_min_mm=8.0, tie_break=sparseness(D))
    assert result.pad.tolist() == [True, False, True, True]


def test_tie_break_never_costs_a_pad():
    D = line_distances([0.0, 6.0, 12.0])  # the middle one is sparse-looking but conflicts with both
    ids = np.arange(3)
    result = place_pads(D, ids, ids, d_min_mm=7.0, tie_break=np.array([0.0, 1000.0, 0.0]))
    assert result.pad.tolist() == [True, False, True] and result.report["objective"] == 2
