"""Test meshes and a simple base/far region fixture for the curve tests (until ``regions.detect`` lands).

The fixture follows the paper's description: base = the largest connected patch of downward faces
(within 15 degrees of -up) in the lowest 5 % of the height; base centre = the base vertex farthest
(heat distance) from the base boundary; far vertex = the vertex farthest from the base centre.
"""
from __future__ import annotations

import dataclasses
import functools
from importlib import resources
from pathlib import Path

import numpy as np
import potpourri3d as pp3d
import pymeshlab
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from retrotouch.nodes.connection import compute_field
from retrotouch.nodes.datatypes import Mesh
from retrotouch.nodes.mesh_tables import build_tables

SHARED_MESHES = Path(__file__).resolve().parents[1].parent / "shared" / "meshes"


@dataclasses.dataclass(frozen=True)
class FixtureRegions:
    base_faces: np.ndarray
    sensing_faces: np.ndarray
    exclusion_base: np.ndarray
    exclusion_far: np.ndarray
    base_centre: int
    base_dipole: np.ndarray
    far_vertex: int
    up: np.ndarray
    base_boundary_edges: np.ndarray


def sample_mesh_path(name: str) -> Path:
    """A mesh shipped with pymeshlab's tests (``bunny.obj``, ``bone.ply``)."""
    return Path(str(resources.files("pymeshlab"))) / "tests" / "sample_meshes" / name


def load_scaled(path: Path, diagonal_mm: float = 170.0, target_vertices: int | None = 5000) -> Mesh:
    """Load ``path``, keep the largest component, scale to ``diagonal_mm`` and isotropically remesh to about ``target_vertices``."""
    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(str(path))
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_remove_unreferenced_vertices()
    v = np.asarray(ms.current_mesh().vertex_matrix(), dtype=np.float64)
    f = np.asarray(ms.current_mesh().face_matrix(), dtype=np.int64)
    rows = np.repeat(np.arange(len(f)), 3)
    incidence = sp.csr_matrix((np.ones(len(rows)), (rows, f.reshape(-1))), shape=(len(f), len(v)))
    _, labels = connected_components(incidence @ incidence.T, directed=False)
    f = f[labels == np.argmax(np.bincount(labels))]
    used, f = np.unique(f, return_inverse=True)
    v = v[used] * (diagonal_mm / np.linalg.norm(v[used].max(axis=0) - v[used].min(axis=0)))
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v, face_matrix=f.reshape(-1, 3).astype(np.int32)))
    if target_vertices:
        m = ms.current_mesh()
        v = np.asarray(m.vertex_matrix())
        f = np.asarray(m.face_matrix())
        area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum()
        edge = np.sqrt(4.0 * area / (np.sqrt(3.0) * 2.0 * target_vertices))
        ms.meshing_isotropic_explicit_remeshing(iterations=6, targetlen=pymeshlab.PureValue(edge))
    m = ms.current_mesh()
    return Mesh(
        vertices=np.ascontiguousarray(m.vertex_matrix(), dtype=np.float64),
        faces=np.ascontiguousarray(m.face_matrix(), dtype=np.int64),
        source=str(path),
    )


def base_candidates(mesh: Mesh, up: np.ndarray) -> np.ndarray:
    """Faces facing down within 15 degrees and lying in the lowest 5 % of the height along ``up``."""
    v, f = mesh.vertices, mesh.faces
    normals = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    height = v @ up
    low = height.min() + 0.05 * (height.max() - height.min())
    return (normals @ -up > np.cos(np.radians(15.0))) & np.all(height[f] < low, axis=1)


def simple_regions(mesh: Mesh, up=None, base_margin_mm: float = 3.0, far_radius_mm: float = 8.0) -> FixtureRegions:
    """Base/far regions as described in the module docstring; ``up`` defaults to the axis direction
    (+-x, +-y, +-z) with the most base-candidate faces."""
    v, f = mesh.vertices, mesh.faces
    if up is None:
        axes = np.vstack([np.eye(3), -np.eye(3)])
        up = axes[int(np.argmax([base_candidates(mesh, a).sum() for a in axes]))]
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    candidate = base_candidates(mesh, up)
    idx = np.flatnonzero(candidate)
    # face adjacency among candidates by shared vertices
    rows = np.repeat(idx, 3)
    inc = sp.csr_matrix((np.ones(len(rows)), (rows, f[idx].reshape(-1))), shape=(len(f), len(v)))
    adj = (inc @ inc.T)[idx][:, idx]
    _, labels = connected_components(adj, directed=False)
    largest = np.argmax(np.bincount(labels))
    base = np.zeros(len(f), dtype=bool)
    base[idx[labels == largest]] = True
    in_base = np.zeros(len(v), dtype=bool)
    in_base[f[base].reshape(-1)] = True
    in_other = np.zeros(len(v), dtype=bool)
    in_other[f[~base].reshape(-1)] = True
    boundary_vertices = np.flatnonzero(in_base & in_other)
    solver = pp3d.MeshHeatMethodDistanceSolver(v, f)
    from_boundary = solver.compute_distance_multisource(boundary_vertices)
    interior = np.flatnonzero(in_base & ~in_other)
    base_centre = int(interior[np.argmax(from_boundary[interior])])
    from_centre = solver.compute_distance(base_centre)
    far_vertex = int(np.argmax(from_centre))
    neighbours = np.unique(f[np.any(f == base_centre, axis=1)].reshape(-1))
    neighbours = neighbours[neighbours != base_centre]
    dipole = np.array([base_centre, int(neighbours[np.argmax(from_boundary[neighbours])])], dtype=np.int64)
    from_base = solver.compute_distance_multisource(np.flatnonzero(in_base))
    exclusion_base = base | np.any(from_base[f] < base_margin_mm, axis=1)
    from_far = solver.compute_distance(far_vertex)
    exclusion_far = np.any(from_far[f] < far_radius_mm, axis=1)
    he = np.stack([f, np.roll(f, -1, axis=1)], axis=2).reshape(-1, 2)
    he_face = np.repeat(np.arange(len(f)), 3)
    key = np.sort(he, axis=1)
    _, inv = np.unique(key[:, 0] * len(v) + key[:, 1], return_inverse=True)
    inside = np.zeros(inv.max() + 1, dtype=int)
    np.add.at(inside, inv, exclusion_base[he_face].astype(int))
    boundary_edges = np.unique(key[inside[inv] == 1], axis=0)
    return FixtureRegions(
        base_faces=base,
        sensing_faces=~(exclusion_base | exclusion_far),
        exclusion_base=exclusion_base,
        exclusion_far=exclusion_far,
        base_centre=base_centre,
        base_dipole=dipole,
        far_vertex=far_vertex,
        up=up,
        base_boundary_edges=boundary_edges.astype(np.int64),
    )


@functools.lru_cache(maxsize=None)
def prepared(path: str, target_vertices: int = 4000):
    """(mesh, regions, tables, tx field, rx field) for a mesh file, cached across the curve tests."""
    mesh = load_scaled(Path(path), target_vertices=target_vertices)
    regions = simple_regions(mesh)
    tables = build_tables(mesh.vertices, mesh.faces)
    return mesh, regions, tables, compute_field(tables, "tx", regions), compute_field(tables, "rx", regions)


def bunny():
    return prepared(str(sample_mesh_path("bunny.obj")))
