"""Synthetic scenes with known truth for the projection tests and benchmark.

* :func:`bunny_mm` -- pymeshlab's bunny, 170 mm bounding-box diagonal, centred, +z up (the
  plane-section layouts of ``fab_layouts`` take meridians about the z axis).
* :func:`bunny_regions` -- its base and resting pose, as ``regions.detect`` finds them.
* :func:`demo_rig` -- a plausible projector-camera rig (the truth of synthetic runs).
* :class:`BoardCaptureSimulator` -- what the camera sees when the projector lights a checkerboard.
* :func:`board_poses` -- checkerboard poses in front of a rig's camera where the projector lights them.
* :func:`calibrate_synthetic` -- a calibration estimated from simulated gray-code captures.
* :func:`write_depth_png` -- a depth frame as the 16-bit PNG a recording holds.
* :func:`landing_points` -- where light from projector pixels lands on the mesh (ray casting).
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from curves_fixture import load_scaled, sample_mesh_path
from fab_layouts import section_layout
from touch_fixture import touch_of
from retrotouch.nodes.data.types import Layout, Mesh, SurfaceRegions
from retrotouch.nodes.projection.calibration import BoardCapture, ProCamCalibration, calibrate_procam
from retrotouch.nodes.projection.camera import DeviceIntrinsics, distort_normalised, invert_pose
from retrotouch.nodes.projection.structured_light import BoardSpec, gray_code_patterns
from retrotouch.nodes.regions.detect import RegionParams, detect_regions

BOARD = BoardSpec(cols=9, rows=7, square_mm=15.0)


def bunny_mm(target_vertices: int = 5000) -> Mesh:
    """The bunny in mm: 170 mm diagonal, bounding-box centre at the origin, y-up file turned to +z up."""
    m = load_scaled(sample_mesh_path("bunny.obj"), 170.0, target_vertices=target_vertices)
    v = m.vertices - (m.vertices.max(axis=0) + m.vertices.min(axis=0)) / 2
    up = Rotation.from_euler("x", 90, degrees=True).as_matrix()  # (x, y, z) -> (x, -z, y): y-up becomes z-up
    return Mesh(v @ up.T, m.faces, "builtin:bunny")


def bunny_regions(mesh: Mesh) -> SurfaceRegions:
    return detect_regions(RegionParams(), mesh, touch_of(mesh))


def bunny_layout(mesh: Mesh, n_tx: int = 12, n_rx: int = 8) -> Layout:
    return section_layout(mesh, n_tx, n_rx)


def board_poses(count: int, seed: int = 0, distance_mm: float = 540.0) -> list[np.ndarray]:
    """``count`` poses T_cam_board: board centred near the optical axis, tilted up to 25 degrees."""
    rng = np.random.default_rng(seed)
    centre = np.array([(BOARD.cols - 1) * BOARD.square_mm / 2, (BOARD.rows - 1) * BOARD.square_mm / 2, 0.0])
    poses = []
    for _ in range(count):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("xyz", rng.uniform(-25, 25, 3), degrees=True).as_matrix()
        target = np.array([rng.uniform(-20, 20), rng.uniform(-15, 15), distance_mm + rng.uniform(-50, 50)])
        T[:3, 3] = target - T[:3, :3] @ centre
        poses.append(T)
    return poses


def calibrate_synthetic(truth: ProCamCalibration, count: int = 8, seed: int = 0) -> ProCamCalibration:
    """Calibrate from ``count`` simulated board captures of the rig ``truth``."""
    sim = BoardCaptureSimulator(truth, BOARD)
    captures = [sim.capture(T, seed=seed + i) for i, T in enumerate(board_poses(count, seed))]
    return calibrate_procam(captures, BOARD, truth.projector.width, truth.projector.height)


def demo_rig(width: int = 1280, height: int = 720) -> ProCamCalibration:
    """A plausible rig (the known truth of synthetic runs): camera f = 0.78 w, projector f = 1.2 w,
    the projector 150 mm left of and 30 mm below the camera, turned 15 degrees towards it, both
    ``width`` x ``height``; a little radial distortion on each; about 550 mm to the work area.
    """
    f_cam, f_proj = 0.78 * width, 1.2 * width
    camera = DeviceIntrinsics(
        np.array([[f_cam, 0.0, width / 2 + 3.0], [0.0, f_cam, height / 2 - 2.0], [0.0, 0.0, 1.0]]),
        np.array([0.04, -0.08, 0.0, 0.0, 0.0]),
        width,
        height,
    )
    projector = DeviceIntrinsics(
        np.array([[f_proj, 0.0, width / 2], [0.0, f_proj, 0.58 * height], [0.0, 0.0, 1.0]]),
        np.array([0.02, 0.0, 0.0, 0.0, 0.0]),
        width,
        height,
    )
    R_cam_proj = Rotation.from_euler("y", 15.0, degrees=True).as_matrix()
    centre = np.array([-150.0, 30.0, 0.0])  # projector centre in camera coordinates (mm)
    R = R_cam_proj.T
    return ProCamCalibration(camera, projector, R, -R @ centre, 0.0, 0.0, 0.0)


class BoardCaptureSimulator:
    """Renders what the camera sees when the projector's patterns light a checkerboard (known truth).

    The board plane (z = 0 of the board frame, mm) has albedo 0.9 on white squares and on a border
    of one square, 0.2 on black squares, 0.05 off the board. Camera pixels are traced through the
    camera's distortion (rays computed once); board points are projected with the projector's
    distortion onto the nearest pattern pixel. The white image is supersampled ``supersample``^2
    times so corners are sub-pixel accurate. Intensity = 255 * albedo * (0.1 + 0.85 * pattern) +
    Gaussian noise of ``noise_sigma`` grey levels.
    """

    def __init__(
        self,
        truth: ProCamCalibration,
        board: BoardSpec,
        noise_sigma: float = 1.0,
        supersample: int = 2,
    ) -> None:
        self.truth, self.board, self.noise_sigma, self.supersample = truth, board, noise_sigma, supersample
        self.patterns = gray_code_patterns(truth.projector.width, truth.projector.height)
        self._rays = {ss: self._camera_rays(ss) for ss in {1, supersample}}

    def _camera_rays(self, ss: int) -> tuple[np.ndarray, np.ndarray]:
        """Sample positions (N, 2) px and their undistorted rays (N, 3) (z = 1), row-major, ``ss``^2 per pixel."""
        cam = self.truth.camera
        offs = (np.arange(ss) + 0.5) / ss - 0.5
        xs = (np.arange(cam.width)[:, None] + offs[None, :]).ravel()
        ys = (np.arange(cam.height)[:, None] + offs[None, :]).ravel()
        gx, gy = np.meshgrid(xs, ys)
        pix = np.stack([gx.ravel(), gy.ravel()], axis=1)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-9)
        rays = cv2.undistortPoints(pix.reshape(-1, 1, 2), cam.K, cam.dist, None, None, None, criteria).reshape(-1, 2)
        return pix, np.column_stack([rays, np.ones(len(rays))])

    def _trace(self, T_cam_board: np.ndarray, ss: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Board albedo, projector pixel and 'lit by the projector' flag for each (super)sample.

        Only samples inside the board's image bounding box are traced; the background beyond it is
        far away, albedo 0.05 and unlit.
        """
        board, proj, cam = self.board, self.truth.projector, self.truth.camera
        pix, rays = self._rays[ss]
        lo, hi = -2 * board.square_mm, (np.array([board.cols, board.rows]) + 1) * board.square_mm
        outline = np.array([[lo, lo, 0], [hi[0], lo, 0], [hi[0], hi[1], 0], [lo, hi[1], 0]], np.float64)
        ob, _ = cv2.projectPoints(outline, cv2.Rodrigues(T_cam_board[:3, :3])[0], T_cam_board[:3, 3], cam.K, cam.dist)
        (x0, y0), (x1, y1) = ob.reshape(-1, 2).min(0) - 3, ob.reshape(-1, 2).max(0) + 3
        sel = np.flatnonzero((pix[:, 0] >= x0) & (pix[:, 0] <= x1) & (pix[:, 1] >= y0) & (pix[:, 1] <= y1))
        T_board_cam = np.linalg.inv(T_cam_board)
        d = rays[sel] @ np.ascontiguousarray(T_board_cam[:3, :3].T)
        o = T_board_cam[:3, 3]
        s = -o[2] / d[:, 2]
        p = o + s[:, None] * d
        sq = np.floor(p[:, :2] / board.square_mm).astype(np.int64) + 1
        on_squares = (sq[:, 0] >= 0) & (sq[:, 0] <= board.cols) & (sq[:, 1] >= 0) & (sq[:, 1] <= board.rows)
        on_board = (p[:, 0] > lo) & (p[:, 0] < hi[0]) & (p[:, 1] > lo) & (p[:, 1] < hi[1])
        black_sq = on_squares & ((sq[:, 0] + sq[:, 1]) % 2 == 0)
        albedo = np.full(len(pix), 0.05)
        albedo[sel] = np.where(on_board, np.where(black_sq, 0.2, 0.9), 0.05)
        T_proj_board = self.truth.T_proj_cam @ T_cam_board
        q = p @ np.ascontiguousarray(T_proj_board[:3, :3].T) + T_proj_board[:3, 3]
        ahead = q[:, 2] > 1e-6
        xy = distort_normalised(q[:, :2] / np.where(ahead, q[:, 2], 1.0)[:, None], proj.dist)
        u = np.rint(proj.K[0, 0] * xy[:, 0] + proj.K[0, 1] * xy[:, 1] + proj.K[0, 2]).astype(np.int64)
        v = np.rint(proj.K[1, 1] * xy[:, 1] + proj.K[1, 2]).astype(np.int64)
        lit_sel = on_board & ahead & (s > 0) & (u >= 0) & (u < proj.width) & (v >= 0) & (v < proj.height)
        lit = np.zeros(len(pix), bool)
        lit[sel] = lit_sel
        uv = np.zeros((len(pix), 2), np.int64)
        uv[sel] = np.stack([u, v], axis=1)
        return albedo, uv, lit

    def _shade(self, pattern: np.ndarray, traced: tuple, ss: int, rng: np.random.Generator) -> np.ndarray:
        albedo, uv, lit = traced
        cam = self.truth.camera
        light = np.zeros(len(albedo))
        light[lit] = pattern[uv[lit, 1], uv[lit, 0]] / 255.0
        img = 255.0 * albedo * (0.1 + 0.85 * light)
        img = img.reshape(cam.height, ss, cam.width, ss).mean(axis=(1, 3))
        return np.clip(img + rng.normal(0.0, self.noise_sigma, img.shape), 0, 255).astype(np.float32)

    def capture(self, T_cam_board: np.ndarray, seed: int = 0) -> BoardCapture:
        """The white, black and gray-code camera images for the board at pose ``T_cam_board``."""
        rng = np.random.default_rng(seed)
        white = self._shade(self.patterns[0], self._trace(T_cam_board, self.supersample), self.supersample, rng)
        traced = self._trace(T_cam_board, 1)
        black = self._shade(self.patterns[1], traced, 1, rng)
        stack = [self._shade(p, traced, 1, rng) for p in self.patterns[2:]]
        return BoardCapture(white=white, black=black, stack=stack)


def write_depth_png(path: Path, depth_mm: np.ndarray) -> None:
    """Write a depth image as 16-bit PNG in whole millimetres (0 where invalid or non-finite)."""
    d = np.where(np.isfinite(depth_mm), depth_mm, 0.0)
    cv2.imwrite(str(path), np.clip(np.rint(d), 0, 65535).astype(np.uint16))


def landing_points(
    pixels: np.ndarray,
    vertices: np.ndarray,
    faces: np.ndarray,
    T_proj_obj: np.ndarray,
    projector: DeviceIntrinsics,
) -> np.ndarray:
    """Where light from projector ``pixels`` (n, 2) lands on the mesh: (n, 3) object-frame points, NaN on a miss.

    Rays leave the projector centre through the undistorted pixels; the first hit counts. Used to
    measure how far a projected landmark lands from where it belongs.
    """
    xy = cv2.undistortPoints(pixels.reshape(-1, 1, 2).astype(np.float64), projector.K, projector.dist).reshape(-1, 2)
    T_obj_proj = invert_pose(T_proj_obj)
    dirs = np.column_stack([xy, np.ones(len(xy))]) @ np.ascontiguousarray(T_obj_proj[:3, :3].T)
    origins = np.tile(T_obj_proj[:3, 3], (len(xy), 1))
    tm = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    hits, ray_idx, _ = tm.ray.intersects_location(origins, dirs, multiple_hits=True)
    out = np.full((len(xy), 3), np.nan)
    dist = np.linalg.norm(hits - origins[ray_idx], axis=1) if len(hits) else np.zeros(0)
    order = np.argsort(-dist)  # nearest hit written last
    out[ray_idx[order]] = hits[order]
    return out
