"""Assembly guide: from the cut foil to a wired sensor (paper section 7.3, printed companion to the
projection), as ``assembly_guide.pdf`` and ``wiring.csv``.

Page 1: the object with all traces, how to import the cut sheets (:data:`IMPORT_STEPS`), the
material and layer order (:data:`BENCH_STEPS`). Then one page per trace in attachment order (Tx
channels first: the bottom layer; then Rx), titled with its Muca pin: the trace on the shaded object
from the ``views_per_trace`` named views (:mod:`.guide_views`) that show most of it, the traces
attached before it drawn thin, its solder tab (•), its crossings (open circles) and, for a split trace,
the joints (×) where a piece's tab overlaps the previous piece; below, its flat cut piece(s) side by
side with the joint overlap drawn dashed and the crossing labels placed so they do not overlap.
Last page: the wiring table (solder tab -> Muca pin), also written as ``wiring.csv``.

Speed: every candidate view is rendered once and its image, cropped to the object, is one array
that the PDF holds once however many pages show it (the traces attached before a page's trace are
thin lines over it, one per view); the trace pages share one figure whose axes are reused (only the
shown images and the drawn artists change from page to page); lines and patches are added without
data-limit updates (every axes' limits are set); the flat pieces' labels are texts at offsets in
points (annotations cost more), with one line collection for the label glyphs and one for all leader
lines, and a scale bar instead of graduated axes; the wiring table is aligned monospace text; the
texts use the PDF's 14 standard fonts (Helvetica, Courier: nothing embedded, no per-glyph layout),
so they hold the cp1252 characters only.
"""
from __future__ import annotations

import contextlib
import csv
import io
import logging

import numpy as np
from pydantic import Field

from ...graph.node import Files, NodeParams, node
from ..data.types import Layout, Mesh
from ..geometry import triangles
from .cut_sheets import IMPORT_STEPS
from .guide_views import ObjectFrame, View, candidate_directions, cropped_image, render, show_view
from .outline import TraceOutlines
from .timestamps import source_date


class Params(NodeParams):
    image_px: int = Field(420, ge=100, le=2000, description="size of each rendered view (pixels)")
    views_per_trace: int = Field(3, ge=1, le=6, description="views shown per trace")


def _curve_points(layout: Layout, trace: int) -> tuple[np.ndarray, str, bool]:
    """3D points, name and base-at-end flag of trace ``trace`` (Tx channels first, then Rx)."""
    if trace < layout.tx.count:
        return layout.tx.points[layout.tx.curve(trace)], f"Tx{trace:02d}", True
    c = trace - layout.tx.count
    return layout.rx.points[layout.rx.curve(c)], f"Rx{c:02d}", False


BENCH_STEPS = (
    "Material: Kapton-copper-Kapton laminate (or copper tape covered with Kapton tape), so traces are insulated",
    "  where the two layers cross. Bare copper tape: cover every Tx trace with Kapton tape before any Rx trace.",
    "Side down: the face that lay on the cutting mat goes onto the object. Never flip a piece: mirrored, it no",
    "  longer follows its curve.",
    "Layer order: 1. the Tx traces (blue, bottom layer), following the projection; 2. the Rx traces (red, top",
    "  layer), aligning each small landmark bulge with the crossing trace it names.",
    "Split traces (Tx03.1, Tx03.2, ...): piece .2's solder tab overlaps the end of piece .1 (the joint, ×);",
    "  solder the overlap so the trace conducts end to end.",
    "Wiring: scrape the Kapton off each solder tab, solder a wire to it and connect it to the Muca pin named",
    "  on its page (table on the last page and in wiring.csv).",
)
"""Bench steps (page 1)."""


def muca_pin(layer: str, channel: int) -> str:
    """The Muca breakout pin of a channel: TX<channel> / RX<channel>, the firmware's channel order
    (frame index ``tx * num_rx + rx``)."""
    return f"{layer.upper()}{channel}"


def wiring_rows(layout: Layout, outlines: TraceOutlines) -> list[dict]:
    """One row per solder tab (part), in attachment order."""
    rows = []
    for i in range(outlines.count):
        trace = int(outlines.trace[i])
        layer, channel = ("tx", trace) if trace < layout.tx.count else ("rx", trace - layout.tx.count)
        pieces = np.nonzero(outlines.trace == trace)[0]
        number = int(np.nonzero(pieces == i)[0][0])
        rows.append({
            "tab": outlines.names[i], "trace": outlines.trace_names[trace], "layer": layer,
            "layer_order": 1 if layer == "tx" else 2, "muca_pin": muca_pin(layer, channel),
            "wire": "to the Muca pin" if number == 0 else f"soldered onto {outlines.names[pieces[number - 1]]}'s end",
            "length_mm": round(float(np.ptp(outlines.arc_range[i])), 1),
        })
    return rows


def wiring_csv(rows: list[dict]) -> bytes:
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return text.getvalue().encode("utf-8")


def _draw_curve(ax, view: View, points: np.ndarray, tolerance: float, **style) -> None:
    px, _ = view.project(points)
    shown = np.where(view.visible(points, tolerance)[:, None], px, np.nan)
    _line(ax, shown[:, 0], shown[:, 1], **style)


def _line(ax, x, y, **style) -> None:
    """``ax.plot(x, y, **style)`` without its data-limit update (every axes' limits are set)."""
    from matplotlib.lines import Line2D

    ax.add_artist(Line2D(x, y, **style))


PAGE_INCHES = (11.69, 8.27)
"""A4 landscape."""

TABLE_ROWS = 38
"""Wiring table rows per page."""

ATTACHED_GREY, ATTACHED_WIDTH_PT = "#404040", 0.45
"""Colour and line width (points; about one pixel of the default 420-pixel views) of the traces
attached before the page's trace."""


def _arc_points(points: np.ndarray, arcs: np.ndarray) -> np.ndarray:
    """3D points at arc lengths ``arcs`` (mm from the curve's start) of a polyline."""
    cumulative = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    return np.stack([np.interp(arcs, cumulative, points[:, k]) for k in range(3)], axis=1).reshape(-1, 3)


def _joint_arcs(outlines: TraceOutlines, trace: int, base_at_end: bool) -> np.ndarray:
    """Arc lengths (from the curve's start) where the pieces of a split trace join (empty if whole)."""
    ranges = outlines.arc_range[outlines.trace == trace]
    return ranges[1:, 1] if base_at_end else ranges[1:, 0]


def object_frame(mesh: Mesh, layout: Layout) -> ObjectFrame:
    """The object's frame with ``up`` pointing from the Tx traces' base ends (Tx curves end on the
    base boundary) through the mesh's centroid; z up when that is undefined."""
    down = layout.tx.points[layout.tx.offsets[1:] - 1].mean(axis=0) - mesh.vertices.mean(axis=0)
    norm = float(np.linalg.norm(down))
    return ObjectFrame.from_up(-down / norm if norm > 1e-9 else np.array([0.0, 0.0, 1.0]))


def _overview_page(figure_type, views, crops, frame: ObjectFrame, traces, tolerance: float, source: str,
                   layout: Layout):
    fig = figure_type(figsize=PAGE_INCHES)
    grid = fig.add_gridspec(2, 3, height_ratios=[3, 2], top=0.9, bottom=0.02)
    fig.suptitle(f"retrotouch assembly guide: {source}\n{layout.tx.count} Tx (blue, bottom layer) then "
                 f"{layout.rx.count} Rx (red, top layer); attach the traces in page order")
    everything = np.vstack([points for points, _, _ in traces])
    overview = np.argsort([np.count_nonzero(v.visible(everything, tolerance)) for v in views], kind="stable")
    for col, v in enumerate(overview[::-1][:3]):
        ax = fig.add_subplot(grid[0, col])
        show_view(ax, crops[v], views[v].size)
        for points, name, _ in traces:
            _draw_curve(ax, views[v], points, tolerance, lw=1.2, color="tab:blue" if name.startswith("Tx") else "tab:red")
        ax.set_title(frame.name(views[v].direction), fontsize=8, y=1.0)
        ax.set_axis_off()
    fig.text(0.03, 0.36, "\n".join(IMPORT_STEPS + ("",) + BENCH_STEPS), fontsize=7.5, va="top")
    return fig


def _label_offsets(anchors_pt: np.ndarray, sizes_pt: np.ndarray, taken: list) -> list[tuple[float, float]]:
    """Greedy offsets (points) for labels centred at ``anchors_pt + offset`` so that no two label
    boxes (``sizes_pt`` (w, h)) overlap each other or the boxes in ``taken`` (x0, y0, x1, y1)."""
    directions = [(0, -1), (0, 1), (1, 0), (-1, 0), (1, -1), (-1, 1), (1, 1), (-1, -1)]
    offsets = []
    for (x, y), (w, h) in zip(anchors_pt, sizes_pt):
        for radius, (dx, dy) in ((r, d) for r in (9, 16, 24, 34, 46) for d in directions):
            box = (x + dx * radius - w / 2, y + dy * radius - h / 2, x + dx * radius + w / 2, y + dy * radius + h / 2)
            if all(box[2] <= t[0] or box[0] >= t[2] or box[3] <= t[1] or box[1] >= t[3] for t in taken):
                break
        taken.append(box)
        offsets.append((dx * radius, dy * radius))
    return offsets


def _leader(offset_pt, half_box_pt, shrink_pt: float = 2.0) -> np.ndarray:
    """(2, 2) ends (points, from the anchor) of a leader line towards a label centred at
    ``offset_pt``: from ``shrink_pt`` off the anchor to ``shrink_pt`` before the label's box (half
    sizes ``half_box_pt``), as matplotlib's annotation arrows; both at the anchor when that is empty."""
    offset = np.asarray(offset_pt, float)
    length = float(np.linalg.norm(offset))
    if length == 0.0:
        return np.zeros((2, 2))
    with np.errstate(divide="ignore"):
        inside = np.min(np.asarray(half_box_pt, float) / np.abs(offset)) * length  # points of it inside the box
    free = length - inside - shrink_pt
    if free <= shrink_pt:
        return np.zeros((2, 2))
    return np.outer([shrink_pt, free], offset / length)


def _scale_bar_mm(width_mm: float) -> float:
    """The longest 1, 2 or 5 x 10^k mm no longer than a fifth of ``width_mm``."""
    bars = [m * 10.0**k for k in range(-1, 4) for m in (1, 2, 5)]
    return max([b for b in bars if b <= width_mm / 5], default=bars[0])


def _draw_pieces(fig, ax, outlines: TraceOutlines, parts: np.ndarray) -> None:
    """The pieces of one trace side by side (unfolded frame, shifted along x), each next piece's
    tab dashed where it overlaps the previous piece, crossing labels that do not overlap.

    Speed: one patch per piece added without data-limit updates (the limits are set first), the
    label glyphs and the leader lines of all labels as one line collection each."""
    from matplotlib.collections import LineCollection
    from matplotlib.patches import Polygon as PolygonPatch
    from matplotlib.transforms import offset_copy

    gap = 12.0
    shifts, x = [], 0.0
    for i in parts:
        ring = outlines.ring[outlines.ring_offsets[i] : outlines.ring_offsets[i + 1]]
        shifts.append(np.array([x - ring[:, 0].min(), 0.0]))
        x += np.ptp(ring[:, 0]) + gap
    rings = [outlines.ring[outlines.ring_offsets[i] : outlines.ring_offsets[i + 1]] + d for i, d in zip(parts, shifts)]
    everything = np.vstack(rings)
    lo, hi = everything.min(axis=0) - 8, everything.max(axis=0) + 8
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    box = ax.get_position()
    width_pt, height_pt = box.width * PAGE_INCHES[0] * 72, box.height * PAGE_INCHES[1] * 72
    pt_per_mm = min(width_pt / (hi[0] - lo[0]), height_pt / (hi[1] - lo[1]))
    taken, glyphs, leaders = [], [], []  # leaders: (anchor (mm), ends (points from it), (line width, colour))

    def label(text, at, offset, half_box, line, **style):
        ax.text(*at, text, transform=offset_copy(ax.transData, fig, *offset, units="points"), ha="center",
                va="center", **style)
        leaders.append((np.asarray(at, float), _leader(offset, half_box), line))

    for k, (i, shift, ring) in enumerate(zip(parts, shifts, rings)):
        ax.add_artist(PolygonPatch(ring, closed=True, facecolor="#c87533", alpha=0.8, lw=0.5, ec="black"))
        glyphs += [glyph + shift for glyph in outlines.label_polylines(int(i))]
        name_at = outlines.tab[i].mean(axis=0) + shift
        label(outlines.names[i], name_at, (0, 16), (20, 6), (1.0, "black"), fontsize=10)
        centre_pt = (name_at - lo) * pt_per_mm + [0, 16]
        taken.append((centre_pt[0] - 25, centre_pt[1] - 7, centre_pt[0] + 25, centre_pt[1] + 7))
        if k + 1 < len(parts):  # the next piece's tab lies over this piece's end
            joint = np.vstack([outlines.tab[parts[k + 1]], outlines.tab[parts[k + 1]][:1]]) + shift
            _line(ax, joint[:, 0], joint[:, 1], ls="--", color="black", lw=0.9)
            label(f"× joint: {outlines.names[parts[k + 1]]}'s tab goes here", joint[:4].mean(axis=0), (0, -22),
                  (60, 4.5), (0.5, "black"), fontsize=7)
        mine = outlines.landmark_part == i
        xy = outlines.landmark_xy[mine] + shift
        names = [outlines.trace_names[o] for o in outlines.landmark_other[mine]]
        sizes = np.array([[0.62 * 6 * len(n) + 2, 8.0] for n in names]).reshape(-1, 2)
        for point, name, offset, size in zip(xy, names, _label_offsets((xy - lo) * pt_per_mm, sizes, taken), sizes):
            label(name, point, offset, size / 2, (0.3, "0.5"), fontsize=6, color="0.3")
    ax.add_collection(LineCollection(glyphs, colors="blue", linewidths=0.5), autolim=False)
    if leaders:  # the axes' scale is pt_per_mm once its aspect is equal: offsets in points -> mm
        segments = [at + ends / pt_per_mm for at, ends, _ in leaders]
        ax.add_collection(LineCollection(segments, linewidths=[lw for *_, (lw, _) in leaders],
                                         colors=[color for *_, (_, color) in leaders]), autolim=False)
    bar = _scale_bar_mm(hi[0] - lo[0])  # a scale bar instead of graduated axes (a third of the page's time)
    ax.xaxis.set_visible(False)
    ax.yaxis.set_visible(False)
    _line(ax, [lo[0] + 3, lo[0] + 3 + bar], [lo[1] + 2.5] * 2, color="black", lw=2, solid_capstyle="butt")
    ax.text(lo[0] + 3 + bar / 2, lo[1] + 2.5, f"{bar:g} mm", ha="center", va="bottom", fontsize=7,
            transform=offset_copy(ax.transData, fig, 0, 3, units="points"))
    ax.set_aspect("equal", adjustable="box")
    ax.set_title("flat cut piece(s) to scale, seen from outside; small bulges = landmarks where the named trace of the "
                 "other layer crosses (open circles in the views)", fontsize=9, y=1.0)


class _TracePages:
    """One figure for every trace page: its view axes and images are made once and reused."""

    def __init__(self, figure_type, views: list[View], views_per_trace: int):
        self.fig = figure_type(figsize=PAGE_INCHES)
        grid = self.fig.add_gridspec(2, views_per_trace, height_ratios=[3, 2], top=0.9, bottom=0.05)
        self.view_axes = [self.fig.add_subplot(grid[0, col]) for col in range(views_per_trace)]
        self.crops = [cropped_image(view) for view in views]  # one array per view for all pages (and the overview)
        self.images = [show_view(ax, self.crops[0], views[0].size) for ax in self.view_axes]
        for ax in self.view_axes:
            ax.set_axis_off()
        self.flat = self.fig.add_subplot(grid[1, :])
        self.attached = [[] for _ in views]  # per view: the attached traces' visible pixels, NaN-separated

    def clear(self) -> None:
        for ax in self.view_axes + [self.flat]:
            for artist in list(ax.lines) + list(ax.texts) + list(ax.patches) + list(ax.collections):
                artist.remove()

    def draw(self, step: int, traces, views, frame: ObjectFrame, tolerance: float, layout: Layout,
             outlines: TraceOutlines, views_per_trace: int):
        self.clear()
        points, name, base_at_end = traces[step]
        layer, channel = ("tx", step) if base_at_end else ("rx", step - layout.tx.count)
        length = float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())
        self.fig.suptitle(
            f"Step {step + 1}/{len(traces)}: {name} -> Muca pin {muca_pin(layer, channel)}   (layer "
            f"{'1, Tx, bottom' if layer == 'tx' else '2, Rx, on top of the Tx layer'}; {length:.1f} mm; solder tab • at "
            f"the {'end' if base_at_end else 'start'} of the curve)", fontsize=12)
        scores = [np.count_nonzero(v.visible(points, tolerance)) for v in views]
        best = np.argsort(scores, kind="stable")[::-1][:views_per_trace]
        base = points[-1] if base_at_end else points[0]
        cells = layout.cells
        mine = (cells.curve_a == step) if base_at_end else (cells.curve_b == step - layout.tx.count)
        crossings = cells.points[mine].reshape(-1, 3)
        joints = _arc_points(points, _joint_arcs(outlines, step, base_at_end))
        for ax, image, v in zip(self.view_axes, self.images, best):
            view = views[v]
            image.crop = self.crops[v]
            if self.attached[v]:
                trail = np.vstack(self.attached[v])
                _line(ax, trail[:, 0], trail[:, 1], color=ATTACHED_GREY, lw=ATTACHED_WIDTH_PT)
            _draw_curve(ax, view, points, tolerance, lw=2.5, color="tab:red" if layer == "rx" else "tab:blue")
            cx, _ = view.project(crossings[view.visible(crossings, tolerance)])
            _line(ax, cx[:, 0], cx[:, 1], ls="none", marker="o", mfc="white", mec="black", ms=4, mew=0.8)
            jx, _ = view.project(joints[view.visible(joints, tolerance)])
            _line(ax, jx[:, 0], jx[:, 1], ls="none", marker="x", color="black", ms=8, mew=2)
            if view.visible(base[None], tolerance)[0]:
                bx, _ = view.project(base[None])
                _line(ax, bx[:1, 0], bx[:1, 1], ls="none", marker="o", color="black", ms=7)
            ax.set_title(frame.name(view.direction), fontsize=9, y=1.0)
        _draw_pieces(self.fig, self.flat, outlines, np.nonzero(outlines.trace == step)[0])
        return self.fig

    def attach(self, points: np.ndarray, views, tolerance: float) -> None:
        """Add an attached trace to every view of the later pages (thin, dark grey, where visible)."""
        for trail, view in zip(self.attached, views):
            px, _ = view.project(points)
            trail.append(np.vstack([np.where(view.visible(points, tolerance)[:, None], px, np.nan), [[np.nan] * 2]]))


def _wiring_pages(figure_type, rows: list[dict]):
    """The wiring table, ``TABLE_ROWS`` rows a page, as aligned monospace columns (one text per
    page: a matplotlib table of cells took longer than all trace pages' labels together)."""
    columns = list(rows[0])
    cells = [columns] + [[str(r[c]) for c in columns] for r in rows]
    widths = [max(len(row[k]) for row in cells) for k in range(len(columns))]
    lines = ["  ".join(v.ljust(w) for v, w in zip(row, widths)).rstrip() for row in cells]
    for start in range(1, len(lines), TABLE_ROWS):
        fig = figure_type(figsize=PAGE_INCHES)
        fig.suptitle("Wiring: solder each tab's wire to its Muca pin (also in wiring.csv)", fontsize=12)
        text = "\n".join([lines[0], "-" * len(lines[0])] + lines[start : start + TABLE_ROWS])
        fig.text(0.04, 0.9, text, family="Courier", fontsize=9.5, va="top", linespacing=1.35)
        yield fig


@contextlib.contextmanager
def _standard_fonts():
    """matplotlib with the PDF's standard fonts. Their only weight is medium, which font lookup takes
    for normal after a warning per font: that warning is silenced meanwhile."""
    from matplotlib import rc_context

    log = logging.getLogger("matplotlib.font_manager")
    level = log.level
    log.setLevel(logging.ERROR)
    try:
        with rc_context({"pdf.use14corefonts": True}):
            yield
    finally:
        log.setLevel(level)


@node("fab.assembly_guide", params=Params, inputs=("mesh", "layout", "outlines"), outputs=("files",), sink=True)
def assembly_guide(params: Params, mesh: Mesh, layout: Layout, outlines: TraceOutlines) -> Files:
    """Write ``assembly_guide.pdf`` (module docstring) and ``wiring.csv`` (solder tab -> Muca pin)."""
    from matplotlib.backends.backend_pdf import PdfPages  # heavy: imported when used
    from matplotlib.figure import Figure  # no pyplot: no global state, safe in worker threads

    frame = object_frame(mesh, layout)
    normals, _ = triangles.normals(triangles.corners(mesh.vertices, mesh.faces))
    views = [render(mesh, d, params.image_px, frame, normals) for d in candidate_directions()]
    tolerance = 0.01 * float(np.ptp(mesh.vertices, axis=0).max())
    traces = [_curve_points(layout, t) for t in range(layout.tx.count + layout.rx.count)]
    rows = wiring_rows(layout, outlines)
    buffer = io.BytesIO()
    metadata = {"Title": "retrotouch assembly guide", "Creator": "retrotouch", "CreationDate": source_date()}
    source = mesh.source.replace("\\", "/").rsplit("/", 1)[-1][:60]
    with _standard_fonts(), PdfPages(buffer, metadata=metadata) as pdf:
        pages = _TracePages(Figure, views, params.views_per_trace)
        pdf.savefig(_overview_page(Figure, views, pages.crops, frame, traces, tolerance, source, layout))
        for step in range(len(traces)):
            pdf.savefig(pages.draw(step, traces, views, frame, tolerance, layout, outlines, params.views_per_trace))
            pages.attach(traces[step][0], views, tolerance)
        for fig in _wiring_pages(Figure, rows):
            pdf.savefig(fig)
    return Files(contents={"assembly_guide.pdf": buffer.getvalue(), "wiring.csv": wiring_csv(rows)})
