"""Session recordings: the raw serial bytes as received, replayable through the same parser.

Recording file (JSON lines)::

    {"format": "retrotouch.muca_recording/1", "frame_format": "ascii", "port": "...", ...}
    {"t": 0.1031, "b64": "<raw bytes as received>"}
    {"t": 2.5, "label": {...}}          # optional annotations (e.g. evaluation ground truth)

``t`` is seconds since the recording started; a header with ``"timebase": "board"`` (simulator
recordings made in fast mode) replays frame ``k`` at ``k / rate_hz`` instead, the time its labels use.
"""
from __future__ import annotations

import base64
import json
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from ...graph.errors import UserError
from ..data.board import NUM_RX, NUM_TX
from .frames import Frame, FrameOptions, make_parser

RECORDING_FORMAT = "retrotouch.muca_recording/1"


class Recorder:
    """Writes a recording (see the module docstring) as bytes arrive."""

    def __init__(self, path: str | Path, header: dict[str, Any]):
        self.path = Path(path)
        self._file = self.path.open("w", encoding="utf-8")
        self._t0 = time.monotonic()
        self._file.write(json.dumps({"format": RECORDING_FORMAT, **header}) + "\n")

    def bytes(self, data: bytes, t: float | None = None) -> None:
        t = time.monotonic() - self._t0 if t is None else t
        self._file.write(json.dumps({"t": round(t, 6), "b64": base64.b64encode(data).decode()}) + "\n")

    def label(self, label: dict[str, Any], t: float | None = None) -> None:
        t = time.monotonic() - self._t0 if t is None else t
        self._file.write(json.dumps({"t": round(t, 6), "label": label}) + "\n")
        self._file.flush()

    def close(self) -> None:
        self._file.close()


def read_recording(path: str | Path) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """A recording -> (header, records); a missing or foreign file is a one-line UserError."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"recording {path} not found: pass a file written by `retrotouch sense --record`")
    lines = path.read_text(encoding="utf-8").splitlines()
    try:
        header = json.loads(lines[0]) if lines else {}
        records = [json.loads(line) for line in lines[1:] if line.strip()]
    except json.JSONDecodeError as exc:
        raise UserError(f"recording {path} is not JSON lines ({exc}): pass a file written by --record") from None
    if header.get("format") != RECORDING_FORMAT:
        raise UserError(f"recording {path} has format {header.get('format')!r}, expected {RECORDING_FORMAT!r}")
    return header, records


def replay_frames(
    path: str | Path,
    options: FrameOptions | None = None,
    speed: float = 0.0,
    on_label: Callable[[float, dict[str, Any]], None] | None = None,
) -> Iterator[Frame]:
    """Frames of a recording, re-parsed from the recorded bytes; ``speed`` 1.0 = real time,
    0 = as fast as possible. Labels are passed to ``on_label(t, label)`` in stream order."""
    header, records = read_recording(path)
    if options is None:
        options = FrameOptions(num_tx=header.get("num_tx", NUM_TX), num_rx=header.get("num_rx", NUM_RX),
                               flip_tx=header.get("flip_tx", False), flip_rx=header.get("flip_rx", False),
                               skip_tx=tuple(header.get("skip_tx", ())), skip_rx=tuple(header.get("skip_rx", ())))
    parser = make_parser(header.get("frame_format", "ascii"), options)
    board_rate = float(header["rate_hz"]) if header.get("timebase") == "board" else None
    start = time.monotonic()
    seq = 0
    for record in records:
        t = float(record["t"])
        if "label" in record:
            if on_label is not None:
                on_label(t, record["label"])
            continue
        if speed > 0:
            delay = start + t / speed - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        for values in parser.feed(base64.b64decode(record["b64"])):
            yield Frame(values, t if board_rate is None else seq / board_rate, seq)
            seq += 1
