"""``preview.render``: see the Tx/Rx layout on the object without other software.

Writes ``preview.png`` (four headless views in a 2 x 2 grid: the mesh flat-shaded with OpenCV's
triangle rasterizer, base region dark blue-grey, exclusion regions mid grey, sensing surface light
grey; Tx curves in ``TX_RGB`` and Rx curves in ``RX_RGB`` drawn only where they pass a depth test
against the mesh's z-buffer) and ``preview.html`` (a self-contained WebGL2 orbit viewer: mesh,
regions and curves embedded as base64 arrays in a JSON block, inline JavaScript, no network).

Camera convention: views orbit the bounding-box centre; elevation is measured from the plane
normal to ``regions.up`` (positive = looking down on the object), azimuth about ``up``.
"""
from __future__ import annotations

import base64
import json

import cv2
import numpy as np
from pydantic import Field

from ...graph.node import Files, NodeParams, node
from ..data.types import CurveSet, Layout, Mesh, SurfaceRegions

TX_RGB = (230, 70, 20)
RX_RGB = (20, 110, 235)
CROSSING_RGB = (250, 210, 0)
BACKGROUND_RGB = (255, 255, 255)
SENSING_RGB = (0.86, 0.85, 0.82)
EXCLUSION_RGB = (0.66, 0.66, 0.66)
BASE_RGB = (0.42, 0.47, 0.60)
VIEWS = (("front left", 35.0, 20.0), ("back right", 215.0, 20.0), ("top", 125.0, 70.0), ("below", 300.0, -55.0))
"""(label, azimuth deg, elevation deg) of the PNG's four views."""
FOV_Y = np.radians(30.0)


class PreviewParams(NodeParams):
    """Image size and file names."""

    view_px: int = Field(480, ge=64, le=4096, description="side of each of the four square views (px)")
    line_px: int = Field(2, ge=1, le=9, description="curve width in the PNG (px)")
    png: str = Field("preview.png", description="PNG file name in the output folder")
    html: str = Field("preview.html", description="HTML viewer file name in the output folder")


def segments(curves: CurveSet) -> tuple[np.ndarray, np.ndarray]:
    """Row indices ``(start, end)`` of every segment of every curve."""
    rows = len(curves.points)
    starts = np.ones(max(rows - 1, 0), dtype=bool)
    last_rows = np.asarray(curves.offsets[1:], dtype=np.int64) - 1
    starts[last_rows[(last_rows >= 0) & (last_rows < rows - 1)]] = False
    start = np.flatnonzero(starts)
    return start, start + 1


def camera(centre: np.ndarray, radius: float, up: np.ndarray, azimuth: float, elevation: float) -> np.ndarray:
    """4x4 world-to-camera matrix (OpenGL convention: the camera looks down its -z axis)."""
    helper = np.eye(3)[int(np.argmin(np.abs(up)))]
    side = np.cross(up, helper)
    side /= np.linalg.norm(side)
    front = np.cross(up, side)
    horizontal = np.cos(azimuth) * side + np.sin(azimuth) * front
    towards_eye = np.cos(elevation) * horizontal + np.sin(elevation) * up
    eye = centre + towards_eye * radius / np.sin(FOV_Y / 2) * 1.05
    z_axis = towards_eye
    x_axis = np.cross(up, z_axis)
    if np.linalg.norm(x_axis) < 1e-9:
        x_axis = side
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(z_axis, x_axis)
    rotation = np.stack([x_axis, y_axis, z_axis])
    world_to_camera = np.eye(4)
    world_to_camera[:3, :3] = rotation
    world_to_camera[:3, 3] = -rotation @ eye
    return world_to_camera


def project(points: np.ndarray, world_to_camera: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(column, row, depth)`` of world points: pixel coordinates and distance along the view axis."""
    cam = points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    depth = -cam[:, 2]
    focal = (size / 2) / np.tan(FOV_Y / 2)
    column = size / 2 + focal * cam[:, 0] / depth
    row = size / 2 - focal * cam[:, 1] / depth
    return column, row, depth


def face_colours(face_count: int, regions: SurfaceRegions | None) -> np.ndarray:
    """Base RGB in [0, 1] per face from the region masks."""
    colours = np.tile(np.asarray(SENSING_RGB, dtype=np.float32), (face_count, 1))
    if regions is not None:
        colours[np.asarray(regions.exclusion_base) | np.asarray(regions.exclusion_far)] = EXCLUSION_RGB
        colours[np.asarray(regions.base_faces)] = BASE_RGB
    return colours


def render_view(
    mesh: Mesh,
    colours: np.ndarray,
    layers: list[tuple[CurveSet, tuple[int, int, int]]],
    crossings: np.ndarray | None,
    world_to_camera: np.ndarray,
    size: int,
    line_px: int,
) -> np.ndarray:
    """One RGB uint8 view: shaded mesh, then curves that pass the depth test, then crossings."""
    vertices, faces = mesh.vertices, mesh.faces
    corners = vertices[faces]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1), 1e-300)[:, None]
    eye = -world_to_camera[:3, :3].T @ world_to_camera[:3, 3]
    to_eye = eye - corners.mean(axis=1)
    to_eye /= np.linalg.norm(to_eye, axis=1)[:, None]
    shade = 0.35 + 0.65 * np.clip(np.einsum("ij,ij->i", normals, to_eye), 0.0, 1.0)
    vertex_colours = np.repeat(colours * shade[:, None], 3, axis=0).astype(np.float32)
    colour = np.zeros((size, size, 3), dtype=np.float32)
    colour[:] = np.asarray(BACKGROUND_RGB, dtype=np.float32) / 255.0
    radius = float(np.linalg.norm(vertices.max(0) - vertices.min(0))) / 2
    distance = float(np.linalg.norm(eye - 0.5 * (vertices.max(0) + vertices.min(0))))
    z_near, z_far = max(distance - 2 * radius, 1e-3), distance + 2 * radius
    depth = np.full((size, size), z_far, dtype=np.float32)
    settings = cv2.TriangleRasterizeSettings()
    settings.setShadingType(cv2.RASTERIZE_SHADING_FLAT)
    settings.setCullingMode(cv2.RASTERIZE_CULLING_NONE)
    colour, depth = cv2.triangleRasterize(
        corners.reshape(-1, 3).astype(np.float32),
        np.arange(3 * len(faces), dtype=np.int32).reshape(-1, 3),
        vertex_colours,
        colour,
        depth,
        world_to_camera,
        FOV_Y,
        z_near,
        z_far,
        settings,
    )
    image = np.clip(colour * 255.0 + 0.5, 0, 255).astype(np.uint8)
    pixel_mm = 2 * distance * np.tan(FOV_Y / 2) / size
    kernel = np.ones((line_px, line_px), dtype=np.uint8)
    for curves, rgb in layers:
        visible = visible_curve_mask(curves, world_to_camera, depth, size, tolerance=4 * pixel_mm)
        image[cv2.dilate(visible, kernel) > 0] = rgb
    if crossings is not None and len(crossings):
        column, row, point_depth = project(crossings, world_to_camera, size)
        for c, r, d in zip(column, row, point_depth):
            ci, ri = int(round(c)), int(round(r))
            if 0 <= ci < size and 0 <= ri < size and d <= depth[ri, ci] + 4 * pixel_mm:
                cv2.circle(image, (ci, ri), line_px + 1, CROSSING_RGB, -1)
    return image


def visible_curve_mask(
    curves: CurveSet, world_to_camera: np.ndarray, depth: np.ndarray, size: int, tolerance: float
) -> np.ndarray:
    """uint8 mask of pixels where the curves are in front of (or on) the rendered surface."""
    mask = np.zeros((size, size), dtype=np.uint8)
    start, end = segments(curves)
    if len(start) == 0:
        return mask
    a, b = curves.points[start], curves.points[end]
    col_a, row_a, _ = project(a, world_to_camera, size)
    col_b, row_b, _ = project(b, world_to_camera, size)
    steps = np.ceil(2 * np.hypot(col_b - col_a, row_b - row_a)).clip(1, 4 * size).astype(np.int64)
    owner = np.repeat(np.arange(len(start)), steps + 1)
    first = np.repeat(np.cumsum(steps + 1) - (steps + 1), steps + 1)
    t = (np.arange(len(owner)) - first) / steps[owner]
    samples = a[owner] + t[:, None] * (b[owner] - a[owner])
    column, row, sample_depth = project(samples, world_to_camera, size)
    ci, ri = np.rint(column).astype(np.int64), np.rint(row).astype(np.int64)
    inside = (ci >= 0) & (ci < size) & (ri >= 0) & (ri < size) & (sample_depth > 0)
    ci, ri, sample_depth = ci[inside], ri[inside], sample_depth[inside]
    # a curve point is visible when no surface is nearer within a small window around its pixel
    nearest = cv2.erode(depth, np.ones((3, 3), np.uint8))
    shown = sample_depth <= np.maximum(depth[ri, ci], nearest[ri, ci]) + tolerance
    mask[ri[shown], ci[shown]] = 1
    return mask


def render_png(
    mesh: Mesh,
    regions: SurfaceRegions | None,
    tx: CurveSet,
    rx: CurveSet,
    crossings: np.ndarray | None,
    view_px: int,
    line_px: int,
) -> bytes:
    """PNG bytes of the 2 x 2 grid of views (size ``2 view_px`` square)."""
    up = np.asarray(regions.up, dtype=np.float64) if regions is not None else np.array([0.0, 0.0, 1.0])
    centre = 0.5 * (mesh.vertices.max(0) + mesh.vertices.min(0))
    radius = float(np.linalg.norm(mesh.vertices.max(0) - mesh.vertices.min(0))) / 2
    colours = face_colours(len(mesh.faces), regions)
    tiles = []
    for label, azimuth, elevation in VIEWS:
        world_to_camera = camera(centre, radius, up, np.radians(azimuth), np.radians(elevation))
        tile = render_view(mesh, colours, [(rx, RX_RGB), (tx, TX_RGB)], crossings, world_to_camera, view_px, line_px)
        cv2.putText(tile, label, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
        tiles.append(tile)
    grid = np.vstack([np.hstack(tiles[:2]), np.hstack(tiles[2:])])
    legend = f"Tx: {tx.count} curves   Rx: {rx.count} curves   base: dark   exclusions: grey"
    cv2.putText(grid, legend, (8, 2 * view_px - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    ok, encoded = cv2.imencode(".png", cv2.cvtColor(grid, cv2.COLOR_RGB2BGR))
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return encoded.tobytes()


def _b64(array: np.ndarray, dtype: str) -> str:
    return base64.b64encode(np.ascontiguousarray(array, dtype=dtype).tobytes()).decode("ascii")


def curve_lines(curves: CurveSet, mesh: Mesh, lift_mm: float) -> np.ndarray:
    """(2 S, 3) float32 line-list endpoints, lifted along their face normals so they show in WebGL."""
    start, end = segments(curves)
    corners = mesh.vertices[mesh.faces[curves.faces]]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1), 1e-300)[:, None]
    lifted = curves.points + lift_mm * normals
    return np.stack([lifted[start], lifted[end]], axis=1).reshape(-1, 3)


def viewer_data(mesh: Mesh, regions: SurfaceRegions | None, tx: CurveSet, rx: CurveSet, crossings: np.ndarray | None) -> dict:
    """The JSON embedded in the HTML viewer (arrays little-endian base64)."""
    diagonal = float(np.linalg.norm(mesh.vertices.max(0) - mesh.vertices.min(0)))
    region = np.zeros(len(mesh.vertices), dtype=np.uint8)  # 0 sensing, 1 exclusion, 2 base
    if regions is not None:
        excluded = np.asarray(regions.exclusion_base) | np.asarray(regions.exclusion_far)
        region[mesh.faces[excluded].ravel()] = 1
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


@node("preview.render", params=PreviewParams, inputs=("mesh", "regions", "tx", "rx"), outputs=("files",), sink=True)
def render_preview(params: PreviewParams, mesh: Mesh, regions: SurfaceRegions, tx: CurveSet, rx: CurveSet) -> Files:
    """A PNG with four views of the object and both curve layers, and an interactive HTML viewer."""
    return Files(
        contents={
            params.png: render_png(mesh, regions, tx, rx, None, params.view_px, params.line_px),
            params.html: render_html(mesh, regions, tx, rx, None),
        }
    )


@node("preview.layout", params=PreviewParams, inputs=("mesh", "regions", "layout"), outputs=("files",), sink=True)
def render_layout_preview(params: PreviewParams, mesh: Mesh, regions: SurfaceRegions, layout: Layout) -> Files:
    """As ``preview.render`` for the optimised layout: the selected curves, with the crossings that
    carry an electrode pad marked as yellow dots."""
    pads = np.asarray(layout.cells.points, dtype=np.float64).reshape(-1, 3)[np.asarray(layout.pad, dtype=bool)]
    return Files(
        contents={
            params.png: render_png(mesh, regions, layout.tx, layout.rx, pads, params.view_px, params.line_px),
            params.html: render_html(mesh, regions, layout.tx, layout.rx, pads),
        }
    )
