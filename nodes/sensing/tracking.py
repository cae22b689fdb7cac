"""Touch tracking (see :mod:`.processing`, step 5): touches are matched to the previous frame's
tracks by minimum total distance (``scipy.optimize.linear_sum_assignment``) within a gate (mm);
unmatched touches get fresh ids, unmatched tracks end."""
from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment


class Tracker:
    """Stable ids across frames and the touch_down / touch_move / touch_up events they give."""

    def __init__(self, gate_mm: float):
        self.gate_mm = gate_mm
        self.reset()

    def reset(self) -> None:
        self._tracks: dict[int, np.ndarray] = {}  # id -> last point (mm)
        self._next_id = 0

    def track(self, touches: list, t: float) -> tuple[list, list[dict[str, Any]]]:
        """Touches (ids unset) at time ``t`` (s) -> (touches with ids, JSON-ready events)."""
        previous_ids = list(self._tracks)
        assigned: dict[int, int] = {}
        if previous_ids and touches:
            before = np.array([self._tracks[i] for i in previous_ids])
            now = np.array([touch.point for touch in touches])
            offsets = before[:, None] - now[None]
            cost = np.sqrt(np.sum(offsets * offsets, axis=2))
            gate = self.gate_mm
            rows, cols = linear_sum_assignment(np.where(cost <= gate, cost, 1e6))
            assigned = {int(c): previous_ids[r] for r, c in zip(rows, cols) if cost[r, c] <= gate}
        events: list[dict[str, Any]] = []
        tracked = []
        for j, touch in enumerate(touches):
            if j in assigned:
                touch = dataclasses.replace(touch, id=assigned[j])
                kind = "touch_move"
            else:
                touch = dataclasses.replace(touch, id=self._next_id)
                self._next_id += 1
                kind = "touch_down"
            tracked.append(touch)
            events.append({"type": kind, "t": round(t, 4), **touch.as_json()})
        live = {touch.id for touch in tracked}
        for track_id in previous_ids:
            if track_id not in live:
                events.append({"type": "touch_up", "t": round(t, 4), "id": track_id,
                               "point": [round(float(x), 3) for x in self._tracks[track_id]]})
        self._tracks = {touch.id: touch.point for touch in tracked}
        return tracked, events
