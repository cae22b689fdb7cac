"""Thin walls: points close in space, far apart along the surface (``geometry.thin_walls``), and the
same-layer clearance that no longer counts them."""
from __future__ import annotations

import numpy as np
import potpourri3d as pp3d
import pytest
import trimesh
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from retrotouch.nodes.data.types import CurveSet, Mesh
from retrotouch.nodes.geometry.thin_walls import GRAPH_STRETCH, corner_reach, thin_walls
from retrotouch.nodes.layout.clearance import clearance_profile, close_pairs, free_end_trims
from retrotouch.nodes.mesh.repair import RemeshParams, remesh

THICKNESS_MM = 1.5
RADIUS_MM = 2.25  # the clearance bound 2 mm plus one resampling step


@pytest.fixture(scope="module")
def plate() -> Mesh:
    """A 60 x 40 x 1.5 mm plate, remeshed as the pipeline does (edges about 1 mm)."""
    box = trimesh.creation.box(extents=[60.0, 40.0, THICKNESS_MM])
    return remesh(RemeshParams(target_edge_mm=1.0), Mesh(np.asarray(box.vertices), np.asarray(box.faces, dtype=np.int64), "plate"))


def on_surface(mesh: Mesh, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(faces, closest points) of ``points`` on the mesh."""
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    closest, _, face = trimesh.proximity.closest_point(tm, points)
    return np.asarray(face, dtype=np.int64), closest


def apart(mesh: Mesh, walls, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    fa, pa = on_surface(mesh, a)
    fb, pb = on_surface(mesh, b)
    return walls.apart(walls.corners_of(fa, pa), walls.corners_of(fb, pb))


def test_the_two_sides_of_a_thin_plate_are_apart_except_round_its_rim(plate):
    walls = thin_walls(plate.vertices, plate.faces, RADIUS_MM)
    half = THICKNESS_MM / 2
    x = np.linspace(-20.0, 20.0, 9)
    top = np.stack([x, np.zeros_like(x), np.full_like(x, half)], axis=1)
    assert apart(plate, walls, top, top * [1, 1, -1]).all()  # across the plate, 10-30 mm from its rim
    assert not apart(plate, walls, top, top + [1.5, 0.0, 0.0]).any()  # side by side on top
    rim = np.array([[29.8, 0.0, half], [29.8, 5.0, half]])  # 0.2 mm from the rim: 1.9 mm round it
    assert not apart(plate, walls, rim, rim * [1, 1, -1]).any()


def test_a_sphere_has_no_walls():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=20.0)
    assert len(thin_walls(np.asarray(sphere.vertices), np.asarray(sphere.faces), RADIUS_MM).keys) == 0


def test_edge_paths_on_the_remesh_stay_within_the_stated_stretch_of_the_geodesic(plate):
    """The bound the walls rest on: shortest edge paths at most ``GRAPH_STRETCH`` times the exact
    geodesic (potpourri3d's edge-flip paths), for vertex pairs 2-12 mm apart along the surface."""
    V, F = plate.vertices, plate.faces
    edges = np.unique(np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1), axis=0)
    length = np.linalg.norm(V[edges[:, 0]] - V[edges[:, 1]], axis=1)
    graph = csr_matrix((np.r_[length, length], (np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]])),
                       shape=(len(V), len(V)))
    rng = np.random.default_rng(0)
    sources = rng.choice(len(V), 20, replace=False)
    paths = dijkstra(graph, indices=sources, limit=14.0)
    solver = pp3d.EdgeFlipGeodesicSolver(V, F)
    ratios = []
    for row, source in enumerate(sources):
        targets = np.flatnonzero((paths[row] > 2.0) & (paths[row] < 12.0))
        for target in rng.choice(targets, 8, replace=False):
            geodesic = solver.find_geodesic_path(int(source), int(target))
            ratios.append(paths[row, target] / np.linalg.norm(np.diff(geodesic, axis=0), axis=1).sum())
    assert 1.0 - 1e-6 <= min(ratios) and max(ratios) < GRAPH_STRETCH
    assert corner_reach(V, F) < 1.5  # a point stands for a corner about an edge away


def strip_curves(mesh: Mesh, z_mm: list[float], y_mm: list[float]) -> CurveSet:
    """Straight curves along x (-25..25 mm) on the plate's top or bottom (z = +-0.75 mm), one per (z, y)."""
    x = np.linspace(-25.0, 25.0, 101)
    rows = []
    for z, y in zip(z_mm, y_mm):
        rows.append(np.stack([x, np.full_like(x, y), np.full_like(x, z)], axis=1))
    faces, points = on_surface(mesh, np.concatenate(rows))
    n = len(rows)
    return CurveSet(layer="tx", points=points, faces=faces, bary=np.full((len(points), 3), 1 / 3),
                    offsets=np.arange(n + 1, dtype=np.int64) * len(x), lengths_mm=np.full(n, 50.0),
                    end_reason=np.zeros(n, dtype=np.int8), angle=0.0)


def test_traces_on_the_two_sides_of_a_thin_wall_do_not_conflict_but_side_by_side_ones_do(plate):
    walls = thin_walls(plate.vertices, plate.faces, RADIUS_MM)
    everywhere = np.ones(len(plate.faces), dtype=bool)
    half = THICKNESS_MM / 2
    curves = strip_curves(plate, [half, -half, half], [0.0, 0.0, 1.5])  # top, under it, beside it on top
    assert close_pairs(curves, everywhere, 2.0).tolist() == [[0, 1], [0, 2], [1, 2]]  # in space
    assert close_pairs(curves, everywhere, 2.0, walls=walls).tolist() == [[0, 2]]  # 1 and 2: 2.1 mm apart across the wall
    profile = clearance_profile(strip_curves(plate, [half, -half], [0.0, 0.0]), everywhere, 2.0, walls=walls)
    assert profile["min_distance_in_space_mm"] == pytest.approx(THICKNESS_MM, abs=0.05)
    assert profile["min_centre_distance_mm"] >= RADIUS_MM - 1e-9 and profile["length_closer_than_bound_mm"] == 0.0
    with pytest.raises(ValueError, match="cannot judge"):
        close_pairs(curves, everywhere, 3.0, walls=walls)  # walls made for a smaller radius


def test_free_ends_are_not_cut_back_for_a_trace_across_a_wall(plate):
    walls = thin_walls(plate.vertices, plate.faces, RADIUS_MM)
    everywhere = np.ones(len(plate.faces), dtype=bool)
    half = THICKNESS_MM / 2
    curves = strip_curves(plate, [half, -half], [0.0, 0.0])
    assert free_end_trims(curves, everywhere, 2.0, free_mm=20.0).tolist() != [0, 0]
    assert free_end_trims(curves, everywhere, 2.0, free_mm=20.0, walls=walls).tolist() == [0, 0]
