"""From raw Muca frames to 3D touch points on the object (paper section 8).

Per frame (``TouchProcessor.process``):

1. **Baseline** (:mod:`.baseline`): over every channel pair the board scans, the first
   ``calibration_frames`` frames (no touch assumed) give the baselines and noise sigmas; per frame
   a relative offset common to the board and one offset per Tx row and per Rx column (correlated
   noise and drift of a drive line or a receiver), estimated from the quiet channels (those without
   a crossing included), are removed; quiet channels' baselines and noise follow with time
   constants ``baseline_tau_s`` / ``noise_tau_s``. Cells near an active touch are *held* (not
   updated, no witnesses of the common modes) while touched; the other witnesses weigh less where a
   touch's heaviest plausible coupling tail may reach them. A cell held longer than ``max_hold_s``
   is re-baselined (a stuck touch fades); one reading far below its baseline for
   ``negative_reset_frames`` frames is re-baselined (a finger that rested on it at start-up).
2. **Detection**: ``delta = raw - baseline`` minus the common modes, in counts (a touch raises
   counts on FT5x16 raw output). A cell turns on above ``on_sigma`` of its measured noise sigmas
   and stays on above ``off_sigma`` (hysteresis).
3. **Contact areas** (:mod:`.contacts`): the deltas are interpolated over the vertices of a simplified copy of the mesh
   (``contact_mesh_faces``; Gaussian kernel, Nadaraya-Watson); vertices above the off threshold form
   connected components over the mesh edges. Each component is split among its touch peaks (active
   cells whose gain-normalised deltas are local maxima among the active cells and are not explained
   by a stronger peak's coupling tail under the current coupling profile); the intensity-weighted,
   area-weighted centroid of each part, projected on the surface, is the coarse touch point, and the
   part's area above half of its peak intensity is the contact area.
4. **Sub-cell refinement** (``refine``; :mod:`.coupling_fit`, :mod:`.plane_fit`): the coupling model ``delta_i = g_i A K(|p - x_i|)``
   (``g_i`` = 1 with a pad, ``no_pad_gain`` without, or per crossing as ``sense --calibrate`` measured
   them, :mod:`.calibration`; ``K`` the radial coupling profile,
   :mod:`.coupling_profile`) fitted by maximum likelihood (Levenberg-Marquardt on
   the deltas of every crossing near the peak, dark ones included) with the finger kept on the
   surface; weak priors (offset ~ N(0, pitch^2), amplitude as calibrated or learned from well-posed touches) keep
   directions that a sparse layout does not resolve bounded. With several touches each one is
   refitted to the deltas minus the others' fitted coupling, starting from its first fit; peaks
   whose first fits land within a finger's width (2 ``finger_radius``) of a stronger one's, or that
   the strongest finger's heaviest plausible (power-law) tail explains, or that one finger of
   plausible amplitude fitted between it and the strongest explains (a finger in a gap between
   crossings far apart, as on ring layouts, raises a peak on either side), are one finger. With
   ``learn_gains`` the crossings' gains and the no-pad gain are learned from well-posed single
   touches (:mod:`.gain_learning`). ``K`` starts as the Gaussian of width ``s = sqrt(finger_radius^2 + (pitch/2)^2)``
   (or as the profile ``coupling_sigma_mm`` / ``coupling_tail`` that ``sense --calibrate`` measured, which
   a calibrated processing keeps); with ``adapt_coupling`` the width is calibrated from the first touches many crossings see
   (log-quadratic fits over every strong crossing the fit sees), then the shape, in units of that width, is learned from well-posed single
   touches: a board whose coupling is not a Gaussian (flat top, heavy tail) is localized without
   the bias of the wrong shape. Without a crossing above 2 sigma near the peak the coarse point stays.
5. **Tracking** (:mod:`.tracking`): touches are matched to the previous frame's tracks by minimum total distance
   (``scipy.optimize.linear_sum_assignment``) within ``track_gate_mm``; unmatched touches get fresh
   ids, unmatched tracks end; a lone finger keeps its id however far it moved, and a touch appearing
   beside live ones must persist ``confirm_frames`` frames before it touches down.

Units: mm for lengths, seconds for times inside (ms only in params named ``*_ms``), counts for
capacitance. Touch points lie on the mesh (``face`` + ``bary`` follow the datatypes conventions).
"""
from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from pydantic import Field, field_validator

from ...graph.node import NodeParams
from ..data.sensing_map import SensingMap
from ..geometry.surface import SurfaceProjector
from ..data.board import NUM_RX, NUM_TX
from .baseline import Baseline, median
from .contacts import ContactAreas
from .coupling_fit import CouplingFit
from .tracking import Tracker

SUPPORT_SIGMA = 4.0  # a reading that supports a new touch's peak is above this many noise sigmas ...
SUPPORT_READINGS = 2  # ... and a new touch's peak needs this many of them (see TouchProcessor._peaks)
SUPPORT_WIDTHS = 2.0  # crossings within this many coupling widths of a peak (its reach) support it


class ProcessingParams(NodeParams):
    """Touch processing settings (counts, mm, seconds; see the module docstring)."""

    calibration_frames: int = Field(20, ge=2, description="frames averaged for the initial baseline")
    baseline_tau_s: float = Field(2.0, gt=0, description="drift tracking time constant of quiet cells (s)")
    noise_tau_s: float = Field(20.0, gt=0, description="noise sigma tracking time constant (s)")
    update_sigma: float = Field(3.0, gt=0, description="a cell updates its baseline only while |delta| < this x sigma")
    on_sigma: float = Field(6.0, gt=0, description="cell turns on above this many noise sigmas")
    off_sigma: float = Field(4.0, gt=0, description="an on cell stays on above this many noise sigmas")
    min_noise_counts: float = Field(0.5, gt=0, description="floor of the per-cell noise sigma (counts)")
    hold_radius_mm: float | None = Field(None, gt=0, description="cells this close to a touch hold their baseline; None: 2.5 x pitch")
    max_hold_s: float = Field(60.0, gt=0, description="a cell held longer is re-baselined (stuck touch)")
    negative_reset_frames: int = Field(10, ge=1, description="frames below -on threshold before a re-baseline")
    coupling_sigma_mm: float | None = Field(None, gt=0, description="width of the profile the coupling starts from; None: sqrt(finger_radius^2 + (pitch/2)^2)")
    coupling_tail: float | None = Field(None, gt=0, description="tail of that profile, (1 + d^2 / (2 tail width^2))^-tail (a calibration measures it); None: a Gaussian")
    amplitude_prior: tuple[float, float] | None = Field(
        None, description="(log counts, spread) of a finger's reading at a padded crossing that the fits start from "
                          "(a calibration measures it); None: learned from well-posed touches")
    finger_radius_mm: float = Field(4.5, gt=0, description="finger contact radius used for the default coupling width")
    interpolation_radius_mm: float | None = Field(None, gt=0, description="vertex-to-cell interpolation radius; None: 1.5 x pitch")
    peak_radius_mm: float | None = Field(None, gt=0, description="a touch peak is the strongest cell within this radius; None: 1.5 x pitch")
    refine: bool = Field(True, description="refine the centroid with the coupling fit")
    no_pad_gain: float = Field(0.5, gt=0, description="coupling of a crossing without electrode pad relative to a padded one")
    adapt_coupling: bool = Field(True, description="learn the coupling width, then the profile's shape, from touches")
    learn_gains: bool = Field(True, description="learn each crossing's gain and the no-pad gain from touches")
    contact_mesh_faces: int = Field(6000, ge=100, description="faces of the simplified mesh used for contact areas")
    track_gate_mm: float = Field(40.0, gt=0, description="largest move between frames of one of several touches (mm); a lone finger is never gated")
    confirm_frames: int = Field(2, ge=1, description="frames a touch appearing beside live ones must persist before it touches down")

    @field_validator("amplitude_prior")
    @classmethod
    def _finite_prior(cls, value: tuple[float, float] | None) -> tuple[float, float] | None:
        if value is not None and not (np.isfinite(value[0]) and np.isfinite(value[1]) and value[1] > 0):
            raise ValueError("amplitude_prior must be (finite log counts, spread > 0)")
        return value


@dataclasses.dataclass(frozen=True)
class Touch:
    """One touch point of one frame."""

    id: int  # stable across frames while the finger stays down
    point: np.ndarray  # (3,) mm, on the surface
    face: int
    bary: np.ndarray  # (3,)
    normal: np.ndarray  # (3,) unit outward face normal
    intensity: float  # peak delta (counts)
    area_mm2: float  # contact area (interpolated intensity >= half of the peak)
    peak_cell: int  # index into the sensing map's cells

    def as_json(self) -> dict[str, Any]:
        return {"id": self.id, "point": [round(x, 3) for x in self.point.tolist()], "face": self.face,
                "bary": [round(x, 5) for x in self.bary.tolist()], "normal": [round(x, 4) for x in self.normal.tolist()],
                "intensity": round(self.intensity, 1), "area_mm2": round(self.area_mm2, 1), "cell": self.peak_cell}


@dataclasses.dataclass(frozen=True)
class FrameResult:
    """What one frame produced: touches (with ids), their lifecycle events, and per-cell deltas."""

    t: float  # s
    calibrated: bool
    touches: tuple[Touch, ...]
    events: tuple[dict[str, Any], ...]  # touch_down / touch_move / touch_up, JSON-ready
    delta: np.ndarray  # (K,) counts after baseline removal (0 during calibration)
    active: np.ndarray  # (K,) bool, cells on


class TouchProcessor:
    """Stateful frame -> touches processing for one sensing map (see the module docstring)."""

    def __init__(self, sensing_map: SensingMap, params: ProcessingParams = ProcessingParams(),
                 cell_gain: np.ndarray | None = None):
        """``cell_gain`` (K,): measured per-cell gains (:mod:`.calibration`) instead of pad ? 1 : no_pad_gain."""
        self.map = sensing_map
        self.params = params
        self.pitch = sensing_map.pitch_mm()
        self.hold_radius = params.hold_radius_mm or 2.5 * self.pitch
        self.peak_radius = params.peak_radius_mm or 1.5 * self.pitch
        cells = sensing_map.cell_points
        self.frame_index = sensing_map.frame_index
        self.cell_gain = (np.where(sensing_map.cell_pad, 1.0, params.no_pad_gain) if cell_gain is None
                          else np.asarray(cell_gain, dtype=np.float64))
        self.cell_distance = np.linalg.norm(cells[:, None] - cells[None], axis=2)
        self.projector = SurfaceProjector(sensing_map.vertices, sensing_map.faces)
        self.fit = CouplingFit(sensing_map, params, self.projector, self.cell_gain, self.cell_distance,
                               measured_gains=cell_gain is not None)
        self.contacts = ContactAreas(sensing_map, params.contact_mesh_faces,
                                     params.interpolation_radius_mm or 1.5 * self.pitch, self.pitch)
        neighbours = [np.flatnonzero((row <= self.peak_radius) & (row > 0)) for row in self.cell_distance]
        width = max(1, max(len(n) for n in neighbours))
        # (width, K): row j holds each cell's j-th neighbour within the peak radius, padded with the cell itself.
        padded = [np.pad(n, (0, width - len(n)), constant_values=k) for k, n in enumerate(neighbours)]
        self.peak_neighbours = np.ascontiguousarray(np.array(padded).T)
        self.holds = self.cell_distance <= self.hold_radius  # (K, K), symmetric: a touch at a row's cell holds the columns
        self.tracker = Tracker(params.track_gate_mm, params.confirm_frames)
        self.channels = Baseline((NUM_TX, NUM_RX), params)
        self.reset()

    def reset(self) -> None:
        """Forget baseline, noise and tracks (the next frames recalibrate)."""
        self.channels.reset()
        self.active = np.zeros(self.map.cell_count, dtype=bool)
        self.near_touch = np.zeros(self.map.cell_count, dtype=bool)  # within the hold radius of a touch of the last frame
        self.previous_delta = np.zeros(self.map.cell_count)  # (K,) counts, the last frame's
        self._touched = np.zeros(NUM_TX * NUM_RX, dtype=bool)  # channels the common modes leave out
        self._reach = np.zeros(NUM_TX * NUM_RX)  # counts the last frame's touches may add per channel
        self.tracker.reset()
        self._last_t: float | None = None

    @property
    def calibrated(self) -> bool:
        return self.channels.calibrated

    def process(self, values: np.ndarray, t: float) -> FrameResult:
        """One channel-order board frame ``(21, 12)`` at time ``t`` (s) -> :class:`FrameResult`."""
        full = np.asarray(values, dtype=np.float64).ravel()
        valid_full = full >= 0
        k = self.map.cell_count
        if not self.calibrated:
            self.channels.calibrate(full)
            self._last_t = t
            return FrameResult(t, self.calibrated, (), (), np.zeros(k), np.zeros(k, dtype=bool))
        dt = 0.1 if self._last_t is None else min(max(t - self._last_t, 1e-3), 1.0)
        self._last_t = t
        p = self.params
        sigma_full = self.channels.sigma()
        delta_full = self.channels.delta(full, valid_full, sigma_full, self._touched, self._reach)
        index = self.frame_index
        delta, sigma, valid = delta_full[index], sigma_full[index], valid_full[index]
        threshold = np.where(self.active, p.off_sigma, p.on_sigma) * sigma
        self.active = valid & (delta > threshold)
        touches = self._touches(delta, sigma) if self.active.any() else []
        self.previous_delta = delta
        tracked, events = self.tracker.track(touches, t)
        held = None
        self._touched.fill(False)
        self.near_touch = (self.holds[[touch.peak_cell for touch in tracked]].any(axis=0) if tracked
                           else np.zeros_like(self.active))
        if tracked:
            held = self._touched
            held[index] = self.near_touch
        self._touched[index[self.active]] = True
        self._reach = self._tail_reach(tracked)
        self.channels.update(delta_full, valid_full, sigma_full, held, t, dt)
        return FrameResult(t, True, tuple(tracked), tuple(events), delta, self.active.copy())

    def _tail_reach(self, touches: list[Touch]) -> np.ndarray:
        """(NUM_TX * NUM_RX,) counts the touches may add to each channel under their heaviest
        plausible coupling tail (:meth:`.CouplingFit.tail_envelope`, each touch's peak delta over its
        gain): how little a channel can tell of its lines' offsets."""
        reach = np.zeros(NUM_TX * NUM_RX)
        for touch in touches:
            offsets = self.map.cell_points - touch.point
            amplitude = touch.intensity / self.cell_gain[touch.peak_cell]
            tail = self.fit.tail_envelope(np.einsum("ij,ij->i", offsets, offsets))
            reach[self.frame_index] += self.cell_gain * amplitude * tail
        return reach

    def sigma(self) -> np.ndarray:
        """(K,) noise sigma per cell (counts) the thresholds use, floored."""
        return self.channels.sigma()[self.frame_index]

    # ---- contact areas and touch points

    def _peaks(self, delta: np.ndarray, sigma: np.ndarray) -> np.ndarray:
        """Active cells that are local maxima among the active cells and not explained by a stronger
        peak's coupling tail, both on gain-normalised deltas ``delta / g`` (a crossing without a pad
        reads less for the same finger: two padded crossings on either side of a finger over pad-less
        ones are not two touches). A cell below the on threshold is no peak and hides none: its noise
        over a small gain would otherwise outweigh the one crossing a finger in a sparse region turns
        on, and the touch would drop for a frame and come back as a second touch-down.

        A candidate must exceed twice the tail bound (:class:`.CouplingFit`) of every stronger peak.
        Away from the last frame's touches (``near_touch``, the hold radius) it must also be a finger
        rather than a board spike, which raises one cell for one frame: a finger couples to several
        crossings and lasts many frames. So it needs ``SUPPORT_READINGS`` supporting readings above
        ``SUPPORT_SIGMA`` noise sigmas besides its own in this frame: each other crossing within the
        finger's reach (``SUPPORT_WIDTHS`` coupling widths, the width as learned: a strong finger on
        a sparse layout lights crossings three pitches away) counts once, the candidate in the
        previous frame once, twice above the on threshold (a finger the board already saw there),
        but not at all if it has since lost more than half of its delta (a spike falling back,
        which the off threshold's hysteresis may keep on). A finger that only one crossing sees
        thus touches down a frame later. A real board's noise has heavier tails than a Gaussian
        (row and column noise, channel drift): a cell reads above 3 sigmas several times as often
        as the Gaussian's 0.13 % of frames, so two of a spike's ~10 neighbours above 3 sigmas, or
        a 4-sigma reading at the spiked cell the frame before, are not rare enough to count.
        """
        before = np.where(delta >= 0.5 * self.previous_delta, self.previous_delta / sigma, 0.0)
        strong = delta > SUPPORT_SIGMA * sigma
        within_reach = self.cell_distance[strong] <= SUPPORT_WIDTHS * self.fit.coupling_sigma  # rows: strong cells
        readings = within_reach.sum(axis=0) - strong + (before > SUPPORT_SIGMA) + (before > self.params.on_sigma)
        supported = self.near_touch | (readings >= SUPPORT_READINGS)
        delta = delta / self.cell_gain
        on = np.where(self.active, delta, -np.inf)
        candidates = np.flatnonzero(self.active & supported & (delta >= on[self.peak_neighbours].max(axis=0)))
        candidates = candidates[np.argsort(-delta[candidates])]
        kept: list[tuple[int, float]] = []  # (cell, normalised delta), strongest first
        for c, value in zip(candidates.tolist(), delta[candidates].tolist()):
            bounds = self.fit.tail_bound[c].tolist()  # plain floats for the loop
            if all(value > 2.0 * peak * bounds[k] for k, peak in kept):
                kept.append((c, value))
        return np.array([c for c, _ in kept], dtype=np.int64)

    def _touches(self, delta: np.ndarray, sigma: np.ndarray) -> list[Touch]:
        peaks = self._peaks(delta, sigma)
        if len(peaks) == 0:
            return []
        # [cell, point, face, bary, area, centroid]; point/face/bary set by the refinement or below
        found = self.contacts.parts(peaks, delta, self.params.off_sigma * median(sigma))
        if self.params.refine and found:
            self.fit.refine_all(found, delta, sigma)
        for entry in found:
            if entry[1] is None:
                entry[1:4] = self._coarse_point(entry[5], entry[0])
        return [Touch(-1, point, face, bary, self.projector.face_normals[face], float(delta[cell]), area, cell)
                for cell, point, face, bary, area, _ in found]

    def _coarse_point(self, centroid: np.ndarray, cell: int) -> tuple[np.ndarray, int, np.ndarray]:
        """The contact centroid projected on the surface on the side facing like the peak cell."""
        facing = self.map.cell_normals[cell]
        points, faces, barys = self.projector.project(centroid, facing)
        face = int(faces[0])
        if self.projector.face_normals[face] @ facing <= 0.0:
            # The centroid of a contact wrapping a thin part projected onto the far side.
            return self.map.cell_points[cell], int(self.map.cell_faces[cell]), self.map.cell_bary[cell]
        return points[0], face, barys[0]
