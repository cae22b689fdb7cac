"""``curves.trace_limbs`` on the generated four-legged figurine (it stands on one leg's sole; the other
three legs, 40-44 mm deep, are limbs): rings and lines per leg, where they start and end, what they cross."""
from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import shapes
from curves_fixture import prepared

from retrotouch.nodes.curves.crossings import CrossingsParams, crossings
from retrotouch.nodes.curves.helices import TraceHelicesParams, trace_helices, winding_angle_node
from retrotouch.nodes.curves.limbs import TraceLimbsParams, trace_limbs
from retrotouch.nodes.curves.ring_levels import RingLevelsParams, ring_levels
from retrotouch.nodes.curves.tracing import TraceTxParams, trace_tx
from retrotouch.nodes.geometry.dead_ends import dead_end_vertices, dead_ends, mesh_edges


@pytest.fixture(scope="module", params=["median", "per_line"])
def figurine(request, tmp_path_factory):
    path = shapes.write_shape("four_legged_figurine", Path(tmp_path_factory.mktemp("figurine")))
    mesh, regions, _, tx_field, rx_field = prepared(str(path))
    tx = trace_tx(TraceTxParams(n_curves=60), mesh, regions, tx_field)["curves"]
    levels = ring_levels(RingLevelsParams(), mesh, regions, tx_field, tx)
    theta = winding_angle_node(None, mesh, levels, tx_field)
    helices = trace_helices(TraceHelicesParams(climb=request.param), mesh, regions, levels, theta, tx, tx_field)
    out = trace_limbs(TraceLimbsParams(), mesh, regions, helices["chart"], tx, tx_field, helices["curves"])
    d = np.asarray(regions.base_distance_mm, dtype=np.float64)
    edges = mesh_edges(mesh.faces)
    ends = dead_ends(d, edges, TraceLimbsParams().min_depth_mm)
    limbs = [dead_end_vertices(d, edges, end) for end in ends]
    return mesh, regions, tx, helices["curves"], out, d, ends, limbs, (tx_field, rx_field)


def test_every_leg_gets_rings_and_lines_after_the_family(figurine):
    _, _, tx, helices, out, _, ends, _, _ = figurine
    legs = [k for k, end in enumerate(ends) if end.depth > 25.0]
    assert len(legs) == 3
    for layer, own in (("tx", tx), ("rx", helices)):
        joined = out[layer]
        assert np.array_equal(joined.points[: len(own.points)], own.points) and np.all(joined.limb[: own.count] == -1)
        per_limb = np.bincount(joined.limb[own.count:], minlength=len(ends))
        assert all(per_limb[k] >= 2 for k in legs), (layer, per_limb)
        assert np.all(joined.end_reason[own.count:] == 0)


def test_rings_run_from_their_limb_to_the_base_and_lines_from_the_base_into_their_limb(figurine):
    mesh, regions, tx, helices, out, d, ends, limbs, _ = figurine
    base_vertices = np.unique(mesh.faces[np.asarray(regions.base_faces) | np.asarray(regions.exclusion_base)])
    for layer, own in (("tx", tx), ("rx", helices)):
        curves = out[layer]
        for c in range(own.count, curves.count):
            first, last = mesh.faces[curves.faces[curves.offsets[c]]], mesh.faces[curves.faces[curves.offsets[c + 1] - 1]]
            end, limb = ends[curves.limb[c]], limbs[curves.limb[c]]
            inside, on_base = (first, last) if layer == "tx" else (last, first)
            assert np.isin(on_base, base_vertices).any()
            assert limb[inside].all()
            if layer == "rx":  # a line reaches beyond half its limb's depth
                assert d[inside].min() > end.join_value + 0.5 * end.depth


def test_lines_cross_helices_only_inside_limbs_and_legs_get_cells(figurine):
    mesh, _, tx, helices, out, _, ends, limbs, fields = figurine
    cross = crossings(CrossingsParams(), mesh, out["tx"], out["rx"], *fields)
    rx_rx = cross["rx_rx"]
    mixed = (rx_rx.curve_a < helices.count) ^ (rx_rx.curve_b < helices.count)
    limb_faces = np.logical_or.reduce([limb[mesh.faces].all(axis=1) for limb in limbs])
    assert limb_faces[rx_rx.faces[mixed]].all()
    tx_rx = cross["tx_rx"]
    counts = Counter(zip(tx_rx.curve_a.tolist(), tx_rx.curve_b.tolist()))
    ring_limb, line_limb = out["tx"].limb, out["rx"].limb
    legs = [k for k, end in enumerate(ends) if end.depth > 25.0]
    assert all(any(ring_limb[a] == line_limb[b] == k for a, b in counts) for k in legs)  # each leg's rings and lines meet
    # a line that leaves its limb on the side of the rings' legs crosses a ring there too (twice in all: no
    # cell); with four lines per limb, a cell on two legs of three at least, under any jitter of the mesh
    with_cell = [k for k in legs if any(n == 1 and ring_limb[a] == line_limb[b] == k for (a, b), n in counts.items())]
    assert len(with_cell) >= 2, with_cell
