"""Muca board serial input: frame parsing (ASCII and binary), a tolerant reader over pyserial that
reconnects after an unplug, and session record/replay.

Frame conventions (stated once here, used by the simulator and the touch processing):

* A frame is a ``(num_tx, num_rx)`` int32 array of raw mutual-capacitance counts (0..65535),
  TX-major: wire index ``tx * num_rx + rx`` (21 x 12 = 252 values on a Muca/FT5316 board).
* Orientation differs between firmware versions (the 2020 library reverses RX, master reverses TX):
  ``flip_tx``/``flip_rx`` reverse the channel order after parsing so that channel 0 is always the
  layout's Tx00/Rx00. Channels listed in ``skip_tx``/``skip_rx`` (unwired or broken lines) read
  ``-1`` (= no reading) and are ignored downstream.
* ASCII format (Muca_Raw.ino): one frame per line, ``num_tx * num_rx`` unsigned decimal fields
  separated by commas, CRLF. Empty fields (sketches that print only positive values) read 0. Any
  other line (``[Muca] ...``, ``Calibration performed k/20``, garbage, truncated frames) is skipped
  and counted; a line whose frame follows status text glued on without a newline (the 2020 library
  prints ``i2c write failed`` without one) is salvaged when the text ends in a non-digit.
* Binary format (Muca_Raw_Basic.ino SendRawByte): ``2 + num_tx * num_rx`` bytes per frame,
  ``[min_hi, min_lo, uint8(value - min) ...]``, no sync marker. Frames are cut every
  ``2 + cells`` bytes from the start of the stream (after any status lines); the reader drops a
  partial frame after a read timeout without a byte (a pause between frames), which re-aligns the
  stream. A board that streams without pauses stays aligned only while no byte is lost: prefer
  the ASCII format when the link is unreliable.

Recording file (JSON lines, replayable through the same parser)::

    {"format": "retrotouch.muca_recording/1", "frame_format": "ascii", "port": "...", ...}
    {"t": 0.1031, "b64": "<raw bytes as received>"}
    {"t": 2.5, "label": {...}}          # optional annotations (e.g. evaluation ground truth)

``t`` is seconds since the recording started; a header with ``"timebase": "board"`` (simulator
recordings made in fast mode) replays frame ``k`` at ``k / rate_hz`` instead, the time its labels use.
"""
from __future__ import annotations

import base64
import dataclasses
import json
import os
import re
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import serial

from ...graph.errors import UserError

NUM_TX = 21
NUM_RX = 12
MAX_COUNT = 65535
RECORDING_FORMAT = "retrotouch.muca_recording/1"
STATUS_PREFIXES = (b"[Muca]", b"Calibration performed", b"i2c write failed", b"RX:")


@dataclasses.dataclass(frozen=True)
class FrameOptions:
    """How raw board output maps to channels (see the module conventions)."""

    num_tx: int = NUM_TX
    num_rx: int = NUM_RX
    flip_tx: bool = False
    flip_rx: bool = False
    skip_tx: tuple[int, ...] = ()
    skip_rx: tuple[int, ...] = ()

    @property
    def cells(self) -> int:
        return self.num_tx * self.num_rx

    def orient(self, wire_values: np.ndarray) -> np.ndarray:
        """Wire-order values (cells,) -> channel-order (num_tx, num_rx) int32 with skips = -1."""
        grid = wire_values.astype(np.int32).reshape(self.num_tx, self.num_rx)
        if self.flip_tx:
            grid = grid[::-1]
        if self.flip_rx:
            grid = grid[:, ::-1]
        grid = np.ascontiguousarray(grid)
        if self.skip_tx:
            grid[list(self.skip_tx), :] = -1
        if self.skip_rx:
            grid[:, list(self.skip_rx)] = -1
        return grid


@dataclasses.dataclass
class ParserStats:
    """Counters of what a parser saw (lines for ASCII, bytes dropped for binary)."""

    frames: int = 0
    status_lines: int = 0
    rejected_lines: int = 0
    salvaged_lines: int = 0
    dropped_bytes: int = 0


class AsciiFrameParser:
    """Incremental parser for the ASCII frame format; feed it bytes in any chunking."""

    def __init__(self, options: FrameOptions = FrameOptions(), skip_first_lines: int = 0):
        self.options = options
        self.stats = ParserStats()
        self._pending = bytearray()
        self._lines_to_skip = skip_first_lines
        n = options.cells
        self._frame_re = re.compile(rb"[0-9]{0,5}(?:,[0-9]{0,5}){%d}" % (n - 1))
        self._suffix_re = re.compile(rb"[0-9]{0,5}(?:,[0-9]{0,5}){%d}\Z" % (n - 1))
        # A frame line is at most n fields of 5 digits plus commas; keep a little more than two so a
        # frame glued behind newline-less garbage survives the trimming of the pending buffer.
        self._max_pending = 2 * (6 * n + 64)

    def feed(self, data: bytes) -> list[np.ndarray]:
        """Parse ``data``; returns the complete frames it finished, in order."""
        self._pending += data
        parts = re.split(rb"[\r\n]", bytes(self._pending))
        self._pending = bytearray(parts.pop())
        if len(self._pending) > self._max_pending:
            self.stats.dropped_bytes += len(self._pending) - self._max_pending
            del self._pending[: len(self._pending) - self._max_pending]
        frames = []
        for line in parts:
            frame = self.parse_line(line)
            if frame is not None:
                frames.append(frame)
        return frames

    def reset(self) -> None:
        """Forget a partial line (after a reconnect)."""
        self._pending.clear()

    def parse_line(self, line: bytes) -> np.ndarray | None:
        """One line without its terminator -> oriented frame, or None (counted in ``stats``)."""
        line = line.strip(b" \t\x00")
        if not line:
            return None
        if self._lines_to_skip > 0:
            self._lines_to_skip -= 1
            self.stats.rejected_lines += 1
            return None
        if self._frame_re.fullmatch(line):
            values = self._values(line)
        else:
            values = None
            match = self._suffix_re.search(line)
            if match is not None and match.start() > 0 and line[match.start() - 1] not in b"0123456789,":
                values = self._values(match.group())
                if values is not None:
                    self.stats.salvaged_lines += 1
            if values is None:
                if line.startswith(STATUS_PREFIXES):
                    self.stats.status_lines += 1
                else:
                    self.stats.rejected_lines += 1
                return None
        if values is None:
            self.stats.rejected_lines += 1
            return None
        self.stats.frames += 1
        return self.options.orient(values)

    @staticmethod
    def _values(text: bytes) -> np.ndarray | None:
        """Fields already matched ``[0-9]{0,5}``; empty ones read 0."""
        fields = text.split(b",")
        if b",," in text or text.startswith(b",") or text.endswith(b","):
            values = np.array([int(f) if f else 0 for f in fields], dtype=np.int64)
        else:
            values = np.array(list(map(int, fields)), dtype=np.int64)
        if values.max(initial=0) > MAX_COUNT:
            return None
        return values


class BinaryFrameParser:
    """Incremental parser for the binary format (``[min_hi, min_lo, 252 x uint8]`` per frame)."""

    def __init__(self, options: FrameOptions = FrameOptions()):
        self.options = options
        self.stats = ParserStats()
        self.frame_bytes = 2 + options.cells
        self._pending = bytearray()

    def feed(self, data: bytes) -> list[np.ndarray]:
        self._pending += data
        frames = []
        while True:
            self._drop_status_line()
            if len(self._pending) < self.frame_bytes:
                return frames
            chunk = bytes(self._pending[: self.frame_bytes])
            del self._pending[: self.frame_bytes]
            base = (chunk[0] << 8) | chunk[1]
            values = base + np.frombuffer(chunk, dtype=np.uint8, offset=2).astype(np.int64)
            if values.max() > MAX_COUNT:
                self.stats.rejected_lines += 1
                continue
            self.stats.frames += 1
            frames.append(self.options.orient(values))

    def _drop_status_line(self) -> None:
        """ASCII status lines printed before streaming starts are not frame bytes."""
        while self._pending.startswith(STATUS_PREFIXES):
            end = self._pending.find(b"\n")
            if end < 0:
                return
            self.stats.status_lines += 1
            del self._pending[: end + 1]

    def resync(self) -> None:
        """Drop a partial frame; called after a pause in the byte stream (frames come in bursts)."""
        self.stats.dropped_bytes += len(self._pending)
        self._pending.clear()

    reset = resync


def make_parser(frame_format: str, options: FrameOptions, skip_first_lines: int = 0):
    """``"ascii"`` or ``"binary"`` -> a fresh parser."""
    if frame_format == "ascii":
        return AsciiFrameParser(options, skip_first_lines)
    if frame_format == "binary":
        return BinaryFrameParser(options)
    raise UserError(f"unknown frame format {frame_format!r}: use 'ascii' or 'binary'")


def encode_ascii_frame(grid: np.ndarray) -> bytes:
    """Wire-order counts (num_tx, num_rx) -> one ASCII frame line with CRLF, as Muca_Raw.ino prints."""
    return (",".join(map(str, np.asarray(grid, dtype=np.int64).ravel().tolist())) + "\r\n").encode()


def encode_binary_frame(grid: np.ndarray) -> bytes:
    """Wire-order counts -> one binary frame; values more than 255 above the minimum wrap, as on the board."""
    values = np.asarray(grid, dtype=np.int64).ravel()
    base = int(values.min())
    return bytes([base >> 8, base & 0xFF]) + ((values - base) & 0xFF).astype(np.uint8).tobytes()


@dataclasses.dataclass(frozen=True)
class Frame:
    """One parsed frame: ``values`` (num_tx, num_rx) int32, channel order, -1 = no reading;
    ``t`` seconds (monotonic clock when read live, recording time when replayed)."""

    values: np.ndarray
    t: float
    seq: int


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


class MucaReader:
    """Frames from a Muca board on ``port`` (a device path or any pyserial URL).

    Tolerant: garbage never raises; after an unplug (read error) the port is closed and reopened
    every ``reconnect_interval_s`` until it is back (or ``reconnect_timeout_s`` passes). A port that
    cannot be opened at start is a one-line :class:`UserError`.
    """

    def __init__(
        self,
        port: str,
        baudrate: int = 115200,
        frame_format: str = "ascii",
        options: FrameOptions = FrameOptions(),
        skip_first_lines: int = 0,
        record: str | Path | None = None,
        read_timeout_s: float = 0.05,
        reconnect_interval_s: float = 0.5,
        reconnect_timeout_s: float | None = None,
        open_port: Callable[..., serial.SerialBase] | None = None,
        record_header: dict[str, Any] | None = None,
    ):
        self.port = port
        self.baudrate = baudrate
        self.frame_format = frame_format
        self.options = options
        self.parser = make_parser(frame_format, options, skip_first_lines)
        self.read_timeout_s = read_timeout_s
        self.reconnect_interval_s = reconnect_interval_s
        self.reconnect_timeout_s = reconnect_timeout_s
        self.reconnects = 0
        self._open_port = open_port or (lambda: serial.serial_for_url(port, baudrate=baudrate, timeout=read_timeout_s))
        self._serial: serial.SerialBase | None = None
        self._closed = False
        self._seq = 0
        if open_port is None and "://" not in port and not os.path.exists(port):
            raise UserError(f"serial port {port} not found: plug in the board and check --port")
        try:
            self._serial = self._open_port()
        except (serial.SerialException, OSError, ValueError) as exc:
            raise UserError(f"cannot open serial port {port} ({_short(exc)}): check the cable and --port") from None
        self.recorder = (
            Recorder(record, {"frame_format": frame_format, "port": port, "baudrate": baudrate,
                              "num_tx": options.num_tx, "num_rx": options.num_rx, "flip_tx": options.flip_tx,
                              "flip_rx": options.flip_rx, "skip_tx": list(options.skip_tx),
                              "skip_rx": list(options.skip_rx), **(record_header or {})})
            if record else None
        )

    def frames(self) -> Iterator[Frame]:
        """Yield frames until :meth:`close`; never raises on bad input or an unplug."""
        idle = False
        while not self._closed:
            if self._serial is None and not self._reconnect():
                return
            try:
                data = self._serial.read(max(1, self._serial.in_waiting or 1))
                if data and self._serial.in_waiting:
                    data += self._serial.read(self._serial.in_waiting)
            except (serial.SerialException, OSError, TypeError, AttributeError):
                # TypeError/AttributeError: pyserial's posix backend after the fd went away.
                if self._closed:
                    return
                self._drop_port()
                continue
            now = time.monotonic()
            if not data:
                idle = True  # a whole read timeout without a byte: the board is between frames
                continue
            if idle and isinstance(self.parser, BinaryFrameParser):
                self.parser.resync()
            idle = False
            if self.recorder is not None:
                self.recorder.bytes(data)
            for values in self.parser.feed(data):
                yield Frame(values, now, self._seq)
                self._seq += 1

    def _drop_port(self) -> None:
        try:
            self._serial.close()
        except Exception:  # noqa: BLE001 - a dead port may fail to close in many ways; it is gone either way
            pass
        self._serial = None
        self.parser.reset()

    def _reconnect(self) -> bool:
        deadline = None if self.reconnect_timeout_s is None else time.monotonic() + self.reconnect_timeout_s
        while not self._closed:
            try:
                self._serial = self._open_port()
                self.reconnects += 1
                return True
            except (serial.SerialException, OSError, ValueError):
                if deadline is not None and time.monotonic() > deadline:
                    return False
                time.sleep(self.reconnect_interval_s)
        return False

    def close(self) -> None:
        self._closed = True
        if self._serial is not None:
            self._drop_port()
        if self.recorder is not None:
            self.recorder.close()


def parse_stream(chunks: Iterable[bytes], parser) -> list[np.ndarray]:
    """All frames of a chunked byte stream (tests and offline tools)."""
    frames: list[np.ndarray] = []
    for chunk in chunks:
        frames.extend(parser.feed(chunk))
    return frames


def _short(exc: BaseException) -> str:
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__

