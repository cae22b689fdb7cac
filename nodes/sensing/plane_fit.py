"""Levenberg-Marquardt of the coupling model with the finger kept on the surface (one fit of
:meth:`.coupling_fit.CouplingFit.refine`).

Within one tangent plane (rows ``t1, t2`` of the face frame) the finger is ``p_r + u0 t1 + u1 t2``,
so ``|x_i - p|^2 = r2_i - 2 u.y_i + |u|^2`` with ``y_i = frame (x_i - p_r)`` (mm) and
``r2_i = |x_i - p_r|^2``, computed once per plane; ``d model_i / d u = 2 h_i exp(a) K'(q_i) (u - y_i)``
with ``K'`` the profile's slope in squared distance; the 3 x 3 system is solved by cofactors. Steps ``(u, a)`` stay in
the tangent plane of the current face; then ``p`` is projected back onto the surface on the side
facing the same way and the fit repeats in the new tangent plane (``SURFACE_ROUNDS``). A step that
stays inside the face needs no projection: the point is on the surface and the fit ends there.
The per-plane work runs compiled (numba): a fit runs thousands of times a second on a few dozen
crossings, where numpy's per-call overhead would be most of the time.

Priors keep directions the crossings do not resolve bounded (on a sparse layout three crossings can
be nearly collinear, or only two see the finger): ``u`` (offset from the start) ~ N(0, pitch^2), so
an unresolved direction stays at the start; ``a`` ~ N(a0, sigma_a^2) once the amplitude is learned,
so the peak crossing's delta tells how far the finger is from it.
"""
from __future__ import annotations

import math

import numba
import numpy as np

from ..geometry.surface import SurfaceProjector
from .coupling_profile import CouplingProfile

FIT_ITERATIONS = 8  # Levenberg-Marquardt iterations per tangent plane (it stops earlier once steps are < 0.05 mm)
SURFACE_ROUNDS = 2  # tangent planes the fit re-linearises in (it stops once the projection moves < 0.05 mm)


class TangentPlaneFit:
    """The fit of one touch to the crossings at ``x`` (k, 3) (mm) with deltas ``z`` and gains ``h``,
    both in units of each crossing's noise sigma (so the residuals are weighted already)."""

    def __init__(self, projector: SurfaceProjector, profile: CouplingProfile, x: np.ndarray, z: np.ndarray,
                 h: np.ndarray, pitch: float, amplitude_prior: tuple[float, float] | None):
        self.projector = projector
        self.profile = (profile.inner_squared, profile.log_slopes, profile.log_intercepts)
        self.x, self.z, self.h = np.ascontiguousarray(x), np.ascontiguousarray(z), np.ascontiguousarray(h)
        # prior_u, prior_a, prior_mean_a, max step (mm)
        self.priors = np.array([1.0 / pitch**2, 0.0, 0.0, 0.5 * pitch])
        if amplitude_prior is not None:
            mean_a, sigma_a = amplitude_prior
            self.priors[1:3] = 1.0 / sigma_a**2, mean_a
        self.columns = np.empty((len(z), 3))  # per plane: r2, -2 y0, -2 y1

    def run(self, point: np.ndarray, face: int, log_amplitude: float, anchor: np.ndarray | None = None):
        """Fit from the surface point ``point`` on ``face`` and ``log_amplitude``, the offset prior
        centred at ``anchor`` (default ``point``); returns (cost, point, face, bary, log amplitude, data
        information as its upper triangle ``(i00, i01, i02, i11, i12, i22)`` in ``(u0, u1, a)``)."""
        start = point if anchor is None else anchor
        for _ in range(SURFACE_ROUNDS):
            frame = self.projector.face_frames[face]
            offsets = _set_plane(self.columns, self.x, point, start, frame)
            u0, u1, log_amplitude, cost, information = _levenberg_marquardt(
                self.columns, self.z, self.h, *self.profile, self.priors, offsets, log_amplitude, FIT_ITERATIONS)
            point = point + u0 * frame[0] + u1 * frame[1]
            bary = self.projector.barycentrics_in_face(point, face)
            if bary is not None:
                return cost, point, face, bary, log_amplitude, information
            moved, faces, barys = self.projector.project(point, self.projector.face_normals[face])
            shift = math.dist(moved[0].tolist(), point.tolist())
            point, face, bary = moved[0], int(faces[0]), barys[0]
            if shift < 0.05:
                break
        offsets = _set_plane(self.columns, self.x, point, start, self.projector.face_frames[face])
        _, _, _, cost, information = _levenberg_marquardt(self.columns, self.z, self.h, *self.profile, self.priors,
                                                          offsets, log_amplitude, 0)
        return cost, point, face, bary, log_amplitude, information


def compile_kernels() -> None:
    """Compile the kernels (or load them from numba's cache) on a one-crossing fit, so that the
    first touch does not wait for it (~2.5 s once per install, ~0.3 s to load)."""
    columns, one = np.zeros((1, 3)), np.ones(1)
    offsets = _set_plane(columns, np.ones((1, 3)), np.zeros(3), np.zeros(3), np.eye(3))
    _levenberg_marquardt(columns, one, one, np.ones(1), np.zeros(2), np.zeros(2), np.ones(4), offsets, 0.0, 1)


@numba.njit(cache=True)
def _set_plane(columns, x, point, start, frame):
    """Fill ``columns`` (k, 3) for the tangent plane at ``point`` with frame rows (t1, t2, n);
    returns the offset (o0, o1) (mm) of ``point`` from ``start`` in it, which the prior sees."""
    for i in range(len(x)):
        q0, q1, q2 = x[i, 0] - point[0], x[i, 1] - point[1], x[i, 2] - point[2]
        columns[i, 0] = q0 * q0 + q1 * q1 + q2 * q2
        columns[i, 1] = -2.0 * (q0 * frame[0, 0] + q1 * frame[0, 1] + q2 * frame[0, 2])
        columns[i, 2] = -2.0 * (q0 * frame[1, 0] + q1 * frame[1, 1] + q2 * frame[1, 2])
    s0, s1, s2 = point[0] - start[0], point[1] - start[1], point[2] - start[2]
    return np.array([s0 * frame[0, 0] + s1 * frame[0, 1] + s2 * frame[0, 2],
                     s0 * frame[1, 0] + s1 * frame[1, 1] + s2 * frame[1, 2]])


@numba.njit(cache=True)
def _evaluate(columns, z, h, inner_squared, log_slopes, log_intercepts, priors, offsets, u0, u1, la,
              model, residual, slope_scaled):
    """Cost at the in-plane offset (u0, u1) (mm) and log-amplitude ``la``; fills the model, the
    residual and d model / d q (noise sigmas) per crossing."""
    amplitude = math.exp(la)
    cost = 0.0
    for i in range(len(z)):
        q = columns[i, 0] + columns[i, 1] * u0 + columns[i, 2] * u1 + (u0 * u0 + u1 * u1)
        segment = np.searchsorted(inner_squared, q, side="right")
        slope = log_slopes[segment]
        k = math.exp(log_intercepts[segment] + slope * q)
        scale = h[i] * amplitude
        model[i] = scale * k
        residual[i] = z[i] - model[i]
        slope_scaled[i] = scale * slope * k
        cost += residual[i] * residual[i]
    o0, o1 = offsets[0] + u0, offsets[1] + u1
    return cost + priors[0] * (o0 * o0 + o1 * o1) + priors[1] * (la - priors[2]) ** 2


@numba.njit(cache=True)
def _normal_equations(columns, model, residual, slope_scaled, u0, u1):
    """Upper triangle of J^T J and J^T r (rows J: d model / d (u0, u1, a)) at the offset (u0, u1)."""
    h00 = h01 = h02 = h11 = h12 = h22 = b0 = b1 = b2 = 0.0
    for i in range(len(model)):
        j0 = slope_scaled[i] * (columns[i, 1] + 2.0 * u0)
        j1 = slope_scaled[i] * (columns[i, 2] + 2.0 * u1)
        j2, r = model[i], residual[i]
        h00 += j0 * j0
        h01 += j0 * j1
        h02 += j0 * j2
        h11 += j1 * j1
        h12 += j1 * j2
        h22 += j2 * j2
        b0 += j0 * r
        b1 += j1 * r
        b2 += j2 * r
    return (h00, h01, h02, h11, h12, h22), (b0, b1, b2)


@numba.njit(cache=True)
def _levenberg_marquardt(columns, z, h, inner_squared, log_slopes, log_intercepts, priors, offsets, log_amplitude,
                         iterations):
    """Damped Gauss-Newton steps (at most ``iterations``) in the current plane from u = 0; returns
    (u0, u1, log amplitude, cost, data information) at the end."""
    prior_u, prior_a, prior_mean_a, max_step = priors[0], priors[1], priors[2], priors[3]
    o0, o1 = offsets[0], offsets[1]
    n = len(z)
    model, residual, slope_scaled = np.empty(n), np.empty(n), np.empty(n)
    trial_model, trial_residual, trial_slope = np.empty(n), np.empty(n), np.empty(n)
    u0 = u1 = 0.0
    cost = _evaluate(columns, z, h, inner_squared, log_slopes, log_intercepts, priors, offsets, u0, u1,
                     log_amplitude, model, residual, slope_scaled)
    damping = 1e-3
    for _ in range(iterations):
        (h00, h01, h02, h11, h12, h22), (b0, b1, b2) = _normal_equations(columns, model, residual, slope_scaled,
                                                                          u0, u1)
        b0 -= prior_u * (o0 + u0)
        b1 -= prior_u * (o1 + u1)
        b2 -= prior_a * (log_amplitude - prior_mean_a)
        scale = 1.0 + damping
        h00, h11, h22 = (h00 + prior_u) * scale, (h11 + prior_u) * scale, (h22 + prior_a) * scale
        # Symmetric 3 x 3 solve by cofactors.
        c00, c01, c02 = h11 * h22 - h12 * h12, h02 * h12 - h01 * h22, h01 * h12 - h02 * h11
        determinant = h00 * c00 + h01 * c01 + h02 * c02
        if determinant == 0.0 or not math.isfinite(determinant):
            break
        c11, c12, c22 = h00 * h22 - h02 * h02, h01 * h02 - h00 * h12, h00 * h11 - h01 * h01
        s0 = (c00 * b0 + c01 * b1 + c02 * b2) / determinant
        s1 = (c01 * b0 + c11 * b1 + c12 * b2) / determinant
        s2 = (c02 * b0 + c12 * b1 + c22 * b2) / determinant
        length = math.hypot(s0, s1)
        if length > max_step:
            shrink = max_step / length
            s0, s1, s2 = s0 * shrink, s1 * shrink, s2 * shrink
        trial = _evaluate(columns, z, h, inner_squared, log_slopes, log_intercepts, priors, offsets, u0 + s0,
                          u1 + s1, log_amplitude + s2, trial_model, trial_residual, trial_slope)
        if trial <= cost:
            u0, u1, log_amplitude, cost = u0 + s0, u1 + s1, log_amplitude + s2, trial
            model, trial_model = trial_model, model
            residual, trial_residual = trial_residual, residual
            slope_scaled, trial_slope = trial_slope, slope_scaled
            damping = max(damping / 3.0, 1e-6)
            if length < 0.05:
                break
        else:
            damping *= 4.0
    information, _ = _normal_equations(columns, model, residual, slope_scaled, u0, u1)
    return u0, u1, log_amplitude, cost, information
