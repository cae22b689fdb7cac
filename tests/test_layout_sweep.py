"""layout.pick_best ranking and the per-angle table, on hand-made branch results."""
from __future__ import annotations

import dataclasses

import pytest

from types import SimpleNamespace

from retrotouch.nodes.layout.pick import PickParams, angle_table, best_branch, best_note, pick_best
from retrotouch.nodes.layout.screen import BranchBound, ScreenParams, prescreen, screen_branches
from retrotouch.nodes.layout.sweep import AngleLayout


def branch(angle, radius, mean, cv, secondary=True, feasible=True, cells=50):
    metrics = {"coverage_radius_mm": radius, "power_mean_distance_mm": mean, "voronoi_cv": cv, "secondary": secondary,
               "cells": cells,
               "pads": 10, "tx_channels": 21, "rx_channels": 12, "relaxations": [],
               "phase1": {"stages": [{"status": "OPTIMAL", "objective": radius, "gap": 0.0, "deterministic_time": 0.5}],
                          "resolution_mm": 0.5}}
    return AngleLayout("dipole", angle, feasible, "ok" if feasible else "no pads", None, metrics)


def test_radius_ties_within_tolerance_fall_to_the_mean_then_the_cv():
    candidates = [branch(-10, 30.0, 8.0, 0.5), branch(0, 30.6, 7.0, 0.6), branch(10, 33.0, 5.0, 0.1)]
    assert best_branch(candidates, 1.0) == 1  # 30.6 ties with 30.0, lower mean wins; 33.0 is out
    assert best_branch(candidates, 0.0) == 0
    off = [branch(-10, 30.0, 8.0, 0.5, False), branch(0, 30.6, 7.0, 0.4, False)]
    assert best_branch(off, 1.0) == 1  # secondary off: the Voronoi CV decides among ties


def test_power_means_within_the_tolerance_fall_to_the_most_cells():
    candidates = [branch(-10, 30.0, 8.0, 0.3, cells=60), branch(0, 30.4, 8.3, 0.6, cells=130), branch(10, 30.2, 9.0, 0.2, cells=200)]
    assert best_branch(candidates, 1.0) == 0  # no mean tolerance: the lowest power mean
    assert best_branch(candidates, 1.0, 0.05) == 1  # 8.3 ties with 8.0, more cells; 9.0 is 12.5 % worse: out
    assert best_branch(candidates, 1.0, 0.2) == 2
    assert best_branch(candidates, 0.1, 0.2) == 0  # the radius comes first


def test_infeasible_branches_are_skipped_and_listed():
    candidates = [branch(-10, 10.0, 1.0, 0.1, feasible=False), branch(0, 30.0, 8.0, 0.5)]
    assert best_branch(candidates, 1.0) == 1
    rows = angle_table(candidates)
    assert [r["angle_deg"] for r in rows] == [-10, 0] and [r["feasible"] for r in rows] == [False, True]
    out = pick_best(PickParams(print_table=False), candidates)
    assert out["metrics"]["chosen_angle_deg"] == 0 and len(out["metrics"]["angles"]) == 2


def test_the_chosen_branch_brings_the_regions_of_its_tx_pole():
    """Branches around two Tx poles compete in one list; the chosen one's regions go to the sinks."""
    far, centre = SimpleNamespace(tx_pole="far"), SimpleNamespace(tx_pole="centre")
    candidates = [dataclasses.replace(branch(0, 40.0, 9.0, 0.5), regions=far),
                  dataclasses.replace(branch(0, 25.0, 7.0, 0.6), regions=centre)]
    out = pick_best(PickParams(print_table=False), candidates)
    assert out["regions"] is centre and out["layout"] is None
    assert [r["tx_pole"] for r in out["metrics"]["angles"]] == ["far", "centre"]


def test_the_run_note_names_the_chosen_branch_its_coverage_and_its_largest_uncovered_spot():
    chosen = branch(20, 15.9, 8.0, 0.4, cells=197)
    chosen.metrics.update(rx_family="helices_per_line", channel_pairs=252, coverage_radius_vertices_mm=18.47,
                          uncovered_threshold_mm=10.0, uncovered_share=0.054,
                          uncovered_spots=[{"area_mm2": 812.4, "max_distance_mm": 18.47, "point": [-30.7, 32.9, -24.0]},
                                           {"area_mm2": 151.0, "max_distance_mm": 13.9, "point": [42.9, -28.2, 2.4]}])
    out = pick_best(PickParams(print_table=False), [dataclasses.replace(chosen, regions=SimpleNamespace(tx_pole="far"))])
    assert best_note(out) == ("chosen helices_per_line at +20 deg around the far Tx pole: 197 of 252 channel pairs as cells, "
                              "coverage radius 15.9 mm (18.5 over every touchable vertex); 5.4% of the touchable sensing area is farther "
                              "than 10 mm from every cell, the largest spot 812 mm2 up to 18.5 mm at (-31, 33, -24) mm")
    out["metrics"].update(uncovered_share=0.0, uncovered_spots=[])
    assert best_note(out).endswith("0.0% of the touchable sensing area is farther than 10 mm from every cell")


def started(radius, lower_bound):
    stage = None if radius is None else SimpleNamespace(radius_mm=radius, lower_bound_mm=lower_bound)
    return SimpleNamespace(stage=stage)


def test_the_screen_finishes_what_can_still_tie_the_best_stage1_radius_and_at_least_two():
    branches = [started(20.0, 19.5), started(21.0, 21.4), started(23.5, 22.6), started(30.0, 22.0), started(None, None)]
    cut = screen_branches(ScreenParams(radius_tolerance_mm=1.0, margin_mm=1.0, keep_at_least=1), branches)
    assert cut.threshold_mm == pytest.approx(22.0)  # 20 + 1 + 1
    assert [cut.keeps(b) for b in branches] == [True, True, False, True, True]  # no stage: finish reports why
    assert [cut.needs_proof(b) for b in branches] == [False, False, True, True, False]  # 30.0 is beyond 22
    assert cut.summary.startswith("3 of 4 solved branches kept")
    tight = screen_branches(ScreenParams(radius_tolerance_mm=0.0, margin_mm=0.0, keep_at_least=2), branches)
    assert [tight.keeps(b) for b in branches] == [True, True, False, False, True]  # 21.0: the second radius
    assert not tight.needs_proof(branches[1])  # kept in any case: no proof can drop it
    every = screen_branches(ScreenParams(margin_mm=None), branches)
    assert all(every.keeps(b) for b in branches) and not any(every.needs_proof(b) for b in branches)


def bounded(start, lower_bound):
    return BranchBound({}, "rings", 0.0, {}, None, start, lower_bound, "ok" if start is not None else "no crossings")


def test_the_prescreen_solves_what_can_still_tie_the_best_start_and_at_least_two():
    bounds = [bounded(20.0, 12.0), bounded(25.0, 21.5), bounded(23.0, 22.5), bounded(40.0, 39.5), bounded(None, None)]
    cut = prescreen(ScreenParams(radius_tolerance_mm=1.0, margin_mm=1.0, keep_at_least=2), bounds, [])
    assert cut.threshold_mm == pytest.approx(22.0) and cut.sure_mm == 23.0  # 20 + 1 + 1; the second start
    assert [cut.keeps(b) for b in bounds] == [True, True, True, False, True]  # 23.0 kept as a best start; no bound: coverage says why
    assert cut.summary.startswith("3 of 4 branches solved")
    assert ScreenParams.model_validate(cut.settings).keep_at_least == 2  # layout.screen applies the same
    every = prescreen(ScreenParams(margin_mm=None), bounds, [])
    assert all(every.keeps(b) for b in bounds) and every.summary == "all 5 branches solved"


def test_a_second_poles_branches_are_screened_against_the_first_poles():
    first = [bounded(20.0, 12.0), bounded(21.0, 15.0)]
    second = [bounded(23.5, 21.0), bounded(30.0, 22.5), bounded(35.0, 35.0)]
    rule = ScreenParams(radius_tolerance_mm=1.0, margin_mm=1.0, keep_at_least=2)
    alone, against = prescreen(rule, second, []), prescreen(rule, second, first)
    assert [alone.keeps(b) for b in second] == [True, True, False]  # its own best start 23.5 + 2; the 2 best in any case
    assert against.threshold_mm == pytest.approx(22.0) and against.sure_mm == 21.0  # the first pole's starts
    assert [against.keeps(b) for b in second] == [True, False, False]  # 22.5 can no longer tie 20 within 1 + 1 mm
    assert against.summary.startswith("1 of 3 branches solved") and "an earlier Tx pole's" in against.summary
    assert "earlier" not in alone.summary
    assert not prescreen(rule, [bounded(40.0, 30.0)], first).keeps(bounded(40.0, 30.0))  # alone it would be solved
    staged = [started(24.0, 21.5), started(26.0, 23.0)]
    cut = screen_branches(rule, staged, [started(20.0, 19.0), started(20.5, 19.5)])
    assert [cut.keeps(b) for b in staged] == [True, False] and cut.summary.startswith("1 of 2 solved branches kept")
    assert [screen_branches(rule, staged).keeps(b) for b in staged] == [True, True]  # alone: its 2 best in any case


def test_a_branch_whose_start_an_earlier_poles_branch_had_is_not_solved_again():
    """Two Tx poles on one vertex give the same branches: the second pole's are not solved again, and
    the rule takes the others over the rest only."""
    import numpy as np

    def started_from(start_radius, lower_bound, tx):
        return BranchBound({"n_drive": 21}, "helices", 0.0, {"candidates": {"tx": 90}},
                           (np.array(tx), np.array([0, 3]), {"radius_mm": start_radius}), start_radius, lower_bound, "ok")

    first = [started_from(20.0, 12.0, [1, 2]), started_from(21.0, 15.0, [4, 5])]
    twin, other = started_from(20.0, 12.0, [1, 2]), started_from(20.0, 12.0, [1, 7])  # other: one curve differs
    rule = ScreenParams(radius_tolerance_mm=1.0, margin_mm=1.0, keep_at_least=2)
    cut = prescreen(rule, [twin, other], first)
    assert cut.repeated(twin) and not cut.keeps(twin)
    assert not cut.repeated(other) and cut.keeps(other)
    assert cut.summary.startswith("1 of 1 branches solved") and "1 the same as an earlier Tx pole's" in cut.summary
    assert not prescreen(rule, [twin, other], []).repeated(twin)  # the first pole solves its own
    assert prescreen(rule, [twin], first).summary == "none solved: 1 branches the same as an earlier Tx pole's"


def test_a_screened_branch_that_could_have_tied_the_chosen_one_is_warned_about(caplog):
    shut = AngleLayout("rings", 90.0, False, "screened out", None,
                       {"screened": True, "coverage_radius_lower_bound_mm": 30.5, "phase1": {"stages": []}})
    far = AngleLayout("rings", 180.0, False, "screened out", None,
                      {"screened": True, "coverage_radius_lower_bound_mm": 31.5, "phase1": {"stages": []}})
    with caplog.at_level("WARNING"):
        out = pick_best(PickParams(print_table=False), [branch(0, 30.0, 8.0, 0.5), far])
    assert not caplog.records and out["metrics"]["angles"][1]["note"] == "screened out"
    with caplog.at_level("WARNING"):
        pick_best(PickParams(print_table=False), [branch(0, 30.0, 8.0, 0.5), shut, far])
    assert len(caplog.records) == 1 and "1 screened branch(es) could have tied" in caplog.text
    caplog.clear()
    twin = AngleLayout("dipole", 0.0, False, "not solved: an earlier Tx pole's branch had its phase-1 start", None,
                       {"screened": True, "repeated": True, "phase1": {"stages": []}})
    with caplog.at_level("WARNING"):
        out = pick_best(PickParams(print_table=False), [branch(0, 30.0, 8.0, 0.5), twin])
    row = out["metrics"]["angles"][1]
    assert not caplog.records and row["status"] == "REPEATED" and row["note"] == twin.message and row["screened"]


def test_gap_is_unknown_when_a_stage_has_no_incumbent():
    c = branch(0, 30.0, 8.0, 0.5)
    c.metrics["phase1"]["stages"].append({"status": "UNKNOWN", "gap": None, "deterministic_time": 1.0})
    assert angle_table([c])[0]["gap"] is None
    assert angle_table([branch(0, 30.0, 8.0, 0.5)])[0]["gap"] == pytest.approx(0.0)


def test_failed_and_far_worse_branches_carry_their_reason():
    candidates = [branch(-10, 10.0, 1.0, 0.1, feasible=False), branch(0, 14.0, 8.0, 0.5), branch(10, 15.0, 8.0, 0.5),
                  branch(20, 45.0, 9.0, 0.5)]
    notes = [r["note"] for r in angle_table(candidates, outlier_factor=1.5)]
    assert notes[0] == "failed: no pads"
    assert notes[1] == notes[2] == ""
    assert notes[3].startswith("far worse: coverage radius 45.0 mm > 1.5 x median 15.0 mm")


def test_more_channels_than_the_muca_board_has_are_refused_before_anything_runs():
    from pydantic import ValidationError

    from retrotouch.nodes.data.board import NUM_RX, NUM_TX
    from retrotouch.nodes.layout.sweep import OptimizeParams

    assert OptimizeParams(n_drive=NUM_TX, n_sense=NUM_RX).n_drive == 21
    for wrong in ({"n_drive": NUM_TX + 1}, {"n_sense": NUM_RX + 1}):
        with pytest.raises(ValidationError, match="less than or equal to"):
            OptimizeParams(**wrong)
