"""Bounds on layout quality over the bunny and ../shared/meshes (layouts at test size, see
tests/layout_quality.py), for the dipole loops at 0 deg and the rings (side-by-side legs) with their
corridor at turn 0. The hard constraint holds everywhere; the quality bounds are the worst case
measured over the whole set and over several remeshes of each (recorded below) with a 15 % margin,
so a change that makes any mesh worse than today's worst fails, and so does one that breaks the median."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from layout_quality import BUNNY, SHARED, layout_metrics

MESHES = [BUNNY] + SHARED


@dataclasses.dataclass(frozen=True)
class Bounds:
    branch: dict  # layout_metrics keyword arguments
    min_cells: int
    max_cv_all: float
    max_radius_mm: float
    median_cells: float
    median_radius_mm: float


# Measured 2026-12-02 over the 16 meshes (bunny + 15 shared; every one has a layout) on nine or ten remeshes
# of each (unperturbed, RETROTOUCH_TEST_JITTER=1e-6:1..8, and for the dipole CI's machine, where the
# same code gives other remeshes), CP-SAT on deterministic time only.
# Dipole: worst cells 2, worst Voronoi CV over all crossings 2.58, worst coverage radius 116.0 mm;
# medians per remesh: cells 24-34, radius 50.5-57.6 mm (62.5 on CI's machine).
# Rings: worst cells 1, worst CV 1.92, worst radius 157.2 mm (the scorpion, whose best branch is another);
# medians: cells 63-81, radius 33.8-41.6 mm.
# The same nine remeshes with the power-mean stage stopping at a 2 % gap (dipole / rings): medians cells
# 24-34 / 63-84.5, radius 50.5-57.6 / 33.8-41.6 mm; worst radius 116.0 / 157.2 mm, worst CV 2.58 / 1.89.
# One object's layout varies that much between remeshes, so the bounds are the worst remesh's with a
# 15 % margin.
# 2026-12-06, the table side of thin objects (their base takes the underside no fingertip reaches above
# the table): the human figure lies flat as a thin object at this size (the pipeline's 20k-vertex remesh
# stands it up), and its rings at turn 0 go from 18 to 8 cells, Voronoi CV over all crossings
# 1.29 -> 2.41, radius 71 -> 111 mm: the rings' CV bound is 2.41 with the same margin.
# 2026-12-07: the fixture's remesh no longer depends on what pymeshlab ran before in the process (its
# surface-distance check is off, as in the pipeline's remesh); every test module passes unchanged.
FAMILIES = {
    "dipole": Bounds({"rx_angle_deg": 0.0}, 1, 2.95, 133.0, 20, 72.0),
    "rings": Bounds({"ring_turn": 0.0}, 1, 2.8, 181.0, 54, 48.0),
}


def name(path: str) -> str:
    return path.rsplit("/", 1)[-1].removesuffix(".ply").removesuffix(".obj")


CASES = [(path, family) for family in FAMILIES for path in MESHES]
IDS = [f"{family}-{name(path)}" for path, family in CASES]


@pytest.mark.parametrize(("path", "family"), CASES, ids=IDS)
def test_same_layer_clearance_holds_on_every_mesh(path, family):
    m = layout_metrics(path, **FAMILIES[family].branch)
    assert m["feasible"], m["message"]
    bound = m["trace_width_mm"] + m["clearance_mm"]
    if m["min_same_layer_clearance_mm"] is None:  # no layer has two traces to measure between
        assert m["tx_channels"] <= 1 and m["rx_channels"] <= 1
    else:
        assert m["min_same_layer_clearance_mm"] >= bound
    assert all(c["length_closer_than_bound_mm"] == 0.0 for c in m["same_layer_clearance"].values())


@pytest.mark.parametrize(("path", "family"), CASES, ids=IDS)
def test_layout_quality_is_no_worse_than_the_measured_worst_case(path, family):
    bounds = FAMILIES[family]
    m = layout_metrics(path, **bounds.branch)
    assert m["feasible"], m["message"]
    assert m["cells"] >= bounds.min_cells
    assert m["voronoi_cv_all_crossings"] <= bounds.max_cv_all
    assert m["coverage_radius_mm"] <= bounds.max_radius_mm
    # the samples' coverage radius, checked over every vertex of the region, is never smaller
    # (to the heat method's 1 mm: samples and vertices are sources in turn)
    assert m["coverage_radius_vertices_mm"] >= m["coverage_radius_mm"] - 1.0


@pytest.mark.skipif(not SHARED, reason="no shared meshes in ../shared/meshes")
@pytest.mark.parametrize("family", FAMILIES)
def test_median_layout_quality_over_the_set(family):
    bounds = FAMILIES[family]
    rows = []
    for path in MESHES:
        m = layout_metrics(path, **bounds.branch)
        assert m["feasible"], f"{name(path)}: {m['message']}"
        rows.append((m["cells"], m["coverage_radius_mm"]))
    cells, radius = np.array(rows).T
    assert np.median(cells) >= bounds.median_cells and np.median(radius) <= bounds.median_radius_mm
