"""Where ``sense`` sends its events: stdout (JSON lines), UDP datagrams and websocket clients.

Every event carries ``"format": EVENTS_FORMAT``; the stream is specified by
``nodes/data/events.schema.json`` (touch, gesture and status events)."""
from __future__ import annotations

import json
import socket
import sys
import threading
from collections.abc import Iterable
from typing import Any

from ...graph.errors import UserError

MAX_PORT = 65535  # the largest TCP/UDP port number

EVENTS_FORMAT = "retrotouch.events/1"


def status_event(kind: str, message: str, t: float | None = None) -> dict[str, Any]:
    """A ``status`` event (kind ``board``, ``baseline`` or ``calibration``; ``t`` s or None)."""
    return {"type": "status", "t": None if t is None else round(t, 4), "kind": kind, "message": message}


def _udp_target(text: str) -> tuple[str, int]:
    """``--udp HOST:PORT`` -> (IPv4 address, port), the host resolved once here, not per event."""
    host, _, digits = text.rpartition(":")
    if not host or not digits.isdigit():
        raise UserError(f"--udp {text!r}: give HOST:PORT, e.g. --udp 127.0.0.1:9000")
    port = int(digits)
    if not 1 <= port <= MAX_PORT:
        raise UserError(f"--udp {text}: the port must be 1-{MAX_PORT}")
    try:
        address = socket.getaddrinfo(host, port, socket.AF_INET, socket.SOCK_DGRAM)[0][4][0]
    except (socket.gaierror, UnicodeError):
        raise UserError(f"--udp {text}: cannot resolve host {host} to an IPv4 address: check the name") from None
    return address, port


class EventSinks:
    """Fans each event out to stdout, UDP targets and websocket clients."""

    def __init__(self, stdout: bool = True, udp: Iterable[str] = (), websocket_port: int | None = None):
        self.stdout = stdout
        self.udp_targets = [_udp_target(target) for target in udp]
        self.udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM) if self.udp_targets else None
        self.websocket_server = None
        self._clients: set[Any] = set()
        self._lock = threading.Lock()
        if websocket_port is not None:
            self._start_websocket(websocket_port)

    def _start_websocket(self, port: int) -> None:
        from websockets.exceptions import ConnectionClosed
        from websockets.sync.server import serve

        def handler(connection) -> None:
            with self._lock:
                self._clients.add(connection)
            try:
                for _ in connection:  # clients only listen; drain until they leave
                    pass
            except ConnectionClosed:
                pass
            finally:
                with self._lock:
                    self._clients.discard(connection)

        try:
            self.websocket_server = serve(handler, "127.0.0.1", port)
        except OSError as exc:
            raise UserError(f"--websocket {port}: cannot listen ({exc.strerror}): pick another port") from None
        threading.Thread(target=self.websocket_server.serve_forever, name="websocket", daemon=True).start()
        print(f"websocket events on ws://127.0.0.1:{self.websocket_server.socket.getsockname()[1]}/", file=sys.stderr)

    def emit(self, event: dict[str, Any]) -> None:
        """Send one event (its ``format`` added) to every sink."""
        line = json.dumps({"format": EVENTS_FORMAT, **event}, separators=(",", ":"))
        if self.stdout:
            sys.stdout.write(line + "\n")
            sys.stdout.flush()
        if self.udp is not None:
            for target in self.udp_targets:
                self.udp.sendto(line.encode(), target)
        with self._lock:
            clients = list(self._clients)
        for client in clients:
            try:
                client.send(line)
            except Exception:  # noqa: BLE001 - a client that went away is dropped on its own thread
                pass

    def close(self) -> None:
        if self.websocket_server is not None:
            self.websocket_server.shutdown()
        if self.udp is not None:
            self.udp.close()
