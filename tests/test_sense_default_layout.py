"""Sensing on the REAL default layout (``retrotouch run pipelines/retrofit.yaml``: on the bunny
helices around the Tx pole, about 190 crossings, dense near the pole and sparser by the base), end
to end through the pseudo-terminal: the issue's localization bar, no false touches, and scripted
gestures recognised."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from retrotouch.nodes.sensing.gestures import GestureRecognizer
from retrotouch.nodes.data.sensing_map import load_sensing_map
from retrotouch.nodes.sensing.processing import ProcessingParams, TouchProcessor
from retrotouch.nodes.sensing.pty_board import frames_through_pty
from retrotouch.nodes.sensing.scripts import DEMO_SCRIPT, ScriptBuilder
from retrotouch.nodes.sensing.virtual_board import BoardParams, VirtualBoard
from retrotouch.nodes.sensing.evaluation import EvalParams, evaluate_simulator

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def layout(default_run):
    return default_run / "out" / "sensing_map.json"


@pytest.fixture(scope="module")
def field_lines_layout(default_run):
    """The default pipeline's layout without Tx lanes (``-S tx_lanes.offsets_mm=[]``), in the same folder
    and cache."""
    result = subprocess.run([sys.executable, "-m", "retrotouch.nodes", "run", str(REPO / "pipelines" / "retrofit.yaml"),
                             "--out", "out_field_lines", "-S", "tx_lanes.offsets_mm=[]"], cwd=default_run,
                            capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr
    return default_run / "out_field_lines" / "sensing_map.json"


def test_localization_on_the_default_layout_through_the_pty_at_snr_60(layout):
    """15 locations surrounded by crossings x 10 presses (sense_eval.evaluation_locations)."""
    report = evaluate_simulator(layout, BoardParams(snr=60), EvalParams(location_rule="surrounded"))
    summary = report.summary()
    assert summary["presses"] == 150 and summary["locations"] == 15
    assert summary["missed_presses"] == 0 and summary["false_touches_at_rest"] == 0
    assert summary["localization_error_mm_mean"] < 1.5
    # measured 1.72 mm on the dipole layout (pitch 7.4 mm), 2.63 mm on the rings (pitch 5.25 mm)
    assert summary["localization_error_mm_max"] < 3.0
    assert summary["locations_surrounded"] == 15 and 0.0 < summary["surrounded_fraction"] <= 1.0
    assert summary["crossings_seen_min"] >= 3  # surrounded: at least three crossings see every press


def test_a_board_whose_coupling_is_not_gaussian_is_localized_once_learned(layout):
    """Disc coupling (flat top, power-law tail; BoardParams.coupling_model), board seeds 0-3: with
    the coupling profile learned the protocol stays within the issue's bar on every seed, and
    learning costs no accuracy on average. What it gains depends on the layout: held to its Gaussian
    start, the mean error was 1.43-1.91 times the learned one on the previous default layout
    (helices climbing as the median Tx line does), 0.94-1.45 times (1.21 pooled) on the per-line
    helices' layout."""
    learned, held = [], []
    for seed in range(4):
        board = BoardParams(snr=60, coupling_model="disc", seed=seed)
        surrounded = EvalParams(location_rule="surrounded", seed=seed)
        report = evaluate_simulator(layout, board, surrounded, through_pty=False).summary()
        assert report["missed_presses"] == 0 and report["false_touches_at_rest"] == 0
        assert report["localization_error_mm_mean"] < 1.5
        learned.append(report["localization_error_mm_mean"])
        held.append(evaluate_simulator(layout, board, surrounded, ProcessingParams(adapt_coupling=False),
                                       through_pty=False).summary()["localization_error_mm_mean"])
    assert np.mean(held) > np.mean(learned)


def test_locations_in_gaps_of_the_default_layout_are_scored_too(layout):
    """Rule 'near' also touches gaps between crossings (reported, not dropped; on the dipole layout
    some are seen by only one or two crossings, on the rings by three or more): the fit's priors keep
    the mean within the bar; a finger seen by two crossings can land on the mirror side of the line
    through them, so the worst press is bounded by 1.5 pitch only (fed directly, the pty path is
    covered above)."""
    summary = evaluate_simulator(layout, BoardParams(snr=60, seed=5), EvalParams(location_rule="near", seed=5),
                                 through_pty=False).summary()
    assert summary["missed_presses"] == 0 and summary["false_touches_at_rest"] == 0
    assert summary["surrounded_fraction"] < 0.9 and summary["locations_surrounded"] < 15
    assert summary["localization_error_mm_mean"] < 1.5
    assert summary["localization_error_mm_max"] < 1.5 * load_sensing_map(layout).pitch_mm()


def test_scripted_gestures_on_the_default_layout_through_the_pty(layout):
    """Tap, double tap, long press, a 40 mm swipe, a 45 -> 20 mm pinch and its spread, placed where
    they fit on the layout's sensed region."""
    sensing_map = load_sensing_map(layout)
    board = VirtualBoard(sensing_map, BoardParams(seed=3))
    script = ScriptBuilder(sensing_map, seed=3).build(DEMO_SCRIPT)
    processor = TouchProcessor(sensing_map)
    recognizer = GestureRecognizer()
    events = []
    for frame in frames_through_pty(board, script, fast=True):
        result = processor.process(frame.values, frame.t)
        events.extend(recognizer.feed(result))
    assert [e["type"] for e in events] == [
        "tap", "tap", "tap", "double_tap", "long_press", "swipe", "pinch", "spread"]
    labels = {label["gesture"]: label for _, label in script.labels}
    by_type = {e["type"]: e for e in reversed(events)}  # the first of each type (the double tap's taps come later)
    # Taps land anywhere near a crossing, gaps included, and are seen in one or two frames.
    half_pitch = sensing_map.pitch_mm() / 2
    assert np.linalg.norm(np.array(by_type["tap"]["point"]) - labels["tap"]["point"]) < half_pitch
    assert np.linalg.norm(np.array(by_type["double_tap"]["point"]) - labels["double_tap"]["point"]) < half_pitch
    assert by_type["swipe"]["distance_mm"] > 25.0  # 40 mm scripted, seen from its first to its last frame
    assert by_type["pinch"]["scale"] < 0.75 and by_type["spread"]["scale"] > 1.35


def test_a_touch_few_crossings_see_is_not_fitted_at_its_mirror_place(field_lines_layout, monkeypatch, tmp_path):
    """Calibrated (so the finger's amplitude is known), on the mismatched board, at the layout's holes
    (15 points of the touchable sensing region 12-18 mm from every crossing, where two or three
    crossings see a press): such a press has a mirror place across the line through them, and a fit
    from the peak crossing alone slides into it. Starting also around the peak, at the distance the
    amplitude implies, gains on the mean and the worst press (board seed 3: 1.83 against 2.35 mm mean,
    10.4 against 13.6 mm max; seeds 0 and 1: 2.53 / 3.34 and 2.28 / 2.44 mm mean). On the layout without
    Tx lanes, whose holes (439 faces) these figures were measured on: the lanes' layout has 62 such faces,
    in one place (the next test)."""
    from retrotouch.nodes.sensing import coupling_fit

    summary = _presses_at_holes(field_lines_layout, 3, tmp_path)
    around = summary()
    monkeypatch.setattr(coupling_fit, "RING_STARTS_MAX_CROSSINGS", 0)
    from_peak = summary()
    assert around["missed_presses"] == 0 and around["presses_without_one_touch_down"] == 0
    assert around["localization_error_mm_mean"] < 0.9 * from_peak["localization_error_mm_mean"]
    assert around["localization_error_mm_max"] <= from_peak["localization_error_mm_max"]


def test_a_finger_in_a_hole_between_crossings_far_apart_is_one_touch(layout, tmp_path):
    """At the default layout's hole (as in the previous test), calibrated, on the mismatched board: the
    finger raises a peak on two crossings about 26 mm apart, whose first fits each put a weak finger
    beside their peak, and the joint fit from between them slides to one side. One finger held
    between the first fits explains both, so every press is one touch-down (board seed 3 split 5 of
    the 150 presses with 6 ghost touches, 5.75 mm mean error; now 3.59; the other seeds 0-9 split none
    before or after)."""
    report = _presses_at_holes(layout, 3, tmp_path)()
    assert report["missed_presses"] == 0 and report["presses_without_one_touch_down"] == 0
    assert report["ghost_touches"] == 0 and report["localization_error_mm_mean"] < 5.0


def _presses_at_holes(layout: Path, seed: int, tmp_path: Path):
    """The summary, as a function, of 15 x 10 presses spread over the faces 12-18 mm from every
    crossing, calibrated, on the mismatched board with ``seed``."""
    from retrotouch.nodes.geometry.surface import farthest_point_sampling
    from retrotouch.nodes.geometry.triangles import corners
    from retrotouch.nodes.sensing.evaluation import calibrate_simulator
    from retrotouch.nodes.sensing.virtual_board import REALISTIC_BOARD

    sensing_map = load_sensing_map(layout)
    centroids = corners(sensing_map.vertices, sensing_map.faces).mean(axis=1)[sensing_map.sensing_faces]
    nearest = np.min(np.linalg.norm(centroids[:, None] - sensing_map.cell_points[None], axis=2), axis=1)
    holes = centroids[(nearest > 12.0) & (nearest < 18.0)]
    if len(holes) == 0:
        pytest.skip(f"{layout} has no face 12-18 mm from every crossing")
    locations = tmp_path / f"holes_{layout.parent.name}.json"
    locations.write_text(json.dumps(holes[farthest_point_sampling(holes, 15, 0)].tolist()))
    board = REALISTIC_BOARD.model_copy(update={"seed": seed})
    calibration, _ = calibrate_simulator(sensing_map, board, seed=seed)
    return lambda: evaluate_simulator(layout, board, EvalParams(seed=seed), calibration=calibration,
                                      through_pty=False, locations=locations).summary()
