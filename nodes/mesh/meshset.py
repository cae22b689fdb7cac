"""pymeshlab MeshSets to and from ``(V, F)`` arrays, and face components: shared by ``mesh.repair``
and ``mesh.check_topology``."""
from __future__ import annotations

import numpy as np
import pymeshlab
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components


def to_meshset(vertices: np.ndarray, faces: np.ndarray) -> pymeshlab.MeshSet:
    """A pymeshlab MeshSet holding one mesh."""
    meshset = pymeshlab.MeshSet()
    meshset.add_mesh(
        pymeshlab.Mesh(
            vertex_matrix=np.ascontiguousarray(vertices, dtype=np.float64),
            face_matrix=np.ascontiguousarray(faces, dtype=np.int32),
        )
    )
    return meshset


def from_meshset(meshset: pymeshlab.MeshSet) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices float64 contiguous, faces int64 contiguous)`` of the current mesh.

    pymeshlab returns a non-contiguous float64 vertex matrix and an int32 face matrix.
    """
    current = meshset.current_mesh()
    vertices = np.ascontiguousarray(current.vertex_matrix(), dtype=np.float64)
    faces = np.ascontiguousarray(current.face_matrix(), dtype=np.int64)
    return vertices, faces


def face_components(faces: np.ndarray, vertex_count: int) -> tuple[int, np.ndarray]:
    """Connected components of faces sharing a vertex: ``(count, label per face)``."""
    m = len(faces)
    rows = np.repeat(np.arange(m), 3)
    incidence = coo_matrix((np.ones(3 * m), (rows, faces.ravel())), shape=(m, vertex_count)).tocsr()
    count, vertex_labels = connected_components(incidence.T @ incidence, directed=False)
    return count, vertex_labels[faces[:, 0]]
