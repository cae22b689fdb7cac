"""Checks of ``retrotouch sense``'s options before anything opens: one-line UserErrors naming the
option and its range or the combination that cannot work."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

from ...graph.errors import UserError
from .sinks import MAX_PORT


def parse_channels(text: Optional[str], option: str, board_channels: int) -> tuple[int, ...]:
    """``--skip-tx``/``--skip-rx`` text -> channel numbers, each one of the board's ``board_channels``."""
    if not text:
        return ()
    try:
        channels = tuple(int(part) for part in text.split(",") if part.strip())
    except ValueError:
        raise UserError(f"{option} takes channel numbers separated by commas, e.g. {option} 3,7") from None
    for channel in channels:
        if not 0 <= channel < board_channels:
            raise UserError(f"{option} {channel}: the board's channels are 0-{board_channels - 1}")
    return channels


def check_inputs(port, simulate, replay, script, record, evaluate, protocol, coupling, frame_format) -> None:
    """One-line UserErrors for option combinations that cannot work and for a ``--record`` file that exists."""
    sources = [name for name, on in (("--port", port), ("--simulate", simulate), ("--replay", replay)) if on]
    if len(sources) != 1:
        raise UserError("choose one input: --port DEVICE, --simulate [SCRIPT] or --replay FILE")
    if script is not None and not simulate:
        raise UserError(f"unexpected argument {script!r}: a script goes with --simulate")
    if record and replay:
        raise UserError("--record and --replay together: a replay is already recorded")
    if record and Path(record).exists():
        raise UserError(f"--record {record} exists: choose another name or delete it")
    if evaluate and port:
        raise UserError("--evaluate needs --simulate or a labelled --replay recording")
    if protocol and not (evaluate and replay):
        raise UserError("--protocol goes with --evaluate --replay FILE (scoring a recorded hardware session)")
    if coupling not in (None, "gaussian", "disc"):
        raise UserError(f"--coupling {coupling!r}: use gaussian or disc")
    from .frames import FRAME_FORMATS

    if frame_format not in FRAME_FORMATS:
        raise UserError(f"--format {frame_format!r}: use {', '.join(FRAME_FORMATS)} (--probe PORT tells which)")


def check_numbers(baudrate: int, probe_seconds: float, speed: float, skip_lines: int, duration: Optional[float],
                   websocket: Optional[int], view_port: int) -> None:
    """One-line UserErrors for numeric options outside their range."""
    for option, value in (("--baud", baudrate), ("--probe-seconds", probe_seconds), ("--duration", duration)):
        if value is not None and not value > 0:
            raise UserError(f"{option} {value}: use a number above 0")
    for option, value in (("--speed", speed), ("--skip-lines", skip_lines)):
        if not value >= 0:
            raise UserError(f"{option} {value}: use 0 or more")
    for option, port in (("--websocket", websocket), ("--view-port", view_port)):
        if port is not None and not 0 <= port <= MAX_PORT:
            raise UserError(f"{option} {port}: a port is 0-{MAX_PORT} (0 = any free port)")
