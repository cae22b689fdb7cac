"""The Tx pole's choices for ``regions.detect`` (see its module docstring): the far pole, with its
rule for near ties, the top pole and the geodesic centre of the free region. Distances mm, heights mm
along up."""
from __future__ import annotations

import numpy as np

from .faces import FaceGraph

CENTRE_SAMPLES = 16
"""Farthest-point samples of the free region whose largest distance the centre Tx pole minimises."""

FAR_TIE_SHARE = 0.05
"""Peaks of the distance from the base within this share of the farthest tie for the far Tx pole ..."""
FAR_TIE_RISE = 0.25
"""... and the highest of them is the pole when it stands higher than the farthest by this share of
the object's height."""
TOP_TIE_SHARE = 0.01
"""Peaks within this share of the object's height below the highest tie for the top Tx pole."""


def farthest_pole(graph: FaceGraph, reach: np.ndarray, free: np.ndarray, height: np.ndarray) -> int:
    """The far Tx pole: the free vertex farthest from the base (``reach``, mm), or, of the peaks of
    ``reach`` (no neighbour farther) within ``FAR_TIE_SHARE`` of it, the highest (``height``, mm above
    the table) when it stands ``FAR_TIE_RISE`` of the object's height above it. A standing figure's
    second foot can lie as far from the base as its head, and a pole on it would send every Tx line
    up from the floor; peaks of about one height (a lying object's ends) keep the farthest."""
    farthest = int(free[np.argmax(reach[free])])
    summits = peaks(graph, reach, free)
    near = summits[reach[summits] >= (1.0 - FAR_TIE_SHARE) * reach[farthest]]
    highest = int(near[np.argmax(height[near])]) if len(near) else farthest
    rises = height[highest] - height[farthest] > FAR_TIE_RISE * (height.max() - height.min())
    return highest if rises else farthest


def peaks(graph: FaceGraph, values: np.ndarray, among: np.ndarray) -> np.ndarray:
    """The vertices of ``among`` that no neighbour exceeds in ``values``."""
    neighbour = np.full(len(values), -np.inf)
    np.maximum.at(neighbour, graph.halfedges[:, 0], values[graph.halfedges[:, 1]])
    return among[values[among] >= neighbour[among]]


def top_pole(graph: FaceGraph, reach: np.ndarray, free: np.ndarray, height: np.ndarray) -> int:
    """The top Tx pole: the highest of the free peaks of ``reach`` (the distance from the base, mm; no
    neighbour farther), of those within ``TOP_TIE_SHARE`` of the object's height below it the farthest
    from the base. On a standing figure whose hand or tail lies farther from the base than its head,
    the far pole sends every Tx line down that thin limb; the head sends them down the body."""
    candidates = peaks(graph, reach, free)
    if len(candidates) == 0:  # every free vertex has a farther neighbour outside the free region
        candidates = free
    top = height[candidates].max()
    tied = candidates[height[candidates] >= top - TOP_TIE_SHARE * (height.max() - height.min())]
    return int(tied[np.argmax(reach[tied])])


def geodesic_centre(solver, free: np.ndarray, first: int, from_first: np.ndarray) -> int:
    """The vertex of ``free`` minimising the largest geodesic distance (mm) to ``CENTRE_SAMPLES``
    farthest-point samples of ``free``, the first being ``first`` (with distances ``from_first``)."""
    nearest, largest = from_first[free], from_first[free]
    for _ in range(CENTRE_SAMPLES - 1):
        distance = solver.compute_distance(int(free[np.argmax(nearest)]))[free]
        nearest, largest = np.minimum(nearest, distance), np.maximum(largest, distance)
    return int(free[np.argmin(largest)])


def tx_pole(kind: str, graph: FaceGraph, reach: np.ndarray, free: np.ndarray, height: np.ndarray,
            solver) -> tuple[int, np.ndarray]:
    """The Tx pole of ``kind`` ("far", "top" or "centre", as ``regions.detect``'s ``tx_pole``) and its
    geodesic distance to every vertex (mm, from the heat-method ``solver``)."""
    vertex = (top_pole if kind == "top" else farthest_pole)(graph, reach, free, height)
    distance = solver.compute_distance(vertex)
    if kind == "centre":
        vertex = geodesic_centre(solver, free, vertex, distance)
        distance = solver.compute_distance(vertex)
    return vertex, distance
