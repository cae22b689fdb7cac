"""Heat-method geodesics, surface samples and the Voronoi uniformity metric."""
from __future__ import annotations

import tracemalloc

import numpy as np
import potpourri3d as pp3d
import pytest
import trimesh
from test_layout_fixtures import RADIUS_MM, Regions, sphere_mesh

from retrotouch.nodes.layout import metrics, samples as samples_module
from retrotouch.nodes.layout.metrics import (
    UNCOVERED_SPOTS_LISTED, coefficient_of_variation, min_pairwise, row_minima, uncovered_spots, voronoi_cell_areas,
)
from retrotouch.nodes.geometry.triangles import areas as triangle_areas, corners, mean_edge_mm
from retrotouch.nodes.layout.samples import HeatGeodesics, SamplesParams, geodesics_for, surface_samples
from retrotouch.nodes.mesh.repair import isotropic_remesh


def locate(mesh, directions):
    """(faces, bary) of the mesh points hit by rays from the centre (the icosphere is star-shaped)."""
    d = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    P = mesh.vertices[mesh.faces]
    faces, bary = [], []
    np.seterr(divide="ignore", invalid="ignore")
    for u in d:
        # Moller-Trumbore against every face (rays parallel to a face give inf/nan, never a hit)
        e1, e2 = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]
        h = np.cross(u, e2)
        a = np.einsum("fi,fi->f", e1, h)
        s = -P[:, 0]
        b1 = np.einsum("fi,fi->f", s, h) / a
        q = np.cross(s, e1)
        b2 = (q @ u) / a
        t = np.einsum("fi,fi->f", e2, q) / a
        ok = (b1 >= 0) & (b2 >= 0) & (b1 + b2 <= 1) & (t > 0)
        f = int(np.flatnonzero(ok)[0])
        faces.append(f)
        bary.append([1 - b1[f] - b2[f], b1[f], b2[f]])
    return np.array(faces), np.array(bary)


def test_heat_geodesics_match_the_sphere_and_potpourri3d():
    mesh = sphere_mesh(5)
    geo = geodesics_for(mesh)
    faces, bary = locate(mesh, np.array([[0.3, 0.2, 1.0], [1.0, -0.4, 0.1], [-0.2, -1.0, -0.5]]))
    fields = geo.fields(faces, bary)
    src = np.einsum("kc,kcd->kd", bary, mesh.vertices[mesh.faces[faces]])
    cosine = (mesh.vertices / RADIUS_MM) @ (src / np.linalg.norm(src, axis=1, keepdims=True)).T
    exact = RADIUS_MM * np.arccos(np.clip(cosine, -1, 1))
    far = exact > 10.0
    assert np.median(np.abs(fields - exact)[far] / exact[far]) < 0.015  # heat method: ~1 % on this mesh
    # a vertex source agrees with potpourri3d's heat solver
    v = int(mesh.faces[faces[0], 0])
    vf = int(np.flatnonzero((mesh.faces == v).any(axis=1))[0])
    ours = geo.fields(np.array([vf]), (mesh.faces[vf] == v).astype(float)[None, :])[:, 0]
    theirs = pp3d.MeshHeatMethodDistanceSolver(mesh.vertices, mesh.faces).compute_distance(v)
    assert np.median(np.abs(ours - theirs)[theirs > 10] / theirs[theirs > 10]) < 0.01


def test_heat_geodesics_from_a_point_inside_a_face_are_not_biased_low():
    # the heat method rounds the distance off around its source: pinning the field to 0 at a face's
    # centroid pulled every distance down by about half an edge (10 % at 3-6 edges away, 5 % at 6-12)
    mesh = sphere_mesh(4)
    geo = geodesics_for(mesh)
    faces = np.random.default_rng(0).choice(len(mesh.faces), 8, replace=False)
    bary = np.full((8, 3), 1.0 / 3.0)
    fields = geo.fields(faces, bary)
    src = np.einsum("kc,kcd->kd", bary, mesh.vertices[mesh.faces[faces]])
    cosine = (mesh.vertices / RADIUS_MM) @ (src / np.linalg.norm(src, axis=1, keepdims=True)).T
    exact = RADIUS_MM * np.arccos(np.clip(cosine, -1, 1))
    for near, far in ((3, 6), (6, 12)):
        band = (exact > near * geo.mean_edge_mm) & (exact < far * geo.mean_edge_mm)
        ratio = fields[band] / exact[band]
        assert abs(np.median(ratio) - 1.0) < 0.02 and ratio.min() > 0.98


def test_fields_solved_on_a_decimated_copy_match_the_sphere_within_an_edge_of_the_copy():
    mesh = sphere_mesh(5)
    geo = HeatGeodesics(mesh.vertices, mesh.faces, proxy_vertices=2500)
    assert geo.proxy is not None and abs(len(geo.proxy.vertices) - 2500) < 250
    np.testing.assert_allclose(np.asarray(geo.proxy.interpolation.sum(axis=1)).ravel(), 1.0)  # barycentric rows
    faces, bary = np.array([0, 500, 9000]), np.full((3, 3), 1.0 / 3.0)
    fields = geo.fields(faces, bary)
    assert fields.shape == (len(mesh.vertices), 3) and fields.dtype == np.float32
    src = np.einsum("kc,kcd->kd", bary, mesh.vertices[mesh.faces[faces]])
    cosine = (mesh.vertices / RADIUS_MM) @ (src / np.linalg.norm(src, axis=1, keepdims=True)).T
    exact = RADIUS_MM * np.arccos(np.clip(cosine, -1, 1))
    far = exact > 10.0
    assert np.median(np.abs(fields - exact)[far] / exact[far]) < 0.01
    assert np.abs(fields - exact).max() < mean_edge_mm(geo.proxy.vertices, geo.proxy.faces)


def test_a_decimated_copy_keeps_the_two_sides_of_a_thin_plate_apart():
    box = trimesh.creation.box(extents=(80.0, 80.0, 1.5))
    V, F = isotropic_remesh(np.asarray(box.vertices), np.asarray(box.faces), 1.2, iterations=6, feature_angle_deg=30.0)
    geo = HeatGeodesics(V, F, proxy_vertices=len(V) // 4)
    assert geo.proxy is not None
    off_axis = np.hypot(V[:, 0], V[:, 1])
    centre = off_axis < 10.0
    top = np.flatnonzero(V[:, 2] > 0)[np.argmin(off_axis[V[:, 2] > 0])]  # the top vertex nearest the axis
    face = np.flatnonzero((F == top).any(axis=1))[0]
    distance = geo.fields(np.array([face]), (F[face] == top).astype(float)[None, :])[:, 0]
    # from the top's centre to the bottom's the way is round the rim, about 80 mm: not through 1.5 mm of plate
    assert distance[centre & (V[:, 2] < 0)].min() > 60.0
    assert distance[centre & (V[:, 2] > 0)].max() < 10.0 + off_axis[top] + 2.0


def test_samples_are_on_sensing_faces_and_spread():
    mesh = sphere_mesh(4)
    regions = Regions(mesh)
    samples = surface_samples(SamplesParams(count=120, seed=3), mesh, regions)
    assert samples.points.shape == (120, 3)
    assert np.all(regions.sensing_faces[samples.faces])
    assert np.allclose(np.einsum("kc,kcd->kd", samples.bary, mesh.vertices[mesh.faces[samples.faces]]), samples.points)
    d = np.linalg.norm(samples.points[:, None] - samples.points[None], axis=2)
    assert min_pairwise(d) >= samples.spacing_mm - 1e-9
    assert samples.spacing_mm > 0.5 * np.sqrt(samples.sensing_area_mm2 / 120)
    assert samples.sensing_area_mm2 == pytest.approx(triangle_areas(corners(mesh.vertices, mesh.faces))[regions.sensing_faces].sum())
    # at its own sample, a distance field is the P1 interpolation of the sample's distances to its face's corners
    geo = geodesics_for(mesh)
    own = geo.evaluate(samples.distances, samples.faces, samples.bary)
    corner_points = mesh.vertices[mesh.faces[samples.faces]]
    to_corners = np.linalg.norm(corner_points - samples.points[:, None], axis=2)
    assert np.diag(own) == pytest.approx(np.einsum("kc,kc->k", samples.bary, to_corners), abs=1e-4)
    again = surface_samples(SamplesParams(count=120, seed=3), mesh, regions)
    assert np.array_equal(again.points, samples.points)


def test_voronoi_cv_is_near_zero_for_octahedron_pads_and_high_for_clusters():
    mesh = sphere_mesh(4)
    geo = geodesics_for(mesh)
    everything = np.ones(len(mesh.faces), dtype=bool)
    octahedron = np.vstack([np.eye(3), -np.eye(3)]) + 1e-3  # off-vertex directions
    faces, bary = locate(mesh, octahedron)
    areas = voronoi_cell_areas(geo.fields(faces, bary), mesh.vertices, mesh.faces, everything)
    assert areas.sum() == pytest.approx(triangle_areas(corners(mesh.vertices, mesh.faces)).sum())
    assert coefficient_of_variation(areas) < 0.05
    clustered = np.array([[0, 0, 1], [0.2, 0, 1], [0, 0.2, 1], [-0.2, 0, 1], [0, -0.2, 1], [0, 0, -1]], dtype=float)
    faces, bary = locate(mesh, clustered)
    cv = coefficient_of_variation(voronoi_cell_areas(geo.fields(faces, bary), mesh.vertices, mesh.faces, everything))
    assert cv > 0.8


def test_fields_by_blocks_of_sources_are_the_all_at_once_values_without_their_memory(monkeypatch):
    mesh = sphere_mesh(5)
    geo = geodesics_for(mesh)
    rng = np.random.default_rng(0)
    faces, bary = rng.integers(0, len(mesh.faces), 48), rng.dirichlet(np.ones(3), 48)
    tracemalloc.start()
    blocked = geo.fields(faces, bary)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    # numpy's allocations at their peak stay below the (3 * faces, 48) float64 gradient of all sources at once
    assert peak < 3 * len(mesh.faces) * 48 * 8
    monkeypatch.setattr(samples_module, "_COLUMNS_PER_BATCH", 48)  # the Cholesky solves too: columns are independent
    assert np.array_equal(geo.fields(faces, bary), blocked)


@pytest.mark.parametrize("heat_scale", [1e-170, 1e-250])
def test_fields_do_not_depend_on_the_scale_of_the_heat(heat_scale, monkeypatch):
    """Far along a long object the heat underflows to the smallest doubles; the heat method only uses
    its direction, so a heat scaled that small must give the same distances (it gave infinities)."""
    mesh = sphere_mesh(4)
    geo = geodesics_for(mesh)
    faces, bary = np.array([0, 17, 301]), np.full((3, 3), 1 / 3)
    expected = geo.fields(faces, bary)
    solve = samples_module.solve
    monkeypatch.setattr(samples_module, "solve",
                        lambda factor, rhs: solve(factor, rhs) * (heat_scale if factor is geo.solver.heat else 1.0))
    scaled = geo.fields(faces, bary)
    assert np.isfinite(scaled).all()
    np.testing.assert_allclose(scaled, expected, rtol=1e-5, atol=1e-4)


def test_fields_that_are_not_finite_stop_the_run_instead_of_reaching_phase_1(monkeypatch):
    mesh = sphere_mesh(3)
    geo = geodesics_for(mesh)
    solve = samples_module.solve
    monkeypatch.setattr(samples_module, "solve",
                        lambda factor, rhs: solve(factor, rhs) * (np.inf if factor is geo.solver.poisson else 1.0))
    with pytest.raises(FloatingPointError, match="not finite"):
        geo.fields(np.array([0, 5]), np.full((2, 3), 1 / 3))


def test_voronoi_and_row_minima_by_blocks_equal_the_whole_array(monkeypatch):
    mesh = sphere_mesh(4)
    geo = geodesics_for(mesh)
    rng = np.random.default_rng(1)
    fields = geo.fields(rng.integers(0, len(mesh.faces), 20), rng.dirichlet(np.ones(3), 20))
    mask = rng.random(len(mesh.faces)) < 0.6
    rows = np.unique(mesh.faces[mask])
    whole_owner = np.argmin(fields[mesh.faces[mask]].mean(axis=1), axis=1)
    whole = np.bincount(whole_owner, weights=triangle_areas(corners(mesh.vertices, mesh.faces[mask])), minlength=20)
    monkeypatch.setattr(metrics, "_ROWS_PER_BLOCK", 97)  # many blocks, the last one partial
    assert np.array_equal(voronoi_cell_areas(fields, mesh.vertices, mesh.faces, mask), whole)
    assert np.array_equal(row_minima(fields, rows), fields[rows].min(axis=1))


def plane_grid(size_mm: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """A flat square (size_mm x size_mm, z = 0) as an n x n grid of vertices, two triangles per square."""
    x, y = np.meshgrid(np.linspace(0.0, size_mm, n), np.linspace(0.0, size_mm, n), indexing="ij")
    vertices = np.c_[x.ravel(), y.ravel(), np.zeros(n * n)]
    k = np.arange(n * n).reshape(n, n)[:-1, :-1].ravel()
    faces = np.r_[np.c_[k, k + n, k + n + 1], np.c_[k, k + n + 1, k + 1]]
    return vertices, faces


def test_uncovered_share_and_spot_match_the_disc_left_by_one_cell():
    # one cell at the centre of a 100 mm square: everything beyond 10 mm of it is one spot, of area
    # 100^2 - pi 10^2, its farthest point a corner at 50 sqrt(2) mm
    vertices, faces = plane_grid(100.0, 201)
    nearest = np.linalg.norm(vertices - [50.0, 50.0, 0.0], axis=1)
    out = uncovered_spots(nearest, vertices, faces, np.ones(len(faces), dtype=bool), 10.0)
    expected = 100.0**2 - np.pi * 10.0**2
    assert len(out["uncovered_spots"]) == 1
    assert out["uncovered_spots"][0]["area_mm2"] == pytest.approx(expected, rel=0.01)
    assert out["uncovered_share"] == pytest.approx(expected / 100.0**2, rel=0.01)
    assert out["uncovered_spots"][0]["max_distance_mm"] == pytest.approx(50.0 * np.sqrt(2.0))
    assert np.abs(out["uncovered_spots"][0]["point"][:2] - np.array([50.0, 50.0])).tolist() == [50.0, 50.0]


def test_uncovered_spots_are_separate_pieces_largest_first_and_outside_faces_do_not_count():
    # cells along the line x = 40: the strip left of x = 30 and the one right of x = 50 are two spots
    # (30 x 100 and 50 x 100 mm); faces outside the mask (x > 90) are neither area nor spots
    vertices, faces = plane_grid(100.0, 201)
    nearest = np.abs(vertices[:, 0] - 40.0)
    mask = vertices[faces, 0].max(axis=1) <= 90.0
    out = uncovered_spots(nearest, vertices, faces, mask, 10.0)
    areas_found = [s["area_mm2"] for s in out["uncovered_spots"]]
    assert len(areas_found) == 2 and areas_found == sorted(areas_found, reverse=True)
    assert areas_found == pytest.approx([40.0 * 100.0, 30.0 * 100.0], rel=0.02)
    assert out["uncovered_share"] == pytest.approx(70.0 / 90.0, rel=0.02)
    assert out["uncovered_spots"][0]["max_distance_mm"] == pytest.approx(50.0)


def test_uncovered_spots_list_the_largest_only_and_none_when_covered():
    vertices, faces = plane_grid(100.0, 101)
    # cells on a 20 mm lattice leave a spot around each lattice square's centre (14.1 mm from its corners)
    lattice = np.arange(0.0, 101.0, 20.0)
    cells = np.array([[x, y, 0.0] for x in lattice for y in lattice])
    nearest = np.linalg.norm(vertices[:, None, :] - cells[None], axis=2).min(axis=1)
    mask = np.ones(len(faces), dtype=bool)
    spots = uncovered_spots(nearest, vertices, faces, mask, 10.0)["uncovered_spots"]
    assert len(spots) == UNCOVERED_SPOTS_LISTED < 25
    assert all(s["max_distance_mm"] == pytest.approx(10.0 * np.sqrt(2.0)) for s in spots)
    covered = uncovered_spots(nearest, vertices, faces, mask, 15.0)
    assert covered["uncovered_spots"] == [] and covered["uncovered_share"] == 0.0
