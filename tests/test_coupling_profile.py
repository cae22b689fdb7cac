"""The learned radial coupling profile: Gaussian start, derivatives, monotone refit from noisy pairs."""
from __future__ import annotations

import numpy as np
import pytest

from retrotouch.nodes.sensing.coupling_profile import CouplingProfile, ProfileLearner, student_profile
from retrotouch.nodes.sensing.virtual_board import disc_coupling_profile

WIDTH = 6.3  # mm, the default layout's nominal coupling width


def test_gaussian_start_is_the_gaussian_everywhere():
    """log K is linear in d^2 between knots, so the Gaussian start is exact, past the reach too."""
    profile = CouplingProfile.gaussian(WIDTH)
    d = np.linspace(0, 7 * WIDTH, 500)
    assert np.allclose(profile.at_distance(d), np.exp(-d**2 / (2 * WIDTH**2)), rtol=1e-9, atol=0)
    assert profile.reach == pytest.approx(5 * WIDTH)
    assert profile.half_maximum_mm() == pytest.approx(WIDTH * np.sqrt(2 * np.log(2)), rel=1e-9)


def test_student_start_matches_its_formula_on_the_knots_and_tends_to_the_gaussian():
    """The calibration's profile family: exact on the knots, log-linear in d^2 between them (within
    1 % of K(0) for a heavy tail), and the Gaussian of the same width as the tail grows."""
    heavy = CouplingProfile.student(WIDTH, 2.0)
    assert np.allclose(heavy.values, student_profile(heavy.distances**2, WIDTH, 2.0), rtol=1e-12)
    d = np.linspace(0, 5 * WIDTH, 400)
    assert np.max(np.abs(heavy.at_distance(d) - student_profile(d**2, WIDTH, 2.0))) < 0.01
    assert heavy.at_distance(3 * WIDTH) > 5 * np.exp(-4.5)  # a heavier tail than the Gaussian's
    light = CouplingProfile.student(WIDTH, 1e7)
    assert np.allclose(light.at_distance(d), np.exp(-d**2 / (2 * WIDTH**2)), atol=1e-5)


def test_slope_is_the_derivative_in_squared_distance():
    distances, values = disc_coupling_profile(4.5, WIDTH * np.sqrt(2 * np.log(2)))
    profile = CouplingProfile(distances[::40], values[::40])  # uneven log-slopes
    # mm^2: inside segments (knots every 4 mm) and past the reach
    squared = np.array([0.3, 10.0, 55.0, 200.0, 410.0, 2000.0])
    value, slope = profile.at_squared(squared)
    step = 1e-4
    numeric = (profile.at_squared(squared + step)[0] - profile.at_squared(squared - step)[0]) / (2 * step)
    assert np.allclose(slope, numeric, rtol=1e-6)
    assert np.all(slope < 0) and np.all((value > 0) & (value < 1))


def test_farthest_reading_inverts_the_profile():
    """K reads the value at the returned distance and less just past it, on a Gaussian, on uneven
    segments with a flat run, and past the reach; the edge cases are inf / -inf."""
    distances, values = disc_coupling_profile(4.5, WIDTH * np.sqrt(2 * np.log(2)))
    flat = np.array([1.0, 1.0, 0.8, 0.8, 0.3, 0.05, 0.01])
    for profile in (CouplingProfile.gaussian(WIDTH), CouplingProfile(distances[::40], values[::40]),
                    CouplingProfile(np.linspace(0.0, 30.0, len(flat)), flat)):
        for value in (1.0, 0.999, 0.8, 0.5, 0.3, 0.11, 0.01, 1e-4):
            d = profile.farthest_reading(value)
            assert profile.at_distance(d) == pytest.approx(value, rel=1e-9)
            assert profile.at_distance(d * 1.0001 + 1e-6) < value
        assert profile.farthest_reading(0.0) == np.inf and profile.farthest_reading(1.01) == -np.inf
    assert CouplingProfile(np.array([0.0, 5.0, 10.0]), np.array([1.0, 0.5, 0.5])).farthest_reading(0.4) == np.inf


def test_refit_recovers_a_disc_profile_from_noisy_pairs():
    """4000 ratios with noise 0.02 drawn from the simulator's disc profile: within 0.01 of it
    everywhere inside the reach."""
    distances, values = disc_coupling_profile(4.5, WIDTH * np.sqrt(2 * np.log(2)))
    rng = np.random.default_rng(0)
    d = rng.uniform(0, 5 * WIDTH, 4000)
    ratios = np.interp(d, distances, values) + rng.normal(0, 0.02, len(d))
    learner = ProfileLearner(CouplingProfile.gaussian(WIDTH), first=1)
    assert learner.add(d**2, ratios, np.full(len(d), 1 / 0.02**2))
    fitted = learner.profile
    assert fitted.values[0] == 1.0 and np.all(np.diff(fitted.values) <= 0)
    inside = np.linspace(0, fitted.reach, 400)
    assert np.max(np.abs(fitted.at_distance(inside) - np.interp(inside, distances, values))) < 0.01
    # The Gaussian start is 0.072 below the disc at two widths; the refit is not.
    assert abs(CouplingProfile.gaussian(WIDTH).at_distance(2 * WIDTH) - np.interp(2 * WIDTH, distances, values)) > 0.05


def test_learner_refits_from_the_first_touch_count_then_periodically():
    """Touches of a Laplacian profile (heavier tail than the Gaussian start): refits at the 3rd
    touch, then after 2, 4, 4 more (the interval doubles up to 4); the older touches fade (memory 5
    touches) but the fit stays on the data."""
    learner = ProfileLearner(CouplingProfile.gaussian(WIDTH), memory=5.0, first=3, every=2, longest=4)
    d = np.linspace(0, 3 * WIDTH, 20)
    ratios = np.exp(-d / WIDTH)
    refits = [learner.add(d**2, ratios, np.ones_like(d)) for _ in range(13)]
    assert np.flatnonzero(refits).tolist() == [2, 4, 8, 12] and learner.updates == 4
    assert learner.profile.at_distance(2.5 * WIDTH) == pytest.approx(np.exp(-2.5), abs=0.02)
