"""What the processing learns early from ordinary touches (issue 14): the coupling width from the
third estimate on, the no-pad gain pooled over every crossing without a pad; and a calibration
touch that the processing puts a pitch off its crossing still counts."""
from __future__ import annotations

import numpy as np
import pytest

from retrotouch.nodes.data.sensing_map import load_sensing_map
from retrotouch.nodes.sensing.calibration import CalibrationSession
from retrotouch.nodes.sensing.coupling_fit import COUPLING_RUNNING_FROM
from retrotouch.nodes.sensing.gain_learning import MIN_TOUCHES, WEIGHT_CAP, GainLearner
from retrotouch.nodes.sensing.processing import TouchProcessor
from retrotouch.nodes.sensing.synthetic_map import synthetic_bunny_map


@pytest.fixture(scope="module")
def bunny(tmp_path_factory):
    path = synthetic_bunny_map(tmp_path_factory.mktemp("bunny"), cells=60)
    return load_sensing_map(path)


def gaussian_touch(processor: TouchProcessor, cell: int, width: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A finger on ``cell`` with a Gaussian coupling of ``width`` (mm): the offsets of the crossings
    that read above 5 % of its peak, its face frame and their deltas (counts)."""
    points = processor.map.cell_points
    offsets = points - points[cell]
    delta = 300.0 * np.exp(-np.sum(offsets**2, axis=1) / (2 * width**2))
    strong = delta > 15.0
    return offsets[strong], processor.projector.face_frames[processor.map.cell_faces[cell]], delta[strong]


def test_the_coupling_width_follows_the_touches_from_the_third_estimate(bunny):
    """A finger 1.6 x wider than the pitch prior: the width stays the prior for the first estimates
    and is the touches' own (within 10 %) from the third on, long before the 30 that fix it."""
    processor = TouchProcessor(bunny)
    fit = processor.fit
    prior = fit.coupling_sigma
    width = 1.6 * prior
    cells = np.argsort(-np.sum(processor.cell_distance < 2.5 * width, axis=1))  # the most crossings nearby
    for k, cell in enumerate(cells[:COUPLING_RUNNING_FROM].tolist(), start=1):
        fit._learn_coupling(*gaussian_touch(processor, cell, width))
        if k < COUPLING_RUNNING_FROM:
            assert fit.coupling_sigma == prior
    assert fit.coupling_sigma == pytest.approx(width, rel=0.1)
    assert fit.profile.half_maximum_mm() == pytest.approx(width * np.sqrt(2 * np.log(2)), rel=0.1)


def test_the_no_pad_gain_is_pooled_over_crossings_that_each_saw_few_touches():
    """Four crossings without a pad, each seen by one touch (too few for a gain of its own), reading
    0.3 of a padded one: together they set the no-pad gain of the crossings no touch has reached;
    without them it stays the assumed 0.5, and a measured calibration keeps its values."""
    pad = np.array([True] * 10 + [False] * 10)
    start = np.where(pad, 1.0, 0.5)
    learner = GainLearner(start, pad)
    assert np.allclose(learner.gains(), start)
    for _ in range(int(MIN_TOUCHES) + 1):  # padded crossings: gains of their own, at 1
        learner.add(np.arange(10), np.zeros(10), np.full(10, WEIGHT_CAP))
    seen = np.arange(10, 14)
    learner.add(seen, np.full(4, np.log(0.3)), np.full(4, WEIGHT_CAP))
    gains = learner.gains()
    assert np.all(learner.learned[seen] < MIN_TOUCHES)
    assert np.allclose(gains[14:], 0.3, rtol=0.02)
    assert np.allclose(gains[:10], 1.0)
    measured = GainLearner(start, pad, measured=True)
    measured.add(seen, np.full(4, np.log(0.3)), np.full(4, WEIGHT_CAP))
    assert np.allclose(measured.gains()[14:], 0.5)


def test_a_calibration_touch_a_pitch_off_its_crossing_counts_and_two_pitches_do_not(bunny):
    """A hand-laid crossing sits 1-3 mm off the map and the processing has not learned the board:
    a touch the processing puts (on average) one pitch from the prompted crossing is that
    crossing's touch; one two pitches from it (and from the next crossings prompted), whose peak
    crossing was none of them, is not."""
    pitch = bunny.pitch_mm()
    session = CalibrationSession(bunny)
    targets = session.targets[:4]
    points = bunny.cell_points
    normal = bunny.cell_normals[targets[0]]
    away = points[targets[0]] - points[targets[1:]].mean(axis=0)  # away from the next crossings prompted
    away -= (away @ normal) * normal
    away /= np.linalg.norm(away)
    elsewhere = [int(np.argmax(np.linalg.norm(points - points[targets[0]], axis=1)))]  # a peak far from all targets
    for distance, counts in ((1.0 * pitch, True), (2.0 * pitch, False)):
        point = points[targets[0]] + distance * away
        assert np.argmin(np.linalg.norm(points[targets] - point, axis=1)) == 0
        assert session._target(point, elsewhere) == (session.next if counts else None)


def test_a_touch_is_not_lost_to_a_quiet_neighbour_with_a_small_gain(bunny):
    """A finger in a sparse region turns on one crossing (14 noise sigmas); a neighbour without a
    pad (gain 0.3) reads 5 sigmas, more than the first once divided by its gain, but stays below
    the on threshold: the active crossing is the touch's peak, so the touch does not drop."""
    processor = TouchProcessor(bunny)
    neighbours = processor.peak_neighbours
    cell = next(k for k in range(bunny.cell_count) if np.any(neighbours[:, k] != k))
    neighbour = int(next(n for n in neighbours[:, cell] if n != cell))
    processor.cell_gain[neighbour] = 0.3
    sigma = np.full(bunny.cell_count, 5.0)
    delta = np.zeros(bunny.cell_count)
    delta[cell], delta[neighbour] = 14 * 5.0, 5 * 5.0
    processor.active = delta > processor.params.on_sigma * sigma
    processor.previous_delta = delta.copy()  # the finger was there in the last frame too
    assert processor._peaks(delta, sigma).tolist() == [cell]
