"""curves.trace_grid: lines across and along the surface from rim to rim, a Tx and an Rx family of their own."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import shapes
from curves_fixture import bunny, load_scaled, regions_for

from retrotouch.graph.errors import UserError
from retrotouch.nodes.curves.crossings import CrossingsParams, crossings
from retrotouch.nodes.curves.grid import (GridLayersParams, TraceGridParams, boundary_loops, disc_distances, distance_share,
                                          grid_layers, plan_coordinates, principal_axis, rim_arcs, trace_grid)
from retrotouch.nodes.data.types import CurveEnd
from retrotouch.nodes.geometry.mesh_tables import build_tables


@pytest.fixture(scope="module")
def grid():
    mesh, regions, _, tx_field, rx_field = bunny()
    tables = build_tables(mesh.vertices, mesh.faces)
    domain = ~(regions.base_faces | regions.exclusion_base)
    return mesh, regions, tx_field, rx_field, tables, domain


def test_the_rim_is_one_loop_split_into_two_ends_and_two_sides(grid):
    _, _, _, _, tables, domain = grid
    loops = boundary_loops(tables, domain)
    assert len(loops) == 1
    rim = loops[0]
    assert len(np.unique(rim)) == len(rim)
    # each step of the loop is an edge between a domain face (on its left) and a face off it
    step = np.c_[rim, np.roll(rim, -1)]
    key = {tuple(e): i for i, e in enumerate(tables.edges.tolist())}
    edge = np.array([key[tuple(sorted(pair))] for pair in step.tolist()])
    left = np.where(tables.edges[edge, 0] == step[:, 0], tables.edge_faces[edge, 0], tables.edge_faces[edge, 1])
    right = np.where(tables.edges[edge, 0] == step[:, 0], tables.edge_faces[edge, 1], tables.edge_faces[edge, 0])
    assert domain[left].all() and not domain[right].any()
    share = 0.1
    arcs = rim_arcs(tables, domain, rim, share)
    labels = np.full(len(rim), -1)
    for k, arc in enumerate(arcs):
        labels[np.isin(rim, arc)] = k
    assert (labels >= 0).all() and sum(len(a) for a in arcs) == len(rim)  # a partition of the rim
    # walking the rim: end a, side c, end b, side d, each one run
    runs = labels[np.r_[True, labels[1:] != labels[:-1]]]
    runs = runs[:-1] if runs[0] == runs[-1] and len(runs) > 1 else runs
    assert len(runs) == 4
    start = int(np.argmax(runs == 0))
    assert list(np.roll(runs, -start)) == [0, 2, 1, 3]
    length = np.linalg.norm(tables.vertices[np.roll(rim, -1)] - tables.vertices[rim], axis=1)
    for end in arcs[:2]:
        assert np.isin(rim, end) @ length == pytest.approx(share * length.sum(), rel=0.15)


def test_the_distance_shares_are_0_and_1_on_their_arcs_and_between_inside(grid):
    _, _, _, _, tables, domain = grid
    end_a, end_b, _, _ = rim_arcs(tables, domain, boundary_loops(tables, domain)[0], 0.1)
    u = distance_share(disc_distances(tables, domain), end_a, end_b)
    inside = np.unique(tables.faces[domain])
    assert np.isnan(np.delete(u, inside)).all() and np.isfinite(u[inside]).all()
    assert (u[end_a] == 0).all() and (u[end_b] == 1).all()
    assert u[inside].min() >= 0.0 and u[inside].max() <= 1.0
    assert 0.3 < np.median(u[inside]) < 0.7


def test_the_lines_across_a_flat_oval_are_evenly_spread_along_it(tmp_path):
    # A flat oval (160 x 40 x 3 mm): along its long axis the share of the way from one end to the other
    # grows linearly once clear of the end arcs (which wrap the tips), so evenly spread levels are
    # evenly spread lines there, where the oval is wide as where it narrows. (The coordinates of a
    # conformal map crowd their lines where it narrows: gaps 3.0 to 4.2 mm over the same 27.)
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=6)
    path = tmp_path / "oval.ply"
    trimesh.Trimesh(sphere.vertices * np.array([80.0, 20.0, 1.5]), sphere.faces).export(path)
    mesh = load_scaled(path, diagonal_mm=float(np.linalg.norm((160.0, 40.0, 3.0))), target_vertices=6000)
    params = TraceGridParams(n_reseeded=0)
    across = trace_grid(params, mesh, regions_for(mesh))["across"]
    side, axis = np.argsort(np.ptp(mesh.vertices, axis=0))[1:]  # across the oval, along it
    middles = []
    for c in range(across.count):  # where each line crosses the long axis
        points = across.points[across.curve(c)]
        middles.append(points[np.argmin(np.abs(points[:, side] - mesh.vertices[:, side].mean())), axis])
    gaps = np.diff(np.sort(middles))[6:-6]  # the middle 27 gaps, between lines clear of the end arcs
    assert len(middles) == params.n_across
    assert gaps.max() < 1.25 * gaps.min()


@pytest.mark.parametrize("tx", ["across", "along"])
def test_grid_lines_run_rim_to_rim_and_cross_once_far_from_tangent(grid, tx):
    mesh, regions, tx_field, rx_field, tables, domain = grid
    params = TraceGridParams()
    out = grid_layers(GridLayersParams(tx=tx), mesh, **trace_grid(params, mesh, regions))
    tx_lines, rx_lines = out["tx"], out["rx"]
    assert tx_lines.layer == "tx" and rx_lines.layer == "rx" and tx_lines.family == rx_lines.family == "grid"
    n_tx, n_rx = (params.n_across, params.n_along) if tx == "across" else (params.n_along, params.n_across)
    assert 0.8 * n_tx <= tx_lines.count <= n_tx + params.n_reseeded
    assert 0.8 * n_rx <= rx_lines.count <= n_rx + params.n_reseeded
    assert np.all(tx_lines.end_reason == int(CurveEnd.BASE)) and np.all(rx_lines.end_reason == int(CurveEnd.BASE))
    off_domain = np.flatnonzero(~domain)
    end_a, end_b, side_c, side_d = rim_arcs(tables, domain, boundary_loops(tables, domain)[0], params.end_share)
    distances = disc_distances(tables, domain)
    across, along = distance_share(distances, end_a, end_b), distance_share(distances, side_c, side_d)
    other = {"across": along, "along": across}
    for curves, sense, name in ((tx_lines, -1, tx), (rx_lines, 1, "along" if tx == "across" else "across")):
        assert domain[curves.faces].all()
        for c in range(curves.count):
            rows = curves.curve(c)
            for end in (0, -1):  # both ends lie on an edge of a face off the domain (base or its exclusion)
                corners = tables.faces[curves.faces[rows][end]][curves.bary[rows][end] > 1e-9]
                assert np.isin(corners, tables.faces[off_domain]).all()
            # an Rx line runs the way the other function grows, a Tx line (walked backwards) against it
            ends = (other[name][tables.faces[curves.faces[rows][[0, -1]]]] * curves.bary[rows][[0, -1]]).sum(axis=1)
            assert sense * (ends[1] - ends[0]) > 0
    cross = crossings(CrossingsParams(), mesh, tx_lines, rx_lines, tx_field, rx_field)
    assert len(cross["tx_tx"].curve_a) == 0 and len(cross["rx_rx"].curve_a) == 0  # level sets of one function
    pairs = np.bincount(cross["tx_rx"].curve_a * rx_lines.count + cross["tx_rx"].curve_b, minlength=tx_lines.count * rx_lines.count)
    assert (pairs <= 1).mean() > 0.99 and (pairs == 1).mean() > 0.9
    # the lines of the two families cross far from tangent (a pad at a crossing has room on both traces)
    t = tx_lines.points[tx_lines.offsets[cross["tx_rx"].curve_a] + cross["tx_rx"].seg_a + 1] - tx_lines.points[tx_lines.offsets[cross["tx_rx"].curve_a] + cross["tx_rx"].seg_a]
    r = rx_lines.points[rx_lines.offsets[cross["tx_rx"].curve_b] + cross["tx_rx"].seg_b + 1] - rx_lines.points[rx_lines.offsets[cross["tx_rx"].curve_b] + cross["tx_rx"].seg_b]
    cos = np.abs(np.einsum("ij,ij->i", t, r)) / (np.linalg.norm(t, axis=1) * np.linalg.norm(r, axis=1))
    assert np.median(np.degrees(np.arccos(cos))) > 60.0


def test_a_surface_with_no_rim_is_refused_with_the_nodes_to_remove(grid):
    mesh, regions, *_ = grid
    none = np.zeros_like(regions.base_faces)
    with pytest.raises(UserError, match="remove the grid nodes"):
        trace_grid(TraceGridParams(), mesh, dataclasses.replace(regions, base_faces=none, exclusion_base=none))


def test_the_layers_are_the_two_families_and_the_tx_lines_are_them_walked_backwards(grid):
    mesh, regions, *_ = grid
    families = trace_grid(TraceGridParams(), mesh, regions)
    for tx, rx in (("across", "along"), ("along", "across")):
        out = grid_layers(GridLayersParams(tx=tx), mesh, **families)
        source = families[tx]
        assert out["tx"].count == source.count and out["rx"].count == families[rx].count
        np.testing.assert_array_equal(out["rx"].points, families[rx].points)
        for c in range(source.count):
            np.testing.assert_allclose(out["tx"].points[out["tx"].curve(c)], source.points[source.curve(c)][::-1], atol=1e-9)
        np.testing.assert_allclose(out["tx"].lengths_mm, source.lengths_mm)
        assert out["tx"].angle == out["rx"].angle == (0.0 if tx == "across" else np.pi / 2)


def test_a_strip_narrower_than_a_finger_still_gets_lines_across(tmp_path):
    # A blade lying flat, 6 mm wide and 1 mm thick: every line across it is about 8 mm long, side to
    # side over the top. A line that holds one pad is a candidate: 40 of them cross the strip.
    import trimesh

    path = tmp_path / "strip.ply"
    trimesh.creation.box(extents=(150.0, 6.0, 1.0)).export(path)
    mesh = load_scaled(path, diagonal_mm=150.1, target_vertices=4000)
    regions = regions_for(mesh)
    params = TraceGridParams()
    across = trace_grid(params, mesh, regions)["across"]
    assert params.n_across <= across.count <= params.n_across + params.n_reseeded
    assert np.median(across.lengths_mm) < 10.0
    centres = np.array([across.points[across.curve(c)].mean(axis=0) for c in range(across.count)])
    axis = np.argmax(np.ptp(mesh.vertices, axis=0))
    spread = np.sort(centres[:, axis])
    assert spread[-1] - spread[0] > 0.8 * np.ptp(mesh.vertices[:, axis])  # along the whole strip


def test_plan_coordinates_are_the_position_seen_from_above_and_their_lines_plane_cuts(tmp_path):
    # A starfish lying on the table: each coordinate is the position along a horizontal axis scaled to
    # [0, 1] over the disc, so its level sets are the disc cut by vertical planes, one piece per arm
    # they pass through, each a candidate of its own.
    path = shapes.write_shape("starfish", tmp_path)
    mesh = load_scaled(path, diagonal_mm=shapes.diagonal_mm("starfish"), target_vertices=4000)
    regions = regions_for(mesh)
    tables = build_tables(mesh.vertices, mesh.faces)
    domain = ~(regions.base_faces | regions.exclusion_base)
    inside = np.unique(tables.faces[domain])
    for u in plan_coordinates(tables, domain, regions.up):
        assert np.isnan(np.delete(u, inside)).all()
        assert u[inside].min() == 0.0 and u[inside].max() == 1.0
    _, axis = principal_axis(tables, domain, regions.up)
    assert abs(axis @ regions.up) < 1e-9 and abs(np.linalg.norm(axis) - 1.0) < 1e-9
    params = TraceGridParams(coordinates="plan")
    families = trace_grid(params, mesh, regions)
    for name, direction, n in (("across", axis, params.n_across), ("along", np.cross(regions.up, axis), params.n_along)):
        curves = families[name]
        assert curves.family == "grid_plan"
        positions = np.array([np.ptp(curves.points[curves.curve(c)] @ direction) for c in range(curves.count)])
        assert positions.max() < 1e-6  # each line lies in one vertical plane
        levels = np.unique(np.round([curves.points[curves.curve(c)][0] @ direction for c in range(curves.count)], 6))
        assert len(levels) <= n + params.n_reseeded < curves.count  # levels through two arms give two pieces
