"""preview.render: PNG views with both layers depth-tested, self-contained HTML viewer."""
from __future__ import annotations

import base64
import json
import re

import cv2
import numpy as np
import pytest
import trimesh

from touch_fixture import touch_of
from retrotouch.nodes.data.types import Crossings, CurveSet, CurveEnd, Layout, Mesh, SurfaceRegions
from retrotouch.nodes.preview.render import PreviewParams, render_layout_preview, render_preview
from retrotouch.nodes.preview.views import (
    CAPTION_LINE_PX, CAPTION_SCALE, CROSSING_RGB, RX_RGB, TABLE_RGB, TX_RGB, UNCOVERED_RGB, UP_RGB, camera, caption_lines, face_colours,
    render_view, segments,
)
from retrotouch.nodes.regions.detect import RegionParams, detect_regions

RADIUS = 40.0


@pytest.fixture(scope="module")
def sphere() -> Mesh:
    tm = trimesh.creation.icosphere(subdivisions=3, radius=RADIUS)
    return Mesh(np.asarray(tm.vertices, dtype=np.float64), np.asarray(tm.faces, dtype=np.int64), "sphere")


@pytest.fixture(scope="module")
def regions(sphere: Mesh) -> SurfaceRegions:
    return detect_regions(RegionParams(up_axis="+z", exclusion_base_mm=5.0, exclusion_far_mm=8.0), sphere, touch_of(sphere))


def curve_set(mesh: Mesh, polylines: list[np.ndarray], layer: str) -> CurveSet:
    """A CurveSet whose points are the polylines snapped onto the mesh, with faces and barycentrics."""
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    points = np.vstack(polylines)
    on_surface, _, faces = trimesh.proximity.closest_point(tm, points)
    bary = trimesh.triangles.points_to_barycentric(tm.triangles[faces], on_surface)
    offsets = np.r_[0, np.cumsum([len(p) for p in polylines])].astype(np.int64)
    lengths = np.array([np.linalg.norm(np.diff(on_surface[a:b], axis=0), axis=1).sum() for a, b in zip(offsets[:-1], offsets[1:])])
    return CurveSet(
        layer=layer,
        points=on_surface,
        faces=faces.astype(np.int64),
        bary=bary,
        offsets=offsets,
        lengths_mm=lengths,
        end_reason=np.full(len(polylines), CurveEnd.BASE, dtype=np.int8),
        angle=0.0,
    )


def circle(axis_a: np.ndarray, axis_b: np.ndarray, count: int = 200, start: float = 0.0, stop: float = 2 * np.pi) -> np.ndarray:
    t = np.linspace(start, stop, count)
    return RADIUS * (np.cos(t)[:, None] * axis_a + np.sin(t)[:, None] * axis_b)


@pytest.fixture(scope="module")
def layers(sphere: Mesh) -> tuple[CurveSet, CurveSet]:
    x, y, z = np.eye(3)
    tx = curve_set(sphere, [circle(x, z), circle(y, z)], "tx")  # two meridian great circles
    rx = curve_set(sphere, [circle(x, y) * [1, 1, 0] + [0, 0, 10.0]], "rx")  # a latitude ring
    return tx, rx


def colour_pixels(image_rgb: np.ndarray, rgb: tuple[int, int, int]) -> int:
    return int(np.all(image_rgb == np.asarray(rgb, dtype=np.uint8), axis=2).sum())


def test_segments_skip_curve_joins(layers: tuple[CurveSet, CurveSet]) -> None:
    tx, _ = layers
    start, end = segments(tx)
    assert len(start) == len(tx.points) - tx.count
    assert 199 not in start  # the last row of curve 0 does not connect to curve 1


def test_png_has_expected_size_and_both_layers(sphere: Mesh, regions: SurfaceRegions, layers) -> None:
    tx, rx = layers
    files = render_preview(PreviewParams(view_px=200), sphere, regions, tx, rx)
    assert set(files.contents) == {"preview.png", "preview.html"}
    image = cv2.imdecode(np.frombuffer(files.contents["preview.png"], np.uint8), cv2.IMREAD_COLOR)
    assert image.shape[1] == 400 and image.shape[0] > 400  # the pose caption below the 2 x 2 views
    rgb = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    assert colour_pixels(rgb, TX_RGB) > 200 and colour_pixels(rgb, RX_RGB) > 100


def test_curves_behind_the_object_are_hidden(sphere: Mesh, regions: SurfaceRegions) -> None:
    view = camera(np.zeros(3), RADIUS, np.array([0.0, 0.0, 1.0]), np.radians(30.0), np.radians(10.0))
    eye = -view[:3, :3].T @ view[:3, 3]
    towards = eye / np.linalg.norm(eye)
    across = np.cross(towards, [0.0, 0.0, 1.0])
    across /= np.linalg.norm(across)
    near_arc = curve_set(sphere, [circle(towards, across, start=-0.6, stop=0.6)], "rx")
    far_arc = curve_set(sphere, [circle(-towards, across, start=-0.6, stop=0.6)], "rx")
    colours = face_colours(len(sphere.faces), regions)
    seen = render_view(sphere, colours, [(near_arc, RX_RGB)], None, view, 200, 2)
    hidden = render_view(sphere, colours, [(far_arc, RX_RGB)], None, view, 200, 2)
    assert colour_pixels(seen, RX_RGB) > 50
    assert colour_pixels(hidden, RX_RGB) == 0


def test_pads_of_a_layout_are_marked(sphere: Mesh, regions: SurfaceRegions, layers) -> None:
    tx, rx = layers
    point = np.array([[RADIUS * np.sqrt(1 - (10 / RADIUS) ** 2), 0.0, 10.0]] * 2)
    one = np.zeros(2, np.int64)
    cells = Crossings("tx", "rx", one, one, one, one, np.zeros(2), np.zeros(2), point, one, np.full((2, 3), 1 / 3))
    def draw(pad: list[bool], spots: list[list[float]] = ()) -> np.ndarray:
        layout = Layout(tx, rx, cells, np.array(pad), np.arange(tx.count), np.arange(rx.count))
        metrics = {"uncovered_threshold_mm": 10.0, "uncovered_share": 0.1 if spots else 0.0,
                   "uncovered_spots": [{"area_mm2": 300.0, "max_distance_mm": 15.0, "point": p} for p in spots]}
        files = render_layout_preview(PreviewParams(view_px=200), sphere, regions, layout, metrics)
        return cv2.cvtColor(cv2.imdecode(np.frombuffer(files.contents["preview.png"], np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    assert colour_pixels(draw([True, False]), CROSSING_RGB) > 5
    assert colour_pixels(draw([False, False]), CROSSING_RGB) == 0
    # an uncovered spot's farthest point is ringed, in every view that sees it
    assert colour_pixels(draw([False, False]), UNCOVERED_RGB) == 0
    assert colour_pixels(draw([False, False], [point[0].tolist()]), UNCOVERED_RGB) > 30


def test_html_is_self_contained_and_embeds_the_data(sphere: Mesh, regions: SurfaceRegions, layers) -> None:
    tx, rx = layers
    html = render_preview(PreviewParams(view_px=64), sphere, regions, tx, rx).contents["preview.html"].decode("utf-8")
    assert not re.search(r"(https?:|ftp:|//[a-z0-9.-]+\.[a-z]{2,}/)", html, re.IGNORECASE)
    assert not re.search(r"<(script|link|img|iframe)[^>]*\s(src|href)\s*=", html, re.IGNORECASE)
    block = re.search(r'<script type="application/json" id="retrotouch-data">(.*?)</script>', html, re.S)
    data = json.loads(block.group(1))
    vertices = np.frombuffer(base64.b64decode(data["vertices"]), "<f4").reshape(-1, 3)
    np.testing.assert_allclose(vertices, sphere.vertices, atol=1e-4)
    faces = np.frombuffer(base64.b64decode(data["faces"]), "<u4").reshape(-1, 3)
    assert np.array_equal(faces, sphere.faces)
    region = np.frombuffer(base64.b64decode(data["region"]), "u1")
    assert set(np.unique(region)) == {0, 1, 2} and (region[np.unique(sphere.faces[regions.base_faces])] == 2).all()
    tx_lines = np.frombuffer(base64.b64decode(data["tx"]["lines"]), "<f4").reshape(-1, 3)
    assert len(tx_lines) == 2 * (len(tx.points) - tx.count) and data["tx"]["count"] == 2
    assert np.abs(np.linalg.norm(tx_lines, axis=1) - RADIUS).max() < 1.5  # on (just above) the surface


def test_png_draws_the_resting_pose(sphere: Mesh, regions: SurfaceRegions, layers) -> None:
    """The table plane (brown) lies below the object, the up arrow (green) points up in a view
    looking down, and the caption under the four views names the pose kind and its reason."""
    tx, rx = layers
    png = render_preview(PreviewParams(view_px=200), sphere, regions, tx, rx).contents["preview.png"]
    image = cv2.cvtColor(cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    assert image.shape[1] == 400 and image.shape[0] > 400 + CAPTION_LINE_PX
    caption = image[400:]
    assert (caption.min(axis=2) < 100).sum() > 200  # dark caption text on white
    front_left = image[:200, :200]
    table_rows = np.flatnonzero((front_left == TABLE_RGB).all(axis=2).any(axis=1))
    arrow_rows = np.flatnonzero((front_left == UP_RGB).all(axis=2).any(axis=1))
    assert len(table_rows) > 20 and len(arrow_rows) > 20
    sphere_rows = np.flatnonzero((np.abs(front_left.astype(int) - 255).sum(axis=2) > 60).any(axis=1))
    assert np.median(table_rows) > np.median(sphere_rows)  # the table is drawn under the sphere
    assert arrow_rows.min() < table_rows.min()  # the arrow rises above the table


def test_caption_wraps_within_the_width() -> None:
    text = "rests on a flat bottom (12.0% of the surface), tips over at 40 deg; the stable pose " * 3
    lines = caption_lines(text, 300)
    assert len(lines) > 3 and " ".join(lines) == " ".join(text.split())
    assert max(cv2.getTextSize(line, cv2.FONT_HERSHEY_SIMPLEX, CAPTION_SCALE, 1)[0][0] for line in lines) <= 300 - 16
