"""``retrotouch sense --probe PORT``: listen to a serial port for a bounded time and say what is on
it: the frame format (``ascii``, ``binary``, ``handshake``, ``touch-point`` or ``unknown``), the frame
rate, the channel count and the ``sense`` command that reads it.

A handshake board (SYNC lines, :mod:`.handshake`) is answered and asked for frames, as ``sense``
would; every other board is only listened to. Raw ASCII frames are recognised by
:class:`.frames.AsciiFrameParser`, binary ones by :class:`.binary_frames.BinaryFrameParser`
(self-aligning); touch-point lines (``id:flag:x:y:weight|...``, the firmware's touch mode) carry no
raw frames, so ``sense`` cannot use them.
"""
from __future__ import annotations

import json
import re
import time
from collections.abc import Callable
from typing import Any

import serial

from ...graph.errors import UserError
from ..data.board import NUM_RX, NUM_TX
from .binary_frames import BinaryFrameParser
from .frames import AsciiFrameParser
from .handshake import REQUEST, SyncWatch

_TOUCH_POINT = re.compile(rb"\d+:[0-2]:\d+:\d+:\d+(?:\|\d+:[0-2]:\d+:\d+:\d+)*\|?")
BAUD_RATES = (115200, 250000, 500000, 1000000)


def _rate(times: list[float]) -> float | None:
    """Frames per second from the arrival times of frames (s)."""
    return (len(times) - 1) / (times[-1] - times[0]) if len(times) >= 2 and times[-1] > times[0] else None


def _listen(port_handle, seconds: float) -> tuple[list[tuple[float, bytes]], SyncWatch, list[float]]:
    """Bytes (with arrival times) for ``seconds``; a handshake board is answered and polled for frames
    (their arrival times are the third result)."""
    sync, frames = SyncWatch(), []
    parser: AsciiFrameParser | None = None
    chunks: list[tuple[float, bytes]] = []
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        data = port_handle.read(max(1, port_handle.in_waiting or 1))
        now = time.monotonic()
        if data:
            chunks.append((now, data))
        if parser is None and sync.feed(data):
            port_handle.write(REQUEST + REQUEST)  # the answer and the first request
            parser = AsciiFrameParser()
        elif parser is not None:
            found = parser.feed(data) if data else []
            if found or not data:
                port_handle.write(REQUEST)
            frames += [now] * len(found)
    return chunks, sync, frames


def probe_port(port: str, baudrate: int = 115200, seconds: float = 3.0,
               open_port: Callable[[], Any] | None = None) -> dict[str, Any]:
    """What is on ``port`` (see the module docstring), as a JSON-ready dict."""
    try:
        handle = open_port() if open_port else serial.serial_for_url(port, baudrate=baudrate, timeout=0.05)
    except (serial.SerialException, OSError, ValueError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise UserError(f"cannot open serial port {port} ({first}): check the cable and --probe") from None
    try:
        chunks, sync, handshake_frames = _listen(handle, seconds)
    finally:
        handle.close()
    data = b"".join(chunk for _, chunk in chunks)
    report: dict[str, Any] = {"port": port, "baud": baudrate, "seconds": seconds, "bytes": len(data),
                              "format": "unknown", "frames": 0, "frames_per_s": None, "rx": None, "tx": None}
    if sync.sync_lines:
        rx, tx = sync.channels
        report.update(format="handshake", frames=len(handshake_frames), frames_per_s=_rate(handshake_frames),
                      rx=rx, tx=tx)
    else:
        report.update(_classify(chunks))
    report["frames_per_s"] = None if report["frames_per_s"] is None else round(report["frames_per_s"], 2)
    report["command"] = _command(report)
    return report


def _classify(chunks: list[tuple[float, bytes]]) -> dict[str, Any]:
    """The format of a stream that was only listened to: ASCII frames, touch-point lines, binary frames."""
    ascii_parser, binary_parser = AsciiFrameParser(), BinaryFrameParser()
    ascii_times, binary_times = [], []
    for t, chunk in chunks:
        ascii_times += [t] * len(ascii_parser.feed(chunk))
        binary_times += [t] * len(binary_parser.feed(chunk))
    binary_times += [chunks[-1][0]] * len(binary_parser.flush()) if chunks else []
    lines = b"".join(chunk for _, chunk in chunks).replace(b"\r", b"\n").split(b"\n")
    touch_lines = sum(bool(_TOUCH_POINT.fullmatch(line.strip())) for line in lines)
    if len(ascii_times) >= 2:
        return {"format": "ascii", "frames": len(ascii_times), "frames_per_s": _rate(ascii_times), "rx": NUM_RX, "tx": NUM_TX}
    if touch_lines >= 2:
        return {"format": "touch-point", "frames": touch_lines, "frames_per_s": _rate([t for t, _ in chunks])}
    if len(binary_times) >= 3:
        return {"format": "binary", "frames": len(binary_times), "frames_per_s": _rate(binary_times),
                "rx": NUM_RX, "tx": NUM_TX}
    return {}


def _command(report: dict[str, Any]) -> str:
    """What to run next for the probed format."""
    port, baud, fmt = report["port"], report["baud"], report["format"]
    if fmt in ("ascii", "binary", "handshake"):
        return f"retrotouch sense --port {port} --format {fmt} --baud {baud} --layout RUN_FOLDER"
    if fmt == "touch-point":
        return ("flash a raw sketch (Muca_Raw for ascii, Muca_Raw_Basic for binary): sense needs raw frames, "
                "not touch points")
    if report["bytes"] == 0:
        return "nothing received: check the port, that the board is powered and running (press reset)"
    others = ", ".join(str(rate) for rate in BAUD_RATES if rate != baud)
    return f"unrecognised bytes: probe again with --baud {others}"


def summary_line(report: dict[str, Any]) -> str:
    """One line for the terminal."""
    fmt = report["format"]
    rate = "rate unknown" if report["frames_per_s"] is None else f"{report['frames_per_s']:.1f} frames/s"
    channels = f", {report['rx']} RX x {report['tx']} TX" if report["rx"] else ""
    what = {"touch-point": "touch-point lines", "unknown": f"unknown ({report['bytes']} bytes)"}.get(fmt, f"{fmt} frames")
    return f"{report['port']}: {what}, {rate}{channels} in {report['seconds']:g} s; {report['command']}"


def run_probe(port: str, baudrate: int, seconds: float, as_json: bool) -> None:
    """Probe ``port`` and print the report (one line, or one JSON object)."""
    if seconds <= 0:
        raise UserError(f"--probe-seconds {seconds:g}: give a positive time, e.g. 3")
    report = probe_port(port, baudrate, seconds)
    print(json.dumps(report) if as_json else summary_line(report), flush=True)
