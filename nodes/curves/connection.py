"""``curves.connection``: trivial connection with prescribed singularities and its per-face field.

Crane, Desbrun, Schröder 2010 "Trivial Connections on Discrete Surfaces", with the sign conventions
verified in ``shared/notes/geometry-trivial-connections.md`` (see :mod:`retrotouch.nodes.geometry.mesh_tables`):

* unknown ``x[e]`` rotates a direction crossing dual edge ``e`` from ``edge_faces[e, 0]`` to
  ``edge_faces[e, 1]`` on top of Levi-Civita transport ``rho[e]`` (the reverse crossing applies
  ``-(rho + x)``);
* holonomy constraint per vertex star: ``d0^T x = -K + 2 pi k`` with ``K`` the angle defect and ``k``
  the prescribed index (``sum k = chi = 2``);
* least-norm solution ``x = d0 beta`` with ``(d0^T d0) beta = -K + 2 pi k`` (graph Laplacian, one
  vertex pinned), solved by a sparse Cholesky factorisation (:mod:`retrotouch.nodes.geometry.sparse_spd`);
* field by transport over a BFS tree of the dual graph: ``alpha_g = alpha_f + s (rho_e + x_e)``,
  ``s = +1`` when ``f = edge_faces[e, 0]``;
* realized index per vertex ``(d0^T wrap(alpha[EF1] - alpha[EF0] - rho) + K) / 2 pi``; it must equal
  the prescribed index everywhere, otherwise the node fails.

Layers: Tx has index +1 at the base centre and +1 at the far vertex; the global rotation of the
field is chosen so it points away from the far vertex (a source there, a sink at the base). Rx has a
dipole: +1 at each of the two adjacent ``base_dipole`` vertices; the field points away from
``base_dipole[0]`` (the source) and into ``base_dipole[1]``.
"""
from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np
import scipy.sparse.csgraph as csgraph

from ...graph.errors import UserError
from ...graph.node import NodeParams, node
from ..data.types import Mesh
from ..geometry.mesh_tables import MeshTables, angle_defects, build_tables, edge_transport, wrap_angle
from ..geometry.sparse_spd import spd_solve


@dataclasses.dataclass(frozen=True)
class DirectionField:
    """A unit direction per face from a trivial connection (module conventions; lengths mm, angles rad).

    ``face_angle[f]`` is measured in the face frame (``e1 = (P1 - P0)/|.|``, ``e2 = N x e1``);
    ``face_direction[f] = cos a e1 + sin a e2``. ``start_vertex`` is the singularity curves start from
    (Tx: far vertex; Rx: the dipole source) and ``start_distance`` the geodesic (heat method)
    distance of every vertex from it; ``stop_distance`` is the distance from the singularities
    curves end at (Tx: the base centre; Rx: both dipole vertices). Both come with the regions
    (``regions.detect`` computes them with its distance solver).
    """

    layer: str  # "tx" or "rx"
    singular_vertices: np.ndarray  # (S,) int64
    singular_indices: np.ndarray  # (S,) int64, prescribed
    singular_points: np.ndarray  # (S, 3) float64, mm
    realized_index: np.ndarray  # (n,) int64, realized index per vertex
    edges: np.ndarray  # (E, 2) int64, a < b
    edge_faces: np.ndarray  # (E, 2) int64
    connection_angle: np.ndarray  # (E,) float64, x_e (rad)
    face_angle: np.ndarray  # (m,) float64, alpha_f (rad)
    face_direction: np.ndarray  # (m, 3) float64, unit, in the face plane
    start_vertex: int
    start_distance: np.ndarray  # (n,) float64, mm
    stop_distance: np.ndarray  # (n,) float64, mm, geodesic distance from the singularities curves stop at

    def singular_distance(self) -> np.ndarray:
        """Geodesic distance (mm) of every vertex from the nearest singularity of this field."""
        return np.minimum(self.start_distance, self.stop_distance)

    @property
    def indices_ok(self) -> bool:
        prescribed = np.zeros_like(self.realized_index)
        prescribed[self.singular_vertices] = self.singular_indices
        return bool(np.array_equal(prescribed, self.realized_index))


class ConnectionParams(NodeParams):
    layer: Literal["tx", "rx"] = "tx"


def genus_check(tables: MeshTables) -> None:
    """``UserError`` unless the closed mesh is one connected genus-0 surface."""
    components = csgraph.connected_components(tables.dual_adjacency(), directed=False)[0]
    if components != 1:
        raise UserError(f"mesh has {components} connected components; keep the largest one (mesh.repair) before computing curves")
    chi = tables.euler_characteristic
    if chi != 2:
        genus = (2 - chi) // 2
        raise UserError(
            f"mesh has genus {genus} (Euler characteristic {chi}); the curve layout needs a genus-0 surface: "
            "close the handles or through-holes of the object in the scan before running"
        )


def solve_connection(tables: MeshTables, singular_vertices: np.ndarray, singular_indices: np.ndarray) -> np.ndarray:
    """Least-norm dual-edge angles ``x`` (E,) with vertex holonomy matching the prescribed indices."""
    n = len(tables.vertices)
    k = np.zeros(n)
    np.add.at(k, singular_vertices, singular_indices)
    if int(k.sum()) != tables.euler_characteristic:
        raise UserError(f"singularity indices sum to {int(k.sum())} but must equal the Euler characteristic {tables.euler_characteristic}")
    rhs = -angle_defects(tables) + 2.0 * np.pi * k
    d0 = tables.d0().tocsc()
    laplacian = (d0.T @ d0).tocsc()
    beta = np.zeros(n)
    beta[1:] = spd_solve(laplacian[1:, 1:], rhs[1:])
    return d0 @ beta


def transport_field(tables: MeshTables, x: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """Face angles from face 0 (angle 0) by transport with ``rho + x`` over a BFS tree of the dual graph."""
    m = len(tables.faces)
    order, pred = csgraph.breadth_first_order(tables.dual_adjacency(), 0, directed=False, return_predecessors=True)
    if len(order) != m:
        raise UserError("mesh faces are not all connected; keep the largest component (mesh.repair) first")
    child = order[1:]
    parent = pred[child]
    # the edge shared by parent and child, and the sign of the crossing parent -> child
    which = np.argmax(tables.opposite_face[child] == parent[:, None], axis=1)
    edge = tables.face_edges[child, (which + 1) % 3]
    sign = np.where(tables.edge_faces[edge, 0] == parent, 1.0, -1.0)
    step = np.zeros(m)
    step[child] = sign * (rho[edge] + x[edge])
    # accumulate along the tree in BFS order (parents first); plain lists are fastest for this loop
    alpha = [0.0] * m
    step_list = step.tolist()
    parent_list = pred.tolist()
    for f in child.tolist():
        alpha[f] = alpha[parent_list[f]] + step_list[f]
    return np.asarray(alpha)


def realized_indices(tables: MeshTables, alpha: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """Index per vertex of the face field ``alpha`` (integers; nonzero only at singularities)."""
    ef = tables.edge_faces
    jump = wrap_angle(alpha[ef[:, 1]] - alpha[ef[:, 0]] - rho)
    total = tables.d0().T @ jump + angle_defects(tables)
    return np.rint(total / (2.0 * np.pi)).astype(np.int64)


def radial_offset(tables: MeshTables, alpha: np.ndarray, vertex: int, exclude_vertex: int | None = None) -> float:
    """Circular mean of (field angle - angle of the direction away from ``vertex``) over its one-ring faces."""
    ring = np.flatnonzero(np.any(tables.faces == vertex, axis=1))
    if exclude_vertex is not None:
        keep = ~np.any(tables.faces[ring] == exclude_vertex, axis=1)
        ring = ring[keep] if np.any(keep) else ring
    centroid = tables.vertices[tables.faces[ring]].mean(axis=1)
    away = centroid - tables.vertices[vertex]
    away_angle = np.arctan2(np.einsum("kj,kj->k", away, tables.frame_e2[ring]), np.einsum("kj,kj->k", away, tables.frame_e1[ring]))
    d = alpha[ring] - away_angle
    return float(np.arctan2(np.sin(d).sum(), np.cos(d).sum()))


def singularities_for(layer: str, regions) -> tuple[np.ndarray, np.ndarray, int, int | None]:
    """Prescribed singular vertices, indices, start vertex and the vertex to ignore when aligning."""
    if layer == "tx":
        vertices = np.array([int(regions.base_centre), int(regions.far_vertex)], dtype=np.int64)
        if vertices[0] == vertices[1]:
            raise UserError("base centre and far vertex coincide: the base region covers the whole object; check the up axis")
        return vertices, np.array([1, 1], dtype=np.int64), int(regions.far_vertex), None
    dipole = np.asarray(regions.base_dipole, dtype=np.int64)
    return dipole, np.array([1, 1], dtype=np.int64), int(dipole[0]), int(dipole[1])


def compute_field(tables: MeshTables, layer: str, regions) -> DirectionField:
    """The layer's direction field; ``UserError`` if the realized indices differ from the prescribed ones."""
    genus_check(tables)
    singular_vertices, singular_indices, start, other = singularities_for(layer, regions)
    x = solve_connection(tables, singular_vertices, singular_indices)
    rho = edge_transport(tables)
    alpha = transport_field(tables, x, rho)
    alpha = wrap_angle(alpha - radial_offset(tables, alpha, start, other))
    realized = realized_indices(tables, alpha, rho)
    prescribed = np.zeros(len(tables.vertices), dtype=np.int64)
    prescribed[singular_vertices] = singular_indices
    wrong = np.flatnonzero(realized != prescribed)
    if len(wrong):
        raise UserError(
            f"{layer} direction field realizes index {realized[wrong[:5]].tolist()} at vertices {wrong[:5].tolist()} "
            f"({len(wrong)} vertices differ from the prescribed singularities): remesh the surface (mesh.remesh) to remove "
            "degenerate triangles"
        )
    direction = np.cos(alpha)[:, None] * tables.frame_e1 + np.sin(alpha)[:, None] * tables.frame_e2
    if layer == "tx":  # from the far vertex to the base centre
        distance, stop_distance = regions.far_distance_mm, regions.centre_distance_mm
    else:  # from the dipole's first vertex (the base centre) to either of its vertices
        distance, stop_distance = regions.centre_distance_mm, regions.dipole_distance_mm
    return DirectionField(
        layer=layer,
        singular_vertices=singular_vertices,
        singular_indices=singular_indices,
        singular_points=tables.vertices[singular_vertices],
        realized_index=realized,
        edges=tables.edges,
        edge_faces=tables.edge_faces,
        connection_angle=x,
        face_angle=alpha,
        face_direction=direction,
        start_vertex=start,
        start_distance=distance,
        stop_distance=stop_distance,
    )


@node("curves.connection", params=ConnectionParams, inputs=("mesh", "regions"), outputs=("field",))
def connection(params: ConnectionParams, mesh: Mesh, regions) -> DirectionField:
    """Trivial connection and per-face direction field of one layer (Tx: base centre + far vertex; Rx: base dipole)."""
    return compute_field(build_tables(mesh.vertices, mesh.faces), params.layer, regions)
