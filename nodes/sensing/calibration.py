"""Calibration a user runs on the real board: ``retrotouch sense --calibrate`` prompts the operator to
touch every crossing of the layout (in Tx/Rx order, ``CalibParams.rounds`` rounds), and from the
touches estimates what the processing otherwise assumes:

* **per-cell gains** ``g_i``: the mean delta of crossing ``i`` while the finger rests on it, relative
  to the median over padded crossings (a padded crossing's gain is 1 in the coupling model);
  touch-to-touch strength varies, so the rounds are averaged;
* **the no-pad gain**: the median gain of the crossings without a pad (for crossings not measured);
* **a finger's amplitude**: the touched crossing's delta over its gain, per touch, as the prior the
  processing's fits start from (:func:`.coupling_fit.amplitude_prior`; the processing learns it from
  well-posed touches too, but only after many of them): it tells one finger between two crossings
  far apart, which raises a peak at each, from two fingers from the first touches on;
* **the finger coupling width** ``s``: from each touch, the gain-normalised delta of crossings
  ``0.5..2.5`` pitches away relative to the touched one's, ``r = K(d)``, gives
  ``s = d / sqrt(-2 ln r)`` for a Gaussian ``K``; the median over all pairs gives the finger
  radius by ``s = sqrt(r_f^2 + (pitch/2)^2)``, and without ``locate_crossings`` it is the width the
  processing starts from (a Gaussian whose width and shape it learns further from touches).

The operator touches the crossings as they are on the object (where the traces cross), never the
evaluation's locations. A touch that stays down for ``min_frames`` frames after ``settle_ms`` counts,
when it lifts, for the crossing it is prompted for when the processing puts its mean point within
``1.2`` pitches of that crossing (a hand-laid crossing sits 1-3 mm off the map, and the processing
does not know the board yet, so a tighter reach turns away most touches of a layout whose median
pitch is small), else for the nearest of the next three within that reach (the operator skipped
some), else for the one of them that was its peak crossing most often (at a layout's edge the
uncalibrated processing can put a touch on a crossing 10 mm off). The prompted crossing comes
first, not the nearest: the uncalibrated point can sit nearer the next crossing than the touched
one (two crossings a few mm apart, one without a pad reading less than assumed), and a touch
counted for the next crossing gives it the touched one's deltas (a wrong gain and position) and
turns away the touch that follows.

* **where each crossing really is** (``locate_crossings``): :mod:`.crossing_positions` fits every
  crossing's position on the surface, with its gain and the coupling profile, to all touches; the
  processing then uses these points instead of the map's (the gains stay the ratios above), and
  that fitted profile (width and tail, :func:`.coupling_profile.student_profile`) as its coupling,
  kept as measured (no online width or shape learning: the calibration fits it to every touch at
  known crossings, the online learning to touches whose positions it estimates itself).
* **touching again where it pays** (``refine_share``, ``refine_rounds``): after the rounds, a first
  estimate says how certain each crossing's fitted position is (:mod:`.crossing_positions`); the
  ``refine_share`` of the measured crossings whose position is least certain (where crossings are
  sparse, what the touches around them pin least) are prompted ``refine_rounds`` more times, then
  everything is estimated from all touches. A crossing's position error weighs most where a finger
  sits far from the crossings: there the fit must place it from a few crossings' faint readings.

The result is a versioned JSON file (``CALIBRATION_FORMAT``) tied to the layout's crossings, loaded by
``sense --calibration FILE``.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import Field

from ...graph.errors import UserError
from ...graph.node import NodeParams
from ..data.board import default_coupling_width_mm
from ..data.sensing_map import SensingMap
from .coupling_fit import amplitude_prior
from .crossing_positions import locate_crossings, relocated_map
from .processing import FrameResult, ProcessingParams, TouchProcessor

CALIBRATION_FORMAT = "retrotouch.sensing_calibration/1"
SKIP_AHEAD = 3  # a touch may count for one of the next crossings this many targets ahead


class CalibParams(NodeParams):
    """Calibration protocol settings (ms, pitches)."""

    rounds: int = Field(2, ge=1, description="touches per crossing")
    settle_ms: float = Field(150.0, ge=0, description="frames this soon after a touch-down are not used")
    min_frames: int = Field(3, ge=1, description="frames a touch must last after settling to count")
    reach_pitch: float = Field(1.2, gt=0, description="a touch counts for a crossing within this many pitches")
    width_snr: float = Field(6.0, gt=0, description="a neighbour enters the width estimate above this many noise sigmas")
    locate_crossings: bool = Field(True, description="estimate where each crossing really is (crossing_positions.py)")
    refine_share: float = Field(0.2, ge=0, le=1, description="share of the crossings touched again after the rounds: "
                                "those whose fitted position is least certain (with locate_crossings; 0: none)")
    refine_rounds: int = Field(2, ge=1, description="touches per crossing touched again")


def layout_key(sensing_map: SensingMap) -> str:
    """sha256 of the crossings (channels, points to 0.01 mm): a calibration belongs to one layout."""
    digest = hashlib.sha256()
    for array in (sensing_map.cell_tx, sensing_map.cell_rx, np.round(sensing_map.cell_points, 2)):
        digest.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())
    return digest.hexdigest()


@dataclasses.dataclass(frozen=True)
class Calibration:
    """What a calibration measured (gains relative to a padded crossing, mm)."""

    cell_gain: np.ndarray  # (K,)
    measured: np.ndarray  # (K,) bool, crossings whose gain was measured (the others: pad ? 1 : no_pad_gain)
    no_pad_gain: float
    coupling_sigma_mm: float  # the profile's width
    finger_radius_mm: float
    touches: int
    layout: str  # layout_key of the sensing map
    cell_points: np.ndarray | None = None  # (K, 3) mm, where the crossings really are (None: the map's)
    map_points: np.ndarray | None = None  # (K, 3) mm, the map's crossings (to report how far they moved)
    coupling_tail: float | None = None  # the profile's tail (None: a Gaussian, learned further online)
    finger_amplitude: tuple[float, float] | None = None  # (log counts, spread) at a padded crossing (None: learned online)
    position_std_mm: np.ndarray | None = None  # (K,) how certain each fitted point is (None: not located)

    def processor(self, sensing_map: SensingMap, params: ProcessingParams = ProcessingParams()) -> TouchProcessor:
        """A touch processor that uses this calibration instead of the default assumptions."""
        if layout_key(sensing_map) != self.layout:
            raise UserError(f"the calibration was made for another layout than {sensing_map.source}: "
                            "run `retrotouch sense --calibrate` on this layout")
        tuned = params.model_copy(update={
            "no_pad_gain": self.no_pad_gain, "coupling_sigma_mm": self.coupling_sigma_mm,
            "finger_radius_mm": self.finger_radius_mm, "coupling_tail": self.coupling_tail,
            "amplitude_prior": self.finger_amplitude,
            "adapt_coupling": params.adapt_coupling and self.coupling_tail is None})  # a measured profile is kept
        if self.cell_points is not None:
            sensing_map = relocated_map(sensing_map, self.cell_points)
        return TouchProcessor(sensing_map, tuned, cell_gain=self.cell_gain)

    def summary(self) -> dict[str, Any]:
        gains = self.cell_gain[self.measured]
        moved = (None if self.cell_points is None or self.map_points is None
                 else np.linalg.norm(self.cell_points - self.map_points, axis=1))
        return {"touches": self.touches, "crossings_measured": int(self.measured.sum()),
                "crossings_moved_mm_median": None if moved is None else round(float(np.median(moved)), 3),
                "crossings_moved_mm_max": None if moved is None else round(float(np.max(moved)), 3),
                "position_std_mm_median": None if self.position_std_mm is None else round(float(np.median(self.position_std_mm)), 3),
                "position_std_mm_max": None if self.position_std_mm is None else round(float(np.max(self.position_std_mm)), 3),
                "no_pad_gain": round(self.no_pad_gain, 4), "coupling_sigma_mm": round(self.coupling_sigma_mm, 3),
                "coupling_tail": None if self.coupling_tail is None else round(self.coupling_tail, 4),
                "finger_amplitude": None if self.finger_amplitude is None else [round(v, 5) for v in self.finger_amplitude],
                "finger_radius_mm": round(self.finger_radius_mm, 3),
                "cell_gain_spread": round(float(np.std(np.log(gains))), 4) if len(gains) > 1 else None}

    def save(self, path: str | Path) -> None:
        doc = {"format": CALIBRATION_FORMAT, "layout": self.layout, "units": "mm", **self.summary(),
               "cell_gain": [round(float(g), 5) for g in self.cell_gain], "measured": self.measured.tolist(),
               "cell_points": None if self.cell_points is None else np.round(self.cell_points, 4).tolist(),
               "map_points": None if self.map_points is None else np.round(self.map_points, 4).tolist(),
               "position_std_mm": None if self.position_std_mm is None else np.round(self.position_std_mm, 4).tolist()}
        Path(path).write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")


def load_calibration(path: str | Path) -> Calibration:
    """A calibration file -> :class:`Calibration`; one-line UserError when missing or foreign."""
    path = Path(path)
    fix = "write one with `retrotouch sense --calibrate --calibration FILE`"
    if not path.is_file():
        raise UserError(f"calibration file {path} not found: {fix}")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        if doc.get("format") != CALIBRATION_FORMAT:
            raise UserError(f"calibration file {path} has format {doc.get('format')!r}, expected "
                            f"{CALIBRATION_FORMAT!r}: {fix}")
        gains, measured = np.array(doc["cell_gain"], dtype=np.float64), np.array(doc["measured"], dtype=bool)
        if gains.shape != measured.shape or not np.all(np.isfinite(gains) & (gains > 0)):
            raise ValueError("cell_gain")
        points, map_points = (None if doc.get(key) is None else np.array(doc[key], dtype=np.float64).reshape(-1, 3)
                              for key in ("cell_points", "map_points"))
        if points is not None and (len(points) != len(gains) or not np.all(np.isfinite(points))):
            raise ValueError("cell_points")
        spread = None if doc.get("position_std_mm") is None else np.array(doc["position_std_mm"], dtype=np.float64)
        if spread is not None and (spread.shape != gains.shape or not np.all(np.isfinite(spread) & (spread >= 0))):
            raise ValueError("position_std_mm")
        tail = doc.get("coupling_tail")
        if tail is not None and not float(tail) > 0:
            raise ValueError("coupling_tail")
        amplitude = doc.get("finger_amplitude")
        if amplitude is not None:  # the processing's own check (two numbers, a positive spread); ValidationError is a ValueError
            amplitude = ProcessingParams(amplitude_prior=amplitude).amplitude_prior
        return Calibration(gains, measured, float(doc["no_pad_gain"]), float(doc["coupling_sigma_mm"]),
                           float(doc["finger_radius_mm"]), int(doc["touches"]), str(doc["layout"]), points, map_points,
                           None if tail is None else float(tail), amplitude, spread)
    except (UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError, ValueError, AttributeError) as exc:
        raise UserError(f"calibration file {path} is malformed ({type(exc).__name__}): {fix}") from None


def calibration_targets(sensing_map: SensingMap, rounds: int) -> np.ndarray:
    """The crossings the operator is asked to touch, in order: every crossing by Tx then Rx channel,
    ``rounds`` times."""
    order = np.lexsort((sensing_map.cell_rx, sensing_map.cell_tx))
    return np.tile(order, rounds)


def refine_targets(sensing_map: SensingMap, calibration: Calibration, params: CalibParams) -> np.ndarray:
    """The crossings to touch again (module docstring): the ``refine_share`` of the measured ones whose
    fitted position is least certain, by Tx then Rx channel, ``refine_rounds`` times; none without
    located crossings."""
    spread = calibration.position_std_mm
    count = int(np.ceil(params.refine_share * np.count_nonzero(calibration.measured)))
    if spread is None or count == 0:
        return np.zeros(0, dtype=np.int64)
    measured = np.flatnonzero(calibration.measured)
    chosen = measured[np.argsort(-spread[measured], kind="stable")[:count]]
    chosen = chosen[np.lexsort((sensing_map.cell_rx[chosen], sensing_map.cell_tx[chosen]))]
    return np.tile(chosen, params.refine_rounds)


def describe_target(sensing_map: SensingMap, cell: int) -> str:
    """How the operator finds a crossing: its channels and position (mm)."""
    point = ", ".join(f"{x:.1f}" for x in sensing_map.cell_points[cell])
    return f"crossing Tx{int(sensing_map.cell_tx[cell]):02d} x Rx{int(sensing_map.cell_rx[cell]):02d} at ({point}) mm"


class CalibrationSession:
    """Follows the operator through the targets: feed it every frame's result; it prompts (through
    ``prompt``) for the next crossing and keeps, per accepted touch, the crossing and its mean deltas."""

    def __init__(self, sensing_map: SensingMap, params: CalibParams = CalibParams(),
                 prompt: Callable[[str], None] = lambda text: None):
        self.map, self.params, self.prompt = sensing_map, params, prompt
        self.targets = calibration_targets(sensing_map, params.rounds)
        self.reach = params.reach_pitch * sensing_map.pitch_mm()
        self.records: list[tuple[int, np.ndarray]] = []  # (crossing, mean delta (K,) counts)
        self.next = 0  # index into targets
        self.skipped = 0
        self._touch: tuple[int, float] | None = None  # (touch id, touch-down t)
        self._sum, self._point_sum, self._peaks, self._frames = np.zeros(sensing_map.cell_count), np.zeros(3), [], 0
        self._prompt_next()

    @property
    def done(self) -> bool:
        return self.next >= len(self.targets)

    def extend(self, targets: np.ndarray) -> None:
        """Prompt these crossings after the targets so far (the session goes on)."""
        was_done = self.done
        self.targets = np.concatenate([self.targets, np.asarray(targets, dtype=np.int64)])
        if was_done and not self.done:
            self._prompt_next()

    def _prompt_next(self) -> None:
        if not self.done:
            cell = int(self.targets[self.next])
            self.prompt(f"touch {describe_target(self.map, cell)} ({self.next + 1} of {len(self.targets)}), "
                        "hold it for a second, lift")

    def feed(self, result: FrameResult) -> None:
        if self.done or not result.calibrated:
            return
        if self._touch is None:
            self._start(result)
            return
        touch_id, t_down = self._touch
        mine = [touch for touch in result.touches if touch.id == touch_id]
        if mine:
            if result.t - t_down >= self.params.settle_ms / 1000:
                self._sum += result.delta
                self._point_sum += mine[0].point
                self._peaks.append(mine[0].peak_cell)
                self._frames += 1
            return
        if self._frames < self.params.min_frames:
            self.prompt("that touch was too short: touch the same crossing again and hold it")
        else:
            index = self._target(self._point_sum / self._frames, self._peaks)
            if index is None:
                self.prompt("that touch was not on the prompted crossing: touch it again and hold it")
            else:
                self.records.append((int(self.targets[index]), self._sum / self._frames))
                self.skipped += index - self.next
                self.next = index + 1
                self._prompt_next()
        self._touch, self._sum, self._point_sum, self._peaks = None, np.zeros(self.map.cell_count), np.zeros(3), []
        self._frames = 0

    def _start(self, result: FrameResult) -> None:
        """A touch-down starts a candidate calibration touch (its target is decided when it lifts)."""
        for event in result.events:
            if event["type"] == "touch_down":
                self._touch = (event["id"], result.t)
                return

    def _target(self, point: np.ndarray, peaks: list[int]) -> int | None:
        """Index into the targets of the crossing a settled touch was on: the prompted one if the
        touch's mean point (mm) is within reach of it, else the nearest of the next few within
        reach, else the one that was the touch's peak crossing most often (the processing does not
        know the board yet and may place a touch at the layout's edge far off); None when neither."""
        ahead = self.targets[self.next:self.next + 1 + SKIP_AHEAD]
        distance = np.linalg.norm(self.map.cell_points[ahead] - point, axis=1)
        if distance[0] <= self.reach:
            return self.next
        if distance.min() <= self.reach:
            return self.next + int(np.argmin(distance))
        peak = int(np.bincount(peaks).argmax())
        hits = np.flatnonzero(ahead == peak)
        return self.next + int(hits[0]) if len(hits) else None


def estimate(sensing_map: SensingMap, records: list[tuple[int, np.ndarray]], sigma: np.ndarray,
             params: CalibParams = CalibParams(), defaults: ProcessingParams = ProcessingParams()) -> Calibration:
    """Gains, no-pad gain and coupling width from the accepted touches (see the module docstring);
    ``sigma`` (K,) the noise sigma per crossing (counts)."""
    if not records:
        raise UserError("no calibration touch was recognised: touch each prompted crossing and hold it for a second")
    k, pad = sensing_map.cell_count, sensing_map.cell_pad
    sums, counts = np.zeros(k), np.zeros(k)
    for cell, delta in records:
        sums[cell] += max(delta[cell], 1e-9)
        counts[cell] += 1
    measured = counts > 0
    raw = np.where(measured, sums / np.maximum(counts, 1), np.nan)
    reference = raw[measured & pad] if np.any(measured & pad) else raw[measured]
    gain = raw / float(np.median(reference))
    no_pad = float(np.median(gain[measured & ~pad])) if np.any(measured & ~pad) else defaults.no_pad_gain
    gain = np.where(measured, gain, np.where(pad, 1.0, no_pad))
    pitch = sensing_map.pitch_mm()
    widths = []
    for cell, delta in records:
        distance = np.linalg.norm(sensing_map.cell_points - sensing_map.cell_points[cell], axis=1)
        ratio = (delta / gain) / (delta[cell] / gain[cell])
        use = ((distance >= 0.5 * pitch) & (distance <= 2.5 * pitch) & (delta > params.width_snr * sigma)
               & (ratio > 0.02) & (ratio < 0.98))
        widths.extend((distance[use] / np.sqrt(-2.0 * np.log(ratio[use]))).tolist())
    if widths:
        width = float(np.median(widths))
        radius = float(np.sqrt(max(width**2 - (pitch / 2) ** 2, (0.3 * pitch) ** 2)))
    else:
        width, radius = None, defaults.finger_radius_mm
    width = width or default_coupling_width_mm(radius, pitch)
    points, tail, spread = None, None, None
    if params.locate_crossings:
        located = locate_crossings(sensing_map, records, sigma, gain, width)
        points, width, tail, spread = located.points, located.width_mm, located.tail, located.position_std_mm
    amplitude = amplitude_prior(np.log([max(delta[cell], 1e-9) / gain[cell] for cell, delta in records]))
    return Calibration(gain, measured, no_pad, width, radius, len(records), layout_key(sensing_map), points,
                       sensing_map.cell_points.copy(), tail, amplitude, spread)


def calibrate(frames: Iterable[Any], sensing_map: SensingMap, params: CalibParams = CalibParams(),
              prompt: Callable[[str], None] = lambda text: None, processor: TouchProcessor | None = None,
              on_result: Callable[[FrameResult], None] | None = None) -> tuple[Calibration, dict[str, Any]]:
    """Run a guided session over ``frames`` (until every target is touched, the refined ones too, or the
    frames end) with ``processor`` (default processing; ``on_result`` sees each frame's result, e.g. a
    live view), then estimate; returns the calibration and what the session saw (``refined``: the
    crossings prompted again, :func:`refine_targets`, ascending)."""
    processor = processor or TouchProcessor(sensing_map)
    session = CalibrationSession(sensing_map, params, prompt)
    refined = np.zeros(0, dtype=np.int64)
    refining = params.locate_crossings and params.refine_share > 0
    count = 0
    start = None
    for frame in frames:
        start = frame.t if start is None else start
        result = processor.process(frame.values, frame.t - start)
        session.feed(result)
        if on_result is not None:
            on_result(result)
        count += 1
        if session.done and refining and session.records:
            refining = False
            refined = refine_targets(sensing_map, estimate(sensing_map, session.records, processor.sigma(), params), params)
            if len(refined):
                prompt(f"{len(refined) // params.refine_rounds} crossings are touched again: their positions are the "
                       "least certain")
                session.extend(refined)
        if session.done:
            break
    calibration = estimate(sensing_map, session.records, processor.sigma(), params)
    return calibration, {"frames": count, "targets": len(session.targets), "accepted": len(session.records),
                         "skipped": session.skipped, "refined": np.unique(refined).tolist()}
