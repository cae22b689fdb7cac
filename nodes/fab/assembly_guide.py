"""Assembly guide PDF: where each cut trace goes on the object (paper section 7.3, printed companion
to the projection).

One overview page, then one page per trace in attachment order (Tx channels first, then Rx): the
trace drawn on the shaded object from the ``views_per_trace`` candidate views that show most of it
(with the traces attached before it drawn thin), its base end (solder tab) marked, and its flat cut
outline(s) with the channel name. Rendering is a CPU painter's algorithm (OpenCV polygon fill of
back-face-culled faces sorted by depth, orthographic); a curve point is drawn where it is not
behind the rendered surface.

View conventions: the 14 candidate view directions are the 6 axis directions and the 8 cube
diagonals of the mesh frame (a view direction points from the object towards the viewer); image
"up" is +z, or +y when looking along z.
"""
from __future__ import annotations

import dataclasses
import io

import numpy as np
from pydantic import Field

from ...graph.node import Files, NodeParams, node
from ..data.types import Layout, Mesh
from ..geometry import triangles
from .outline import TraceOutlines
from .timestamps import source_date


class Params(NodeParams):
    image_px: int = Field(420, ge=100, le=2000, description="size of each rendered view (pixels)")
    views_per_trace: int = Field(3, ge=1, le=6, description="views shown per trace")


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


def render(mesh: Mesh, direction: np.ndarray, size: int) -> View:
    """Shaded orthographic render of the mesh seen from ``direction`` (painter's algorithm)."""
    import cv2  # heavy: imported when used

    up_hint = np.array([0.0, 1.0, 0.0]) if abs(direction[2]) > 0.99 else np.array([0.0, 0.0, 1.0])
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
    normals, _ = triangles.normals(triangles.corners(V, F))
    facing = normals @ direction
    front = np.nonzero(facing > 0)[0]
    order = front[np.argsort(depth[F[front]].mean(axis=1))]
    corners = np.round(px[F[order]] * 16).astype(np.int32)  # 4 fractional bits
    face_id = np.full((size, size), -1, np.int32)
    for k, f in enumerate(order.tolist()):
        cv2.fillConvexPoly(face_id, corners[k], f, lineType=cv2.LINE_8, shift=4)
    covered = face_id >= 0
    ids = face_id[covered]
    grey = (70 + 170 * facing[ids]).astype(np.uint8)
    view.shade[covered] = grey[:, None]
    # depth of each covered pixel on its face's plane, clamped to the face's depth range
    yy, xx = np.nonzero(covered)
    n = normals[ids]
    nu, nv, nw = n @ right, n @ up, n @ direction
    p0 = V[F[ids, 0]]
    du = (xx - size / 2) / scale + view.centre[0] - p0 @ right
    dv = (size / 2 - yy) / scale + view.centre[1] - p0 @ up
    plane = p0 @ direction - (nu * du + nv * dv) / np.maximum(nw, 1e-6)
    face_depths = depth[F[ids]]
    view.depth[covered] = np.clip(plane, face_depths.min(axis=1), face_depths.max(axis=1))
    return view


def _curve_points(layout: Layout, trace: int) -> tuple[np.ndarray, str, bool]:
    """3D points, name and base-at-end flag of trace ``trace`` (Tx channels first, then Rx)."""
    if trace < layout.tx.count:
        return layout.tx.points[layout.tx.curve(trace)], f"Tx{trace:02d}", True
    c = trace - layout.tx.count
    return layout.rx.points[layout.rx.curve(c)], f"Rx{c:02d}", False


def _draw_curve(ax, view: View, points: np.ndarray, tolerance: float, **style) -> None:
    px, _ = view.project(points)
    shown = np.where(view.visible(points, tolerance)[:, None], px, np.nan)
    ax.plot(shown[:, 0], shown[:, 1], **style)


@node("fab.assembly_guide", params=Params, inputs=("mesh", "layout", "outlines"), outputs=("files",), sink=True)
def assembly_guide(params: Params, mesh: Mesh, layout: Layout, outlines: TraceOutlines) -> Files:
    """Write ``assembly_guide.pdf``: per trace in attachment order (Tx then Rx), the trace on the
    object from the views that show it best, and its flat outline with the channel name."""
    from matplotlib.backends.backend_pdf import PdfPages  # heavy: imported when used
    from matplotlib.figure import Figure  # no pyplot: no global state, safe in worker threads

    views = [render(mesh, d, params.image_px) for d in candidate_directions()]
    tolerance = 0.01 * float(np.ptp(mesh.vertices, axis=0).max())
    traces = [_curve_points(layout, t) for t in range(layout.tx.count + layout.rx.count)]
    buffer = io.BytesIO()
    metadata = {"Title": "retrotouch assembly guide", "Creator": "retrotouch", "CreationDate": source_date()}
    with PdfPages(buffer, metadata=metadata) as pdf:
        fig = Figure(figsize=(11.69, 8.27))
        axes = fig.subplots(1, 3)
        source = mesh.source.replace("\\", "/").rsplit("/", 1)[-1][:60]
        fig.suptitle(f"retrotouch assembly guide: {source}\n{layout.tx.count} Tx (blue) then {layout.rx.count} Rx "
                     "(red); attach the traces in page order")
        everything = np.vstack([points for points, _, _ in traces])
        overview = np.argsort([np.count_nonzero(v.visible(everything, tolerance)) for v in views], kind="stable")
        for ax, v in zip(axes, overview[::-1][:3]):
            view = views[v]
            ax.imshow(view.shade)
            for points, name, _ in traces:
                _draw_curve(ax, view, points, tolerance, lw=1.2, color="tab:blue" if name.startswith("Tx") else "tab:red")
            ax.set_axis_off()
        pdf.savefig(fig)
        for step, (points, name, base_at_end) in enumerate(traces):
            scores = [np.count_nonzero(v.visible(points, tolerance)) for v in views]
            best = np.argsort(scores, kind="stable")[::-1][: params.views_per_trace]
            fig = Figure(figsize=(11.69, 8.27))
            length = float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())
            fig.suptitle(f"Step {step + 1}/{len(traces)}: {name}   ({length:.1f} mm; solder tab at the "
                         f"{'end' if base_at_end else 'start'} of the curve, marked ●)", fontsize=13)
            grid = fig.add_gridspec(2, params.views_per_trace, height_ratios=[3, 2])
            base = points[-1] if base_at_end else points[0]
            cells = layout.cells
            mine = (cells.curve_a == step) if base_at_end else (cells.curve_b == step - layout.tx.count)
            crossings = cells.points[mine].reshape(-1, 3)
            for col, v in enumerate(best):
                ax = fig.add_subplot(grid[0, col])
                view = views[v]
                ax.imshow(view.shade)
                for earlier, _, _ in traces[:step]:
                    _draw_curve(ax, view, earlier, tolerance, lw=0.8, color="0.25")
                _draw_curve(ax, view, points, tolerance, lw=2.5, color="tab:red" if name.startswith("Rx") else "tab:blue")
                seen = view.visible(crossings, tolerance)
                cx, _ = view.project(crossings[seen])
                ax.plot(cx[:, 0], cx[:, 1], "o", mfc="white", mec="black", ms=4, mew=0.8)
                if view.visible(base[None], tolerance)[0]:
                    bx, _ = view.project(base[None])
                    ax.plot(bx[0, 0], bx[0, 1], "o", color="black", ms=7)
                ax.set_title(f"view {np.round(view.direction, 2).tolist()}", fontsize=8)
                ax.set_axis_off()
            ax = fig.add_subplot(grid[1, :])
            for i in np.nonzero(outlines.trace == step)[0]:
                ring = outlines.ring[outlines.ring_offsets[i] : outlines.ring_offsets[i + 1]]
                ax.fill(ring[:, 0], ring[:, 1], color="#c87533", alpha=0.8, lw=0.5, ec="black")
                for glyph in outlines.label_polylines(int(i)):
                    ax.plot(glyph[:, 0], glyph[:, 1], color="blue", lw=0.5)
                for xy, other in zip(outlines.landmark_xy[outlines.landmark_part == i],
                                     outlines.landmark_other[outlines.landmark_part == i]):
                    ax.annotate(outlines.trace_names[other], xy, xytext=(0, -10), textcoords="offset points",
                                ha="center", fontsize=6, color="0.3")
                tab = outlines.tab[i]
                ax.annotate(outlines.names[i], tab.mean(axis=0), xytext=(0, 14), textcoords="offset points",
                            ha="center", fontsize=10, arrowprops={"arrowstyle": "-"})
            ax.set_aspect("equal")
            ax.set_title("flat cut outline (mm, seen from outside); small bulges = landmarks where the named trace "
                         "of the other layer crosses (○ in the views)", fontsize=9)
            pdf.savefig(fig)
    return Files(contents={"assembly_guide.pdf": buffer.getvalue()})
