"""Triangle rasterization through a calibrated device: z-buffers and the textured projector route.

Both use OpenCV 5's rasterizer, which takes a symmetric GL-style frustum (``fovY``); an arbitrary
pinhole ``K`` is reproduced by a linear shear of the device coordinates (see :func:`gl_frustum`).
Conventions: :mod:`.camera`. Depth images here hold ``inf`` where nothing was hit.
"""
from __future__ import annotations

import cv2
import numpy as np

from ...graph.errors import UserError
from ..data.scene import ProjectionScene
from .camera import DeviceIntrinsics, apply_distortion, transform_points

Z_NEAR_MM = 10.0
Z_FAR_MM = 1.0e5


def gl_frustum(K: np.ndarray, width: int, height: int) -> tuple[float, np.ndarray]:
    """(fovY, world2cam) making OpenCV's symmetric GL-style rasterizer reproduce pinhole ``K``.

    ``world2cam`` is a linear shear of camera coordinates (z -> -z, y flipped); the rasterizer's
    depth stays the camera z. OpenCV puts pixel centres at i + 0.5, ours at i: half-pixel shift.
    """
    fov_y = np.deg2rad(60.0)
    f_gl = (height / 2.0) / np.tan(fov_y / 2.0)
    shear = np.eye(4)
    shear[:3, :3] = np.array(
        [
            [K[0, 0] / f_gl, K[0, 1] / f_gl, (K[0, 2] + 0.5 - width / 2.0) / f_gl],
            [0.0, -K[1, 1] / f_gl, -(K[1, 2] + 0.5 - height / 2.0) / f_gl],
            [0.0, 0.0, -1.0],
        ]
    )
    return float(fov_y), shear


def _raster_settings(shading: int) -> cv2.TriangleRasterizeSettings:
    settings = cv2.TriangleRasterizeSettings()
    # RASTERIZE_CULLING_CW drops the back faces of our CCW-outward meshes (checked against an unculled render).
    settings.setCullingMode(cv2.RASTERIZE_CULLING_CW)
    settings.setShadingType(shading)
    return settings


def rasterize_depth(
    vertices_cam: np.ndarray,
    faces: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    z_near_mm: float = Z_NEAR_MM,
    z_far_mm: float = Z_FAR_MM,
) -> np.ndarray:
    """Z-buffer (height, width) float32 in mm of a mesh given in camera coordinates; ``inf`` = empty.

    The stored depth is the z coordinate; back faces are culled (hidden on a closed mesh anyway).
    """
    fov_y, shear = gl_frustum(K, width, height)
    depth = np.full((height, width), z_far_mm, np.float32)
    depth = cv2.triangleRasterizeDepth(
        np.ascontiguousarray(vertices_cam, np.float32),
        np.ascontiguousarray(faces, np.int32),
        depth,
        shear,
        fov_y,
        z_near_mm,
        z_far_mm,
        _raster_settings(cv2.RASTERIZE_SHADING_FLAT),
    )
    depth[depth >= z_far_mm] = np.inf
    return depth


def render_textured(scene: ProjectionScene, layer: int, T_dev_obj: np.ndarray, device: DeviceIntrinsics) -> np.ndarray:
    """BGR uint8 image of the atlas mesh textured with ``scene.layer_textures[layer]``, seen by ``device``.

    The rasterizer interpolates the atlas UVs perspective-correctly (checked against exact ray-plane
    UVs in the tests), culls back faces and depth-tests; the texture is then sampled bilinearly
    with ``cv2.remap`` and the result warped by the device's distortion.
    """
    if scene.atlas_uv is None or not scene.layer_textures:
        raise UserError("this projection scene has no baked textures: re-run the projection.textures sink")
    texture = scene.layer_textures[layer]
    size_y, size_x = texture.shape[:2]
    w, h = device.width, device.height
    fov_y, shear = gl_frustum(device.K, w, h)
    verts = transform_points(T_dev_obj, scene.vertices[scene.atlas_vertex_map])
    colours = np.column_stack([scene.atlas_uv, np.ones(len(scene.atlas_uv))]).astype(np.float32)
    colour_buf = np.zeros((h, w, 3), np.float32)
    depth_buf = np.full((h, w), Z_FAR_MM, np.float32)
    colour_buf, depth_buf = cv2.triangleRasterize(
        np.ascontiguousarray(verts, np.float32),
        np.ascontiguousarray(scene.atlas_faces, np.int32),
        colours,
        colour_buf,
        depth_buf,
        shear,
        fov_y,
        Z_NEAR_MM,
        Z_FAR_MM,
        _raster_settings(cv2.RASTERIZE_SHADING_SHADED),
    )
    hit = colour_buf[..., 2] > 0.5
    map_x = np.where(hit, colour_buf[..., 0] * size_x - 0.5, -1.0).astype(np.float32)
    map_y = np.where(hit, (1.0 - colour_buf[..., 1]) * size_y - 0.5, -1.0).astype(np.float32)
    image = cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return apply_distortion(image, device, cv2.INTER_LINEAR)
