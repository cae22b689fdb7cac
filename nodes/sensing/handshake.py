"""The Muca firmware's handshake variant: after reset the board repeats ``RX:<n>:TX:<m>:SYNC``
(CRLF) every 500 ms until the host sends a byte; from then on it sends one ASCII frame line
(:mod:`.frames`) per request byte ``s`` from the host. A board drains every request byte waiting
when it starts a frame, so extra requests never queue up more than one frame.

The host (:class:`.muca_serial.MucaReader`) answers a SYNC line with ``s`` and requests the first
frame with another ``s``, requests the next frame as soon as a frame line is complete (the board
scans while the host processes), and requests again after a read timeout without a byte (a lost
request, or a board that was already answered before the host connected).
"""
from __future__ import annotations

import re

REQUEST = b"s"
SYNC_PERIOD_S = 0.5
_SYNC_LINE = re.compile(rb"RX:(\d{1,3}):TX:(\d{1,3}):SYNC")


def sync_line(num_rx: int, num_tx: int) -> bytes:
    """The board's SYNC announcement for its channel counts."""
    return b"RX:%d:TX:%d:SYNC\r\n" % (num_rx, num_tx)


class SyncWatch:
    """Finds SYNC lines in a byte stream fed in any chunking; remembers the channel counts."""

    def __init__(self):
        self.channels: tuple[int, int] | None = None  # (rx, tx) of the last SYNC line
        self.sync_lines = 0
        self._tail = b""

    def feed(self, data: bytes) -> int:
        """SYNC lines completed by ``data``."""
        text = self._tail + data
        found = list(_SYNC_LINE.finditer(text))
        if found:
            self.channels = (int(found[-1].group(1)), int(found[-1].group(2)))
            text = text[found[-1].end():]
        self._tail = text[-24:]  # a SYNC line is at most 22 bytes
        self.sync_lines += len(found)
        return len(found)
