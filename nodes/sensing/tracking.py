"""Touch tracking (see :mod:`.processing`, step 5): touches are matched to the previous frame's
tracks by minimum total distance (``scipy.optimize.linear_sum_assignment``) within a gate (mm);
unmatched tracks end, unmatched touches get fresh ids, with two rules for what one finger does:

* one finger is one finger: when the previous frame had one track and this frame has one touch, the
  touch continues the track however far it moved (a fast swipe on a slow board, or a point that
  jumps where the crossings are sparse), instead of a touch_up and a touch_down;
* a touch that appears while other touches are live touches down only once it has been seen in
  ``confirm_frames`` consecutive frames (within the gate of where it was): a peak that a finger's
  own coupling raises for one frame beside it (on a first touch, before the coupling is learned, or
  at lift-off) is not a second finger. A first finger touches down at once.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment


def _matches(before: np.ndarray, now: np.ndarray, gate_mm: float) -> list[tuple[int, int]]:
    """(row of ``before``, row of ``now``) pairs of least total distance, each at most ``gate_mm``."""
    if len(before) == 0 or len(now) == 0:
        return []
    offsets = before[:, None] - now[None]
    cost = np.sqrt(np.sum(offsets * offsets, axis=2))
    rows, cols = linear_sum_assignment(np.where(cost <= gate_mm, cost, 1e6))
    return [(int(r), int(c)) for r, c in zip(rows, cols) if cost[r, c] <= gate_mm]


class Tracker:
    """Stable ids across frames and the touch_down / touch_move / touch_up events they give."""

    def __init__(self, gate_mm: float, confirm_frames: int = 2):
        self.gate_mm = gate_mm
        self.confirm_frames = confirm_frames
        self.reset()

    def reset(self) -> None:
        self._tracks: dict[int, np.ndarray] = {}  # id -> last point (mm)
        self._pending: list[tuple[np.ndarray, int]] = []  # (last point, frames seen) of unconfirmed touches
        self._next_id = 0

    def track(self, touches: list, t: float) -> tuple[list, list[dict[str, Any]]]:
        """Touches (ids unset) at time ``t`` (s) -> (confirmed touches with ids, JSON-ready events)."""
        previous_ids = list(self._tracks)
        now = np.array([touch.point for touch in touches]).reshape(-1, 3)
        before = np.array([self._tracks[i] for i in previous_ids]).reshape(-1, 3)
        if len(previous_ids) == 1 and len(touches) == 1:
            assigned = {0: previous_ids[0]}
        else:
            assigned = {c: previous_ids[r] for r, c in _matches(before, now, self.gate_mm)}
        new = [j for j in range(len(touches)) if j not in assigned]
        confirmed, pending = set(new), []
        if previous_ids and new:  # beside live touches a new one must persist
            seen = {c: self._pending[r][1] for r, c in
                    _matches(np.array([p for p, _ in self._pending]).reshape(-1, 3), now[new], self.gate_mm)}
            confirmed = set()
            for k, j in enumerate(new):
                frames = seen.get(k, 0) + 1
                if frames >= self.confirm_frames:
                    confirmed.add(j)
                else:
                    pending.append((now[j], frames))
        self._pending = pending
        events: list[dict[str, Any]] = []
        tracked = []
        for j, touch in enumerate(touches):
            if j in assigned:
                touch = dataclasses.replace(touch, id=assigned[j])
                kind = "touch_move"
            elif j in confirmed:
                touch = dataclasses.replace(touch, id=self._next_id)
                self._next_id += 1
                kind = "touch_down"
            else:
                continue
            tracked.append(touch)
            events.append({"type": kind, "t": round(t, 4), **touch.as_json()})
        live = {touch.id for touch in tracked}
        for track_id in previous_ids:
            if track_id not in live:
                events.append({"type": "touch_up", "t": round(t, 4), "id": track_id,
                               "point": [round(float(x), 3) for x in self._tracks[track_id]]})
        self._tracks = {touch.id: touch.point for touch in tracked}
        return tracked, events
