"""curves.trace_helices: Rx helices around the Tx pole (level sets of ``rho + theta``), no corridor."""
from __future__ import annotations

import numpy as np
import pytest
from curves_fixture import bunny

from retrotouch.graph.errors import UserError
from retrotouch.nodes.curves.crossings import CrossingsParams, crossings
from retrotouch.nodes.curves.helices import (ALONG_MM, BASE_RHO, MIN_CROSSING_ANGLE_DEG, TraceHelicesParams, cut_path,
                                             helix_function, trace_helices, winding_angle)
from retrotouch.nodes.curves.ring_levels import POLE_START, LevelSets, RingLevelsParams, ring_levels, row_values
from retrotouch.nodes.curves.tracing import TraceTxParams, trace_tx
from retrotouch.nodes.data.types import CurveEnd
from retrotouch.nodes.geometry.mesh_tables import build_tables


@pytest.fixture(scope="module")
def family():
    mesh, regions, _, tx_field, rx_field = bunny()
    tx = trace_tx(TraceTxParams(n_curves=100), mesh, regions, tx_field)["curves"]
    levels = ring_levels(RingLevelsParams(), mesh, regions, tx_field, tx)
    tables = build_tables(mesh.vertices, mesh.faces)
    return mesh, regions, tx, tx_field, rx_field, levels, tables


@pytest.fixture(scope="module")
def theta(family):
    _, _, _, tx_field, _, levels, tables = family
    return winding_angle(tables, levels.values, tx_field.face_direction)


def unwrapped(turns: np.ndarray) -> np.ndarray:
    return np.unwrap(turns * 2 * np.pi) / (2 * np.pi)


def test_the_angle_winds_once_round_the_pole_and_holds_along_the_tx_lines(family, theta):
    mesh, regions, tx, tx_field, _, levels, tables = family
    u = levels.values
    between = (u > 0) & (u < 1)
    assert np.isfinite(theta[between]).all() and ((theta[between] >= 0) & (theta[between] < 1)).all()
    # once round a level set of u (a closed loop around the pole): the angle changes by one whole turn
    faces, p, _ = LevelSets(tables, u, np.asarray(regions.sensing_faces, dtype=bool))(0.5)
    loop = row_values(tables, theta, faces, np.clip(tables.bary_of_points(faces, p), 0, 1))
    assert abs(np.diff(unwrapped(np.r_[loop, loop[:1]])).sum()) == pytest.approx(1.0, abs=1e-6)
    # along the Tx candidates (away from the pole's and the base's boundary) it barely changes
    spread = []
    for c in range(tx.count):
        rows = tx.curve(c)
        u_rows = row_values(tables, u, tx.faces[rows], tx.bary[rows])
        inside = (u_rows > 0.05) & (u_rows < 0.95)
        if inside.sum() > 2:
            spread.append(np.ptp(unwrapped(row_values(tables, theta, tx.faces[rows][inside], tx.bary[rows][inside]))))
    assert np.median(spread) < 0.05


def test_the_angle_grows_clockwise_seen_from_outside_at_the_pole(family, theta):
    mesh, _, _, tx_field, _, levels, tables = family
    u = levels.values[tables.faces]
    near = np.flatnonzero((u.min(axis=1) > 0.0) & (u.max(axis=1) < 0.3))  # faces round the pole
    corner = theta[tables.faces[near]]
    corner = corner - np.round(corner - corner[:, :1])  # one face's corners on one branch of the angle
    grad = np.einsum("kij,ki->kj", tables.bary_gradients[near], corner)
    radial = mesh.vertices[tables.faces[near]].mean(axis=1) - mesh.vertices[tx_field.start_vertex]
    turn = np.einsum("ij,ij->i", np.cross(radial, grad), tables.normals[near])
    assert np.mean(turn < 0) > 0.9  # counter-clockwise about the outward normal is positive


@pytest.mark.parametrize("winding,climb", [("left", "median"), ("right", "median"), ("left", "per_line")])
def test_helices_start_on_the_base_climb_and_never_meet(family, theta, winding, climb):
    mesh, regions, tx, tx_field, rx_field, levels, tables = family
    params = TraceHelicesParams(winding=winding, climb=climb)
    helices = trace_helices(params, mesh, regions, levels, theta, tx, tx_field)["curves"]
    assert helices.layer == "rx" and helices.family == ("helices" if climb == "median" else "helices_per_line")
    assert params.n_helices - params.n_reseeded <= helices.count <= params.n_helices
    assert np.all(helices.end_reason == int(CurveEnd.BASE))
    rho = helix_function(tables, levels, theta, tx, winding, climb).rho
    sense = 1 if winding == "left" else -1
    turns = []
    for c in range(helices.count):
        rows = helices.curve(c)
        r = row_values(tables, rho, helices.faces[rows], helices.bary[rows])
        assert r[0] > 0.97  # wired end on the base
        assert r[-1] < r[0] - 0.1  # climbed towards the pole
        t = unwrapped(row_values(tables, theta, helices.faces[rows], helices.bary[rows]))
        turns.append(sense * (t[-1] - t[0]))
    assert 0.3 < np.median(turns) <= 1.0 + 1e-6  # at most one turn round the pole, in its winding sense
    cross = crossings(CrossingsParams(), mesh, tx, helices, tx_field, rx_field)
    assert len(cross["rx_rx"].curve_a) == 0  # level sets of one function never meet


def arc_deviation(tables, tx, u: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """Per Tx candidate from the pole's exclusion: the largest difference between ``rho`` and the
    share of the line's length walked."""
    deviation = []
    for c in range(tx.count):
        rows = tx.curve(c)
        if row_values(tables, u, tx.faces[rows][:1], tx.bary[rows][:1])[0] > POLE_START:
            continue  # reseeded from a free end, not from the pole
        step = np.linalg.norm(np.diff(tx.points[rows], axis=0), axis=1)
        walked = np.r_[0.0, np.cumsum(step)] / step.sum()
        deviation.append(np.abs(row_values(tables, rho, tx.faces[rows], tx.bary[rows]) - walked).max())
    return np.asarray(deviation)


def test_per_line_climb_is_each_tx_lines_share_of_its_length(family, theta):
    # The median climb is one function of u for all lines; lines of other lengths (a detour through
    # the second ear) climb at another rate. The per-line climb follows each line's own length.
    mesh, regions, tx, tx_field, _, levels, tables = family
    per_line = arc_deviation(tables, tx, levels.values, helix_function(tables, levels, theta, tx, "left", "per_line").rho)
    median = arc_deviation(tables, tx, levels.values, helix_function(tables, levels, theta, tx, "left", "median").rho)
    assert len(per_line) > 0.5 * tx.count  # most lines start at the pole
    assert np.percentile(per_line, 90) < 0.1
    assert np.percentile(per_line, 90) < 0.5 * np.percentile(median, 90)


def mean_cos_along(points: np.ndarray, direction: np.ndarray, j: int) -> float:
    """Length-weighted mean |cos| between a polyline and ``direction`` (per segment) over the ALONG_MM
    centred on segment ``j`` (each segment clipped to the window, the window to the polyline)."""
    segment = np.diff(points, axis=0)
    length = np.linalg.norm(segment, axis=1)
    cos = np.abs(np.einsum("ij,ij->i", segment, direction)) / np.maximum(length, 1e-12)
    start = np.r_[0.0, np.cumsum(length)[:-1]]
    middle = start[j] + 0.5 * length[j]
    lo, hi = max(middle - 0.5 * ALONG_MM, 0.0), min(middle + 0.5 * ALONG_MM, start[-1] + length[-1])
    inside = np.clip(np.minimum(start + length, hi) - np.maximum(start, lo), 0.0, None)
    return float((inside * cos).sum() / (hi - lo))


@pytest.mark.parametrize("min_angle_deg", [MIN_CROSSING_ANGLE_DEG, 20.0])
def test_a_helix_stops_where_it_would_run_along_the_tx_lines(family, theta, min_angle_deg):
    # Off the base, no ALONG_MM of a kept helix runs nearer the Tx lines' direction than the angle
    # allows, and a helix is cut only there: its uncut walk (angle 0) goes on with a window that does.
    mesh, regions, tx, tx_field, _, levels, tables = family
    limit = np.cos(np.radians(min_angle_deg))
    cut = trace_helices(TraceHelicesParams(min_crossing_angle_deg=min_angle_deg), mesh, regions, levels, theta, tx, tx_field)["curves"]
    whole = trace_helices(TraceHelicesParams(min_crossing_angle_deg=0.0), mesh, regions, levels, theta, tx, tx_field)["curves"]
    rho = helix_function(tables, levels, theta, tx, "left", "median").rho
    assert cut.count == whole.count
    shortened = 0
    for c in range(cut.count):
        rows, whole_rows = cut.curve(c), whole.curve(c)
        n = rows.stop - rows.start
        assert np.array_equal(cut.points[rows], whole.points[whole_rows][:n])  # a prefix of the whole walk
        points, direction = whole.points[whole_rows], tx_field.face_direction[whole.faces[whole_rows][:-1]]
        r = row_values(tables, rho, whole.faces[whole_rows], whole.bary[whole_rows])
        off_base = np.maximum(r[:-1], r[1:]) < BASE_RHO
        assert all(mean_cos_along(points, direction, j) <= limit + 1e-9 for j in np.flatnonzero(off_base[: n - 1]))
        if n < whole_rows.stop - whole_rows.start:
            shortened += 1
            assert off_base[n - 1] and mean_cos_along(points, direction, n - 1) > limit
    if min_angle_deg > 15.0:  # the bunny's helices cross the Tx lines at 12-16 deg near the pole
        assert shortened > cut.count // 2


def test_each_helix_crosses_most_tx_lines_once_and_none_twice(family, theta):
    # Bunny fixture: shares crossed once 0.64-0.86 per helix (rings 0.55-0.675 median over nine remeshes).
    mesh, regions, tx, tx_field, rx_field, levels, _ = family
    helices = trace_helices(TraceHelicesParams(), mesh, regions, levels, theta, tx, tx_field)["curves"]
    cross = crossings(CrossingsParams(), mesh, tx, helices, tx_field, rx_field)["tx_rx"]
    counts = np.bincount(cross.curve_a * helices.count + cross.curve_b, minlength=tx.count * helices.count)
    counts = counts.reshape(tx.count, helices.count)
    assert np.median((counts == 1).mean(axis=0)) >= 0.5
    assert (counts >= 2).mean() < 0.02


def test_a_region_that_does_not_join_pole_and_base_is_refused(family):
    _, _, _, _, _, levels, tables = family
    u = levels.values
    region = np.zeros(len(tables.faces), dtype=bool)
    region[np.flatnonzero(u[tables.faces].max(axis=1) <= 0.0)[:10]] = True  # faces inside the pole's exclusion only
    with pytest.raises(UserError, match="rings or dipole"):
        cut_path(tables, u, region)


def test_an_island_between_the_levels_that_the_cut_misses_gets_no_angle(family, theta):
    # Faces between the pole's exclusion and the base that the cut's piece does not reach (here: a
    # patch in the middle of the base lifted to u = 0.5; on the lying sword, 357 vertices on its
    # other side) have no winding angle: NaN there, the rest unchanged (the Cholesky would fail on them).
    _, regions, _, tx_field, _, levels, tables = family
    u = levels.values.copy()
    island = np.array([regions.base_centre])
    for _ in range(2):
        island = np.unique(tables.faces[np.isin(tables.faces, island).any(axis=1)])
    assert (u[island] >= 1.0).all()
    u[island] = 0.5
    lifted = winding_angle(tables, u, tx_field.face_direction)
    assert np.isnan(lifted[island]).all()
    kept = np.isfinite(theta)
    np.testing.assert_allclose(lifted[kept], theta[kept], atol=1e-9)
