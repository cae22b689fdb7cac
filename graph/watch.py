"""``watch PIPELINE``: rerun on every save of the pipeline file and serve one local page of the result.

The page (http://127.0.0.1:PORT/) shows the state of the last run (ok, running, or its one-line
error), the pipeline graph with each node's state (cached, queued, running, ran, failed), and the
files of the last good output folder: images (PNG, SVG: previews, cut sheets) inline, HTML files
(interactive previews) in frames, JSON and CSV files as tables, the rest as links. It polls
``/state.json`` once a second, updates the node states in place and reloads itself when a new
result is written. A pipeline that fails (a YAML typo, a bad param, a failing node) shows the error
and keeps the last good result on the page (and in the output folder, which is only ever replaced
as a whole). Runs happen in the main thread, so Ctrl-C stops the watch like a run.
"""
from __future__ import annotations

import hashlib
import http.server
import json
import os
import re
import threading
import time
import urllib.parse
from typing import Any, Callable, Iterator

from . import dag
from .errors import NodeFailed, UserError
from .watch_page import render_page

STATE_ORDER = ("failed", "running", "queued", "ran", "cached", "skipped")
"""How branch states combine into a node's state: the first one any branch has."""


class WatchState:
    """What the page shows; written by the watch loop, read by the server threads."""

    def __init__(self, pipeline: str, out_dir: str):
        self.lock = threading.Lock()
        self.pipeline_file = pipeline
        self.out_dir = os.path.abspath(out_dir)
        self.version = 0  # bumps on every change
        self.result_version = 0  # bumps when a new output folder was written
        self.runs = 0
        self.phase = "starting"
        self.error = ""
        self.summary = ""
        self.pipeline: Any = None  # the last pipeline that parsed (for the graph)
        self.branches: dict[str, dict[str, str]] = {}  # node -> instance id -> state
        self.files: list[dict[str, Any]] = []  # of the last good output folder

    def _bump(self) -> None:
        self.version += 1

    def node_states(self) -> dict[str, str]:
        out = {}
        for node, states in self.branches.items():
            found = set(states.values())
            out[node] = next((s for s in STATE_ORDER if s in found), "skipped")
        return out

    def snapshot(self) -> dict[str, Any]:
        with self.lock:
            nodes = self.node_states()
            return {"version": self.version, "result_version": self.result_version, "runs": self.runs,
                    "phase": self.phase, "error": self.error, "summary": self.summary,
                    "pipeline": self.pipeline_file, "out_dir": self.out_dir, "files": self.files,
                    "nodes": [{"node": n, "state": s, "branches": len(self.branches[n])} for n, s in nodes.items()]}

    # -- events from the watch loop --------------------------------------------------------------
    def begin(self) -> None:
        with self.lock:
            self.runs += 1
            self.phase, self.error = "running", ""
            self._bump()

    def parsed(self, pipeline: Any) -> None:
        with self.lock:
            self.pipeline = pipeline
            self.branches = {name: {} for name in pipeline.nodes}
            self._bump()

    def planned(self, plan: Any) -> None:
        with self.lock:
            self.branches = {}
            for inst in plan.instances:
                self.branches.setdefault(inst.node, {})[inst.id] = "queued" if inst.runs else "cached"
            self._bump()

    def set_branch(self, instance_id: str, state: str) -> None:
        with self.lock:
            node = instance_id.split("[", 1)[0]
            self.branches.setdefault(node, {})[instance_id] = state
            self._bump()

    def succeeded(self, result: Any) -> None:
        with self.lock:
            ran = len(result.ran())
            self.phase, self.error = "ok", ""
            self.summary = f"{ran} ran, {len(result.plan.instances) - ran} cached, {result.seconds:.2f} s"
            if result.fallback and result.fallback["ran_again"]:
                self.summary += f" (fallback: {result.fallback['summary']})"
            self.files = [{"path": p, "size": f["size"]} for p, f in sorted(result.manifest["files"].items())]
            self.result_version += 1
            self._bump()

    def failed(self, message: str) -> None:
        with self.lock:
            self.phase, self.error = "error", message
            match = re.match(r"node ([^\s:]+)", message)
            if match:  # "node ID: ..." or "node ID failed: ..."
                self.branches.setdefault(match.group(1).split("[", 1)[0], {})[match.group(1)] = "failed"
            for states in self.branches.values():
                for inst, s in states.items():
                    if s in ("running", "queued"):
                        states[inst] = "skipped"
            self._bump()


class _Progress:
    """The runner's progress hook, reporting into a :class:`WatchState`."""

    def __init__(self, state: WatchState):
        self.state = state

    def __call__(self, total: int) -> "_Progress":
        return self

    def __enter__(self) -> "_Progress":
        return self

    def __exit__(self, *exc: Any) -> None:
        return None

    def start(self, instance_id: str) -> None:
        self.state.set_branch(instance_id, "running")

    def done(self, instance_id: str) -> None:
        self.state.set_branch(instance_id, "ran")


def _handler(state: WatchState, graph_svg: Callable[[], str | None]) -> type[http.server.BaseHTTPRequestHandler]:
    class Handler(http.server.BaseHTTPRequestHandler):
        def log_message(self, *args: Any) -> None:  # the terminal shows runs, not requests
            pass

        def _send(self, body: bytes, kind: str, status: int = 200) -> None:
            self.send_response(status)
            self.send_header("Content-Type", kind)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def do_GET(self) -> None:  # noqa: N802 (http.server's name)
            path = urllib.parse.urlparse(self.path).path
            if path == "/":
                self._send(render_page(state.snapshot(), state.out_dir).encode(), "text/html; charset=utf-8")
            elif path == "/state.json":
                self._send(json.dumps(state.snapshot()).encode(), "application/json")
            elif path == "/graph.svg":
                svg = graph_svg()
                self._send(*((svg.encode(), "image/svg+xml") if svg else (b"no graph", "text/plain", 404)))
            elif path.startswith("/files/"):
                self._file(urllib.parse.unquote(path[len("/files/"):]))
            else:
                self._send(b"not found", "text/plain", 404)

        def _file(self, rel: str) -> None:
            if rel not in {f["path"] for f in state.snapshot()["files"]}:
                self._send(b"not an output file", "text/plain", 404)
                return
            try:
                with open(os.path.join(state.out_dir, *rel.split("/")), "rb") as f:
                    body = f.read()
            except OSError:
                self._send(b"gone", "text/plain", 404)
                return
            kinds = {".svg": "image/svg+xml", ".png": "image/png", ".html": "text/html; charset=utf-8",
                     ".json": "application/json", ".pdf": "application/pdf", ".csv": "text/csv; charset=utf-8"}
            self._send(body, kinds.get(os.path.splitext(rel)[1].lower(), "application/octet-stream"))

    return Handler


def _graph_renderer(state: WatchState) -> Callable[[], str | None]:
    """SVG of the last parsed pipeline with the current node states (cached per state), or None
    without Graphviz (the page then shows the node table alone)."""
    cache: dict[str, str] = {}

    def render() -> str | None:
        with state.lock:
            pipeline, states = state.pipeline, state.node_states()
        if pipeline is None:
            return None
        ident = hashlib.sha256(json.dumps([id(pipeline), states], sort_keys=True).encode()).hexdigest()
        if ident not in cache:
            try:
                cache.clear()
                cache[ident] = dag.to_svg(pipeline, states)
            except UserError:
                return None
        return cache[ident]

    return render


def _fingerprint(path: str) -> tuple[Any, ...]:
    try:
        st = os.stat(path)
        with open(path, "rb") as f:
            return st.st_mtime_ns, st.st_size, hashlib.sha256(f.read()).hexdigest()
    except OSError as exc:
        return ("missing", exc.errno)


def _changes(path: str, poll_s: float) -> Iterator[int]:
    """Yields once now and once after every change of ``path`` (polled every ``poll_s`` seconds)."""
    last = None
    count = 0
    while True:
        current = _fingerprint(path)
        if current != last:
            last = current
            count += 1
            yield count
        time.sleep(poll_s)


def run_once(state: WatchState, overrides: list[str], run: dict[str, Any]) -> str:
    """One run for the page; returns the line the terminal shows."""
    from .pipeline import load_pipeline
    from .runner import run_pipeline

    state.begin()
    try:
        state.parsed(load_pipeline(state.pipeline_file, overrides))
        result = run_pipeline(state.pipeline_file, overrides, out_dir=state.out_dir, on_plan=state.planned,
                              progress=_Progress(state), **run)
    except (UserError, NodeFailed) as exc:
        state.failed(" ".join(str(exc).split("\n")))
        return f"run {state.runs} failed: {state.error}"
    except Exception as exc:  # keep watching: the next save may fix it
        state.failed(f"unexpected {type(exc).__name__}: {exc}")
        return f"run {state.runs} failed: {state.error}"
    state.succeeded(result)
    return f"run {state.runs}: {state.summary}; outputs in {state.out_dir}"


def watch(pipeline: str, overrides: list[str], out_dir: str, *, port: int = 8770, poll_s: float = 0.3,
          say: Callable[[str], None] = print, **run: Any) -> None:
    """Serve the page and rerun ``pipeline`` after every change until interrupted (``run``: the
    keyword arguments of :func:`.runner.run_pipeline`, e.g. ``cache_dir``, ``scheduler``)."""
    state = WatchState(pipeline, out_dir)
    try:
        server = http.server.ThreadingHTTPServer(("127.0.0.1", port), _handler(state, _graph_renderer(state)))
    except OSError as exc:
        raise UserError(f"--port {port}: cannot listen on 127.0.0.1:{port} ({exc.strerror}); pick another port "
                        "(0 picks a free one)") from None
    server.daemon_threads = True
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.2}, daemon=True)
    thread.start()
    try:
        say(f"watching {pipeline}: http://127.0.0.1:{server.server_address[1]}/ (Ctrl-C to stop)")
        for _ in _changes(pipeline, poll_s):
            say(run_once(state, overrides, run))
    finally:
        server.shutdown()
        server.server_close()
