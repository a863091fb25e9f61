"""The null-space cascade's arithmetic: one level's QP, what it owns and passes down (docs/method.md §7.5).

**Null-space form** (not the fragile equality form, docs/qp-notes.md): level ``k``
moves the answer of the levels above only inside the directions that no higher
level owns, through an orthonormal basis ``Z_k`` (n×r) of them:
``x = x_{k−1} + Z_k z``.  The answer is always formed through ``Z_k``, so a
higher task's residual is preserved by construction, whatever the solver's
tolerance.  Each level's QP (:func:`level_qp_arrays`, variable ``z`` ∈ Rʳ plus one
scaled slack per soft row) has NO equality rows: on the first level ``Z = I``
and the bounds are ProxSuite's native box; below, the bounds are the n rows
``Z z``.  After a full-rank 6×7 tool task r = 1 (the self-motion direction),
so level 2 is a QP in 1 (+ slack) variables.  Its shape changes only when the
rank does (singularities): ProxSuite keeps one object per (level, shape).  The
sign of a basis column is fixed (largest-magnitude entry positive) so that the
previous tick's ``z`` stays a good warm start.  (Measured against the earlier
projector form: docs/changelog.md.)

The Hessian carries a tie-break ``½ μ ‖z‖²`` only in the directions that the
level's own task leaves free (``μ = QPSettings.regularization``: 1e-7 for the
active-set back ends, which need a positive-definite H — DAQP failed at 1e-8 on
a level without curvature, 1e-6 biased answers by 2.5e-6, measured; 0 for
ProxQP, whose proximal iterations handle a semi-definite H and which lost
accuracy and hit max_iter with a tiny curvature at tight tolerances,
measured).  μ must stay small: with bounds active, moving along a task's null
space can still lower its residual (it changes which bounds bind).

A level *owns* (removes from ``Z`` for the levels below it; all in z, r×r):

1. the right singular vectors of ``W^½ A Z_k`` with ``σ > rank_tol·max(1, σ_max)``
   — so lower levels change a higher equality task's residual by at most
   ``rank_tol·‖d‖`` (≈1e-10·‖d‖, exactly zero for an exactly singular row);
2. the range of ``Zᵀ H Z`` (eigenvalues above ``rank_tol·max(1, ‖H‖)``);
3. the direction of its projected gradient, if that is not ~0 (a linear cost
   blocked by constraints).

Together with the constraints below this is the exact optimal set of a convex
level (on that set the Hessian term and the gradient term are constant).
Every constraint of a level (bounds, hard rows, soft rows) is passed down with
its interval widened just enough to contain that level's solution: hard
constraints stay hard, and a soft row's violation can never grow.  A side
within ``active_tol`` (1e-7) of that solution is moved onto it: an inexact
(interior) answer otherwise leaves the lower level a sliver of a feasible set
that ProxQP's infeasibility test can mistake for an empty one (measured).

**Singular tasks** (damped least squares, singular-value
dependent): along a right singular direction with
``rank_tol < σ < ε`` (``ε = QPSettings.damping_threshold``, units of ``A``,
e.g. m/rad) the cost gets ``(ε² − σ²)·(vᵀd)²``, so the effective curvature is
``ε²`` and the joint speed demanded per unit of task error never exceeds
``1/ε``; directions with ``σ ≥ ε`` are not damped at all.  Damped directions
stay owned by their level (frozen for lower levels); directions with
``σ ≤ rank_tol·max(1, σ_max)`` are exactly null and free for lower levels.

A level's answer is checked in joint space by one kernel, :func:`level_answer` (bounds and hard
rows within ``feasibility_tol``, each soft row's slack), which the line fast path
(:mod:`qpnso.qp.line`) shares.  All of it is Numba kernels (:func:`level_qp_arrays`,
:func:`level_answer`, :func:`advance_basis`, :func:`pass_down`); :mod:`qpnso.qp.cascade_state` runs them on
the cascade's state, and :class:`~qpnso.qp.solver.HierarchicalQP` runs the cascade level after level.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numba import njit

from qpnso.linalg import dot, matmul, matvec
from qpnso.qp.arrays import LevelParts, QPArrays, qp_data_finite
from qpnso.qp.levels import _LevelData

__all__ = ["advance_basis", "level_answer", "level_qp_arrays"]


@functools.lru_cache(maxsize=16)
def _eye(n: int) -> np.ndarray:
    """A read-only n×n identity (cached: this is on the per-tick path)."""
    eye = np.eye(n)
    eye.flags.writeable = False
    return eye


_NO_VECTOR = np.zeros(0)


@functools.lru_cache(maxsize=16)
def _no_rows(n: int) -> np.ndarray:
    """A (0, n) array: an absent matrix part passed to a kernel (cached, any width).  Writable like every
    other array the kernels get: a read-only one is another Numba type, compiled (seconds) in the first
    tick that takes a rare path (the general path's line level with the elbow dropped did, in the fuzz)."""
    return np.zeros((0, n))


def _c(a: np.ndarray) -> np.ndarray:
    """``a`` as a writable C-contiguous float array: the one array type the kernels are compiled for
    (another layout or a read-only array is another Numba signature, compiled in the tick that meets it)."""
    return a if a.flags.c_contiguous and a.flags.writeable else np.array(a, dtype=float, order="C")


@njit(cache=True)
def task_svd(level, basis):
    """The level's weighted task in z, ``At = W^½ A Z`` (m, r), its singular values ``sigma`` (descending)
    and right singular vectors ``vt`` (r, r), and its residual at the higher levels' answer
    ``r0 = W^½(A x_prev − b)``; ``level`` a :class:`~qpnso.qp.arrays.LevelParts` (weights folded in),
    ``basis`` a :class:`~qpnso.qp.arrays.Basis`.  Empty ``At``, ``sigma`` and ``r0`` without a task or a free
    direction.  A task that is not finite has no singular values (the QP's linear term is then not finite,
    and the level reports it: ``finite``, :func:`level_qp_arrays`)."""
    A, Z = level.A, basis.Z
    r = Z.shape[1]
    if A.shape[0] == 0 or r == 0:
        return np.zeros((0, r)), np.zeros(0), np.zeros((r, r)), np.zeros(0)
    At = A if basis.full else matmul(A, Z)  # (read only: no copy)
    r0 = matvec(A, basis.x_prev) - level.b if basis.moved else -level.b
    if not np.all(np.isfinite(At)):
        return At, np.zeros(0), np.eye(r), r0
    _, sigma, vt = np.linalg.svd(At)
    return At, sigma, vt, r0


@njit(cache=True)
def level_qp_arrays(level, basis, inherited, tol):
    """The QP of a level in the free coordinates ``z`` (``x = x_prev + Z z``): ``level`` the level's
    :class:`~qpnso.qp.arrays.LevelParts`, ``basis`` and ``inherited`` what the levels above leave
    (:class:`~qpnso.qp.arrays.Basis`, :class:`~qpnso.qp.arrays.Inherited`), ``tol`` the tolerances
    (:func:`qpnso.qp.settings.tolerance_record`); the task's SVD is :func:`task_svd`'s.

    Returns ``(arrays, has_box, owned_z, free_z, has_task, finite)``: ``arrays`` the
    :class:`~qpnso.qp.arrays.QPArrays` fields as a plain tuple (a named tuple returned to Python is built
    through its class, unpickled on every call: 6 % of a cascade's instructions, measured), ``finite``
    :func:`~qpnso.qp.arrays.qp_data_finite` of them."""
    At, sigma, vt, r0 = task_svd(level, basis)
    H, g, C, l, u = level.H, level.g, level.C, level.l, level.u
    Z, full, x_prev, moved = basis.Z, basis.full, basis.x_prev, basis.moved
    T = tol[0]
    reg, rank_tol, damping = T.regularization, T.rank_tol, T.damping_threshold
    n, r = x_prev.shape[0], Z.shape[1]
    ns = level.n_slack
    nv = r + ns
    Hv = np.zeros((nv, nv))
    gv = np.zeros(nv)
    k = 0
    has_task = At.shape[0] > 0
    if has_task:  # damped least squares (module docstring): owned directions σ > rank_tol·max(1, σ_max)
        threshold = rank_tol * max(1.0, sigma[0] if sigma.shape[0] else 0.0)  # (none: a task not finite)
        while k < sigma.shape[0] and sigma[k] > threshold:  # sorted: a prefix
            k += 1
        for p in range(k):
            c = 2.0 * max(sigma[p] * sigma[p], damping * damping)
            for i in range(r):
                a = c * vt[p, i]
                for j in range(r):
                    Hv[i, j] += a * vt[p, j]
        gv[:r] = 2.0 * matvec(At.T, r0)
    owned_z = vt[:k].T.copy()
    free_z = vt[k:].T.copy()
    linear = np.zeros(n)
    has_linear = False
    if H.shape[0]:
        Hz = H if full else matmul(matmul(Z.T, H), Z)
        Hv[:r, :r] += Hz
        if moved:
            linear += matvec(H, x_prev)
            has_linear = True
    if g.shape[0]:
        linear += g
        has_linear = True
    if has_linear:
        gv[:r] += linear if full else matvec(Z.T, linear)
    if reg > 0.0 and r:  # tie-break on the directions the task leaves free
        for i in range(r):
            Hv[i, i] += reg
        if k:
            Hv[:r, :r] -= reg * matmul(owned_z, owned_z.T)
    for i in range(ns):
        Hv[r + i, r + i] = 1.0
    C_inh = inherited.C
    p_inh, p_own = C_inh.shape[0], C.shape[0]
    nb = 0 if full else n
    m = p_inh + p_own + nb
    Cv = np.zeros((m, nv))
    lo, hi = np.empty(m), np.empty(m)
    for start, Cp, lp, up in ((0, C_inh, inherited.l, inherited.u), (p_inh, C, l, u)):
        p = Cp.shape[0]
        if p:
            Cv[start : start + p, :r] = Cp if full else matmul(Cp, Z)
            cx = matvec(Cp, x_prev) if moved else np.zeros(p)
            lo[start : start + p] = lp - cx
            hi[start : start + p] = up - cx
    for i in range(ns):
        Cv[p_inh + i, r + i] = level.slack_scale
    has_box = nb == 0
    box_l, box_u = np.full(nv, -np.inf), np.full(nv, np.inf)
    if nb:
        Cv[m - n :, :r] = Z
        lo[m - n :] = inherited.lb - x_prev
        hi[m - n :] = inherited.ub - x_prev
    else:  # Z the identity: the bounds as a box on z (free slacks)
        box_l[:n] = inherited.lb - x_prev
        box_u[:n] = inherited.ub - x_prev
    finite = qp_data_finite(QPArrays(Hv, gv, Cv, lo, hi, box_l, box_u))
    return (Hv, gv, Cv, lo, hi, box_l, box_u), has_box, owned_z, free_z, has_task, finite


@njit(cache=True)
def objective_gradient(level, x):
    """∇ₓ of a level's x-cost ``‖A x − b‖² + ½xᵀHx + gᵀx`` at ``x`` (weights folded into ``A``, ``b``; no
    slack part); ``level`` a :class:`~qpnso.qp.arrays.LevelParts`."""
    n = x.shape[0]
    grad = np.zeros(n)
    if level.A.shape[0]:
        grad += 2.0 * matvec(level.A.T, matvec(level.A, x) - level.b)
    if level.H.shape[0]:
        grad += matvec(level.H, x)
    if level.g.shape[0]:
        grad += level.g
    return grad


@njit(cache=True)
def strictly_convex(H, r, rank_tol):
    """Whether a level's QP (Hessian ``H`` in ``v = [z; σ]``, ``r`` free directions) has a single optimum:
    its Hessian in z positive definite, every eigenvalue above ``rank_tol·max(1, λ_max)`` (the test
    :func:`advance_basis` applies to what a level owns), so that the cascade below it would have no free
    direction left."""
    if r == 0:
        return True
    if r == 1:  # the usual last level (one self-motion direction): its curvature
        return H[0, 0] > rank_tol * max(1.0, H[0, 0])
    eig = np.linalg.eigvalsh(np.ascontiguousarray(H[:r, :r]))
    return eig[0] > rank_tol * max(1.0, eig[-1])


@njit(cache=True)
def fix_signs(Z):
    """``Z`` with each column's largest-magnitude entry positive, in place (the SVD's sign is arbitrary; a
    stable sign keeps the previous tick's ``z`` a good warm start)."""
    n, r = Z.shape
    for j in range(r):
        big, at = -1.0, 0
        for i in range(n):
            if abs(Z[i, j]) > big:
                big, at = abs(Z[i, j]), i
        if Z[at, j] < 0.0:
            for i in range(n):
                Z[i, j] = -Z[i, j]
    return Z


@njit(cache=True)
def complement(p):
    """An orthonormal basis (r, r − 1) of the directions orthogonal to the unit vector ``p``: columns 2…r of
    the Householder reflector that maps ``p`` onto the first axis (LAPACK's ``dlarfg``; NumPy's complete QR of
    ``p`` gives the same columns)."""
    r = p.shape[0]
    Q = np.eye(r)
    alpha = p[0]
    rest = 0.0
    for i in range(1, r):
        rest += p[i] * p[i]
    if rest == 0.0:  # p is ±e1: the reflector is the identity
        return Q[:, 1:].copy()
    beta = -math.copysign(math.sqrt(alpha * alpha + rest), alpha)
    tau = (beta - alpha) / beta
    v = p / (alpha - beta)
    v[0] = 1.0
    for i in range(r):
        for j in range(r):
            Q[i, j] -= tau * v[i] * v[j]
    return Q[:, 1:].copy()


@njit(cache=True)
def advance_basis(level, Z, full, free_z, x, tol):
    """The free basis after a level (module docstring, items 1–3; all r×r work in z): ``Z`` (n, r) the basis
    the level was solved in (``full``: the identity), ``free_z`` (r, r − k) the task directions it leaves (r
    columns: it owns none of its task's), ``x`` its answer (rad/s), ``tol`` the tolerance record.  Returns
    ``(Z_next, changed)``: the directions left for the levels below, columns sign-fixed (:func:`fix_signs`),
    and whether the level owned any."""
    T = tol[0]
    r = Z.shape[1]
    B = free_z
    owned = free_z.shape[1] < r
    if level.H.shape[0]:
        M = level.H.copy() if full else matmul(matmul(Z.T, level.H), Z)
        if owned:
            M = matmul(matmul(B.T, M), B)
        if M.shape[0]:
            w, E = np.linalg.eigh(0.5 * (M + M.T))
            big = w > T.rank_tol * max(1.0, np.abs(w).max())
            keep = np.nonzero(~big)[0]
            if keep.shape[0] < w.shape[0]:
                Ek = np.ascontiguousarray(E[:, keep])
                B = matmul(B, Ek) if owned else Ek
                owned = True
    if level.H.shape[0] or level.g.shape[0]:  # (a pure task's gradient lies in its owned range already)
        grad = objective_gradient(level, x)
        p = grad.copy() if full else matvec(Z.T, grad)
        if owned:
            p = matvec(B.T, p)
        norm_p = math.sqrt(dot(p, p))
        if p.shape[0] and norm_p > T.gradient_tol * max(1.0, math.sqrt(dot(grad, grad))):
            Q = complement(p / norm_p)
            B = matmul(B, Q) if owned else Q
            owned = True
    if not owned:
        return Z, False
    return fix_signs(np.ascontiguousarray(B) if full else matmul(Z, B)), True


@njit(cache=True)
def pass_down(lo, value, hi, active_tol):
    """The interval a lower level inherits, in place: widened to contain ``value`` (a violation never grows),
    and a side within ``active_tol`` of ``value`` moved onto it (exactly active), so that an inexact solver's
    answer a hair inside a bound does not leave a sliver of a feasible set."""
    for i in range(value.shape[0]):
        if value[i] - lo[i] < active_tol:
            lo[i] = value[i]
        if hi[i] - value[i] < active_tol:
            hi[i] = value[i]


@njit(cache=True)
def level_answer(v, basis, qp, slack_start, n_slack):
    """A level QP's answer ``v = [z; σ]`` checked: ``x = x_prev + Z z`` (``basis.full``: ``Z`` is I), the
    worst violation of the box on z (if ``qp`` has one) and of the hard rows (rows taken without σ; the
    bound rows, if any, are ``Z z`` against ``lb − x_prev``), and each soft row's violation (its slack:
    rows ``slack_start`` … ``slack_start + n_slack − 1``)."""
    Z, C, l, u = basis.Z, qp.C, qp.l, qp.u
    r = Z.shape[1]
    z = v[:r]
    worst = 0.0
    if qp.box_l.shape[0]:
        for i in range(r):
            worst = max(worst, qp.box_l[i] - z[i], z[i] - qp.box_u[i])
    slack = np.zeros(n_slack)
    for i in range(C.shape[0]):
        row = 0.0
        for j in range(r):
            row += C[i, j] * z[j]
        violation = max(l[i] - row, row - u[i])
        if slack_start <= i < slack_start + n_slack:
            slack[i - slack_start] = max(violation, 0.0)
        else:
            worst = max(worst, violation)
    d = z.copy() if basis.full else matvec(Z, z)
    return basis.x_prev + d, worst, slack


def level_parts(data: _LevelData, n: int) -> LevelParts:
    """A validated level's parts as the kernels take them (absent parts with zero rows; C-contiguous)."""
    ns = data.n_slack
    return LevelParts(
        _no_rows(n) if data.Aw is None else _c(data.Aw),
        _NO_VECTOR if data.bw is None else _c(data.bw),
        _no_rows(n) if data.H is None else _c(data.H),
        _NO_VECTOR if data.g is None else _c(data.g),
        _no_rows(n) if data.C is None else _c(data.C),
        _NO_VECTOR if data.l is None else _c(data.l),
        _NO_VECTOR if data.u is None else _c(data.u),
        ns,
        1.0 / math.sqrt(2.0 * data.rho) if ns and data.rho is not None else 0.0,  # (ns > 0: rho is set)
    )
