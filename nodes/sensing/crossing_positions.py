"""Where each crossing really is, from the calibration touches (``sense --calibrate``): a hand-laid
sensor's crossings sit a few mm from the layout's map, and a touch localized against the map's
points carries that error.

The operator touches every crossing where it is on the object, so each calibration touch ``t`` at
crossing ``c`` is a finger at the crossing's real point (plus an aim error), and the crossings
around it read that finger at their own real distances. All touches are fitted together (a
bundle adjustment, :func:`scipy.optimize.least_squares` with a sparse Jacobian)::

    delta_tj = exp(b_j + a_t) K(|y_j - p_t|),   y_j = x_j + T_j u_j,   p_t = y_c + T_c v_t

with ``x_j`` the map's point, ``T_j`` its tangent frame (2 columns), ``u_j`` (mm) the crossing's
displacement, ``v_t`` (mm) the aim error, ``b_j`` the crossing's log gain, ``a_t`` the touch's log
strength and ``K(d) = (1 + d^2 / (2 nu w^2))^-nu`` a radial profile whose width ``w`` (mm) and tail
``nu`` are fitted too (:func:`.coupling_profile.student_profile`: a Gaussian as ``nu`` grows;
smaller ``nu``: a heavier tail). Residuals are in units of ``sqrt(sigma_j^2 + (RELATIVE_ERROR
delta)^2)`` (noise plus the model's own error);
priors ``u ~ N(0, placement_sigma^2)``, ``v ~ N(0, aim_sigma^2)`` and ``b ~ N(log gain, 1)`` fix
what the touches leave free (a common shift of every crossing and touch, a common gain).
``placement_sigma`` is the placement's own spread (1-3 mm off the map: about 1.5 mm RMS along each
tangent direction): the touches pin only distances, so a sparse patch (two crossings within 1.5
pitches) and its touches move together at little cost, and a looser prior let one drift as a block.
Pairs are every crossing within ``reach_pitch`` pitches (on the map) of the touched one, dark ones
included. How well the touches pin each crossing is its position's posterior spread, from the
Gauss-Newton covariance ``(J^T J)^-1`` at the fit (residuals and priors as above): the root of the
trace of its 2 x 2 tangent block (mm). On the default layout it is about twice as large where the
fitted points err most (the 10 % least certain err 0.8-0.9 mm, the rest 0.4 mm): those crossings are
the ones worth touching again (:func:`.calibration.refine_targets`).
"""
from __future__ import annotations

import dataclasses

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from ..data.sensing_map import SensingMap
from ..geometry.surface import SurfaceProjector
from ..geometry.triangles import surface_normals
from .coupling_profile import student_profile

RELATIVE_ERROR = 0.05  # the profile's misfit relative to a delta, added to the noise in the residual scale


@dataclasses.dataclass(frozen=True)
class CrossingFit:
    """Fitted crossings: points on the surface (mm), log gains, and the profile (width mm, tail)."""

    points: np.ndarray  # (K, 3) mm, on the surface
    log_gain: np.ndarray  # (K,)
    width_mm: float
    tail: float
    moved_mm: np.ndarray  # (K,) distance from the map's point
    position_std_mm: np.ndarray  # (K,) posterior spread of each point (module docstring)


def tangent_frames(normals: np.ndarray) -> np.ndarray:
    """(K, 2, 3) two unit tangent directions per unit normal (K, 3)."""
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    first = np.cross(normals, helper)
    first /= np.linalg.norm(first, axis=1, keepdims=True)
    return np.stack([first, np.cross(normals, first)], axis=1)


def locate_crossings(sensing_map: SensingMap, records: list[tuple[int, np.ndarray]], sigma: np.ndarray,
                     gain: np.ndarray, width_mm: float, placement_sigma_mm: float = 1.5,
                     aim_sigma_mm: float = 1.0, reach_pitch: float = 3.0) -> CrossingFit:
    """The joint fit of the module docstring over ``records`` ((touched crossing, mean delta (K,)
    counts) per calibration touch), ``sigma`` (K,) noise sigma (counts), starting from ``gain`` (K,)
    and the Gaussian width ``width_mm``."""
    k, n = sensing_map.cell_count, len(records)
    x = sensing_map.cell_points
    frames = tangent_frames(sensing_map.cell_normals)
    reach = reach_pitch * sensing_map.pitch_mm()
    touched = np.array([cell for cell, _ in records])
    pair_touch, pair_cell, observed = [], [], []
    for t, (cell, delta) in enumerate(records):
        near = np.flatnonzero(np.linalg.norm(x - x[cell], axis=1) <= reach)
        pair_touch.append(np.full(len(near), t))
        pair_cell.append(near)
        observed.append(delta[near])
    pt, pc, z = np.concatenate(pair_touch), np.concatenate(pair_cell), np.concatenate(observed)
    pk = touched[pt]  # the touched crossing of each pair
    scale = np.sqrt(sigma[pc] ** 2 + (RELATIVE_ERROR * np.maximum(z, 0.0)) ** 2)
    # Unknowns: u (2K), b (K), v (2N), a (N), log width, log tail.
    iu, ib, iv, ia = 0, 2 * k, 3 * k, 3 * k + 2 * n
    iw = 3 * k + 3 * n

    def unpack(theta):
        u = theta[iu:ib].reshape(k, 2)
        v = theta[iv:ia].reshape(n, 2)
        return u, theta[ib:iv], v, theta[ia:iw], np.exp(theta[iw]), np.exp(theta[iw + 1])

    def residuals(theta):
        u, b, v, a, width, tail = unpack(theta)
        y = x + np.einsum("ki,kid->kd", u, frames)
        p = y[touched] + np.einsum("ti,tid->td", v, frames[touched])
        d2 = np.sum((y[pc] - p[pt]) ** 2, axis=1)
        model = np.exp(b[pc] + a[pt]) * student_profile(d2, width, tail)
        return np.concatenate([(z - model) / scale, u.ravel() / placement_sigma_mm, v.ravel() / aim_sigma_mm,
                               b - start[ib:iv]])

    m = len(z)
    sparsity = lil_matrix((m + 2 * k + 2 * n + k, iw + 2), dtype=np.int8)
    rows = np.arange(m)
    for offset in (0, 1):
        sparsity[rows, iu + 2 * pc + offset] = 1
        sparsity[rows, iu + 2 * pk + offset] = 1
        sparsity[rows, iv + 2 * pt + offset] = 1
    sparsity[rows, ib + pc] = 1
    sparsity[rows, ia + pt] = 1
    sparsity[:m, iw:] = 1
    sparsity[m + np.arange(2 * k), iu + np.arange(2 * k)] = 1
    sparsity[m + 2 * k + np.arange(2 * n), iv + np.arange(2 * n)] = 1
    sparsity[m + 2 * k + 2 * n + np.arange(k), ib + np.arange(k)] = 1
    start = np.zeros(iw + 2)
    start[ib:iv] = np.log(np.maximum(gain, 1e-3))
    peak = np.array([max(delta[cell], 1e-3) for cell, delta in records])
    start[ia:iw] = np.log(peak / np.maximum(gain[touched], 1e-3))
    start[iw], start[iw + 1] = np.log(width_mm), np.log(20.0)
    fit = least_squares(residuals, start, jac_sparsity=sparsity.tocsr(), method="trf", x_scale="jac",
                        max_nfev=60, xtol=1e-6, ftol=1e-8)
    u, b, _, _, width, tail = unpack(fit.x)
    located = relocated_map(sensing_map, x + np.einsum("ki,kid->kd", u, frames))
    return CrossingFit(located.cell_points, b, float(width), float(tail),
                       np.linalg.norm(located.cell_points - x, axis=1), position_spread(fit.jac, k))


def position_spread(jacobian, k: int) -> np.ndarray:
    """(k,) root of the trace of each crossing's 2 x 2 displacement block of ``(J^T J)^-1`` (mm), the
    displacements being the first ``2 k`` unknowns of the Jacobian ``J`` (sparse or dense)."""
    from scipy.linalg import cho_factor, cho_solve

    information = jacobian.T @ jacobian
    information = information.toarray() if hasattr(information, "toarray") else np.array(information)
    information[np.diag_indices_from(information)] += 1e-12 * np.abs(information).max()  # a numerically flat direction
    first = np.zeros((len(information), 2 * k))
    first[np.arange(2 * k), np.arange(2 * k)] = 1.0
    covariance = cho_solve(cho_factor(information), first)  # the first 2k columns of the inverse
    return np.sqrt(np.maximum(covariance[np.arange(0, 2 * k, 2), np.arange(0, 2 * k, 2)]
                              + covariance[np.arange(1, 2 * k, 2), np.arange(1, 2 * k, 2)], 0.0))


def relocated_map(sensing_map: SensingMap, points: np.ndarray) -> SensingMap:
    """``sensing_map`` with its crossings at ``points`` (K, 3) (mm), projected on the surface."""
    projector = SurfaceProjector(sensing_map.vertices, sensing_map.faces)
    k = sensing_map.cell_count
    moved, faces, bary = np.empty((k, 3)), np.empty(k, dtype=np.int64), np.empty((k, 3))
    for j in range(k):
        found = projector.project(points[j], sensing_map.cell_normals[j])
        moved[j], faces[j], bary[j] = found[0][0], found[1][0], found[2][0]
    normals = surface_normals(sensing_map.vertices, sensing_map.faces, faces, bary)
    return dataclasses.replace(sensing_map, cell_points=moved, cell_faces=faces, cell_bary=bary, cell_normals=normals)
