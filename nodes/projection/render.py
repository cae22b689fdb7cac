"""CPU rendering of the projector image that guides trace attachment (paper section 7.3).

Conventions (stated once here, used by the projection modules):

* Cameras and projectors are pinhole devices in OpenCV convention: x right, y down, z forward
  (viewing direction); pixel centres at integer coordinates; ``K`` (3, 3) in pixels; ``dist`` the
  OpenCV ``(k1, k2, p1, p2, k3)`` coefficients.
* A pose ``T_b_a`` is a (4, 4) float64 rigid transform taking points from frame ``a`` to frame ``b``
  in millimetres: ``X_b = T_b_a[:3, :3] @ X_a + T_b_a[:3, 3]``. The object frame is the mesh frame.
* Depth images hold the z coordinate (mm) along the optical axis, ``inf`` where nothing was hit.

The projector image is rendered per layer (Tx first): curve points are culled when their surface
faces away from the projector (or is nearly edge-on), lifted ``offset_mm`` along the interpolated
surface normal and depth-tested against a z-buffer of the mesh rendered from the projector; the
visible surface points are projected with the projector's distortion and drawn as anti-aliased
polylines (the light lands on the surface point itself; the lift only keeps the depth test from
self-occluding). Every curve vertex is projected exactly, so straight 3D segments map to straight
image segments (perspective-correct by construction, no affine interpolation in screen space).
"""
from __future__ import annotations

import dataclasses
import functools
import io
from pathlib import Path

import cv2
import numpy as np

from ...graph.errors import UserError
from ..data.types import PAD_RADIUS_MM, CurveSet, Layout, Mesh
from .calibration import DeviceIntrinsics

SCENE_FORMAT = "retrotouch.projection_scene/1"


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid (4, 4) transform."""
    R, t = T[:3, :3], T[:3, 3]
    inv = np.eye(4)
    inv[:3, :3] = R.T
    inv[:3, 3] = -R.T @ t
    return inv


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply the rigid (4, 4) transform ``T`` to (n, 3) points."""
    # A contiguous rotation keeps the product on the BLAS path (a strided 3x3 view is ~100x slower).
    return points @ np.ascontiguousarray(T[:3, :3].T) + T[:3, 3]


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (n, 3) of a CCW-outward mesh."""
    tri = vertices[faces]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals = np.zeros_like(vertices)
    for corner in range(3):
        np.add.at(normals, faces[:, corner], face_n)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)


def rasterize_depth(
    vertices_cam: np.ndarray,
    faces: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    z_near_mm: float = 10.0,
    z_far_mm: float = 1.0e5,
) -> np.ndarray:
    """Z-buffer (height, width) float32 in mm of a mesh given in camera coordinates; ``inf`` = empty.

    Uses OpenCV 5 ``triangleRasterizeDepth`` (a symmetric GL-style frustum given by ``fovY``); an
    arbitrary ``K`` is obtained by a linear shear of the camera coordinates, which keeps the stored
    depth equal to the z coordinate. Back faces are culled (they are hidden on a closed mesh anyway).
    """
    fov_y, shear = _gl_frustum(K, width, height)
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


def _gl_frustum(K: np.ndarray, width: int, height: int) -> tuple[float, np.ndarray]:
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
    # Culling mode checked against an unculled render: RASTERIZE_CULLING_CW drops the back faces here.
    settings.setCullingMode(cv2.RASTERIZE_CULLING_CW)
    settings.setShadingType(shading)
    return settings


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
    fov_y, shear = _gl_frustum(device.K, w, h)
    verts = transform_points(T_dev_obj, scene.vertices[scene.atlas_vertex_map])
    colours = np.column_stack([scene.atlas_uv, np.ones(len(scene.atlas_uv))]).astype(np.float32)
    colour_buf = np.zeros((h, w, 3), np.float32)
    depth_buf = np.full((h, w), 1.0e5, np.float32)
    colour_buf, depth_buf = cv2.triangleRasterize(
        np.ascontiguousarray(verts, np.float32),
        np.ascontiguousarray(scene.atlas_faces, np.int32),
        colours,
        colour_buf,
        depth_buf,
        shear,
        fov_y,
        10.0,
        1.0e5,
        _raster_settings(cv2.RASTERIZE_SHADING_SHADED),
    )
    hit = colour_buf[..., 2] > 0.5
    map_x = np.where(hit, colour_buf[..., 0] * size_x - 0.5, -1.0).astype(np.float32)
    map_y = np.where(hit, (1.0 - colour_buf[..., 1]) * size_y - 0.5, -1.0).astype(np.float32)
    image = cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return apply_distortion(image, device, cv2.INTER_LINEAR)


@dataclasses.dataclass(frozen=True)
class ProjectionScene:
    """Everything the projector renderer needs, in the object (mesh) frame, mm.

    ``layer_names`` in attachment order (Tx first). Layer ``i`` owns polylines
    ``layer_offsets[i][c]:layer_offsets[i][c + 1]`` of ``layer_points[i]`` (surface points) with unit
    surface normals ``layer_normals[i]``. ``crossing_points``/``crossing_normals`` are the Tx x Rx
    crossings, ``pad[k]`` marks those that carry an electrode pad.

    Optional texture route: ``atlas_vertex_map``/``atlas_faces``/``atlas_uv`` describe a UV atlas
    (split vertices into ``vertices``, OBJ UV convention) and ``layer_textures[i]`` is layer ``i``
    baked into it as a projector image (BGR uint8, black = no light); see :func:`render_textured`.
    """

    vertices: np.ndarray  # (n, 3) float64
    faces: np.ndarray  # (m, 3) int64
    layer_names: tuple[str, ...]
    layer_points: tuple[np.ndarray, ...]
    layer_normals: tuple[np.ndarray, ...]
    layer_offsets: tuple[np.ndarray, ...]
    crossing_points: np.ndarray  # (K, 3)
    crossing_normals: np.ndarray  # (K, 3)
    pad: np.ndarray  # (K,) bool
    pad_radius_mm: float = PAD_RADIUS_MM  # the layout's pad radius
    atlas_vertex_map: np.ndarray | None = None  # (n',) int64
    atlas_faces: np.ndarray | None = None  # (m, 3) int64
    atlas_uv: np.ndarray | None = None  # (n', 2) float64
    layer_textures: tuple[np.ndarray, ...] = ()


def interpolated_normals(mesh: Mesh, faces: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Unit normals at surface points given by face ids and barycentrics (vertex-normal interpolation)."""
    vn = vertex_normals(mesh.vertices, mesh.faces)
    n = np.einsum("kj,kjd->kd", bary, vn[mesh.faces[faces]])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def build_scene(mesh: Mesh, layout: Layout) -> ProjectionScene:
    """Collect the layout's curves, crossings and pads with their surface normals (Tx layer first)."""
    sets: tuple[CurveSet, ...] = (layout.tx, layout.rx)
    return ProjectionScene(
        vertices=np.asarray(mesh.vertices, np.float64),
        faces=np.asarray(mesh.faces, np.int64),
        layer_names=tuple(s.layer for s in sets),
        layer_points=tuple(np.asarray(s.points, np.float64) for s in sets),
        layer_normals=tuple(interpolated_normals(mesh, s.faces, s.bary) for s in sets),
        layer_offsets=tuple(np.asarray(s.offsets, np.int64) for s in sets),
        crossing_points=np.asarray(layout.cells.points, np.float64),
        crossing_normals=interpolated_normals(mesh, layout.cells.faces, layout.cells.bary),
        pad=np.asarray(layout.pad, bool),
        pad_radius_mm=float(layout.pad_radius_mm),
    )


def save_scene(scene: ProjectionScene) -> bytes:
    """Serialise a scene as ``.npz`` bytes (no pickle)."""
    arrays: dict[str, np.ndarray] = {
        "format": np.array(SCENE_FORMAT),
        "vertices": scene.vertices,
        "faces": scene.faces,
        "layer_names": np.array(scene.layer_names),
        "crossing_points": scene.crossing_points,
        "crossing_normals": scene.crossing_normals,
        "pad": scene.pad,
        "pad_radius_mm": np.array(scene.pad_radius_mm),
    }
    if scene.atlas_uv is not None:
        arrays["atlas_vertex_map"] = scene.atlas_vertex_map
        arrays["atlas_faces"] = scene.atlas_faces
        arrays["atlas_uv"] = scene.atlas_uv
        for i, tex in enumerate(scene.layer_textures):
            ok, png = cv2.imencode(".png", tex)
            if not ok:
                raise RuntimeError("PNG encoding of a layer texture failed")
            arrays[f"layer{i}_texture_png"] = png.ravel()
    for i in range(len(scene.layer_names)):
        arrays[f"layer{i}_points"] = scene.layer_points[i]
        arrays[f"layer{i}_normals"] = scene.layer_normals[i]
        arrays[f"layer{i}_offsets"] = scene.layer_offsets[i]
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def load_scene(path: Path) -> ProjectionScene:
    """Read a scene written by :func:`save_scene`; UserError when the file is not one."""
    try:
        data = np.load(path, allow_pickle=False)
        if str(data["format"]) != SCENE_FORMAT:
            raise UserError(f"{path} is {data['format']}, expected {SCENE_FORMAT}: re-run the projection.textures sink")
        names = tuple(str(n) for n in data["layer_names"])
        textured = "atlas_uv" in data
        textures = tuple(
            cv2.imdecode(data[f"layer{i}_texture_png"], cv2.IMREAD_COLOR) for i in range(len(names))
        ) if textured else ()
        return ProjectionScene(
            vertices=data["vertices"],
            faces=data["faces"],
            layer_names=names,
            layer_points=tuple(data[f"layer{i}_points"] for i in range(len(names))),
            layer_normals=tuple(data[f"layer{i}_normals"] for i in range(len(names))),
            layer_offsets=tuple(data[f"layer{i}_offsets"] for i in range(len(names))),
            crossing_points=data["crossing_points"],
            crossing_normals=data["crossing_normals"],
            pad=data["pad"],
            pad_radius_mm=float(data["pad_radius_mm"]) if "pad_radius_mm" in data else PAD_RADIUS_MM,
            atlas_vertex_map=data["atlas_vertex_map"] if textured else None,
            atlas_faces=data["atlas_faces"] if textured else None,
            atlas_uv=data["atlas_uv"] if textured else None,
            layer_textures=textures,
        )
    except (OSError, KeyError, ValueError) as exc:
        raise UserError(f"cannot read projection scene {path}: {exc}; point --layout at a run folder with projection/*_scene.npz") from exc


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


def project_points(points_dev: np.ndarray, device: DeviceIntrinsics) -> np.ndarray:
    """Pixel coordinates (n, 2) of points given in the device frame, with the device's distortion."""
    if len(points_dev) == 0:
        return np.zeros((0, 2))
    uv, _ = cv2.projectPoints(points_dev.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), device.K, device.dist)
    return uv.reshape(-1, 2)


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
    import trimesh

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
