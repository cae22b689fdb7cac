"""Projector rendering: z-buffer accuracy, back-face culling, occlusion, layer order."""
from __future__ import annotations

import cv2
import numpy as np
import trimesh

from retrotouch.nodes.data.scene import ProjectionScene
from retrotouch.nodes.projection.camera import DeviceIntrinsics, project_points
from retrotouch.nodes.projection.raster import rasterize_depth, render_textured
from retrotouch.nodes.projection.render import render_layers

K = np.array([[800.0, 0.0, 330.0], [0.0, 790.0, 236.0], [0.0, 0.0, 1.0]])
PROJECTOR = DeviceIntrinsics(K, np.array([0.02, 0.0, 0.0, 0.0, 0.0]), 640, 480)


def test_zbuffer_matches_the_analytic_plane_depth():
    # a tilted square, outward normal towards the camera (-z), CCW seen from the camera
    corners = np.array([[-80.0, -60.0, 520.0], [-80.0, 60.0, 470.0], [80.0, 60.0, 480.0], [80.0, -60.0, 530.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    depth = rasterize_depth(corners, faces, K, 640, 480)
    n = np.cross(corners[1] - corners[0], corners[2] - corners[0])
    rows, cols = np.nonzero(np.isfinite(depth))
    rays = np.linalg.solve(K, np.stack([cols, rows, np.ones_like(cols)]).astype(float)).T
    z = (n @ corners[0]) / (rays @ n)  # ray (x, y, 1) * z hits the plane
    assert np.abs(depth[rows, cols] - z).max() < 0.05
    proj = corners @ K.T
    proj = proj[:, :2] / proj[:, 2:]
    assert cols.min() >= np.floor(proj[:, 0].min()) and cols.max() <= np.ceil(proj[:, 0].max())
    assert rows.min() >= np.floor(proj[:, 1].min()) and rows.max() <= np.ceil(proj[:, 1].max())
    assert 0.97 < len(rows) / _quad_area(proj) < 1.03


def _quad_area(p: np.ndarray) -> float:
    x, y = p[:, 0], p[:, 1]
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _ring(centre: np.ndarray, radius: float, normal_sign: float, z_offset: float, count: int = 90):
    """A circle on a sphere (centre, radius) at height z_offset from its centre along the view axis."""
    r = np.sqrt(radius**2 - z_offset**2)
    t = np.linspace(0, 2 * np.pi, count)
    pts = centre + np.stack([r * np.cos(t), r * np.sin(t), np.full(count, z_offset)], axis=1)
    return pts, (pts - centre) / radius


def test_culling_and_occlusion():
    """Two spheres on the projector axis: A in front hides part of B; rings on B's back, B's hidden front and B's visible rim."""
    a = trimesh.creation.icosphere(subdivisions=4, radius=40.0)
    b = trimesh.creation.icosphere(subdivisions=4, radius=80.0)
    ca, cb = np.array([0.0, 0.0, 450.0]), np.array([0.0, 0.0, 700.0])
    vertices = np.vstack([a.vertices + ca, b.vertices + cb])
    faces = np.vstack([a.faces, b.faces + len(a.vertices)])
    hidden_front, n_hidden = _ring(cb, 80.0, 1.0, -79.0)  # small ring facing the projector, behind A
    back, n_back = _ring(cb, 80.0, 1.0, 60.0)  # on B's far side
    rim, n_rim = _ring(cb, 80.0, 1.0, -50.0)  # facing the projector, outside A's shadow
    scene = ProjectionScene(
        vertices=vertices,
        faces=faces,
        layer_names=("tx", "rx"),
        layer_points=(np.vstack([hidden_front, back]), rim),
        layer_normals=(np.vstack([n_hidden, n_back]), n_rim),
        layer_offsets=(np.array([0, 90, 180]), np.array([0, 90])),
        crossing_points=np.zeros((0, 3)),
        crossing_normals=np.zeros((0, 3)),
        pad=np.zeros(0, bool), pad_radius_mm=2.0,
    )
    images = render_layers(scene, np.eye(4), PROJECTOR)
    assert list(images) == ["tx", "rx"]
    assert images["tx"].max() == 0  # every tx point is culled or occluded
    uv = np.rint(project_points(rim, PROJECTOR)).astype(int)
    lit = images["rx"].max(axis=2)[uv[:, 1], uv[:, 0]] > 0
    assert lit.mean() > 0.95


def test_rendered_lines_sit_on_the_projected_points():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=60.0)
    centre = np.array([10.0, -5.0, 500.0])
    pts, normals = _ring(centre, 60.0, 1.0, -40.0)
    scene = ProjectionScene(
        vertices=sphere.vertices + centre,
        faces=np.asarray(sphere.faces),
        layer_names=("tx", "rx"),
        layer_points=(pts, pts[:0]),
        layer_normals=(normals, normals[:0]),
        layer_offsets=(np.array([0, len(pts)]), np.array([0])),
        crossing_points=np.zeros((0, 3)),
        crossing_normals=np.zeros((0, 3)),
        pad=np.zeros(0, bool), pad_radius_mm=2.0,
    )
    images = render_layers(scene, np.eye(4), PROJECTOR)
    lit_rows, lit_cols = np.nonzero(images["tx"].max(axis=2) > 127)
    uv = project_points(pts, PROJECTOR)
    # every lit pixel is within the line half-width (+ AA) of the projected polyline
    d = np.min(np.linalg.norm(np.stack([lit_cols, lit_rows], axis=1)[:, None, :] - uv[None, :, :], axis=2), axis=1)
    seg = np.linalg.norm(np.diff(uv, axis=0), axis=1).max()
    assert d.max() < 2.0 + seg / 2
    assert images["rx"].max() == 0


def test_textured_route_interpolates_uv_perspective_correctly():
    """A steeply tilted quad with a texture encoding its own coordinates: rendered colours match exact ray-plane UVs."""
    corners = np.array([[-80.0, -60.0, 520.0], [-80.0, 60.0, 330.0], [80.0, 60.0, 330.0], [80.0, -60.0, 520.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.array([[0.0, 1.0], [0.0, 0.0], [1.0, 0.0], [1.0, 1.0]])  # v up (OBJ): top image row = corner 0 side
    cols, rows = np.meshgrid(np.arange(256), np.arange(256))
    texture = np.stack([cols, rows, np.zeros_like(cols)], axis=2).astype(np.uint8)
    scene = ProjectionScene(
        vertices=corners, faces=faces, layer_names=("tx",), layer_points=(np.zeros((0, 3)),),
        layer_normals=(np.zeros((0, 3)),), layer_offsets=(np.array([0]),), crossing_points=np.zeros((0, 3)),
        crossing_normals=np.zeros((0, 3)), pad=np.zeros(0, bool), pad_radius_mm=2.0,
        atlas_vertex_map=np.arange(4), atlas_faces=faces, atlas_uv=uv, layer_textures=(texture,),
    )
    device = DeviceIntrinsics(K, np.zeros(5), 640, 480)
    image = render_textured(scene, 0, np.eye(4), device)
    depth = rasterize_depth(corners, faces, K, 640, 480)
    inner = np.isfinite(depth) & (cv2.erode(np.isfinite(depth).astype(np.uint8), np.ones((5, 5))) > 0)
    r, c = np.nonzero(inner)
    rays = np.linalg.solve(K, np.stack([c, r, np.ones_like(c)]).astype(float)).T
    n = np.cross(corners[1] - corners[0], corners[2] - corners[0])
    p = rays * ((n @ corners[0]) / (rays @ n))[:, None]
    u = (p[:, 0] + 80.0) / 160.0
    v_row = (p[:, 1] + 60.0) / 120.0  # texture row fraction (0 at corner 0's edge)
    assert np.abs(image[r, c, 0] - (u * 256 - 0.5)).max() < 1.5
    assert np.abs(image[r, c, 1] - (v_row * 256 - 0.5)).max() < 1.5
