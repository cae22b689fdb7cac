"""Baseline, common-mode and noise estimation of the board's channels (see :mod:`.processing`,
step 1), over every channel pair the board scans (``num_tx x num_rx``), wired to a crossing or not.

* **Start-up**: the first ``calibration_frames`` frames (no touch assumed) give each channel's
  baseline; their noise sigma is measured after the frames' common modes are removed.
* **Common modes** per frame, from the channels the caller does not exclude as touched: a relative
  offset common to the whole board (temperature drift: median of ``delta / baseline``), then one
  offset per Tx row and one per Rx column (noise and drift that a drive line or a receiver adds to
  every channel it scans): medians along the rows and columns first, then the mean of the *quiet*
  channels (within ``update_sigma`` noise sigmas of those medians) along each row, then along each
  column. Channel pairs
  without a crossing carry these common modes but no touch, so they make the estimates robust
  beside a touch. A row or column with fewer than ``MIN_QUIET`` quiet channels gets no offset.
* **Tracking**: each quiet channel's baseline follows the raw counts with time constant
  ``baseline_tau_s``, its noise sigma (on the common-mode-free deltas) with ``noise_tau_s``.
  Channels the caller holds (near an active touch) do not update; a channel held longer than
  ``max_hold_s`` is re-baselined (a stuck touch fades); one reading far below its baseline for
  ``negative_reset_frames`` frames is re-baselined (a finger that rested on it at start-up).

Units: counts, seconds.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .processing import ProcessingParams

MIN_QUIET = 3  # quiet channels a row or column needs for its common-mode offset


def median(values: np.ndarray) -> float:
    """Median of a small 1-D array of finite values (what ``np.median`` returns, at a tenth of its
    per-call overhead)."""
    ordered = np.sort(values)
    middle = len(ordered) // 2
    return float(ordered[middle]) if len(ordered) % 2 else float((ordered[middle - 1] + ordered[middle]) / 2)


def _medians(grid: np.ndarray, axis: int) -> np.ndarray:
    """Medians of ``grid`` along ``axis``, kept as a length-1 axis (``np.median`` at a fifth of its cost)."""
    ordered = np.sort(grid if axis == 1 else grid.T, axis=1)
    n = ordered.shape[1]
    middle = (ordered[:, (n - 1) // 2] + ordered[:, n // 2]) / 2
    return middle[:, None] if axis == 1 else middle[None]


def line_offsets(delta: np.ndarray, quiet: np.ndarray) -> np.ndarray:
    """(num_tx, num_rx) offsets common to Tx rows, then to Rx columns: the mean of the quiet entries
    of ``delta`` (num_tx, num_rx) along each row, then of what is left along each column (0 for a
    line with fewer than ``MIN_QUIET`` quiet entries)."""
    weights = quiet.astype(np.float64)
    count = weights.sum(axis=1, keepdims=True)
    rows = np.where(count >= MIN_QUIET, (delta * weights).sum(axis=1, keepdims=True) / np.maximum(count, 1), 0.0)
    rest = delta - rows
    count = weights.sum(axis=0, keepdims=True)
    columns = np.where(count >= MIN_QUIET, (rest * weights).sum(axis=0, keepdims=True) / np.maximum(count, 1), 0.0)
    return rows + columns


class Baseline:
    """Per-channel baseline and noise of a ``shape = (num_tx, num_rx)`` board (see the module docstring)."""

    def __init__(self, shape: tuple[int, int], params: ProcessingParams):
        self.shape = shape
        self.params = params
        self.reset()

    def reset(self) -> None:
        n = self.shape[0] * self.shape[1]
        self._frames: list[np.ndarray] = []
        self.baseline = np.zeros(n)
        self.noise = np.ones(n)
        self._held_since = np.full(n, np.inf)
        self._below = np.zeros(n, dtype=np.int64)

    @property
    def calibrated(self) -> bool:
        return len(self._frames) >= self.params.calibration_frames

    def calibrate(self, raw: np.ndarray) -> None:
        """Add one start-up frame (flattened channel order, counts); the last one sets the baseline
        (mean) and the noise (std of the common-mode-free deviations, at least the pooled median:
        20 frames give a sigma within ~+-16 %, and the channels of one board share their floor)."""
        self._frames.append(raw)
        if not self.calibrated:
            return
        stack = np.array(self._frames)
        valid = np.all(stack >= 0, axis=0)
        self.baseline = stack.mean(axis=0)
        deviation = stack - self.baseline
        quiet = np.broadcast_to(valid.reshape(self.shape), (len(stack), *self.shape))
        lines = np.array([line_offsets(d.reshape(self.shape), q) for d, q in zip(deviation, quiet)])
        spread = (deviation - lines.reshape(len(stack), -1)).std(axis=0, ddof=1)
        self.noise = np.maximum(spread, float(median(spread[valid]))) if valid.any() else spread

    def sigma(self) -> np.ndarray:
        """(channels,) noise sigma the thresholds use, floored (counts)."""
        floor = max(self.params.min_noise_counts, 0.5 * median(self.noise))
        return np.maximum(self.noise, floor)

    def delta(self, raw: np.ndarray, valid: np.ndarray, sigma: np.ndarray, touched: np.ndarray) -> np.ndarray:
        """``raw - baseline`` with the frame's common modes removed (counts; 0 where not ``valid``);
        ``touched`` channels never inform the common modes."""
        delta = raw - self.baseline
        candidates = valid & ~touched & (self.baseline > 0)
        if np.count_nonzero(candidates) >= MIN_QUIET:
            common = median(delta[candidates] / self.baseline[candidates])
            delta = raw - self.baseline * (1.0 + common)
            # Quiet is judged after a first, robust removal (medians along the lines, the excluded
            # channels read as 0): correlated noise larger than the channels' own would otherwise
            # leave whole lines un-quiet.
            grid = np.where(candidates, delta, 0.0).reshape(self.shape)
            rough = _medians(grid, axis=1)
            rough = rough + _medians(grid - rough, axis=0)
            quiet = candidates & (np.abs(delta - rough.ravel()) < self.params.update_sigma * sigma)
            delta -= line_offsets(delta.reshape(self.shape), quiet.reshape(self.shape)).ravel()
        delta[~valid] = 0.0
        return delta

    def update(self, raw: np.ndarray, delta: np.ndarray, valid: np.ndarray, sigma: np.ndarray,
               held: np.ndarray | None, t: float, dt: float) -> None:
        """Track drift and noise on the quiet channels after a frame at ``t`` (s), ``dt`` (s) after the
        previous one; ``held`` (channels,) bool or None: channels near a touch."""
        p = self.params
        quiet = valid & (np.abs(delta) < p.update_sigma * sigma)
        if held is not None:
            self._held_since = np.where(held, np.minimum(self._held_since, t), np.inf)
            stuck = held & (t - self._held_since > p.max_hold_s)
            self.baseline[stuck] = raw[stuck]
            self._held_since[stuck] = np.inf
            quiet &= ~held
        else:
            self._held_since.fill(np.inf)
        alpha = 1.0 - np.exp(-dt / p.baseline_tau_s)
        self.baseline[quiet] += alpha * (raw[quiet] - self.baseline[quiet])
        beta = 1.0 - np.exp(-dt / p.noise_tau_s)
        self.noise[quiet] = np.sqrt((1 - beta) * self.noise[quiet] ** 2 + beta * delta[quiet] ** 2)
        below = valid & (delta < -p.on_sigma * sigma)
        self._below = np.where(below, self._below + 1, 0)
        reset = self._below >= p.negative_reset_frames
        self.baseline[reset] = raw[reset]
        self._below[reset] = 0
