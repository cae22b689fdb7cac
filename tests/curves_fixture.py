"""Test meshes for the curve tests: scaled to 170 mm, remeshed small, regions from ``regions.detect``
(cached across the curve test modules).

Isotropic remeshing is chaotic: a relative change of 1e-6 in the input, or another machine's rounding,
gives a different mesh of the same object. The tests must hold for any of them, so
``RETROTOUCH_TEST_JITTER=REL:SEED`` perturbs every input mesh by ``REL`` (relative, normal, seeded)
before it is remeshed: run the tests under a few seeds to check.
"""
from __future__ import annotations

import functools
import os
from importlib import resources
from pathlib import Path

import numpy as np
import pymeshlab
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from touch_fixture import touch_of
from retrotouch.graph.errors import UserError
from retrotouch.nodes.curves.connection import compute_field
from retrotouch.nodes.data.types import Mesh
from retrotouch.nodes.geometry.mesh_tables import build_tables
from retrotouch.nodes.geometry.triangles import areas, corners
from retrotouch.nodes.mesh.repair import edge_length_for_vertices, isotropic_remesh
from retrotouch.nodes.regions.detect import RegionParams, detect_regions

SHARED_MESHES = Path(__file__).resolve().parents[1].parent / "shared" / "meshes"


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
    f = f.reshape(-1, 3)
    v = v[used] * (diagonal_mm / np.linalg.norm(v[used].max(axis=0) - v[used].min(axis=0)))
    if os.environ.get("RETROTOUCH_TEST_JITTER"):
        relative, seed = os.environ["RETROTOUCH_TEST_JITTER"].split(":")
        v = v * (1.0 + float(relative) * np.random.default_rng(int(seed)).standard_normal(v.shape))
    if target_vertices:
        area = areas(corners(v, f)).sum()
        v, f = isotropic_remesh(v, f, edge_length_for_vertices(area, target_vertices), iterations=6, feature_angle_deg=30.0)
    return Mesh(
        vertices=np.ascontiguousarray(v, dtype=np.float64),
        faces=np.ascontiguousarray(f, dtype=np.int64),
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


def regions_for(mesh: Mesh):
    """``regions.detect`` with default params; when it finds no flat base, retry with ``up_axis`` set to
    the axis direction (+-x, +-y, +-z) with the most downward faces near the bottom."""
    try:
        return detect_regions(RegionParams(), mesh, touch_of(mesh))
    except UserError:
        axes = np.vstack([np.eye(3), -np.eye(3)])
        up = axes[int(np.argmax([base_candidates(mesh, a).sum() for a in axes]))]
        return detect_regions(RegionParams(up_axis=tuple(float(x) for x in up)), mesh, touch_of(mesh))


@functools.lru_cache(maxsize=None)
def prepared(path: str, target_vertices: int = 4000):
    """(mesh, regions, tables, tx field, rx field) for a mesh file, cached across the curve tests."""
    mesh = load_scaled(Path(path), target_vertices=target_vertices)
    regions = regions_for(mesh)
    tables = build_tables(mesh.vertices, mesh.faces)
    return mesh, regions, tables, compute_field(tables, "tx", regions), compute_field(tables, "rx", regions)


def bunny():
    return prepared(str(sample_mesh_path("bunny.obj")))
