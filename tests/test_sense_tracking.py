"""Touch tracking: ids, touch_down / touch_up, one finger kept as one, unconfirmed extra touches."""
from __future__ import annotations

import numpy as np

from retrotouch.nodes.sensing.processing import Touch
from retrotouch.nodes.sensing.tracking import Tracker


def touch(x: float, y: float = 0.0) -> Touch:
    return Touch(-1, np.array([x, y, 0.0]), 0, np.full(3, 1 / 3), np.array([0.0, 0.0, 1.0]), 100.0, 50.0, 0)


def run(tracker: Tracker, frames: list[list[Touch]]) -> list[list[tuple[str, int]]]:
    """Per frame, the (event type, id) pairs the tracker emits."""
    return [[(e["type"], e["id"]) for e in tracker.track(touches, 0.1 * k)[1]] for k, touches in enumerate(frames)]


def test_a_first_finger_touches_down_at_once_and_up_when_it_lifts():
    assert run(Tracker(40.0), [[touch(0)], [touch(1)], []]) == [
        [("touch_down", 0)], [("touch_move", 0)], [("touch_up", 0)]]


def test_a_one_frame_peak_beside_a_finger_is_no_second_touch():
    events = run(Tracker(40.0), [[touch(0)], [touch(0), touch(15)], [touch(0)], [touch(0), touch(15)], []])
    assert [kind for frame in events for kind, _ in frame].count("touch_down") == 1
    assert events[1] == [("touch_move", 0)] and events[3] == [("touch_move", 0)]


def test_a_second_finger_that_stays_touches_down_on_its_second_frame():
    events = run(Tracker(40.0), [[touch(0)], [touch(0), touch(30)], [touch(0), touch(31)], [touch(0), touch(32)]])
    assert events[1] == [("touch_move", 0)]
    assert events[2] == [("touch_move", 0), ("touch_down", 1)]
    assert events[3] == [("touch_move", 0), ("touch_move", 1)]


def test_two_fingers_landing_together_touch_down_together():
    events = run(Tracker(40.0), [[touch(0), touch(30)]])
    assert events == [[("touch_down", 0), ("touch_down", 1)]]


def test_a_lone_finger_keeps_its_id_however_far_it_moves():
    events = run(Tracker(40.0), [[touch(0)], [touch(60)], [touch(130)], []])
    assert events == [[("touch_down", 0)], [("touch_move", 0)], [("touch_move", 0)], [("touch_up", 0)]]


def test_with_two_fingers_the_gate_still_separates_them():
    events = run(Tracker(40.0), [[touch(0), touch(30)], [touch(0), touch(100)], [touch(0), touch(100)]])
    assert events[1] == [("touch_move", 0), ("touch_up", 1)]  # the second finger lifted, a new one is unconfirmed
    assert events[2] == [("touch_move", 0), ("touch_down", 2)]


def test_one_confirm_frame_reports_every_touch_at_once():
    events = run(Tracker(40.0, confirm_frames=1), [[touch(0)], [touch(0), touch(15)]])
    assert events[1] == [("touch_move", 0), ("touch_down", 1)]
