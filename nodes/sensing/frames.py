"""Muca board frames: the ASCII and binary wire formats, parsed incrementally from bytes in any
chunking, and encoded (for the simulator).

Frame conventions (stated once here, used by the simulator and the touch processing):

* A frame is a ``(num_tx, num_rx)`` int32 array of raw mutual-capacitance counts (0..65535),
  TX-major: wire index ``tx * num_rx + rx`` (21 x 12 = 252 values on a Muca/FT5316 board,
  :mod:`..data.board`).
* Orientation differs between firmware versions (the 2020 library reverses RX, master reverses TX):
  ``flip_tx``/``flip_rx`` reverse the channel order after parsing so that channel 0 is always the
  layout's Tx00/Rx00. Channels listed in ``skip_tx``/``skip_rx`` (unwired or broken lines) read
  ``-1`` (= no reading) and are ignored downstream.
* ASCII format (Muca_Raw.ino): one frame per line, ``num_tx * num_rx`` unsigned decimal fields
  separated by commas, CRLF. Empty fields (sketches that print only positive values) read 0. Any
  other line (``[Muca] ...``, ``Calibration performed k/20``, garbage, truncated frames, signs,
  decimals, hex) is skipped and counted; a frame behind status text glued on without a newline
  (the 2020 library prints ``i2c write failed`` without one) is salvaged.
* Binary format (Muca_Raw_Basic.ino SendRawByte): ``2 + num_tx * num_rx`` bytes per frame,
  ``[min_hi, min_lo, uint8(value - min) ...]``, no sync marker; parsed with self-alignment by
  :mod:`.binary_frames`.
* Handshake variant: the board repeats ``RX:<n>:TX:<m>:SYNC`` until the host answers, then sends
  one ASCII frame per host request byte (:mod:`.handshake`).
"""
from __future__ import annotations

import dataclasses
import re

import numpy as np

from ...graph.errors import UserError
from ..data.board import MAX_COUNT, NUM_RX, NUM_TX

FRAME_FORMATS = ("ascii", "handshake", "binary")
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
    resyncs: int = 0  # binary: times the frame alignment was lost and searched again


class AsciiFrameParser:
    """Incremental parser for the ASCII frame format; feed it bytes in any chunking.

    A frame line is exactly ``cells`` fields separated by commas, each empty (reads 0) or an
    unsigned decimal integer as the firmware prints it (no sign, no leading zero, no decimal point,
    at most ``MAX_COUNT``). Every other line is rejected (or counted as a status line) after work
    proportional to its length: a length test, a comma count, a scan for bytes other than digits
    and commas, one anchored regular-expression match without backtracking, and the integer
    conversion of a line that matched. Status text the firmware glues
    to a frame without a newline (``GLUED_STATUS``) is stripped from the start of a line first.
    """

    GLUED_STATUS = (b"i2c write failed",)  # printed without a newline by the 2020 library

    def __init__(self, options: FrameOptions = FrameOptions(), skip_first_lines: int = 0):
        self.options = options
        self.stats = ParserStats()
        self._pending = bytearray()
        self._lines_to_skip = skip_first_lines
        n = options.cells
        field = rb"(?:0|[1-9][0-9]{0,4})?"
        self._frame_re = re.compile(field + rb"(?:," + field + rb"){%d}" % (n - 1))
        self._commas = n - 1
        self._max_line = 6 * n  # n fields of at most 5 digits and n - 1 commas
        # Keep a little more than two frame lines of an unterminated line, so a frame glued behind
        # newline-less status text survives the trimming of the pending buffer.
        self._max_pending = 2 * (6 * n + 64)

    def feed(self, data: bytes) -> list[np.ndarray]:
        """Parse ``data``; returns the complete frames it finished, in order."""
        self._pending += data
        end = max(self._pending.rfind(b"\n"), self._pending.rfind(b"\r"))
        frames = []
        if end >= 0:
            complete = bytes(self._pending[:end])
            del self._pending[: end + 1]
            for line in complete.replace(b"\r", b"\n").split(b"\n"):
                frame = self.parse_line(line)
                if frame is not None:
                    frames.append(frame)
        if len(self._pending) > self._max_pending:
            self.stats.dropped_bytes += len(self._pending) - self._max_pending
            del self._pending[: len(self._pending) - self._max_pending]
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
        glued = False
        while line.startswith(self.GLUED_STATUS):
            line = line[len(next(s for s in self.GLUED_STATUS if line.startswith(s))):]
            glued = True
        values = self._values(line)
        if values is None:
            if line.startswith(STATUS_PREFIXES) or (glued and not line):
                self.stats.status_lines += 1
            else:
                self.stats.rejected_lines += 1
            return None
        self.stats.salvaged_lines += glued
        self.stats.frames += 1
        return self.options.orient(values)

    def _values(self, line: bytes) -> np.ndarray | None:
        """The fields of a frame line, or None when ``line`` is not exactly one frame."""
        if (len(line) > self._max_line or line.count(b",") != self._commas
                or line.translate(None, b"0123456789,") or not self._frame_re.fullmatch(line)):
            return None
        if b",," in line or line.startswith(b",") or line.endswith(b","):
            values = np.array([int(f) if f else 0 for f in line.split(b",")], dtype=np.int64)
        else:
            values = np.fromstring(line, dtype=np.int64, sep=",")  # decimal text, parsed in C
        if values.max(initial=0) > MAX_COUNT:
            return None
        return values


def make_parser(frame_format: str, options: FrameOptions, skip_first_lines: int = 0):
    """A fresh parser for ``frame_format``: ``"ascii"``, ``"handshake"`` (ASCII frames, one per
    host request: :mod:`.handshake`) or ``"binary"`` (:mod:`.binary_frames`)."""
    if frame_format in ("ascii", "handshake"):
        return AsciiFrameParser(options, skip_first_lines)
    if frame_format == "binary":
        from .binary_frames import BinaryFrameParser

        return BinaryFrameParser(options)
    raise UserError(f"unknown frame format {frame_format!r}: use {', '.join(FRAME_FORMATS)}")


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
