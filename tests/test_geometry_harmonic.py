"""geometry.harmonic and geometry.sparse_spd: the cotan Laplacian, harmonic interpolation over (V, F)
and the Cholesky solves behind them."""
from __future__ import annotations

import numpy as np
import trimesh

from retrotouch.nodes.geometry.harmonic import cotan_laplacian, harmonic_interpolation
from retrotouch.nodes.geometry.sparse_spd import cholesky, solve, spd_solve


def flat_grid(n: int = 21, size_mm: float = 40.0, jitter: float = 0.3, seed: int = 0):
    """A jittered, triangulated square in the plane z = 0 and its boundary vertex indices."""
    x, y = np.meshgrid(np.linspace(0, size_mm, n), np.linspace(0, size_mm, n))
    V = np.c_[x.ravel(), y.ravel(), np.zeros(n * n)]
    inner = (x.ravel() > 0) & (x.ravel() < size_mm) & (y.ravel() > 0) & (y.ravel() < size_mm)
    V[inner, :2] += np.random.default_rng(seed).uniform(-jitter, jitter, (inner.sum(), 2)) * size_mm / (n - 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    F = np.r_[np.c_[a, b, d], np.c_[a, d, c]]
    return V, F, np.flatnonzero(~inner)


def test_laplacian_is_symmetric_with_zero_row_sums_and_the_cotan_weights_of_an_equilateral_pair():
    V, F, _ = flat_grid()
    L = cotan_laplacian(V, F)
    assert abs(L - L.T).max() < 1e-12
    assert np.abs(np.asarray(L.sum(axis=1))).max() < 1e-12
    # two equilateral triangles sharing an edge: each opposite angle is 60 deg, weight -(2 cot 60)/2
    h = np.sqrt(3) / 2
    L2 = cotan_laplacian(np.array([[0, 0, 0], [1, 0, 0], [0.5, h, 0], [0.5, -h, 0]]), np.array([[0, 1, 2], [1, 0, 3]]))
    np.testing.assert_allclose(L2[0, 1], -1 / np.sqrt(3))


def test_a_linear_function_is_reproduced_exactly_from_its_boundary_values():
    V, F, boundary = flat_grid()
    linear = 0.7 * V[:, 0] - 0.2 * V[:, 1] + 3.0
    u = harmonic_interpolation(V, F, boundary, linear[boundary])
    np.testing.assert_allclose(u, linear, atol=1e-9)


def test_values_stay_between_the_fixed_ones_on_a_sphere_with_two_poles():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=50.0)
    V, F = sphere.vertices, sphere.faces
    south = np.flatnonzero(V[:, 2] < -45.0)
    north = np.flatnonzero(V[:, 2] > 45.0)
    u = harmonic_interpolation(V, F, np.r_[south, north], np.r_[np.zeros(len(south)), np.ones(len(north))])
    assert u.min() >= -1e-9 and u.max() <= 1 + 1e-9
    # symmetric caps: the solution depends on the height only and is monotone in it
    free = np.setdiff1d(np.arange(len(V)), np.r_[south, north])
    order = np.argsort(V[free, 2])
    assert np.all(np.diff(u[free][order]) > -0.02)
    assert abs(np.median(u[free][np.abs(V[free, 2]) < 2.0]) - 0.5) < 0.01


def test_the_cholesky_solves_a_pinned_laplacian_for_one_and_for_many_right_hand_sides():
    V, F, boundary = flat_grid()
    L = cotan_laplacian(V, F)
    free = np.setdiff1d(np.arange(len(V)), boundary)
    A = L[free][:, free]
    rhs = np.random.default_rng(1).normal(size=(len(free), 3))
    x = spd_solve(A, rhs[:, 0])
    assert x.shape == (len(free),)
    np.testing.assert_allclose(A @ x, rhs[:, 0], atol=1e-10)
    many = solve(cholesky(A), rhs)
    np.testing.assert_allclose(A @ many, rhs, atol=1e-10)
    np.testing.assert_allclose(many[:, 0], x, atol=1e-12)
