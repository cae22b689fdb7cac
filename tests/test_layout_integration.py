"""The layout nodes on real curve families: pymeshlab's bunny (170 mm, ~4k vertices), Tx and one
Rx angle traced by the curve nodes, crossings from ``curves.crossings``."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from curves_fixture import bunny
from test_layout_sensing_map import validate_sensing_map

from retrotouch.graph.node import NodeParams
from retrotouch.nodes.curves.crossings import CrossingsParams, crossings
from retrotouch.nodes.layout.pick import PickParams, pick_best
from retrotouch.nodes.layout.screen import PreScreen, Screen
from retrotouch.nodes.layout.sweep import OptimizeParams, bound, coverage, finish, optimize
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
    params = OptimizeParams(n_drive=10, n_sense=6, time_limit_s=1.0, rx_free_end_mm=60.0)  # both free ends
    candidate = optimize(params, mesh, samples, tx, rx, cross["tx_rx"], cross["tx_tx"], cross["rx_rx"])
    return mesh, tx, rx, cross, params, candidate, regions


def test_the_radius_stage_bounds_the_finished_layout_and_a_screen_below_it_skips_the_rest(bunny_run):
    mesh, tx, rx, cross, params, candidate, regions = bunny_run
    samples = surface_samples(SamplesParams(count=150), mesh, regions)
    curves = (mesh, samples, tx, rx, cross["tx_rx"], cross["tx_tx"], cross["rx_rx"])
    start = bound(params, *curves)
    branch = coverage(NodeParams(), *curves, start, PreScreen(np.inf, np.inf, {}, ""))
    radius, low = candidate.metrics["coverage_radius_mm"], branch.stage.lower_bound_mm
    assert low < radius  # trimming may only take crossings away
    # the stage only improves on the heuristic start, and nothing beats the layer bound
    assert start.lower_bound_mm <= branch.stage.radius_mm <= start.start_radius_mm
    dropped = coverage(NodeParams(), *curves, start, PreScreen(start.lower_bound_mm - 0.1, 0.0, {}, ""))
    assert dropped.stage is None and dropped.prescreened_bound_mm == start.lower_bound_mm
    assert finish(NodeParams(), *curves, dropped, Screen(np.inf, np.inf, ""), regions).metrics["screened"]

    def finished(threshold_mm):
        return finish(NodeParams(), mesh, samples, tx, rx, cross["tx_rx"], cross["tx_tx"], cross["rx_rx"], branch,
                      Screen(threshold_mm, threshold_mm, ""), regions)

    below = finished(low - 0.1)
    assert not below.feasible and below.layout is None and below.metrics["screened"]
    assert below.regions is regions  # a candidate carries the regions it was laid out on, screened or not
    assert below.message.startswith(f"screened out: its coverage radius is at least {low:.1f} mm")
    at_bound = finished(low)  # kept by the bound, then the model capped there is proven infeasible
    assert at_bound.metrics["screened"] and at_bound.message.endswith("(proven)")
    kept = finished(branch.stage.radius_mm)
    assert kept.feasible and kept.metrics["coverage_radius_mm"] == radius


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
    # the cells are the selected pairs' crossings, but for those on the trimmed start of a Tx curve
    # or the trimmed end of an Rx curve
    tx_cut = dict(zip(layout.tx_source.tolist(), tx.lengths_mm[layout.tx_source] - layout.tx.lengths_mm))
    rx_kept = dict(zip(layout.rx_source.tolist(), layout.rx.lengths_mm))
    tx_rx = cross["tx_rx"]
    on_traces = [a in tx_sel and b in rx_sel and arc_a >= tx_cut[a] and arc_b <= rx_kept[b]
                 for a, b, arc_a, arc_b in zip(tx_rx.curve_a.tolist(), tx_rx.curve_b.tolist(), tx_rx.arc_a, tx_rx.arc_b)]
    assert len(cells.curve_a) == sum(on_traces)
    for c, source in enumerate(layout.rx_source):  # Rx: at most the free end is trimmed
        full = rx.points[rx.offsets[source] : rx.offsets[source + 1]]
        part = layout.rx.points[layout.rx.offsets[c] : layout.rx.offsets[c + 1]]
        assert np.array_equal(full[: len(part)], part)
        assert rx.lengths_mm[source] - layout.rx.lengths_mm[c] <= params.rx_free_end_mm + 5.0  # plus one segment
    for curves, channel, seg in ((layout.tx, cells.curve_a, cells.seg_a), (layout.rx, cells.curve_b, cells.seg_b)):
        for k in range(len(cells.curve_a)):  # cells still sit on their curves' segments after trimming
            curve = curves.points[curves.offsets[channel[k]] : curves.offsets[channel[k] + 1]]
            p, q = curve[seg[k]], curve[seg[k] + 1]
            t = np.dot(cells.points[k] - p, q - p) / np.dot(q - p, q - p)
            assert -1e-6 <= t <= 1 + 1e-6 and np.linalg.norm(p + t * (q - p) - cells.points[k]) < 1e-6
    pads = np.flatnonzero(layout.pad)
    D = geodesics_for(mesh).pairwise(cells.faces[pads], cells.bary[pads])
    assert D[np.triu_indices(len(pads), 1)].min() >= m["d_min_mm"] - 0.05  # heat asymmetry tolerance
    assert m["d_min_mm"] == 4 * m["pad_radius_mm"]
    assert 0 < m["voronoi_cv"] < 2 and m["pads"] == len(pads)
    assert set(np.unique(cells.curve_a[pads])) == set(range(layout.tx.count))  # a pad on every Tx channel
    # design values travel with the layout
    assert (layout.pad_radius_mm, layout.d_min_mm) == (m["pad_radius_mm"], m["d_min_mm"])
    assert (layout.trace_width_mm, layout.clearance_mm) == (params.trace_width_mm, params.clearance_mm)


def test_bunny_layout_keeps_same_layer_clearance(bunny_run):
    mesh, tx, rx, cross, params, candidate, _ = bunny_run
    m = candidate.metrics
    bound = params.trace_width_mm + params.clearance_mm
    assert m["min_same_layer_clearance_mm"] >= bound
    for layer in ("tx", "rx"):
        assert m["same_layer_clearance"][layer]["length_closer_than_bound_mm"] == 0.0
    assert m["candidates"]["tx_clearance_conflicts"] > 0 and m["candidates"]["rx_clearance_conflicts"] > 0
    assert m["cells"] <= m["channel_pairs"] == params.n_drive * params.n_sense
    assert m["voronoi_cv_all_crossings"] is not None and m["voronoi_cv_pads"] == m["voronoi_cv"]


def test_bunny_sensing_map(bunny_run):
    mesh, _, _, _, _, candidate, regions = bunny_run
    picked = pick_best(PickParams(print_table=False), [candidate])
    files = write_sensing_map(SensingMapParams(), mesh, regions, picked["layout"], picked["metrics"])
    doc = json.loads(files.contents["sensing_map.json"])
    validate_sensing_map(doc)
    assert doc["tx_channels"] == picked["layout"].tx.count


def test_a_branch_whose_crossings_all_go_with_the_trimming_fails_alone(bunny_run, monkeypatch):
    """When trimming the selected curves where they crowd takes every crossing (a thin object's branch),
    that branch reports why and the sweep goes on with the others: no crash of the whole run."""
    import retrotouch.nodes.layout.sweep as sweep

    mesh, tx, rx, cross, params, candidate, regions = bunny_run
    monkeypatch.setattr(sweep, "_free_end_trims", lambda params, samples, curves, selected, bound, walls: np.diff(curves.offsets))
    samples = surface_samples(SamplesParams(count=150), mesh, regions)
    failed = optimize(params, mesh, samples, tx, rx, cross["tx_rx"], cross["tx_tx"], cross["rx_rx"])
    assert not failed.feasible and failed.layout is None and "no Tx/Rx crossing is left" in failed.message
    picked = pick_best(PickParams(print_table=False), [failed, candidate])
    assert picked["layout"] is candidate.layout
    assert picked["metrics"]["angles"][0]["note"].startswith("failed: no Tx/Rx crossing is left")


def test_relaxed_pad_radius_travels_with_the_layout(bunny_run):
    from retrotouch.nodes.fab.unfold import Params as UnfoldParams, unfold

    mesh, tx, rx, cross, params, _, regions = bunny_run
    samples = surface_samples(SamplesParams(count=150), mesh, regions)
    relaxed = params.model_copy(update={"pad_radius_mm": 20.0, "relax_pad_radii_mm": (2.0,)})  # 80 mm spacing cannot work
    candidate = optimize(relaxed, mesh, samples, tx, rx, cross["tx_rx"], cross["tx_tx"], cross["rx_rx"])
    assert candidate.feasible and candidate.message == "relaxed"
    layout = candidate.layout
    assert (layout.pad_radius_mm, layout.d_min_mm) == (2.0, 8.0)
    assert candidate.metrics["relaxations"][0]["failed"].startswith("pad radius 20 mm")
    assert unfold(UnfoldParams(), mesh, layout).pad_radius_mm == 2.0  # what fab.outline cuts


def assert_identical(a, b, where="candidate"):
    """Deep equality of nested dataclasses, dicts, sequences, arrays (dtype and shape too) and scalars."""
    if dataclasses.is_dataclass(a):
        assert type(a) is type(b), where
        for f in dataclasses.fields(a):
            assert_identical(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, dict):
        assert isinstance(b, dict) and list(a) == list(b), where
        for key in a:
            assert_identical(a[key], b[key], f"{where}[{key!r}]")
    elif isinstance(a, (list, tuple)):
        assert type(a) is type(b) and len(a) == len(b), where
        for i, (u, v) in enumerate(zip(a, b)):
            assert_identical(u, v, f"{where}[{i}]")
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape, where
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), where
    else:
        assert type(a) is type(b) and (a == b or (a != a and b != b)), f"{where}: {a!r} != {b!r}"


def test_optimize_is_a_function_of_its_inputs(bunny_run):
    """A second run (fresh samples, warm geodesic cache) gives the same layout and the same metrics:
    CP-SAT stops on deterministic time only and no wall-clock figure enters the result."""
    mesh, tx, rx, cross, params, candidate, regions = bunny_run
    samples = surface_samples(SamplesParams(count=150), mesh, regions)
    again = optimize(params, mesh, samples, tx, rx, cross["tx_rx"], cross["tx_tx"], cross["rx_rx"])
    assert candidate.feasible and len(candidate.layout.pad) > 0
    assert_identical(candidate, again)
    assert "seconds" not in json.dumps(candidate.metrics, default=str)
