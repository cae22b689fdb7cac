"""Baseline, common-mode and noise estimation of the board's channels (see :mod:`.processing`,
step 1), over every channel pair the board scans (``num_tx x num_rx``), wired to a crossing or not.

* **Start-up**: the first ``calibration_frames`` frames (no touch assumed) give each channel's
  baseline; their noise sigma is measured after the frames' common modes are removed.
* **Common modes** per frame, from the channels the caller does not exclude as touched: a relative
  offset common to the whole board (temperature drift: median of ``delta / baseline`` after the last
  frame's line offsets), then one offset per Tx row and one per Rx column (noise and drift that a
  drive line or a receiver adds to every channel it scans): the last frame's offsets updated by a
  median polish over the candidates, then the weighted least-squares fit ``r_i + c_j`` to the
  *quiet* channels (within ``update_sigma`` noise sigmas of the polish), each weighted by
  ``sigma^2 / (sigma^2 + reach^2)`` with ``reach`` what the caller's touches may add to it (a
  finger's faint tail on a witness would pull its lines' offsets up and the touch's own crossings
  low). Channel pairs without a crossing carry these common modes but no touch, so they make the
  estimates robust beside a touch. A row or column whose witnesses weigh less than ``MIN_QUIET``
  quiet channels (a touch along a Tx line) keeps its last offset: only its change since is
  unobservable.
* **Tracking**: each quiet channel's baseline follows its common-mode-free delta with time constant
  ``baseline_tau_s`` (what the common modes do not explain: the channel's own slow walk), its noise
  sigma with ``noise_tau_s``. The common modes are removed anew in every frame, so a channel that
  does not update (held, or out of the quiet band) still loses its line's drift; a baseline that
  followed the raw counts would carry the line drift too, and a channel out of the quiet band would
  drift on with it, from a slow rise to a false touch at rest.
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

MIN_QUIET = 3  # quiet channels (their weight) a row or column needs for its common-mode offset
LINE_SWEEPS = 2  # alternating row / column passes of the line offsets' least-squares fit
POLISH_SWEEPS = 2  # row / column passes of the median polish that judges which channels are quiet


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


def median_polish(grid: np.ndarray, mask: np.ndarray, sweeps: int = POLISH_SWEEPS) -> tuple[np.ndarray, np.ndarray]:
    """Row (num_tx, 1) and column (1, num_rx) offsets of ``grid``: medians along the rows, then along
    the columns, of what the other lines leave, ``sweeps`` times (the first row medians see every
    column's offset as spread, which the second sweep has removed); entries outside ``mask`` read as
    0 (no offset), so a line of excluded entries gets none."""
    rows, columns = np.zeros((grid.shape[0], 1)), np.zeros((1, grid.shape[1]))
    for _ in range(sweeps):
        rows = rows + _medians(np.where(mask, grid - rows - columns, 0.0), axis=1)
        columns = columns + _medians(np.where(mask, grid - rows - columns, 0.0), axis=0)
    return rows, columns


def line_offsets(delta: np.ndarray, weights: np.ndarray, rows: np.ndarray, columns: np.ndarray,
                 sweeps: int = LINE_SWEEPS) -> tuple[np.ndarray, np.ndarray]:
    """Offsets ``r_i`` (num_tx, 1) and ``c_j`` (1, num_rx) common to Tx rows and Rx columns, fitted by
    least squares to the entries of ``delta`` (num_tx, num_rx) with ``weights`` (0 for an entry that
    is not quiet) from ``rows`` / ``columns``: alternating weighted means along the rows and the
    columns, ``sweeps`` times (one sweep is exact when every weight is equal; a touch's excluded
    entries make the rows see different columns, which later sweeps even out). A line whose weights
    sum to less than ``MIN_QUIET`` keeps its offset from the start."""
    weights = weights.astype(np.float64)
    row_count, column_count = weights.sum(axis=1, keepdims=True), weights.sum(axis=0, keepdims=True)
    for _ in range(sweeps):
        rest = (delta - columns) * weights
        rows = np.where(row_count >= MIN_QUIET, rest.sum(axis=1, keepdims=True) / np.maximum(row_count, 1), rows)
        rest = (delta - rows) * weights
        columns = np.where(column_count >= MIN_QUIET, rest.sum(axis=0, keepdims=True) / np.maximum(column_count, 1),
                           columns)
    return rows, columns


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
        self._scale = 1.0  # 1 + the last frame's relative common mode
        self.rows, self.columns = np.zeros((self.shape[0], 1)), np.zeros((1, self.shape[1]))  # line offsets (counts)

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
        zero_rows, zero_columns = np.zeros((self.shape[0], 1)), np.zeros((1, self.shape[1]))
        lines = np.array([np.add(*line_offsets(d.reshape(self.shape), q, zero_rows, zero_columns))
                          for d, q in zip(deviation, quiet)])
        spread = (deviation - lines.reshape(len(stack), -1)).std(axis=0, ddof=1)
        self.noise = np.maximum(spread, float(median(spread[valid]))) if valid.any() else spread

    def sigma(self) -> np.ndarray:
        """(channels,) noise sigma the thresholds use, floored (counts)."""
        floor = max(self.params.min_noise_counts, 0.5 * median(self.noise))
        return np.maximum(self.noise, floor)

    def delta(self, raw: np.ndarray, valid: np.ndarray, sigma: np.ndarray, touched: np.ndarray,
              reach: np.ndarray | None = None) -> np.ndarray:
        """``raw - baseline`` with the frame's common modes removed (counts; 0 where not ``valid``);
        ``touched`` channels never inform the common modes; ``reach`` (channels,) counts, how much
        the touches may add to each channel, weighs the line offsets' witnesses by
        ``sigma^2 / (sigma^2 + reach^2)``."""
        delta = raw - self.baseline
        self._scale = 1.0
        candidates = valid & ~touched & (self.baseline > 0)
        if np.count_nonzero(candidates) >= MIN_QUIET:
            lines = (self.rows + self.columns).ravel()
            common = median((delta - lines)[candidates] / self.baseline[candidates])
            delta = raw - self.baseline * (1.0 + common)
            # Quiet is judged after a first, robust update of the last frame's line offsets (a median
            # polish over the candidates): correlated noise larger than the channels' own would
            # otherwise leave whole lines un-quiet.
            rows, columns = median_polish((delta - lines).reshape(self.shape), candidates.reshape(self.shape))
            rows, columns = self.rows + rows, self.columns + columns
            quiet = candidates & (np.abs(delta - (rows + columns).ravel()) < self.params.update_sigma * sigma)
            weights = quiet if reach is None else quiet * sigma**2 / (sigma**2 + reach**2)
            rows, columns = line_offsets(delta.reshape(self.shape), weights.reshape(self.shape), rows, columns)
            delta -= (rows + columns).ravel()
            # Kept with zero means: their common level is the next frame's common mode's (else it
            # would walk from frame to frame, and the relative mode with it).
            self.rows, self.columns = rows - rows.mean(), columns - columns.mean()
            self._scale = 1.0 + common
        delta[~valid] = 0.0
        return delta

    def update(self, delta: np.ndarray, valid: np.ndarray, sigma: np.ndarray,
               held: np.ndarray | None, t: float, dt: float) -> None:
        """Track drift and noise on the quiet channels after a frame at ``t`` (s), ``dt`` (s) after the
        previous one; ``held`` (channels,) bool or None: channels near a touch."""
        p = self.params
        quiet = valid & (np.abs(delta) < p.update_sigma * sigma)
        if held is not None:
            self._held_since = np.where(held, np.minimum(self._held_since, t), np.inf)
            stuck = held & (t - self._held_since > p.max_hold_s)
            self.baseline[stuck] += delta[stuck] / self._scale
            self._held_since[stuck] = np.inf
            quiet &= ~held
        else:
            self._held_since.fill(np.inf)
        alpha = 1.0 - np.exp(-dt / p.baseline_tau_s)
        self.baseline[quiet] += alpha * delta[quiet] / self._scale
        beta = 1.0 - np.exp(-dt / p.noise_tau_s)
        self.noise[quiet] = np.sqrt((1 - beta) * self.noise[quiet] ** 2 + beta * delta[quiet] ** 2)
        below = valid & (delta < -p.on_sigma * sigma)
        self._below = np.where(below, self._below + 1, 0)
        reset = self._below >= p.negative_reset_frames
        self.baseline[reset] += delta[reset] / self._scale
        self._below[reset] = 0
