"""Per-crossing gains learned online from ordinary touches (see :mod:`.processing`, step 4): a
crossing's gain ``g_i`` (1 for a nominal padded crossing) is what multiplies the coupling model
``A K(|p - x_i|)`` of a well-posed touch to give the crossing's delta.

From every well-posed single touch, each crossing the finger is close to (``K >= NEAR_PROFILE``,
where the profile's shape matters least) and that reads above ``MIN_SNR`` noise sigmas gives one
estimate ``log(delta_i / (A K_i))``, weighted by its signal-to-noise squared (capped: many frames
of one touch are not independent). Estimates accumulate with a fading memory of ``memory`` touches,
on top of the starting gains (the sensing map's pad / no-pad default or a calibration's
measurement) counted as ``prior_touches`` touches. A crossing's gain is the weighted mean of its
log estimates once it has ``MIN_TOUCHES`` touches' worth of weight; the gains are then rescaled
so the median learned padded crossing stays at 1 (the touch amplitude ``A`` carries the overall
scale), and the crossings without a pad and without enough touches take the no-pad gain,
estimated rather than assumed: the weighted mean of every log estimate of every crossing without a
pad, once they add up to ``MIN_TOUCHES`` touches' worth (each such crossing may see too few touches
for a gain of its own, but together they tell how much less a crossing without a pad reads).

Units: gains relative to a padded crossing, log counts.
"""
from __future__ import annotations

import numpy as np

NEAR_PROFILE = 0.3  # a crossing informs its gain when the profile there is at least this (within ~1.5 widths)
MIN_SNR = 6.0  # ... and its delta reads above this many noise sigmas
WEIGHT_CAP = 400.0  # largest weight of one estimate ((signal / noise)^2 of 20 sigmas)
MEASURED_TOUCHES = 3.0  # touches' worth of weight of a calibration's measured gain
MIN_TOUCHES = 3.0  # touches' worth of weight (at the cap) before a crossing's learned gain is used
LOG_RANGE = (np.log(0.1), np.log(10.0))  # learned gains stay within 0.1..10 of a padded crossing


class GainLearner:
    """Accumulates per-crossing log-gain estimates from touches and gives the current gains."""

    def __init__(self, gains: np.ndarray, pad: np.ndarray, measured: bool = False, memory: float = 300.0):
        """``gains`` the starting gains, ``measured`` whether a calibration measured them (they then
        count as ``MEASURED_TOUCHES`` touches and keep their no-pad values) or they are the map's
        defaults (one touch)."""
        self.pad = np.asarray(pad, dtype=bool)
        self.measured = measured
        prior_touches = MEASURED_TOUCHES if measured else 1.0
        self.start = np.asarray(gains, dtype=np.float64).copy()
        self.fade = 1.0 - 1.0 / memory
        self.weight = np.full(len(self.start), prior_touches * WEIGHT_CAP)
        self.moment = self.weight * np.log(self.start)
        self.learned = np.zeros(len(self.start))  # touches' worth of weight from touches, no prior
        self.learned_moment = np.zeros(len(self.start))  # weighted log estimates from touches, no prior
        self.touches = 0

    def add(self, cells: np.ndarray, log_ratios: np.ndarray, weights: np.ndarray) -> None:
        """One touch's estimates at ``cells``: ``log(delta / (A K))`` and their weights."""
        weights = np.minimum(weights, WEIGHT_CAP)
        keep = np.isfinite(log_ratios)
        cells, log_ratios, weights = cells[keep], log_ratios[keep], weights[keep]
        weighted = weights * np.minimum(np.maximum(log_ratios, LOG_RANGE[0]), LOG_RANGE[1])  # np.clip, without its overhead
        self.weight[cells] = self.fade * self.weight[cells] + weights
        self.moment[cells] = self.fade * self.moment[cells] + weighted
        self.learned[cells] = self.fade * self.learned[cells] + weights / WEIGHT_CAP
        self.learned_moment[cells] = self.fade * self.learned_moment[cells] + weighted
        self.touches += 1

    def gains(self) -> np.ndarray:
        """(K,) current gains (see the module docstring)."""
        log_gain = self.moment / self.weight
        known = self.learned >= MIN_TOUCHES
        padded = known & self.pad
        shift = float(np.median(log_gain[padded])) if np.count_nonzero(padded) >= 3 else 0.0
        gains = np.where(known, np.exp(log_gain - shift), self.start)
        no_pad = ~self.pad & (self.learned > 0)
        pooled = float(self.learned[no_pad].sum())
        if pooled >= MIN_TOUCHES and not self.measured:
            no_pad_gain = np.exp(self.learned_moment[no_pad].sum() / (pooled * WEIGHT_CAP) - shift)
            gains = np.where(~known & ~self.pad, no_pad_gain, gains)
        return gains
