"""The tick's compiled linear algebra (qpnso.linalg) against NumPy's SVD, pinv, Cholesky and inverse."""

from __future__ import annotations

import numpy as np
import pytest

from qpnso.linalg import (
    cholesky,
    cholesky_solve,
    dot,
    dynamically_consistent_projection,
    least_norm_line,
    matmul,
    matvec,
    nullspace_part,
)


def _upper_only(M: np.ndarray) -> np.ndarray:
    """``M`` with garbage below the diagonal: the kernels must read the upper triangle only."""
    out = M.copy()
    out[np.tril_indices_from(out, -1)] = 1e6
    return out


def test_small_products_equal_numpy_in_every_layout():
    rng = np.random.default_rng(7)
    A, B = rng.standard_normal((6, 7)), rng.standard_normal((7, 3))
    x, y = rng.standard_normal(7), rng.standard_normal(6)
    for a in (A, np.asfortranarray(A), A.T.copy().T):  # C, F and a transposed view
        np.testing.assert_allclose(matvec(a, x), A @ x, rtol=1e-14, atol=1e-14)
        np.testing.assert_allclose(matvec(a.T, y), A.T @ y, rtol=1e-14, atol=1e-14)
        np.testing.assert_allclose(matmul(a, B), A @ B, rtol=1e-14, atol=1e-14)
        np.testing.assert_allclose(matmul(a, a.T), A @ A.T, rtol=1e-14, atol=1e-14)
    assert dot(x, x) == pytest.approx(x @ x, rel=1e-15)
    assert matvec(np.zeros((0, 7)), x).shape == (0,)


@pytest.mark.parametrize("seed", range(20))
def test_least_norm_line_is_the_pseudo_inverse_and_the_null_vector(seed):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((6, 7)) * rng.uniform(0.01, 3.0, size=(6, 1))
    b = rng.standard_normal(6)
    x0, d, floor = least_norm_line(A, b)
    np.testing.assert_allclose(x0, np.linalg.pinv(A) @ b, atol=1e-9 * (1 + np.abs(x0).max()))
    assert abs(np.linalg.norm(d) - 1.0) < 1e-14 and np.abs(A @ d).max() < 1e-12
    _, sigma, vt = np.linalg.svd(A)
    assert abs(abs(d @ vt[-1]) - 1.0) < 1e-12  # the null space is one-dimensional
    assert sigma[-1] / np.sqrt(6) - 1e-12 <= floor <= sigma[-1] + 1e-12  # a lower bound, within √m


def test_least_norm_line_fortran_order_and_singular_rows():
    rng = np.random.default_rng(1)
    A = rng.standard_normal((6, 7))
    b = rng.standard_normal(6)
    np.testing.assert_allclose(least_norm_line(np.asfortranarray(A), b)[0], least_norm_line(A, b)[0], atol=1e-14)
    A[3] = 0.0  # rank 5: no lower bound on σ_min, never NaN
    x0, d, floor = least_norm_line(A, b)
    assert floor == 0.0 and np.all(np.isfinite(x0)) and np.all(np.isfinite(d))
    A[3] = A[2]  # two equal rows: rank 5 up to round-off, the bound collapses
    assert least_norm_line(A, b)[2] < 1e-6


@pytest.mark.parametrize("seed", range(10))
def test_cholesky_from_the_upper_triangle(seed):
    rng = np.random.default_rng(seed)
    M = rng.standard_normal((7, 7))
    M = M @ M.T + 0.1 * np.eye(7)
    L, ok = cholesky(_upper_only(M), 0.0)
    assert ok
    np.testing.assert_allclose(L, np.linalg.cholesky(M), atol=1e-12)
    b = rng.standard_normal(7)
    np.testing.assert_allclose(cholesky_solve(L, b), np.linalg.solve(M, b), rtol=1e-9, atol=1e-12)
    L_reg, _ = cholesky(_upper_only(M), 1e-3)
    np.testing.assert_allclose(L_reg @ L_reg.T, M + 1e-3 * np.trace(M) * np.eye(7), atol=1e-10)


def test_cholesky_reports_an_indefinite_matrix():
    M = np.diag([1.0, 2.0, -1e-9, 3.0])
    assert cholesky(M, 0.0)[1] is False
    assert cholesky(np.zeros((3, 3)), 0.0)[1] is False
    # the last pivot the only one at or below zero (nothing after it to turn NaN): still reported
    assert cholesky(np.diag([1.0, 2.0, 3.0, -1e-9]), 0.0)[1] is False
    assert cholesky(np.diag([1.0, 2.0, 3.0, 0.0]), 0.0)[1] is False


@pytest.mark.parametrize("seed", range(10))
def test_nullspace_part_is_the_projection_on_ker_j(seed):
    """v − J⁺Jv: in ker J, and v minus it in range Jᵀ (NumPy's pinv)."""
    rng = np.random.default_rng(seed)
    J = rng.standard_normal((6, 7))
    v = rng.standard_normal(7)
    part = nullspace_part(J, v)
    # (JJᵀ is regularised by 1e-12 of its trace: ~1e-10 relative here)
    assert np.abs(J @ part).max() < 1e-8
    np.testing.assert_allclose(part, v - np.linalg.pinv(J) @ (J @ v), atol=1e-8)


@pytest.mark.parametrize("seed", range(10))
def test_dynamically_consistent_projection(seed):
    """Nᵀτ against the explicit formula with NumPy inverses; J A⁻¹ Nᵀτ = 0 (no tool acceleration)."""
    rng = np.random.default_rng(seed)
    M = rng.standard_normal((7, 7))
    A = M @ M.T + 0.5 * np.eye(7)
    J = rng.standard_normal((6, 7))
    tau = rng.standard_normal(7)
    out, ok = dynamically_consistent_projection(_upper_only(A), J, tau)
    assert ok
    A_inv = np.linalg.inv(A)
    lam = np.linalg.inv(J @ A_inv @ J.T)
    N = np.eye(7) - A_inv @ J.T @ lam @ J
    np.testing.assert_allclose(out, N.T @ tau, atol=1e-9)
    assert np.abs(J @ A_inv @ out).max() < 1e-9


def test_projection_of_a_singular_inertia_is_no_torque_at_all():
    """No factorisation, no projection: zero (an unprojected torque would push the tool), never NaN."""
    out, ok = dynamically_consistent_projection(np.zeros((7, 7)), np.ones((6, 7)), np.arange(7.0))
    assert not ok
    np.testing.assert_array_equal(out, np.zeros(7))
