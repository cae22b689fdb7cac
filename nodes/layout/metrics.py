"""Layout quality metrics (paper Table 1): Voronoi uniformity of the pads and friends.

Voronoi CV: every sensing face is assigned to the pad geodesically nearest to its centroid (the
centroid value of the P1-interpolated heat-method distance field of each pad); the cell area of a
pad is the summed area of its faces; CV = population std / mean of the cell areas (0 for a perfectly
regular layout). Distances and lengths in mm, areas in mm^2.
"""
from __future__ import annotations

import numpy as np

from ..geometry.triangles import areas, corners


def voronoi_cell_areas(
    pad_fields: np.ndarray, vertices: np.ndarray, faces: np.ndarray, face_mask: np.ndarray
) -> np.ndarray:
    """Cell area (mm^2) per pad; ``pad_fields`` (n_vertices, P) are the pads' distance fields."""
    P = pad_fields.shape[1]
    idx = np.flatnonzero(face_mask)
    centroid_distance = pad_fields[faces[idx]].mean(axis=1)  # (m_s, P)
    owner = np.argmin(centroid_distance, axis=1)
    return np.bincount(owner, weights=areas(corners(vertices, faces[idx])), minlength=P)


def coefficient_of_variation(values: np.ndarray) -> float:
    """Population standard deviation over mean."""
    values = np.asarray(values, dtype=np.float64)
    return float(values.std() / values.mean())


def min_pairwise(distance_mm: np.ndarray) -> float:
    """Smallest off-diagonal entry of a symmetric distance matrix (inf for fewer than 2 points)."""
    if len(distance_mm) < 2:
        return float("inf")
    return float(distance_mm[np.triu_indices(len(distance_mm), k=1)].min())
