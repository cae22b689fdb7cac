"""Shaded orthographic views of the object for the assembly guide (CPU painter's algorithm), and
their images as the guide's pages show them (cropped, one array per view).

View conventions: the 14 candidate view directions are the 6 axis directions and the 8 cube
diagonals of the mesh frame (a view direction points from the object towards the viewer). The
object's own frame (:class:`ObjectFrame`) names them and keeps them upright: ``up`` (the object
standing on its base), ``front`` (the mesh axis most perpendicular to ``up``, taken negative, so a
z-up mesh faces -y) and ``right`` = up x front, on the right of a viewer in front. Image "up" is the object's up projected into the view (``front`` when looking along up).
"""
from __future__ import annotations

import dataclasses
import functools

import numpy as np

from ..data.types import Mesh
from ..geometry import triangles

SECTORS = ("front", "front right", "right", "back right", "back", "back left", "left", "front left")
"""Horizontal view sectors, counter-clockwise seen from above, starting at the front."""


@dataclasses.dataclass(frozen=True)
class ObjectFrame:
    """Unit vectors of the object's own frame in mesh coordinates (module conventions)."""

    up: np.ndarray
    front: np.ndarray
    right: np.ndarray

    @classmethod
    def from_up(cls, up: np.ndarray) -> "ObjectFrame":
        up = np.asarray(up, float) / np.linalg.norm(up)
        axes = np.eye(3)[[1, 0, 2]]  # prefer y, then x, then z as the front axis
        axis = axes[int(np.argmin(np.abs(axes @ up) - 1e-9 * np.arange(3)[::-1]))]
        front = -(axis - (axis @ up) * up)
        front /= np.linalg.norm(front)
        return cls(up, front, np.cross(up, front))

    def name(self, direction: np.ndarray) -> str:
        """Readable name of a view direction: "front view", "top view", "front left view from above"..."""
        direction = np.asarray(direction, float) / np.linalg.norm(direction)
        elevation = float(direction @ self.up)
        if abs(elevation) > 0.95:
            return "top view" if elevation > 0 else "bottom view"
        angle = np.degrees(np.arctan2(direction @ self.right, direction @ self.front)) % 360.0
        sector = SECTORS[int(np.round(angle / 45.0)) % 8]
        height = " from above" if elevation > 0.3 else " from below" if elevation < -0.3 else ""
        return f"{sector} view{height}"


@dataclasses.dataclass(frozen=True)
class View:
    direction: np.ndarray  # (3,) unit, towards the viewer
    right: np.ndarray
    up: np.ndarray
    scale: float  # pixels per mm
    centre: np.ndarray  # (2,) view-plane coordinates of the image centre (mm)
    size: int
    shade: np.ndarray  # (size, size, 3) uint8 RGB
    depth: np.ndarray  # (size, size) float32, towards the viewer (mm); -inf = background

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (x right, y down) and depth of 3D points."""
        uv = np.stack([points @ self.right, points @ self.up], axis=1) - self.centre
        px = np.stack([self.size / 2 + uv[:, 0] * self.scale, self.size / 2 - uv[:, 1] * self.scale], axis=1)
        return px, points @ self.direction

    def visible(self, points: np.ndarray, tolerance_mm: float) -> np.ndarray:
        px, depth = self.project(points)
        ij = np.clip(np.round(px).astype(int), 0, self.size - 1)
        return depth >= self.depth[ij[:, 1], ij[:, 0]] - tolerance_mm


def candidate_directions() -> np.ndarray:
    axes = np.vstack([np.eye(3), -np.eye(3)])
    diagonals = np.array([[x, y, z] for x in (1, -1) for y in (1, -1) for z in (1, -1)]) / np.sqrt(3)
    return np.vstack([axes, diagonals])


def render(mesh: Mesh, direction: np.ndarray, size: int, frame: ObjectFrame | None = None,
           normals: np.ndarray | None = None) -> View:
    """Shaded orthographic render of the mesh seen from ``direction`` (painter's algorithm), upright
    in ``frame`` (default: z up). ``normals``: the mesh's unit face normals, when already computed
    (the guide renders 14 views of one mesh)."""
    import cv2  # heavy: imported when used

    frame = frame or ObjectFrame.from_up(np.array([0.0, 0.0, 1.0]))
    up_hint = frame.front if abs(direction @ frame.up) > 0.99 else frame.up
    right = np.cross(up_hint, direction)
    right /= np.linalg.norm(right)
    up = np.cross(direction, right)
    V, F = mesh.vertices, mesh.faces
    uv = np.stack([V @ right, V @ up], axis=1)
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    scale = 0.92 * size / max(hi - lo)
    view = View(direction, right, up, scale, (lo + hi) / 2, size,
                np.full((size, size, 3), 255, np.uint8), np.full((size, size), -np.inf, np.float32))
    px, depth = view.project(V)
    if normals is None:
        normals, _ = triangles.normals(triangles.corners(V, F))
    facing = normals @ direction
    front = np.nonzero(facing > 0)[0]
    order = front[np.argsort(depth[F[front]].mean(axis=1))]
    corners = np.round(px[F[order]] * 16).astype(np.int32)  # 4 fractional bits
    face_id = np.full((size, size), -1, np.int32)
    fill = cv2.fillConvexPoly  # positional arguments: the call costs more than filling a small face
    for polygon, f in zip(corners, order.tolist()):
        fill(face_id, polygon, f, cv2.LINE_8, 4)
    covered = face_id >= 0
    ids = face_id[covered]
    grey = (70 + 170 * facing[ids]).astype(np.uint8)
    view.shade[covered] = grey[:, None]
    # depth of each covered pixel on its face's plane, clamped to the face's depth range
    yy, xx = np.nonzero(covered)
    present = np.zeros(len(F), bool)  # per drawn face first, then per pixel (np.unique without its sort)
    present[ids] = True
    drawn, pixel_face = np.flatnonzero(present), (np.cumsum(present) - 1)[ids]
    n, p0 = normals[drawn], V[F[drawn, 0]]
    nu, nv, nw = (n @ right)[pixel_face], (n @ up)[pixel_face], (n @ direction)[pixel_face]
    du = (xx - size / 2) / scale + view.centre[0] - (p0 @ right)[pixel_face]
    dv = (size / 2 - yy) / scale + view.centre[1] - (p0 @ up)[pixel_face]
    plane = (p0 @ direction)[pixel_face] - (nu * du + nv * dv) / np.maximum(nw, 1e-6)
    face_depths = depth[F[drawn]]
    view.depth[covered] = np.clip(plane, face_depths.min(axis=1)[pixel_face], face_depths.max(axis=1)[pixel_face])
    return view


def cropped_image(view: View) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """A view's image as RGBA cropped to the object and 2 pixels around it (fewer pixels to write
    into the PDF), and the rows and columns ``(r0, r1, c0, c1)`` it keeps."""
    covered = np.isfinite(view.depth)
    rows, cols = np.nonzero(covered.any(axis=1))[0], np.nonzero(covered.any(axis=0))[0]
    r0, r1 = (max(rows[0] - 2, 0), min(rows[-1] + 3, view.size)) if len(rows) else (0, view.size)
    c0, c1 = (max(cols[0] - 2, 0), min(cols[-1] + 3, view.size)) if len(cols) else (0, view.size)
    pixels = np.full((r1 - r0, c1 - c0, 4), 255, np.uint8)
    pixels[:, :, :3] = view.shade[r0:r1, c0:c1]
    return pixels, (r0, r1, c0, c1)


@functools.cache
def _raster_type():
    """The artist type that draws a cropped view (:func:`cropped_image`) unsampled in place in its axes
    (pixel centres at integer data coordinates) and hands the renderer the same array on every
    draw: the PDF backend writes one image object per array, however many pages show it (an
    ``imshow`` image hands it a new array, a new image object, on every page). Made on first use:
    matplotlib is heavy to import."""
    from matplotlib.artist import Artist
    from matplotlib.transforms import Affine2D

    class Raster(Artist):
        zorder = 0

        def __init__(self, crop):
            super().__init__()
            self.crop = crop

        def draw(self, renderer):
            pixels, (r0, r1, c0, c1) = self.crop
            gc = renderer.new_gc()
            self._set_gc_clip(gc)
            placed = Affine2D().scale(c1 - c0, r1 - r0).translate(c0 - 0.5, r0 - 0.5) + self.axes.transData
            renderer.draw_image(gc, 0.0, 0.0, pixels, placed)
            gc.restore()

    return Raster


def show_view(ax, crop: tuple, size: int):
    """Show a cropped view (:func:`cropped_image`) of ``size`` pixels in place in the axes' full view, as
    ``imshow`` would; return its artist."""
    raster = ax.add_artist(_raster_type()(crop))
    ax.set_aspect("equal")
    ax.set_xlim(-0.5, size - 0.5)
    ax.set_ylim(size - 0.5, -0.5)
    return raster
