"""Contact areas of touches (see :mod:`.processing`, step 3): cell deltas interpolated over the
vertices of a simplified copy of the mesh, connected components above the off threshold, split among
the touch peaks; each part's intensity- and area-weighted centroid and its contact area.

Units: mm, mm^2, counts.
"""
from __future__ import annotations

from typing import Any

import numba
import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from ..data.sensing_map import SensingMap
from ..geometry.triangles import vertex_areas


def processing_mesh(vertices: np.ndarray, faces: np.ndarray, target_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """A simplified copy of the mesh (quadric edge collapse, topology kept) for contact areas; the
    mesh itself when it is already small enough."""
    if len(faces) <= target_faces:
        return vertices, faces
    import pymeshlab

    meshes = pymeshlab.MeshSet()
    meshes.add_mesh(pymeshlab.Mesh(vertices, faces))
    meshes.meshing_decimation_quadric_edge_collapse(targetfacenum=target_faces, preservetopology=True,
                                                   preservenormal=True, planarquadric=True)
    simplified = meshes.current_mesh()
    return simplified.vertex_matrix().astype(np.float64), simplified.face_matrix().astype(np.int64)


class ContactAreas:
    """The contact mesh of a sensing map (``contact_vertices``, ``contact_faces``), its vertex areas
    and edges, and the cell -> vertex interpolation ``vertex_to_cell`` (vertices x cells, sparse)."""

    def __init__(self, sensing_map: SensingMap, target_faces: int, interpolation_radius: float, pitch: float):
        self.map = sensing_map
        self.contact_vertices, self.contact_faces = processing_mesh(sensing_map.vertices, sensing_map.faces,
                                                                    target_faces)
        self.areas = vertex_areas(self.contact_vertices, self.contact_faces)
        edges = self.contact_faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
        source, target = np.unique(np.concatenate([edges, edges[:, ::-1]]), axis=0).T  # sorted by source
        degree = np.bincount(source, minlength=len(self.contact_vertices))
        # (max degree, n): row j holds each contact vertex's j-th mesh neighbour, padded with the vertex itself.
        self.neighbour_rows = np.repeat(np.arange(len(degree))[None], max(int(degree.max()), 1), axis=0)
        self.neighbour_rows[np.arange(len(source)) - (np.cumsum(degree) - degree)[source], source] = target
        self.vertex_to_cell = self._interpolation(interpolation_radius, pitch / 2)
        _component_labels(self.neighbour_rows, np.zeros(len(degree), dtype=bool), np.zeros(0, dtype=np.intp))  # compiles now, not at the first touch

    def _interpolation(self, radius: float, bandwidth: float) -> sp.csr_matrix:
        """Sparse Nadaraya-Watson weights from cells to the vertices within ``radius`` of a cell
        (Gaussian kernel of ``bandwidth``, mm)."""
        vertices = self.contact_vertices
        cell_tree = cKDTree(self.map.cell_points)
        pairs = cell_tree.sparse_distance_matrix(cKDTree(vertices), radius, output_type="coo_matrix")
        weights = np.exp(-(pairs.data**2) / (2 * bandwidth**2))
        cell_to_vertex = sp.csr_matrix((weights, (pairs.row, pairs.col)), shape=(self.map.cell_count, len(vertices)))
        totals = np.asarray(cell_to_vertex.sum(axis=0)).ravel()
        return sp.csr_matrix(cell_to_vertex.T.multiply(1.0 / np.maximum(totals, 1e-300)[:, None]))

    def parts(self, peaks: np.ndarray, delta: np.ndarray, floor: float) -> list[list[Any]]:
        """One entry ``[cell, None, None, None, area_mm2, centroid]`` per peak cell (strongest first)
        whose part of the contact area above ``floor`` (counts) is not empty: each vertex belongs to
        the nearest peak of its own component (components without a peak drop); a peak's component is
        its nearest vertex's. The centroid weighs vertices by area x (intensity - floor); the area is
        that of the vertices at or above half the part's peak intensity."""
        field = self.vertex_to_cell @ np.maximum(delta, 0.0)
        inside = field > floor
        region = np.flatnonzero(inside)
        if len(region) == 0:
            return []
        field = field[region]
        labels = _component_labels(self.neighbour_rows, inside, region)
        vertices = self.contact_vertices[region]
        peak_points = self.map.cell_points[peaks]
        d2 = np.sum((vertices[:, None] - peak_points[None]) ** 2, axis=2)
        peak_label = labels[np.argmin(d2, axis=0)]
        d2[labels[:, None] != peak_label[None]] = np.inf
        owner = np.argmin(d2, axis=1)
        owned = np.isfinite(d2[np.arange(len(region)), owner])
        found = []
        areas = self.areas[region]
        for j, cell in enumerate(peaks.tolist()):
            mine = np.flatnonzero(owned & (owner == j))
            if len(mine) == 0:
                continue
            mine_field, mine_areas = field[mine], areas[mine]
            weights = mine_areas * (mine_field - floor)
            centroid = weights @ vertices[mine] / weights.sum()
            area = float(mine_areas[mine_field >= 0.5 * mine_field.max()].sum())
            found.append([cell, None, None, None, area, centroid])
        return found


@numba.njit(cache=True)
def _component_labels(neighbour_rows: np.ndarray, inside: np.ndarray, region: np.ndarray) -> np.ndarray:
    """Connected-component labels of the contact vertices ``region`` (= ``flatnonzero(inside)``)
    over the mesh edges between them (``neighbour_rows``: row j holds each vertex's j-th neighbour,
    padded with the vertex itself): each label is the smallest region index of its component (a
    depth-first walk from each vertex not yet reached, in region order)."""
    local = np.full(len(inside), -1, dtype=np.int64)  # index in region (of the vertices inside)
    for i in range(len(region)):
        local[region[i]] = i
    labels = np.full(len(region), -1, dtype=np.int64)
    stack = np.empty(len(region), dtype=np.int64)
    for start in range(len(region)):
        if labels[start] >= 0:
            continue
        labels[start] = start
        stack[0] = start
        top = 1
        while top > 0:
            top -= 1
            vertex = region[stack[top]]
            for j in range(neighbour_rows.shape[0]):
                k = local[neighbour_rows[j, vertex]]
                if k >= 0 and labels[k] < 0:
                    labels[k] = start
                    stack[top] = k
                    top += 1
    return labels
