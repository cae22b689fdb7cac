"""Camera maths shared by calibration, projector rendering and tracking.

Conventions (stated once here, used by the projection modules):

* Cameras and projectors are pinhole devices in OpenCV convention: x right, y down, z forward
  (viewing direction); pixel centres at integer coordinates; ``K`` (3, 3) in pixels; ``dist`` the
  OpenCV ``(k1, k2, p1, p2, k3)`` coefficients.
* A pose ``T_b_a`` is a (4, 4) float64 rigid transform taking points from frame ``a`` to frame ``b``
  in millimetres: ``X_b = T_b_a[:3, :3] @ X_a + T_b_a[:3, 3]``. The object frame is the mesh frame.
* Depth images hold the z coordinate (mm) along the optical axis.
* Normalised image coordinates are ``(x / z, y / z)`` of a point in the device frame.
"""
from __future__ import annotations

import dataclasses
import functools

import cv2
import numpy as np


@dataclasses.dataclass(frozen=True)
class DeviceIntrinsics:
    """Pinhole intrinsics of a camera or projector: ``K`` (3, 3) px, ``dist`` (5,) OpenCV coefficients."""

    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid (4, 4) transform."""
    R, t = T[:3, :3], T[:3, 3]
    inv = np.eye(4)
    inv[:3, :3] = R.T
    inv[:3, 3] = -R.T @ t
    return inv


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply the rigid (4, 4) transform ``T`` to (n, 3) points."""
    # A contiguous rotation keeps the product on the BLAS path (a strided 3x3 view is much slower).
    return points @ np.ascontiguousarray(T[:3, :3].T) + T[:3, 3]


def project_points(points_dev: np.ndarray, device: DeviceIntrinsics) -> np.ndarray:
    """Pixel coordinates (n, 2) of points given in the device frame, with the device's distortion."""
    if len(points_dev) == 0:
        return np.zeros((0, 2))
    uv, _ = cv2.projectPoints(points_dev.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), device.K, device.dist)
    return uv.reshape(-1, 2)


def normalised_coordinates(pixels: np.ndarray, device: DeviceIntrinsics) -> np.ndarray:
    """Undistorted normalised coordinates (n, 2) of (distorted) device pixels (n, 2)."""
    pixels = np.asarray(pixels, np.float64)
    if np.any(device.dist):
        return cv2.undistortPoints(pixels.reshape(-1, 1, 2), device.K, device.dist).reshape(-1, 2)
    K = device.K
    y = (pixels[:, 1] - K[1, 2]) / K[1, 1]
    return np.stack([(pixels[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0], y], axis=1)


def distort_normalised(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """OpenCV (k1, k2, p1, p2, k3) distortion of normalised image coordinates (n, 2)."""
    k1, k2, p1, p2, k3 = np.asarray(dist, np.float64).ravel()[:5]
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=1)


@functools.lru_cache(maxsize=4)
def _distortion_map(K_bytes: bytes, dist_bytes: bytes, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """For every distorted pixel, the pinhole pixel it corresponds to (float32 maps for cv2.remap)."""
    K = np.frombuffer(K_bytes).reshape(3, 3)
    dist = np.frombuffer(dist_bytes)
    gx, gy = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pix = np.stack([gx.ravel(), gy.ravel()], axis=1).reshape(-1, 1, 2)
    und = cv2.undistortPoints(pix, K, dist, None, None, K).reshape(height, width, 2)
    return und[..., 0].astype(np.float32), und[..., 1].astype(np.float32)


def apply_distortion(image: np.ndarray, device: DeviceIntrinsics, interpolation: int) -> np.ndarray:
    """Warp a pinhole rendering (through ``device.K``) into the device's distorted image."""
    if not np.any(device.dist):
        return image
    K = np.ascontiguousarray(device.K, np.float64)
    dist = np.ascontiguousarray(device.dist, np.float64)
    map_x, map_y = _distortion_map(K.tobytes(), dist.tobytes(), device.width, device.height)
    return cv2.remap(image, map_x, map_y, interpolation, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
