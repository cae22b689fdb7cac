"""The Muca binary raw format (Muca_Raw_Basic.ino ``SendRawByte``): per frame ``[min_hi, min_lo,
cells x uint8(value - min)]`` (254 bytes on a 21 x 12 board), streamed back to back with no sync
marker; values more than 255 above the frame's minimum wrap, as on the board.

Alignment is found and kept by plausibility. Cut at a frame boundary, a frame's payload holds a 0
(the firmware subtracts the frame's minimum) and its 16-bit minimum moves by at most
``BASE_STEP`` counts from one frame to the next (the smallest cell drifts slowly). Cut anywhere
else, the "minimum" is built from a payload byte (or the low byte of the minimum) as its high byte,
which changes with the noise of that cell and so jumps by multiples of 256 counts.

* At the start of the stream (after ASCII status lines such as ``[Muca] Initialized``) the parser
  assumes the stream starts on a boundary.
* A frame is released once the next frame's two header bytes confirm the boundary (or, on
  :meth:`flush`, when the stream pauses and the frame checks out on its own); so a dropped byte
  never releases a frame whose tail is shifted: the frame it falls in is dropped.
* A frame that checks out on its own but not with the next frame's header (garbage follows it, or it
  holds a byte of the next frame after a lost one) is dropped whole before the search, when a frame
  before it was confirmed: no frame starts inside it (a "frame" cut from its tail and what follows can
  pass every check by chance; a frame it held the start of is lost, at most two per incident).
* A frame that fails sends the parser searching: over ``SEARCH_FRAMES`` frames' worth of bytes it
  tries every offset up to two frames and, among those whose frames all pass (of two a frame apart,
  the first), locks on the first whose minimum is near the last one seen (within ``4 BASE_STEP``),
  then very near it (within ``BASE_STEP / 4``: on a quiet board an offset a byte off can look as
  steady as the boundary), then with the fewest changes of the minimum's high byte, then not below
  256 counts, then with the smallest total change; the bytes before it are counted in
  ``stats.dropped_bytes``, each loss of lock in ``stats.resyncs``. A noise-free stream (every cell
  constant) would leave the offset ambiguous.
"""
from __future__ import annotations

import numpy as np

from .frames import STATUS_PREFIXES, FrameOptions, ParserStats

BASE_STEP = 128  # largest change (counts) of a frame's minimum from one frame to the next
SEARCH_FRAMES = 8  # frames of bytes a search scores each offset on


class BinaryFrameParser:
    """Incremental, self-aligning parser of the binary format; feed it bytes in any chunking."""

    def __init__(self, options: FrameOptions = FrameOptions()):
        self.options = options
        self.stats = ParserStats()
        self.frame_bytes = 2 + options.cells
        self.reset()

    def reset(self) -> None:
        """Forget the stream (after a reconnect): the next bytes start a new one."""
        self._pending = bytearray()
        self._base: int | None = None  # minimum of the last frame released while locked
        self._last_base: int | None = None  # ... kept across a loss of lock
        self._locked = True  # a fresh stream is assumed to start on a boundary
        self._at_start = True  # status lines may come first

    def feed(self, data: bytes) -> list[np.ndarray]:
        """Parse ``data``; returns the frames it confirmed, in order."""
        self._pending += data
        frames: list[np.ndarray] = []
        if self._at_start:
            self._drop_status_lines()
            if self._at_start:
                return frames
        n = self.frame_bytes
        while True:
            if not self._locked and not self._search():
                return frames
            if len(self._pending) < n + 2:
                return frames
            chunk = bytes(self._pending[:n])
            frame = self._checked(chunk, (self._pending[n] << 8) | self._pending[n + 1])
            if frame is None:
                if self._base is not None and self._plausible(chunk):
                    self.stats.dropped_bytes += n
                    del self._pending[:n]
                self._lose_lock()
                continue
            del self._pending[:n]
            frames.append(frame)

    def flush(self) -> list[np.ndarray]:
        """The stream paused (a read timeout without a byte): search over the frames buffered if the
        lock was lost, release a complete pending frame that checks out on its own, drop any rest."""
        frames: list[np.ndarray] = []
        if not self._pending or self._at_start:
            return frames
        if not self._locked and self._search(min(SEARCH_FRAMES, len(self._pending) // self.frame_bytes - 2)):
            frames += self.feed(b"")  # a search over the frames there are, as the stream may not go on
        if self._locked and len(self._pending) == self.frame_bytes:
            frame = self._checked(bytes(self._pending))
            if frame is not None:
                frames.append(frame)
                self._pending.clear()
        if self._pending:
            self.stats.dropped_bytes += len(self._pending)
            self._pending.clear()
        self._locked = True  # after a pause the board starts its next frame on a boundary
        return frames

    def _plausible(self, chunk: bytes, next_base: int | None = None) -> bool:
        """Whether ``chunk`` can be a frame after the last one and before the next frame's minimum
        ``next_base`` (when known)."""
        base = (chunk[0] << 8) | chunk[1]
        return bool(np.frombuffer(chunk, dtype=np.uint8, offset=2).min() == 0
                    and (self._base is None or abs(base - self._base) <= BASE_STEP)
                    and (next_base is None or abs(next_base - base) <= BASE_STEP))

    def _checked(self, chunk: bytes, next_base: int | None = None) -> np.ndarray | None:
        """The oriented frame of ``chunk`` if it is :meth:`_plausible`; sets the last frame's minimum."""
        if not self._plausible(chunk, next_base):
            return None
        base = (chunk[0] << 8) | chunk[1]
        payload = np.frombuffer(chunk, dtype=np.uint8, offset=2)
        self._base = self._last_base = base
        self.stats.frames += 1
        return self.options.orient(base + payload.astype(np.int64))

    def _lose_lock(self) -> None:
        self._locked = False
        self._base = None
        self.stats.resyncs += 1
        self.stats.rejected_lines += 1

    def _search(self, count: int = SEARCH_FRAMES) -> bool:
        """Lock on the best offset once ``count + 2`` frames of bytes are buffered; False while
        waiting for bytes (nothing is dropped until a decision)."""
        if count < 2:
            return False
        n = self.frame_bytes
        # Offsets up to two frames: the frame after garbage of up to a frame's length gets a clean window.
        starts = np.arange(2 * n)[:, None] + n * np.arange(count)[None]  # (offsets, frames)
        window = (count + 2) * n
        while True:
            if len(self._pending) < window:
                return False
            data = np.frombuffer(bytes(self._pending[:window]), dtype=np.uint8)
            bases = (data[starts].astype(np.int64) << 8) | data[starts + 1]
            payload_min = np.min(data[starts[..., None] + 2 + np.arange(n - 2)], axis=2)
            steps = np.abs(np.diff(bases, axis=1))
            passing = np.flatnonzero(np.all(payload_min == 0, axis=1) & np.all(steps <= BASE_STEP, axis=1))
            if len(passing):
                passing = passing[np.unique(passing % n, return_index=True)[1]]  # one alignment: its first frame
                break
            self.stats.dropped_bytes += n
            del self._pending[:n]
        # The high byte of the true minimum changes only when the minimum crosses a multiple of 256;
        # a payload byte changes with its cell's noise (its 16-bit pair can still look steady when
        # the low byte wraps as the high byte steps).
        # A minimum below 256 counts (every cell under 512; FT5x16 raw counts are in the thousands) is
        # what the 0 byte of a steady smallest cell and its neighbour's byte look like.
        high_changes = np.count_nonzero(np.diff(bases[passing] >> 8, axis=1), axis=1)
        tiny = bases[passing, 0] < 256
        if self._last_base is None:
            near = far = np.zeros(len(passing), dtype=bool)
        else:
            away = np.abs(bases[passing, 0] - self._last_base)
            near, far = away <= BASE_STEP // 4, away > 4 * BASE_STEP
        offset = int(passing[np.lexsort((steps[passing].sum(axis=1), tiny, high_changes, ~near, far))[0]])
        self.stats.dropped_bytes += offset
        del self._pending[:offset]
        self._locked = True
        self._base = int(bases[offset, 0])
        return True

    def _drop_status_lines(self) -> None:
        """ASCII status lines the firmware prints before streaming are not frame bytes."""
        while self._pending.startswith(STATUS_PREFIXES):
            end = self._pending.find(b"\n")
            if end < 0:
                return
            self.stats.status_lines += 1
            del self._pending[: end + 1]
        if len(self._pending) >= max(len(prefix) for prefix in STATUS_PREFIXES) or not any(
                prefix.startswith(bytes(self._pending)) for prefix in STATUS_PREFIXES):
            self._at_start = False
