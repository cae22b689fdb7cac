"""The projection GLB in real glTF viewers in headless Chromium: three.js's GLTFLoader and
Google's ``<model-viewer>``.

Both come from npm (``npm ci --prefix tests/glb_viewer`` and ``--prefix tests/model_viewer``,
pinned in their ``package.json``, MIT and Apache-2.0); Chromium is Debian's. Without them the
viewer tests skip and say what is missing. Each page loads the GLB with the viewer's defaults (for
three.js: a hemisphere + directional light, the lights a three.js scene is typically set up with;
``<model-viewer>``: its own neutral environment and framing, nothing set) and posts the viewer's
bounding box to the test's server; an image the server answers only after that post holds the
page's load event, so Chromium's screenshot is taken after the frame was drawn. The screenshot must
show a lit, not a black, object, standing as it rests on a table.
"""
from __future__ import annotations

import contextlib
import functools
import http.server
import io
import json
import shutil
import struct
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

from chromium import run_chromium
from proj_fixtures import bunny_layout, bunny_mm, bunny_regions
from retrotouch.nodes.data.ply import ply_bytes
from retrotouch.nodes.projection.textures import GLB_ROUGHNESS, TextureParams, projection_textures, standing_transform

THREE = Path(__file__).resolve().parent / "glb_viewer" / "node_modules" / "three"
MODEL_VIEWER_JS = (Path(__file__).resolve().parent / "model_viewer" / "node_modules" / "@google" / "model-viewer" / "dist"
                   / "model-viewer-umd.min.js")
VIEW_W, VIEW_H = 640, 480

PAGE = """<!DOCTYPE html>
<html><head><meta charset="utf-8"><style>body{margin:0;background:#000}</style>
<script type="importmap">{"imports": {"three": "./three/build/three.module.js", "three/addons/": "./three/examples/jsm/"}}</script>
</head><body>
<script type="module">
import * as THREE from "three";
import {GLTFLoader} from "three/addons/loaders/GLTFLoader.js";
const report = body => fetch("result", {method: "POST", body: typeof body === "string" ? body : JSON.stringify(body)});
try {
  const renderer = new THREE.WebGLRenderer({antialias: false, preserveDrawingBuffer: true});
  renderer.setPixelRatio(1);
  renderer.setSize(__W__, __H__);
  renderer.setClearColor(0x000000, 1);
  document.body.prepend(renderer.domElement);
  const scene = new THREE.Scene();
  scene.add(new THREE.HemisphereLight(0xffffff, 0x444444, 1.0));
  const sun = new THREE.DirectionalLight(0xffffff, 2.0);
  scene.add(sun, sun.target);
  new GLTFLoader().load("model.glb", gltf => {
    const box = new THREE.Box3().setFromObject(gltf.scene, true);  // precise, world space: the node matrix applied
    const size = box.getSize(new THREE.Vector3()), centre = box.getCenter(new THREE.Vector3());
    const radius = size.length() / 2;
    const camera = new THREE.PerspectiveCamera(40, __W__ / __H__, radius / 50, radius * 50);
    const dir = new THREE.Vector3(0.4, 0.3, 1.0).normalize();
    camera.position.copy(centre).addScaledVector(dir, 1.15 * radius / Math.sin(THREE.MathUtils.degToRad(20)));
    camera.lookAt(centre);
    sun.position.copy(camera.position);
    sun.target.position.copy(centre);
    scene.add(gltf.scene);
    renderer.render(scene, camera);
    let mesh = null;
    gltf.scene.traverse(o => { if (o.isMesh) mesh = o; });
    const m = mesh.material;
    report({
      size: size.toArray(), min: box.min.toArray(), max: box.max.toArray(), metalness: m.metalness, roughness: m.roughness, color: m.color.toArray(),
      map: m.map ? [m.map.image.width, m.map.image.height] : null,
      triangles: mesh.geometry.index.count / 3, normals: !!mesh.geometry.attributes.normal,
      units: gltf.asset.extras ? gltf.asset.extras.units : null});
  }, undefined, err => report("error " + err));
} catch (err) { report("error " + err); }
</script><img src="wait.png" alt="" style="display:none"></body></html>
"""


MODEL_VIEWER_PAGE = """<!DOCTYPE html>
<html><head><meta charset="utf-8"><style>body{margin:0;background:#000}
model-viewer{width:__W__px;height:__H__px;background:#000;--poster-color:transparent}</style>
<script src="model-viewer-umd.min.js"></script>
</head><body>
<model-viewer id="mv" src="model.glb" interaction-prompt="none"></model-viewer>
<script>
const report = body => fetch("result", {method: "POST", body: typeof body === "string" ? body : JSON.stringify(body)});
const mv = document.getElementById("mv");
mv.addEventListener("error", e => report("error " + JSON.stringify(e.detail)));
mv.addEventListener("load", () => {
  // two frames after the load: the model is drawn
  requestAnimationFrame(() => requestAnimationFrame(() => {
    const size = mv.getDimensions();
    report({size: [size.x, size.y, size.z]});
  }));
});
</script><img src="wait.png" alt="" style="display:none"></body></html>
"""


@pytest.fixture(scope="module")
def baked():
    mesh = bunny_mm(3000)
    regions = bunny_regions(mesh)
    files = projection_textures(TextureParams(texture_px=1024), mesh, regions, bunny_layout(mesh, 8, 6))
    return mesh, files.contents, regions.up


def _standing_m(vertices_mm: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Vertices (m) as a viewer places them: the standing transform applied."""
    v = vertices_mm / 1000.0
    T = standing_transform(v, up)
    return v @ T[:3, :3].T + T[:3, 3]


def _glb_json(glb: bytes) -> dict:
    length = struct.unpack("<I", glb[12:16])[0]
    return json.loads(glb[20 : 20 + length])


def test_glb_is_metres_with_a_matte_material_and_the_texture_embedded(baked):
    mesh, contents, _ = baked
    glb = contents["projection/bunny_layout.glb"]
    tree = _glb_json(glb)
    assert tree["asset"]["extras"] == {"units": "m", "face_order": "mesh.ply"}
    (material,) = tree["materials"]
    pbr = material["pbrMetallicRoughness"]
    assert pbr["metallicFactor"] == 0.0 and pbr["roughnessFactor"] == GLB_ROUGHNESS
    assert pbr["baseColorFactor"] == [1.0, 1.0, 1.0, 1.0]
    (image,) = tree["images"]
    assert image["mimeType"] == "image/png" and "bufferView" in image and "uri" not in image  # embedded
    (geometry,) = trimesh.load(io.BytesIO(glb), file_type="glb", force="scene", process=False).geometry.values()
    extent_m = np.ptp(mesh.vertices, axis=0) / 1000.0
    np.testing.assert_allclose(np.ptp(geometry.vertices, axis=0), extent_m, rtol=1e-6)  # the mesh's frame, in m
    assert "NORMAL" in tree["meshes"][0]["primitives"][0]["attributes"]


def test_obj_and_glb_face_order_is_mesh_ply_face_order(baked, tmp_path):
    """Face k of the OBJ and of the GLB has the corners of face k of mesh.ply, in the same order."""
    mesh, contents, _ = baked
    (tmp_path / "mesh.ply").write_bytes(ply_bytes(mesh.vertices, mesh.faces))
    ply = trimesh.load(tmp_path / "mesh.ply", process=False)
    ply_corners = ply.vertices[ply.faces]
    np.testing.assert_array_equal(ply.faces, mesh.faces)
    glb_scene = trimesh.load(io.BytesIO(contents["projection/bunny_layout.glb"]), file_type="glb", force="scene", process=False)
    (glb,) = glb_scene.geometry.values()  # untransformed: the node matrix only stands it up
    np.testing.assert_allclose(glb.vertices[glb.faces] * 1000.0, ply_corners, atol=1e-4)
    for rel, data in contents.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_bytes(data)
    obj = trimesh.load(tmp_path / "projection/bunny_layout.obj", process=False, maintain_order=True)
    np.testing.assert_allclose(obj.vertices[obj.faces], ply_corners, atol=1e-5)


class _ViewerSite(http.server.SimpleHTTPRequestHandler):
    """Static files, plus POST /result (the page's report) and GET /wait.png (answered after it)."""

    reported: threading.Event
    report: list[str]

    def do_POST(self) -> None:  # noqa: N802 (http.server's naming)
        body = self.rfile.read(int(self.headers.get("Content-Length", 0))).decode()
        self.report.append(body)
        self.reported.set()
        self.send_response(204)
        self.end_headers()

    def do_GET(self) -> None:  # noqa: N802
        if self.path.startswith("/wait.png"):
            self.reported.wait(90)
            ok, png = cv2.imencode(".png", np.zeros((1, 1, 3), np.uint8))
            self.send_response(200)
            self.send_header("Content-Type", "image/png")
            self.send_header("Content-Length", str(len(png)))
            self.end_headers()
            self.wfile.write(png.tobytes())
            return
        super().do_GET()

    def log_message(self, *args) -> None:
        pass


@contextlib.contextmanager
def _serve(glb: bytes, site: Path, page: str, library: tuple[str, Path]):
    """The GLB, the page and the viewer library in ``site`` on 127.0.0.1 (a random port): yields
    (url, reports, event)."""
    site.mkdir()
    (site / library[0]).symlink_to(library[1])
    (site / "model.glb").write_bytes(glb)
    (site / "index.html").write_text(page.replace("__W__", str(VIEW_W)).replace("__H__", str(VIEW_H)))
    reported, reports = threading.Event(), []
    handler = type("Site", (_ViewerSite,), {"reported": reported, "report": reports})
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(handler, directory=str(site)))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/index.html", reports, reported
    finally:
        reported.set()
        server.shutdown()
        server.server_close()


def _need_chromium() -> None:
    if shutil.which("chromium") is None:
        pytest.skip("chromium is not installed (apt-get install -y chromium): the GLB is not checked in a viewer")


@pytest.fixture
def served(baked, tmp_path):
    """The GLB and the three.js page served: yields (url, reports, event)."""
    _need_chromium()
    if not (THREE / "build" / "three.module.js").is_file():
        pytest.skip("three.js is not installed (npm ci --prefix tests/glb_viewer): the GLB is not checked in three.js")
    with _serve(baked[1]["projection/bunny_layout.glb"], tmp_path / "site", PAGE, ("three", THREE)) as site:
        yield site


def _lit_object_pixels(shot: Path) -> np.ndarray:
    """Luminance (0-255) of the screenshot's object pixels (the background is black)."""
    image = cv2.imread(str(shot))
    assert image is not None and image.shape[:2] == (VIEW_H, VIEW_W)
    luminance = image.astype(float) @ np.array([0.114, 0.587, 0.299])  # BGR
    object_pixels = luminance > 8
    assert object_pixels.mean() > 0.05, "the object covers too little of the view"
    return luminance[object_pixels]


def test_three_js_sees_the_object_in_metres_standing_and_renders_it_lit(baked, served, tmp_path):
    mesh, _, up = baked
    url, reports, reported = served
    shot = tmp_path / "view.png"
    run_chromium([f"--window-size={VIEW_W},{VIEW_H}", "--virtual-time-budget=5000", f"--screenshot={shot}", url],
              tmp_path / "profile")
    assert reported.is_set() and reports and reports[0].startswith("{"), reports
    report = json.loads(reports[0])
    standing = _standing_m(mesh.vertices, up)
    extent_m = np.ptp(standing, axis=0)
    # three.js's bounding box is the standing object's size in metres (within 1 % of its diagonal),
    # resting on the ground plane y = 0
    assert np.abs(np.array(report["size"]) - extent_m).max() < 0.01 * np.linalg.norm(extent_m), report
    assert abs(report["min"][1]) < 1e-6 and report["max"][1] == pytest.approx(extent_m[1], rel=1e-4)
    assert report["metalness"] == 0.0 and report["roughness"] == pytest.approx(GLB_ROUGHNESS)
    assert report["color"] == [1, 1, 1] and report["map"] == [1024, 1024] and report["normals"]
    assert report["triangles"] == len(mesh.faces) and report["units"] == "m"
    lit = _lit_object_pixels(shot)
    assert lit.mean() > 110, lit.mean()


def test_model_viewer_frames_the_standing_object_in_metres_and_renders_it_lit(baked, tmp_path):
    """``<model-viewer>`` with nothing set: its dimensions are the standing object's size in metres
    (the height along its up axis, within 1 % of the diagonal) and its default lighting shows it lit."""
    _need_chromium()
    if not MODEL_VIEWER_JS.is_file():
        pytest.skip("model-viewer is not installed (npm ci --prefix tests/model_viewer): the GLB is not checked in it")
    mesh, contents, up = baked
    glb = contents["projection/bunny_layout.glb"]
    with _serve(glb, tmp_path / "site", MODEL_VIEWER_PAGE, ("model-viewer-umd.min.js", MODEL_VIEWER_JS)) as (url, reports, reported):
        shot = tmp_path / "view.png"
        run_chromium([f"--window-size={VIEW_W},{VIEW_H}", "--virtual-time-budget=10000", f"--screenshot={shot}", url],
                     tmp_path / "profile")
    assert reported.is_set() and reports and reports[0].startswith("{"), reports
    extent_m = np.ptp(_standing_m(mesh.vertices, up), axis=0)
    size = np.array(json.loads(reports[0])["size"])
    assert np.abs(size - extent_m).max() < 0.01 * np.linalg.norm(extent_m), (size, extent_m)
    assert _lit_object_pixels(shot).mean() > 80


@pytest.mark.parametrize("file_up", ["z", "y", "tilted"])
def test_glb_stands_the_object_whatever_axis_the_file_called_up(file_up):
    """The same object turned in the file so that its up is +z, +y or a tilted axis: the standing
    transform puts it on the ground plane the same way (up along +Y, same height, lowest point at 0)."""
    from scipy.spatial.transform import Rotation

    mesh = bunny_mm(1500)
    up = np.array([0.0, 0.0, 1.0])  # bunny_mm is +z up
    turn = {"z": Rotation.identity(), "y": Rotation.from_euler("x", -90, degrees=True),
            "tilted": Rotation.from_euler("xyz", [30, -50, 110], degrees=True)}[file_up]
    turned_mm = turn.apply(mesh.vertices)
    turned_up = turn.apply(up)
    standing = _standing_m(turned_mm, turned_up)
    reference = _standing_m(mesh.vertices, up)
    assert standing[:, 1].min() == pytest.approx(0.0, abs=1e-9)
    # heights above the ground do not depend on how the file was turned
    np.testing.assert_allclose(standing[:, 1], reference[:, 1], atol=1e-9)
    np.testing.assert_allclose(standing[:, 1], (turned_mm @ turned_up - (turned_mm @ turned_up).min()) / 1000.0, atol=1e-9)
