"""Cutter mats: cut areas (mm) and the usable area inside a margin, shared by outline (split to fit)
and nesting (place on the mat)."""
from __future__ import annotations

import numpy as np
from shapely.geometry import Polygon

MATS_MM = {"12x12": (292.1, 292.1), "12x24": (292.1, 596.9)}
"""Cut areas (width, height) in mm, smallest first (the order ``mat: auto`` tries them): Cricut's
published maximum cut size on a mat is 11.5 x 11.5 in on the 12 x 12 in mat and 11.5 x 23.5 in on
the 12 x 24 in mat (Explore / Maker); Silhouette's Cameo mats of the same nominal sizes cut at least
that much, so these sheets fit both."""

MARGIN_MM = 1.0
"""Default empty border inside the cut area (mm)."""


def usable_sides(width: float, height: float, margin: float) -> tuple[float, float]:
    """(long, short) sides (mm) of a sheet's usable area inside ``margin``."""
    return max(width, height) - 2 * margin, min(width, height) - 2 * margin


def fit_angles(polygon: Polygon, long_side: float, short_side: float) -> np.ndarray:
    """Rotations (deg, 0.5 deg grid over a half turn) at which the polygon's bounding box fits
    long x short."""
    return points_fit_angles(np.asarray(polygon.convex_hull.exterior.coords), long_side, short_side)


def points_fit_angles(points: np.ndarray, long_side: float, short_side: float) -> np.ndarray:
    """Rotations (deg, 0.5 deg grid over a half turn) at which the points' bounding box fits long x short."""
    angles = np.radians(np.arange(0.0, 180.0, 0.5))
    c, s = np.cos(angles), np.sin(angles)
    x = np.outer(c, points[:, 0]) - np.outer(s, points[:, 1])
    y = np.outer(s, points[:, 0]) + np.outer(c, points[:, 1])
    fits = (np.ptp(x, axis=1) <= long_side) & (np.ptp(y, axis=1) <= short_side)
    return np.degrees(angles[fits])
