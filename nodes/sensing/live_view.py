"""Live view: a local web page showing the object with the touch heatmap and touch points, served by
the tool itself (stdlib ``http.server``; frames pushed as Server-Sent Events; self-contained JS that
draws on a 2D canvas, no network access).

Endpoints: ``/`` the page (``?frames=N`` stops updating after N frames, ``?follow=1`` turns the
strongest touch towards the viewer), ``/mesh.json`` the contact mesh (the processor's simplified mesh, mm) and
its up axis, ``/events`` one ``data:`` line per frame::

    {"seq": 12, "t": 1.2, "heat": [0..255 per mesh vertex],
     "touches": [{"id", "point", "normal", "intensity", "area_mm2"}],
     "events": ["tap", ...]}

Heat is the interpolated delta over the mesh vertices, scaled to the frame's peak (at least
``10 x`` the median noise sigma, so a quiet frame stays dark).
"""
from __future__ import annotations

import json
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import numpy as np

from ..geometry.triangles import corners
from ..geometry.triangles import normals as face_normals
from .processing import FrameResult, TouchProcessor

PAGE = """<!doctype html>
<html><head><meta charset="utf-8"><title>retrotouch live view</title>
<style>
 body { margin: 0; font: 13px sans-serif; background: #15171a; color: #ddd; display: flex; }
 canvas { flex: 1; cursor: grab; }
 aside { width: 260px; padding: 10px; border-left: 1px solid #333; }
 li.touch { margin: 4px 0; } #events li { color: #8fd; }
</style></head>
<body><canvas id="view" width="800" height="700"></canvas>
<aside><div id="prompt" style="color:#fd8;font-size:15px"></div><div id="status">connecting</div><h4>touches</h4><ul id="touches"></ul><h4>gestures</h4><ul id="events"></ul>
<p>drag to rotate</p></aside>
<script>
"use strict";
const canvas = document.getElementById("view"), ctx = canvas.getContext("2d");
let mesh = null, heat = null, touches = [], yaw = 0.6, pitch = -0.3, dirty = true;
function heatColor(h) {  // 0..1 -> dark blue, red, yellow
  const r = Math.min(1, 2 * h), g = Math.max(0, 2 * h - 1), b = 0.35 * (1 - h);
  return [255 * r, 255 * g, 255 * b];
}
function basis() {
  const up = mesh.up, a = Math.abs(up[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0];
  let x = [up[1] * a[2] - up[2] * a[1], up[2] * a[0] - up[0] * a[2], up[0] * a[1] - up[1] * a[0]];
  const n = Math.hypot(...x); x = x.map(v => v / n);
  const z = [x[1] * up[2] - x[2] * up[1], x[2] * up[0] - x[0] * up[2], x[0] * up[1] - x[1] * up[0]];
  const cy = Math.cos(yaw), sy = Math.sin(yaw), cp = Math.cos(pitch), sp = Math.sin(pitch);
  const right = x.map((v, i) => cy * v + sy * z[i]);
  const fwd = x.map((v, i) => -sy * v + cy * z[i]);
  const screenUp = up.map((v, i) => cp * v + sp * fwd[i]);
  const depth = fwd.map((v, i) => cp * v - sp * up[i]);
  return [right, screenUp, depth];
}
function draw() {
  if (!mesh || !dirty) return;
  dirty = false;
  const [r, u, d] = basis(), V = mesh.vertices, F = mesh.faces, nv = V.length / 3;
  const W = canvas.width, H = canvas.height, s = 0.8 * Math.min(W, H) / mesh.size;
  const sx = new Float32Array(nv), sy = new Float32Array(nv), sz = new Float32Array(nv);
  for (let i = 0; i < nv; i++) {
    const px = V[3 * i] - mesh.centre[0], py = V[3 * i + 1] - mesh.centre[1], pz = V[3 * i + 2] - mesh.centre[2];
    sx[i] = W / 2 + s * (px * r[0] + py * r[1] + pz * r[2]);
    sy[i] = H / 2 - s * (px * u[0] + py * u[1] + pz * u[2]);
    sz[i] = px * d[0] + py * d[1] + pz * d[2];
  }
  const order = [];
  for (let f = 0; f < F.length / 3; f++) {
    const a = F[3 * f], b = F[3 * f + 1], c = F[3 * f + 2];
    const area = (sx[b] - sx[a]) * (sy[c] - sy[a]) - (sy[b] - sy[a]) * (sx[c] - sx[a]);
    if (area < 0) order.push([f, sz[a] + sz[b] + sz[c], -area]);
  }
  order.sort((p, q) => p[1] - q[1]);  // the viewer sits on the +depth side: far (small depth) first
  ctx.fillStyle = "#15171a"; ctx.fillRect(0, 0, W, H);
  const N = mesh.normals;
  for (const [f] of order) {
    const a = F[3 * f], b = F[3 * f + 1], c = F[3 * f + 2];
    const light = 0.35 + 0.65 * Math.abs(N[3 * f] * d[0] + N[3 * f + 1] * d[1] + N[3 * f + 2] * d[2]);
    const h = heat ? (heat[a] + heat[b] + heat[c]) / 765 : 0;
    const hc = heatColor(h), g = 150 * light;
    const col = [0, 1, 2].map(k => Math.round((1 - h) * g + h * hc[k] * (0.5 + 0.5 * light)));
    ctx.fillStyle = ctx.strokeStyle = `rgb(${col[0]},${col[1]},${col[2]})`;
    ctx.beginPath(); ctx.moveTo(sx[a], sy[a]); ctx.lineTo(sx[b], sy[b]); ctx.lineTo(sx[c], sy[c]);
    ctx.closePath(); ctx.fill(); ctx.stroke();
  }
  for (const t of touches) {
    const px = t.point[0] - mesh.centre[0], py = t.point[1] - mesh.centre[1], pz = t.point[2] - mesh.centre[2];
    const X = W / 2 + s * (px * r[0] + py * r[1] + pz * r[2]), Y = H / 2 - s * (px * u[0] + py * u[1] + pz * u[2]);
    // A touch whose surface normal points away from the viewer is on the far side: drawn hidden.
    const facing = t.normal[0] * d[0] + t.normal[1] * d[1] + t.normal[2] * d[2] > 0;
    ctx.globalAlpha = facing ? 1 : 0.55; ctx.setLineDash(facing ? [] : [3, 3]);
    ctx.fillStyle = "#3cf"; ctx.strokeStyle = facing ? "#fff" : "#3cf"; ctx.lineWidth = 2;
    ctx.beginPath(); ctx.arc(X, Y, 8, 0, 2 * Math.PI); if (facing) ctx.fill(); ctx.stroke(); ctx.lineWidth = 1;
    ctx.setLineDash([]);
    ctx.fillStyle = "#fff"; ctx.fillText("#" + t.id + (facing ? "" : " (far side)"), X + 10, Y - 10);
    ctx.globalAlpha = 1;
  }
}
function faceTowards(n) {  // choose yaw/pitch so that depth = n (right x up = depth points at the viewer)
  const up = mesh.up, a = Math.abs(up[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0];
  let x = [up[1] * a[2] - up[2] * a[1], up[2] * a[0] - up[0] * a[2], up[0] * a[1] - up[1] * a[0]];
  const len = Math.hypot(...x); x = x.map(v => v / len);
  const z = [x[1] * up[2] - x[2] * up[1], x[2] * up[0] - x[0] * up[2], x[0] * up[1] - x[1] * up[0]];
  const dot = (p, q) => p[0] * q[0] + p[1] * q[1] + p[2] * q[2];
  pitch = Math.max(-1.5, Math.min(1.5, Math.asin(Math.max(-1, Math.min(1, -dot(n, up))))));
  yaw = Math.atan2(-dot(n, x), dot(n, z));
}
function showTouches(list) {
  const ul = document.getElementById("touches");
  ul.innerHTML = "";
  for (const t of list) {
    const li = document.createElement("li");
    li.className = "touch"; li.dataset.id = t.id;
    li.textContent = `#${t.id} (${t.point.map(v => v.toFixed(1)).join(", ")}) mm, ${Math.round(t.intensity)} counts`;
    ul.appendChild(li);
  }
}
function showEvents(names, t) {
  const ul = document.getElementById("events");
  for (const name of names) {
    const li = document.createElement("li"); li.className = "gesture"; li.textContent = `${t.toFixed(1)} s ${name}`;
    ul.insertBefore(li, ul.firstChild);
    while (ul.children.length > 12) ul.removeChild(ul.lastChild);
  }
}
let drag = null;
canvas.addEventListener("mousedown", e => { drag = [e.clientX, e.clientY]; });
window.addEventListener("mouseup", () => { drag = null; });
window.addEventListener("mousemove", e => {
  if (!drag) return;
  yaw += 0.01 * (e.clientX - drag[0]); pitch = Math.max(-1.5, Math.min(1.5, pitch + 0.01 * (e.clientY - drag[1])));
  drag = [e.clientX, e.clientY]; dirty = true;
});
function resize() { canvas.width = window.innerWidth - 281; canvas.height = window.innerHeight; dirty = true; }
window.addEventListener("resize", resize);
fetch("mesh.json").then(r => r.json()).then(m => {
  mesh = m; resize();
  const source = new EventSource("events");
  // ?frames=N: stop after N frames (a still snapshot, e.g. for headless checks);
  // ?follow=1: turn the object so that the strongest touch faces the viewer.
  const query = new URLSearchParams(location.search);
  const limit = Number(query.get("frames") || 0), follow = query.get("follow") === "1";
  let received = 0;
  source.onmessage = e => {
    const frame = JSON.parse(e.data);
    if (limit && ++received >= limit) source.close();
    heat = frame.heat; touches = frame.touches; dirty = true;
    if (follow && touches.length) faceTowards(touches.reduce((a, b) => (b.intensity > a.intensity ? b : a)).normal);
    document.getElementById("status").textContent = `frame ${frame.seq}, t ${frame.t.toFixed(1)} s, ${touches.length} touch(es)`;
    document.getElementById("prompt").textContent = frame.prompt || "";
    showTouches(touches); showEvents(frame.events, frame.t);
  };
  source.onerror = () => { document.getElementById("status").textContent = "disconnected"; };
  (function loop() { draw(); requestAnimationFrame(loop); })();
});
</script></body></html>
"""


class LiveView:
    """Serves the live page on ``host:port`` (0 = any free port) in a background thread."""

    def __init__(self, processor: TouchProcessor, host: str = "127.0.0.1", port: int = 0):
        self.processor = processor
        vertices, faces = processor.contacts.contact_vertices, processor.contacts.contact_faces
        normals = face_normals(corners(vertices, faces))[0]
        up = processor.map.up
        self._mesh_json = json.dumps({
            "vertices": np.round(vertices, 2).ravel().tolist(), "faces": faces.ravel().tolist(),
            "normals": np.round(normals, 3).ravel().tolist(), "up": up.tolist(),
            "centre": ((vertices.min(axis=0) + vertices.max(axis=0)) / 2).round(2).tolist(),
            "size": float(np.linalg.norm(np.ptp(vertices, axis=0))),
        }).encode()
        self._latest: bytes | None = None
        self._seq = 0
        self.prompt = ""  # what the operator is asked to do (sense --calibrate), shown above the status
        self._changed = threading.Condition()
        self._stopping = False
        view = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args: Any) -> None:  # keep stdout for the event stream
                pass

            def do_GET(self) -> None:  # noqa: N802 - http.server naming
                path = self.path.split("?")[0]
                if path in ("/", "/index.html"):
                    self._send(PAGE.encode(), "text/html; charset=utf-8")
                elif path == "/mesh.json":
                    self._send(view._mesh_json, "application/json")
                elif path == "/events":
                    self._stream()
                else:
                    self.send_error(404)

            def _send(self, body: bytes, kind: str) -> None:
                self.send_response(200)
                self.send_header("Content-Type", kind)
                self.send_header("Content-Length", str(len(body)))
                self.send_header("Cache-Control", "no-store")
                self.end_headers()
                self.wfile.write(body)

            def _stream(self) -> None:
                self.send_response(200)
                self.send_header("Content-Type", "text/event-stream")
                self.send_header("Cache-Control", "no-store")
                self.end_headers()
                seen = -1
                try:
                    while not view._stopping:
                        with view._changed:
                            view._changed.wait_for(lambda: view._seq != seen or view._stopping, timeout=1.0)
                            data, seq = view._latest, view._seq
                        if view._stopping:
                            return
                        if data is None or seq == seen:
                            self.wfile.write(b": keep-alive\n\n")
                        else:
                            self.wfile.write(b"data: " + data + b"\n\n")
                            seen = seq
                        self.wfile.flush()
                except (BrokenPipeError, ConnectionResetError):
                    return

        self.server = ThreadingHTTPServer((host, port), Handler)
        self.server.daemon_threads = True
        self._thread = threading.Thread(target=self.server.serve_forever, name="live-view", daemon=True)

    @property
    def url(self) -> str:
        host, port = self.server.server_address[:2]
        return f"http://{host}:{port}/"

    def start(self) -> str:
        self._thread.start()
        return self.url

    def publish(self, result: FrameResult, gestures: list[dict[str, Any]] = ()) -> None:
        """Make ``result`` the frame every open page shows next."""
        positive = np.maximum(result.delta, 0.0)
        field = self.processor.contacts.vertex_to_cell @ positive
        scale = max(float(field.max(initial=0.0)), 10.0 * float(np.median(self.processor.sigma())))
        heat = np.clip(np.rint(255.0 * field / max(scale, 1e-9)), 0, 255).astype(np.int64)
        payload = json.dumps({
            "seq": self._seq + 1, "t": round(result.t, 3), "heat": heat.tolist(),
            "touches": [{"id": t.id, "point": [round(float(x), 2) for x in t.point],
                         "normal": [round(float(x), 3) for x in t.normal],
                         "intensity": round(t.intensity, 1), "area_mm2": round(t.area_mm2, 1)} for t in result.touches],
            "events": [e["type"] for e in gestures], "prompt": self.prompt,
        }, separators=(",", ":")).encode()
        with self._changed:
            self._latest = payload
            self._seq += 1
            self._changed.notify_all()

    def stop(self) -> None:
        with self._changed:
            self._stopping = True
            self._changed.notify_all()
        self.server.shutdown()
        self.server.server_close()
        self._thread.join(timeout=2.0)

