"""Synthetic scenes with known truth for the projection tests and benchmark.

* :func:`bunny_mm` -- pymeshlab's bunny, 170 mm bounding-box diagonal, centred, +z up (the
  plane-section layouts of ``fab_layouts`` take meridians about the z axis).
* :func:`board_poses` -- checkerboard poses in front of a rig's camera where the projector lights them.
* :func:`calibrate_synthetic` -- a calibration estimated from simulated gray-code captures.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from curves_fixture import load_scaled, sample_mesh_path
from fab_layouts import section_layout
from retrotouch.nodes.data.types import Layout, Mesh
from retrotouch.nodes.projection.calibration import BoardCaptureSimulator, BoardSpec, ProCamCalibration, calibrate_procam

BOARD = BoardSpec(cols=9, rows=7, square_mm=15.0)


def bunny_mm(target_vertices: int = 5000) -> Mesh:
    """The bunny in mm: 170 mm diagonal, bounding-box centre at the origin, y-up file turned to +z up."""
    m = load_scaled(sample_mesh_path("bunny.obj"), 170.0, target_vertices=target_vertices)
    v = m.vertices - (m.vertices.max(axis=0) + m.vertices.min(axis=0)) / 2
    up = Rotation.from_euler("x", 90, degrees=True).as_matrix()  # (x, y, z) -> (x, -z, y): y-up becomes z-up
    return Mesh(v @ up.T, m.faces, "builtin:bunny")


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
