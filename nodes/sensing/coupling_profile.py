"""The finger's radial coupling profile ``K(d)``: the fraction of a touch's peak signal that a
crossing at distance ``d`` (mm, 3D) from the finger reads, learned from touches.

A real board's profile is not known in advance (finger size, overlay thickness, pad shape, the
hand's own capacitance all shape it), and a position fit that assumes the wrong shape is biased
(``bench/sensing.py`` measures it with the simulator's flat-topped, heavy-tailed ``disc`` profile).

The profile is a table on knots at fixed multiples of a width (0 to 5 widths), ``K(0) = 1``,
non-increasing, with ``log K`` linear in ``q = d^2`` between knots (a Gaussian is represented
exactly, and the slope in ``d`` is 0 at the centre); the last segment continues past the reach.
:class:`ProfileLearner` refits the knot values from pairs of well-posed touches (squared distance
from the fitted finger to a crossing, delta / (gain x fitted amplitude), weight = (gain x amplitude
/ noise sigma)^2): weighted least squares under the monotone constraint (NNLS on the knot-to-knot
drops, with a small penalty on changes of slope between knots), accumulated as normal equations
with a fading memory. The processing learns the width first (see
:meth:`.coupling_fit.CouplingFit._learn_coupling`) and the shape in units
of it: the shape alone cannot tell a wider finger from a larger amplitude (``K(0) = 1`` rests on
the few crossings right under a finger).
"""
from __future__ import annotations

import math

import numpy as np
from scipy.optimize import nnls

KNOTS_IN_WIDTHS = np.array([0.0, 0.25, 0.5, 0.75, 1.0, 1.25, 1.5, 1.75, 2.0, 2.5, 3.0, 3.5, 4.0, 4.5, 5.0])
SLOPE_PENALTY = 0.01  # weight of slope changes between knots, relative to the mean pair weight per knot
SMALLEST = 1e-6  # floor of the knot values (their logs are interpolated)


def student_profile(squared: np.ndarray, width: float, tail: float) -> np.ndarray:
    """``(1 + d^2 / (2 tail width^2))^-tail`` at squared distances (mm^2): a Gaussian of ``width``
    (mm) as ``tail`` grows, heavier-tailed as it shrinks (the family a calibration fits)."""
    return np.exp(-tail * np.log1p(squared / (2.0 * tail * width**2)))


class CouplingProfile:
    """``K`` on knots ``distances`` (mm, increasing from 0) with ``values`` (1 at 0, non-increasing,
    positive); ``log K`` is linear in ``q = d^2`` between knots (exact for a Gaussian) and the last
    segment continues past the last knot (the reach)."""

    def __init__(self, distances: np.ndarray, values: np.ndarray):
        self.distances = np.asarray(distances, dtype=np.float64)
        self.values = np.maximum(np.asarray(values, dtype=np.float64), SMALLEST)
        self.squared = self.distances**2
        self.reach = float(self.distances[-1])  # mm: pairs beyond it do not inform the fit
        log_values = np.log(self.values)
        # Per segment: log K = intercept + slope q.
        self.log_slopes = np.diff(log_values) / np.diff(self.squared)  # 1/mm^2
        self.log_intercepts = log_values[:-1] - self.log_slopes * self.squared[:-1]
        self.inner_squared = self.squared[1:-1].copy()  # segment boundaries (segment s: q in [inner_squared[s-1], inner_squared[s]))

    @classmethod
    def gaussian(cls, width: float) -> CouplingProfile:
        """``exp(-d^2 / (2 width^2))`` (``width`` in mm), exactly, on knots out to 5 widths."""
        return cls(KNOTS_IN_WIDTHS * width, np.exp(-(KNOTS_IN_WIDTHS**2) / 2))

    @classmethod
    def student(cls, width: float, tail: float) -> CouplingProfile:
        """:func:`student_profile` of ``width`` (mm) and ``tail`` on knots out to 5 widths."""
        return cls(KNOTS_IN_WIDTHS * width, student_profile((KNOTS_IN_WIDTHS * width) ** 2, width, tail))

    def scaled(self, width: float) -> CouplingProfile:
        """This profile's values on the knots ``KNOTS_IN_WIDTHS x width`` (mm): a shape learned in
        units of a width (knots ``KNOTS_IN_WIDTHS``), stretched to that width."""
        return CouplingProfile(KNOTS_IN_WIDTHS * width, self.values)

    def at_squared(self, squared: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``K`` and ``dK/dq`` at squared distances ``squared`` (mm^2)."""
        segment = self.inner_squared.searchsorted(squared, side="right")
        slope = self.log_slopes[segment]
        value = np.exp(self.log_intercepts[segment] + slope * squared)
        return value, slope * value

    def at_distance(self, distance: np.ndarray | float) -> np.ndarray:
        """``K`` at distances (mm)."""
        return self.at_squared(np.square(distance))[0]

    def farthest_reading(self, value: float) -> float:
        """Largest distance (mm) at which ``K >= value`` (``K`` is non-increasing): ``inf`` when
        ``K`` never falls below ``value`` (``value <= 0``, or a flat tail above it), ``-inf`` when
        ``value`` exceeds ``K(0) = 1``."""
        if value > self.values[0]:
            return -math.inf
        if value <= 0.0:
            return math.inf
        last = int(np.searchsorted(-self.values, -value, side="right")) - 1  # last knot with K >= value
        segment = min(last, len(self.log_slopes) - 1)  # past the last knot: the tail continues the last segment
        slope = float(self.log_slopes[segment])
        if slope >= 0.0:
            return math.inf
        squared = (math.log(value) - float(self.log_intercepts[segment])) / slope
        return math.sqrt(max(squared, float(self.squared[segment])))

    def half_maximum_mm(self) -> float:
        """Distance (mm) where ``K`` falls to 1/2."""
        segment = min(int(np.argmax(self.values < 0.5)) - 1, len(self.log_slopes) - 1)
        return float(np.sqrt((np.log(0.5) - self.log_intercepts[segment]) / self.log_slopes[segment]))

    def basis(self, squared: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The least-squares rows of pairs at ``squared`` distances (mm^2) in the knot-to-knot drops
        (``K_k = 1 - sum_{j<k} drop_j``). Between knots the fit takes K linear in ``q`` (a linear
        problem; the log-linear evaluation differs by < 0.006 on the simulator's disc profile): a pair
        in segment ``s`` at fraction ``t`` reads ``inside - sum_j drop_j below_j`` with ``below_j`` = 1
        for ``j < s``, ``t`` for ``j = s``, 0 after, and ``inside`` = 1 within the reach (pairs beyond
        it give zero rows: no information). Returns (``below`` (n, knots - 1), ``inside`` (n,))."""
        segment = np.searchsorted(self.squared[1:], squared, side="right")
        inside = segment < len(self.squared) - 1
        segment = np.minimum(segment, len(self.squared) - 2)
        t = (squared - self.squared[segment]) / (self.squared[segment + 1] - self.squared[segment])
        knots = np.arange(len(self.squared) - 1)
        below = (knots < segment[:, None]) + np.where(knots == segment[:, None], t[:, None], 0.0)
        return below * inside[:, None], inside.astype(np.float64)

    def fitted(self, gram: np.ndarray, moment: np.ndarray, total_weight: float) -> CouplingProfile:
        """The table on the same knots that minimises ``sum w (ratio - K(d))^2`` given the weighted
        normal equations of the drops (``gram = B^T W B``, ``moment = B^T W (inside - ratio)`` over
        rows ``B`` of :meth:`basis`, ``total_weight = sum w``) under ``drop >= 0`` (K non-increasing),
        plus a small penalty on changes of slope (in d) between knots; NNLS on the Cholesky factor."""
        count = len(self.squared)
        gaps = np.diff(self.squared) / self.reach**2
        smooth = np.zeros((count - 2, count - 1))  # slope in q of segment j is -drop_j / gap_j
        smooth[np.arange(count - 2), np.arange(1, count - 1)] = 1.0 / gaps[1:]
        smooth[np.arange(count - 2), np.arange(count - 2)] = -1.0 / gaps[:-1]
        penalty = SLOPE_PENALTY * total_weight / (count - 1) * gaps.mean() ** 2
        regularised = gram + penalty * smooth.T @ smooth + 1e-12 * np.trace(gram) * np.eye(count - 1)
        factor = np.linalg.cholesky(regularised).T  # upper: factor^T factor = regularised
        drops, _ = nnls(factor, np.linalg.solve(factor.T, moment))
        return CouplingProfile(self.distances, 1.0 - np.concatenate([[0.0], np.cumsum(drops)]))


class ProfileLearner:
    """Accumulates the weighted normal equations of well-posed touches' pairs (squared distance,
    ratio, weight), each touch's share fading by ``1 - 1 / memory`` per later touch (no pair is
    stored), and refits the profile at the ``first``-th touch, then after ``every`` more touches,
    the interval doubling up to ``longest`` (the profile settles; each refit costs the processing
    new tail bounds)."""

    def __init__(self, profile: CouplingProfile, memory: float = 150.0, first: int = 20, every: int = 20,
                 longest: int = 160):
        self.profile = profile
        self.fade = 1.0 - 1.0 / memory
        self.next_refit, self.interval, self.longest = first, every, longest
        count = len(profile.squared) - 1
        self.gram, self.moment, self.total_weight = np.zeros((count, count)), np.zeros(count), 0.0
        self.touches = 0
        self.updates = 0

    def add(self, squared: np.ndarray, ratios: np.ndarray, weights: np.ndarray) -> bool:
        """Add one touch's pairs (mm^2, ratio, 1 / variance of the ratio); returns whether the
        profile was refitted."""
        below, inside = self.profile.basis(squared)
        weighted = below * weights[:, None]
        self.gram = self.fade * self.gram + below.T @ weighted
        self.moment = self.fade * self.moment + weighted.T @ (inside - ratios)
        self.total_weight = self.fade * self.total_weight + float(weights.sum())
        self.touches += 1
        if self.touches < self.next_refit:
            return False
        self.profile = self.profile.fitted(self.gram, self.moment, self.total_weight)
        self.updates += 1
        self.next_refit += self.interval
        self.interval = min(2 * self.interval, self.longest)
        return True
