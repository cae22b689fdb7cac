"""Scripted touches for the virtual board: gesture steps -> finger strokes on the surface.

Scripts (``--simulate script.json``) are JSON lists of steps, times in ms, lengths in mm::

    [{"gesture": "tap", "at": "random"}, {"gesture": "wait", "ms": 500},
     {"gesture": "double_tap", "at": {"cell": 40}}, {"gesture": "long_press", "at": [x, y, z], "ms": 1200},
     {"gesture": "swipe", "at": "random", "length_mm": 40, "ms": 600},
     {"gesture": "pinch", "at": "random", "from_mm": 45, "to_mm": 20, "ms": 800},
     {"gesture": "spread", "at": "random", "from_mm": 20, "to_mm": 45, "ms": 800},
     {"gesture": "press", "at": "random", "ms": 500}]

``at`` is a point (projected on the surface), ``{"cell": k}`` (a crossing) or ``"random"`` (inside
the sensed region: within one coupling width of a crossing, where the nearest crossing reads at
least 61 % of a centred finger). Swipes and pinches follow the surface (tangent marching with re-projection);
``direction`` (3D vector) is optional.
"""
from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ...graph.errors import UserError
from ..data.board import default_coupling_width_mm
from ..data.sensing_map import SensingMap
from ..geometry.surface import SurfaceProjector
from .virtual_board import BoardParams


@dataclasses.dataclass(frozen=True)
class Stroke:
    """One finger down from ``t0`` to ``t1`` (s), moving along ``path`` from arc length ``arc0`` to
    ``arc1`` (mm) at constant speed."""

    t0: float
    t1: float
    path: np.ndarray  # (M, 3) mm, on the surface
    arc0: float
    arc1: float
    strength: float  # counts

    def position(self, t: float) -> np.ndarray:
        cumulative = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(self.path, axis=0), axis=1))])
        fraction = 0.0 if self.t1 <= self.t0 else min(max((t - self.t0) / (self.t1 - self.t0), 0.0), 1.0)
        arc = self.arc0 + fraction * (self.arc1 - self.arc0)
        return np.array([np.interp(arc, cumulative, self.path[:, d]) for d in range(3)])


@dataclasses.dataclass(frozen=True)
class Script:
    """Strokes plus ground-truth labels ``(t, dict)``; ``duration`` in s."""

    strokes: tuple[Stroke, ...]
    labels: tuple[tuple[float, dict[str, Any]], ...]
    duration: float

    def fingers_at(self, t: float) -> list[tuple[np.ndarray, float]]:
        return [(s.position(t), s.strength) for s in self.strokes if s.t0 <= t < s.t1]


class ScriptBuilder:
    """Turns script steps (see the module docstring) into strokes on a sensing map's surface."""

    def __init__(self, sensing_map: SensingMap, params: BoardParams = BoardParams(), seed: int = 0):
        self.map = sensing_map
        self.params = params
        self.rng = np.random.default_rng(seed)
        self.projector = SurfaceProjector(sensing_map.vertices, sensing_map.faces)
        self.pitch = sensing_map.pitch_mm()
        self.reach = params.coupling_sigma_mm or default_coupling_width_mm(params.finger_radius_mm, self.pitch)
        self.cell_tree = cKDTree(sensing_map.cell_points)
        counts = np.array([len(n) for n in self.cell_tree.query_ball_point(sensing_map.cell_points, 1.6 * self.pitch)])
        self.interior_cells = np.flatnonzero(counts >= np.percentile(counts, 50))

    def inside(self, points: np.ndarray) -> bool:
        """Whether every point is within one coupling width of a crossing (the sensed region)."""
        distance, _ = self.cell_tree.query(np.atleast_2d(points))
        return bool(np.all(distance <= self.reach))

    def location(self, spec: Any) -> np.ndarray:
        if isinstance(spec, dict) and "cell" in spec:
            return self.map.cell_points[int(spec["cell"])].copy()
        if isinstance(spec, (list, tuple)) and len(spec) == 3:
            return self.projector.project(np.asarray(spec, dtype=np.float64))[0][0]
        if spec in (None, "random"):
            for _ in range(100):
                cell = self.map.cell_points[self.rng.choice(self.interior_cells)]
                offset = self.rng.normal(0, self.pitch / 3, 3)
                point = self.projector.project(cell + offset)[0][0]
                if self.inside(point):
                    return point
            return cell.copy()
        raise UserError(f"bad touch location {spec!r}: use [x, y, z], {{\"cell\": k}} or \"random\"")

    def march(self, start: np.ndarray, direction: np.ndarray, length: float, step: float = 1.0) -> np.ndarray:
        """Polyline from ``start`` along the surface, keeping the tangent direction (mm). Stops early
        where a step makes no headway (a ridge or a sharp fold): callers check the length reached."""
        points = [start]
        point, face = start, self.projector.project(start)[1][0]
        for _ in range(int(np.ceil(length / step))):
            normal = self.projector.face_normals[face]
            direction = direction - (direction @ normal) * normal
            direction /= max(np.linalg.norm(direction), 1e-12)
            projected, faces, _ = self.projector.project(point + step * direction)
            moved = projected[0] - point
            if moved @ direction < 0.5 * step:
                break
            direction = moved / np.linalg.norm(moved)
            point, face = projected[0], faces[0]
            points.append(point)
        return np.array(points)

    def fits(self, path: np.ndarray, length: float) -> bool:
        """Whether a marched path reached ``length`` (mm), stays inside the sensed region and runs over a
        broad patch (its chord is at least 80 % of its length: no wrapping around an ear or a rim)."""
        reached = np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1)) >= length - 1.0
        broad = np.linalg.norm(path[-1] - path[0]) >= 0.8 * length
        return bool(reached and broad) and self.inside(path)

    def _tangent(self, point: np.ndarray, direction: Any) -> np.ndarray:
        normal = self.projector.face_normals[self.projector.project(point)[1][0]]
        d = np.asarray(direction, dtype=np.float64) if direction is not None else self.rng.normal(size=3)
        d = d - (d @ normal) * normal
        return d / max(np.linalg.norm(d), 1e-12)

    def _strength(self) -> float:
        jitter = self.params.touch_strength_jitter
        return self.params.signal_counts * (1 + self.rng.uniform(-jitter, jitter))

    def build(self, steps: list[dict[str, Any]], lead_in_s: float = 3.0, tail_s: float = 1.0) -> Script:
        strokes: list[Stroke] = []
        labels: list[tuple[float, dict[str, Any]]] = []
        t = lead_in_s
        for index, step in enumerate(steps):
            kind = step.get("gesture")
            ms = float(step.get("ms", 0)) / 1000.0
            if kind == "wait":
                t += ms
                continue
            if kind in ("tap", "press", "long_press"):
                duration = ms or {"tap": 0.15, "press": 0.5, "long_press": 1.2}[kind]
                point = self.location(step.get("at"))
                strokes.append(Stroke(t, t + duration, point[None], 0.0, 0.0, self._strength()))
                labels.append((t, {"step": index, "gesture": kind, "point": point.tolist(), "t_end": t + duration,
                                   **{k: step[k] for k in ("location", "repetition") if k in step}}))
                t += duration
            elif kind == "double_tap":
                point = self.location(step.get("at"))
                for k in range(2):
                    strokes.append(Stroke(t, t + 0.15, point[None], 0.0, 0.0, self._strength()))
                    t += 0.15 + (0.2 if k == 0 else 0.0)
                labels.append((t - 0.5, {"step": index, "gesture": kind, "point": point.tolist(), "t_end": t}))
            elif kind == "swipe":
                duration = ms or 0.6
                length = float(step.get("length_mm", 40.0))
                path = self._surface_path(step.get("at"), step.get("direction"), length)
                strokes.append(Stroke(t, t + duration, path, 0.0, length, self._strength()))
                labels.append((t, {"step": index, "gesture": kind, "from": path[0].tolist(), "to": path[-1].tolist(),
                                   "t_end": t + duration}))
                t += duration
            elif kind in ("pinch", "spread"):
                duration = ms or 0.8
                start_mm = float(step.get("from_mm", 45.0 if kind == "pinch" else 20.0))
                end_mm = float(step.get("to_mm", 20.0 if kind == "pinch" else 45.0))
                half = max(start_mm, end_mm) / 2
                centre, direction = self._pinch_centre(step.get("at"), step.get("direction"), half)
                for sign in (1.0, -1.0):
                    path = self.march(centre, sign * direction, half)
                    strokes.append(Stroke(t, t + duration, path, start_mm / 2, end_mm / 2, self._strength()))
                labels.append((t, {"step": index, "gesture": kind, "centre": centre.tolist(), "from_mm": start_mm,
                                   "to_mm": end_mm, "t_end": t + duration}))
                t += duration
            else:
                raise UserError(f"script step {index}: unknown gesture {kind!r} (tap, double_tap, long_press, "
                                "press, swipe, pinch, spread, wait)")
            t += float(step.get("gap_ms", 600)) / 1000.0
        return Script(tuple(strokes), tuple(labels), t + tail_s)

    def _starts(self, at: Any, direction: Any) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """Start points and tangent directions to try: 200 random draws, then (for ``"random"``)
        every crossing (in 12 directions unless one is given), so a gesture that fits somewhere is
        always found."""
        for _ in range(200):
            start = self.location(at)
            yield start, self._tangent(start, direction)
        if at in (None, "random"):
            for start in self.map.cell_points:
                if direction is not None:
                    yield start.copy(), self._tangent(start, direction)
                    continue
                normal = self.projector.face_normals[self.projector.project(start)[1][0]]
                u = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
                u /= np.linalg.norm(u)
                v = np.cross(normal, u)
                for angle in np.linspace(0, 2 * np.pi, 12, endpoint=False):
                    yield start.copy(), np.cos(angle) * u + np.sin(angle) * v

    def _surface_path(self, at: Any, direction: Any, length: float) -> np.ndarray:
        for start, tangent in self._starts(at, direction):
            path = self.march(start, tangent, length)
            if self.fits(path, length):
                return path
        raise UserError(f"no {length:g} mm swipe fits inside the sensed region from {at!r}: shorten length_mm")

    def _pinch_centre(self, at: Any, direction: Any, half: float) -> tuple[np.ndarray, np.ndarray]:
        for centre, d in self._starts(at, direction):
            ahead, behind = self.march(centre, d, half), self.march(centre, -d, half)
            if self.fits(np.concatenate([behind[::-1], ahead[1:]]), 2 * half):
                return centre, d
        raise UserError(f"no pinch of {2 * half:g} mm fits inside the sensed region at {at!r}: use smaller distances")


def load_script(path: str | Path) -> list[dict[str, Any]]:
    """A JSON list of steps; one-line UserError when missing or malformed."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"simulation script {path} not found: pass a JSON list of steps")
    try:
        steps = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise UserError(f"simulation script {path} is not valid JSON ({exc})") from None
    if not isinstance(steps, list) or not all(isinstance(s, dict) and "gesture" in s for s in steps):
        raise UserError(f"simulation script {path} must be a JSON list of {{\"gesture\": ...}} steps")
    return steps


DEMO_SCRIPT = [
    {"gesture": "tap", "at": "random"},
    {"gesture": "double_tap", "at": "random"},
    {"gesture": "long_press", "at": "random"},
    {"gesture": "swipe", "at": "random", "length_mm": 40},
    {"gesture": "pinch", "at": "random", "from_mm": 45, "to_mm": 20},
    {"gesture": "spread", "at": "random", "from_mm": 20, "to_mm": 45},
]
