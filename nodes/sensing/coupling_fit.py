"""Sub-cell touch refinement: the coupling model ``delta_i = g_i A K(|p - x_i|)`` fitted to the
crossings around a touch peak by maximum likelihood, with the finger kept on the surface, and the
coupling width, shape and amplitude learned from touches (see :mod:`.processing`, step 4).

``g_i`` is 1 with a pad and ``no_pad_gain`` without; ``K`` the radial coupling profile
(:mod:`.coupling_profile`). Units: mm, counts, deltas in noise sigmas inside the fit.
"""
from __future__ import annotations

import collections
import math
from typing import TYPE_CHECKING, Any

import numpy as np

from ..data.board import default_coupling_width_mm
from ..data.sensing_map import SensingMap
from ..geometry.surface import SurfaceProjector
from .baseline import median
from .coupling_profile import CouplingProfile, ProfileLearner
from .gain_learning import MIN_SNR, NEAR_PROFILE, GainLearner
from .plane_fit import TangentPlaneFit, compile_kernels

if TYPE_CHECKING:
    from .processing import ProcessingParams

NORMAL_RIDGE = 0.05  # ridge on the width fit's normal component, relative to the in-plane information
COUPLING_MIN_ESTIMATES = 30  # width estimates whose median becomes the coupling width
COUPLING_RUNNING_FROM = 3  # from this many estimates on, their running median is the width until then
COUPLING_MIN_CELLS = 7  # crossings with signal a touch needs to give a width estimate
AMPLITUDE_WINDOW = 300  # well-posed fits whose amplitudes make up the amplitude prior
AMPLITUDE_MIN_ESTIMATES = 20  # well-posed fits needed before the amplitude prior applies
SPLIT_SIGMA = 6.0  # noise sigmas a second finger's peak reads above what the first finger's tail can explain
JOINT_AMPLITUDE_FACTOR = 2.0  # a finger fitted between two peaks may read up to this much above the first fit or prior
JOINT_AMPLITUDE_SIGMAS = 3.0  # ... or this many of the prior's spreads, if more
REACH_MARGIN_MM = 0.01  # slack of the joint refit's distance test against rounding (it only skips hopeless fits)
AMPLITUDE_WELL_POSED_MM = 0.5  # tangential 1-sigma (from the data alone) of a fit whose amplitude is learned
RING_STARTS_MAX_CROSSINGS = 3  # a first fit seen by at most this many crossings also starts around its peak ...
RING_STARTS = 6  # ... from this many points, evenly around the circle the peak's delta and the amplitude prior imply
RING_MIN_PITCH_SHARE = 0.25  # ... unless that circle is smaller than this share of the pitch


def amplitude_prior(log_amplitudes: np.ndarray) -> tuple[float, float]:
    """``(centre, spread)`` of a finger's log-amplitude (log counts at a padded crossing) from estimates of
    it: their median and 1.4826 MAD, at least 0.05."""
    centre = float(np.median(log_amplitudes))
    return centre, max(1.4826 * float(np.median(np.abs(log_amplitudes - centre))), 0.05)


class CouplingFit:
    """The coupling model of one sensing map and what it learned so far (width, shape, amplitude)."""

    def __init__(self, sensing_map: SensingMap, params: ProcessingParams, projector: SurfaceProjector,
                 cell_gain: np.ndarray, cell_distance: np.ndarray, measured_gains: bool = False):
        self.map, self.params, self.projector = sensing_map, params, projector
        self.cell_gain, self.cell_distance = cell_gain, cell_distance
        self.pitch = sensing_map.pitch_mm()
        self.coupling_sigma = params.coupling_sigma_mm or default_coupling_width_mm(params.finger_radius_mm, self.pitch)
        self.initial_coupling_sigma = self.coupling_sigma
        self._width_estimates: list[float] = []
        self._amplitude_estimates: collections.deque[float] = collections.deque(maxlen=AMPLITUDE_WINDOW)
        self.amplitude_prior: tuple[float, float] | None = params.amplitude_prior  # (log counts, sigma) of a padded crossing
        self._amplitude_count = 0  # well-posed fits seen
        shape = (CouplingProfile.gaussian(1.0) if params.coupling_tail is None
                 else CouplingProfile.student(1.0, params.coupling_tail))
        self.coupling = ProfileLearner(shape)  # the shape, in units of the width
        self.gains = (GainLearner(cell_gain, sensing_map.cell_pad, measured=measured_gains)
                      if params.learn_gains else None)
        self._use_profile()
        compile_kernels()  # now, not at the first touch

    def _use_profile(self) -> None:
        """Fit with the learned shape stretched to the learned width from now on; the peak test's
        tail bounds follow: a finger at most ``a = 0.6 pitch`` from a peak crossing (inside the sensed
        region) gives a crossing ``D`` from that peak at most ``K(max(D - a, 0)) / K(a)`` times the
        peak's delta."""
        profile = self.profile = self.coupling.profile.scaled(self.coupling_sigma)
        offset = 0.6 * self.pitch
        reach = profile.at_distance(np.maximum(self.cell_distance - offset, 0.0))
        self.tail_bound = reach / profile.at_distance(offset)

    def refine_all(self, found: list[list[Any]], delta: np.ndarray, sigma: np.ndarray) -> None:
        """Refine every touch in place (entries ``[cell, point, face, bary, area, centroid]`` of
        ``found``, strongest peak first; entries that are one finger are merged out). Each fit starts
        at its peak crossing (on the touched side, within a pitch of the finger); with several
        touches the first pass fits each one to its own cells (nearest to its peak), peaks whose fits
        land within ``2 finger_radius`` of a stronger one's, or whose delta the strongest finger's
        tail can explain (:meth:`_separate_fingers`), are dropped (their area added to it), and
        a second pass fits each remaining touch to all deltas minus the other touches' fitted
        coupling, starting from its first fit's point and amplitude. The coupling profile learns from
        single touches and from second-pass fits (a first pass beside another touch carries that
        touch's tail)."""
        single = len(found) == 1
        fits: list[tuple[np.ndarray, float] | None] = []  # (point, log amplitude) of each first-pass fit
        peaks = np.array([entry[0] for entry in found])
        # First pass: each touch sees only the cells nearer its own peak than any other peak.
        nearest_peak = np.argmin(self.cell_distance[:, peaks], axis=1)
        for j, entry in enumerate(found):
            cell = entry[0]
            own_cells = delta if single else np.where(nearest_peak == j, delta, np.nan)
            refined = self.refine(self.map.cell_points[cell], int(self.map.cell_faces[cell]), own_cells, sigma,
                                  learn_profile=single)
            fits.append(None if refined is None else (refined[0], min(refined[3], 30.0)))
            if refined is not None:
                entry[1:4] = refined[:3]
        if single:
            return
        fits = self._merge_same_finger(found, fits)
        start = (self.map.cell_points[found[0][0]], int(self.map.cell_faces[found[0][0]]))
        if len(found) > 1:
            separate, between = self._separate_fingers(found, fits, delta, sigma)
            found[0][4] += sum(entry[4] for entry, own in zip(found, separate) if not own)
            found[:] = [entry for entry, own in zip(found, separate) if own]
            fits = [fit for fit, own in zip(fits, separate) if own]
            start = between or start
        if len(found) == 1:  # merged into one finger after all: fit it to every delta
            entry = found[0]
            refined = self.refine(*start, delta, sigma, learn_profile=True)
            if refined is not None:
                entry[1:4] = refined[:3]
            return
        if sum(fit is not None for fit in fits) >= 2:
            self._refit_beside_others(found, fits, delta, sigma)

    def _merge_same_finger(self, found: list[list[Any]], fits: list) -> list:
        """Drop the entries whose first fits land within a finger's width of a stronger one's (their
        area goes to it); returns the fits of the entries kept."""
        merge_mm = 2.0 * self.params.finger_radius_mm
        kept: list[int] = []  # found is strongest peak first
        for j, fit in enumerate(fits):
            same = None if fit is None else next((k for k in kept if fits[k] is not None
                                                  and math.dist(fits[k][0].tolist(), fit[0].tolist()) < merge_mm), None)
            if same is None:
                kept.append(j)
            else:
                found[same][4] += found[j][4]
        if len(kept) < len(found):
            found[:] = [found[j] for j in kept]
            fits = [fits[j] for j in kept]
        return fits

    def _separate_fingers(self, found: list[list[Any]], fits: list, delta: np.ndarray,
                          sigma: np.ndarray) -> tuple[np.ndarray, tuple[np.ndarray, int] | None]:
        """Which entries are fingers of their own (the strongest always), and where the first finger
        between two peaks that explains both lies (point, face; None if none): the strongest peak's finger
        (its first fit) could not have raised a secondary peak whose delta exceeds ``SPLIT_SIGMA``
        noise sigmas plus twice that finger's coupling there under the heaviest plausible tail,
        :meth:`tail_envelope` (cell gains known to a factor 2). A finger's tail, or a finger between
        crossings of a sparse layout, raises local maxima that no bound from a learned
        Gaussian-like profile tells from a second finger; a second finger reads about the full
        amplitude at its own crossing."""
        separate, between = np.ones(len(found), dtype=bool), None
        if fits[0] is None:
            return separate, between
        point, log_amplitude = fits[0]
        peaks = np.array([entry[0] for entry in found])
        squared = np.sum((self.map.cell_points[peaks] - point) ** 2, axis=1)
        reach = self.cell_gain[peaks] * math.exp(log_amplitude) * self.tail_envelope(squared)
        separate[1:] = (delta[peaks] > 2.0 * reach + SPLIT_SIGMA * sigma[peaks])[1:]
        for k in np.flatnonzero(separate[1:]) + 1:
            beside = None if fits[k] is None else (point, fits[k][0])
            one = self._one_finger_between(peaks[0], peaks[k], log_amplitude, delta, sigma, beside)
            separate[k] = one is None
            between = between or one
        return separate, between

    def _one_finger_between(self, first: int, second: int, log_amplitude: float, delta: np.ndarray, sigma: np.ndarray,
                            beside: tuple[np.ndarray, np.ndarray] | None) -> tuple[np.ndarray, int] | None:
        """Where (point, face) one finger of plausible amplitude between two peak crossings explains
        both peaks (:meth:`_explains`); None if nowhere. A finger in a gap between crossings far apart
        raises a peak on either side, and the first fits, each seeing only its own peak's crossings,
        put a weak finger beside each peak (``beside``: their points). The finger is fitted to every
        delta from between the peaks; as that fit can slide to one peak's side, a finger held at
        points between the first fits, of any plausible amplitude, counts too. Plausible: at most
        ``JOINT_AMPLITUDE_FACTOR`` times the strongest peak's first fit (``log_amplitude``; the factor
        squared until the width is learned, as a too-narrow initial width makes a finger between
        crossings need more amplitude), or the amplitude prior plus the larger of
        ``JOINT_AMPLITUDE_SIGMAS`` spreads and that factor, if more. Two fingers on crossings far
        apart would need a finger between them many times stronger than either; peaks farther apart
        than such a finger's coupling can reach to explain both are two without a fit."""
        cells, gains = self.map.cell_points, self.cell_gain
        learned = len(self._width_estimates) >= COUPLING_MIN_ESTIMATES or not self.params.adapt_coupling
        limit = log_amplitude + math.log(JOINT_AMPLITUDE_FACTOR) * (1.0 if learned else 2.0)
        if self.amplitude_prior is not None:
            centre, spread = self.amplitude_prior
            limit = max(limit, centre + max(JOINT_AMPLITUDE_SIGMAS * spread, math.log(JOINT_AMPLITUDE_FACTOR)))
        # Before the fit: a finger of amplitude at most exp(limit) that explains a peak reads at least
        # (delta - tolerance) / (2 g exp(limit)) of it there, so it lies within the profile's reach of
        # that fraction from the peak; peaks farther apart than the two reaches are two fingers.
        reaches = [self.profile.farthest_reading((delta[peak] - SPLIT_SIGMA * sigma[peak])
                                                 / (2.0 * gains[peak] * math.exp(limit))) for peak in (first, second)]
        if reaches[0] + reaches[1] + REACH_MARGIN_MM < self.cell_distance[first, second]:
            return None
        peaks = np.array([first, second])
        weights = delta[peaks] / gains[peaks]
        points, faces, _ = self.projector.project(weights @ cells[peaks] / weights.sum(), self.map.cell_normals[first])
        joint = self.refine(points[0], int(faces[0]), delta, sigma, update=False)
        if joint is not None and self._explains(joint[0], joint[3], min(joint[3], limit), peaks, delta, sigma):
            return joint[0], joint[1]
        if beside is None:
            return None
        held = beside[0] + np.array([[0.25], [0.5], [0.75]]) * (beside[1] - beside[0])
        points, faces, _ = self.projector.project(held, self.map.cell_normals[first])
        return next(((point, int(face)) for point, face in zip(points, faces)
                     if self._explains(point, -math.inf, limit, peaks, delta, sigma)), None)

    def _explains(self, point: np.ndarray, low: float, high: float, peaks: np.ndarray, delta: np.ndarray,
                  sigma: np.ndarray) -> bool:
        """Whether a finger at ``point`` of some log-amplitude in [``low``, ``high``] reads at least half
        of each of the ``peaks``' deltas, less ``SPLIT_SIGMA`` noise sigmas, and lights no crossing near
        it more than twice its delta (0 if negative: noise below the baseline is no darker than none)
        plus ``SPLIT_SIGMA`` noise sigmas (two fingers with dark crossings between them are two)."""
        squared = np.sum((self.map.cell_points - point) ** 2, axis=1)
        near = (squared <= (3.0 * self.coupling_sigma + self.pitch) ** 2) & np.isfinite(delta)
        near[peaks] = True
        shape = self.cell_gain[near] * self.profile.at_squared(squared[near])[0]  # reading per unit amplitude
        tolerance = SPLIT_SIGMA * sigma[near]
        is_peak = np.isin(np.flatnonzero(near), peaks)
        with np.errstate(divide="ignore", invalid="ignore"):
            least = np.max((delta[near][is_peak] - tolerance[is_peak]) / (2.0 * shape[is_peak]))
            most = np.min((2.0 * np.maximum(delta[near], 0.0) + tolerance) / shape)
        return bool(max(least, math.exp(low)) <= min(most, math.exp(high)))

    def tail_envelope(self, squared: np.ndarray) -> np.ndarray:
        """The larger of the coupling profile and ``(1 + d^2 / h^2)^(-3/2)`` at squared distances
        (mm^2): the field of a point charge at height ``h`` over the crossing's plane, with ``h``
        such that it has the profile's half-maximum distance. It falls as a power law: a real
        finger's coupling reaches farther than a Gaussian's, and a profile learned from nearby
        crossings does not know its tail."""
        height2 = self.profile.half_maximum_mm() ** 2 / (2.0 ** (2.0 / 3.0) - 1.0)
        return np.maximum(self.profile.at_squared(squared)[0], (1.0 + squared / height2) ** -1.5)

    def _refit_beside_others(self, found: list[list[Any]], fits: list, delta: np.ndarray, sigma: np.ndarray) -> None:
        """Second pass: each touch refitted to the deltas minus the other touches' fitted coupling."""
        cells = self.map.cell_points
        modelled = [np.zeros(len(cells)) if fit is None else
                    self.cell_gain * math.exp(fit[1]) * self.profile.at_squared(np.sum((cells - fit[0]) ** 2, axis=1))[0]
                    for fit in fits]
        total = np.sum(modelled, axis=0)
        reach2 = (3.0 * self.coupling_sigma + self.pitch) ** 2  # the crossings a refit sees (see refine)
        for entry, fit, own in zip(found, fits, modelled):
            if fit is None:
                continue
            others = total - own
            seen = np.einsum("ij,ij->i", cells - entry[1], cells - entry[1]) <= reach2
            if not np.any(others[seen] > sigma[seen]):  # the others' coupling does not reach this touch's crossings
                continue
            refined = self.refine(entry[1], entry[2], delta - others, sigma, fit[1], learn_profile=True)
            if refined is not None:
                entry[1:4] = refined[:3]

    def refine(self, point, face, values, sigma, log_amplitude=None, learn_profile=False, update=True):
        """Maximum-likelihood coupling fit around ``point`` (the peak crossing, or a first fit's point
        refitted from its log-amplitude ``log_amplitude``); returns (point, face, bary) on the surface
        and the fitted log-amplitude ``a`` (log counts), or None when no crossing near ``point``
        carries signal above 2 sigma.

        Model ``delta_i = g_i exp(a) K(|p - x_i|)`` over every crossing within ``3 s + pitch`` of the
        start (``s`` the coupling width), dark ones included (a crossing that reads nothing says the
        finger is not near it); residuals weighted by ``1 / sigma_i^2`` (the deltas' noise is
        additive, so this is the likelihood); the surface-constrained fit is :class:`.TangentPlaneFit`.

        A first fit (no ``log_amplitude``) starts ``a`` at the log of the largest gain-normalised
        delta, or at the amplitude prior's mean if higher. On thin parts (ears) and tips the strongest
        crossing can sit on the far side, so a first fit also starts from the two strongest crossings
        facing away (normals > 60 degrees apart, at least half the strongest gain-normalised delta),
        and, when at most :data:`RING_STARTS_MAX_CROSSINGS` crossings carry signal and the amplitude
        prior is known, from points around the peak (:meth:`_ring_starts`; their fits' prior on the
        offset stays centred at the peak, as the first start's), and keeps the lowest cost; a refit
        starts from its first fit only. A well-posed fit with
        ``learn_profile`` gives the coupling profile its (squared distance, delta / (g exp(a)),
        weight) pairs (:class:`~retrotouch.nodes.sensing.coupling_profile.ProfileLearner`); without
        ``update`` the fit changes nothing it has learned.
        """
        cells = self.map.cell_points
        offsets = cells - point
        distance2 = np.einsum("ij,ij->i", offsets, offsets)
        near = np.flatnonzero((distance2 <= (3.0 * self.coupling_sigma + self.pitch) ** 2) & np.isfinite(values))
        d, g, x, noise = values[near], self.cell_gain[near], cells[near], sigma[near]
        strong = d > 2.0 * noise
        if not strong.any():
            return None
        width_learned = len(self._width_estimates) >= COUPLING_MIN_ESTIMATES
        if update and self.params.adapt_coupling and not width_learned:
            # Width estimates from touches many crossings see (log-linear form), over every strong
            # crossing the fit sees: a window in units of a too-narrow initial width would keep out
            # the crossings that show it is too narrow, most where crossings are sparse or clustered.
            if np.count_nonzero(strong) >= COUPLING_MIN_CELLS:
                self._learn_coupling(offsets[near[strong]], self.projector.face_frames[face], d[strong] / g[strong])
        starts = [(point, face)]
        first_ring = math.inf  # index of the first start on the ring around the peak (prior anchored at the peak)
        if log_amplitude is None:
            normalised = d / g
            facing = self.projector.face_normals[face]
            away = np.flatnonzero(strong & (self.map.cell_normals[near] @ facing < 0.5)
                                  & (normalised >= 0.5 * normalised[strong].max()))
            if len(away):
                for k in away[np.argsort(-normalised[away])][:2].tolist():
                    starts.append((x[k], int(self.map.cell_faces[near[k]])))
            log_amplitude = math.log(normalised[strong].max())
            if self.amplitude_prior is not None:
                log_amplitude = max(log_amplitude, self.amplitude_prior[0])
                if np.count_nonzero(strong) <= RING_STARTS_MAX_CROSSINGS:
                    first_ring = len(starts)
                    starts += self._ring_starts(point, face, float(normalised[strong].max()))
        z, h = d / noise, g / noise  # in noise sigmas
        plane_fit = TangentPlaneFit(self.projector, self.profile, x, z, h, self.pitch, self.amplitude_prior)
        fits = [plane_fit.run(p, f, log_amplitude, anchor=point if k >= first_ring else None)
                for k, (p, f) in enumerate(starts)]
        _, point, face, bary, log_amplitude, information = min(fits, key=lambda fit: fit[0])
        if not (update and self._learn_amplitude(log_amplitude, information) and learn_profile):
            return point, face, bary, log_amplitude
        if self.gains is not None:
            self._learn_gains(near, x - point, log_amplitude, d, noise)
        if width_learned:
            scale = h * math.exp(log_amplitude)
            offsets = x - point
            squared = np.einsum("ij,ij->i", offsets, offsets) / self.coupling_sigma**2  # in widths
            if self.coupling.add(squared, z / scale, scale * scale):
                self._use_profile()
        return point, face, bary, log_amplitude

    def _ring_starts(self, point: np.ndarray, face: int, peak_normalised: float) -> list[tuple[np.ndarray, int]]:
        """Surface points around the peak crossing at ``point`` where a finger of the prior amplitude
        would give its gain-normalised delta ``peak_normalised``: :data:`RING_STARTS` directions in the
        peak face's tangent plane, projected onto the side facing the same way. Few crossings leave
        the finger's side unresolved (two crossings: two mirror places), and a fit from the peak
        alone slides to the nearer local minimum."""
        radius = self.profile.farthest_reading(peak_normalised / math.exp(self.amplitude_prior[0]))
        if not math.isfinite(radius) or radius < RING_MIN_PITCH_SHARE * self.pitch:
            return []
        frame = self.projector.face_frames[face]
        turn = 2.0 * math.pi * np.arange(RING_STARTS) / RING_STARTS
        around = point + radius * (np.cos(turn)[:, None] * frame[0] + np.sin(turn)[:, None] * frame[1])
        moved, faces, _ = self.projector.project(around, frame[2])
        return [(p, int(f)) for p, f in zip(moved, faces)]

    def _learn_gains(self, cells: np.ndarray, offsets: np.ndarray, log_amplitude: float, values: np.ndarray,
                     noise: np.ndarray) -> None:
        """Give the gain learner (:mod:`.gain_learning`) a well-posed single touch's crossings near the
        fitted finger (``offsets`` from it, mm) that read above ``MIN_SNR`` sigmas, and use its gains
        (in place: the peak test shares the array) every 10th touch."""
        profile = self.profile.at_squared(np.einsum("ij,ij->i", offsets, offsets))[0]
        use = (profile >= NEAR_PROFILE) & (values > MIN_SNR * noise)
        if not use.any():
            return
        model = math.exp(log_amplitude) * profile[use]
        self.gains.add(cells[use], np.log(values[use] / model), (values[use] / noise[use]) ** 2)
        if self.gains.touches % 10 == 0:
            self.cell_gain[:] = self.gains.gains()

    def _learn_amplitude(self, log_amplitude: float, information: tuple[float, ...]) -> bool:
        """Keep the log-amplitude of fits whose tangential position the data alone pin within
        ``AMPLITUDE_WELL_POSED_MM`` (1 sigma); from ``AMPLITUDE_MIN_ESTIMATES`` on, their median and
        spread (:func:`amplitude_prior`), updated every 10th estimate, are the amplitude prior of later
        fits (replacing a calibration's). Returns whether the fit was well posed."""
        # Tangential 2 x 2 block of the inverse by cofactors, its largest eigenvalue in closed form.
        i00, i01, i02, i11, i12, i22 = information  # upper triangle, in (u0, u1, log amplitude)
        c00, c01, c11 = i11 * i22 - i12 * i12, i02 * i12 - i01 * i22, i00 * i22 - i02 * i02
        determinant = i00 * c00 + i01 * c01 + i02 * (i01 * i12 - i02 * i11)
        if determinant == 0.0 or not np.isfinite(determinant):
            return False
        v00, v01, v11 = c00 / determinant, c01 / determinant, c11 / determinant
        largest = 0.5 * (v00 + v11) + float(np.hypot(0.5 * (v00 - v11), v01))
        if not np.isfinite(largest) or largest > AMPLITUDE_WELL_POSED_MM**2:
            return False
        self._amplitude_estimates.append(float(log_amplitude))
        self._amplitude_count += 1
        if len(self._amplitude_estimates) >= AMPLITUDE_MIN_ESTIMATES and self._amplitude_count % 10 == 0:
            self.amplitude_prior = amplitude_prior(np.array(self._amplitude_estimates))
        return True

    def _learn_coupling(self, offsets: np.ndarray, frame: np.ndarray, normalised: np.ndarray) -> None:
        """One estimate of the coupling width from a touch's strong crossings at ``offsets`` (k, 3) (mm)
        from its peak crossing, with gain-normalised deltas ``normalised`` (counts): with ``y_i`` the
        offsets in the face ``frame`` (rows t1, t2, n), ``log d_i = c + b.y_i / s^2 - a |y_i|^2`` is linear
        in (c, b, a) and ``s = sqrt(1 / (2 a))``. From ``COUPLING_RUNNING_FROM`` estimates on their
        median, kept within half to twice the initial width, is the width (the initial width, from
        the median pitch, is too narrow where crossings are far apart, as on ring layouts: the first
        touches should not wait for it); the median of the first ``COUPLING_MIN_ESTIMATES`` becomes
        the width for good: the profile's shape is learned in units of it from then on."""
        full = np.empty((len(normalised), 5))
        full[:, 0] = 1.0
        full[:, 1:4] = offsets @ frame.T / self.coupling_sigma**2
        full[:, 4] = -np.einsum("ij,ij->i", offsets, offsets)
        weights = normalised * normalised
        normal_matrix = full.T @ (full * weights[:, None])
        normal_matrix[3, 3] += NORMAL_RIDGE * 0.5 * (normal_matrix[1, 1] + normal_matrix[2, 2])
        try:
            a = np.linalg.solve(normal_matrix, full.T @ (weights * np.log(normalised)))[4]
        except np.linalg.LinAlgError:
            return
        if a <= 0:
            return
        self._width_estimates.append(float(np.sqrt(1.0 / (2.0 * a))))
        if len(self._width_estimates) >= COUPLING_RUNNING_FROM:
            learned = median(np.array(self._width_estimates))
            self.coupling_sigma = min(max(learned, 0.5 * self.initial_coupling_sigma), 2.0 * self.initial_coupling_sigma)
            self._use_profile()
