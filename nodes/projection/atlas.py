"""The UV atlas the layout is baked into: charts only where the bake paints (the layout's bands).

The bake draws curves, crossing rings and pads; everything else stays background. So only the
faces within reach of a curve or a crossing (:func:`layout_band`) get xatlas charts; every other
face maps all its corners to one background texel that no chart and no gutter touches. xatlas's
chart computation is the sink's largest cost; charting the bands alone also packs them at a
higher texel density in the same texture.

UV convention: OBJ/trimesh (origin bottom-left, v up); texture row = (1 - v) * size; lengths mm.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..data.types import CurveSet, Layout, Mesh
from ..geometry.triangles import areas, corners, mean_edge_mm

SAMPLE_SPACING_MM = 0.25
"""Curves are sampled this densely (mm) to find the faces near them."""
MIN_UTILIZATION = 0.4
"""Assumed worst chart utilization of the packed texture, for an upper bound of the texel size."""
CHART_BOUNDARY_EDGES = 128
"""Longest chart boundary, in mean edge lengths of the charted faces. xatlas checks a growing
chart's parametrization for overlaps at a cost that grows with its boundary; unbounded, a few
long charts along the layout's strips dominate the sink's time."""


@dataclasses.dataclass(frozen=True)
class Atlas:
    """Split vertices ``vertex_map`` (into the mesh), ``faces`` (same order as the mesh's), ``uv`` in [0, 1].

    ``charted[f]`` says whether face ``f`` has a chart; the others map to one background texel.
    """

    vertex_map: np.ndarray  # (n', ) int64
    faces: np.ndarray  # (m, 3) int64
    uv: np.ndarray  # (n', 2) float64
    charted: np.ndarray  # (m,) bool


def curve_samples(curves: CurveSet, spacing_mm: float = SAMPLE_SPACING_MM) -> np.ndarray:
    """(k, 3) points along every curve, at most ``spacing_mm`` apart (the curve points included)."""
    out = [np.asarray(curves.points, np.float64).reshape(-1, 3)]
    for c in range(curves.count):
        p = curves.points[curves.curve(c)]
        if len(p) < 2:
            continue
        seg = np.diff(p, axis=0)
        steps = np.maximum(1, np.ceil(np.linalg.norm(seg, axis=1) / spacing_mm).astype(np.int64))
        owner = np.repeat(np.arange(len(seg)), steps)
        t = (np.arange(steps.sum()) - np.repeat(np.cumsum(steps) - steps, steps)) / steps[owner]
        out.append(p[owner] + t[:, None] * seg[owner])
    return np.concatenate(out)


def layout_band(mesh: Mesh, layout: Layout, texture_px: int, line_reach_mm: float, cell_reach_mm: float) -> np.ndarray:
    """(m,) bool: faces that may receive paint: within ``line_reach_mm`` of a curve or ``cell_reach_mm`` of a crossing.

    Conservative: a face counts when its centroid lies within reach + its circumradius (+ half
    the sample spacing) of a sample; two texels at the lowest density the atlas can have are added
    to the reach for anti-aliasing.
    """
    from scipy.spatial import cKDTree

    tri = corners(mesh.vertices, mesh.faces)
    centroid = tri.mean(axis=1)
    circumradius = np.linalg.norm(tri - centroid[:, None], axis=2).max(axis=1)
    texel_mm = 1.0 / np.sqrt(MIN_UTILIZATION * texture_px**2 / areas(tri).sum())
    slack = circumradius + 2.0 * texel_mm + SAMPLE_SPACING_MM / 2
    band = np.zeros(len(mesh.faces), bool)
    for points, reach in ((np.concatenate([curve_samples(layout.tx), curve_samples(layout.rx)]), line_reach_mm),
                          (np.asarray(layout.cells.points, np.float64).reshape(-1, 3), cell_reach_mm)):
        if len(points):
            distance, _ = cKDTree(points).query(centroid, distance_upper_bound=reach + slack.max())
            band |= distance <= reach + slack
    return band


def _xatlas(vertices: np.ndarray, faces: np.ndarray, texture_px: int, padding_px: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """xatlas charts of (vertices, faces) packed into a ``texture_px`` square: (vertex_map, faces, uv).

    Chart boundaries are at most :data:`CHART_BOUNDARY_EDGES` mean edge lengths long. The charts
    are packed at half the resolution with half the gutter (rounded up): at least ``padding_px``
    between charts at full resolution, with a quarter of the texels in the packer's bitmaps. The
    UVs are scaled alike in u and v (texels stay square when xatlas's atlas is not)."""
    import xatlas

    atlas = xatlas.Atlas()
    atlas.add_mesh(vertices.astype(np.float32), faces.astype(np.uint32))
    charts = xatlas.ChartOptions()
    charts.max_boundary_length = CHART_BOUNDARY_EDGES * mean_edge_mm(vertices, faces)
    pack = xatlas.PackOptions()
    pack.resolution = max(1, texture_px // 2)
    pack.padding = -(-padding_px // 2)
    pack.bilinear = True
    atlas.generate(chart_options=charts, pack_options=pack)
    vmap, chart_faces, uv = atlas[0]
    if not np.array_equal(vmap[chart_faces], faces):
        raise RuntimeError("xatlas reordered faces; the face -> UV mapping would be wrong")
    size = np.array([atlas.width, atlas.height], np.float64)
    return np.asarray(vmap, np.int64), np.asarray(chart_faces, np.int64), np.asarray(uv, np.float64) * size / size.max()


def background_texel(uv: np.ndarray, faces: np.ndarray, texture_px: int, clearance_px: int) -> np.ndarray | None:
    """UV (2,) of the texel centre farthest from every chart (at least ``clearance_px`` away), or None."""
    import cv2

    charts = np.zeros((texture_px, texture_px), np.uint8)
    pixels = np.stack([uv[:, 0] * texture_px - 0.5, (1.0 - uv[:, 1]) * texture_px - 0.5], axis=1)
    cv2.fillPoly(charts, list(np.rint(pixels[faces] * 16).astype(np.int32)), 255, cv2.LINE_8, 4)
    free = cv2.distanceTransform((charts == 0).astype(np.uint8), cv2.DIST_L2, 5)
    row, col = np.unravel_index(int(np.argmax(free)), free.shape)
    if free[row, col] < clearance_px:
        return None
    return np.array([(col + 0.5) / texture_px, 1.0 - (row + 0.5) / texture_px])


def build_atlas(mesh: Mesh, texture_px: int, padding_px: int, band: np.ndarray, reach_mm: float) -> Atlas:
    """Charts for the ``band`` faces packed into a ``texture_px`` square (``padding_px`` gutters),
    the other faces on one background texel farther than ``reach_mm`` of paint (plus the gutter)
    from every chart. Every face is charted when ``band`` is all or nothing, or no such texel is free."""
    band = np.asarray(band, bool)
    if not band.any():
        band = np.ones(len(mesh.faces), bool)
    used, compact = np.unique(mesh.faces[band], return_inverse=True)
    vmap, chart_faces, uv = _xatlas(mesh.vertices[used], compact.reshape(-1, 3), texture_px, padding_px)
    faces = np.zeros_like(mesh.faces)
    faces[band] = chart_faces
    atlas = Atlas(used[vmap], faces, uv, band)
    if band.all():
        return atlas
    clearance = padding_px + 2 + int(np.ceil(reach_mm * texels_per_mm(mesh, atlas, texture_px)))
    spot = background_texel(uv, chart_faces, texture_px, clearance)
    if spot is None:
        return build_atlas(mesh, texture_px, padding_px, np.ones(len(mesh.faces), bool), reach_mm)
    rest, rest_compact = np.unique(mesh.faces[~band], return_inverse=True)
    faces[~band] = len(uv) + rest_compact.reshape(-1, 3)
    return Atlas(np.concatenate([atlas.vertex_map, rest]), faces, np.concatenate([uv, np.tile(spot, (len(rest), 1))]), band)


def texels_per_mm(mesh: Mesh, atlas: Atlas, texture_px: int) -> float:
    """Mean texel density of the charted faces: sqrt(UV area in px^2 / surface area in mm^2)."""
    area_3d = areas(corners(mesh.vertices, mesh.faces[atlas.charted])).sum()
    t = atlas.uv[atlas.faces[atlas.charted]] * texture_px
    e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    area_uv = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum()
    return float(np.sqrt(area_uv / area_3d))


def face_uv_pixels(atlas: Atlas, faces: np.ndarray, bary: np.ndarray, texture_px: int) -> np.ndarray:
    """Texture pixel coordinates (k, 2) (x right, y down) of surface points given by face + barycentrics."""
    uv = np.einsum("kj,kjd->kd", bary, atlas.uv[atlas.faces[faces]])
    return np.stack([uv[:, 0] * texture_px - 0.5, (1.0 - uv[:, 1]) * texture_px - 0.5], axis=1)
