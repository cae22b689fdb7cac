"""The virtual board on a pseudo-terminal, so the real serial path (termios, pyserial, the parser) is
exercised; :func:`frames_through_pty` reads it back with :class:`.muca_serial.MucaReader`."""
from __future__ import annotations

import multiprocessing
import os
import pty
import select
import threading
import time
import tty
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..data.board import NUM_RX, NUM_TX
from .frames import FRAME_FORMATS, Frame, FrameOptions, encode_ascii_frame, encode_binary_frame
from .handshake import REQUEST, SYNC_PERIOD_S, sync_line
from .muca_serial import MucaReader
from .scripts import Script
from .virtual_board import VirtualBoard


class LinkCutShort(RuntimeError):
    """The reader got fewer of a finite stream's frames than the board sent."""


class PtyBoard:
    """Serves a virtual board's frames on a pseudo-terminal; open :attr:`port` with pyserial.

    Speaks ``frame_format``: ``"ascii"`` or ``"binary"`` streamed, or ``"handshake"`` (SYNC lines
    until the host answers, then one ASCII frame per request byte, :mod:`.handshake`).
    Paced at ``rate_hz`` of board time, or as fast as the reader drains the pty when ``fast``; with
    ``separate_process`` the board runs in a forked process (as a real board runs on its own chip);
    ``prerender`` (fast mode, finite) synthesizes all frames before writing the first one.
    Frame ``k`` shows the script at board time ``k / rate_hz``. Stops after the script's duration
    (or ``frames`` frames if given; ``loop`` repeats the script forever). For tests of a bad link,
    every ``garbage_every``-th frame comes after status text and garbage, and every
    ``drop_byte_every``-th frame loses one byte.
    """

    def __init__(
        self,
        board: VirtualBoard,
        script: Script | None = None,
        frame_format: str = "ascii",
        fast: bool = False,
        frames: int | None = None,
        loop: bool = False,
        garbage_every: int = 0,
        separate_process: bool = False,
        prerender: bool = False,
        drop_byte_every: int = 0,
    ):
        if frame_format not in FRAME_FORMATS:
            raise ValueError(f"unknown frame format {frame_format!r}")
        self.board = board
        self.script = script
        self.frame_format = frame_format
        self.fast = fast
        self.rate_hz = board.params.rate_hz
        if frames is None:
            frames = int(np.ceil(script.duration * self.rate_hz)) if script is not None else None
        self.frames_total = None if loop else frames
        self.loop = loop
        self.garbage_every = garbage_every
        self.drop_byte_every = drop_byte_every
        if prerender and (not fast or self.frames_total is None):
            raise ValueError("prerender needs fast mode and a finite number of frames")
        self.prerender = prerender
        self.master, self.slave = pty.openpty()
        tty.setraw(self.slave)
        self.port = os.ttyname(self.slave)
        if separate_process:
            # A board of its own: frame synthesis does not compete with the reader for the GIL.
            context = multiprocessing.get_context("fork")
            self.done, self._stop = context.Event(), context.Event()
            self._thread = context.Process(target=self._run, name="muca-simulator", daemon=True)
        else:
            self.done, self._stop = threading.Event(), threading.Event()
            self._thread = threading.Thread(target=self._run, name="muca-simulator", daemon=True)

    def __enter__(self) -> PtyBoard:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def start(self) -> None:
        self._thread.start()

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view and not self._stop.is_set():
            written = os.write(self.master, view)
            view = view[written:]

    def _frame_bytes(self, k: int) -> bytes:
        t = k / self.rate_hz
        script_t = t % self.script.duration if (self.script is not None and self.loop) else t
        fingers = self.script.fingers_at(script_t) if self.script is not None else []
        grid = self.board.frame(t, fingers)
        data = encode_binary_frame(grid) if self.frame_format == "binary" else encode_ascii_frame(grid)
        if self.drop_byte_every and k % self.drop_byte_every == self.drop_byte_every - 1:
            cut = (k * 7919) % len(data)
            data = data[:cut] + data[cut + 1:]
        if self.garbage_every and k % self.garbage_every == self.garbage_every - 1:
            data = b"Calibration performed 3/20\r\n\x00\xff garbage,12,\r\n" + data
        return data

    def _run(self) -> None:
        try:
            frames = (self._frame_bytes(k) for k in self._indices())
            if self.prerender:
                # Synthesize every frame first, then only write: the stream runs at the reader's pace.
                frames = iter([b"".join(frames)] if self.frame_format != "handshake" else list(frames))
            self._write(b"[Muca] Initialized\r\n[Muca] Set TEST mode\r\n")
            if self.frame_format == "handshake":
                self._serve_requests(frames)
                return
            start = time.monotonic()
            for k, data in enumerate(frames):
                if not self.fast and not self.prerender:
                    delay = start + k / self.rate_hz - time.monotonic()
                    if delay > 0:
                        self._stop.wait(delay)
                self._write(data)
        except OSError:
            pass  # the reader side went away
        finally:
            self.done.set()

    def _indices(self) -> Iterator[int]:
        k = 0
        while not self._stop.is_set() and (self.frames_total is None or k < self.frames_total):
            yield k
            k += 1

    def _serve_requests(self, frames: Iterator[bytes]) -> None:
        """The handshake variant: SYNC lines every 0.5 s until the host sends a byte, then one frame
        per request (request bytes waiting when a frame starts are drained: one frame for them all)."""
        sync = sync_line(NUM_RX, NUM_TX)
        while not self._stop.is_set():
            self._write(sync)
            if select.select([self.master], [], [], SYNC_PERIOD_S)[0]:
                os.read(self.master, 4096)  # the answer ends the SYNC phase
                break
        start = time.monotonic()
        k = 0
        while not self._stop.is_set():
            if not select.select([self.master], [], [], 0.1)[0] or REQUEST not in os.read(self.master, 4096):
                continue
            data = next(frames, None)
            if data is None:
                return
            if not self.fast:
                delay = start + k / self.rate_hz - time.monotonic()
                if delay > 0:
                    self._stop.wait(delay)
            self._write(data)
            k += 1

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        if isinstance(self._thread, multiprocessing.process.BaseProcess) and self._thread.is_alive():
            self._thread.kill()  # blocked writing into a pty nobody reads any more
            self._thread.join()
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


def frames_through_pty(
    board: VirtualBoard,
    script: Script | None,
    fast: bool = True,
    frame_format: str = "ascii",
    frames: int | None = None,
    garbage_every: int = 0,
    record: str | Path | None = None,
    loop: bool = False,
    separate_process: bool = False,
    prerender: bool = False,
    drop_byte_every: int = 0,
    on_status=None,
) -> Iterator[Frame]:
    """Run ``board`` on a pseudo-terminal and read it back with :class:`MucaReader` (the real serial
    path). Frames carry board time ``seq / rate_hz`` (s), so fast mode keeps the script's timing.
    Ends after the board's last frame (never with ``loop``); the script's labels go into the recording.
    Raises :class:`LinkCutShort` when a finite stream ends before its last frame came through (the
    reader lost the port; not counted with ``drop_byte_every``, which loses frames on purpose), so that
    no caller scores a stream cut short."""
    simulator = PtyBoard(board, script, frame_format=frame_format, fast=fast, frames=frames,
                         garbage_every=garbage_every, loop=loop, separate_process=separate_process,
                         prerender=prerender, drop_byte_every=drop_byte_every)
    options = FrameOptions(flip_tx=board.params.flip_tx, flip_rx=board.params.flip_rx)
    last_status = ["the port went quiet"]

    def status(line: str) -> None:
        last_status[0] = line
        if on_status is not None:
            on_status(line)

    # Open before the board starts: pyserial flushes the input queue when it opens a port.
    reader = MucaReader(simulator.port, frame_format=frame_format, options=options, record=record,
                        reconnect_timeout_s=0.0, on_status=status,
                        record_header={"timebase": "board", "rate_hz": board.params.rate_hz, "simulated": True})
    simulator.start()
    if reader.recorder is not None and script is not None:
        for t, label in script.labels:
            reader.recorder.label(label, t=t)
    stalled = threading.Event()

    def watchdog() -> None:
        # The reader blocks on the port: end it once the board is done and no frame came for 5 s
        # (only if frames were lost; normally the loop below stops at the board's last frame).
        seen, quiet = -1, 0
        while not stalled.wait(0.5):
            quiet = quiet + 1 if simulator.done.is_set() and reader_seq[0] == seen else 0
            if quiet >= 10:
                reader.close()
                return
            seen = reader_seq[0]

    reader_seq = [0]
    guard = threading.Thread(target=watchdog, daemon=True)
    guard.start()
    try:
        for frame in reader.frames():
            yield Frame(frame.values, frame.seq / board.params.rate_hz, frame.seq)
            reader_seq[0] = frame.seq + 1
            if simulator.frames_total is not None and reader_seq[0] >= simulator.frames_total:
                break
        if simulator.frames_total is not None and reader_seq[0] < simulator.frames_total and not drop_byte_every:
            raise LinkCutShort(f"the virtual board's stream ended after {reader_seq[0]} of {simulator.frames_total} "
                               f"frames ({last_status[0]})")
    finally:
        stalled.set()
        reader.close()
        simulator.stop()
        guard.join()
