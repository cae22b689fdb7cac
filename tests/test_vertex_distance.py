"""geometry.vertex_distance: potpourri3d's heat-method distances on the mesh, or on a decimated copy."""
from __future__ import annotations

import numpy as np
import potpourri3d as pp3d
from test_layout_fixtures import RADIUS_MM, sphere_mesh

from retrotouch.nodes.geometry.vertex_distance import VertexDistances
from retrotouch.nodes.geometry.triangles import mean_edge_mm


def sphere_distance_mm(vertices: np.ndarray, sources: np.ndarray) -> np.ndarray:
    """Exact great-circle distance (mm) of every vertex of the sphere from the nearest of ``sources``."""
    unit = vertices / np.linalg.norm(vertices, axis=1, keepdims=True)
    return RADIUS_MM * np.arccos(np.clip(unit @ unit[sources].T, -1.0, 1.0)).min(axis=1)


def test_below_the_threshold_the_distances_are_potpourri3d_s_on_the_mesh():
    mesh = sphere_mesh(4)
    distances = VertexDistances(mesh.vertices, mesh.faces)
    assert distances.proxy is None
    solver = pp3d.MeshHeatMethodDistanceSolver(mesh.vertices, mesh.faces)
    np.testing.assert_array_equal(distances.compute_distance(17), solver.compute_distance(17))
    np.testing.assert_array_equal(distances.compute_distance_multisource([3, 900]), solver.compute_distance_multisource([3, 900]))


def test_on_a_decimated_copy_the_distances_match_the_sphere_within_an_edge_of_the_copy():
    mesh = sphere_mesh(6)  # 40,962 vertices
    distances = VertexDistances(mesh.vertices, mesh.faces, proxy_vertices=2500)
    assert distances.proxy is not None and abs(len(distances.proxy.vertices) - 2500) < 250
    copy_edge = mean_edge_mm(distances.proxy.vertices, distances.proxy.faces)
    cap_rim = np.flatnonzero(np.abs(mesh.vertices[:, 2] - 0.6 * RADIUS_MM) < 0.5)  # a circle of sources
    for sources in (np.array([123]), cap_rim):
        found = distances.compute_distance_multisource(sources)
        exact = sphere_distance_mm(mesh.vertices, sources)
        assert found.shape == (len(mesh.vertices),) and np.all(found[sources] == 0.0) and found.min() >= 0.0
        assert np.median(np.abs(found - exact)) < 0.25 * copy_edge
        assert np.abs(found - exact).max() < copy_edge
    np.testing.assert_array_equal(distances.compute_distance(123), distances.compute_distance_multisource([123]))
