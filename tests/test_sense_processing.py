"""Touch processing end to end on the synthetic bunny sensing map: localization through the
pseudo-terminal, rest without false touches under drift, holds, multi-touch ids, one finger between
two peaks, map loading."""
from __future__ import annotations

import json

import numpy as np
import pytest

from retrotouch.graph.errors import UserError
from retrotouch.nodes.data.sensing_map import load_sensing_map
from retrotouch.nodes.geometry.surface import closest_points_on_triangles, SurfaceProjector
from retrotouch.nodes.sensing.processing import SUPPORT_WIDTHS, ProcessingParams, TouchProcessor
from retrotouch.nodes.sensing.pty_board import frames_through_pty
from retrotouch.nodes.sensing.scripts import ScriptBuilder
from retrotouch.nodes.sensing.synthetic_map import synthetic_bunny_map
from retrotouch.nodes.sensing.virtual_board import BoardParams, VirtualBoard
from retrotouch.nodes.sensing.evaluation import EvalParams, evaluate_recording, evaluate_simulator


@pytest.fixture(scope="module")
def bunny_map_path(tmp_path_factory):
    return synthetic_bunny_map(tmp_path_factory.mktemp("bunny"))


@pytest.fixture(scope="module")
def bunny_map(bunny_map_path):
    return load_sensing_map(bunny_map_path)


def feed(processor, board, fingers_at, seconds, start=0.0):
    """Feed ``seconds`` of board frames directly; returns the FrameResults."""
    rate = board.params.rate_hz
    results = []
    for k in range(int(round(seconds * rate))):
        t = start + k / rate
        results.append(processor.process(board.frame(t, fingers_at(t)), t))
    return results


def test_synthetic_map_is_a_bunny_170mm_with_cells_on_the_surface(bunny_map):
    diagonal = np.linalg.norm(np.ptp(bunny_map.vertices, axis=0))
    assert diagonal == pytest.approx(170.0, rel=1e-9)
    assert 150 <= bunny_map.cell_count <= 252
    pairs = bunny_map.cell_tx * 12 + bunny_map.cell_rx
    assert len(np.unique(pairs)) == bunny_map.cell_count
    corners = bunny_map.vertices[bunny_map.faces[bunny_map.cell_faces]]
    assert np.allclose(np.einsum("kj,kjd->kd", bunny_map.cell_bary, corners), bunny_map.cell_points, atol=1e-9)
    assert np.allclose(np.linalg.norm(bunny_map.cell_normals, axis=1), 1.0)
    assert 5.0 < bunny_map.pitch_mm() < 15.0


def test_closest_point_on_triangles_matches_brute_force():
    rng = np.random.default_rng(0)
    triangles = rng.normal(size=(300, 3, 3))
    points = rng.normal(size=(300, 3)) * 2
    bary = closest_points_on_triangles(points, triangles)
    closest = np.einsum("ij,ijd->id", bary, triangles)
    assert np.all(bary >= -1e-9) and np.allclose(bary.sum(axis=1), 1.0)
    # Dense sampling of each triangle never beats the returned point.
    u, v = np.meshgrid(np.linspace(0, 1, 60), np.linspace(0, 1, 60))
    keep = u + v <= 1
    samples = np.stack([1 - u[keep] - v[keep], u[keep], v[keep]], axis=1)
    sampled = np.einsum("sj,ijd->isd", samples, triangles)
    best = np.min(np.linalg.norm(sampled - points[:, None], axis=2), axis=1)
    assert np.all(np.linalg.norm(closest - points, axis=1) <= best + 1e-9)


def test_projector_finds_the_closest_surface_point(bunny_map):
    projector = SurfaceProjector(bunny_map.vertices, bunny_map.faces)
    queries = bunny_map.cell_points[:12] + 0.5 * bunny_map.cell_normals[:12]
    points, faces, bary = projector.project(queries)
    assert np.allclose(np.einsum("kj,kjd->kd", bary, bunny_map.vertices[bunny_map.faces[faces]]), points)
    triangles = bunny_map.vertices[bunny_map.faces]
    for query, point in zip(queries, points):
        every = np.einsum("ij,ijd->id", closest_points_on_triangles(np.broadcast_to(query, (len(triangles), 3)),
                                                                    triangles), triangles)
        assert np.linalg.norm(point - query) == pytest.approx(np.linalg.norm(every - query, axis=1).min(), abs=1e-9)
        assert np.linalg.norm(point - query) <= 0.5 + 1e-6


def test_projector_one_point_at_a_time_agrees_with_the_batch_bit_for_bit(bunny_map):
    """The compiled single-point path and the vectorised one pick the same face (ties included) and
    the same point, with and without a facing direction."""
    projector = SurfaceProjector(bunny_map.vertices, bunny_map.faces)
    rng = np.random.default_rng(3)
    vertices = bunny_map.vertices[rng.choice(len(bunny_map.vertices), 150, replace=False)]
    queries = np.concatenate([vertices, vertices + rng.normal(0.0, 1.5, vertices.shape)])  # on vertices: ties
    for facing in (None, np.array([0.0, 0.0, 1.0])):
        points, faces, barys = projector.project(queries, facing)
        for query, point, face, bary in zip(queries, points, faces, barys):
            one = projector.project(query, facing)
            assert int(one[1][0]) == int(face) and np.array_equal(one[0][0], point) and np.array_equal(one[2][0], bary)


def test_contact_components_are_the_mesh_components_of_the_vertices_inside(bunny_map):
    """Each contact vertex inside gets the smallest region index of its connected component (over
    mesh edges between vertices inside), as scipy's connected components give them."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    from retrotouch.nodes.sensing.contacts import ContactAreas, _component_labels

    contacts = ContactAreas(bunny_map, 2000, 10.0, 6.0)
    n = len(contacts.contact_vertices)
    rng = np.random.default_rng(5)
    edges = contacts.contact_faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    for share in (0.2, 0.35, 0.45):  # below the site-percolation threshold of a triangulation (0.5): many components
        inside = rng.random(n) < share
        region = np.flatnonzero(inside)
        labels = _component_labels(contacts.neighbour_rows, inside, region)
        keep = inside[edges].all(axis=1)
        local = np.cumsum(inside) - 1
        graph = sp.coo_matrix((np.ones(keep.sum()), (local[edges[keep, 0]], local[edges[keep, 1]])),
                              shape=(len(region), len(region)))
        count, components = connected_components(graph, directed=False)
        smallest = np.full(count, len(region))
        np.minimum.at(smallest, components, np.arange(len(region)))
        assert count > 1 and np.array_equal(labels, smallest[components])


def test_localization_through_the_pty_at_snr_60(bunny_map_path, tmp_path):
    """The paper's protocol (15 locations x 10 presses) through the pseudo-terminal in fast mode."""
    recording = tmp_path / "eval.jsonl"
    report = evaluate_simulator(bunny_map_path, BoardParams(snr=60), EvalParams(location_rule="surrounded"),
                                record=recording)
    summary = report.summary()
    assert summary["presses"] == 150 and summary["locations"] == 15
    assert summary["missed_presses"] == 0 and summary["false_touches_at_rest"] == 0
    assert summary["localization_error_mm_mean"] < 1.5
    assert 35 < summary["snr_mean"] < 65  # 60 for a finger centred on a crossing, less in between
    assert summary["snr_p2p_mean"] < summary["snr_mean"] / 3  # p2p of gaussian noise spans several sigma
    # The same session replayed from its recording scores the same.
    replayed = evaluate_recording(recording, bunny_map_path).summary()
    assert replayed["localization_error_mm_mean"] == pytest.approx(summary["localization_error_mm_mean"], abs=1e-9)


def test_unlabelled_session_is_scored_with_a_protocol_file(bunny_map_path, tmp_path):
    """A hardware-style recording (no labels) plus the list of touched locations scores like the labelled one."""
    params = EvalParams(locations=5, repetitions=3, seed=4, location_rule="surrounded")
    labelled = tmp_path / "labelled.jsonl"
    reference = evaluate_simulator(bunny_map_path, BoardParams(seed=4), params, record=labelled).summary()
    lines = labelled.read_text().splitlines()
    unlabelled = tmp_path / "unlabelled.jsonl"
    unlabelled.write_text("\n".join(line for line in lines if '"label"' not in line) + "\n")
    truth = [json.loads(line)["label"] for line in lines if '"label"' in line]
    points = [label["point"] for label in sorted(truth, key=lambda l: (l["repetition"], l["location"]))[:5]]
    protocol = tmp_path / "protocol.json"
    protocol.write_text(json.dumps({"points": points, "repetitions": 3}))
    scored = evaluate_recording(unlabelled, bunny_map_path, params, protocol=protocol).summary()
    assert scored["presses"] == 15 and scored["false_touches_at_rest"] == 0
    assert scored["localization_error_mm_mean"] == pytest.approx(reference["localization_error_mm_mean"], abs=0.1)
    protocol.write_text(json.dumps({"points": points, "repetitions": 4}))
    with pytest.raises(UserError, match="found 15 presses but the protocol has 5 locations x 4 repetitions = 20"):
        evaluate_recording(unlabelled, bunny_map_path, params, protocol=protocol)


def test_low_snr_still_localizes_within_a_pitch(bunny_map_path, bunny_map):
    summary = evaluate_simulator(bunny_map_path, BoardParams(snr=15, seed=3),
                                 EvalParams(locations=6, repetitions=3, location_rule="surrounded"),
                                 through_pty=False).summary()
    assert summary["missed_presses"] == 0 and summary["false_touches_at_rest"] == 0
    assert summary["localization_error_mm_mean"] < bunny_map.pitch_mm() / 2


def test_disc_coupling_profile_has_the_gaussians_reach_and_a_heavier_tail(bunny_map):
    """K(0) = 1, K = 1/2 where the nominal Gaussian is 1/2, decreasing, and at three widths about
    7 x the Gaussian (flat top over the finger disc, power-law tail)."""
    board = VirtualBoard(bunny_map, BoardParams(coupling_model="disc"))
    distances, values = board.disc_profile
    s = board.coupling_sigma
    assert values[0] == 1.0 and np.all(np.diff(values) < 0)
    assert np.interp(s * np.sqrt(2 * np.log(2)), distances, values) == pytest.approx(0.5, abs=2e-3)
    assert np.interp(3 * s, distances, values) > 5 * np.exp(-4.5)
    finger = bunny_map.cell_points[7]
    signal = board.signal([(finger, 100.0)]) / board.gain
    assert signal[7] == pytest.approx(100.0) and np.all(signal <= 100.0 + 1e-9)
    with pytest.raises(UserError, match="finger disc reaches past the half-maximum distance"):
        VirtualBoard(bunny_map, BoardParams(coupling_model="disc", finger_radius_mm=8.0, coupling_sigma_mm=3.0))


def test_coupling_profile_is_learned_from_touches(bunny_map, bunny_map_path):
    """The board couples 25 % wider than the processing's starting Gaussian: 20 presses teach it
    the width, then the shape, to the board's half-maximum distance; with adapt_coupling off the
    start stays."""
    processor = TouchProcessor(bunny_map)
    true_width = 1.25 * processor.fit.coupling_sigma
    params = BoardParams(coupling_sigma_mm=true_width, seed=12)
    board = VirtualBoard(bunny_map, params)
    steps = [{"gesture": "press", "at": "random", "ms": 500} for _ in range(20)]
    script = ScriptBuilder(bunny_map, params, seed=12).build(steps)
    feed(processor, board, script.fingers_at, script.duration)
    half_maximum = true_width * np.sqrt(2 * np.log(2))
    assert processor.fit.coupling.updates >= 2
    assert processor.fit.profile.half_maximum_mm() == pytest.approx(half_maximum, rel=0.05)
    fixed = TouchProcessor(bunny_map, ProcessingParams(adapt_coupling=False))
    feed(fixed, board, script.fingers_at, script.duration)
    assert fixed.fit.coupling.updates == 0
    assert fixed.fit.profile.half_maximum_mm() == pytest.approx(half_maximum / 1.25, rel=1e-9)


def test_ten_minutes_at_rest_with_drift_give_no_touch(bunny_map):
    board = VirtualBoard(bunny_map, BoardParams(drift_fraction=0.01, drift_period_s=240, cell_walk_counts=0.3, seed=5))
    processor = TouchProcessor(bunny_map)
    results = feed(processor, board, lambda t: [], 600.0)
    assert len(results) == 6000
    assert sum(len(r.touches) for r in results) == 0
    # The common drift swings by +-100 counts; the baseline follows it to within the noise.
    assert max(np.abs(r.delta).max() for r in results[100:]) < 6 * board.noise_sigma


def test_a_long_hold_does_not_fade_and_releases_cleanly(bunny_map):
    board = VirtualBoard(bunny_map, BoardParams(drift_fraction=0.01, drift_period_s=60, seed=6))
    processor = TouchProcessor(bunny_map)
    point = bunny_map.cell_points[ScriptBuilder(bunny_map).interior_cells[0]]
    held = lambda t: [(point, 300.0)] if 3.0 <= t < 23.0 else []  # noqa: E731
    results = feed(processor, board, held, 30.0)
    during = results[31:230]
    assert all(len(r.touches) == 1 for r in during)
    assert len({r.touches[0].id for r in during}) == 1
    assert all(len(r.touches) == 0 for r in results[231:])


def test_finger_resting_at_start_up_is_forgotten(bunny_map):
    board = VirtualBoard(bunny_map, BoardParams(seed=7))
    processor = TouchProcessor(bunny_map)
    resting = bunny_map.cell_points[5]
    results = feed(processor, board, lambda t: [(resting, 300.0)] if t < 2.5 else [], 5.0)
    assert sum(len(r.touches) for r in results) == 0  # the finger left: counts fall below baseline
    again = feed(processor, board, lambda t: [(resting, 300.0)], 1.0, start=5.0)
    assert len(again[-1].touches) == 1  # the cell re-baselined and sees touches again


def test_two_fingers_keep_their_ids_while_moving(bunny_map):
    board = VirtualBoard(bunny_map, BoardParams(seed=8))
    builder = ScriptBuilder(bunny_map, seed=8)
    script = builder.build([{"gesture": "spread", "at": "random", "from_mm": 30, "to_mm": 60, "ms": 1500}])
    processor = TouchProcessor(bunny_map)
    results = feed(processor, board, script.fingers_at, script.duration)
    two = [r for r in results if len(r.touches) == 2]
    assert len(two) >= 13
    assert len({tuple(sorted(t.id for t in r.touches)) for r in two}) == 1
    for r in two:
        truth = np.array([s.position(r.t) for s in script.strokes])
        got = np.array([t.point for t in r.touches])
        assert np.min(np.linalg.norm(got[:, None] - truth[None], axis=2), axis=1).max() < 2.0


def test_binary_format_with_flipped_rx_through_the_pty(bunny_map):
    # Binary frames carry value - min in one byte (wrapping above 255, as on the board): keep the spread small.
    params = BoardParams(flip_rx=True, seed=9, baseline_low=9980, baseline_high=10020, signal_counts=150,
                         drift_fraction=0.0)
    board = VirtualBoard(bunny_map, params)
    script = ScriptBuilder(bunny_map, params, seed=9).build([{"gesture": "press", "at": {"cell": 10}, "ms": 500}])
    processor = TouchProcessor(bunny_map, ProcessingParams())
    touches = []
    for frame in frames_through_pty(board, script, fast=True, frame_format="binary"):
        touches.extend(processor.process(frame.values, frame.t).touches)
    assert len(touches) == 5
    assert all(np.linalg.norm(t.point - bunny_map.cell_points[10]) < 2.5 for t in touches)  # pitch 8.7 mm


def test_layout_wiring_fewer_channels_than_the_board(tmp_path):
    """18 Tx x 10 Rx wired: frames still carry 21 x 12 values, cells index them as tx * 12 + rx."""
    sensing_map = load_sensing_map(synthetic_bunny_map(tmp_path, cells=160, num_tx=18, num_rx=10))
    assert sensing_map.num_tx == 18 and sensing_map.num_rx == 10
    assert sensing_map.frame_index.max() < 21 * 12
    assert np.array_equal(sensing_map.frame_index, sensing_map.cell_tx * 12 + sensing_map.cell_rx)
    summary = evaluate_simulator(sensing_map.source, BoardParams(seed=11),
                                 EvalParams(locations=4, repetitions=2, location_rule="surrounded"),
                                 through_pty=True).summary()
    assert summary["missed_presses"] == 0 and summary["false_touches_at_rest"] == 0
    assert summary["localization_error_mm_mean"] < 1.5


def test_sensing_map_errors_are_one_line_user_errors(bunny_map_path, tmp_path):
    with pytest.raises(UserError, match="not found"):
        load_sensing_map(tmp_path / "missing")
    bad = tmp_path / "bad" / "sensing_map.json"
    bad.parent.mkdir()
    bad.write_text(json.dumps({"format": "something/else"}))
    with pytest.raises(UserError, match="expected 'retrotouch.sensing_map/2'"):
        load_sensing_map(bad.parent)
    doc = json.loads(bunny_map_path.read_text())
    old = {**doc, "format": "retrotouch.sensing_map/1"}
    del old["up"]
    bad.write_text(json.dumps(old))
    with pytest.raises(UserError, match="format 'retrotouch.sensing_map/1', expected .* re-run the pipeline"):
        load_sensing_map(bad)  # version 1 carries no up axis
    doc["mesh"]["sha256"] = "0" * 64
    tampered = bunny_map_path.parent / "tampered.json"
    tampered.write_text(json.dumps(doc))
    with pytest.raises(UserError, match="does not match the sha256"):
        load_sensing_map(tampered)
    del doc["cells"][0]["tx"]
    tampered.write_text(json.dumps(doc))
    with pytest.raises(UserError, match="misses or mangles field"):
        load_sensing_map(tampered)


def test_a_one_frame_spike_beside_a_noisy_crossing_is_no_touch_but_a_press_is_one(bunny_map):
    """A board spike raises one crossing for one frame (14 noise sigmas) while one crossing within
    a finger's reach reads 3.4 sigmas by chance, and the spiked crossing reads 4.4 sigmas in the next
    frame (kept on by the off threshold's hysteresis): no touch; nor when two crossings within reach
    read 3.9 and 3.5 sigmas, or the spiked crossing read 4.1 sigmas the frame before (noise on a
    board with row and column noise and channel drift: each seen in ten-minute rests on the
    simulator's board). A finger over the same crossing, and a weak one only that crossing sees
    (7 sigmas for five frames), each give one touch-down."""
    processor = TouchProcessor(bunny_map)
    rng = np.random.default_rng(3)
    baseline = rng.uniform(9650.0, 10360.0, 21 * 12)
    noise = 5.0
    distance = processor.cell_distance
    reach = (distance <= SUPPORT_WIDTHS * processor.fit.coupling_sigma) & (distance > 0)
    cell = int(np.argmax(reach.sum(axis=0)))  # the crossing with the most crossings within a finger's reach
    neighbour, second_neighbour = (int(k) for k in np.flatnonzero(reach[cell])[:2])
    channel = processor.frame_index

    def frame(extra_sigmas=None):
        raw = baseline + np.clip(rng.normal(0.0, noise, baseline.shape), -2 * noise, 2 * noise)
        for k, z in (extra_sigmas or {}).items():  # exactly z sigmas over the processing's baseline
            raw[channel[k]] = processor.channels.baseline[channel[k]] + z * sigma[k]
        return np.rint(raw).reshape(21, 12)

    sigma = np.full(bunny_map.cell_count, noise)
    t = 0.0
    events = []
    for k in range(40):  # start-up and rest
        events += processor.process(frame(), t).events
        t += 0.1
    sigma = processor.sigma()
    for extra in ({cell: 14.0, neighbour: 3.4}, {cell: 4.4}, None, None,
                  {cell: 14.0, neighbour: 3.9, second_neighbour: 3.5}, None, None,
                  {cell: 4.1}, {cell: 14.0}, None, None):
        events += processor.process(frame(extra), t).events
        t += 0.1
    assert not [e for e in events if e["type"] == "touch_down"]

    width = np.sqrt(4.5**2 + (processor.pitch / 2) ** 2)
    finger = {k: 300.0 / noise * processor.cell_gain[k] * np.exp(-distance[cell, k] ** 2 / (2 * width**2))
              for k in np.flatnonzero(distance[cell] < 3 * width)}
    for press in (finger, {cell: 7.0}):
        downs = []
        for extra in [press] * 5 + [None] * 5:
            downs += [e for e in processor.process(frame(extra), t).events if e["type"] == "touch_down"]
            t += 0.1
        assert len(downs) == 1 and downs[0]["cell"] == cell


def test_one_finger_between_two_peaks_is_not_split_by_a_crossing_reading_below_its_baseline(bunny_map):
    """One finger between two crossings, with every crossing reading what it couples plus nothing,
    is one finger; so it stays when a crossing the finger barely reaches reads 3.5 noise sigmas below
    its baseline (noise: no darker than a crossing reading 0, which the test lets the finger light
    up to 6 sigmas)."""
    processor = TouchProcessor(bunny_map)
    fit, cells, noise, amplitude = processor.fit, bunny_map.cell_points, 5.0, 300.0
    width = fit.coupling_sigma
    pairs = np.argwhere((processor.cell_distance > 1.5 * width) & (processor.cell_distance < 2.0 * width))
    first, second = (int(k) for k in pairs[0])
    middle = processor.projector.project(0.5 * (cells[first] + cells[second]), bunny_map.cell_normals[first])[0][0]
    squared = np.sum((cells - middle) ** 2, axis=1)
    delta = processor.cell_gain * amplitude * fit.profile.at_squared(squared)[0]
    sigma = np.full(bunny_map.cell_count, noise)
    assert fit._one_finger_between(first, second, np.log(amplitude), delta, sigma, None) is not None
    faint = (delta > 0.2 * noise) & (delta < 2.0 * noise)  # the finger reaches them, barely
    faint[[first, second]] = False
    delta[np.flatnonzero(faint)[0]] = -3.5 * noise
    assert fit._one_finger_between(first, second, np.log(amplitude), delta, sigma, None) is not None
