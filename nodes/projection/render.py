"""CPU rendering of the projector image that guides trace attachment (paper section 7.3), polyline route.

The projector image is rendered per layer (Tx first): curve points are culled when their surface
faces away from the projector (or is nearly edge-on), lifted ``offset_mm`` along the interpolated
surface normal and depth-tested against a z-buffer of the mesh rendered from the projector; the
visible surface points are projected with the projector's distortion and drawn as anti-aliased
polylines (the light lands on the surface point itself; the lift only keeps the depth test from
self-occluding). Every curve vertex is projected exactly, so straight 3D segments map to straight
image segments (perspective-correct by construction, no affine interpolation in screen space).
Conventions: :mod:`.camera`. The textured route is :func:`.raster.render_textured`.
"""
from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from ..data.scene import ProjectionScene
from .camera import DeviceIntrinsics, project_points, transform_points
from .raster import rasterize_depth


@dataclasses.dataclass(frozen=True)
class RenderStyle:
    """How the projector image looks: BGR colours, widths in projector pixels, marker sizes in mm."""

    offset_mm: float = 1.0
    line_px: int = 3
    layer_bgr: tuple[tuple[int, int, int], ...] = ((255, 255, 255), (255, 255, 0))
    crossing_bgr: tuple[int, int, int] = (0, 255, 255)
    pad_bgr: tuple[int, int, int] = (0, 160, 255)
    crossing_radius_mm: float = 1.0
    depth_tolerance_mm: float = 2.0
    max_incidence_deg: float = 80.0
    landmark_max_incidence_deg: float = 60.0  # crossings/pads: steeper spots smear and shift with pose error
    landmark_clearance_px: int = 4  # crossings/pads need the same surface (no depth jump) this far around them
    landmark_depth_jump_mm: float = 10.0


def visible_points(
    points_obj: np.ndarray,
    normals_obj: np.ndarray,
    T_dev_obj: np.ndarray,
    K: np.ndarray,
    zbuffer: np.ndarray,
    style: RenderStyle,
    landmarks: bool = False,
) -> np.ndarray:
    """(n,) bool: the surface point is lit by the device and should be drawn.

    Kept when the surface faces the device at less than ``style.max_incidence_deg`` from its normal
    (back-face culling plus dropping grazing spots, where light smears), lies in front of the device
    and inside the image, and the point lifted ``style.offset_mm`` along its normal passes the depth
    test against the z-buffer (nearest undistorted pixel, ``style.depth_tolerance_mm`` slack).
    ``landmarks=True`` (crossings, pads) uses ``style.landmark_max_incidence_deg`` instead and also
    drops points within ``landmark_clearance_px`` of a silhouette or depth jump, where a small pose
    error would move the light onto another part of the object.
    """
    p = transform_points(T_dev_obj, points_obj)
    n = normals_obj @ np.ascontiguousarray(T_dev_obj[:3, :3].T)
    lifted = p + style.offset_mm * n
    to_device = -p / np.maximum(np.linalg.norm(p, axis=1, keepdims=True), 1e-12)
    max_incidence = style.landmark_max_incidence_deg if landmarks else style.max_incidence_deg
    facing = np.einsum("ij,ij->i", n, to_device) > np.cos(np.deg2rad(max_incidence))
    z = lifted[:, 2]
    in_front = z > 1e-6
    safe_z = np.where(in_front, z, 1.0)
    col = np.rint((K[0, 0] * lifted[:, 0] + K[0, 1] * lifted[:, 1]) / safe_z + K[0, 2]).astype(np.int64)
    row = np.rint(K[1, 1] * lifted[:, 1] / safe_z + K[1, 2]).astype(np.int64)
    h, w = zbuffer.shape
    ok = facing & in_front & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    z_ok = np.zeros(len(p), bool)
    z_ok[ok] = z[ok] <= zbuffer[row[ok], col[ok]] + style.depth_tolerance_mm
    if landmarks:
        r = style.landmark_clearance_px
        for dr, dc in ((-r, 0), (r, 0), (0, -r), (0, r), (-r, -r), (r, r), (-r, r), (r, -r)):
            rr, cc = np.clip(row + dr, 0, h - 1), np.clip(col + dc, 0, w - 1)
            z_ok[ok] &= np.abs(zbuffer[rr[ok], cc[ok]] - z[ok]) < style.landmark_depth_jump_mm
    return ok & z_ok


def _visible_runs(uv: np.ndarray, visible: np.ndarray, offsets: np.ndarray) -> list[np.ndarray]:
    """Split each polyline into runs of consecutive visible vertices (>= 2 points each)."""
    breaks = np.zeros(len(uv), bool)
    breaks[offsets[1:-1]] = True  # a new curve starts here
    runs: list[np.ndarray] = []
    idx = np.flatnonzero(visible)
    if len(idx) == 0:
        return runs
    cut = np.flatnonzero((np.diff(idx) != 1) | breaks[idx[1:]]) + 1
    for run in np.split(idx, cut):
        if len(run) >= 2:
            runs.append(uv[run])
    return runs


def render_layers(
    scene: ProjectionScene,
    T_proj_obj: np.ndarray,
    projector: DeviceIntrinsics,
    style: RenderStyle = RenderStyle(),
) -> dict[str, np.ndarray]:
    """One BGR uint8 projector image (height, width, 3) per layer, keyed by layer name in attachment order.

    Each image shows that layer's visible curves plus the crossing landmarks and pads.
    """
    zbuffer = rasterize_depth(
        transform_points(T_proj_obj, scene.vertices), scene.faces, projector.K, projector.width, projector.height
    )
    shift = 4  # sub-pixel precision bits for cv2 drawing
    scale = float(1 << shift)
    cross_vis = visible_points(
        scene.crossing_points, scene.crossing_normals, T_proj_obj, projector.K, zbuffer, style, landmarks=True
    )
    cross_dev = transform_points(T_proj_obj, scene.crossing_points[cross_vis])
    cross_uv = project_points(cross_dev, projector)
    f_px = float(projector.K[0, 0])
    images: dict[str, np.ndarray] = {}
    for i, name in enumerate(scene.layer_names):
        img = np.zeros((projector.height, projector.width, 3), np.uint8)
        pts, nrm, offs = scene.layer_points[i], scene.layer_normals[i], scene.layer_offsets[i]
        vis = visible_points(pts, nrm, T_proj_obj, projector.K, zbuffer, style)
        uv = project_points(transform_points(T_proj_obj, pts), projector)
        runs = _visible_runs(uv, vis, offs)
        colour = style.layer_bgr[i % len(style.layer_bgr)]
        if runs:
            cv2.polylines(
                img, [np.rint(r * scale).astype(np.int32) for r in runs], False, colour, style.line_px, cv2.LINE_AA, shift
            )
        for (u, v), z, has_pad in zip(cross_uv, cross_dev[:, 2], scene.pad[cross_vis]):
            centre = (int(round(u * scale)), int(round(v * scale)))
            if has_pad:
                r = int(round(scene.pad_radius_mm * f_px / z * scale))
                cv2.circle(img, centre, r, style.pad_bgr, -1, cv2.LINE_AA, shift)
            r = int(round(style.crossing_radius_mm * f_px / z * scale))
            cv2.circle(img, centre, r, style.crossing_bgr, max(1, style.line_px // 2), cv2.LINE_AA, shift)
        images[name] = img
    return images
