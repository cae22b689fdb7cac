"""The paper's sensing evaluation: SNR per location and 3D localization error over 15 locations x
10 repetitions, on a recording with ground-truth labels or on the simulator.

Protocol: press ``p`` (location ``i``, repetition ``r``) is a label
``{"gesture": "press", "location": i, "repetition": r, "point": [x, y, z], "t_end": t1}`` at time
``t0`` (the simulator writes them; for hardware, insert them into the recording while touching the
marked locations). Frames in ``[t0 + settle, t1)`` are touch frames; frames farther than
``rest_margin`` from every press are rest frames.

* Localization error of a press: distance (mm, 3D) between the mean reported touch point over its
  touch frames (the touch nearest the truth in each frame) and the label's point.
* SNR of a location, on baseline-removed deltas of the cell that responds most to it:
  ``signal = mean(touch) - mean(rest)``; ``snr_sigma = signal / std(rest)`` (the common HCI form)
  and ``snr_p2p = signal / peak-to-peak(rest)`` (the CapSense form).
* False touches: touch-downs outside every press window (+ margin); missed presses: presses with
  no touch in their touch frames.

A hardware session needs no hand-made labels: record it while touching the marked locations round
by round, then score it with a protocol file listing the locations (:func:`load_protocol`); the
detected presses are matched to the protocol in order.
"""
from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field
from scipy.spatial import Delaunay, QhullError

from ...graph.errors import UserError
from ...graph.node import NodeParams
from ..data.board import default_coupling_width_mm
from ..data.sensing_map import SensingMap, load_sensing_map
from ..geometry.surface import SurfaceProjector, farthest_point_sampling
from .frames import Frame
from .processing import ProcessingParams, TouchProcessor
from .pty_board import frames_through_pty
from .recording import replay_frames
from .scripts import ScriptBuilder
from .virtual_board import BoardParams, VirtualBoard


class EvalParams(NodeParams):
    """Evaluation protocol settings (ms)."""

    locations: int = Field(15, ge=1, description="touch locations")
    repetitions: int = Field(10, ge=1, description="presses per location")
    press_ms: float = Field(500.0, gt=0, description="how long each press lasts")
    gap_ms: float = Field(700.0, gt=0, description="pause after each press")
    settle_ms: float = Field(100.0, ge=0, description="frames this soon after a press starts are not measured")
    rest_margin_ms: float = Field(300.0, ge=0, description="frames this close to a press are neither touch nor rest")
    location_rule: Literal["surrounded", "near"] = Field(
        "surrounded", description="where locations may be: surrounded by crossings, or anywhere near one (evaluation_locations)")
    seed: int = 0


def surrounded(sensing_map: SensingMap, points: np.ndarray, reach: float) -> np.ndarray:
    """Whether each surface point (n, 3) lies inside the convex hull, in its tangent plane, of the
    crossings within ``reach`` (mm) of it (at least three, not all collinear)."""
    projector = SurfaceProjector(sensing_map.vertices, sensing_map.faces)
    _, faces, _ = projector.project(points)
    inside = np.zeros(len(points), dtype=bool)
    for k, (point, face) in enumerate(zip(points, faces)):
        near = np.linalg.norm(sensing_map.cell_points - point, axis=1) <= reach
        if np.count_nonzero(near) < 3:
            continue
        planar = (sensing_map.cell_points[near] - point) @ projector.face_frames[face][:2].T
        try:
            inside[k] = Delaunay(planar).find_simplex(np.zeros(2)) >= 0
        except QhullError:  # all collinear (or coincident): nothing is enclosed
            continue
    return inside


def evaluation_locations(sensing_map: SensingMap, params: EvalParams = EvalParams(),
                         board_params: BoardParams = BoardParams()) -> tuple[np.ndarray, dict[str, Any]]:
    """The protocol's touch locations (``params.locations``, mm) and how they were chosen.

    Candidates: ``20 x locations`` random points of the sensed region (within 0.8 pitch of a
    crossing, around crossings with at least the median number of neighbours;
    :meth:`ScriptBuilder.location`). Rule ``"surrounded"`` (default) keeps the candidates inside the
    tangent-plane convex hull of the crossings within two coupling widths ``2 s`` (``s`` the board's
    finger coupling width): there a nominal finger reaches crossings on at least three sides with
    >= exp(-2) = 13.5 % of its peak signal, so both tangent directions are measured, which is what
    "a location on the instrumented surface" means on hardware (the paper touched 15 such
    locations). Rule ``"near"`` keeps every candidate, including spots in gaps of a sparse layout
    where only one or two crossings see the finger (one direction then rests on the fit's priors).
    Either way the fraction of candidates the rule keeps is reported (``surrounded_fraction``), so a
    layout that leaves much of its sensed region unsurrounded shows it; farthest-point sampling
    spreads the locations over the kept candidates.
    """
    builder = ScriptBuilder(sensing_map, board_params, params.seed)
    candidates = np.array([builder.location("random") for _ in range(20 * params.locations)])
    pitch = sensing_map.pitch_mm()
    width = board_params.coupling_sigma_mm or default_coupling_width_mm(board_params.finger_radius_mm, pitch)
    inside = surrounded(sensing_map, candidates, 2.0 * width)
    pool = candidates[inside] if params.location_rule == "surrounded" else candidates
    if len(pool) < params.locations:
        raise UserError(f"only {len(pool)} of {len(candidates)} candidate locations are surrounded by crossings: "
                        "evaluate fewer locations or use location_rule 'near'")
    points = pool[farthest_point_sampling(pool, params.locations, params.seed)]
    return points, {"location_rule": params.location_rule, "candidates": len(candidates),
                    "surrounded_fraction": round(float(inside.mean()), 4),
                    "locations_surrounded": int(surrounded(sensing_map, points, 2.0 * width).sum())}


def press_steps(points: np.ndarray, params: EvalParams) -> list[dict[str, Any]]:
    """Press steps over ``points`` (mm), ``params.repetitions`` rounds of every location in order."""
    return [{"gesture": "press", "at": points[i].tolist(), "ms": params.press_ms, "gap_ms": params.gap_ms,
             "location": i, "repetition": r}
            for r in range(params.repetitions) for i in range(len(points))]


@dataclasses.dataclass(frozen=True)
class EvalReport:
    """Per-press errors, per-location SNR and counts of detection failures."""

    errors_mm: np.ndarray  # (presses,) nan for a missed press
    press_location: np.ndarray  # (presses,) int
    locations: tuple[dict[str, Any], ...]  # per location: point, cell, crossings_seen, snr_sigma, snr_p2p, error_mm_mean
    false_touches: int
    missed_presses: int
    frames: int
    choice: dict[str, Any] = dataclasses.field(default_factory=dict)  # how the simulator chose the locations

    def summary(self) -> dict[str, Any]:
        e = self.errors_mm[np.isfinite(self.errors_mm)]
        snr_sigma = np.array([loc["snr_sigma"] for loc in self.locations])
        snr_p2p = np.array([loc["snr_p2p"] for loc in self.locations])
        stats = {}
        if len(e):
            stats = {"localization_error_mm_mean": float(e.mean()), "localization_error_mm_min": float(e.min()),
                     "localization_error_mm_max": float(e.max()),
                     "localization_error_mm_mad": float(np.mean(np.abs(e - e.mean()))),
                     "localization_error_mm_std": float(e.std()), "localization_error_mm_var": float(e.var()),
                     "localization_error_mm_rmse": float(np.sqrt(np.mean(e**2)))}
        return {**{k: round(v, 4) for k, v in stats.items()},
                "snr_mean": round(float(snr_sigma.mean()), 2), "snr_std": round(float(snr_sigma.std()), 2),
                "snr_p2p_mean": round(float(snr_p2p.mean()), 2), "snr_p2p_std": round(float(snr_p2p.std()), 2),
                "presses": int(len(self.errors_mm)), "locations": len(self.locations),
                "crossings_seen_min": min((loc["crossings_seen"] for loc in self.locations), default=0),
                "false_touches": self.false_touches, "missed_presses": self.missed_presses, "frames": self.frames,
                **self.choice}


def evaluate(frames: Iterable[Frame], labels: list[tuple[float, dict[str, Any]]], processor: TouchProcessor,
             params: EvalParams = EvalParams()) -> EvalReport:
    """Run ``processor`` over ``frames`` and score it against the press ``labels``."""
    presses = sorted((t, label) for t, label in labels if label.get("gesture") == "press")
    if not presses:
        raise UserError("the recording holds no press labels: the evaluation needs {\"gesture\": \"press\", "
                        "\"location\": i, \"point\": [x, y, z], \"t_end\": t} labels (see sense_eval)")
    starts = np.array([t for t, _ in presses])
    ends = np.array([float(label["t_end"]) for _, label in presses])
    truth = np.array([label["point"] for _, label in presses], dtype=np.float64)
    location = np.array([int(label.get("location", k)) for k, (_, label) in enumerate(presses)])
    settle, margin = params.settle_ms / 1000, params.rest_margin_ms / 1000
    sums = np.zeros((len(presses), 3))
    counts = np.zeros(len(presses), dtype=np.int64)
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
        inside = np.flatnonzero((t >= starts + settle - 1e-6) & (t < ends - 1e-6))
        near = np.any((t >= starts - margin) & (t < ends + margin))
        deltas.append(result.delta)
        frame_press.append(int(inside[0]) if len(inside) else -1)
        rest.append(not near)
        for event in result.events:
            if event["type"] == "touch_down" and not near:
                false_touches += 1
        if len(inside) and result.touches:
            k = int(inside[0])
            points = np.array([touch.point for touch in result.touches])
            sums[k] += points[np.argmin(np.linalg.norm(points - truth[k], axis=1))]
            counts[k] += 1
    errors = np.full(len(presses), np.nan)
    seen = counts > 0
    errors[seen] = np.linalg.norm(sums[seen] / counts[seen, None] - truth[seen], axis=1)
    deltas_arr = np.array(deltas)
    frame_press_arr = np.array(frame_press)
    rest_arr = np.array(rest, dtype=bool)
    report_locations = []
    for i in np.unique(location):
        touch_frames = np.isin(frame_press_arr, np.flatnonzero(location == i))
        if not touch_frames.any() or not rest_arr.any():
            continue
        mean_touch = deltas_arr[touch_frames].mean(axis=0)
        cell = int(np.argmax(mean_touch))
        rest_values = deltas_arr[rest_arr, cell]
        signal = float(mean_touch[cell] - rest_values.mean())
        rest_sigma = np.maximum(deltas_arr[rest_arr].std(axis=0), 1e-9)
        report_locations.append({
            "location": int(i), "point": truth[location == i][0].round(3).tolist(), "cell": cell,
            "crossings_seen": int(np.count_nonzero(mean_touch - deltas_arr[rest_arr].mean(axis=0) > 6.0 * rest_sigma)),
            "signal_counts": round(signal, 2),
            "snr_sigma": round(signal / max(float(rest_values.std()), 1e-9), 2),
            "snr_p2p": round(signal / max(float(np.ptp(rest_values)), 1e-9), 2),
            "error_mm_mean": round(float(np.nanmean(errors[location == i])), 4) if seen[location == i].any() else None,
        })
    return EvalReport(errors, location, tuple(report_locations), false_touches, int((~seen).sum()), n_frames)


def evaluate_simulator(
    sensing_map_path: str | Path,
    board_params: BoardParams = BoardParams(),
    eval_params: EvalParams = EvalParams(),
    processing_params: ProcessingParams = ProcessingParams(),
    through_pty: bool = True,
    record: str | Path | None = None,
) -> EvalReport:
    """The protocol on the virtual board, read back through a pseudo-terminal in fast mode (or fed to
    the processor directly when ``through_pty`` is False)."""
    sensing_map = load_sensing_map(sensing_map_path)
    board = VirtualBoard(sensing_map, board_params)
    points, choice = evaluation_locations(sensing_map, eval_params, board_params)
    script = ScriptBuilder(sensing_map, board_params, eval_params.seed).build(press_steps(points, eval_params))
    processor = TouchProcessor(sensing_map, processing_params)
    if through_pty:
        frames: Iterable[Frame] = frames_through_pty(board, script, fast=True, record=record)
    else:
        total = int(np.ceil(script.duration * board_params.rate_hz))
        frames = (Frame(board.frame(k / board_params.rate_hz, script.fingers_at(k / board_params.rate_hz)),
                        k / board_params.rate_hz, k) for k in range(total))
    return dataclasses.replace(evaluate(frames, list(script.labels), processor, eval_params), choice=choice)


def load_protocol(path: str | Path) -> tuple[np.ndarray, int]:
    """``{"points": [[x, y, z], ...], "repetitions": 10}`` (mm): the marked locations of a hardware
    session, touched in rounds (every location once per round, in list order)."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"protocol file {path} not found: write {{\"points\": [[x, y, z], ...], \"repetitions\": 10}}")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        points = np.array(doc["points"], dtype=np.float64).reshape(-1, 3)
        repetitions = int(doc.get("repetitions", 10))
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise UserError(f"protocol file {path} is malformed ({exc}): write "
                        "{\"points\": [[x, y, z], ...], \"repetitions\": 10}") from None
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
                       protocol: str | Path | None = None) -> EvalReport:
    """The protocol scored on a recording: its press labels (simulator recordings carry them), or,
    with ``protocol`` (see :func:`load_protocol`), presses detected in an unlabelled hardware session.
    With detected presses, ``missed_presses`` is 0 by construction (a miss shows as a count error)."""
    labels: list[tuple[float, dict[str, Any]]] = []
    processor = TouchProcessor(load_sensing_map(sensing_map_path), processing_params)
    frames = list(replay_frames(recording, on_label=lambda t, label: labels.append((t, label))))
    if protocol is not None:
        points, repetitions = load_protocol(protocol)
        labels = labels_from_presses(frames, processor, points, repetitions)
    return evaluate(frames, labels, processor, eval_params)
