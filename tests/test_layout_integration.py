"""The layout nodes on real curve families: pymeshlab's bunny (170 mm, ~4k vertices), Tx and one
Rx angle traced by the curve nodes, crossings from ``curves.crossings``."""
from __future__ import annotations

import json

import numpy as np
import pytest
from curves_fixture import bunny
from test_layout_sensing_map import validate_sensing_map

from retrotouch.nodes.curves.crossings import CrossingsParams, crossings
from retrotouch.nodes.layout.sweep import OptimizeParams, PickParams, optimize, pick_best
from retrotouch.nodes.layout.sensing_map import SensingMapParams, write_sensing_map
from retrotouch.nodes.layout.samples import SamplesParams, geodesics_for, surface_samples
from retrotouch.nodes.curves.tracing import TraceRxParams, TraceTxParams, trace_rx, trace_tx


@pytest.fixture(scope="module")
def bunny_run():
    mesh, regions, _, tx_field, rx_field = bunny()
    tx = trace_tx(TraceTxParams(n_curves=40), mesh, regions, tx_field)["curves"]
    rx = trace_rx(TraceRxParams(angle_deg=10.0, n_curves=40), mesh, regions, rx_field)["curves"]
    cross = crossings(CrossingsParams(), mesh, tx, rx, tx_field, rx_field)
    samples = surface_samples(SamplesParams(count=150), mesh, regions)
    params = OptimizeParams(n_drive=10, n_sense=6, time_limit_s=1.0)
    candidate = optimize(params, mesh, samples, tx, rx, cross["tx_rx"], cross["tx_tx"], cross["rx_rx"])
    return mesh, tx, rx, cross, params, candidate, regions


def test_bunny_layout_respects_constraints_and_spacing(bunny_run):
    mesh, tx, rx, cross, params, candidate, _ = bunny_run
    assert candidate.feasible, candidate.message
    layout, m = candidate.layout, candidate.metrics
    assert 0 < layout.tx.count <= 10 and 0 < layout.rx.count <= 6
    tx_sel, rx_sel = set(layout.tx_source.tolist()), set(layout.rx_source.tolist())
    for same, chosen in ((cross["tx_tx"], tx_sel), (cross["rx_rx"], rx_sel)):
        assert not any(a in chosen and b in chosen and a != b for a, b in zip(same.curve_a, same.curve_b))  # C1
    pairs = list(zip(cross["tx_rx"].curve_a.tolist(), cross["tx_rx"].curve_b.tolist()))
    multiplicity = {p: pairs.count(p) for p in set(pairs)}
    assert all(multiplicity[p] == 1 for p in multiplicity if p[0] in tx_sel and p[1] in rx_sel)  # C2
    cells = layout.cells
    assert len(cells.curve_a) == sum(1 for p in pairs if p[0] in tx_sel and p[1] in rx_sel)
    assert np.array_equal(layout.tx.lengths_mm, tx.lengths_mm[layout.tx_source])
    pads = np.flatnonzero(layout.pad)
    D = geodesics_for(mesh).pairwise(cells.faces[pads], cells.bary[pads])
    assert D[np.triu_indices(len(pads), 1)].min() >= m["d_min_mm"] - 0.05  # heat asymmetry tolerance
    assert m["d_min_mm"] == 4 * m["pad_radius_mm"]
    assert 0 < m["voronoi_cv"] < 2 and m["pads"] == len(pads)
    assert set(np.unique(cells.curve_a[pads])) == set(range(layout.tx.count))  # a pad on every Tx channel


def test_bunny_sensing_map(bunny_run):
    mesh, _, _, _, _, candidate, regions = bunny_run
    picked = pick_best(PickParams(print_table=False), [candidate])
    files = write_sensing_map(SensingMapParams(), mesh, regions, picked["layout"], picked["metrics"])
    doc = json.loads(files.contents["sensing_map.json"])
    validate_sensing_map(doc)
    assert doc["tx_channels"] == picked["layout"].tx.count
