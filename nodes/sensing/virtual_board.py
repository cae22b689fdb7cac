"""A virtual Muca board: raw frames from simulated finger touches on a sensing map (the pseudo-terminal
that serves them is :mod:`.pty_board`, the touches come from :mod:`.scripts`).

Signal model per cell ``i`` at crossing ``x_i`` (counts, clipped to 0..65535)::

    raw_i(t) = B_i (1 + c(t)) + w_i(t) + g_i sum_f S_f K(|p_f - x_i|) + N(0, sigma_n^2)

* ``B_i`` uniform in the FT5x06 range seen on real boards (9650..10360); channel pairs without a
  crossing read baseline + noise only.
* ``c(t)`` common drift (``drift_fraction`` x a slow sine of period ``drift_period_s``, temperature),
  ``w_i`` an independent per-cell random walk (``cell_walk_counts`` per sqrt(s)).
* ``g_i`` cell gain: 1 with an electrode pad, ``no_pad_gain`` without, times a lognormal jitter.
* ``S_f`` finger strength: ``signal_counts`` x a per-touch jitter (pressure, finger orientation).
* ``K`` the coupling profile (1 at distance 0), ``coupling_model``:

  - ``"gaussian"`` (default): ``K(d) = exp(-d^2 / (2 s^2))``, the processing's own model, with
    ``s`` = :func:`..data.board.default_coupling_width_mm` unless ``coupling_sigma_mm`` is given;
  - ``"disc"``: a contact disc of radius ``finger_radius`` over a crossing whose sensitivity falls
    off like ``(1 + rho^2 / h^2)^(-3/2)`` (the field of a charge at height ``h`` over the plane),
    ``K(d)`` = that kernel integrated over the disc centred at distance ``d``, normalised.
    ``h`` is set so that ``K`` falls to one half where the Gaussian does (same reach), so the
    difference is the shape: a flat top and a power-law tail, which the processing's Gaussian fit
    does not contain. It measures how localization holds up when the real coupling is not the
    assumed one.
* ``sigma_n = signal_counts / snr``: ``snr`` is the peak-signal-over-noise-sigma of a nominal finger
  centred on a padded cell.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np
from pydantic import Field

from ...graph.errors import UserError
from ...graph.node import NodeParams
from ..data.board import MAX_COUNT, NUM_RX, NUM_TX, default_coupling_width_mm
from ..data.sensing_map import SensingMap


class BoardParams(NodeParams):
    """Virtual board settings (counts, mm, seconds; see the module docstring)."""

    snr: float = Field(60.0, gt=0, description="peak signal of a nominal centred finger over noise sigma")
    signal_counts: float = Field(300.0, gt=0, description="peak delta of a nominal finger on a padded cell")
    baseline_low: float = Field(9650.0, ge=0, description="lowest cell baseline (counts)")
    baseline_high: float = Field(10360.0, ge=0, description="highest cell baseline (counts)")
    finger_radius_mm: float = Field(4.5, gt=0, description="finger contact radius (mm)")
    coupling_sigma_mm: float | None = Field(None, gt=0, description="coupling width; None: sqrt(r^2 + (pitch/2)^2)")
    coupling_model: Literal["gaussian", "disc"] = Field(
        "gaussian", description="coupling profile: the processing's Gaussian, or a contact disc with a power-law tail")
    no_pad_gain: float = Field(0.5, gt=0, description="gain of a crossing without an electrode pad")
    cell_gain_jitter: float = Field(0.05, ge=0, description="lognormal sigma of per-cell gain")
    touch_strength_jitter: float = Field(0.15, ge=0, description="uniform +- relative jitter of each touch's strength")
    drift_fraction: float = Field(0.005, ge=0, description="amplitude of the common relative drift")
    drift_period_s: float = Field(300.0, gt=0, description="period of the common drift (s)")
    cell_walk_counts: float = Field(0.2, ge=0, description="per-cell random walk (counts per sqrt(s))")
    rate_hz: float = Field(10.0, gt=0, description="frame rate of the board")
    flip_tx: bool = Field(False, description="emit TX in reversed wire order (master firmware)")
    flip_rx: bool = Field(False, description="emit RX in reversed wire order (2020 library)")
    seed: int = 0


def disc_kernel_integral(radius: float, height: float, distances: np.ndarray) -> np.ndarray:
    """Integral of ``(1 + rho^2 / height^2)^(-3/2)`` over a disc of ``radius`` (mm) whose centre is
    ``distances`` (mm, 1D) from the kernel's centre, normalised to 1 at distance 0 (polar midpoint
    quadrature, 48 x 96 nodes: the profile is smooth)."""
    radial = (np.arange(48) + 0.5) / 48 * radius
    angles = (np.arange(96) + 0.5) / 96 * 2 * np.pi
    rho, theta = np.meshgrid(radial, angles, indexing="ij")
    weights = (rho * (radius / 48) * (2 * np.pi / 96)).ravel()
    x, y = (rho * np.cos(theta)).ravel(), (rho * np.sin(theta)).ravel()
    d = np.concatenate([[0.0], np.atleast_1d(distances)])[:, None]
    integral = (1 + ((x - d) ** 2 + y**2) / height**2) ** -1.5 @ weights
    return integral[1:] / integral[0]


def disc_coupling_profile(radius: float, half_maximum: float) -> tuple[np.ndarray, np.ndarray]:
    """The ``"disc"`` coupling profile as a table ``(distances, values)`` (mm, 0.1 mm steps out to
    ``8 x half_maximum``) for ``np.interp``: a disc of ``radius`` (mm), the kernel height found by
    bisection so that the profile is 1/2 at ``half_maximum`` (mm)."""
    # As the height goes to 0 the profile tends to 1 inside the disc and 0 outside it.
    if half_maximum <= radius:
        raise UserError(f"disc coupling: the {radius:.2f} mm finger disc reaches past the half-maximum distance "
                        f"{half_maximum:.2f} mm; lower finger_radius_mm or raise coupling_sigma_mm")
    low, high = 1e-3 * radius, 100.0 * half_maximum
    for _ in range(60):  # the profile at a fixed distance grows with the height
        height = np.sqrt(low * high)
        if disc_kernel_integral(radius, height, np.array([half_maximum]))[0] < 0.5:
            low = height
        else:
            high = height
    distances = np.arange(0.0, 8.0 * half_maximum + 0.1, 0.1)
    return distances, np.concatenate([[1.0], disc_kernel_integral(radius, np.sqrt(low * high), distances[1:])])


class VirtualBoard:
    """Frames of a Muca board on a sensing map (see the module docstring for the model)."""

    def __init__(self, sensing_map: SensingMap, params: BoardParams = BoardParams()):
        self.map = sensing_map
        self.params = params
        self.rng = np.random.default_rng(params.seed)
        n = NUM_TX * NUM_RX  # the board scans all its channels, wired or not
        self.baseline = self.rng.uniform(params.baseline_low, params.baseline_high, n)
        self.pitch = sensing_map.pitch_mm()
        self.coupling_sigma = params.coupling_sigma_mm or default_coupling_width_mm(params.finger_radius_mm, self.pitch)
        if params.coupling_model == "disc":
            half_maximum = self.coupling_sigma * np.sqrt(2 * np.log(2))
            self.disc_profile = disc_coupling_profile(params.finger_radius_mm, half_maximum)
        pad_gain = np.where(sensing_map.cell_pad, 1.0, params.no_pad_gain)
        self.gain = pad_gain * self.rng.lognormal(0.0, params.cell_gain_jitter, sensing_map.cell_count)
        self.noise_sigma = params.signal_counts / params.snr
        self.drift_phase = self.rng.uniform(0, 2 * np.pi)
        self.walk = np.zeros(n)
        self._last_t: float | None = None

    def signal(self, fingers: Sequence[tuple[np.ndarray, float]]) -> np.ndarray:
        """Noise-free touch signal (counts) per sensing-map cell for fingers ``(point, strength)``."""
        signal = np.zeros(self.map.cell_count)
        for point, strength in fingers:
            d2 = np.sum((self.map.cell_points - point) ** 2, axis=1)
            if self.params.coupling_model == "disc":
                signal += strength * np.interp(np.sqrt(d2), *self.disc_profile, right=0.0)
            else:
                signal += strength * np.exp(-d2 / (2 * self.coupling_sigma**2))
        return self.gain * signal

    def frame(self, t: float, fingers: Sequence[tuple[np.ndarray, float]] = ()) -> np.ndarray:
        """Counts at time ``t`` (s) in wire order, shape (21, 12), int64."""
        p = self.params
        if p.cell_walk_counts and self._last_t is not None and t > self._last_t:
            self.walk += self.rng.normal(0, p.cell_walk_counts * np.sqrt(t - self._last_t), len(self.walk))
        self._last_t = t
        common = p.drift_fraction * np.sin(2 * np.pi * t / p.drift_period_s + self.drift_phase)
        raw = self.baseline * (1 + common) + self.walk + self.rng.normal(0, self.noise_sigma, len(self.walk))
        raw[self.map.frame_index] += self.signal(fingers)
        grid = np.clip(np.rint(raw), 0, MAX_COUNT).astype(np.int64).reshape(NUM_TX, NUM_RX)
        if p.flip_tx:
            grid = grid[::-1]
        if p.flip_rx:
            grid = grid[:, ::-1]
        return grid
