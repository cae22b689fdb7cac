"""The preview HTML: a self-contained WebGL2 orbit viewer (no network).

Mesh, regions and curves are embedded as little-endian base64 arrays in a JSON block
(``retrotouch.preview/1``), read by inline JavaScript; lengths in mm.
"""
from __future__ import annotations

import base64
import json

import numpy as np

from ..data.types import CurveSet, Mesh, SurfaceRegions
from ..geometry.triangles import normals
from .views import BASE_RGB, EXCLUSION_RGB, RX_RGB, SENSING_RGB, TX_RGB, greyed_faces, segments


def _b64(array: np.ndarray, dtype: str) -> str:
    return base64.b64encode(np.ascontiguousarray(array, dtype=dtype).tobytes()).decode("ascii")


def curve_lines(curves: CurveSet, mesh: Mesh, lift_mm: float) -> np.ndarray:
    """(2 S, 3) float32 line-list endpoints, lifted along their face normals so they show in WebGL."""
    start, end = segments(curves)
    face_normals, _ = normals(mesh.vertices[mesh.faces[curves.faces]])
    lifted = curves.points + lift_mm * face_normals
    return np.stack([lifted[start], lifted[end]], axis=1).reshape(-1, 3)


def viewer_data(mesh: Mesh, regions: SurfaceRegions | None, tx: CurveSet, rx: CurveSet, crossings: np.ndarray | None) -> dict:
    """The JSON embedded in the HTML viewer (arrays little-endian base64)."""
    diagonal = float(np.linalg.norm(mesh.vertices.max(0) - mesh.vertices.min(0)))
    region = np.zeros(len(mesh.vertices), dtype=np.uint8)  # 0 sensing, 1 exclusion or untouchable, 2 base
    if regions is not None:
        region[mesh.faces[greyed_faces(regions)].ravel()] = 1
        region[mesh.faces[np.asarray(regions.base_faces)].ravel()] = 2
    up = np.asarray(regions.up, dtype=float) if regions is not None else np.array([0.0, 0.0, 1.0])
    lift = 0.002 * diagonal
    return {
        "format": "retrotouch.preview/1",
        "source": mesh.source,
        "vertex_count": int(len(mesh.vertices)),
        "face_count": int(len(mesh.faces)),
        "vertices": _b64(mesh.vertices, "<f4"),
        "faces": _b64(mesh.faces, "<u4"),
        "region": _b64(region, "u1"),
        "up": up.tolist(),
        "tx": {"count": tx.count, "rgb": TX_RGB, "lines": _b64(curve_lines(tx, mesh, lift), "<f4")},
        "rx": {"count": rx.count, "rgb": RX_RGB, "lines": _b64(curve_lines(rx, mesh, lift), "<f4")},
        "crossings": _b64(crossings if crossings is not None else np.zeros((0, 3)), "<f4"),
        "colours": {"sensing": SENSING_RGB, "exclusion": EXCLUSION_RGB, "base": BASE_RGB},
    }


HTML_TEMPLATE = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>retrotouch preview</title>
<style>
 body{margin:0;background:#fff;font:14px sans-serif;overflow:hidden}
 canvas{display:block;width:100vw;height:100vh}
 #panel{position:absolute;top:8px;left:8px;background:rgba(255,255,255,.85);padding:6px 10px;border-radius:4px}
 .tx{color:rgb(__TX__)} .rx{color:rgb(__RX__)}
</style></head><body>
<canvas id="view"></canvas>
<div id="panel"><b>retrotouch preview</b> &mdash; drag: orbit, wheel: zoom<br>
<label><input type="checkbox" id="showTx" checked> <span class="tx">Tx</span> (<span id="ntx"></span>)</label>
<label><input type="checkbox" id="showRx" checked> <span class="rx">Rx</span> (<span id="nrx"></span>)</label>
<label><input type="checkbox" id="showRegions" checked> regions</label></div>
<script type="application/json" id="retrotouch-data">__DATA__</script>
<script>
"use strict";
const data = JSON.parse(document.getElementById("retrotouch-data").textContent);
function decode(text, Type) {
  const bytes = Uint8Array.from(atob(text), c => c.charCodeAt(0));
  return new Type(bytes.buffer);
}
const positions = decode(data.vertices, Float32Array), indices = decode(data.faces, Uint32Array);
const region = decode(data.region, Uint8Array);
const txLines = decode(data.tx.lines, Float32Array), rxLines = decode(data.rx.lines, Float32Array);
document.getElementById("ntx").textContent = data.tx.count;
document.getElementById("nrx").textContent = data.rx.count;
const canvas = document.getElementById("view");
const gl = canvas.getContext("webgl2", {antialias: true});
if (!gl) { document.body.innerHTML = "<p>This viewer needs WebGL2.</p>"; throw new Error("no WebGL2"); }
function shader(type, source) {
  const s = gl.createShader(type); gl.shaderSource(s, source); gl.compileShader(s);
  if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
  return s;
}
function program(vs, fs) {
  const p = gl.createProgram();
  gl.attachShader(p, shader(gl.VERTEX_SHADER, vs)); gl.attachShader(p, shader(gl.FRAGMENT_SHADER, fs));
  gl.linkProgram(p); return p;
}
const meshProgram = program(`#version 300 es
in vec3 position; in float region; uniform mat4 mvp; out vec3 world; out float reg;
void main(){ world = position; reg = region; gl_Position = mvp * vec4(position, 1.0); }`,
`#version 300 es
precision highp float; in vec3 world; in float reg; uniform vec3 eye; uniform vec3 colours[3];
uniform bool showRegions; out vec4 outColour;
void main(){
  vec3 n = normalize(cross(dFdx(world), dFdy(world)));
  float shade = 0.35 + 0.65 * abs(dot(n, normalize(eye - world)));
  int k = showRegions ? int(reg + 0.5) : 0;
  outColour = vec4(colours[k] * shade, 1.0);
}`);
const lineProgram = program(`#version 300 es
in vec3 position; uniform mat4 mvp; void main(){ gl_Position = mvp * vec4(position, 1.0); }`,
`#version 300 es
precision highp float; uniform vec3 colour; out vec4 outColour; void main(){ outColour = vec4(colour, 1.0); }`);
function buffer(target, array) { const b = gl.createBuffer(); gl.bindBuffer(target, b); gl.bufferData(target, array, gl.STATIC_DRAW); return b; }
const meshVao = gl.createVertexArray(); gl.bindVertexArray(meshVao);
buffer(gl.ARRAY_BUFFER, positions);
let loc = gl.getAttribLocation(meshProgram, "position"); gl.enableVertexAttribArray(loc); gl.vertexAttribPointer(loc, 3, gl.FLOAT, false, 0, 0);
buffer(gl.ARRAY_BUFFER, new Float32Array(region));
loc = gl.getAttribLocation(meshProgram, "region"); gl.enableVertexAttribArray(loc); gl.vertexAttribPointer(loc, 1, gl.FLOAT, false, 0, 0);
buffer(gl.ELEMENT_ARRAY_BUFFER, indices);
function lineVao(lines) {
  const vao = gl.createVertexArray(); gl.bindVertexArray(vao); buffer(gl.ARRAY_BUFFER, lines);
  const l = gl.getAttribLocation(lineProgram, "position"); gl.enableVertexAttribArray(l); gl.vertexAttribPointer(l, 3, gl.FLOAT, false, 0, 0);
  return vao;
}
const txVao = lineVao(txLines), rxVao = lineVao(rxLines);
let lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
for (let i = 0; i < positions.length; i += 3) for (let k = 0; k < 3; k++) { lo[k] = Math.min(lo[k], positions[i + k]); hi[k] = Math.max(hi[k], positions[i + k]); }
const centre = lo.map((v, k) => (v + hi[k]) / 2);
const radius = Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]) / 2;
const up = data.up;
const helper = [[1,0,0],[0,1,0],[0,0,1]][[0,1,2].reduce((a, k) => Math.abs(up[k]) < Math.abs(up[a]) ? k : a, 0)];
const cross = (a, b) => [a[1]*b[2]-a[2]*b[1], a[2]*b[0]-a[0]*b[2], a[0]*b[1]-a[1]*b[0]];
const norm = a => { const l = Math.hypot(...a); return a.map(v => v / l); };
const dot = (a, b) => a[0]*b[0] + a[1]*b[1] + a[2]*b[2];
const side = norm(cross(up, helper)), front = cross(up, side);
let azimuth = 0.6, elevation = 0.35, zoom = 1.0;
function matrices() {
  const h = side.map((v, k) => Math.cos(azimuth) * v + Math.sin(azimuth) * front[k]);
  const dir = h.map((v, k) => Math.cos(elevation) * v + Math.sin(elevation) * up[k]);
  const dist = zoom * radius / Math.sin(0.2618) * 1.05;
  const eye = centre.map((c, k) => c + dist * dir[k]);
  const z = dir, x = norm(cross(up, z)), y = cross(z, x);
  const aspect = canvas.width / canvas.height, f = 1 / Math.tan(0.2618);
  const near = Math.max(dist - 2 * radius, dist * 0.01), far = dist + 2 * radius;
  const view = [x[0], y[0], z[0], 0, x[1], y[1], z[1], 0, x[2], y[2], z[2], 0, -dot(x, eye), -dot(y, eye), -dot(z, eye), 1];
  const proj = [f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) / (near - far), -1, 0, 0, 2 * far * near / (near - far), 0];
  const mvp = new Float32Array(16);
  for (let c = 0; c < 4; c++) for (let r = 0; r < 4; r++) { let s = 0; for (let k = 0; k < 4; k++) s += proj[k * 4 + r] * view[c * 4 + k]; mvp[c * 4 + r] = s; }
  return {mvp, eye};
}
function draw() {
  const w = canvas.clientWidth * devicePixelRatio, h = canvas.clientHeight * devicePixelRatio;
  if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
  gl.viewport(0, 0, canvas.width, canvas.height);
  gl.clearColor(1, 1, 1, 1); gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT); gl.enable(gl.DEPTH_TEST);
  const {mvp, eye} = matrices();
  gl.useProgram(meshProgram);
  gl.uniformMatrix4fv(gl.getUniformLocation(meshProgram, "mvp"), false, mvp);
  gl.uniform3fv(gl.getUniformLocation(meshProgram, "eye"), eye);
  gl.uniform3fv(gl.getUniformLocation(meshProgram, "colours"), [...data.colours.sensing, ...data.colours.exclusion, ...data.colours.base]);
  gl.uniform1i(gl.getUniformLocation(meshProgram, "showRegions"), document.getElementById("showRegions").checked);
  gl.enable(gl.POLYGON_OFFSET_FILL); gl.polygonOffset(1, 1);
  gl.bindVertexArray(meshVao); gl.drawElements(gl.TRIANGLES, indices.length, gl.UNSIGNED_INT, 0);
  gl.disable(gl.POLYGON_OFFSET_FILL);
  gl.useProgram(lineProgram);
  gl.uniformMatrix4fv(gl.getUniformLocation(lineProgram, "mvp"), false, mvp);
  for (const [vao, lines, layer, box] of [[rxVao, rxLines, data.rx, "showRx"], [txVao, txLines, data.tx, "showTx"]]) {
    if (!document.getElementById(box).checked || lines.length === 0) continue;
    gl.uniform3fv(gl.getUniformLocation(lineProgram, "colour"), layer.rgb.map(v => v / 255));
    gl.bindVertexArray(vao); gl.drawArrays(gl.LINES, 0, lines.length / 3);
  }
}
let dragging = null;
canvas.addEventListener("pointerdown", e => { dragging = [e.clientX, e.clientY]; canvas.setPointerCapture(e.pointerId); });
canvas.addEventListener("pointerup", () => { dragging = null; });
canvas.addEventListener("pointermove", e => {
  if (!dragging) return;
  azimuth -= (e.clientX - dragging[0]) * 0.01;
  elevation = Math.max(-1.55, Math.min(1.55, elevation + (e.clientY - dragging[1]) * 0.01));
  dragging = [e.clientX, e.clientY]; draw();
});
canvas.addEventListener("wheel", e => { e.preventDefault(); zoom = Math.max(0.2, Math.min(5, zoom * Math.exp(e.deltaY * 0.001))); draw(); }, {passive: false});
for (const id of ["showTx", "showRx", "showRegions"]) document.getElementById(id).addEventListener("change", draw);
window.addEventListener("resize", draw);
draw();
</script></body></html>
"""


def render_html(mesh: Mesh, regions: SurfaceRegions | None, tx: CurveSet, rx: CurveSet, crossings: np.ndarray | None) -> bytes:
    """The self-contained HTML viewer (UTF-8)."""
    payload = json.dumps(viewer_data(mesh, regions, tx, rx, crossings), separators=(",", ":"))
    html = (
        HTML_TEMPLATE.replace("__TX__", ",".join(map(str, TX_RGB)))
        .replace("__RX__", ",".join(map(str, RX_RGB)))
        .replace("__DATA__", payload.replace("</", "<\\/"))
    )
    return html.encode("utf-8")
