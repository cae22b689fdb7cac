"""Levenberg-Marquardt of the coupling model with the finger kept on the surface (one fit of
:meth:`.coupling_fit.CouplingFit.refine`).

Within one tangent plane (rows ``t1, t2`` of the face frame) the finger is ``p_r + u0 t1 + u1 t2``,
so ``|x_i - p|^2 = r2_i - 2 u.y_i + |u|^2`` with ``y_i = frame (x_i - p_r)`` (mm) and
``r2_i = |x_i - p_r|^2``, computed once per plane; ``d model_i / d u = 2 h_i exp(a) K'(q_i) (u - y_i)``
with ``K'`` the profile's slope in squared distance. The 3 x 3 system is solved in plain floats
(numpy's per-call overhead dominates on arrays of a few dozen crossings). Steps ``(u, a)`` stay in
the tangent plane of the current face; then ``p`` is projected back onto the surface on the side
facing the same way and the fit repeats in the new tangent plane (``SURFACE_ROUNDS``). A step that
stays inside the face needs no projection: the point is on the surface and the fit ends there.

Priors keep directions the crossings do not resolve bounded (on a sparse layout three crossings can
be nearly collinear, or only two see the finger): ``u`` (offset from the start) ~ N(0, pitch^2), so
an unresolved direction stays at the start; ``a`` ~ N(a0, sigma_a^2) once the amplitude is learned,
so the peak crossing's delta tells how far the finger is from it.
"""
from __future__ import annotations

import math

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
        self.projector, self.profile = projector, profile
        self.x, self.z, self.h = x, z, h
        self.prior_u = 1.0 / pitch**2
        self.prior_mean_a, self.prior_a = 0.0, 0.0
        if amplitude_prior is not None:
            self.prior_mean_a, sigma_a = amplitude_prior
            self.prior_a = 1.0 / sigma_a**2
        self.max_step = 0.5 * pitch
        self.columns = np.empty((len(z), 3))  # per plane: r2, -2 y0, -2 y1
        self.offset = np.ones(3)  # (1, u0, u1): columns @ offset + |u|^2 is the squared distance
        self.rows = np.empty((4, len(z)))  # J (d model / d (u0, u1, a)) and the residual
        self.start = self.o0 = self.o1 = None

    def run(self, point: np.ndarray, face: int, log_amplitude: float, anchor: np.ndarray | None = None):
        """Fit from the surface point ``point`` on ``face`` and ``log_amplitude``, the offset prior
        centred at ``anchor`` (default ``point``); returns (cost, point, face, bary, log amplitude, data
        information as its upper triangle ``(i00, i01, i02, i11, i12, i22)`` in ``(u0, u1, a)``)."""
        self.start = point if anchor is None else anchor
        for _ in range(SURFACE_ROUNDS):
            frame = self._set_plane(point, face)
            u0, u1, log_amplitude, state = self._levenberg_marquardt(log_amplitude)
            cost, residual, model, dmodel_dq = state
            point = point + u0 * frame[0] + u1 * frame[1]
            bary = self.projector.barycentrics_in_face(point, face)
            if bary is not None:
                return cost, point, face, bary, log_amplitude, self._normal_equations(model, residual, dmodel_dq, u0, u1)[0]
            moved, faces, barys = self.projector.project(point, self.projector.face_normals[face])
            shift = math.dist(moved[0].tolist(), point.tolist())
            point, face, bary = moved[0], int(faces[0]), barys[0]
            if shift < 0.05:
                break
        self._set_plane(point, face)
        cost, residual, model, dmodel_dq = self._evaluate(0.0, 0.0, log_amplitude)
        return cost, point, face, bary, log_amplitude, self._normal_equations(model, residual, dmodel_dq, 0.0, 0.0)[0]

    def _set_plane(self, point: np.ndarray, face: int) -> np.ndarray:
        """Fill the columns for the tangent plane at ``point`` on ``face``; returns its frame rows
        (t1, t2) and keeps the offset (o0, o1) (mm) of ``point`` from the start, which the prior sees."""
        frame = self.projector.face_frames[face][:2]
        q = self.x - point
        self.columns[:, 0] = np.einsum("ij,ij->i", q, q)
        self.columns[:, 1:] = q @ (-2.0 * frame.T)
        self.o0, self.o1 = ((point - self.start) @ frame.T).tolist()
        return frame

    def _evaluate(self, u0: float, u1: float, la: float):
        """(cost, residual, model, d model / d q), all but the cost in noise sigmas, at the in-plane
        offset (u0, u1) (mm) and log-amplitude ``la`` in the current plane."""
        offset = self.offset
        offset[1], offset[2] = u0, u1
        k, slope = self.profile.at_squared(self.columns @ offset + (u0 * u0 + u1 * u1))
        scale = self.h * math.exp(la)
        model = scale * k
        residual = self.z - model
        cost = (float(residual @ residual) + self.prior_u * ((self.o0 + u0) ** 2 + (self.o1 + u1) ** 2)
                + self.prior_a * (la - self.prior_mean_a) ** 2)
        return cost, residual, model, scale * slope

    def _normal_equations(self, model, residual, dmodel_dq, u0: float, u1: float):
        """Upper triangle of J^T J and J^T r at the in-plane offset (u0, u1) (mm), from one product
        of the rows [J; r] with themselves."""
        rows, columns = self.rows, self.columns
        np.multiply(dmodel_dq, columns[:, 1] + 2.0 * u0, out=rows[0])
        np.multiply(dmodel_dq, columns[:, 2] + 2.0 * u1, out=rows[1])
        rows[2] = model
        rows[3] = residual
        (h00, h01, h02, b0), (_, h11, h12, b1), (_, _, h22, b2), _ = (rows @ rows.T).tolist()
        return (h00, h01, h02, h11, h12, h22), (b0, b1, b2)

    def _levenberg_marquardt(self, log_amplitude: float):
        """Damped Gauss-Newton steps in the current plane from u = 0; returns (u0, u1, log amplitude,
        (cost, residual, model, d model / d q) there)."""
        prior_u, prior_a, prior_mean_a, o0, o1 = self.prior_u, self.prior_a, self.prior_mean_a, self.o0, self.o1
        u0 = u1 = 0.0
        state = self._evaluate(u0, u1, log_amplitude)
        damping = 1e-3
        for _ in range(FIT_ITERATIONS):
            cost, residual, model, dmodel_dq = state
            (h00, h01, h02, h11, h12, h22), (b0, b1, b2) = self._normal_equations(model, residual, dmodel_dq, u0, u1)
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
            if length > self.max_step:
                shrink = self.max_step / length
                s0, s1, s2 = s0 * shrink, s1 * shrink, s2 * shrink
            trial = self._evaluate(u0 + s0, u1 + s1, log_amplitude + s2)
            if trial[0] <= cost:
                u0, u1, log_amplitude = u0 + s0, u1 + s1, log_amplitude + s2
                state = trial
                damping = max(damping / 3.0, 1e-6)
                if length < 0.05:
                    break
            else:
                damping *= 4.0
        return u0, u1, log_amplitude, state
