"""curves.trace_rings: Rx rings around the Tx pole with legs along a corridor of Tx lines."""
from __future__ import annotations

import numpy as np
import pytest
from curves_fixture import bunny

from retrotouch.graph.errors import UserError
from retrotouch.nodes.curves.crossings import CrossingsParams, crossings
from retrotouch.nodes.curves.rings import TraceRingsParams, corridor, trace_rings
from retrotouch.nodes.curves.tracing import TraceRxParams, TraceTxParams, trace_rx, trace_tx
from retrotouch.nodes.data.types import CurveEnd


@pytest.fixture(scope="module")
def families():
    mesh, regions, _, tx_field, rx_field = bunny()
    tx = trace_tx(TraceTxParams(n_curves=100), mesh, regions, tx_field)["curves"]
    params = TraceRingsParams(n_rings=30, corridor_turn=0.25)
    rings = trace_rings(params, mesh, regions, tx_field, tx)["curves"]
    dipole = trace_rx(TraceRxParams(angle_deg=0.0, n_curves=30), mesh, regions, rx_field)["curves"]
    return mesh, tx, tx_field, rx_field, params, rings, dipole


def crossed_once_share(mesh, tx, rx, tx_field, rx_field) -> np.ndarray:
    """Per Rx candidate, the share of Tx candidates it crosses exactly once."""
    cross = crossings(CrossingsParams(), mesh, tx, rx, tx_field, rx_field)["tx_rx"]
    counts = np.bincount(cross.curve_a * rx.count + cross.curve_b, minlength=tx.count * rx.count)
    return (counts.reshape(tx.count, rx.count) == 1).mean(axis=0)


def test_rings_cross_most_tx_lines_once_where_dipole_loops_cross_half(families):
    mesh, tx, tx_field, rx_field, _, rings, dipole = families
    ring_share = crossed_once_share(mesh, tx, rings, tx_field, rx_field)
    dipole_share = crossed_once_share(mesh, tx, dipole, tx_field, rx_field)
    assert np.median(ring_share) >= 0.6
    assert np.median(ring_share) >= np.median(dipole_share) + 0.15


def test_each_ring_starts_at_the_base_end_of_a_corridor_leg(families):
    mesh, tx, tx_field, _, params, rings, _ = families
    assert rings.count >= 20 and rings.layer == "rx"
    assert np.all(rings.end_reason == int(CurveEnd.BASE))
    leg_ends = tx.points[tx.offsets[corridor(tx, params.n_rings, params.corridor_turn) + 1] - 1]
    starts = rings.points[rings.offsets[:-1]]
    assert np.min(np.linalg.norm(starts[:, None] - leg_ends[None], axis=2), axis=1).max() < 1e-6
    assert rings.angle == pytest.approx(2 * np.pi * params.corridor_turn)
    lengths = [np.linalg.norm(np.diff(rings.points[a:b], axis=0), axis=1).sum()
               for a, b in zip(rings.offsets[:-1], rings.offsets[1:])]
    np.testing.assert_allclose(rings.lengths_mm, lengths)


def test_the_rings_need_the_tx_field(families):
    mesh, tx, _, rx_field, params, _, _ = families
    regions = bunny()[1]
    with pytest.raises(UserError, match="needs the tx field"):
        trace_rings(params, mesh, regions, rx_field, tx)
