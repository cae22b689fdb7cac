"""Phase 1 with the limbs' curves among the candidates (``curves.trace_limbs``): a pair move reaches a
crossing of two curves neither of which is selected, and curves that do not lower the coverage radius
leave the branch's selection as it is without them."""
from __future__ import annotations

import dataclasses

import numpy as np

from retrotouch.nodes.layout.heuristic import heuristic_selection, local_search
from retrotouch.nodes.layout.problem import SelectionProblem, evaluate_selection
from retrotouch.nodes.layout.selection import select_curves

LIMB_TIP = (150.0, 50.0)


def body_and_limb(limb_crossing: tuple[float, float]) -> SelectionProblem:
    """A body of 6 Tx x 4 Rx lines crossing on a grid over a 100 mm square (11 x 11 samples, Euclidean
    distances) and a limb: one more Tx (id 6) and Rx (id 4) that cross each other once, at
    ``limb_crossing`` (mm), and nothing else; one more sample at the limb's tip, ``LIMB_TIP``."""
    xs, ys = np.linspace(10.0, 90.0, 6), np.linspace(10.0, 90.0, 4)
    tx, rx = np.meshgrid(np.arange(6), np.arange(4), indexing="ij")
    points = np.vstack([np.stack([xs[tx.ravel()], ys[rx.ravel()]], axis=1), limb_crossing])
    grid = np.stack(np.meshgrid(np.linspace(0, 100, 11), np.linspace(0, 100, 11)), axis=-1).reshape(-1, 2)
    samples = np.vstack([grid, LIMB_TIP])
    none = np.empty((0, 2), dtype=np.int64)
    return SelectionProblem(np.ones(7, bool), np.ones(5, bool), np.r_[tx.ravel(), 6], np.r_[rx.ravel(), 4],
                            np.arange(25), np.linalg.norm(samples[:, None] - points[None], axis=2), none, none, none,
                            limb_curves=(np.arange(7) == 6, np.arange(5) == 4))


def test_a_pair_move_brings_in_both_curves_of_a_limb():
    problem = body_and_limb((145.0, 50.0))
    body = (np.arange(6), np.arange(4))
    swapped_tx, swapped_rx, _ = local_search(problem, *body, 6, 4, True, 0.5)
    assert 6 not in swapped_tx and 4 not in swapped_rx  # alone, neither limb curve adds a crossing
    assert evaluate_selection(problem, swapped_tx, swapped_rx)[1].max() > 60.0
    tx, rx, report = heuristic_selection(problem, 6, 4, True, 0.5)
    assert 6 in tx and 4 in rx and report["local_search"]["pair_moves"] >= 1
    nearest = evaluate_selection(problem, tx, rx)[1]
    assert nearest[-1] <= 5.0 + 1e-9 and nearest.max() < 40.0  # the tip covered, the body still within 40 mm


def test_limb_curves_are_kept_where_they_lower_the_radius():
    problem = body_and_limb((145.0, 50.0))
    result = select_curves(problem, 6, 4, time_limit_s=1.0)
    assert 6 in result.tx and 4 in result.rx and result.coverage_radius_mm < 40.0
    assert "limbs" not in result.report


def test_limb_curves_that_do_not_lower_the_radius_leave_the_selection_as_without_them():
    problem = body_and_limb((50.0, 50.0))  # the limb's crossing lies on the body: the tip stays 61 mm away
    without = dataclasses.replace(problem, tx_usable=np.arange(7) < 6, rx_usable=np.arange(5) < 4, limb_curves=None)
    result, reference = select_curves(problem, 6, 4, time_limit_s=1.0), select_curves(without, 6, 4, time_limit_s=1.0)
    assert result.report["limbs"]["kept"] is False
    assert np.array_equal(result.tx, reference.tx) and np.array_equal(result.rx, reference.rx)
    assert np.array_equal(np.sort(result.active), np.sort(reference.active))
    assert result.coverage_radius_mm == reference.coverage_radius_mm > 60.0


def test_a_pair_move_never_brings_in_a_pair_laid_along_each_other():
    problem = dataclasses.replace(body_and_limb((145.0, 50.0)), multi_pairs=np.array([[6, 4]]))  # one crossing, but C2
    tx, rx, _ = heuristic_selection(problem, 6, 4, True, 0.5)
    assert not (6 in tx and 4 in rx)
    result = select_curves(problem, 6, 4, time_limit_s=1.0)
    assert not (6 in result.tx and 4 in result.rx) and result.report["stages"][0]["status"] == "OPTIMAL"
