"""Face adjacency of a closed triangle mesh: halfedges, edge-connected components, vertex masks."""
from __future__ import annotations

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components


class FaceGraph:
    """Halfedge adjacency of a closed triangle mesh.

    Halfedge ``h = 3 f + k`` runs ``faces[f, k] -> faces[f, (k + 1) % 3]``; ``opposite[h]`` is the
    halfedge running the other way (-1 on a boundary).
    """

    def __init__(self, faces: np.ndarray, vertex_count: int) -> None:
        self.faces = faces
        self.vertex_count = vertex_count
        self.halfedges = np.stack([faces, np.roll(faces, -1, axis=1)], axis=2).reshape(-1, 2)
        keys = self.halfedges[:, 0] * vertex_count + self.halfedges[:, 1]
        order = np.argsort(keys)
        wanted = self.halfedges[:, 1] * vertex_count + self.halfedges[:, 0]
        position = np.clip(np.searchsorted(keys[order], wanted), 0, len(keys) - 1)
        found = keys[order][position] == wanted
        self.opposite = np.where(found, order[position], -1)
        inner = np.flatnonzero(self.opposite >= 0)
        self.pairs = np.stack([inner // 3, self.opposite[inner] // 3], axis=1)  # sorted by first face

    def components(self, mask: np.ndarray) -> np.ndarray:
        """Edge-connected component label of each face in ``mask`` (-1 outside)."""
        m = len(self.faces)
        pairs = self.pairs[mask[self.pairs[:, 0]] & mask[self.pairs[:, 1]]]
        row_starts = np.r_[0, np.cumsum(np.bincount(pairs[:, 0], minlength=m))]  # CSR rows: the pairs are sorted
        graph = csr_matrix((np.ones(len(pairs), dtype=np.int8), pairs[:, 1], row_starts), shape=(m, m))
        labels = connected_components(graph, directed=False)[1]
        return np.where(mask, labels, -1)

    def halfedges_between(self, inside: np.ndarray, outside: np.ndarray) -> np.ndarray:
        """Indices of the halfedges of faces in ``inside`` whose opposite face is in ``outside``."""
        h = np.flatnonzero(inside[np.arange(len(self.halfedges)) // 3] & (self.opposite >= 0))
        return h[outside[self.opposite[h] // 3]]

    def vertex_masks(self, face_mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(touched by a face in mask, touched by a face outside mask)`` per vertex."""
        inside = np.zeros(self.vertex_count, dtype=bool)
        outside = np.zeros(self.vertex_count, dtype=bool)
        inside[self.faces[face_mask].ravel()] = True
        outside[self.faces[~face_mask].ravel()] = True
        return inside, outside

    def has_interior_edge(self, face_mask: np.ndarray) -> bool:
        """Whether two adjacent vertices touch only faces in ``face_mask`` (room for the Rx dipole)."""
        inside, outside = self.vertex_masks(face_mask)
        return bool((inside & ~outside)[self.halfedges].all(axis=1).any())

    def ring(self, face_mask: np.ndarray) -> np.ndarray:
        """``face_mask`` plus every face sharing a vertex with it."""
        inside, _ = self.vertex_masks(face_mask)
        return inside[self.faces].any(axis=1)
