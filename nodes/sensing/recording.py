"""Session recordings: the raw serial bytes as received, replayable through the same parser.

Recording file (JSON lines)::

    {"format": "retrotouch.muca_recording/1", "frame_format": "ascii", "port": "...", ...}
    {"t": 0.1031, "b64": "<raw bytes as received>"}
    {"t": 2.5, "label": {...}}          # optional annotations (e.g. evaluation ground truth)

``t`` is seconds since the recording started; a header with ``"timebase": "board"`` (simulator
recordings made in fast mode) replays frame ``k`` at ``k / rate_hz`` instead, the time its labels use.
A last line cut off without its newline (a session ended by a crash or power loss) is dropped with a
note on stderr; the lines before it replay.
"""
from __future__ import annotations

import base64
import binascii
import json
import sys
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
    """A recording -> (header, records); a missing, unreadable or foreign file is a one-line UserError."""
    path = Path(path)
    fix = "pass a file written by `retrotouch sense --record`"
    if path.is_dir():
        raise UserError(f"recording {path} is a folder, not a recording: {fix}")
    if not path.is_file():
        raise UserError(f"recording {path} not found: {fix}")
    try:
        lines = _complete_lines(path, path.read_text(encoding="utf-8"))
        header = json.loads(lines[0]) if lines else {}
        records = [json.loads(line) for line in lines[1:] if line.strip()]
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UserError(f"recording {path} is not a recording (not UTF-8 JSON lines: {type(exc).__name__}): "
                        f"{fix}") from None
    except OSError as exc:
        raise UserError(f"cannot read recording {path} ({exc.strerror}): check its permissions") from None
    found = header.get("format") if isinstance(header, dict) else type(header).__name__
    if found != RECORDING_FORMAT:
        raise UserError(f"recording {path} has format {found!r}, expected {RECORDING_FORMAT!r}: {fix}")
    _check_channels(path, header)
    for number, record in enumerate(records, start=2):
        if not (isinstance(record, dict) and isinstance(record.get("t"), (int, float))
                and (isinstance(record.get("b64"), str) or "label" in record)):
            raise UserError(f"recording {path} line {number} is not a {{\"t\", \"b64\"}} or {{\"t\", \"label\"}} "
                            f"record: {fix}")
    return header, records


def _complete_lines(path: Path, text: str) -> list[str]:
    """The lines of ``text`` without a last line cut off before its newline (said on stderr); a
    header alone is kept, to be judged as one."""
    lines = text.splitlines()
    if len(lines) > 1 and not text.endswith("\n"):
        try:
            json.loads(lines[-1])
        except json.JSONDecodeError:
            print(f"recording {path}: dropped its incomplete last line (the session was cut off)", file=sys.stderr)
            return lines[:-1]
    return lines


def _check_channels(path: Path, header: dict[str, Any]) -> None:
    """One-line UserError for header channel counts or skipped channels outside the board's."""
    for count_field, skip_field, board_count in (("num_tx", "skip_tx", NUM_TX), ("num_rx", "skip_rx", NUM_RX)):
        count = header.get(count_field, board_count)
        if type(count) is not int or not 1 <= count <= board_count:
            raise UserError(f"recording {path} header: {count_field} {count!r} is not 1-{board_count} (the board's "
                            f"channels): correct the header's first line or record again")
        skipped = header.get(skip_field, [])
        if not (isinstance(skipped, list) and all(type(c) is int and 0 <= c < count for c in skipped)):
            raise UserError(f"recording {path} header: {skip_field} {skipped!r} is not a list of channels "
                            f"0-{count - 1}: correct the header's first line or record again")


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
    seq, t = 0, 0.0
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
        try:
            data = base64.b64decode(record["b64"], validate=True)
        except binascii.Error:
            raise UserError(f"recording {path} holds a record whose b64 bytes do not decode: re-record the session") from None
        for values in parser.feed(data):
            yield Frame(values, t if board_rate is None else seq / board_rate, seq)
            seq += 1
    # The end of the recording releases a binary frame still waiting for the next frame's header.
    for values in parser.flush() if hasattr(parser, "flush") else ():
        yield Frame(values, t if board_rate is None else seq / board_rate, seq)
        seq += 1
