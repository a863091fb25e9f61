"""Small dense linear algebra of the control tick, compiled with Numba.

A 1 kHz tick on a 7-DOF arm works on 6×7 and 7×7 matrices; there LAPACK's
arithmetic takes well under a microsecond and Python's call overhead (several
µs per NumPy or SciPy call) is the cost.  These kernels do the tick's few
factorisations in scalar loops instead, compiled once per machine by Numba
(``cache=True``: the machine code is kept beside the module).  Each is tested
against NumPy/SciPy (tests/test_linalg.py).

* :func:`least_norm_line` — Householder QR of ``Aᵀ`` for a full-row-rank
  (n−1)×n ``A``: least-norm solution ``A⁺b``, unit null vector, and a lower
  bound on ``σ_min(A)`` (the hierarchical QP's line fast path, :mod:`qpnso.qp.line`);
* :func:`cholesky` / :func:`cholesky_solve` — for symmetric positive-definite
  matrices given by their upper triangle (Pinocchio's ``crba`` fills only that);
* :func:`nullspace_part` — ``v − J⁺Jv``, the part of ``v`` in ``ker J``;
* :func:`dynamically_consistent_projection` — ``Nᵀτ`` with
  ``N = I − J̄J``, ``J̄ = A⁻¹Jᵀ(JA⁻¹Jᵀ)⁻¹`` (docs/method.md §2); the tick factorises once
  (:func:`nullspace_factors`) and takes from the factors ``Nᵀτ`` (:func:`project_torque`), the
  self-motion part ``N q̇`` of a velocity (:func:`project_velocity`) and the self-motion's inertia
  ``1/trace(N A⁻¹)`` (:func:`selfmotion_inertia`).
"""

from __future__ import annotations

import numpy as np
from numba import njit

REGULARIZATION = 1e-12
"""Relative (to the trace) regularisation of ``JJᵀ`` and ``JA⁻¹Jᵀ``: a singular ``J`` gives a finite answer."""


@njit(cache=True)
def dot(a, b):
    """``aᵀb`` of two vectors."""
    acc = 0.0
    for i in range(a.shape[0]):
        acc += a[i] * b[i]
    return acc


@njit(cache=True)
def matvec(A, x):
    """``A x`` (``A`` (m, n), any layout).  The kernels' products are written as loops: at these
    sizes (n ≤ 7) a BLAS call costs more than the arithmetic, and every ``@`` of a new layout
    costs seconds of Numba compilation."""
    m, n = A.shape
    y = np.zeros(m)
    for i in range(m):
        for j in range(n):
            y[i] += A[i, j] * x[j]
    return y


@njit(cache=True)
def matmul(A, B):
    """``A B`` (any layouts)."""
    m, k = A.shape
    n = B.shape[1]
    C = np.zeros((m, n))
    for i in range(m):
        for p in range(k):
            a = A[i, p]
            for j in range(n):
                C[i, j] += a * B[p, j]
    return C


@njit(cache=True)
def least_norm_line(A, b):
    """``(x0, d, σ_floor)`` for ``A`` (n−1, n) and ``b`` (n−1,): ``x0 = A⁺b``, ``d`` a unit vector
    with ``A d = 0`` and ``σ_floor = 1/‖R⁻¹‖_F ≤ σ_min(A)`` (conservative by at most √(n−1));
    ``σ_floor = 0`` when ``A`` is singular.  Householder QR of ``Aᵀ = Q [R; 0]``."""
    m, n = A.shape
    R = A.T.copy()  # (n, m), reduced in place
    V = np.zeros((m, n))  # reflector k: I − β_k v_k v_kᵀ acting on entries k…n−1
    beta = np.zeros(m)
    for k in range(m):
        norm = 0.0
        for i in range(k, n):
            norm += R[i, k] * R[i, k]
        norm = np.sqrt(norm)
        if norm == 0.0:
            return np.zeros(n), np.zeros(n), 0.0
        for i in range(k, n):
            V[k, i] = R[i, k]
        V[k, k] += norm if R[k, k] >= 0.0 else -norm
        vv = 0.0
        for i in range(k, n):
            vv += V[k, i] * V[k, i]
        beta[k] = 2.0 / vv
        for j in range(k, m):
            dot = 0.0
            for i in range(k, n):
                dot += V[k, i] * R[i, j]
            dot *= beta[k]
            for i in range(k, n):
                R[i, j] -= dot * V[k, i]
    y = np.zeros(n)  # Rᵀ y = b (forward substitution), then x0 = Q [y; 0]
    for i in range(m):
        acc = b[i]
        for j in range(i):
            acc -= R[j, i] * y[j]
        y[i] = acc / R[i, i]
    d = np.zeros(n)
    d[n - 1] = 1.0
    for k in range(m - 1, -1, -1):  # Q = H_0 … H_{m−1}, applied right to left
        dy, dd = 0.0, 0.0
        for i in range(k, n):
            dy += V[k, i] * y[i]
            dd += V[k, i] * d[i]
        for i in range(k, n):
            y[i] -= beta[k] * dy * V[k, i]
            d[i] -= beta[k] * dd * V[k, i]
    frob = 0.0  # ‖R⁻¹‖_F², column by column (back substitution)
    col = np.zeros(m)
    for j in range(m):
        for i in range(j, -1, -1):
            acc = 1.0 if i == j else 0.0
            for k in range(i + 1, j + 1):
                acc -= R[i, k] * col[k]
            col[i] = acc / R[i, i]
            frob += col[i] * col[i]
    return y, d, 1.0 / np.sqrt(frob)


@njit(cache=True)
def cholesky(M, regularization):
    """Lower factor ``L`` with ``L Lᵀ = M + regularization·tr(M)·I`` from the upper triangle of
    symmetric ``M``, and whether ``M`` was positive definite (else ``L`` is garbage)."""
    n = M.shape[0]
    shift = 0.0
    for i in range(n):
        shift += M[i, i]
    shift *= regularization
    L = np.zeros((n, n))
    for j in range(n):
        acc = M[j, j] + shift
        for k in range(j):
            acc -= L[j, k] * L[j, k]
        if not acc > 0.0:
            return L, False
        L[j, j] = np.sqrt(acc)
        for i in range(j + 1, n):
            acc = M[j, i]  # upper triangle: M[i, j] = M[j, i]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            L[i, j] = acc / L[j, j]
    return L, True


@njit(cache=True)
def cholesky_solve(L, b):
    """``x`` with ``L Lᵀ x = b`` (``b`` a vector)."""
    n = L.shape[0]
    y = np.empty(n)
    for i in range(n):
        acc = b[i]
        for k in range(i):
            acc -= L[i, k] * y[k]
        y[i] = acc / L[i, i]
    for i in range(n - 1, -1, -1):
        acc = y[i]
        for k in range(i + 1, n):
            acc -= L[k, i] * y[k]
        y[i] = acc / L[i, i]
    return y


@njit(cache=True)
def nullspace_part(J, v):
    """``v − J⁺Jv`` (``JJᵀ`` regularised by 1e-12 of its trace); ``v`` unchanged if that fails."""
    L, ok = cholesky(matmul(J, J.T), REGULARIZATION)
    if not ok:
        return v.copy()
    return v - matvec(J.T, cholesky_solve(L, matvec(J, v)))


@njit(cache=True)
def lower_solve(L, B):
    """``X`` with ``L X = B`` (``L`` lower triangular (n, n), ``B`` (n, k)): forward substitution, column by
    column."""
    n, k = B.shape
    X = np.empty((n, k))
    for c in range(k):
        for i in range(n):
            acc = B[i, c]
            for j in range(i):
                acc -= L[i, j] * X[j, c]
            X[i, c] = acc / L[i, i]
    return X


@njit(cache=True)
def nullspace_factors(A, J):
    """``(L_A, W, L_Λ, ok)``, the factors of the dynamically consistent null space of ``J`` (m, n) under the
    inertia ``A`` (n, n; by its upper triangle): ``L_A L_Aᵀ = A``, ``W = A⁻¹Jᵀ`` (n, m) and
    ``L_Λ L_Λᵀ = J A⁻¹ Jᵀ = Λ⁻¹`` (regularised by :data:`REGULARIZATION` of its trace: a singular ``J`` gives
    finite factors).  ``ok`` False when ``A`` or ``Λ⁻¹`` cannot be factorised (then the factors are garbage)."""
    m, n = J.shape
    LA, ok = cholesky(A, 0.0)
    W = np.zeros((n, m))
    if not ok:
        return LA, W, np.zeros((m, m)), False
    for k in range(m):
        W[:, k] = cholesky_solve(LA, J[k].copy())
    LL, ok = cholesky(matmul(J, W), REGULARIZATION)
    return LA, W, LL, ok


@njit(cache=True)
def project_torque(J, W, LL, tau):
    """``Nᵀτ = τ − Jᵀ Λ J A⁻¹ τ`` (N·m) from :func:`nullspace_factors` (``Λ = (J A⁻¹ Jᵀ)⁻¹``): a torque that
    gives the tool no acceleration (``J A⁻¹ Nᵀτ = 0``)."""
    return tau - matvec(J.T, cholesky_solve(LL, matvec(W.T, tau)))


@njit(cache=True)
def project_velocity(J, W, LL, dq):
    """``N q̇ = q̇ − A⁻¹Jᵀ Λ J q̇`` (rad/s) from :func:`nullspace_factors`: the self-motion part of a joint
    velocity (``J N q̇ = 0``), its part A-orthogonal to the tool's motion — what the arm's kinetic energy
    splits into, ``q̇ᵀAq̇ = (J̄Jq̇)ᵀA(J̄Jq̇) + (Nq̇)ᵀA(Nq̇)`` — so a velocity a tool force gives the arm from rest,
    ``A⁻¹Jᵀf`` (in the range of ``J̄ = A⁻¹JᵀΛ``), has none."""
    return dq - matvec(W, cholesky_solve(LL, matvec(J, dq)))


@njit(cache=True)
def selfmotion_inertia(LA, W, LL):
    """``1/trace(N A⁻¹)`` (kg·m² for revolute joints) from :func:`nullspace_factors`: the inertia a null-space
    torque moves.  ``N A⁻¹ = A⁻¹ − W Λ Wᵀ = Z (ZᵀAZ)⁻¹ Zᵀ`` for an orthonormal basis ``Z`` of ``ker J``, so
    its trace is the sum of the inverse self-motion inertias (the eigenvalues of ``ZᵀAZ``): exactly the
    self-motion's inertia ``zᵀAz`` when ``ker J`` is one direction ``z`` (a 7-joint arm and a 6-D tool), the
    least of them or less otherwise (conservative).  ``trace(A⁻¹) = ‖L_A⁻¹‖²_F``,
    ``trace(WΛWᵀ) = ‖L_Λ⁻¹Wᵀ‖²_F``.  0 when the difference is not positive (round-off on a null space much
    heavier than the arm's lightest direction)."""
    n = LA.shape[0]
    inv_a = lower_solve(LA, np.eye(n))
    part = lower_solve(LL, W.T.copy())
    trace = 0.0
    for i in range(n):
        for j in range(n):
            trace += inv_a[i, j] * inv_a[i, j]
    for i in range(part.shape[0]):
        for j in range(n):
            trace -= part[i, j] * part[i, j]
    return 1.0 / trace if trace > 0.0 else 0.0


@njit(cache=True)
def dynamically_consistent_projection(A, J, tau):
    """``(Nᵀτ, ok)``: ``Nᵀτ = τ − Jᵀ Λ J A⁻¹ τ`` with ``Λ = (J A⁻¹ Jᵀ)⁻¹`` (docs/method.md §2); ``A`` by its
    upper triangle.  When ``A`` or ``J A⁻¹ Jᵀ`` cannot be factorised (``ok`` False): zero, never NaN and
    never ``τ`` unprojected (that would push the tool): the tick's torque is then ``g(q)`` alone."""
    _, W, LL, ok = nullspace_factors(A, J)
    if not ok:
        return np.zeros_like(tau), False
    return project_torque(J, W, LL, tau), True
