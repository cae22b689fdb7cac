"""Muca board serial input: a tolerant reader over pyserial that reconnects after an unplug and
can record the session (:mod:`.recording`); frames are parsed by :mod:`.frames`."""
from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import serial

from ...graph.errors import UserError
from .frames import Frame, FrameOptions, make_parser
from .handshake import REQUEST, SyncWatch
from .recording import Recorder


class MucaReader:
    """Frames from a Muca board on ``port`` (a device path or any pyserial URL).

    ``frame_format`` is ``"ascii"``, ``"binary"`` (self-aligning, :mod:`.binary_frames`) or
    ``"handshake"`` (the reader answers the board's SYNC and requests every frame,
    :mod:`.handshake`). Tolerant: garbage never raises (``on_status`` gets one line, at most every
    ``status_interval_s``, when lines are rejected or the binary alignment is searched again); after an unplug (read error) the port is closed and reopened
    every ``reconnect_interval_s`` until it is back (or ``reconnect_timeout_s`` passes). A port that
    cannot be opened at start is a one-line :class:`UserError`. ``on_status`` (if given) receives one
    line when the board goes away, one every ``status_interval_s`` while the reader waits for it
    (with the time waited), and one when it is back or the wait is given up.
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
        on_status: Callable[[str], None] | None = None,
        status_interval_s: float = 10.0,
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
        self.on_status = on_status
        self.status_interval_s = status_interval_s
        self._open_port = open_port or (lambda: serial.serial_for_url(port, baudrate=baudrate, timeout=read_timeout_s))
        self._serial: serial.SerialBase | None = None
        self._closed = False
        self._seq = 0
        self._sync = SyncWatch() if frame_format == "handshake" else None
        self._garbled_reported = 1  # joining mid-line (or mid-frame) costs one rejection: not garble
        self._next_garble_status = 0.0
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
                if not data and self._sync is not None:
                    self._serial.write(REQUEST)  # a lost request, or a board answered before
                elif self._sync is not None and self._sync.feed(data):
                    self._serial.write(REQUEST + REQUEST)  # answer the SYNC, request the first frame
            except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
                # TypeError/AttributeError: pyserial's posix backend after the fd went away.
                if self._closed:
                    return
                self._status(f"board on {self.port} went away at {_clock()} ({_short(exc)[:80]}): "
                             "waiting for it to come back (Ctrl-C to stop)")
                self._drop_port()
                continue
            now = time.monotonic()
            if not data:
                # A whole read timeout without a byte: the board is between frames.
                found = [] if idle or not hasattr(self.parser, "flush") else self.parser.flush()
                idle = True
            else:
                idle = False
                if self.recorder is not None:
                    self.recorder.bytes(data)
                found = self.parser.feed(data)
                self._report_garble(now)
            for values in found:
                if self._sync is not None:
                    self._request()
                yield Frame(values, now, self._seq)
                self._seq += 1

    def _request(self) -> None:
        """Ask a handshake board for its next frame (a failed write shows at the next read)."""
        try:
            self._serial.write(REQUEST)
        except (serial.SerialException, OSError, TypeError, AttributeError):
            pass

    def _report_garble(self, now: float) -> None:
        """One status line (at most every ``status_interval_s``) when input was rejected."""
        stats = self.parser.stats
        garbled = stats.rejected_lines
        if garbled > self._garbled_reported and now >= self._next_garble_status:
            what = "lost frame alignments" if self.frame_format == "binary" else "unparsable lines"
            self._status(f"board on {self.port}: {garbled - self._garbled_reported} {what} at {_clock()}, "
                         f"resynced ({stats.frames} frames so far)")
            self._garbled_reported = garbled
            self._next_garble_status = now + self.status_interval_s

    def _drop_port(self) -> None:
        try:
            self._serial.close()
        except Exception:  # noqa: BLE001 - a dead port may fail to close in many ways; it is gone either way
            pass
        self._serial = None
        self.parser.reset()

    def _reconnect(self) -> bool:
        started = time.monotonic()
        deadline = None if self.reconnect_timeout_s is None else started + self.reconnect_timeout_s
        next_status = started + self.status_interval_s
        while not self._closed:
            try:
                self._serial = self._open_port()
                self.reconnects += 1
                self._garbled_reported = self.parser.stats.rejected_lines + 1
                self._status(f"board on {self.port} is back at {_clock()} after {time.monotonic() - started:.1f} s")
                return True
            except (serial.SerialException, OSError, ValueError):
                now = time.monotonic()
                if deadline is not None and now > deadline:
                    self._status(f"board on {self.port} did not come back within {self.reconnect_timeout_s:g} s: "
                                 "stopping")
                    return False
                if now >= next_status:
                    self._status(f"still waiting for the board on {self.port} ({now - started:.0f} s, since "
                                 f"{_clock(time.time() - (now - started))})")
                    next_status += self.status_interval_s
                time.sleep(self.reconnect_interval_s)
        return False

    def _status(self, line: str) -> None:
        if self.on_status is not None:
            self.on_status(line)

    def close(self) -> None:
        self._closed = True
        if self._serial is not None:
            self._drop_port()
        if self.recorder is not None:
            self.recorder.close()


def _short(exc: BaseException) -> str:
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__


def _clock(when: float | None = None) -> str:
    """Local wall-clock time ``HH:MM:SS`` (now, or at ``when`` seconds since the epoch)."""
    return time.strftime("%H:%M:%S", time.localtime(when))
