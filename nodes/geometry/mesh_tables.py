"""Edge, adjacency and per-face frame tables of a closed triangle mesh (used by the curve nodes).

Conventions (verified in ``shared/notes/geometry-trivial-connections.md``):

* Faces are CCW seen from outside. Halfedge ``(f, k)`` runs ``F[f, k] -> F[f, (k + 1) % 3]``; it is
  the edge *opposite* corner ``(k + 2) % 3``.
* Edge ``e = (a, b)`` with ``a < b``. ``edge_faces[e, 0]`` is the face containing the halfedge
  ``a -> b`` (left of the edge), ``edge_faces[e, 1]`` the face containing ``b -> a``.
* ``d0`` (edges x vertices): ``d0[e, a] = -1``, ``d0[e, b] = +1``.
* Face frame: ``e1 = (P1 - P0) / |P1 - P0|``, ``e2 = N x e1`` with ``N`` the unit outward normal.
* ``opposite_face[f, i]`` is the face across the edge opposite corner ``i`` of face ``f``;
  ``opposite_corner[f, i]`` is the corner of that neighbour opposite the same edge. Because both
  faces are CCW, neighbour ``g`` with opposite corner ``c`` has ``F[g, c+1] = F[f, i+2]`` and
  ``F[g, c+2] = F[f, i+1]`` (indices mod 3), which is how barycentrics carry over an edge.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse as sp

from ...graph.errors import UserError
from .triangles import zero_area


@dataclasses.dataclass(frozen=True)
class MeshTables:
    """Connectivity and per-face geometry of a closed, manifold, consistently oriented mesh (mm)."""

    vertices: np.ndarray  # (n, 3) float64, mm
    faces: np.ndarray  # (m, 3) int64
    edges: np.ndarray  # (E, 2) int64, a < b
    edge_faces: np.ndarray  # (E, 2) int64, [face with a->b, face with b->a]
    face_edges: np.ndarray  # (m, 3) int64, edge of halfedge (f, k)
    opposite_face: np.ndarray  # (m, 3) int64, neighbour across the edge opposite corner i
    opposite_corner: np.ndarray  # (m, 3) int64, that neighbour's corner opposite the shared edge
    normals: np.ndarray  # (m, 3) float64, unit outward face normals
    areas: np.ndarray  # (m,) float64, mm^2
    frame_e1: np.ndarray  # (m, 3) float64
    frame_e2: np.ndarray  # (m, 3) float64
    corner_angles: np.ndarray  # (m, 3) float64, radians
    bary_gradients: np.ndarray  # (m, 3, 3) float64, row i = grad of barycentric i (1/mm)

    @property
    def euler_characteristic(self) -> int:
        return len(self.vertices) - len(self.edges) + len(self.faces)

    def d0(self) -> sp.csr_matrix:
        """Signed edge-vertex incidence (E x n): -1 at ``a``, +1 at ``b``."""
        e = len(self.edges)
        rows = np.repeat(np.arange(e), 2)
        cols = self.edges.reshape(-1)
        vals = np.tile([-1.0, 1.0], e)
        return sp.csr_matrix((vals, (rows, cols)), shape=(e, len(self.vertices)))

    def dual_adjacency(self) -> sp.csr_matrix:
        """Face-face adjacency (m x m), symmetric, entries 1."""
        m = len(self.faces)
        a, b = self.edge_faces[:, 0], self.edge_faces[:, 1]
        ones = np.ones(2 * len(a))
        return sp.csr_matrix((ones, (np.r_[a, b], np.r_[b, a])), shape=(m, m))

    def points(self, faces: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """3D points (mm) of barycentric coordinates ``bary`` (k, 3) in ``faces`` (k,)."""
        return np.einsum("ki,kij->kj", bary, self.vertices[self.faces[faces]])

    def bary_of_points(self, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Barycentrics of 3D points (k, 3) with respect to ``faces`` (k,), after projecting to the face plane."""
        rel = points - self.vertices[self.faces[faces, 0]]
        bary = np.einsum("kij,kj->ki", self.bary_gradients[faces], rel)
        bary[:, 0] += 1.0
        return bary


def build_tables(vertices: np.ndarray, faces: np.ndarray) -> MeshTables:
    """Tables for a closed, manifold, consistently oriented triangle mesh; ``UserError`` otherwise."""
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    m = len(faces)
    n = len(vertices)
    tail = faces.reshape(-1)
    head = np.roll(faces, -1, axis=1).reshape(-1)
    lo, hi = np.minimum(tail, head), np.maximum(tail, head)
    keys = lo * n + hi
    unique_keys, halfedge_edge, counts = np.unique(keys, return_inverse=True, return_counts=True)
    if np.any(counts != 2):
        bad = int(np.count_nonzero(counts != 2))
        raise UserError(
            f"mesh has {bad} boundary or non-manifold edges; curves need a closed manifold surface: "
            "run mesh.repair (close holes, split non-manifold edges) first"
        )
    edges = np.stack([unique_keys // n, unique_keys % n], axis=1)
    forward = tail < head
    face_of_halfedge = np.repeat(np.arange(m), 3)
    edge_faces = np.full((len(edges), 2), -1, dtype=np.int64)
    edge_faces[halfedge_edge[forward], 0] = face_of_halfedge[forward]
    edge_faces[halfedge_edge[~forward], 1] = face_of_halfedge[~forward]
    if np.any(edge_faces < 0):
        raise UserError(
            "mesh faces are not consistently oriented (an edge is traversed twice in the same "
            "direction): run mesh.repair to re-orient faces coherently"
        )
    face_edges = halfedge_edge.reshape(m, 3)

    # Neighbour across the edge opposite corner i = across halfedge (f, i + 1).
    he_of_corner = face_edges[:, [1, 2, 0]]
    ef = edge_faces[he_of_corner]
    opposite_face = np.where(ef[..., 0] == np.arange(m)[:, None], ef[..., 1], ef[..., 0])
    # In the neighbour, the shared edge is halfedge (g, c + 1) for opposite corner c.
    g_edges = face_edges[opposite_face]  # (m, 3, 3): edges of the neighbour's halfedges
    k = np.argmax(g_edges == he_of_corner[..., None], axis=2)
    opposite_corner = (k + 2) % 3

    p0, p1, p2 = (vertices[faces[:, i]] for i in range(3))
    cross = np.cross(p1 - p0, p2 - p0)
    double_area = np.linalg.norm(cross, axis=1)
    if np.any(zero_area(double_area)):
        raise UserError("mesh has degenerate (zero-area) faces: run mesh.repair or mesh.remesh first")
    normals = cross / double_area[:, None]
    e1 = (p1 - p0) / np.linalg.norm(p1 - p0, axis=1)[:, None]
    e2 = np.cross(normals, e1)
    corners = np.stack([p0, p1, p2], axis=1)
    nxt = np.roll(corners, -1, axis=1) - corners
    prv = np.roll(corners, 1, axis=1) - corners
    cos = np.einsum("fkj,fkj->fk", nxt, prv)
    sin = np.linalg.norm(np.cross(nxt, prv), axis=2)
    corner_angles = np.arctan2(sin, cos)
    # grad lambda_i = N x (P_{i+2} - P_{i+1}) / (2A)
    opposite_edge = np.roll(corners, -2, axis=1) - np.roll(corners, -1, axis=1)
    bary_gradients = np.cross(normals[:, None, :], opposite_edge) / double_area[:, None, None]
    return MeshTables(
        vertices=vertices,
        faces=faces,
        edges=edges,
        edge_faces=edge_faces,
        face_edges=face_edges,
        opposite_face=opposite_face,
        opposite_corner=opposite_corner,
        normals=normals,
        areas=0.5 * double_area,
        frame_e1=e1,
        frame_e2=e2,
        corner_angles=corner_angles,
        bary_gradients=bary_gradients,
    )


def angle_defects(tables: MeshTables) -> np.ndarray:
    """Gaussian curvature per vertex as angle defect ``2 pi - sum of corner angles`` (radians)."""
    total = np.bincount(tables.faces.reshape(-1), weights=tables.corner_angles.reshape(-1), minlength=len(tables.vertices))
    return 2.0 * np.pi - total


def edge_transport(tables: MeshTables) -> np.ndarray:
    """Levi-Civita transport angle per edge: angle ``a`` in ``edge_faces[e, 0]`` maps to ``a + rho[e]`` in ``edge_faces[e, 1]``."""
    u = tables.vertices[tables.edges[:, 1]] - tables.vertices[tables.edges[:, 0]]
    theta = []
    for side in (0, 1):
        f = tables.edge_faces[:, side]
        theta.append(np.arctan2(np.einsum("ej,ej->e", u, tables.frame_e2[f]), np.einsum("ej,ej->e", u, tables.frame_e1[f])))
    return theta[1] - theta[0]


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles wrapped to ``[-pi, pi)``."""
    return (a + np.pi) % (2.0 * np.pi) - np.pi
