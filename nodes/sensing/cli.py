"""``retrotouch sense``: live touch sensing from a Muca board (or the simulator, or a recording) to an
event stream for applications.

Usage::

    retrotouch sense --port /dev/ttyACM0 --layout out/retrofit            # a board
    retrotouch sense --simulate [script.json] [--fast] [--layout ...]       # the virtual board on a pty
    retrotouch sense --replay session.jsonl --layout out/retrofit           # a recording
    ... --record session.jsonl   --udp 127.0.0.1:9000   --websocket 8765   --view [--view-port 8080]
    ... --evaluate [--locations points.json] [--board board.yaml]   (with --simulate or --replay: the
                      15 x 10 SNR / localization protocol, one JSON report; a hardware recording
                      without labels needs --locations or --protocol)

    retrotouch sense --probe /dev/ttyACM0 [--baud 115200] [--json]         # what is on the port
    retrotouch sense --port ... --calibrate --calibration cal.json          # guided touches on every crossing
    retrotouch sense --port ... --calibration cal.json                      # ... used by the processing
    ... --simulate --evaluate --calibrate          (calibrate the virtual board, then evaluate with it)

Events are JSON lines on stdout (``touch_down``/``touch_move``/``touch_up`` from the processing,
gestures from :mod:`retrotouch.nodes.sensing.gestures`, ``status`` lines about the board and the
baseline), each with ``"format": "retrotouch.events/1"`` and specified by
``nodes/data/events.schema.json``; the same lines go to every ``--udp`` target as datagrams and to
every client of ``--websocket``. Diagnostics go to stderr.
"""
from __future__ import annotations

import dataclasses
import json
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, Optional

import typer

from ...graph import interrupts
from ...graph.app import current
from ...graph.errors import UserError
from .cli_checks import check_inputs, check_numbers, parse_channels
from .sinks import EventSinks, status_event

def run_session(frames: Iterable[Any], processor, recognizer, sinks: EventSinks, view=None,
                duration_s: float | None = None, on_frame: Callable[[Any], None] | None = None) -> int:
    """Process frames until they end (or ``duration_s`` of frame time); returns the frame count."""
    count = 0
    start = None
    calibrated = False
    for frame in frames:
        interrupts.check()
        start = frame.t if start is None else start
        t = frame.t - start
        result = processor.process(frame.values, t)
        if result.calibrated and not calibrated:
            calibrated = True
            sinks.emit(status_event("baseline", f"baseline ready after {count + 1} frames: touch now", t))
        gestures = recognizer.feed(result)
        for event in (*result.events, *gestures):
            sinks.emit(event)
        if view is not None:
            view.publish(result, gestures)
        if on_frame is not None:
            on_frame(result)
        count += 1
        if duration_s is not None and t >= duration_s:
            break
    return count


def sense(
    port: Optional[str] = typer.Option(None, "--port", help="Serial port of the Muca board (or a pyserial URL)."),
    layout: Optional[str] = typer.Option(None, "--layout", help="sensing_map.json or the run folder holding it "
                                         "(default with --simulate: out/retrofit, else a synthetic bunny)."),
    simulate: bool = typer.Option(False, "--simulate", help="Use the virtual board on a pseudo-terminal; "
                                  "optionally follow SCRIPT (JSON steps), else a demo of every gesture."),
    script: Optional[str] = typer.Argument(None, help="Simulation script (with --simulate)."),
    fast: bool = typer.Option(False, "--fast", help="Simulator: run as fast as the processing goes."),
    loop: bool = typer.Option(False, "--loop", help="Simulator: repeat the script until stopped."),
    board: Optional[str] = typer.Option(None, "--board", help="Simulator: board model YAML (BoardParams settings over "
                                        "the default board, which is unlike the processing's assumptions)."),
    snr: Optional[float] = typer.Option(None, "--snr", help="Simulator: peak signal over noise sigma (board: 60)."),
    seed: Optional[int] = typer.Option(None, "--seed", help="Simulator: random seed (board: 0)."),
    coupling: Optional[str] = typer.Option(None, "--coupling", help="Simulator: finger coupling profile, gaussian (the "
                                           "processing's model) or disc (flat top, power-law tail; the default board's)."),
    replay: Optional[str] = typer.Option(None, "--replay", help="Replay a recording made with --record."),
    speed: float = typer.Option(1.0, "--speed", help="Replay speed (1 = real time, 0 = as fast as possible)."),
    record: Optional[str] = typer.Option(None, "--record", help="Record the raw serial bytes to FILE (a new file)."),
    frame_format: str = typer.Option("ascii", "--format", help="Board output: ascii, binary (Muca_Raw_Basic) or "
                                     "handshake (SYNC, then one frame per request); --probe tells which."),
    baudrate: int = typer.Option(115200, "--baud", help="Serial baud rate."),
    flip_tx: bool = typer.Option(False, "--flip-tx", help="The firmware reverses TX (Muca master)."),
    flip_rx: bool = typer.Option(False, "--flip-rx", help="The firmware reverses RX (Muca 2020 library)."),
    skip_tx: Optional[str] = typer.Option(None, "--skip-tx", help="TX channels to ignore, e.g. 3,7."),
    skip_rx: Optional[str] = typer.Option(None, "--skip-rx", help="RX channels to ignore."),
    skip_lines: int = typer.Option(0, "--skip-lines", help="Ignore this many lines after connecting."),
    udp: Optional[list[str]] = typer.Option(None, "--udp", help="Also send events as UDP datagrams to HOST:PORT."),
    websocket: Optional[int] = typer.Option(None, "--websocket", help="Also serve events on ws://127.0.0.1:PORT/."),
    view: bool = typer.Option(False, "--view", help="Serve the live 3D view (URL on stderr)."),
    view_port: int = typer.Option(8080, "--view-port", help="Port of the live view (0 = any free port)."),
    duration: Optional[float] = typer.Option(None, "--duration", help="Stop after this many seconds of frames."),
    evaluate: bool = typer.Option(False, "--evaluate", help="Run the SNR/localization protocol (with --simulate "
                                  "or --replay) and print its report as one JSON object."),
    locations: Optional[str] = typer.Option(None, "--locations", help="With --evaluate: JSON list of the touched points "
                                            "[[x, y, z], ...] (mm on the object; a --replay touched them 10 times "
                                            "round by round); default: 15 spread over the sensing surface."),
    calibrate: bool = typer.Option(False, "--calibrate", help="Guide the operator through touching every crossing "
                                   "and write the measured gains and finger coupling to --calibration FILE (with "
                                   "--simulate --evaluate: calibrate the virtual board first, then evaluate)."),
    calibration: Optional[str] = typer.Option(None, "--calibration", help="Calibration file: written by --calibrate "
                                              "(default calibration.json), else loaded for the processing."),
    probe: Optional[str] = typer.Option(None, "--probe", help="Listen to serial port PORT and say what is on it "
                                        "(format, frame rate, channels, the sense command to use)."),
    probe_seconds: float = typer.Option(3.0, "--probe-seconds", help="How long --probe listens (s)."),
    as_json: bool = typer.Option(False, "--json", help="With --probe: print the finding as one JSON object."),
    protocol: Optional[str] = typer.Option(None, "--protocol", help="With --evaluate --replay of an unlabelled "
                                           "hardware session: JSON {points: [[x,y,z],...], repetitions: n} touched "
                                           "round by round."),
) -> None:
    """Stream touch and gesture events (JSON lines) from a Muca board, the simulator or a recording.
    Ctrl-C ends it with one ``interrupted`` line (as the engine words it) and exit code 130."""
    try:
        _sense(**locals())
    except KeyboardInterrupt:
        # Handled here: once a command runs, click turns Ctrl-C into a silent exit 130.
        print(f"{current().name}: error: interrupted", file=sys.stderr, flush=True)
        raise typer.Exit(130) from None


def _sense(port, layout, simulate, script, fast, loop, board, snr, seed, coupling, replay, speed, record, frame_format,
           baudrate, flip_tx, flip_rx, skip_tx, skip_rx, skip_lines, udp, websocket, view, view_port, duration,
           evaluate, locations, calibrate, calibration, probe, probe_seconds, as_json, protocol) -> None:
    """:func:`sense` with its options as plain values."""
    from ..data.sensing_map import resolve_sensing_map_path

    check_numbers(baudrate, probe_seconds, speed, skip_lines, duration, websocket, view_port)
    if probe:
        if port or simulate or replay or evaluate:
            raise UserError("--probe PORT only listens: leave out --port, --simulate, --replay and --evaluate")
        from .probe import run_probe

        run_probe(probe, baudrate, probe_seconds, as_json)
        return
    if as_json:
        raise UserError("--json goes with --probe (events are JSON lines already)")
    check_inputs(port, simulate, replay, script, record, evaluate, protocol, coupling, frame_format)
    if locations and not evaluate:
        raise UserError("--locations goes with --evaluate (the points touched in the protocol)")
    if board and not simulate:
        raise UserError("--board goes with --simulate (it describes the virtual board)")
    board_params = _board(board, snr, seed, coupling)
    if layout is None and not simulate:
        raise UserError("--layout is required: pass the run folder or its sensing_map.json")
    layout_path = _default_layout() if layout is None else resolve_sensing_map_path(layout)
    loaded = None
    if calibration and not calibrate:
        from .calibration import load_calibration

        loaded = load_calibration(calibration)
    if evaluate:
        _evaluate(layout_path, replay, board_params, record, protocol or (locations if replay else None),
                  None if replay else locations, loaded, calibrate, calibration)
        return
    from ..data.board import NUM_RX, NUM_TX
    from .frames import FrameOptions

    options = FrameOptions(flip_tx=flip_tx, flip_rx=flip_rx, skip_tx=parse_channels(skip_tx, "--skip-tx", NUM_TX),
                           skip_rx=parse_channels(skip_rx, "--skip-rx", NUM_RX))
    source = Source(port=port, baudrate=baudrate, frame_format=frame_format, options=options, skip_lines=skip_lines,
                    record=record, replay=replay, replay_options=flip_tx or flip_rx or bool(skip_tx or skip_rx),
                    speed=speed, steps=None if not simulate else _steps(script), board_params=board_params,
                    fast=fast, loop=loop)
    if calibrate:
        from .calibration_cli import run_calibration

        run_calibration(layout_path, source, Path(calibration or "calibration.json"), _open_frames,
                        (lambda processor: _live_view(processor, view_port)) if view else None)
        return
    _stream(layout_path, source, udp or (), websocket, view_port if view else None, duration, loaded)


@dataclasses.dataclass(frozen=True)
class Source:
    """Where frames come from: a board on ``port``, a recording ``replay`` or the simulator (``steps``)."""

    port: Optional[str]
    baudrate: int
    frame_format: str
    options: Any  # FrameOptions
    skip_lines: int
    record: Optional[str]
    replay: Optional[str]
    replay_options: bool  # the options override the recording's header
    speed: float
    steps: Optional[list[dict[str, Any]]]
    board_params: Any  # BoardParams
    fast: bool
    loop: bool


def _open_frames(source: Source, sensing_map, sinks: EventSinks) -> tuple[Iterator[Any], Any]:
    """Frames from ``source`` and the serial reader to close (None unless a board)."""
    if source.port:
        from .muca_serial import MucaReader

        reader = MucaReader(source.port, baudrate=source.baudrate, frame_format=source.frame_format,
                            options=source.options, skip_first_lines=source.skip_lines, record=source.record,
                            on_status=lambda line: _board_status(sinks, line))
        return reader.frames(), reader
    if source.replay:
        from .recording import replay_frames

        # A recording's header holds the board's orientation unless the options override it.
        return replay_frames(source.replay, options=source.options if source.replay_options else None,
                             speed=source.speed), None
    return _simulated(sensing_map, source.steps, source.board_params, source.fast, source.loop,
                      source.frame_format, source.record, lambda line: _board_status(sinks, line)), None


def _stream(layout_path: Path, source: Source, udp: Iterable[str], websocket: Optional[int],
            view_port: Optional[int], duration: Optional[float], calibration=None) -> None:
    """Process frames from ``source`` into events until they end (or Ctrl-C), with ``calibration``
    (:mod:`.calibration`) if given."""
    from ..data.sensing_map import load_sensing_map
    from .gestures import GestureRecognizer
    from .processing import TouchProcessor

    sensing_map = load_sensing_map(layout_path)
    processor = TouchProcessor(sensing_map) if calibration is None else calibration.processor(sensing_map)
    sinks = EventSinks(udp=udp, websocket_port=websocket)
    live = reader = frames = None
    try:
        if view_port is not None:
            live = _live_view(processor, view_port)
        frames, reader = _open_frames(source, sensing_map, sinks)
        count = run_session(frames, processor, GestureRecognizer(), sinks, live, duration)
        print(f"{count} frames processed", file=sys.stderr)
        if live is not None:
            print("the frames ended; the live view keeps serving its last frame (Ctrl-C to stop)", file=sys.stderr,
                  flush=True)
            while True:
                time.sleep(1.0)
                interrupts.check()
    finally:
        if hasattr(frames, "close"):
            frames.close()  # a generator: stops the simulator and closes its port now
        if reader is not None:
            reader.close()
        if live is not None:
            live.stop()
        sinks.close()


def _board_status(sinks: EventSinks, line: str) -> None:
    """A board status line: on stderr for the operator and as a status event for applications."""
    print(line, file=sys.stderr, flush=True)
    sinks.emit(status_event("board", line))


def _live_view(processor, port: int):
    from .live_view import LiveView

    try:
        live = LiveView(processor, port=port)
    except OSError as exc:
        raise UserError(f"--view-port {port}: cannot listen ({exc.strerror}): pick another port") from None
    print(f"live view on {live.start()}", file=sys.stderr)
    return live


def _default_layout() -> Path:
    from .synthetic_map import default_sensing_map_path

    cache = Path.home() / ".cache" / "retrotouch" / "synthetic_bunny"
    path, description = default_sensing_map_path(Path.cwd(), cache)
    print(f"layout: {description}", file=sys.stderr)
    return path


def _steps(script: Optional[str]) -> list[dict[str, Any]]:
    from .scripts import DEMO_SCRIPT, load_script

    return DEMO_SCRIPT if script is None else load_script(script)


def _simulated(sensing_map, steps, params, fast, loop, frame_format, record, on_status) -> Iterator[Any]:
    from .pty_board import frames_through_pty
    from .scripts import ScriptBuilder
    from .virtual_board import VirtualBoard

    board = VirtualBoard(sensing_map, params)
    built = ScriptBuilder(sensing_map, params, params.seed).build(steps)
    return frames_through_pty(board, built, fast=fast, frame_format=frame_format, record=record, loop=loop,
                              on_status=on_status)


def _board(board: Optional[str], snr: Optional[float], seed: Optional[int], coupling: Optional[str]):
    """The simulated board: a ``--board`` file over the default board, then the single options."""
    from pydantic import ValidationError

    from .virtual_board import REALISTIC_BOARD, BoardParams, load_board

    params = load_board(board) if board else REALISTIC_BOARD
    given = {key: value for key, value in (("snr", snr), ("seed", seed), ("coupling_model", coupling)) if value is not None}
    try:
        return BoardParams.model_validate({**params.model_dump(), **given})
    except ValidationError as exc:
        error = exc.errors()[0]
        raise UserError(f"--{str(error['loc'][0]).split('_')[0]}: {error['msg']}") from None


def _evaluate(layout_path: Path, replay: Optional[str], board_params, record: Optional[str],
              protocol: Optional[str], locations: Optional[str], calibration, calibrate: bool,
              calibration_path: Optional[str]) -> None:
    """The evaluation report (one JSON object); with ``calibrate`` the virtual board is calibrated
    first (the operator's touches on its crossings) and the processing uses the result."""
    from ..data.sensing_map import load_sensing_map
    from .evaluation import EvalParams, calibrate_simulator, evaluate_recording, evaluate_simulator

    started = time.perf_counter()
    session = None
    if calibrate:
        if replay:
            raise UserError("--evaluate --calibrate calibrates the virtual board: use it with --simulate")
        calibration, session = calibrate_simulator(load_sensing_map(layout_path), board_params, seed=board_params.seed)
        if calibration_path:
            calibration.save(calibration_path)
    if replay:
        report = evaluate_recording(replay, layout_path, protocol=protocol, calibration=calibration)
    else:
        report = evaluate_simulator(layout_path, board_params, EvalParams(seed=board_params.seed), record=record,
                                    locations=locations, calibration=calibration)
    print(json.dumps({**report.summary(), "per_location": list(report.locations),
                      "board": board_params.model_dump(mode="json") if not replay else None,
                      "calibration": None if calibration is None else {**calibration.summary(), **(session or {})},
                      "seconds": round(time.perf_counter() - started, 2)}))


def register(app: typer.Typer) -> None:
    """Add ``sense`` to the retrotouch CLI."""
    app.command("sense")(sense)
