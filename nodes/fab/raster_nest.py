"""Deterministic raster bottom-left-fill nesting of parts on fixed-size sheets.

Strip frame: mm, x along the sheet's longer side (``long_side``), y along the shorter, origin at the
usable corner. The sheet is a grid of ``pixel_mm`` cells. A part occupies every cell whose centre
lies within ``spacing / 2 + pixel_mm * sqrt(2) / 2`` of its outline (a conservative raster): two
parts whose occupied cells are disjoint are therefore at least ``spacing`` apart, exactly, whatever
the rounding. Parts are moved by whole cells only, so a placed part's cells are its raster shifted.

Parts are placed one by one in the caller's order. At each trial angle the free positions on a
sheet are those where the correlation of the part's raster with the sheet's occupied cells is zero
(OpenCV ``matchTemplate``, DFT-based) and the outline lies inside the usable area. The angles are
ranked on a coarse grid first, the best few are placed exactly (on an empty sheet where none of
them fits, as with a piece that fits the sheet only within a degree or two, every angle is); the
part takes the free position and angle that end leftmost (then lowest) on the first sheet that has
one; a part no sheet holds opens the next sheet. The result depends only on the input: no clock, no random numbers.

Speed: each part's grown outlines are built once (:class:`Part`) and rotated with plain array
arithmetic (the same operations as ``shapely.affinity.rotate``, so the same numbers); angles whose
rotated outline is longer or wider than the usable area are dropped before rasterizing; each sheet
keeps its coarse grid and its occupied column extent up to date as parts are added; an angle is
searched only for positions that end no further right than the current last finalist (ranking,
narrowest angles first) or the current best (exact placement), since no other can win; a pass
given the score to beat stops as soon as its placement so far is worse (more sheets, or a longer
last strip), since more parts cannot make it better.
"""
from __future__ import annotations

import math

import numpy as np
import shapely
from shapely.geometry import Polygon

from .mats import fit_angles

BUFFER_SEGMENTS = 8
"""Segments per quarter circle of the spacing buffer (its polygon lies inside the true buffer by at
most 0.5 % of the radius, covered by ``BUFFER_SLACK_MM``)."""

BUFFER_SLACK_MM = 0.02

COARSE = 4
"""Cell size ratio of the ranking grid to the placement grid."""


def _rotation(angle_deg: float) -> tuple[float, float]:
    """(cos, sin) exactly as ``shapely.affinity.rotate`` computes them."""
    angle = angle_deg * math.pi / 180.0
    c, s = math.cos(angle), math.sin(angle)
    return (0.0 if abs(c) < 2.5e-16 else c), (0.0 if abs(s) < 2.5e-16 else s)


def _rotate(coords: np.ndarray, cos: np.ndarray, sin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x, y), each (A, N): the (N, 2) points rotated CCW about the origin by each of A angles given
    by their cosines and sines (``shapely.affinity.rotate``'s arithmetic, bit for bit)."""
    x, y = coords.T
    c, s = np.asarray(cos)[:, None], np.asarray(sin)[:, None]
    return c * x + -s * y + 0.0, s * x + c * y + 0.0


def occupied_radius(spacing: float, pixel: float) -> float:
    """Distance (mm) from a part's outline within which a cell centre makes the cell occupied."""
    return spacing / 2 + pixel * np.sqrt(2) / 2


class Part:
    """One part prepared once for every pass, angle and sheet: its convex hull, ``coarse`` (exterior of
    the ``spacing / 2`` buffer, for ranking), ``fine`` (the :func:`occupied_radius` buffer) and
    ``own_angles`` (:func:`_own_angles`)."""

    def __init__(self, polygon: Polygon, spacing: float, pixel: float, long_side: float, short_side: float):
        self.hull = np.asarray(polygon.convex_hull.exterior.coords)  # input vertices: the same bounds
        self.coarse = np.asarray(polygon.buffer(spacing / 2 + BUFFER_SLACK_MM, quad_segs=BUFFER_SEGMENTS).exterior.coords)
        self.fine = polygon.buffer(occupied_radius(spacing, pixel) + BUFFER_SLACK_MM, quad_segs=BUFFER_SEGMENTS)
        self.own_angles = _own_angles(polygon, long_side, short_side)

    def rasters(self, angles_deg: np.ndarray, pixel: float, exact: bool, long_side: float, short_side: float):
        """Per angle whose rotated outline fits long x short: (angle, (occupied cells (h, w) float32,
        cell-grid origin of the raster in the part's rotated frame (2,), rotated outline bounds (4,))).
        ``exact``: a cell is occupied exactly when its centre is inside the fine buffer (else OpenCV's
        fill of the coarse buffer, a little wider and much faster: for ranking only)."""
        import cv2  # heavy: imported when used

        cos, sin = np.array([_rotation(float(a)) for a in angles_deg]).reshape(-1, 2).T
        x, y = _rotate(self.hull, cos, sin)
        bounds = np.stack([x.min(axis=1), y.min(axis=1), x.max(axis=1), y.max(axis=1)], axis=1)
        fits = np.nonzero(np.all(bounds[:, 2:] - bounds[:, :2] <= [long_side + 1e-9, short_side + 1e-9], axis=1))[0]
        if exact:  # the others: no position keeps them inside the usable area
            shapes = [shapely.transform(self.fine, lambda xy: np.stack(_rotate(xy, cos[k : k + 1], sin[k : k + 1]), -1)[0])
                      for k in fits]
            low, high = np.array([shape.bounds for shape in shapes]).reshape(-1, 2, 2).transpose(1, 0, 2)
        else:
            x, y = _rotate(self.coarse, cos[fits], sin[fits])
            low = np.stack([x.min(axis=1), y.min(axis=1)], axis=1)
            high = np.stack([x.max(axis=1), y.max(axis=1)], axis=1)
            corners = np.stack([x, y], axis=-1)
        origins = np.floor(low / pixel) * pixel
        sizes = np.ceil((high - origins) / pixel).astype(int)  # (w, h) per angle
        rasters = []
        for n, k in enumerate(fits):
            origin, (w, h) = origins[n], sizes[n]
            if exact:
                cells = _inside_cells(shapes[n], origin, w, h, pixel)
            else:
                cells = np.zeros((h, w), np.float32)
                fixed = np.round(((corners[n] - origin) / pixel - 0.5) * 16).astype(np.int32)  # cell centres at integers
                cv2.fillPoly(cells, [fixed], 1.0, lineType=cv2.LINE_8, shift=4)
            rasters.append((float(angles_deg[k]), (cells, origin, bounds[k])))
        return rasters


def _inside_cells(shape, origin: np.ndarray, w: int, h: int, pixel: float) -> np.ndarray:
    """(h, w) float32: 1 where the cell centre ``origin + (column, row + 0.5) * pixel`` lies inside
    ``shape``. OpenCV fills the rings; only the cells within 2.5 cells of a ring (where its fill
    rule could differ) are tested exactly, with shapely."""
    import cv2  # heavy: imported when used

    rings = [np.asarray(shape.exterior.coords)] + [np.asarray(r.coords) for r in shape.interiors]
    fixed = [np.round(((r - origin) / pixel - 0.5) * 16).astype(np.int32) for r in rings]  # cell centres at integers
    cells = np.zeros((h, w), np.uint8)
    cv2.fillPoly(cells, fixed, 1, lineType=cv2.LINE_8, shift=4)
    near = np.zeros((h, w), np.uint8)
    cv2.polylines(near, fixed, True, 1, thickness=5, lineType=cv2.LINE_8, shift=4)
    rows, cols = np.nonzero(near)
    shapely.prepare(shape)
    cells[rows, cols] = shapely.contains_xy(shape, origin[0] + (cols + 0.5) * pixel, origin[1] + (rows + 0.5) * pixel)
    return cells.astype(np.float32)


class Sheet:
    """Occupied cells of one sheet, padded by ``pad`` cells on every side (parts' rasters may reach
    beyond the usable area by their spacing buffer), with ``used_end``: one past the last occupied
    column; and its :meth:`rough` grid (``COARSE`` x ``COARSE`` max-pooled), kept up to date."""

    def __init__(self, long_side: float, short_side: float, pixel: float, pad: int, shape=None):
        self.pixel, self.pad = pixel, pad
        self.long_side, self.short_side = long_side, short_side
        shape = shape or (int(np.ceil(short_side / pixel)) + 2 * pad, int(np.ceil(long_side / pixel)) + 2 * pad)
        self.cells = np.zeros(shape, np.float32)
        self.used_end = 0
        self._rough: Sheet | None = None

    def best_position(self, raster, limit_x: float = np.inf) -> tuple[float, float, int, int] | None:
        """(right end x, bottom y, cell column, cell row) of the leftmost-then-lowest free position
        of a part raster, or None; also None when that position's right end would lie beyond
        ``limit_x`` (mm, rounded to 1e-6: those positions are not searched)."""
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
        first_ok = int(np.argmax(col_ok))
        within = np.count_nonzero(tx + bounds[2] <= limit_x + 1e-6)  # positions 0 .. within - 1
        if within <= first_ok:
            return None
        # positions right of every occupied cell are free: correlate only up to the first of them
        end = min(self.cells.shape[1], max(self.used_end, first_ok) + w, within - 1 + w)
        overlap = cv2.matchTemplate(self.cells[:, :end], cells, cv2.TM_CCORR)
        free = (overlap < 0.5) & row_ok[:, None] & col_ok[None, : overlap.shape[1]]
        columns = np.nonzero(free.any(axis=0))[0]
        if len(columns) == 0:
            return None
        c = int(columns[0])
        r = int(np.nonzero(free[:, c])[0][0])
        return float(tx[c] + bounds[2]), float(ty[r] + bounds[1]), c, r

    def occupy(self, raster, col: int, row: int) -> tuple[float, float]:
        """Mark the part's cells (here and on the rough grid); its translation (mm) in the strip frame."""
        cells, origin, _ = raster
        self._mark(cells, col, row)
        if self._rough is not None:
            extra = self._rough.pad * COARSE - self.pad
            r, c = row + extra, col + extra
            block = _coarse(np.pad(cells, ((r % COARSE, 0), (c % COARSE, 0))))
            self._rough._mark(block, c // COARSE, r // COARSE)
        return (col - self.pad) * self.pixel - origin[0], (row - self.pad) * self.pixel - origin[1]

    def _mark(self, cells: np.ndarray, col: int, row: int) -> None:
        h, w = cells.shape
        target = self.cells[row : row + h, col : col + w]
        target[...] = np.maximum(target, cells[: target.shape[0], : target.shape[1]])
        occupied = np.nonzero(cells.any(axis=0))[0]
        if len(occupied):
            self.used_end = max(self.used_end, col + int(occupied[-1]) + 1)

    def rough(self) -> "Sheet":
        """The same sheet on a grid of ``COARSE`` times the cell size (a coarse cell is occupied when
        any of its cells is)."""
        if self._rough is None:
            pad = -(-self.pad // COARSE)
            extra = pad * COARSE - self.pad
            pooled = _coarse(np.pad(self.cells, ((extra, 0), (extra, 0))))
            self._rough = Sheet(self.long_side, self.short_side, COARSE * self.pixel, pad, pooled.shape)
            self._rough._mark(pooled, 0, 0)
        return self._rough


def _coarse(cells: np.ndarray) -> np.ndarray:
    """COARSE x COARSE max-pooled occupied cells (a cell is occupied when any of its cells is)."""
    h, w = -(-cells.shape[0] // COARSE) * COARSE, -(-cells.shape[1] // COARSE) * COARSE
    padded = np.zeros((h, w), np.float32)
    padded[: cells.shape[0], : cells.shape[1]] = cells
    return padded.reshape(h // COARSE, COARSE, w // COARSE, COARSE).max(axis=3).max(axis=1)


def _ranked_angles(part: Part, sheet: Sheet, angles: np.ndarray, finalists: int) -> list[float]:
    """The ``finalists`` angles whose placement on the coarse grid ends leftmost (then lowest)."""
    rough = sheet.rough()
    scores = {}
    rasters = part.rasters(angles, rough.pixel, False, sheet.long_side, sheet.short_side)
    # narrowest first: they tend to end leftmost, so the limit below tightens early (speed only)
    for a, raster in sorted(rasters, key=lambda r: r[1][2][2] - r[1][2][0]):
        # an angle can only rank among the finalists by ending no further right than the last of them
        limit = sorted(scores.values())[finalists - 1][0] if len(scores) >= finalists else np.inf
        position = rough.best_position(raster, limit)
        if position:
            scores[a] = (round(position[0], 6), round(position[1], 6))
    ranked = sorted((*scores.get(float(a), (np.inf, np.inf)), float(a)) for a in angles)  # unplaced ones last
    return [a for *_, a in ranked[:finalists]]


def _exact_positions(part: Part, sheet: Sheet, angles, pixel: float) -> list[tuple]:
    """The part's placements on ``sheet``'s fine grid at ``angles`` (in that order, ties to the earlier):
    (right end, bottom, index, angle, raster, column, row), best (leftmost, then lowest) first."""
    found = []
    for n, (a, raster) in enumerate(part.rasters(np.asarray(angles), pixel, True, sheet.long_side, sheet.short_side)):
        position = sheet.best_position(raster, found[0][0] if found else np.inf)
        if position:
            found = sorted(found + [(round(position[0], 6), round(position[1], 6), n, a, raster, *position[2:])],
                           key=lambda f: f[:3])
    return found


def _own_angles(polygon: Polygon, long_side: float, short_side: float) -> np.ndarray:
    """The angles (deg) that lay the part's minimum rotated rectangle along the strip, and the
    middle of the angles at which it fits the sheet (both ways round)."""
    rect = np.asarray(polygon.minimum_rotated_rectangle.exterior.coords)
    edge = rect[1] - rect[0]
    base = -np.degrees(np.arctan2(edge[1], edge[0]))
    fits = fit_angles(polygon, long_side, short_side)
    middle = [fits[len(fits) // 2]] if len(fits) else []
    return np.concatenate([base + np.array([0.0, 90.0, 180.0, 270.0]), middle, np.add(middle, 180.0)])


def raster_nest(parts: list[Part], long_side: float, short_side: float, spacing: float, pixel: float,
                rotations: int, finalists: int, order: list[int],
                beaten_by: tuple[int, float] | None = None) -> list[tuple[int, float, tuple[float, float]]] | None:
    """(sheet, rotation deg, strip translation) per part (made with the same sizes), placing parts
    in ``order``; None as soon as the placement so far is worse than ``beaten_by`` (sheets, extent
    of the last sheet's parts along the strip, mm): placing more parts can only make it worse.

    Each part's angles (``rotations`` evenly spaced ones and its own angles) are first ranked on a
    grid of ``COARSE`` times the cell size; the ``finalists`` best are then placed exactly on the
    fine grid."""
    pad = int(np.ceil((occupied_radius(spacing, pixel) + BUFFER_SLACK_MM) / pixel)) + 2
    even = np.arange(rotations) * (360.0 / rotations)
    sheets: list[Sheet] = []
    extents: list[list[float]] = []  # per sheet: [lowest x, highest x] of its parts' outlines (mm)
    result = {}
    for i in order:
        part = parts[i]
        angles = np.concatenate([even, part.own_angles])
        for k in range(len(sheets) + 1):
            if k == len(sheets):
                sheets.append(Sheet(long_side, short_side, pixel, pad))
                extents.append([np.inf, -np.inf])
            sheet = sheets[k]
            empty = not sheet.cells.any()
            chosen = _ranked_angles(part, sheet, angles, finalists)
            found = _exact_positions(part, sheet, chosen, pixel)
            if not found and empty:  # a tight fit the coarse grid misses: every angle, exactly
                found = _exact_positions(part, sheet, angles, pixel)
            if found:
                *_, a, raster, col, row = found[0]
                result[i] = (k, a, sheet.occupy(raster, col, row))
                bounds, shift = raster[2], result[i][2][0]
                extents[k] = [min(extents[k][0], bounds[0] + shift), max(extents[k][1], bounds[2] + shift)]
                break
            if empty:
                raise ValueError(f"part {i} fits no empty sheet at any of {rotations} rotations")
        if beaten_by is not None and (len(sheets), extents[-1][1] - extents[-1][0]) > beaten_by:
            return None
    return [result[i] for i in range(len(parts))]
