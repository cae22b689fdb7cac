"""Depth frame sources for tracking: a folder of depth PNGs, a live camera, or synthetic renders.

Depth frames are float32 (height, width) millimetres along the optical axis, 0 where invalid; they
must be registered to the calibrated camera (same intrinsics). Conventions: :mod:`.camera`; poses
are ``T_cam_obj`` (object -> depth camera, mm).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Iterator, Protocol

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ...graph.errors import UserError
from ..data.types import Mesh
from .camera import DeviceIntrinsics, apply_distortion, transform_points
from .raster import rasterize_depth


@dataclasses.dataclass(frozen=True)
class DepthFrame:
    """One depth image: float32 (height, width) mm, 0 = invalid; ``timestamp_s`` seconds."""

    depth_mm: np.ndarray
    timestamp_s: float
    index: int


class FrameSource(Protocol):
    """Anything that yields depth frames registered to ``camera`` (a live RGB-D camera plugs in here).

    A live source wraps its SDK: e.g. for an Azure Kinect (pyk4a), ``camera`` holds the colour
    camera's calibrated intrinsics and ``frames()`` yields ``capture.transformed_depth`` (depth
    mapped into the colour camera) as float32 with the device timestamp in seconds.
    """

    camera: DeviceIntrinsics

    def frames(self) -> Iterator[DepthFrame]:
        """Frames in time order; a live source blocks until the next one arrives."""
        ...


@dataclasses.dataclass
class DepthFolderSource:
    """Depth PNG sequence (16-bit, millimetres, 0 = invalid) from a folder, in file-name order."""

    folder: Path
    camera: DeviceIntrinsics
    fps: float = 30.0

    def files(self) -> list[Path]:
        files = sorted(Path(self.folder).glob("*.png"))
        if not files:
            raise UserError(f"no depth PNGs in {self.folder}: pass --frames a folder of 16-bit depth images (mm)")
        return files

    def frames(self) -> Iterator[DepthFrame]:
        for i, path in enumerate(self.files()):
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if img is None or img.dtype != np.uint16 or img.ndim != 2:
                raise UserError(f"{path} is not a single-channel 16-bit depth PNG (mm): re-export the recording")
            if img.shape != (self.camera.height, self.camera.width):
                raise UserError(
                    f"{path} is {img.shape[1]}x{img.shape[0]} but the calibrated camera is "
                    f"{self.camera.width}x{self.camera.height}: register depth to the calibrated camera"
                )
            yield DepthFrame(img.astype(np.float32), i / self.fps, i)


def render_depth(mesh: Mesh, T_cam_obj: np.ndarray, camera: DeviceIntrinsics) -> np.ndarray:
    """Ideal depth image (float32 mm, 0 = background) of the mesh at pose ``T_cam_obj``, with the camera's distortion.

    Rendered through the pinhole ``K`` and warped (nearest pixel) by the distortion model.
    """
    depth = rasterize_depth(transform_points(T_cam_obj, mesh.vertices), mesh.faces, camera.K, camera.width, camera.height)
    depth[~np.isfinite(depth)] = 0.0
    return apply_distortion(depth, camera, cv2.INTER_NEAREST)


def demo_trajectory(count: int, distance_mm: float = 550.0, fps: float = 30.0, seed: int = 0) -> np.ndarray:
    """(count, 4, 4) smooth object poses ``T_cam_obj``: an operator slowly turning the object in front of the camera.

    The object's +z axis points up (camera -y); it yaws up to +-35 degrees at <= 20 deg/s, tilts a
    few degrees and drifts a few centimetres.
    """
    t = np.arange(count) / fps
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0, 2 * np.pi, 4)
    yaw = np.deg2rad(35.0) * np.sin(2 * np.pi * 0.09 * t + phase[0])
    tilt = np.deg2rad(6.0) * np.sin(2 * np.pi * 0.13 * t + phase[1])
    upright = Rotation.from_euler("x", -90, degrees=True)  # object +z -> camera -y
    poses = np.tile(np.eye(4), (count, 1, 1))
    for i in range(count):
        rot = Rotation.from_euler("x", tilt[i]) * upright * Rotation.from_euler("z", yaw[i])
        poses[i, :3, :3] = rot.as_matrix()
    poses[:, 0, 3] = 30.0 * np.sin(2 * np.pi * 0.05 * t + phase[2])
    poses[:, 1, 3] = 10.0 * np.sin(2 * np.pi * 0.07 * t + phase[3])
    poses[:, 2, 3] = distance_mm
    return poses


@dataclasses.dataclass
class SyntheticDepthSource:
    """Renders the mesh at known poses with Gaussian depth noise (``noise_mm``) and 1 mm quantisation."""

    mesh: Mesh
    camera: DeviceIntrinsics
    poses: np.ndarray  # (N, 4, 4) T_cam_obj
    noise_mm: float = 0.5
    fps: float = 30.0
    seed: int = 0

    def frames(self) -> Iterator[DepthFrame]:
        rng = np.random.default_rng(self.seed)
        for i, T in enumerate(self.poses):
            depth = render_depth(self.mesh, T, self.camera)
            valid = depth > 0
            depth[valid] = np.rint(depth[valid] + rng.normal(0.0, self.noise_mm, int(valid.sum())))
            yield DepthFrame(depth.astype(np.float32), i / self.fps, i)
