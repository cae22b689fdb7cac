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

What a real board and a hand-laid sensor add (all off in :class:`BoardParams`' defaults, which are
the processing's own assumptions; :data:`REALISTIC_BOARD`, the simulator's default board, turns
them on): noise common to a whole Tx row and to a whole Rx column per frame (``tx_noise_counts``,
``rx_noise_counts``, sigma), single-frame spikes on a cell (``spike_probability`` per cell and
frame, ``spike_counts`` high), a slow sine per Tx and per Rx channel (``channel_drift_counts``,
periods drawn in ``channel_drift_period_s`` x 0.5..2) and crossings that sit ``crossing_offset_mm``
(a range, mm) away from where the sensing map says, in a random tangent direction (hand placement).
These draw from their own random stream, so a board without them gives the same frames as before.
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

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
    tx_noise_counts: float = Field(0.0, ge=0, description="per-frame noise common to one Tx row (counts, sigma)")
    rx_noise_counts: float = Field(0.0, ge=0, description="per-frame noise common to one Rx column (counts, sigma)")
    spike_probability: float = Field(0.0, ge=0, le=1, description="chance of a one-frame spike per cell and frame")
    spike_counts: float = Field(0.0, ge=0, description="height of a spike (counts)")
    channel_drift_counts: float = Field(0.0, ge=0, description="amplitude of the slow drift of each Tx and Rx channel")
    channel_drift_period_s: float = Field(120.0, gt=0, description="typical period of a channel's drift (s)")
    crossing_offset_mm: tuple[float, float] = Field(
        (0.0, 0.0), description="range of the distance (mm) from each crossing's mapped point to where it really is")
    flip_tx: bool = Field(False, description="emit TX in reversed wire order (master firmware)")
    flip_rx: bool = Field(False, description="emit RX in reversed wire order (2020 library)")
    seed: int = 0

    @model_validator(mode="after")
    def _ranges(self) -> BoardParams:
        low, high = self.crossing_offset_mm
        if not 0 <= low <= high:
            raise ValueError("crossing_offset_mm must be [low, high] with 0 <= low <= high")
        if self.baseline_low > self.baseline_high:
            raise ValueError("baseline_low must not exceed baseline_high")
        return self


REALISTIC_BOARD = BoardParams(
    no_pad_gain=0.3, cell_gain_jitter=0.2, finger_radius_mm=5.5, coupling_model="disc", tx_noise_counts=2.0,
    rx_noise_counts=2.0, spike_probability=2e-5, spike_counts=60.0, channel_drift_counts=15.0,
    crossing_offset_mm=(1.0, 3.0),
)
"""The simulator's default board: unlike the processing's assumptions in every setting the
processing relies on (no-pad gain 0.3 vs 0.5, 20 % per-cell gain spread, a 5.5 mm finger with a
flat-topped, heavy-tailed coupling, correlated row/column noise, spikes, per-channel drift,
crossings 1-3 mm from the map)."""


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
        self._has_imperfections = bool(params.tx_noise_counts or params.rx_noise_counts or params.channel_drift_counts
                                       or (params.spike_probability and params.spike_counts))
        self._imperfection_rng = np.random.default_rng([params.seed, 1])  # keeps rng's stream as without them
        self.cell_points = self._displaced_crossings()
        self.channel_drift = (self._imperfection_rng.uniform(0, 2 * np.pi, NUM_TX + NUM_RX),
                              params.channel_drift_period_s * self._imperfection_rng.uniform(0.5, 2.0, NUM_TX + NUM_RX))

    def _displaced_crossings(self) -> np.ndarray:
        """(K, 3) where the crossings really are: ``crossing_offset_mm`` from the map's points in a
        random tangent direction, back on the surface."""
        low, high = self.params.crossing_offset_mm
        points = self.map.cell_points
        if high <= 0:
            return points
        from ..geometry.surface import SurfaceProjector

        projector = SurfaceProjector(self.map.vertices, self.map.faces)
        rng = self._imperfection_rng
        direction = rng.normal(size=points.shape)
        normals = self.map.cell_normals
        direction -= np.einsum("ij,ij->i", direction, normals)[:, None] * normals
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        moved = points + rng.uniform(low, high, len(points))[:, None] * direction
        return np.array([projector.project(p, n)[0][0] for p, n in zip(moved, normals)])

    def _imperfections(self, t: float) -> np.ndarray:
        """(NUM_TX * NUM_RX,) counts added by row/column noise, spikes and channel drift at ``t`` (s)."""
        p, rng = self.params, self._imperfection_rng
        extra = np.zeros((NUM_TX, NUM_RX))
        if p.tx_noise_counts:
            extra += rng.normal(0, p.tx_noise_counts, (NUM_TX, 1))
        if p.rx_noise_counts:
            extra += rng.normal(0, p.rx_noise_counts, (1, NUM_RX))
        if p.channel_drift_counts:
            phase, period = self.channel_drift
            drift = p.channel_drift_counts * np.sin(2 * np.pi * t / period + phase)
            extra += drift[:NUM_TX, None] + drift[None, NUM_TX:]
        if p.spike_probability and p.spike_counts:
            extra += p.spike_counts * (rng.random((NUM_TX, NUM_RX)) < p.spike_probability)
        return extra.ravel()

    def signal(self, fingers: Sequence[tuple[np.ndarray, float]]) -> np.ndarray:
        """Noise-free touch signal (counts) per sensing-map cell for fingers ``(point, strength)``."""
        signal = np.zeros(self.map.cell_count)
        for point, strength in fingers:
            d2 = np.sum((self.cell_points - point) ** 2, axis=1)
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
        if self._has_imperfections:
            raw += self._imperfections(t)
        grid = np.clip(np.rint(raw), 0, MAX_COUNT).astype(np.int64).reshape(NUM_TX, NUM_RX)
        if p.flip_tx:
            grid = grid[::-1]
        if p.flip_rx:
            grid = grid[:, ::-1]
        return grid


def load_board(path: str | Path, base: BoardParams = REALISTIC_BOARD) -> BoardParams:
    """A board model file: a YAML mapping of :class:`BoardParams` settings over ``base`` (the
    simulator's default board), validated like pipeline params; one-line UserError with
    ``file:line:col`` naming the setting and the fix."""
    import difflib

    import yaml
    from pydantic import ValidationError

    path = Path(path)
    if not path.is_file():
        raise UserError(f"board file {path} not found: write a YAML mapping of board settings (e.g. snr: 40)")
    try:
        root = yaml.compose(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, yaml.YAMLError) as exc:
        raise UserError(f"board file {path} is not YAML ({type(exc).__name__}): write a mapping of board settings") from None
    if root is None:
        return base
    if not isinstance(root, yaml.MappingNode):
        raise UserError(f"{path}:1:1: a board file is a mapping of settings (e.g. snr: 40)")
    settings, marks = {}, {}
    for key_node, value_node in root.value:
        key = key_node.value
        marks[key] = f"{path}:{value_node.start_mark.line + 1}:{value_node.start_mark.column + 1}"
        if key not in BoardParams.model_fields:
            close = difflib.get_close_matches(key, list(BoardParams.model_fields), n=1, cutoff=0.6)
            hint = f"; did you mean {close[0]!r}?" if close else f" (settings: {', '.join(BoardParams.model_fields)})"
            raise UserError(f"{path}:{key_node.start_mark.line + 1}:{key_node.start_mark.column + 1}: "
                            f"unknown board setting {key!r}{hint}")
        settings[key] = yaml.safe_load(yaml.serialize(value_node))
    try:
        return BoardParams.model_validate({**base.model_dump(), **settings})
    except ValidationError as exc:
        error = exc.errors()[0]
        name = str(error["loc"][0]) if error["loc"] else ""
        where = marks.get(name, f"{path}:1:1")
        raise UserError(f"{where}: board setting {name!r}: {error['msg']}" if name else f"{where}: {error['msg']}") from None
