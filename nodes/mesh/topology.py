"""``mesh.check_topology``: make sure the surface is what the layout method needs.

The trivial-connection layout needs one closed, manifold, coherently and outwardly oriented
genus-0 surface. The check measures components, boundary edges and holes, non-manifold edges and
vertices, orientation, the Euler characteristic / genus and the mean thickness (a flat sheet, such
as a 2D outline closed into a double layer, has none), and fails with one line that says what is
wrong and what to do.
"""
from __future__ import annotations

import numpy as np
from pydantic import Field
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ...graph.errors import UserError
from ...graph.node import NodeParams, node
from ..data.types import Mesh
from ..geometry.triangles import corners, cross_products, signed_volume, zero_area
from .meshset import face_components, to_meshset

RECONSTRUCTED = "reconstructed a closed surface from"
"""How ``Mesh.repairs`` starts the entry of a surface reconstructed from a point cloud (``mesh.load``)."""
MIN_MEAN_THICKNESS_MM = 0.01
"""A closed surface thinner than this on average (2 x volume / area), or an open one whose points all lie
this close to one plane, is a flat sheet, not an object."""


def inconsistent_edges(faces: np.ndarray) -> int:
    """How many edges two of ``faces`` (m, 3) traverse in the same direction (no re-orientation makes
    them agree when the surface is one-sided, or parts of it were glued through each other)."""
    if not faces.size:
        return 0
    halfedges = np.stack([faces, np.roll(faces, -1, axis=1)], axis=2).reshape(-1, 2)
    _, directed_count = np.unique(halfedges[:, 0] * (int(faces.max()) + 1) + halfedges[:, 1], return_counts=True)
    return int(np.count_nonzero(directed_count > 1))


def topology_report(vertices: np.ndarray, faces: np.ndarray) -> dict[str, int | float]:
    """Topological measures of a triangle mesh (plain ints/floats).

    ``genus`` is ``(2 C - chi - holes) / 2`` over the referenced vertices, meaningful for manifold
    meshes; ``inconsistent_edges`` counts edges whose two faces traverse them in the same direction;
    ``mean_thickness_mm`` is 2 x |signed volume| / area (a slab's thickness, 0 for a flat sheet);
    ``flat_extent_mm`` is the vertices' extent along their axis of least spread (0 for a plane figure).
    """
    faces = np.asarray(faces, dtype=np.int64)
    used = np.flatnonzero(np.bincount(faces.ravel(), minlength=len(vertices)))  # np.unique(faces), without the sort
    halfedges = np.stack([faces, np.roll(faces, -1, axis=1)], axis=2).reshape(-1, 2)
    n_keys = max(int(faces.max()) + 1, 1) if faces.size else 1  # an edge (a, b) as the one number a * n_keys + b
    keys, edge_count = np.unique(halfedges.min(axis=1) * n_keys + halfedges.max(axis=1), return_counts=True)
    edges = np.stack(np.divmod(keys, n_keys), axis=1)
    boundary = edges[edge_count == 1]
    if len(boundary):
        n = int(boundary.max()) + 1
        graph = coo_matrix((np.ones(len(boundary)), (boundary[:, 0], boundary[:, 1])), shape=(n, n))
        labels = connected_components(graph, directed=False)[1]
        holes = len(np.unique(labels[np.unique(boundary)]))
    else:
        holes = 0
    components = face_components(faces, len(vertices))[0] if len(faces) else 0
    measures = to_meshset(vertices, faces).get_topological_measures()
    chi = len(used) - len(edges) + len(faces)
    volume = signed_volume(vertices, faces)
    double_areas = np.linalg.norm(cross_products(corners(vertices, faces)), axis=1)
    return {
        "vertices": int(len(used)),
        "faces": int(len(faces)),
        "edges": int(len(edges)),
        "unreferenced_vertices": int(len(vertices) - len(used)),
        "components": int(components),
        "boundary_edges": int(len(boundary)),
        "holes": int(holes),
        "non_manifold_edges": int(np.count_nonzero(edge_count > 2)),
        "non_manifold_vertices": int(measures["non_two_manifold_vertices"]),
        "inconsistent_edges": inconsistent_edges(faces),
        "zero_area_faces": int(np.count_nonzero(zero_area(double_areas))),
        "euler_characteristic": int(chi),
        "genus": int((2 * components - chi - holes) // 2),
        "signed_volume_mm3": volume,
        "mean_thickness_mm": 4.0 * abs(volume) / max(float(double_areas.sum()), 1e-300),
        "flat_extent_mm": flat_extent(vertices[used]),
    }


def keeps_closed_topology(vertices: np.ndarray, faces: np.ndarray, new_vertices: np.ndarray, new_faces: np.ndarray) -> bool:
    """True when ``new_faces`` is one closed, manifold, coherently oriented component without unused
    vertices (:func:`topology_report`) with the Euler characteristic ``V - F / 2`` of the closed input
    ``faces`` and the input's orientation (sign of the volume)."""
    report = topology_report(new_vertices, new_faces)
    input_chi = np.count_nonzero(np.bincount(faces.ravel(), minlength=len(vertices))) - len(faces) / 2
    return (report["components"] == 1 and report["boundary_edges"] == 0 and report["non_manifold_edges"] == 0
            and report["non_manifold_vertices"] == 0 and report["inconsistent_edges"] == 0
            and report["unreferenced_vertices"] == 0 and report["euler_characteristic"] == input_chi
            and (report["signed_volume_mm3"] > 0) == (signed_volume(vertices, faces) > 0))


def flat_extent(points: np.ndarray) -> float:
    """The extent (mm) of ``points`` along their principal axis of least variance."""
    if len(points) < 3:
        return 0.0
    centred = points - points.mean(axis=0)
    least = np.linalg.svd(centred, full_matrices=False)[2][-1]
    along = centred @ least
    return float(along.max() - along.min())


def topology_problems(report: dict[str, int | float], expected_genus: int | None,
                      from_points: bool = False) -> list[str]:
    """Operator-facing descriptions (what is wrong: what to do) of everything wrong in ``report``
    (``from_points``: the surface was reconstructed from a point cloud)."""
    problems = []
    if report["non_manifold_edges"] or report["non_manifold_vertices"]:
        problems.append(
            f"{report['non_manifold_edges']} non-manifold edges and "
            f"{report['non_manifold_vertices']} non-manifold vertices: put mesh.repair before this node if the "
            "pipeline has none, else fix them in a mesh editor (repair could not)"
        )
    if report["components"] > 1:
        problems.append(
            f"{report['components']} components: add mesh.repair (keep_largest: true keeps the largest)"
        )
    if report["boundary_edges"] and report["flat_extent_mm"] < MIN_MEAN_THICKNESS_MM:
        problems.append(
            f"the surface is an open flat sheet ({report['boundary_edges']} boundary edges, every point in one "
            "plane), not a solid object: give it its thickness in a mesh editor"
        )
    elif report["boundary_edges"]:
        problems.append(
            f"{report['boundary_edges']} boundary edges ({report['holes']} hole(s)) left open: add "
            "mesh.repair with close_holes, raise its max_hole_edges, or fill them in a mesh editor"
        )
    if report["inconsistent_edges"]:
        problems.append(
            f"{report['inconsistent_edges']} edges with inconsistent face orientation: add mesh.repair, "
            "or, if it is there, re-orient the faces in a mesh editor (the surface may be non-orientable)"
        )
    elif report["signed_volume_mm3"] < 0 and not report["boundary_edges"]:
        problems.append("faces point inward (negative signed volume): add mesh.repair before this node")
    if report["zero_area_faces"]:
        problems.append(
            f"{report['zero_area_faces']} faces of zero area: remesh to another vertex count (-S vertices=...), "
            "or collapse them in a mesh editor"
        )
    if not problems and report["mean_thickness_mm"] < MIN_MEAN_THICKNESS_MM:
        problems.append(
            f"the surface encloses no volume (mean thickness {report['mean_thickness_mm']:.2g} mm): it is a "
            "flat sheet, not a solid object; give it its thickness in a mesh editor"
        )
    clean = not problems
    if clean and expected_genus is not None and report["genus"] != expected_genus:
        problems.append(
            f"genus {report['genus']} as reconstructed from the scan's points at every octree depth tried: "
            "the object has handles, or the points are too noisy or hold several objects for their normals to "
            f"be oriented; the layout method needs a genus-{expected_genus} surface, so export the scan as a mesh "
            "(closing any handle in a mesh editor) or scan one object alone"
            if from_points else
            f"genus {report['genus']}: the layout method needs a genus-{expected_genus} surface; close "
            "the handle(s) in a mesh editor or pick another object"
        )
    return problems


class CheckTopologyParams(NodeParams):
    """What counts as a usable surface."""

    expected_genus: int | None = Field(0, ge=0, description="required genus (null: any)")


def ingest_note(outputs: dict[str, object]) -> str:
    """The run summary's line: every repair ingest made to the mesh (``Mesh.repairs``), or none."""
    repairs = outputs["mesh"].repairs  # type: ignore[attr-defined]
    return "ingest repairs: " + "; ".join(repairs) if repairs else "ingest repairs: none"


@node(
    "mesh.check_topology",
    params=CheckTopologyParams,
    inputs=("mesh",),
    outputs=("mesh", "report"),
    note=ingest_note,
)
def check_topology(params: CheckTopologyParams, mesh: Mesh) -> dict[str, object]:
    """Pass the mesh through unchanged when it is one closed, manifold, outward genus-0 surface.

    Otherwise raise one line listing each problem with its fix. ``report`` holds the measures.
    """
    if len(mesh.faces) == 0:
        raise UserError(f"{mesh.source_name} has no faces: load a triangle mesh")
    if not np.isfinite(mesh.vertices).all():
        raise UserError(f"{mesh.source_name} has vertices at NaN or infinite coordinates: "
                        "repair the file, or check the scale (units, diagonal_mm)")
    report = topology_report(mesh.vertices, mesh.faces)
    from_points = any(repair.startswith(RECONSTRUCTED) for repair in mesh.repairs)
    problems = topology_problems(report, params.expected_genus, from_points)
    if problems:
        raise UserError(f"{mesh.source_name}: " + "; ".join(problems))
    return {"mesh": mesh, "report": report}
