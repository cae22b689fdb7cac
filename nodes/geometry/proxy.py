"""A coarser copy of a closed triangle mesh for solves whose answers are smooth on the copy's scale,
and the maps between the two (conventions: :mod:`.triangles`; mm).

A solve on the copy costs what it costs at the copy's size however fine the mesh: a vertex function on
the copy reaches the mesh through :attr:`Proxy.interpolation`, each mesh vertex taking the value at its
closest point on the copy (on the copy's side that faces the way the vertex does, so that the two sides
of a thin part stay apart).
"""
from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np

from ...graph.errors import UserError
from .triangles import vertex_normals

if TYPE_CHECKING:
    from .surface import SurfaceProjector  # compiled with numba: imported when a copy is made

PROXY_VERTICES = 30_000
"""Above this many vertices the geodesic solves run on a decimated copy: their cost (sparse
factorisations) then stops growing with the mesh, while the heat method's own error is about an edge
of the mesh it runs on (the 170 mm bunny's copy: 1.1 mm, finer than the default 20,000-vertex mesh's
1.3 mm)."""

LOCATE_CHUNK = 20_000
"""Points located on the copy at once (bounds the ``(points, candidates, 3)`` temporaries)."""


def closest_on(projector: "SurfaceProjector", points: np.ndarray, facing: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(faces (k,), barycentrics (k, 3))`` of the closest points to ``points`` (k, 3) on the
    projector's mesh, on faces whose normal points the way of the unit ``facing`` (k, 3) where any
    near one does."""
    found_faces, found_bary = [], []
    for start in range(0, len(points), LOCATE_CHUNK):
        window = slice(start, start + LOCATE_CHUNK)
        _, face, bary = projector.project(points[window], facing[window])
        found_faces.append(face)
        found_bary.append(bary)
    return np.concatenate(found_faces).astype(np.int64), np.concatenate(found_bary)


@dataclasses.dataclass(frozen=True)
class Proxy:
    """The copy ``(vertices (p, 3) mm, faces (q, 3))``, ``interpolation`` the scipy CSR ``(n, p)`` that
    takes a copy vertex function to the mesh's ``n`` vertices, and ``projector`` its closest points."""

    vertices: np.ndarray
    faces: np.ndarray
    interpolation: object
    projector: "SurfaceProjector"

    def locate(self, points: np.ndarray, facing: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:func:`closest_on` the copy."""
        return closest_on(self.projector, points, facing)


def proxy_of(vertices: np.ndarray, faces: np.ndarray, target_vertices: int) -> Proxy | None:
    """The closed mesh ``(vertices, faces)`` decimated to about ``target_vertices`` by quadric edge
    collapse (fast-simplification), with its maps; None when the collapse changed the surface's
    topology (a hole, a lost handle, a flipped face), left a face of zero area or a vertex unused, where only
    the mesh itself will do."""
    import fast_simplification  # imported when a mesh is large enough to need a copy
    import scipy.sparse as sp

    from .mesh_tables import build_tables
    from .surface import SurfaceProjector

    vertices = np.array(vertices, dtype=np.float64, order="C")
    faces = np.array(faces, dtype=np.int64, order="C")
    coarse_vertices, coarse_faces = fast_simplification.simplify(vertices, faces, target_count=2 * target_vertices)
    coarse_faces = np.asarray(coarse_faces, dtype=np.int64)
    try:  # closed, manifold, consistently oriented, no face of zero area
        coarse_chi = build_tables(coarse_vertices, coarse_faces).euler_characteristic
    except UserError:
        return None
    chi = np.count_nonzero(np.bincount(faces.ravel(), minlength=len(vertices))) - len(faces) // 2  # V - F / 2, closed
    if coarse_chi != chi or not np.bincount(coarse_faces.ravel(), minlength=len(coarse_vertices)).all():
        return None
    projector = SurfaceProjector(np.ascontiguousarray(coarse_vertices, dtype=np.float64), coarse_faces)
    face, bary = closest_on(projector, vertices, vertex_normals(vertices, faces))
    rows = np.repeat(np.arange(len(vertices)), 3)
    interpolation = sp.csr_matrix((bary.ravel(), (rows, coarse_faces[face].ravel())),
                                  shape=(len(vertices), len(coarse_vertices)))
    return Proxy(projector.vertices, coarse_faces, interpolation, projector)
