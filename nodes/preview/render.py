"""``preview.render`` / ``preview.layout``: see the Tx/Rx layout on the object without other software.

Writes ``preview.png`` (four views in a 2 x 2 grid, :mod:`.views`) and ``preview.html`` (a
self-contained WebGL2 orbit viewer, :mod:`.viewer`).
"""
from __future__ import annotations

import numpy as np
from pydantic import Field

from ...graph.node import Files, NodeParams, node
from ..data.types import CurveSet, Layout, Mesh, SurfaceRegions
from .viewer import render_html
from .views import render_png


class PreviewParams(NodeParams):
    """Image size and file names."""

    view_px: int = Field(480, ge=64, le=4096, description="side of each of the four square views (px)")
    line_px: int = Field(2, ge=1, le=9, description="curve width in the PNG (px)")
    png: str = Field("preview.png", description="PNG file name in the output folder")
    html: str = Field("preview.html", description="HTML viewer file name in the output folder")


@node("preview.render", params=PreviewParams, inputs=("mesh", "regions", "tx", "rx"), outputs=("files",), sink=True)
def render_preview(params: PreviewParams, mesh: Mesh, regions: SurfaceRegions, tx: CurveSet, rx: CurveSet) -> Files:
    """A PNG with four views of the object and both curve layers, and an interactive HTML viewer."""
    return Files(
        contents={
            params.png: render_png(mesh, regions, tx, rx, None, params.view_px, params.line_px),
            params.html: render_html(mesh, regions, tx, rx, None),
        }
    )


@node("preview.layout", params=PreviewParams, inputs=("mesh", "regions", "layout", "metrics"), outputs=("files",), sink=True)
def render_layout_preview(params: PreviewParams, mesh: Mesh, regions: SurfaceRegions, layout: Layout, metrics: dict) -> Files:
    """As ``preview.render`` for the optimised layout: the selected curves, with the crossings that
    carry an electrode pad marked as yellow dots and the largest uncovered spots of ``metrics`` (the
    layout's) ringed in red."""
    pads = np.asarray(layout.cells.points, dtype=np.float64).reshape(-1, 3)[np.asarray(layout.pad, dtype=bool)]
    uncovered = {key: metrics[key] for key in ("uncovered_threshold_mm", "uncovered_share", "uncovered_spots")}
    return Files(
        contents={
            params.png: render_png(mesh, regions, layout.tx, layout.rx, pads, params.view_px, params.line_px, uncovered),
            params.html: render_html(mesh, regions, layout.tx, layout.rx, pads),
        }
    )
