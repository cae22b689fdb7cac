"""Mesh clean-up and isotropic remeshing with pymeshlab (the paper's MeshLab step).

Nodes:

* ``mesh.repair`` -- remove duplicate vertices/faces, null faces and unreferenced vertices, repair
  non-manifold edges and vertices, orient faces coherently, close small holes, optionally keep only
  the largest connected component, and make the orientation outward (signed volume > 0).
* ``mesh.remesh`` -- isotropic explicit remeshing to a target edge length in mm, or to a target
  vertex count (the edge length is solved for in a few passes).
"""
from __future__ import annotations

import math
from typing import Literal

import numpy as np
import pymeshlab
from pydantic import Field, model_validator
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ...graph.errors import UserError
from ...graph.node import NodeParams, node
from ..data.types import Mesh


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


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed enclosed volume (mm^3); positive when faces are CCW seen from outside."""
    p0, p1, p2 = (vertices[faces[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", p0, np.cross(p1, p2)).sum() / 6.0)


def face_components(faces: np.ndarray, vertex_count: int) -> tuple[int, np.ndarray]:
    """Connected components of faces sharing a vertex: ``(count, label per face)``."""
    m = len(faces)
    rows = np.repeat(np.arange(m), 3)
    incidence = coo_matrix((np.ones(3 * m), (rows, faces.ravel())), shape=(m, vertex_count)).tocsr()
    count, vertex_labels = connected_components(incidence.T @ incidence, directed=False)
    return count, vertex_labels[faces[:, 0]]


def keep_largest_component(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The connected component with the largest surface area, unreferenced vertices dropped."""
    count, labels = face_components(faces, len(vertices))
    if count > 1:
        p0, p1, p2 = (vertices[faces[:, k]] for k in range(3))
        areas = 0.5 * np.linalg.norm(np.cross(p1 - p0, p2 - p0), axis=1)
        faces = faces[labels == np.argmax(np.bincount(labels, weights=areas))]
    used = np.unique(faces)
    remap = np.full(len(vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return np.ascontiguousarray(vertices[used]), np.ascontiguousarray(remap[faces])


class RepairParams(NodeParams):
    """Which clean-up steps run."""

    close_holes: bool = Field(True, description="fill holes bounded by at most max_hole_edges edges")
    max_hole_edges: int = Field(30, ge=3, description="largest hole (in boundary edges) to close")
    keep_largest: bool = Field(False, description="drop every component but the largest (by area)")
    non_manifold_edges: Literal["remove_faces", "split_vertices"] = Field(
        "remove_faces", description="how non-manifold edges are repaired"
    )


@node("mesh.repair", params=RepairParams, inputs=("mesh",), outputs=("mesh",))
def repair_mesh(params: RepairParams, mesh: Mesh) -> Mesh:
    """Clean a scanned mesh with pymeshlab and orient it outward (signed volume > 0)."""
    meshset = to_meshset(mesh.vertices, mesh.faces)
    meshset.meshing_remove_duplicate_vertices()
    meshset.meshing_remove_duplicate_faces()
    meshset.meshing_remove_null_faces()
    meshset.meshing_remove_unreferenced_vertices()
    method = "Remove Faces" if params.non_manifold_edges == "remove_faces" else "Split Vertices"
    meshset.meshing_repair_non_manifold_edges(method=method)
    meshset.meshing_repair_non_manifold_vertices()
    meshset.meshing_remove_unreferenced_vertices()
    meshset.meshing_re_orient_faces_coherently()
    if params.close_holes:
        try:
            meshset.meshing_close_holes(maxholesize=params.max_hole_edges)
        except pymeshlab.PyMeshLabException as exc:
            raise UserError(
                f"closing holes failed ({str(exc).strip()[:100]}): set close_holes: false and "
                "fill the holes in a mesh editor"
            ) from None
    vertices, faces = from_meshset(meshset)
    if params.keep_largest:
        vertices, faces = keep_largest_component(vertices, faces)
    if len(faces) == 0:
        raise UserError(f"repair left no faces in {mesh.source}: the input is not a usable surface")
    if signed_volume(vertices, faces) < 0.0:
        faces = np.ascontiguousarray(faces[:, ::-1])
    return Mesh(vertices=vertices, faces=faces, source=mesh.source)


class RemeshParams(NodeParams):
    """Set exactly one of ``target_edge_mm`` and ``target_vertices``."""

    target_edge_mm: float | None = Field(None, gt=0, description="target edge length (mm)")
    target_vertices: int | None = Field(None, ge=100, description="target vertex count (within ~10%)")
    iterations: int = Field(10, ge=1, le=50, description="remeshing iterations per pass")
    feature_angle_deg: float = Field(30.0, gt=0, lt=180, description="crease angle kept sharp (deg)")
    max_passes: int = Field(3, ge=1, le=6, description="passes to hit target_vertices")

    @model_validator(mode="after")
    def _exactly_one_target(self) -> "RemeshParams":
        if (self.target_edge_mm is None) == (self.target_vertices is None):
            raise ValueError("set exactly one of target_edge_mm and target_vertices")
        return self


def surface_area(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Total triangle area (mm^2)."""
    p0, p1, p2 = (vertices[faces[:, k]] for k in range(3))
    return float(0.5 * np.linalg.norm(np.cross(p1 - p0, p2 - p0), axis=1).sum())


def edge_length_for_vertices(area_mm2: float, vertex_count: int) -> float:
    """Edge length (mm) of an equilateral closed mesh with ``vertex_count`` vertices and given area.

    A closed mesh has about ``2 V`` faces of area ``sqrt(3)/4 L^2`` each.
    """
    return math.sqrt(4.0 * area_mm2 / (math.sqrt(3.0) * 2.0 * vertex_count))


def isotropic_remesh(
    vertices: np.ndarray, faces: np.ndarray, edge_mm: float, iterations: int, feature_angle_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """One pymeshlab isotropic explicit remeshing run at absolute edge length ``edge_mm``."""
    meshset = to_meshset(vertices, faces)
    meshset.meshing_isotropic_explicit_remeshing(
        iterations=iterations,
        targetlen=pymeshlab.PureValue(edge_mm),
        featuredeg=feature_angle_deg,
        adaptive=False,
    )
    return from_meshset(meshset)


@node("mesh.remesh", params=RemeshParams, inputs=("mesh",), outputs=("mesh",))
def remesh(params: RemeshParams, mesh: Mesh) -> Mesh:
    """Isotropic remeshing to ``target_edge_mm``, or to about ``target_vertices`` vertices.

    For a vertex target the edge length starts from the equilateral estimate and is corrected by
    ``sqrt(V_got / V_target)`` from the original mesh until within 10% (at most ``max_passes``).
    """
    if params.target_edge_mm is not None:
        vertices, faces = isotropic_remesh(
            mesh.vertices, mesh.faces, params.target_edge_mm, params.iterations, params.feature_angle_deg
        )
    else:
        target = params.target_vertices
        edge = edge_length_for_vertices(surface_area(mesh.vertices, mesh.faces), target)
        best: tuple[float, np.ndarray, np.ndarray] | None = None
        for _ in range(params.max_passes):
            vertices, faces = isotropic_remesh(
                mesh.vertices, mesh.faces, edge, params.iterations, params.feature_angle_deg
            )
            error = abs(len(vertices) - target) / target
            if best is None or error < best[0]:
                best = (error, vertices, faces)
            if error <= 0.10:
                break
            edge *= math.sqrt(len(vertices) / target)
        _, vertices, faces = best
    if signed_volume(vertices, faces) * signed_volume(mesh.vertices, mesh.faces) < 0.0:
        faces = np.ascontiguousarray(faces[:, ::-1])
    return Mesh(vertices=vertices, faces=faces, source=mesh.source)
