"""The preview PNG: four headless views of the object as it rests, with both curve layers, depth-tested.

The mesh is flat-shaded with OpenCV's triangle rasterizer (base region dark blue-grey, exclusion
regions mid grey, sensing surface light grey); Tx curves in ``TX_RGB`` and Rx curves in ``RX_RGB``
are drawn only where they pass a depth test against the mesh's z-buffer, and so are the resting
pose's guides (:func:`pose_guides`): the table plane under the object in ``TABLE_RGB`` and an up
arrow beside it in ``UP_RGB``; the layout's uncovered spots are ringed in ``UNCOVERED_RGB`` at their
points farthest from every crossing. A caption under the views names the pose kind and its reason, and
the share of the touchable sensing area the spots hold.

Camera convention: views orbit the bounding-box centre; elevation is measured from the plane
normal to ``regions.up`` (positive = looking down on the object), azimuth about ``up``; lengths mm.
"""
from __future__ import annotations

import cv2
import numpy as np

from ..data.types import CurveSet, Mesh, SurfaceRegions
from ..geometry.triangles import normals

TX_RGB = (230, 70, 20)
RX_RGB = (20, 110, 235)
CROSSING_RGB = (250, 210, 0)
UNCOVERED_RGB = (220, 30, 30)
BACKGROUND_RGB = (255, 255, 255)
SENSING_RGB = (0.86, 0.85, 0.82)
EXCLUSION_RGB = (0.66, 0.66, 0.66)
BASE_RGB = (0.42, 0.47, 0.60)
TABLE_RGB = (150, 105, 60)
UP_RGB = (20, 150, 60)
TABLE_GRID_LINES = 5
"""Lines across the table square in each direction (edges included)."""
CAPTION_LINE_PX = 18
CAPTION_SCALE = 0.45
"""Caption text: line height (px) and OpenCV font scale."""
VIEWS = (("front left", 35.0, 20.0), ("back right", 215.0, 20.0), ("top", 125.0, 70.0), ("below", 300.0, -55.0))
"""(label, azimuth deg, elevation deg) of the PNG's four views."""
FOV_Y = np.radians(30.0)


def segments(curves: CurveSet) -> tuple[np.ndarray, np.ndarray]:
    """Row indices ``(start, end)`` of every segment of every curve."""
    rows = len(curves.points)
    starts = np.ones(max(rows - 1, 0), dtype=bool)
    last_rows = np.asarray(curves.offsets[1:], dtype=np.int64) - 1
    starts[last_rows[(last_rows >= 0) & (last_rows < rows - 1)]] = False
    start = np.flatnonzero(starts)
    return start, start + 1


def camera(centre: np.ndarray, radius: float, up: np.ndarray, azimuth: float, elevation: float) -> np.ndarray:
    """4x4 world-to-camera matrix (OpenGL convention: the camera looks down its -z axis)."""
    helper = np.eye(3)[int(np.argmin(np.abs(up)))]
    side = np.cross(up, helper)
    side /= np.linalg.norm(side)
    front = np.cross(up, side)
    horizontal = np.cos(azimuth) * side + np.sin(azimuth) * front
    towards_eye = np.cos(elevation) * horizontal + np.sin(elevation) * up
    eye = centre + towards_eye * radius / np.sin(FOV_Y / 2) * 1.05
    z_axis = towards_eye
    x_axis = np.cross(up, z_axis)
    if np.linalg.norm(x_axis) < 1e-9:
        x_axis = side
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(z_axis, x_axis)
    rotation = np.stack([x_axis, y_axis, z_axis])
    world_to_camera = np.eye(4)
    world_to_camera[:3, :3] = rotation
    world_to_camera[:3, 3] = -rotation @ eye
    return world_to_camera


def project(points: np.ndarray, world_to_camera: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(column, row, depth)`` of world points: pixel coordinates and distance along the view axis."""
    cam = points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    depth = -cam[:, 2]
    focal = (size / 2) / np.tan(FOV_Y / 2)
    column = size / 2 + focal * cam[:, 0] / depth
    row = size / 2 - focal * cam[:, 1] / depth
    return column, row, depth


def greyed_faces(regions: SurfaceRegions) -> np.ndarray:
    """(m,) bool: the faces drawn in ``EXCLUSION_RGB``, the exclusions and the sensing faces no finger can touch."""
    untouchable = np.asarray(regions.sensing_faces) & ~np.asarray(regions.touch_faces)
    return np.asarray(regions.exclusion_base) | np.asarray(regions.exclusion_far) | untouchable


def face_colours(face_count: int, regions: SurfaceRegions | None) -> np.ndarray:
    """Base RGB in [0, 1] per face from the region masks (:func:`greyed_faces`, the base)."""
    colours = np.tile(np.asarray(SENSING_RGB, dtype=np.float32), (face_count, 1))
    if regions is not None:
        colours[greyed_faces(regions)] = EXCLUSION_RGB
        colours[np.asarray(regions.base_faces)] = BASE_RGB
    return colours


def render_view(
    mesh: Mesh,
    colours: np.ndarray,
    layers: list[tuple[CurveSet, tuple[int, int, int]]],
    crossings: np.ndarray | None,
    world_to_camera: np.ndarray,
    size: int,
    line_px: int,
    guides: list[tuple[np.ndarray, np.ndarray, tuple[int, int, int]]] = (),
    spots: np.ndarray | None = None,
) -> np.ndarray:
    """One RGB uint8 view: shaded mesh, then the ``guides`` segments (:func:`pose_guides`) and the
    curves where they pass the depth test, then crossings (dots) and uncovered ``spots`` (rings)."""
    vertices, faces = mesh.vertices, mesh.faces
    corners = vertices[faces]
    face_normals, _ = normals(corners)
    eye = -world_to_camera[:3, :3].T @ world_to_camera[:3, 3]
    to_eye = eye - corners.mean(axis=1)
    to_eye /= np.linalg.norm(to_eye, axis=1)[:, None]
    shade = 0.35 + 0.65 * np.clip(np.einsum("ij,ij->i", face_normals, to_eye), 0.0, 1.0)
    vertex_colours = np.repeat(colours * shade[:, None], 3, axis=0).astype(np.float32)
    colour = np.zeros((size, size, 3), dtype=np.float32)
    colour[:] = np.asarray(BACKGROUND_RGB, dtype=np.float32) / 255.0
    radius = float(np.linalg.norm(vertices.max(0) - vertices.min(0))) / 2
    distance = float(np.linalg.norm(eye - 0.5 * (vertices.max(0) + vertices.min(0))))
    z_near, z_far = max(distance - 2 * radius, 1e-3), distance + 2 * radius
    depth = np.full((size, size), z_far, dtype=np.float32)
    settings = cv2.TriangleRasterizeSettings()
    settings.setShadingType(cv2.RASTERIZE_SHADING_FLAT)
    settings.setCullingMode(cv2.RASTERIZE_CULLING_NONE)
    colour, depth = cv2.triangleRasterize(
        corners.reshape(-1, 3).astype(np.float32),
        np.arange(3 * len(faces), dtype=np.int32).reshape(-1, 3),
        vertex_colours,
        colour,
        depth,
        world_to_camera,
        FOV_Y,
        z_near,
        z_far,
        settings,
    )
    image = np.clip(colour * 255.0 + 0.5, 0, 255).astype(np.uint8)
    pixel_mm = 2 * distance * np.tan(FOV_Y / 2) / size
    kernel = np.ones((line_px, line_px), dtype=np.uint8)
    for starts, ends, rgb in guides:
        shown = visible_segments_mask(starts, ends, world_to_camera, depth, size, 4 * pixel_mm)
        image[cv2.dilate(shown, kernel) > 0] = rgb
    for curves, rgb in layers:
        visible = visible_curve_mask(curves, world_to_camera, depth, size, tolerance=4 * pixel_mm)
        image[cv2.dilate(visible, kernel) > 0] = rgb
    for points, rgb, radius_px, thickness in ((crossings, CROSSING_RGB, line_px + 1, -1),
                                              (spots, UNCOVERED_RGB, 3 * line_px + 4, line_px + 1)):
        if points is None or not len(points):
            continue
        column, row, point_depth = project(points, world_to_camera, size)
        for c, r, d in zip(column, row, point_depth):
            ci, ri = int(round(c)), int(round(r))
            if 0 <= ci < size and 0 <= ri < size and d <= depth[ri, ci] + 4 * pixel_mm:
                cv2.circle(image, (ci, ri), radius_px, rgb, thickness)
    return image


def pose_guides(mesh: Mesh, up: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, tuple[int, int, int]]]:
    """``(starts, ends, rgb)`` segments (mm) of the table plane (a grid square 2.5 times the
    object's horizontal reach, at its lowest point along ``up``) and of the up arrow (beside the
    object on the table, 0.6 times its height long)."""
    heights = mesh.vertices @ up
    centre = 0.5 * (mesh.vertices.max(0) + mesh.vertices.min(0))
    floor_centre = centre - (centre @ up - heights.min()) * up
    helper = np.eye(3)[int(np.argmin(np.abs(up)))]
    across = np.cross(up, helper)
    across /= np.linalg.norm(across)
    along = np.cross(up, across)
    offsets = mesh.vertices - centre
    reach = float(np.linalg.norm(offsets - np.outer(offsets @ up, up), axis=1).max())
    half = 1.25 * reach
    ticks = np.linspace(-half, half, TABLE_GRID_LINES)
    lines = [(floor_centre + t * across, half * along) for t in ticks]
    lines += [(floor_centre + t * along, half * across) for t in ticks]
    starts = [middle - reach_along for middle, reach_along in lines]
    ends = [middle + reach_along for middle, reach_along in lines]
    length = 0.6 * float(np.ptp(heights))
    foot = floor_centre + 1.1 * reach * across
    tip = foot + length * up
    head = [tip - 0.2 * length * (up + side) for side in (0.5 * across, -0.5 * across)]
    return [
        (np.asarray(starts), np.asarray(ends), TABLE_RGB),
        (np.asarray([foot, tip, tip]), np.asarray([tip, head[0], head[1]]), UP_RGB),
    ]


def caption_lines(text: str, width_px: int) -> list[str]:
    """``text`` wrapped at word boundaries into lines that fit ``width_px`` (8 px margins)."""
    lines: list[str] = []
    for word in text.split():
        wider = f"{lines[-1]} {word}" if lines else word
        if lines and cv2.getTextSize(wider, cv2.FONT_HERSHEY_SIMPLEX, CAPTION_SCALE, 1)[0][0] <= width_px - 16:
            lines[-1] += " " + word
        else:
            lines.append(word)
    return lines


def with_caption(image: np.ndarray, text: str) -> np.ndarray:
    """``image`` with a white strip below it holding ``text`` wrapped to its width."""
    lines = caption_lines(text, image.shape[1])
    strip = np.full((CAPTION_LINE_PX * len(lines) + 8, image.shape[1], 3), 255, dtype=np.uint8)
    for index, line in enumerate(lines):
        baseline = CAPTION_LINE_PX * (index + 1)
        cv2.putText(strip, line, (8, baseline), cv2.FONT_HERSHEY_SIMPLEX, CAPTION_SCALE, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([image, strip])


def visible_curve_mask(
    curves: CurveSet, world_to_camera: np.ndarray, depth: np.ndarray, size: int, tolerance: float
) -> np.ndarray:
    """uint8 mask of pixels where the curves are in front of (or on) the rendered surface."""
    start, end = segments(curves)
    return visible_segments_mask(curves.points[start], curves.points[end], world_to_camera, depth, size, tolerance)


def visible_segments_mask(
    a: np.ndarray, b: np.ndarray, world_to_camera: np.ndarray, depth: np.ndarray, size: int, tolerance: float
) -> np.ndarray:
    """uint8 mask of pixels where the segments ``a[i]-b[i]`` (mm) are in front of (or on) the
    rendered surface."""
    mask = np.zeros((size, size), dtype=np.uint8)
    if len(a) == 0:
        return mask
    col_a, row_a, _ = project(a, world_to_camera, size)
    col_b, row_b, _ = project(b, world_to_camera, size)
    steps = np.ceil(2 * np.hypot(col_b - col_a, row_b - row_a)).clip(1, 4 * size).astype(np.int64)
    owner = np.repeat(np.arange(len(a)), steps + 1)
    first = np.repeat(np.cumsum(steps + 1) - (steps + 1), steps + 1)
    t = (np.arange(len(owner)) - first) / steps[owner]
    samples = a[owner] + t[:, None] * (b[owner] - a[owner])
    column, row, sample_depth = project(samples, world_to_camera, size)
    ci, ri = np.rint(column).astype(np.int64), np.rint(row).astype(np.int64)
    inside = (ci >= 0) & (ci < size) & (ri >= 0) & (ri < size) & (sample_depth > 0)
    ci, ri, sample_depth = ci[inside], ri[inside], sample_depth[inside]
    # a curve point is visible when no surface is nearer within a small window around its pixel
    nearest = cv2.erode(depth, np.ones((3, 3), np.uint8))
    shown = sample_depth <= np.maximum(depth[ri, ci], nearest[ri, ci]) + tolerance
    mask[ri[shown], ci[shown]] = 1
    return mask


def render_png(
    mesh: Mesh,
    regions: SurfaceRegions | None,
    tx: CurveSet,
    rx: CurveSet,
    crossings: np.ndarray | None,
    view_px: int,
    line_px: int,
    uncovered: dict | None = None,
) -> bytes:
    """PNG bytes of the 2 x 2 grid of views (``2 view_px`` wide; with ``regions``, the pose caption
    below them makes it taller); ``uncovered`` the layout metrics' ``uncovered_*`` entries."""
    up = np.asarray(regions.up, dtype=np.float64) if regions is not None else np.array([0.0, 0.0, 1.0])
    centre = 0.5 * (mesh.vertices.max(0) + mesh.vertices.min(0))
    radius = float(np.linalg.norm(mesh.vertices.max(0) - mesh.vertices.min(0))) / 2
    colours = face_colours(len(mesh.faces), regions)
    guides = pose_guides(mesh, up) if regions is not None else []
    spots = np.array([spot["point"] for spot in uncovered["uncovered_spots"]]).reshape(-1, 3) if uncovered else None
    tiles = []
    for label, azimuth, elevation in VIEWS:
        world_to_camera = camera(centre, 1.3 * radius, up, np.radians(azimuth), np.radians(elevation))
        tile = render_view(
            mesh, colours, [(rx, RX_RGB), (tx, TX_RGB)], crossings, world_to_camera, view_px, line_px, guides, spots
        )
        cv2.putText(tile, label, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
        tiles.append(tile)
    grid = np.vstack([np.hstack(tiles[:2]), np.hstack(tiles[2:])])
    legend = f"Tx: {tx.count} curves   Rx: {rx.count} curves   base: dark   exclusions, untouchable: grey"
    cv2.putText(grid, legend, (8, 2 * view_px - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    caption = ""
    if regions is not None:
        caption = f"resting pose: {regions.pose_kind} (table brown, up arrow green): {regions.pose_reason}"
    if uncovered:
        caption += (f"{'; ' if caption else ''}uncovered (red rings, the farthest point of each of the largest spots): "
                    f"{100 * uncovered['uncovered_share']:.1f}% of the touchable sensing area is farther than "
                    f"{uncovered['uncovered_threshold_mm']:g} mm from every crossing")
    if caption:
        grid = with_caption(grid, caption)
    ok, encoded = cv2.imencode(".png", cv2.cvtColor(grid, cv2.COLOR_RGB2BGR))
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return encoded.tobytes()
