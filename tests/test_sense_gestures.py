"""Gestures: scripted sequences through the pseudo-terminal, and the recognizer's thresholds."""
from __future__ import annotations

import numpy as np
import pytest

from retrotouch.nodes.sensing.gestures import GestureParams, GestureRecognizer
from retrotouch.nodes.data.sensing_map import load_sensing_map
from retrotouch.nodes.sensing.processing import FrameResult, Touch, TouchProcessor
from retrotouch.nodes.sensing.pty_board import frames_through_pty
from retrotouch.nodes.sensing.scripts import DEMO_SCRIPT, ScriptBuilder
from retrotouch.nodes.sensing.synthetic_map import synthetic_bunny_map
from retrotouch.nodes.sensing.virtual_board import BoardParams, VirtualBoard


@pytest.fixture(scope="module")
def bunny_map(tmp_path_factory):
    return load_sensing_map(synthetic_bunny_map(tmp_path_factory.mktemp("bunny")))


@pytest.mark.parametrize("seed", [0, 1])
def test_scripted_gestures_are_recognised_through_the_pty(bunny_map, seed):
    board = VirtualBoard(bunny_map, BoardParams(seed=seed))
    script = ScriptBuilder(bunny_map, seed=seed).build(DEMO_SCRIPT)
    processor = TouchProcessor(bunny_map)
    recognizer = GestureRecognizer()
    events = []
    for frame in frames_through_pty(board, script, fast=True, garbage_every=7):
        events.extend(recognizer.feed(processor.process(frame.values, frame.t)))
    assert [e["type"] for e in events] == [
        "tap", "tap", "tap", "double_tap", "long_press", "swipe", "pinch", "spread"]
    by_type = {e["type"]: e for e in events}
    labels = {label["gesture"]: (t, label) for t, label in script.labels}
    (swipe_stroke,) = [s for s in script.strokes if len(s.path) > 1 and s.t0 == labels["swipe"][0]]
    for end in ("from", "to"):  # both ends lie on the scripted path (frames sample it every 100 ms)
        assert np.min(np.linalg.norm(swipe_stroke.path - by_type["swipe"][end], axis=1)) < 2.0
    assert by_type["swipe"]["distance_mm"] > 25.0  # 40 mm scripted, seen from its first to its last frame
    # 600 ms after the first frame that saw the finger, which comes up to one frame after it landed.
    assert 0.6 - 1e-6 <= by_type["long_press"]["t"] - labels["long_press"][0] <= 0.8 + 1e-6
    assert by_type["pinch"]["scale"] < 0.75 and by_type["spread"]["scale"] > 1.35
    first_tap = next(e for e in events if e["type"] == "tap")
    assert np.linalg.norm(np.array(first_tap["point"]) - labels["tap"][1]["point"]) < 2.0
    assert np.linalg.norm(np.array(by_type["double_tap"]["point"]) - labels["double_tap"][1]["point"]) < 2.0


def frames_of(tracks: dict[int, list[tuple[float, tuple[float, float, float]]]], rate: float = 10.0):
    """FrameResults from per-id lists of (t, point); a touch exists at the listed times only."""
    times = sorted({t for samples in tracks.values() for t, _ in samples})
    times = np.arange(times[0], times[-1] + 2 / rate, 1 / rate)
    results = []
    for t in times:
        touches = tuple(
            Touch(i, np.array(p, dtype=float), 0, np.array([1.0, 0, 0]), np.array([0, 0, 1.0]), 200.0, 50.0, 0)
            for i, samples in tracks.items() for ts, p in samples if abs(ts - t) < 1e-6)
        results.append(FrameResult(float(t), True, touches, (), np.zeros(1), np.zeros(1, dtype=bool)))
    return results


def run(tracks, params=GestureParams()):
    recognizer = GestureRecognizer(params)
    return [e for r in frames_of(tracks) for e in recognizer.feed(r)]


def test_tap_and_its_limits():
    assert [e["type"] for e in run({0: [(1.0, (0, 0, 0)), (1.1, (2, 0, 0))]})] == ["tap"]
    # Moving farther than tap_max_move_mm is not a tap; held longer than tap_max_ms is not either.
    assert run({0: [(1.0, (0, 0, 0)), (1.1, (8, 0, 0))]}) == []
    assert run({0: [(1.0 + 0.1 * k, (0, 0, 0)) for k in range(4)]}) == []


def test_double_tap_needs_both_taps_close_in_time_and_space():
    near = run({0: [(1.0, (0, 0, 0))], 1: [(1.3, (3, 0, 0))]})
    assert [e["type"] for e in near] == ["tap", "tap", "double_tap"]
    far = run({0: [(1.0, (0, 0, 0))], 1: [(1.3, (30, 0, 0))]})
    assert [e["type"] for e in far] == ["tap", "tap"]
    late = run({0: [(1.0, (0, 0, 0))], 1: [(1.7, (0, 0, 0))]})
    assert [e["type"] for e in late] == ["tap", "tap"]


def test_long_press_fires_once_while_held_and_suppresses_the_tap():
    events = run({0: [(1.0 + 0.1 * k, (0.1 * k, 0, 0)) for k in range(15)]})
    assert [e["type"] for e in events] == ["long_press"]
    assert events[0]["t"] == pytest.approx(1.6)


def test_swipe_direction_length_and_minimum():
    events = run({0: [(1.0 + 0.1 * k, (6.0 * k, 0, 0)) for k in range(6)]})
    assert [e["type"] for e in events] == ["swipe"]
    assert events[0]["direction"] == [1.0, 0.0, 0.0]
    assert events[0]["distance_mm"] == pytest.approx(30.0)
    assert run({0: [(1.0 + 0.1 * k, (3.0 * k, 0, 0)) for k in range(6)]}) == []  # 15 mm < swipe_min_mm


def test_pinch_spread_and_small_changes():
    closing = {0: [(1.0 + 0.1 * k, (-20 + 2.0 * k, 0, 0)) for k in range(6)],
               1: [(1.0 + 0.1 * k, (20 - 2.0 * k, 0, 0)) for k in range(6)]}
    events = run(closing)
    assert [e["type"] for e in events] == ["pinch"]
    assert events[0]["from_mm"] == pytest.approx(40.0) and events[0]["to_mm"] == pytest.approx(20.0)
    opening = {0: [(1.0 + 0.1 * k, (-10 - 2.0 * k, 0, 0)) for k in range(6)],
               1: [(1.0 + 0.1 * k, (10 + 2.0 * k, 0, 0)) for k in range(6)]}
    assert [e["type"] for e in run(opening)] == ["spread"]
    still = {0: [(1.0 + 0.1 * k, (-10 - 0.5 * k, 0, 0)) for k in range(6)],
             1: [(1.0 + 0.1 * k, (10 + 0.5 * k, 0, 0)) for k in range(6)]}
    assert run(still) == []
