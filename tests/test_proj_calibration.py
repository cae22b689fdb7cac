"""Projector-camera calibration on synthetic captures of known truth, and the end-to-end landmark accuracy."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from proj_fixtures import BOARD, bunny_layout, bunny_mm, calibrate_synthetic, demo_rig, landing_points
from retrotouch.graph.errors import UserError
from retrotouch.nodes.data.scene import build_scene
from retrotouch.nodes.projection.calibration import load_calibration, save_calibration
from retrotouch.nodes.projection.camera import project_points, transform_points
from retrotouch.nodes.projection.depth_frames import SyntheticDepthSource, demo_trajectory
from retrotouch.nodes.projection.raster import rasterize_depth
from retrotouch.nodes.projection.render import RenderStyle, visible_points
from retrotouch.nodes.projection.structured_light import checkerboard_image, decode_gray_code, find_board_corners, gray_code_patterns
from retrotouch.nodes.projection.tracking import DepthTracker


@pytest.fixture(scope="module")
def rig():
    return demo_rig(640, 360)


@pytest.fixture(scope="module")
def estimated(rig):
    return calibrate_synthetic(rig, count=7)


def test_gray_code_decodes_the_projector_itself():
    w, h = 100, 37
    white, black, *stack = gray_code_patterns(w, h)
    assert len(stack) == 2 * (7 + 6)
    px, py, valid = decode_gray_code(stack, w, h, white, black)
    assert valid.all()
    np.testing.assert_array_equal(px, np.tile(np.arange(w), (h, 1)))
    np.testing.assert_array_equal(py, np.tile(np.arange(h)[:, None], (1, w)))


def test_decoding_rejects_unlit_and_ambiguous_pixels():
    w, h = 64, 16
    white, black, *stack = gray_code_patterns(w, h)
    stack = [s.astype(np.float32) for s in stack]
    white = white.astype(np.float32)
    white[:, :8] = 20.0  # shadow: white - black below the black threshold
    for s in stack:
        s[:, 8:16] = 128.0  # no contrast between a pattern and its inverse
    _, _, valid = decode_gray_code(stack, w, h, white, black)
    assert not valid[:, :16].any() and valid[:, 16:].all()


def test_decoding_needs_the_full_stack():
    white, black, *stack = gray_code_patterns(64, 16)
    with pytest.raises(UserError, match="gray-code captures"):
        decode_gray_code(stack[:-2], 64, 16, white, black)


def test_checkerboard_image_corners_are_where_printed():
    img = checkerboard_image(BOARD, square_px=30)
    assert img.shape == ((BOARD.rows + 1) * 30 + 60, (BOARD.cols + 1) * 30 + 60)
    corners = find_board_corners(img.astype(np.float32), BOARD)
    assert corners is not None
    expected = BOARD.object_points()[:, :2] / BOARD.square_mm * 30 + 30 + 30 - 0.5
    d = np.linalg.norm(np.sort(corners, axis=0) - np.sort(expected, axis=0), axis=1)
    assert d.max() < 0.3


def test_synthetic_calibration_recovers_the_rig(rig, estimated):
    assert estimated.rms_camera_px < 0.3
    assert estimated.rms_projector_px < 0.3
    assert estimated.rms_stereo_px < 0.3
    assert abs(estimated.camera.K[0, 0] / rig.camera.K[0, 0] - 1) < 0.005
    assert abs(estimated.projector.K[0, 0] / rig.projector.K[0, 0] - 1) < 0.005
    assert np.rad2deg(Rotation.from_matrix(estimated.R @ rig.R.T).magnitude()) < 0.2
    assert np.linalg.norm(estimated.T - rig.T) < 1.0


def test_calibration_file_round_trip_and_errors(tmp_path, estimated):
    path = tmp_path / "rig.json"
    save_calibration(estimated, path)
    back = load_calibration(path)
    np.testing.assert_allclose(back.projector.K, estimated.projector.K)
    np.testing.assert_allclose(back.T, estimated.T)
    assert back.camera.width == 640 and back.rms_stereo_px == estimated.rms_stereo_px
    with pytest.raises(UserError, match="cannot read"):
        load_calibration(tmp_path / "missing.json")
    data = json.loads(path.read_text())
    data["camera"]["K"] = [[1, 0], [0, 1]]
    path.write_text(json.dumps(data))
    with pytest.raises(UserError, match="camera"):
        load_calibration(path)


def test_projected_crossings_land_within_1mm(rig, estimated):
    """Estimated calibration + tracked pose -> projector pixels; light from them, in the true rig, hits the true crossing."""
    mesh = bunny_mm(5000)
    scene = build_scene(mesh, bunny_layout(mesh))
    poses = demo_trajectory(4)
    tracker = DepthTracker(mesh, estimated.camera)
    errors = []
    for frame in SyntheticDepthSource(mesh, rig.camera, poses, noise_mm=0.5).frames():
        result = tracker.update(frame)
        assert result.status in ("found", "tracked")
        T_true = rig.T_proj_cam @ poses[frame.index]
        T_est = estimated.T_proj_cam @ result.raw_T_cam_obj
        zbuf = rasterize_depth(transform_points(T_est, mesh.vertices), mesh.faces, estimated.projector.K, 640, 360)
        vis = visible_points(scene.crossing_points, scene.crossing_normals, T_est, estimated.projector.K, zbuf, RenderStyle(), landmarks=True)
        assert vis.sum() >= 5
        pixels = project_points(transform_points(T_est, scene.crossing_points[vis]), estimated.projector)
        landed = landing_points(pixels, mesh.vertices, mesh.faces, T_true, rig.projector)
        errors.append(np.linalg.norm(landed - scene.crossing_points[vis], axis=1))
    errors = np.concatenate(errors)
    assert np.isfinite(errors).all()
    assert errors.max() < 1.0, errors
