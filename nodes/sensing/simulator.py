"""A virtual Muca board: frames from simulated finger touches on the object, served on a pseudo-terminal
so the real serial path (termios, pyserial, the parser) is exercised.

Signal model per cell ``i`` at crossing ``x_i`` (counts, clipped to 0..65535)::

    raw_i(t) = B_i (1 + c(t)) + w_i(t) + g_i sum_f S_f K(|p_f - x_i|) + N(0, sigma_n^2)

* ``B_i`` uniform in the FT5x06 range seen on real boards (9650..10360); channel pairs without a
  crossing read baseline + noise only.
* ``c(t)`` common drift (``drift_fraction`` x a slow sine of period ``drift_period_s``, temperature),
  ``w_i`` an independent per-cell random walk (``cell_walk_counts`` per sqrt(s)).
* ``g_i`` cell gain: 1 with an electrode pad, ``no_pad_gain`` without, times a lognormal jitter.
* ``S_f`` finger strength: ``signal_counts`` x a per-touch jitter (pressure, finger orientation).
* ``K`` the coupling profile (1 at distance 0), ``coupling_model``:

  - ``"gaussian"`` (default): ``K(d) = exp(-d^2 / (2 s^2))``, the processing's own model, with
    ``s = sqrt(finger_radius^2 + (pitch / 2)^2)`` unless ``coupling_sigma_mm`` is given;
  - ``"disc"``: a contact disc of radius ``finger_radius`` over a crossing whose sensitivity falls
    off like ``(1 + rho^2 / h^2)^(-3/2)`` (the field of a charge at height ``h`` over the plane),
    ``K(d)`` = that kernel integrated over the disc centred at distance ``d``, normalised.
    ``h`` is set so that ``K`` falls to one half where the Gaussian does (same reach), so the
    difference is the shape: a flat top and a power-law tail, which the processing's Gaussian fit
    does not contain. It measures how localization holds up when the real coupling is not the
    assumed one.
* ``sigma_n = signal_counts / snr``: ``snr`` is the peak-signal-over-noise-sigma of a nominal finger
  centred on a padded cell.

Scripts (``--simulate script.json``) are JSON lists of steps, times in ms, lengths in mm::

    [{"gesture": "tap", "at": "random"}, {"gesture": "wait", "ms": 500},
     {"gesture": "double_tap", "at": {"cell": 40}}, {"gesture": "long_press", "at": [x, y, z], "ms": 1200},
     {"gesture": "swipe", "at": "random", "length_mm": 40, "ms": 600},
     {"gesture": "pinch", "at": "random", "from_mm": 45, "to_mm": 20, "ms": 800},
     {"gesture": "spread", "at": "random", "from_mm": 20, "to_mm": 45, "ms": 800},
     {"gesture": "press", "at": "random", "ms": 500}]

``at`` is a point (projected on the surface), ``{"cell": k}`` (a crossing) or ``"random"`` (inside
the sensed region). Swipes and pinches follow the surface (tangent marching with re-projection);
``direction`` (3D vector) is optional.
"""
from __future__ import annotations

import dataclasses
import importlib.util
import json
import multiprocessing
import os
import pty
import threading
import time
import tty
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
import trimesh
from pydantic import Field
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from ...graph.errors import UserError
from ...graph.node import NodeParams
from .muca_serial import MAX_COUNT, NUM_RX, NUM_TX, Frame, FrameOptions, MucaReader, encode_ascii_frame, encode_binary_frame
from .processing import SensingMap, SurfaceProjector, write_sensing_map

# --------------------------------------------------------------------------------------------
# Synthetic layout (until the pipeline's sensing map exists)


def bunny_path() -> Path:
    """The embedded default mesh (pymeshlab's sample bunny), located through the installed package."""
    spec = importlib.util.find_spec("pymeshlab")
    if spec is None or spec.origin is None:
        raise UserError("pymeshlab is not installed: pip install pymeshlab")
    path = Path(spec.origin).parent / "tests" / "sample_meshes" / "bunny.obj"
    if not path.is_file():
        raise UserError(f"pymeshlab's sample bunny is missing ({path}): reinstall pymeshlab")
    return path


def up_axis(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The axis (one of +-x, +-y, +-z) opposite to the flattest downward-facing extreme: the object
    rests on the side whose faces within 3 % of the extent face outward along it with most area."""
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    extent = np.ptp(vertices, axis=0).max()
    best, best_area = np.array([0.0, 0.0, 1.0]), -1.0
    for axis in range(3):
        for sign in (-1.0, 1.0):
            direction = np.zeros(3)
            direction[axis] = sign
            height = mesh.triangles_center @ direction
            near = height >= height.max() - 0.03 * extent
            facing = mesh.face_normals @ direction > 0.9
            area = float(mesh.area_faces[near & facing].sum())
            if area > best_area:
                best, best_area = -direction, area
    return best


def synthetic_bunny_map(
    folder: str | Path,
    cells: int = 200,
    diagonal_mm: float = 170.0,
    base_fraction: float = 0.1,
    seed: int = 0,
    num_tx: int = 21,
    num_rx: int = 12,
) -> Path:
    """Write a realistic synthetic sensing map on the bunny into ``folder``; returns its json path.

    The bunny is scaled to ``diagonal_mm`` bounding-box diagonal; ``cells`` crossings are spread by
    farthest-point sampling over the surface above the bottom ``base_fraction`` of its height, and
    assigned to distinct (tx, rx) pairs so that Tx channels run around the object at increasing
    height and Rx channels at increasing azimuth (as the pipeline's two curve families do).
    """
    mesh = trimesh.load(bunny_path(), process=False, force="mesh")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    vertices = (vertices - vertices.min(axis=0)) * (diagonal_mm / np.linalg.norm(np.ptp(vertices, axis=0)))
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    up = up_axis(vertices, faces)
    samples, sample_faces = trimesh.sample.sample_surface(mesh, 30 * cells, seed=seed)
    height = samples @ up
    low, high = (vertices @ up).min(), (vertices @ up).max()
    keep = height > low + base_fraction * (high - low)
    samples, sample_faces = samples[keep], sample_faces[keep]
    chosen = farthest_point_sampling(samples, cells, seed)
    points, cell_faces = samples[chosen], sample_faces[chosen]
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[cell_faces], points)
    rank_height = np.argsort(np.argsort(points @ up)) / max(cells - 1, 1)
    centre = points.mean(axis=0)
    side = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    azimuth = np.arctan2((points - centre) @ np.cross(up, side), (points - centre) @ side)
    rank_azimuth = np.argsort(np.argsort(azimuth)) / max(cells - 1, 1)
    tx_target = (np.arange(num_tx) + 0.5) / num_tx
    rx_target = (np.arange(num_rx) + 0.5) / num_rx
    cost = ((rank_height[:, None, None] - tx_target[None, :, None]) ** 2
            + (rank_azimuth[:, None, None] - rx_target[None, None, :]) ** 2).reshape(cells, -1)
    rows, slots = linear_sum_assignment(cost)
    cell_tx, cell_rx = np.divmod(slots[np.argsort(rows)], num_rx)  # slot = tx * num_rx + rx of the cost matrix
    return write_sensing_map(folder, vertices, faces, cell_tx, cell_rx, cell_faces, bary, num_tx, num_rx)


def farthest_point_sampling(points: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """Indices of ``count`` points chosen greedily farthest from those already chosen (Euclidean)."""
    rng = np.random.default_rng(seed)
    chosen = [int(rng.integers(len(points)))]
    distance = np.linalg.norm(points - points[chosen[0]], axis=1)
    for _ in range(count - 1):
        nxt = int(np.argmax(distance))
        chosen.append(nxt)
        distance = np.minimum(distance, np.linalg.norm(points - points[nxt], axis=1))
    return np.array(chosen)


def default_sensing_map_path(repo_root: str | Path, cache_folder: str | Path) -> tuple[Path, str]:
    """The real default pipeline output ``out/retrofit/sensing_map.json`` if present, else the
    synthetic bunny map (generated once into ``cache_folder``). Returns (path, description)."""
    real = Path(repo_root) / "out" / "retrofit" / "sensing_map.json"
    if real.is_file():
        return real, f"default pipeline output {real}"
    cache = Path(cache_folder)
    path = cache / "sensing_map.json"
    if not path.is_file():
        path = synthetic_bunny_map(cache)
    return path, f"synthetic bunny map {path} (out/retrofit/sensing_map.json not found)"


# --------------------------------------------------------------------------------------------
# Board model


class BoardParams(NodeParams):
    """Virtual board settings (counts, mm, seconds; see the module docstring)."""

    snr: float = Field(60.0, gt=0, description="peak signal of a nominal centred finger over noise sigma")
    signal_counts: float = Field(300.0, gt=0, description="peak delta of a nominal finger on a padded cell")
    baseline_low: float = Field(9650.0, ge=0, description="lowest cell baseline (counts)")
    baseline_high: float = Field(10360.0, ge=0, description="highest cell baseline (counts)")
    finger_radius_mm: float = Field(4.5, gt=0, description="finger contact radius (mm)")
    coupling_sigma_mm: float | None = Field(None, gt=0, description="coupling width; None: sqrt(r^2 + (pitch/2)^2)")
    coupling_model: Literal["gaussian", "disc"] = Field(
        "gaussian", description="coupling profile: the processing's Gaussian, or a contact disc with a power-law tail")
    no_pad_gain: float = Field(0.5, gt=0, description="gain of a crossing without an electrode pad")
    cell_gain_jitter: float = Field(0.05, ge=0, description="lognormal sigma of per-cell gain")
    touch_strength_jitter: float = Field(0.15, ge=0, description="uniform +- relative jitter of each touch's strength")
    drift_fraction: float = Field(0.005, ge=0, description="amplitude of the common relative drift")
    drift_period_s: float = Field(300.0, gt=0, description="period of the common drift (s)")
    cell_walk_counts: float = Field(0.2, ge=0, description="per-cell random walk (counts per sqrt(s))")
    rate_hz: float = Field(10.0, gt=0, description="frame rate of the board")
    flip_tx: bool = Field(False, description="emit TX in reversed wire order (master firmware)")
    flip_rx: bool = Field(False, description="emit RX in reversed wire order (2020 library)")
    seed: int = 0


def disc_kernel_integral(radius: float, height: float, distances: np.ndarray) -> np.ndarray:
    """Integral of ``(1 + rho^2 / height^2)^(-3/2)`` over a disc of ``radius`` (mm) whose centre is
    ``distances`` (mm, 1D) from the kernel's centre, normalised to 1 at distance 0 (polar midpoint
    quadrature, 48 x 96 nodes: the profile is smooth)."""
    radial = (np.arange(48) + 0.5) / 48 * radius
    angles = (np.arange(96) + 0.5) / 96 * 2 * np.pi
    rho, theta = np.meshgrid(radial, angles, indexing="ij")
    weights = (rho * (radius / 48) * (2 * np.pi / 96)).ravel()
    x, y = (rho * np.cos(theta)).ravel(), (rho * np.sin(theta)).ravel()
    d = np.concatenate([[0.0], np.atleast_1d(distances)])[:, None]
    integral = (1 + ((x - d) ** 2 + y**2) / height**2) ** -1.5 @ weights
    return integral[1:] / integral[0]


def disc_coupling_profile(radius: float, half_maximum: float) -> tuple[np.ndarray, np.ndarray]:
    """The ``"disc"`` coupling profile as a table ``(distances, values)`` (mm, 0.1 mm steps out to
    ``8 x half_maximum``) for ``np.interp``: a disc of ``radius`` (mm), the kernel height found by
    bisection so that the profile is 1/2 at ``half_maximum`` (mm)."""
    # As the height goes to 0 the profile tends to 1 inside the disc and 0 outside it.
    if half_maximum <= radius:
        raise UserError(f"disc coupling: the {radius:.2f} mm finger disc reaches past the half-maximum distance "
                        f"{half_maximum:.2f} mm; lower finger_radius_mm or raise coupling_sigma_mm")
    low, high = 1e-3 * radius, 100.0 * half_maximum
    for _ in range(60):  # the profile at a fixed distance grows with the height
        height = np.sqrt(low * high)
        if disc_kernel_integral(radius, height, np.array([half_maximum]))[0] < 0.5:
            low = height
        else:
            high = height
    distances = np.arange(0.0, 8.0 * half_maximum + 0.1, 0.1)
    return distances, np.concatenate([[1.0], disc_kernel_integral(radius, np.sqrt(low * high), distances[1:])])


class VirtualBoard:
    """Frames of a Muca board on a sensing map (see the module docstring for the model)."""

    def __init__(self, sensing_map: SensingMap, params: BoardParams = BoardParams()):
        self.map = sensing_map
        self.params = params
        self.rng = np.random.default_rng(params.seed)
        n = NUM_TX * NUM_RX  # the board scans all its channels, wired or not
        self.baseline = self.rng.uniform(params.baseline_low, params.baseline_high, n)
        self.pitch = sensing_map.pitch_mm()
        self.coupling_sigma = params.coupling_sigma_mm or float(np.hypot(params.finger_radius_mm, self.pitch / 2))
        if params.coupling_model == "disc":
            half_maximum = self.coupling_sigma * np.sqrt(2 * np.log(2))
            self.disc_profile = disc_coupling_profile(params.finger_radius_mm, half_maximum)
        pad_gain = np.where(sensing_map.cell_pad, 1.0, params.no_pad_gain)
        self.gain = pad_gain * self.rng.lognormal(0.0, params.cell_gain_jitter, sensing_map.cell_count)
        self.noise_sigma = params.signal_counts / params.snr
        self.drift_phase = self.rng.uniform(0, 2 * np.pi)
        self.walk = np.zeros(n)
        self._last_t: float | None = None

    def signal(self, fingers: Sequence[tuple[np.ndarray, float]]) -> np.ndarray:
        """Noise-free touch signal (counts) per sensing-map cell for fingers ``(point, strength)``."""
        signal = np.zeros(self.map.cell_count)
        for point, strength in fingers:
            d2 = np.sum((self.map.cell_points - point) ** 2, axis=1)
            if self.params.coupling_model == "disc":
                signal += strength * np.interp(np.sqrt(d2), *self.disc_profile, right=0.0)
            else:
                signal += strength * np.exp(-d2 / (2 * self.coupling_sigma**2))
        return self.gain * signal

    def frame(self, t: float, fingers: Sequence[tuple[np.ndarray, float]] = ()) -> np.ndarray:
        """Counts at time ``t`` (s) in wire order, shape (21, 12), int64."""
        p = self.params
        if p.cell_walk_counts and self._last_t is not None and t > self._last_t:
            self.walk += self.rng.normal(0, p.cell_walk_counts * np.sqrt(t - self._last_t), len(self.walk))
        self._last_t = t
        common = p.drift_fraction * np.sin(2 * np.pi * t / p.drift_period_s + self.drift_phase)
        raw = self.baseline * (1 + common) + self.walk + self.rng.normal(0, self.noise_sigma, len(self.walk))
        raw[self.map.frame_index] += self.signal(fingers)
        grid = np.clip(np.rint(raw), 0, MAX_COUNT).astype(np.int64).reshape(NUM_TX, NUM_RX)
        if p.flip_tx:
            grid = grid[::-1]
        if p.flip_rx:
            grid = grid[:, ::-1]
        return grid


# --------------------------------------------------------------------------------------------
# Scripted touches


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
        self.cell_tree = cKDTree(sensing_map.cell_points)
        counts = np.array([len(n) for n in self.cell_tree.query_ball_point(sensing_map.cell_points, 1.6 * self.pitch)])
        self.interior_cells = np.flatnonzero(counts >= np.percentile(counts, 50))

    def inside(self, points: np.ndarray) -> bool:
        """Whether every point is within 0.8 pitch of a crossing (the sensed region)."""
        distance, _ = self.cell_tree.query(np.atleast_2d(points))
        return bool(np.all(distance <= 0.8 * self.pitch))

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


# --------------------------------------------------------------------------------------------
# The board on a pseudo-terminal


class PtyBoard:
    """Serves a virtual board's frames on a pseudo-terminal; open :attr:`port` with pyserial.

    Paced at ``rate_hz`` of board time, or as fast as the reader drains the pty when ``fast``; with
    ``separate_process`` the board runs in a forked process (as a real board runs on its own chip);
    ``prerender`` (fast mode, finite) synthesizes all frames before writing the first one.
    Frame ``k`` shows the script at board time ``k / rate_hz``. Stops after the script's duration
    (or ``frames`` frames if given; ``loop`` repeats the script forever).
    """

    def __init__(
        self,
        board: VirtualBoard,
        script: Script | None = None,
        frame_format: str = "ascii",
        fast: bool = False,
        frames: int | None = None,
        loop: bool = False,
        garbage_every: int = 0,
        separate_process: bool = False,
        prerender: bool = False,
    ):
        self.board = board
        self.script = script
        self.frame_format = frame_format
        self.fast = fast
        self.rate_hz = board.params.rate_hz
        if frames is None:
            frames = int(np.ceil(script.duration * self.rate_hz)) if script is not None else None
        self.frames_total = None if loop else frames
        self.loop = loop
        self.garbage_every = garbage_every
        if prerender and (not fast or self.frames_total is None):
            raise ValueError("prerender needs fast mode and a finite number of frames")
        self.prerender = prerender
        self.master, self.slave = pty.openpty()
        tty.setraw(self.slave)
        self.port = os.ttyname(self.slave)
        if separate_process:
            # A board of its own: frame synthesis does not compete with the reader for the GIL.
            context = multiprocessing.get_context("fork")
            self.done, self._stop = context.Event(), context.Event()
            self._thread = context.Process(target=self._run, name="muca-simulator", daemon=True)
        else:
            self.done, self._stop = threading.Event(), threading.Event()
            self._thread = threading.Thread(target=self._run, name="muca-simulator", daemon=True)

    def __enter__(self) -> PtyBoard:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def start(self) -> None:
        self._thread.start()

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view and not self._stop.is_set():
            written = os.write(self.master, view)
            view = view[written:]

    def _frame_bytes(self, k: int) -> bytes:
        t = k / self.rate_hz
        script_t = t % self.script.duration if (self.script is not None and self.loop) else t
        fingers = self.script.fingers_at(script_t) if self.script is not None else []
        grid = self.board.frame(t, fingers)
        data = encode_ascii_frame(grid) if self.frame_format == "ascii" else encode_binary_frame(grid)
        if self.garbage_every and k % self.garbage_every == self.garbage_every - 1:
            data = b"Calibration performed 3/20\r\n\x00\xff garbage,12,\r\n" + data
        return data

    def _run(self) -> None:
        try:
            if self.prerender:
                # Synthesize every frame first, then only write: the stream runs at the reader's pace.
                stream = b"".join(self._frame_bytes(k) for k in range(self.frames_total))
                self._write(b"[Muca] Initialized\r\n[Muca] Set TEST mode\r\n" + stream)
                return
            self._write(b"[Muca] Initialized\r\n[Muca] Set TEST mode\r\n")
            start = time.monotonic()
            k = 0
            while not self._stop.is_set() and (self.frames_total is None or k < self.frames_total):
                data = self._frame_bytes(k)
                if not self.fast:
                    delay = start + k / self.rate_hz - time.monotonic()
                    if delay > 0:
                        self._stop.wait(delay)
                self._write(data)
                k += 1
        except OSError:
            pass  # the reader side went away
        finally:
            self.done.set()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        if isinstance(self._thread, multiprocessing.process.BaseProcess) and self._thread.is_alive():
            self._thread.kill()  # blocked writing into a pty nobody reads any more
            self._thread.join()
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


def frames_through_pty(
    board: VirtualBoard,
    script: Script | None,
    fast: bool = True,
    frame_format: str = "ascii",
    frames: int | None = None,
    garbage_every: int = 0,
    record: str | Path | None = None,
    loop: bool = False,
    separate_process: bool = False,
    prerender: bool = False,
) -> Iterator[Frame]:
    """Run ``board`` on a pseudo-terminal and read it back with :class:`MucaReader` (the real serial
    path). Frames carry board time ``seq / rate_hz`` (s), so fast mode keeps the script's timing.
    Ends after the board's last frame (never with ``loop``); the script's labels go into the recording."""
    simulator = PtyBoard(board, script, frame_format=frame_format, fast=fast, frames=frames,
                         garbage_every=garbage_every, loop=loop, separate_process=separate_process,
                         prerender=prerender)
    options = FrameOptions(flip_tx=board.params.flip_tx, flip_rx=board.params.flip_rx)
    # Open before the board starts: pyserial flushes the input queue when it opens a port.
    reader = MucaReader(simulator.port, frame_format=frame_format, options=options, record=record,
                        reconnect_timeout_s=0.0,
                        record_header={"timebase": "board", "rate_hz": board.params.rate_hz, "simulated": True})
    simulator.start()
    if reader.recorder is not None and script is not None:
        for t, label in script.labels:
            reader.recorder.label(label, t=t)
    stalled = threading.Event()

    def watchdog() -> None:
        # The reader blocks on the port: end it once the board is done and no frame came for 5 s
        # (only if frames were lost; normally the loop below stops at the board's last frame).
        seen, quiet = -1, 0
        while not stalled.wait(0.5):
            quiet = quiet + 1 if simulator.done.is_set() and reader_seq[0] == seen else 0
            if quiet >= 10:
                reader.close()
                return
            seen = reader_seq[0]

    reader_seq = [0]
    guard = threading.Thread(target=watchdog, daemon=True)
    guard.start()
    try:
        for frame in reader.frames():
            yield Frame(frame.values, frame.seq / board.params.rate_hz, frame.seq)
            reader_seq[0] = frame.seq + 1
            if simulator.frames_total is not None and reader_seq[0] >= simulator.frames_total:
                break
    finally:
        stalled.set()
        reader.close()
        simulator.stop()
        guard.join()
