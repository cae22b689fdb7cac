"""Gestures from tracked 3D touches: tap, double tap, long press, swipe along the surface, pinch and
spread. Thresholds are in mm and ms (``GestureParams``); distances are measured in 3D on the
surface points the processing reports (a swipe's length is its path length over the surface).

At the board's ~10 Hz a touch's duration is quantised to 100 ms: a touch seen in one frame lasts
100 ms (down at its first frame, up at the first frame without it).

Events (JSON-ready dicts, ``t`` in s, points in mm)::

    {"type": "tap", "t", "id", "point"}
    {"type": "double_tap", "t", "id", "point"}              # emitted after the second tap's "tap"
    {"type": "long_press", "t", "id", "point"}              # while still held
    {"type": "swipe", "t", "id", "from", "to", "direction", "distance_mm", "duration_ms", "speed_mm_s"}
    {"type": "pinch" | "spread", "t", "ids", "centre", "from_mm", "to_mm", "scale"}
"""
from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from pydantic import Field

from ...graph.node import NodeParams
from .processing import FrameResult


class GestureParams(NodeParams):
    """Gesture thresholds (mm, ms)."""

    tap_max_ms: float = Field(300.0, gt=0, description="longest touch that still counts as a tap")
    tap_max_move_mm: float = Field(6.0, gt=0, description="largest drift of a tap from where it started")
    double_tap_max_gap_ms: float = Field(400.0, gt=0, description="longest pause between two taps of a double tap")
    double_tap_max_distance_mm: float = Field(15.0, gt=0, description="largest distance between two taps of a double tap")
    long_press_ms: float = Field(600.0, gt=0, description="hold this long (without moving) for a long press")
    long_press_max_move_mm: float = Field(6.0, gt=0, description="largest drift of a long press")
    swipe_min_mm: float = Field(20.0, gt=0, description="shortest path of a swipe over the surface (its chord must reach half)")
    swipe_max_ms: float = Field(1500.0, gt=0, description="longest duration of a swipe")
    pinch_min_change_mm: float = Field(12.0, gt=0, description="smallest change of the finger distance for a pinch/spread")


@dataclasses.dataclass
class _Track:
    t_down: float
    start: np.ndarray
    last: np.ndarray
    path_mm: float = 0.0
    max_offset_mm: float = 0.0
    long_pressed: bool = False
    multi: bool = False  # another finger was down at the same time


def _point(values: np.ndarray) -> list[float]:
    return [round(float(x), 3) for x in values]


class GestureRecognizer:
    """Feed it every :class:`FrameResult`; it returns the gesture events each frame completes."""

    def __init__(self, params: GestureParams = GestureParams()):
        self.params = params
        self._tracks: dict[int, _Track] = {}
        self._last_tap: tuple[float, np.ndarray] | None = None
        self._pair: tuple[int, int, float] | None = None  # ids and their distance when both were down

    def feed(self, result: FrameResult) -> list[dict[str, Any]]:
        p = self.params
        t = result.t
        events: list[dict[str, Any]] = []
        now = {touch.id: touch.point for touch in result.touches}
        for track_id, point in now.items():
            track = self._tracks.get(track_id)
            if track is None:
                self._tracks[track_id] = _Track(t, point, point)
                continue
            track.path_mm += float(np.linalg.norm(point - track.last))
            track.last = point
            track.max_offset_mm = max(track.max_offset_mm, float(np.linalg.norm(point - track.start)))
        if len(now) > 1:
            for track_id in now:
                self._tracks[track_id].multi = True
            if self._pair is None and len(now) == 2:
                a, b = sorted(now)
                self._pair = (a, b, float(np.linalg.norm(now[a] - now[b])))
        for track_id, track in self._tracks.items():
            if (track_id in now and not track.long_pressed and not track.multi
                    and (t - track.t_down) * 1000 >= p.long_press_ms and track.max_offset_mm <= p.long_press_max_move_mm):
                track.long_pressed = True
                events.append({"type": "long_press", "t": round(t, 4), "id": track_id, "point": _point(track.last)})
        lifted = [track_id for track_id in self._tracks if track_id not in now]
        if self._pair is not None and any(i in lifted for i in self._pair[:2]):
            events.extend(self._pinch(t))
        for track_id in lifted:
            events.extend(self._release(track_id, self._tracks.pop(track_id), t))
        return events

    def _pinch(self, t: float) -> list[dict[str, Any]]:
        a, b, start_mm = self._pair
        self._pair = None
        end_mm = float(np.linalg.norm(self._tracks[a].last - self._tracks[b].last))
        if abs(end_mm - start_mm) < self.params.pinch_min_change_mm:
            return []
        centre = (self._tracks[a].last + self._tracks[b].last) / 2
        return [{"type": "pinch" if end_mm < start_mm else "spread", "t": round(t, 4), "ids": [a, b],
                 "centre": _point(centre), "from_mm": round(start_mm, 2), "to_mm": round(end_mm, 2),
                 "scale": round(end_mm / max(start_mm, 1e-9), 4)}]

    def _release(self, track_id: int, track: _Track, t: float) -> list[dict[str, Any]]:
        p = self.params
        if track.multi or track.long_pressed:
            return []
        duration_ms = (t - track.t_down) * 1000
        events: list[dict[str, Any]] = []
        if duration_ms <= p.tap_max_ms and track.max_offset_mm <= p.tap_max_move_mm:
            events.append({"type": "tap", "t": round(t, 4), "id": track_id, "point": _point(track.start)})
            last = self._last_tap
            if (last is not None and (track.t_down - last[0]) * 1000 <= p.double_tap_max_gap_ms
                    and np.linalg.norm(track.start - last[1]) <= p.double_tap_max_distance_mm):
                events.append({"type": "double_tap", "t": round(t, 4), "id": track_id, "point": _point(track.start)})
                self._last_tap = None
            else:
                self._last_tap = (t, track.start)
            return events
        displacement = track.last - track.start
        distance = float(np.linalg.norm(displacement))
        # Along a curved surface the chord is shorter than the path: the path decides, the chord
        # only has to show the finger went somewhere (not a wiggle in place).
        if track.path_mm >= p.swipe_min_mm and distance >= 0.5 * p.swipe_min_mm and duration_ms <= p.swipe_max_ms:
            events.append({"type": "swipe", "t": round(t, 4), "id": track_id, "from": _point(track.start),
                           "to": _point(track.last), "direction": _point(displacement / distance),
                           "distance_mm": round(track.path_mm, 2), "duration_ms": round(duration_ms, 1),
                           "speed_mm_s": round(track.path_mm / max(duration_ms / 1000, 1e-9), 1)})
        return events
