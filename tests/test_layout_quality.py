"""Bounds on layout quality over the bunny and ../shared/meshes (layouts at test size, see
tests/layout_quality.py). The hard constraint holds everywhere; the quality bounds are the worst case
measured over the whole set (recorded in the commit that set them) with a 10 % margin, so a change
that makes any mesh worse than today's worst fails, and so does one that breaks the median."""
from __future__ import annotations

import numpy as np
import pytest
from layout_quality import BUNNY, SHARED, layout_metrics

MESHES = [BUNNY] + SHARED
NOT_LAYOUT = {"airplane_oded": "regions.detect finds a base without an interior vertex (issue of the regions stage)"}
NO_SINGLE_CROSSING = {"scorpion_lowres_oded"}  # no Tx/Rx candidate pair crosses exactly once at test size

# Measured 2026-12-01 over the 14 meshes with a layout (bunny + 13 shared), worst / median:
# cells 2 (human_man_oded) / 49, Voronoi CV over all crossings 1.512 (hand_closed_oded) / 0.971,
# coverage radius 88.1 mm (sword_oded) / 40.2 mm, min same-layer clearance 2.247 mm / 2.258 mm.
# A run with CP-SAT's former 4x wall-clock guard gave spot_crane a CV over all crossings of 1.896 (0.978
# in another); the CV bound still covers it. CP-SAT now stops on deterministic time only, so these
# figures no longer depend on the machine's load.
MIN_CELLS = 1
MAX_CV_ALL = 2.1
MAX_RADIUS_MM = 97.0
MEDIAN_CELLS = 44
MEDIAN_RADIUS_MM = 44.0


def name(path: str) -> str:
    return path.rsplit("/", 1)[-1].removesuffix(".ply").removesuffix(".obj")


def metrics_of(path: str) -> dict:
    if name(path) in NOT_LAYOUT:
        pytest.skip(NOT_LAYOUT[name(path)])
    return layout_metrics(path)


@pytest.mark.parametrize("path", MESHES, ids=[name(p) for p in MESHES])
def test_same_layer_clearance_holds_on_every_mesh(path):
    m = metrics_of(path)
    if name(path) in NO_SINGLE_CROSSING:
        assert not m["feasible"] and "crosses exactly once" in m["message"]
        return
    assert m["feasible"], m["message"]
    bound = m["trace_width_mm"] + m["clearance_mm"]
    assert m["min_same_layer_clearance_mm"] >= bound
    assert all(c["length_closer_than_bound_mm"] == 0.0 for c in m["same_layer_clearance"].values())


@pytest.mark.parametrize("path", MESHES, ids=[name(p) for p in MESHES])
def test_layout_quality_is_no_worse_than_the_measured_worst_case(path):
    m = metrics_of(path)
    if not m["feasible"]:
        pytest.skip(m["message"])  # asserted in the clearance test
    assert m["cells"] >= MIN_CELLS
    assert m["voronoi_cv_all_crossings"] <= MAX_CV_ALL
    assert m["coverage_radius_mm"] <= MAX_RADIUS_MM


@pytest.mark.skipif(not SHARED, reason="no shared meshes in ../shared/meshes")
def test_median_layout_quality_over_the_set():
    rows = []
    for path in MESHES:
        if name(path) in NOT_LAYOUT or name(path) in NO_SINGLE_CROSSING:
            continue
        m = layout_metrics(path)
        assert m["feasible"], f"{name(path)}: {m['message']}"
        rows.append((m["cells"], m["coverage_radius_mm"]))
    cells, radius = np.array(rows).T
    assert np.median(cells) >= MEDIAN_CELLS and np.median(radius) <= MEDIAN_RADIUS_MM
