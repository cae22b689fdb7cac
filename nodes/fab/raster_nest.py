"""Deterministic raster bottom-left-fill nesting of parts on fixed-size sheets.

Strip frame: mm, x along the sheet's longer side (``long_side``), y along the shorter, origin at the
usable corner. The sheet is a grid of ``pixel_mm`` cells. A part occupies every cell whose centre
lies within ``spacing / 2 + pixel_mm * sqrt(2) / 2`` of its outline (a conservative raster): two
parts whose occupied cells are disjoint are therefore at least ``spacing`` apart, exactly, whatever
the rounding. Parts are moved by whole cells only, so a placed part's cells are its raster shifted.

Parts are placed one by one in the caller's order. At each trial angle the free positions on a
sheet are those where the correlation of the part's raster with the sheet's occupied cells is zero
(OpenCV ``matchTemplate``, DFT-based) and the outline lies inside the usable area. The angles are
ranked on a coarse grid first, the best few are placed exactly; the part takes the free position
and angle that end leftmost (then lowest) on the first sheet that has one; a part no sheet holds
opens the next sheet. The result depends only on the input: no clock, no random numbers.
"""
from __future__ import annotations

import numpy as np
import shapely
from shapely import affinity
from shapely.geometry import Polygon

from .mats import fit_angles

BUFFER_SEGMENTS = 8
"""Segments per quarter circle of the spacing buffer (its polygon lies inside the true buffer by at
most 0.5 % of the radius, covered by ``BUFFER_SLACK_MM``)."""

BUFFER_SLACK_MM = 0.02

REFINE_STEPS = 0

COARSE = 4
"""Cell size ratio of the ranking grid to the placement grid."""
"""Halvings of the angle step around the best coarse angles."""


def part_rasters(polygon: Polygon, angles_deg: np.ndarray, radius: float, pixel: float, exact: bool = True):
    """Per angle: (occupied cells (h, w) float32, cell-grid origin of the raster in the part's
    rotated frame (2,), rotated outline bounds (4,)). ``exact``: a cell is occupied exactly when its
    centre is within ``radius`` of the outline (else OpenCV's polygon fill, a little wider and
    much faster: for ranking only)."""
    import cv2  # heavy: imported when used

    grown = polygon.buffer(radius + BUFFER_SLACK_MM, quad_segs=BUFFER_SEGMENTS)
    rasters = []
    for angle in angles_deg:
        bounds = np.asarray(affinity.rotate(polygon, float(angle), origin=(0, 0)).bounds)
        shape = affinity.rotate(grown, float(angle), origin=(0, 0))
        x0, y0, x1, y1 = shape.bounds
        origin = np.floor(np.array([x0, y0]) / pixel) * pixel
        w, h = int(np.ceil((x1 - origin[0]) / pixel)), int(np.ceil((y1 - origin[1]) / pixel))
        if exact:
            shapely.prepare(shape)
            gx, gy = np.meshgrid(origin[0] + (np.arange(w) + 0.5) * pixel, origin[1] + (np.arange(h) + 0.5) * pixel)
            cells = shapely.contains_xy(shape, gx, gy).astype(np.float32)
        else:
            corners = (np.asarray(shape.exterior.coords) - origin) / pixel - 0.5  # cell centres at integers
            cells = np.zeros((h, w), np.float32)
            cv2.fillPoly(cells, [np.round(corners * 16).astype(np.int32)], 1.0, lineType=cv2.LINE_8, shift=4)
        rasters.append((cells, origin, bounds))
    return rasters


class Sheet:
    """Occupied cells of one sheet, padded by ``pad`` cells on every side (parts' rasters may reach
    beyond the usable area by their spacing buffer)."""

    def __init__(self, long_side: float, short_side: float, pixel: float, pad: int):
        self.pixel, self.pad = pixel, pad
        self.long_side, self.short_side = long_side, short_side
        self.cells = np.zeros((int(np.ceil(short_side / pixel)) + 2 * pad, int(np.ceil(long_side / pixel)) + 2 * pad),
                              np.float32)

    def best_position(self, raster) -> tuple[float, float, int, int] | None:
        """(right end x, bottom y, cell column, cell row) of the leftmost-then-lowest free position
        of a part raster, or None."""
        import cv2  # heavy: imported when used

        cells, origin, bounds = raster
        h, w = cells.shape
        if h > self.cells.shape[0] or w > self.cells.shape[1]:
            return None
        # placing the raster's first cell at grid (col, row) translates the part by
        # (col - pad) * pixel - origin; the outline must stay inside [0, long] x [0, short]
        p = self.pixel
        col = np.arange(self.cells.shape[1] - w + 1)
        row = np.arange(self.cells.shape[0] - h + 1)
        tx, ty = (col - self.pad) * p - origin[0], (row - self.pad) * p - origin[1]
        col_ok = (tx + bounds[0] >= -1e-9) & (tx + bounds[2] <= self.long_side + 1e-9)
        row_ok = (ty + bounds[1] >= -1e-9) & (ty + bounds[3] <= self.short_side + 1e-9)
        if not col_ok.any() or not row_ok.any():
            return None
        # positions right of every occupied cell are free: correlate only up to the first of them
        occupied = np.nonzero(self.cells.any(axis=0))[0]
        first_ok = int(np.argmax(col_ok))
        end = min(self.cells.shape[1], max(int(occupied[-1]) + 1 if len(occupied) else 0, first_ok) + w)
        overlap = cv2.matchTemplate(self.cells[:, :end], cells, cv2.TM_CCORR)
        free = (overlap < 0.5) & row_ok[:, None] & col_ok[None, : overlap.shape[1]]
        columns = np.nonzero(free.any(axis=0))[0]
        if len(columns) == 0:
            return None
        c = int(columns[0])
        r = int(np.nonzero(free[:, c])[0][0])
        return float(tx[c] + bounds[2]), float(ty[r] + bounds[1]), c, r

    def occupy(self, raster, col: int, row: int) -> tuple[float, float]:
        """Mark the part's cells; its translation (mm) in the strip frame."""
        cells, origin, _ = raster
        h, w = cells.shape
        self.cells[row : row + h, col : col + w] = np.maximum(self.cells[row : row + h, col : col + w], cells)
        return (col - self.pad) * self.pixel - origin[0], (row - self.pad) * self.pixel - origin[1]


def _coarse(cells: np.ndarray) -> np.ndarray:
    """COARSE x COARSE max-pooled occupied cells (a cell is occupied when any of its cells is)."""
    h, w = -(-cells.shape[0] // COARSE) * COARSE, -(-cells.shape[1] // COARSE) * COARSE
    padded = np.zeros((h, w), np.float32)
    padded[: cells.shape[0], : cells.shape[1]] = cells
    return padded.reshape(h // COARSE, COARSE, w // COARSE, COARSE).max(axis=(1, 3))


def _ranked_angles(polygon: Polygon, sheet: Sheet, angles: np.ndarray, spacing: float, finalists: int) -> list[float]:
    """The ``finalists`` angles whose placement on the coarse grid ends leftmost (then lowest)."""
    pixel = COARSE * sheet.pixel
    rough = Sheet(sheet.long_side, sheet.short_side, pixel, -(-sheet.pad // COARSE))
    extra = rough.pad * COARSE - sheet.pad
    rough.cells = _coarse(np.pad(sheet.cells, ((extra, 0), (extra, 0))))
    scores = []
    for a, raster in zip(angles, part_rasters(polygon, angles, spacing / 2, pixel, exact=False)):
        position = rough.best_position(raster)
        scores.append((round(position[0], 6), round(position[1], 6), float(a)) if position else (np.inf, np.inf, float(a)))
    return [a for *_, a in sorted(scores)[:finalists]]


def _own_angles(polygon: Polygon, long_side: float, short_side: float) -> np.ndarray:
    """The angles (deg) that lay the part's minimum rotated rectangle along the strip, and the
    middle of the angles at which it fits the sheet (both ways round)."""
    rect = np.asarray(polygon.minimum_rotated_rectangle.exterior.coords)
    edge = rect[1] - rect[0]
    base = -np.degrees(np.arctan2(edge[1], edge[0]))
    fits = fit_angles(polygon, long_side, short_side)
    middle = [fits[len(fits) // 2]] if len(fits) else []
    return np.concatenate([base + np.array([0.0, 90.0, 180.0, 270.0]), middle, np.add(middle, 180.0)])


def raster_nest(polygons: list[Polygon], long_side: float, short_side: float, spacing: float, pixel: float,
                rotations: int, finalists: int, order: list[int]) -> list[tuple[int, float, tuple[float, float]]]:
    """(sheet, rotation deg, strip translation) per part, placing parts in ``order``.

    Each part's angles (``rotations`` evenly spaced ones and :func:`_own_angles`) are first ranked
    on a grid of ``COARSE`` times the cell size; the ``finalists`` best are then placed exactly on
    the fine grid."""
    radius = spacing / 2 + pixel * np.sqrt(2) / 2
    pad = int(np.ceil((radius + BUFFER_SLACK_MM) / pixel)) + 2
    even = np.arange(rotations) * (360.0 / rotations)
    sheets: list[Sheet] = []
    result = {}
    for i in order:
        angles = np.concatenate([even, _own_angles(polygons[i], long_side, short_side)])
        for k in range(len(sheets) + 1):
            if k == len(sheets):
                sheets.append(Sheet(long_side, short_side, pixel, pad))
            sheet = sheets[k]
            chosen = np.asarray(_ranked_angles(polygons[i], sheet, angles, spacing, finalists))
            fine = part_rasters(polygons[i], chosen, radius, pixel)
            found = [(pos, a) for a, raster in enumerate(fine) if (pos := sheet.best_position(raster))]
            if found:
                (_, _, col, row), a = min(found, key=lambda f: (round(f[0][0], 6), round(f[0][1], 6), f[1]))
                result[i] = (k, float(chosen[a]), sheet.occupy(fine[a], col, row))
                break
            if not sheet.cells.any():
                raise ValueError(f"part {i} fits no empty sheet at any of {rotations} rotations")
    return [result[i] for i in range(len(polygons))]
