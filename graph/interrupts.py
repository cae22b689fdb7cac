"""Ctrl-C and SIGTERM: one clean stop, wherever the run is.

:func:`install` (called first thing by the entry point) turns the first SIGINT or SIGTERM into an
:class:`Interrupted` exception and ignores any further one, so the ``finally`` blocks that remove
temp folders and stop worker processes run to the end. :class:`Interrupted` derives from
``BaseException`` (not ``KeyboardInterrupt``), so no library on the way up (click, dask) reports
or swallows it; the command line prints one ``interrupted`` line and exits 130 (143 for SIGTERM).
Inside :func:`deferred` a signal is held until the block ends (for steps that must not be cut in
half, such as swapping the output folder).

A library may still swallow the exception (some guard their optional imports with ``except
BaseException``, and a C extension whose initialisation is cut reports an ImportError instead), so
the signal is also remembered: :func:`check` raises it again (called by loops that would otherwise
run on forever), and :func:`requested` tells an error handler that an error came from it.
"""
from __future__ import annotations

import contextlib
import signal
import sys
import threading
from typing import Iterator

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Interrupted(BaseException):
    """The operator stopped the run (Ctrl-C or SIGTERM)."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


_depth = 0
_pending: int | None = None
_received: Interrupted | None = None


def _handler(signum: int, frame: object) -> None:
    global _pending, _received
    ignore()
    _received = Interrupted(signum)
    if _depth:
        _pending = signum
        return
    raise Interrupted(signum)


def requested() -> Interrupted | None:
    """The interruption received, if any."""
    return _received


def check() -> None:
    """Raise the interruption again if one was received (and swallowed on its way up)."""
    if _received is not None:
        raise Interrupted(_received.signum)


def install() -> dict[int, object]:
    """Handle SIGINT/SIGTERM as described in the module docstring (main thread only); returns the
    previous handlers, for :func:`restore`."""
    previous: dict[int, object] = {}
    if threading.current_thread() is threading.main_thread():
        for signum in SIGNALS:
            previous[signum] = signal.signal(signum, _handler)
    return previous


def restore(previous: dict[int, object]) -> None:
    """Put back the handlers :func:`install` replaced."""
    global _pending, _received
    _pending = _received = None
    for signum, handler in previous.items():
        signal.signal(signum, handler)  # type: ignore[arg-type]


def ignore() -> None:
    """Ignore SIGINT/SIGTERM from now on (once stopping, or once the command is done)."""
    if threading.current_thread() is threading.main_thread():
        for signum in SIGNALS:
            signal.signal(signum, signal.SIG_IGN)


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """Hold an interruption until the block has finished, then raise it."""
    global _depth, _pending
    _depth += 1
    try:
        yield
    finally:
        _depth -= 1
        if _depth == 0 and _pending is not None:
            signum, _pending = _pending, None
            raise Interrupted(signum)


def exit_interrupted(program: str, exc: Interrupted) -> None:
    """Print the one ``interrupted`` line and exit with the signal's code (for entry points,
    interrupted before the command line's own handling is in place)."""
    ignore()
    print(f"{program}: error: interrupted", file=sys.stderr)
    sys.exit(exc.exit_code)
