"""The paper's sensing evaluation: SNR per location and 3D localization error over 15 locations x
10 presses, on a recording with ground-truth labels or on the simulator, scored strictly.

Protocol: press ``p`` (location ``i``, repetition ``r``) is a label
``{"gesture": "press", "location": i, "repetition": r, "point": [x, y, z], "t_end": t1}`` at time
``t0`` (the simulator writes them; a hardware session is scored with the list of touched
locations, :func:`load_protocol`). Locations: :mod:`.locations` (spread over the sensing surface by
default, or a user's file).

Strict scoring, per press (window ``[t0, t1 + rest_margin)``):

* the press's touch is the track of the *first* touch-down in its window; its error is the
  distance (mm, 3D) between that track's mean point over the settled frames ``[t0 + settle, t1)``
  and the label's point (no choosing of the touch nearest the truth);
* a press without a touch-down in its window is *missed*; one with other than exactly one
  touch-down counts in ``presses_without_one_touch_down``; every touch-down after the first in a
  window is a *ghost touch*;
* touch-downs farther than ``rest_margin`` from every press are *false touches at rest*.

SNR of a location, on baseline-removed deltas of the cell that responds most to it:
``signal = mean(touch) - mean(rest)``; ``snr_sigma = signal / std(rest)`` (the common HCI form) and
``snr_p2p = signal / peak-to-peak(rest)`` (the CapSense form).
"""
from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, Literal, TypeVar

import numpy as np
from pydantic import Field

from ...graph.errors import UserError
from ...graph.node import NodeParams
from ..data.sensing_map import SensingMap, load_sensing_map
from .calibration import CalibParams, Calibration, calibrate, calibration_targets, refine_targets
from .frames import Frame
from .locations import crossing_locations, load_locations, nearest_crossing_mm, spread_locations
from .processing import ProcessingParams, TouchProcessor
from .pty_board import LinkCutShort, frames_through_pty
from .recording import replay_frames
from .scripts import ScriptBuilder
from .virtual_board import BoardParams, VirtualBoard

log = logging.getLogger(__name__)
Result = TypeVar("Result")

PTY_ATTEMPTS = 3
"""Runs of a simulated session through the pseudo-terminal before a stream cut short is an error."""


class EvalParams(NodeParams):
    """Evaluation protocol settings (ms)."""

    locations: int = Field(15, ge=1, description="touch locations")
    repetitions: int = Field(10, ge=1, description="presses per location")
    press_ms: float = Field(500.0, gt=0, description="how long each press lasts")
    gap_ms: float = Field(700.0, gt=0, description="pause after each press")
    settle_ms: float = Field(100.0, ge=0, description="frames this soon after a press starts are not measured")
    rest_margin_ms: float = Field(300.0, ge=0, description="frames this close to a press are neither touch nor rest")
    location_rule: Literal["spread", "surrounded", "near"] = Field(
        "spread", description="where locations are: spread over the sensing surface, or near crossings (locations.py)")
    seed: int = 0


def press_steps(points: np.ndarray, params: EvalParams) -> list[dict[str, Any]]:
    """Press steps over ``points`` (mm), ``params.repetitions`` rounds of every location in order."""
    return [{"gesture": "press", "at": points[i].tolist(), "ms": params.press_ms, "gap_ms": params.gap_ms,
             "location": i, "repetition": r}
            for r in range(params.repetitions) for i in range(len(points))]


@dataclasses.dataclass(frozen=True)
class EvalReport:
    """Per-press errors and touch-down counts, per-location figures and counts of failures."""

    errors_mm: np.ndarray  # (presses,) nan for a missed press
    press_location: np.ndarray  # (presses,) int
    touch_downs: np.ndarray  # (presses,) touch-downs in each press window
    locations: tuple[dict[str, Any], ...]  # per location: point, error, nearest crossing, SNR, ...
    false_touches_at_rest: int
    frames: int
    choice: dict[str, Any] = dataclasses.field(default_factory=dict)  # how the locations were chosen

    def summary(self) -> dict[str, Any]:
        e = self.errors_mm[np.isfinite(self.errors_mm)]
        snr_sigma = np.array([loc["snr_sigma"] for loc in self.locations])
        snr_p2p = np.array([loc["snr_p2p"] for loc in self.locations])
        stats = {}
        if len(e):
            stats = {"localization_error_mm_mean": float(e.mean()), "localization_error_mm_median": float(np.median(e)),
                     "localization_error_mm_min": float(e.min()), "localization_error_mm_max": float(e.max()),
                     "localization_error_mm_std": float(e.std()), "localization_error_mm_rmse": float(np.sqrt(np.mean(e**2)))}
        return {**{k: round(v, 4) for k, v in stats.items()},
                "snr_mean": round(float(snr_sigma.mean()), 2), "snr_std": round(float(snr_sigma.std()), 2),
                "snr_p2p_mean": round(float(snr_p2p.mean()), 2), "snr_p2p_std": round(float(snr_p2p.std()), 2),
                "presses": int(len(self.errors_mm)), "locations": len(self.locations),
                "missed_presses": int(np.count_nonzero(self.touch_downs == 0)),
                "presses_without_one_touch_down": int(np.count_nonzero(self.touch_downs != 1)),
                "ghost_touches": int(np.maximum(self.touch_downs - 1, 0).sum()),
                "false_touches_at_rest": self.false_touches_at_rest,
                "missed_presses_by_nearest_crossing": self.missed_by_nearest_crossing(),
                "crossings_seen_min": min((loc["crossings_seen"] for loc in self.locations), default=0),
                "nearest_crossing_mm_max": max((loc["nearest_crossing_mm"] for loc in self.locations), default=0.0),
                "frames": self.frames, **self.choice}


    def missed_by_nearest_crossing(self) -> dict[str, int]:
        """Missed presses by how far their location lies from the nearest crossing (mm): a finger
        15 mm or more from every crossing may raise no crossing above the noise (a layout limit)."""
        bands = {"under_10_mm": (0.0, 10.0), "10_to_15_mm": (10.0, 15.0), "15_mm_or_more": (15.0, np.inf)}
        return {name: sum(loc["touch_downs"].count(0) for loc in self.locations
                          if low <= loc["nearest_crossing_mm"] < high) for name, (low, high) in bands.items()}


@dataclasses.dataclass
class _Presses:
    """Ground truth of the labelled presses and what the processing did during them."""

    starts: np.ndarray
    ends: np.ndarray
    truth: np.ndarray
    location: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.starts)
        self.sums, self.counts = np.zeros((n, 3)), np.zeros(n, dtype=np.int64)
        self.first_touch = np.full(n, -1)  # track id of the first touch-down of each press
        self.touch_downs = np.zeros(n, dtype=np.int64)

    @classmethod
    def of(cls, labels: list[tuple[float, dict[str, Any]]]) -> _Presses:
        presses = sorted(((t, label) for t, label in labels if label.get("gesture") == "press"), key=lambda p: p[0])
        if not presses:
            raise UserError("the recording holds no press labels: the evaluation needs {\"gesture\": \"press\", "
                            "\"location\": i, \"point\": [x, y, z], \"t_end\": t} labels (see sensing/evaluation.py)")
        return cls(np.array([t for t, _ in presses]), np.array([float(label["t_end"]) for _, label in presses]),
                   np.array([label["point"] for _, label in presses], dtype=np.float64),
                   np.array([int(label.get("location", k)) for k, (_, label) in enumerate(presses)]))


def evaluate(frames: Iterable[Frame], labels: list[tuple[float, dict[str, Any]]], processor: TouchProcessor,
             params: EvalParams = EvalParams()) -> EvalReport:
    """Run ``processor`` over ``frames`` and score it strictly against the press ``labels``."""
    presses = _Presses.of(labels)
    settle, margin = params.settle_ms / 1000, params.rest_margin_ms / 1000
    deltas, frame_press, rest = [], [], []
    false_touches = 0
    n_frames = 0
    for frame in frames:
        result = processor.process(frame.values, frame.t)
        n_frames += 1
        if not result.calibrated:
            continue
        t = frame.t
        # Labels sit on frame times; the epsilon keeps rounding in recordings from moving a boundary frame.
        window = np.flatnonzero((t >= presses.starts - 1e-6) & (t < presses.ends + margin - 1e-6))
        settled = np.flatnonzero((t >= presses.starts + settle - 1e-6) & (t < presses.ends - 1e-6))
        near = np.any((t >= presses.starts - margin) & (t < presses.ends + margin))
        deltas.append(result.delta)
        frame_press.append(int(settled[0]) if len(settled) else -1)
        rest.append(not near)
        for event in result.events:
            if event["type"] != "touch_down":
                continue
            if len(window):
                k = int(window[0])
                if presses.touch_downs[k] == 0:
                    presses.first_touch[k] = event["id"]
                presses.touch_downs[k] += 1
            elif not near:
                false_touches += 1
        if len(settled):
            k = int(settled[0])
            mine = [touch.point for touch in result.touches if touch.id == presses.first_touch[k]]
            if mine:
                presses.sums[k] += mine[0]
                presses.counts[k] += 1
    errors = np.full(len(presses.starts), np.nan)
    seen = presses.counts > 0
    errors[seen] = np.linalg.norm(presses.sums[seen] / presses.counts[seen, None] - presses.truth[seen], axis=1)
    per_location = _per_location(processor, presses, errors, np.array(deltas), np.array(frame_press),
                                 np.array(rest, dtype=bool))
    return EvalReport(errors, presses.location, presses.touch_downs, per_location, false_touches, n_frames)


def _per_location(processor: TouchProcessor, presses: _Presses, errors: np.ndarray, deltas: np.ndarray,
                  frame_press: np.ndarray, rest: np.ndarray) -> tuple[dict[str, Any], ...]:
    """Per location: its point, errors (mean, max), nearest crossing, SNR (sigma and p2p forms) of
    the cell that responds most, crossings that see it, touch-down counts."""
    out = []
    for i in np.unique(presses.location):
        own = presses.location == i
        touch_frames = np.isin(frame_press, np.flatnonzero(own))
        if not touch_frames.any() or not rest.any():
            continue
        mean_touch = deltas[touch_frames].mean(axis=0)
        cell = int(np.argmax(mean_touch))
        rest_values = deltas[rest, cell]
        signal = float(mean_touch[cell] - rest_values.mean())
        rest_sigma = np.maximum(deltas[rest].std(axis=0), 1e-9)
        point = presses.truth[own][0]
        found = np.isfinite(errors[own])
        out.append({
            "location": int(i), "point": point.round(3).tolist(),
            "nearest_crossing_mm": round(float(nearest_crossing_mm(processor.map, point)[0]), 2), "cell": cell,
            "crossings_seen": int(np.count_nonzero(mean_touch - deltas[rest].mean(axis=0) > 6.0 * rest_sigma)),
            "signal_counts": round(signal, 2),
            "snr_sigma": round(signal / max(float(rest_values.std()), 1e-9), 2),
            "snr_p2p": round(signal / max(float(np.ptp(rest_values)), 1e-9), 2),
            "error_mm_mean": round(float(np.mean(errors[own][found])), 4) if found.any() else None,
            "error_mm_max": round(float(np.max(errors[own][found])), 4) if found.any() else None,
            "touch_downs": presses.touch_downs[own].tolist(),
        })
    return tuple(out)


def rerun_if_cut_short(session: Callable[[VirtualBoard], Result], board: VirtualBoard) -> Result:
    """``session(board)``, a simulated session read through a new pseudo-terminal, run again on a new
    board like it (the virtual board is deterministic) when the reader lost the port before the last
    frame, at most :data:`PTY_ATTEMPTS` times; then a one-line error."""
    for attempt in range(1, PTY_ATTEMPTS + 1):
        try:
            return session(board if attempt == 1 else VirtualBoard(board.map, board.params))
        except LinkCutShort as exc:
            if attempt == PTY_ATTEMPTS:
                raise UserError(f"{exc}, {PTY_ATTEMPTS} times: the machine is too busy for the pseudo-terminal; "
                                "rerun when it is quieter") from None
            log.warning("%s: running the simulated session again (%d of %d)", exc, attempt + 1, PTY_ATTEMPTS)
    raise AssertionError("unreachable")


def calibrate_simulator(sensing_map: SensingMap, board_params: BoardParams, params: CalibParams = CalibParams(),
                        seed: int = 0, prompt=lambda text: None, **session: Any) -> tuple[Calibration, dict[str, Any]]:
    """``sense --calibrate`` on the virtual board: a simulated operator touches each prompted crossing
    where it really is on the board (the crossings of a hand-laid sensor sit off the map) with an aim
    error of up to 1.5 mm, 0.9 s per touch and 0.6 s between touches, in the order prompted;
    ``session`` goes to :func:`.calibration.calibrate` (processor, on_result). The operator's script is
    written before the session runs, so the crossings the session prompts again after the rounds
    (:func:`.calibration.refine_targets`) come from a first, silent run of the rounds alone: the board
    is deterministic, so the session finds the same ones. Through the pseudo-terminal, rerun when the
    stream is cut short (:func:`rerun_if_cut_short`)."""
    rng = np.random.default_rng([seed, 7])
    board = VirtualBoard(sensing_map, board_params)

    def touches(targets: np.ndarray, first: int) -> list[dict[str, Any]]:
        steps = []
        for k, cell in enumerate(targets.tolist(), start=first):
            normal = sensing_map.cell_normals[cell]
            aim = rng.normal(size=3)
            aim -= aim @ normal * normal
            aim *= 1.5 * np.sqrt(rng.random()) / np.linalg.norm(aim)
            steps.append({"gesture": "press", "at": (board.cell_points[cell] + aim).tolist(), "ms": 900, "gap_ms": 600,
                          "calibration_touch": k})
        return steps

    def run(steps: list[dict[str, Any]], run_params: CalibParams, quiet: bool,
            unused: VirtualBoard) -> tuple[Calibration, dict[str, Any]]:
        """The session over ``steps`` on ``unused`` (a board that has made no frame yet)."""
        script = ScriptBuilder(sensing_map, board_params, seed).build(steps)
        options = {} if quiet else session

        def run_once(fresh: VirtualBoard) -> tuple[Calibration, dict[str, Any]]:
            if options.get("processor") is not None:
                options["processor"].reset()  # a run cut short left its baseline and tracks
            return calibrate(frames_through_pty(fresh, script, fast=True), sensing_map, run_params,
                             (lambda text: None) if quiet else prompt, **options)

        return rerun_if_cut_short(run_once, unused)

    steps = touches(calibration_targets(sensing_map, params.rounds), 0)
    if params.locate_crossings and params.refine_share > 0:
        rounds_only, _ = run(steps, params.model_copy(update={"refine_share": 0.0}), True, board)
        again = refine_targets(sensing_map, rounds_only, params)
        steps += touches(again, len(steps))
        calibration, seen = run(steps, params, False, VirtualBoard(sensing_map, board_params))  # frames from the start
        if seen["refined"] != np.unique(again).tolist():
            raise AssertionError("the simulated session prompted other crossings again than its silent first run")
        return calibration, seen
    return run(steps, params, False, board)


def evaluate_simulator(
    sensing_map_path: str | Path,
    board_params: BoardParams = BoardParams(),
    eval_params: EvalParams = EvalParams(),
    processing_params: ProcessingParams = ProcessingParams(),
    through_pty: bool = True,
    record: str | Path | None = None,
    locations: str | Path | None = None,
    calibration: Calibration | None = None,
) -> EvalReport:
    """The protocol on the virtual board, read back through a pseudo-terminal in fast mode (or fed to
    the processor directly when ``through_pty`` is False); ``locations`` a user's JSON list of points
    (:func:`.locations.load_locations`) instead of ``eval_params.location_rule``'s; ``calibration``
    (:mod:`.calibration`) replaces the processing's default assumptions. Through the pseudo-terminal,
    rerun when the stream is cut short (:func:`rerun_if_cut_short`)."""
    sensing_map = load_sensing_map(sensing_map_path)
    if locations is not None:
        points, choice = load_locations(locations, sensing_map), {"location_rule": f"file {locations}"}
    elif eval_params.location_rule == "spread":
        points, choice = spread_locations(sensing_map, eval_params.locations, eval_params.seed), {"location_rule": "spread"}
    else:
        points, choice = crossing_locations(sensing_map, eval_params.locations, eval_params.location_rule,
                                            eval_params.seed, board_params)
    script = ScriptBuilder(sensing_map, board_params, eval_params.seed).build(press_steps(points, eval_params))

    def session(frames: Iterable[Frame]) -> EvalReport:
        processor = (TouchProcessor(sensing_map, processing_params) if calibration is None
                     else calibration.processor(sensing_map, processing_params))
        return dataclasses.replace(evaluate(frames, list(script.labels), processor, eval_params), choice=choice)

    board = VirtualBoard(sensing_map, board_params)
    if through_pty:
        return rerun_if_cut_short(
            lambda fresh: session(frames_through_pty(fresh, script, fast=True, record=record)), board)
    total = int(np.ceil(script.duration * board_params.rate_hz))
    return session(Frame(board.frame(k / board_params.rate_hz, script.fingers_at(k / board_params.rate_hz)),
                         k / board_params.rate_hz, k) for k in range(total))


def load_protocol(path: str | Path) -> tuple[np.ndarray, int]:
    """``{"points": [[x, y, z], ...], "repetitions": 10}`` or a plain list of points (10 repetitions)
    (mm): the marked locations of a hardware session, touched in rounds (every location once per
    round, in list order)."""
    path = Path(path)
    example = "write {\"points\": [[x, y, z], ...], \"repetitions\": 10} or a list of points"
    if not path.is_file():
        raise UserError(f"protocol file {path} not found: {example}")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        doc = {"points": doc} if isinstance(doc, list) else doc
        points = np.array(doc["points"], dtype=np.float64).reshape(-1, 3)
        repetitions = int(doc.get("repetitions", 10))
    except (UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError, ValueError, AttributeError) as exc:
        raise UserError(f"protocol file {path} is malformed ({type(exc).__name__}): {example}") from None
    return points, repetitions


def labels_from_presses(frames: list[Frame], processor: TouchProcessor, points: np.ndarray,
                        repetitions: int) -> list[tuple[float, dict[str, Any]]]:
    """Press labels for an unlabelled hardware session: the detected single-finger presses, in
    order, are the protocol's presses (round by round over ``points``). Needs exactly
    ``len(points) x repetitions`` presses; the processor is reset afterwards."""
    presses: list[list[float]] = []
    open_ids: dict[int, float] = {}
    for frame in frames:
        for event in processor.process(frame.values, frame.t).events:
            if event["type"] == "touch_down":
                open_ids[event["id"]] = event["t"]
            elif event["type"] == "touch_up" and event["id"] in open_ids:
                presses.append([open_ids.pop(event["id"]), event["t"]])
    processor.reset()
    expected = len(points) * repetitions
    if len(presses) != expected:
        raise UserError(f"found {len(presses)} presses but the protocol has {len(points)} locations x "
                        f"{repetitions} repetitions = {expected}: record the session again or fix the protocol file")
    return [(t0, {"gesture": "press", "location": k % len(points), "repetition": k // len(points),
                  "point": points[k % len(points)].tolist(), "t_end": t1})
            for k, (t0, t1) in enumerate(presses)]


def evaluate_recording(recording: str | Path, sensing_map_path: str | Path,
                       eval_params: EvalParams = EvalParams(),
                       processing_params: ProcessingParams = ProcessingParams(),
                       protocol: str | Path | None = None, calibration: Calibration | None = None) -> EvalReport:
    """The protocol scored on a recording: its press labels (simulator recordings carry them), or,
    with ``protocol`` (see :func:`load_protocol`), presses detected in an unlabelled hardware session.
    With detected presses, ``missed_presses`` is 0 by construction (a miss shows as a count error)."""
    labels: list[tuple[float, dict[str, Any]]] = []
    sensing_map = load_sensing_map(sensing_map_path)
    processor = (TouchProcessor(sensing_map, processing_params) if calibration is None
                 else calibration.processor(sensing_map, processing_params))
    frames = list(replay_frames(recording, on_label=lambda t, label: labels.append((t, label))))
    if protocol is not None:
        points, repetitions = load_protocol(protocol)
        labels = labels_from_presses(frames, processor, points, repetitions)
    return evaluate(frames, labels, processor, eval_params)
