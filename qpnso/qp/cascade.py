"""The null-space cascade's arithmetic: one level's QP, what it owns and passes down (docs/method.md §7.5).

**Null-space form** (not the fragile equality form, docs/qp-notes.md): level ``k``
moves the answer of the levels above only inside the directions that no higher
level owns, through an orthonormal basis ``Z_k`` (n×r) of them:
``x = x_{k−1} + Z_k z``.  The answer is always formed through ``Z_k``, so a
higher task's residual is preserved by construction, whatever the solver's
tolerance.  Each level's QP (:class:`LevelQP`, variable ``z`` ∈ Rʳ plus one
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
(:mod:`qpnso.qp.line`) shares.  The per-tick arithmetic is in Numba kernels
(:func:`level_qp_arrays`, :func:`level_answer`); :class:`~qpnso.qp.solver.HierarchicalQP` runs the
cascade level after level.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from qpnso.linalg import matmul, matvec
from qpnso.qp.arrays import Basis, Inherited, LevelParts, QPArrays, qp_data_finite
from qpnso.qp.levels import Level, _LevelData, _validate_level
from qpnso.qp.settings import QPSettings, tolerance_record

__all__ = ["Cascade", "LevelQP", "advance_cascade", "build_level_qp"]


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


@dataclass(slots=True)
class Cascade:
    """What the higher levels leave to the next one.

    ``x`` (n,) their solution (rad/s); ``Z`` (n, r) an orthonormal basis of the
    directions they leave free (``full``: ``Z`` is the identity, nothing taken
    yet); ``lb``/``ub`` the bounds and ``C``/``l``/``u`` the inherited rows,
    widened to contain ``x`` (see module docstring).
    """

    x: np.ndarray
    Z: np.ndarray
    lb: np.ndarray
    ub: np.ndarray
    C: np.ndarray
    l: np.ndarray
    u: np.ndarray
    depth: int = 0  # number of levels already solved
    full: bool = True  # Z is the n×n identity

    @property
    def N(self) -> np.ndarray:
        """The n×n orthogonal projector ``Z Zᵀ`` onto the free directions."""
        return self.Z @ self.Z.T

    @classmethod
    def start(cls, lb: np.ndarray, ub: np.ndarray) -> "Cascade":
        n = lb.shape[0]
        return cls(np.zeros(n), _eye(n), lb, ub, np.zeros((0, n)), np.zeros(0), np.zeros(0))


@dataclass(slots=True)
class LevelQP:
    """The QP of one level in ``v = [z; σ]`` (r + n_slack), ``x = x_prev + Z z`` (rad/s):

    ``min ½ vᵀ H v + gᵀ v``  s.t.  ``l ≤ C v ≤ u`` and, if ``box_l`` is not None,
    ``box_l ≤ v ≤ box_u``.  Rows of ``C``, in this order: the inherited rows, the
    level's own rows (its soft rows get ``+ σ/√(2ρ)``; the scaled slack
    ``σ = √(2ρ)·s`` has unit curvature), then — when ``Z`` is not the identity —
    the bounds as the n rows ``Z z`` (``bound_rows`` of them).  When ``Z`` is the
    identity the bounds are a box on ``z`` (∓inf on σ) instead.  No equality
    constraints: the null-space form is exact by construction.
    ``owned_z`` (r, k) / ``free_z`` (r, r − k): orthonormal bases, in z, of the
    task directions the level takes and of those it leaves (``free_z`` None: the
    level has no task, all r are free).
    """

    H: np.ndarray
    g: np.ndarray
    C: np.ndarray
    l: np.ndarray
    u: np.ndarray
    box_l: np.ndarray | None
    box_u: np.ndarray | None
    x_prev: np.ndarray
    Z: np.ndarray
    owned_z: np.ndarray
    free_z: np.ndarray | None
    n_slack: int
    slack_start: int  # first soft row of C
    bound_rows: int  # n if the bounds are the last rows of C, else 0
    finite: bool = True  # the data can be solved (qp_data_finite): nothing that is not finite but ±inf bounds

    @property
    def r(self) -> int:
        """Number of free directions (variables before the slacks)."""
        return self.Z.shape[1]

    @property
    def owned(self) -> np.ndarray:
        """The owned task directions in joint coordinates (n, k)."""
        return self.Z @ self.owned_z

    def d_of(self, v: np.ndarray) -> np.ndarray:
        """``x − x_prev = Z z`` (rad/s) of a QP solution ``v``."""
        return self.Z @ v[: self.r]

    def x_of(self, v: np.ndarray) -> np.ndarray:
        """Joint velocity (rad/s) of a QP solution ``v``."""
        return self.x_prev + self.d_of(v)

    @property
    def arrays(self) -> QPArrays:
        """The QP as the back ends and kernels take it (no box: empty box arrays)."""
        box = self.box_l is not None and self.box_u is not None
        return QPArrays(
            self.H,
            self.g,
            self.C,
            self.l,
            self.u,
            self.box_l if box else _NO_VECTOR,  # type: ignore[arg-type]
            self.box_u if box else _NO_VECTOR,  # type: ignore[arg-type]
        )

    def rows_with_box(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All constraints as rows ``l ≤ C v ≤ u``: the finite box entries appended as
        unit rows (for back ends without a native box); no box: ``C, l, u`` as they are."""
        if self.box_l is None:
            return self.C, self.l, self.u
        assert self.box_u is not None  # a box has both sides
        keep = np.isfinite(self.box_l) | np.isfinite(self.box_u)
        unit = _eye(self.H.shape[0])[keep]
        return (
            np.vstack([self.C, unit]),
            np.concatenate([self.l, self.box_l[keep]]),
            np.concatenate([self.u, self.box_u[keep]]),
        )


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
    and the level reports it: :attr:`LevelQP.finite`)."""
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
    """The arrays of :func:`build_level_qp`: ``level`` the level's :class:`~qpnso.qp.arrays.LevelParts`,
    ``basis`` and ``inherited`` what the levels above leave (:class:`~qpnso.qp.arrays.Basis`,
    :class:`~qpnso.qp.arrays.Inherited`), ``tol`` the tolerances (:func:`qpnso.qp.settings.tolerance_record`);
    the task's SVD is :func:`task_svd`'s.

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


def build_level_qp(
    level: Level | _LevelData, cascade: Cascade, settings: QPSettings = QPSettings(), tol: np.ndarray | None = None
) -> LevelQP:
    """The QP of ``level`` in the free coordinates ``z`` (``x = x_prev + Z z``); pure.

    Hessian: ``Zᵀ(2AᵀWA + H)Z`` (task part damped, module docstring) ``+ μ`` on
    the free directions the task leaves; slack block ``I``.  Rows: inherited and
    own rows in z, then the bounds ``Z z`` unless ``Z`` is the identity (box).
    The arithmetic, the task's SVD included, is one kernel, :func:`level_qp_arrays`.  ``tol``:
    ``settings``' :func:`~qpnso.qp.settings.tolerance_record`, if the caller holds it already.
    """
    n = cascade.x.shape[0]
    data = level if isinstance(level, _LevelData) else _validate_level(level, n, "level")
    ns = data.n_slack
    qp, has_box, owned_z, free_z, has_task, finite = level_qp_arrays(
        level_parts(data, n),
        Basis(_c(cascade.x), _c(cascade.Z), cascade.full, cascade.depth > 0),
        Inherited(_c(cascade.lb), _c(cascade.ub), _c(cascade.C), _c(cascade.l), _c(cascade.u)),
        tolerance_record(settings) if tol is None else tol,
    )
    H, g, C, lo, hi, box_l, box_u = qp
    return LevelQP(
        H,
        g,
        C,
        lo,
        hi,
        box_l if has_box else None,
        box_u if has_box else None,
        cascade.x,
        cascade.Z,
        owned_z,
        free_z if has_task else None,
        ns,
        cascade.C.shape[0],
        0 if cascade.full else n,
        finite,
    )


def _objective_gradient(data: _LevelData, x: np.ndarray) -> np.ndarray | None:
    """∇ₓ of the level's x-cost ``‖W^½(Ax − b)‖² + ½xᵀHx + gᵀx`` at ``x`` (no slack part)."""
    grad = None
    if data.Aw is not None:
        grad = 2.0 * (data.Aw.T @ (data.Aw @ x - data.bw))
    if data.H is not None:
        grad = data.H @ x if grad is None else grad + data.H @ x
    if data.g is not None:
        grad = data.g if grad is None else grad + data.g
    return grad


def strictly_convex(qp: LevelQP, rank_tol: float) -> bool:
    """Whether the level's QP has a single optimum: its Hessian in z positive definite, every
    eigenvalue above ``rank_tol·max(1, λ_max)`` (the test :func:`advance_cascade` applies to what a level
    owns), so that the cascade below it would have no free direction left."""
    r = qp.r
    if r == 0:
        return True
    if r == 1:  # the usual last level (one self-motion direction): its curvature
        return bool(qp.H[0, 0] > rank_tol * max(1.0, float(qp.H[0, 0])))
    eig = np.linalg.eigvalsh(qp.H[:r, :r])
    return bool(eig[0] > rank_tol * max(1.0, float(eig[-1])))


def _fix_signs(Z: np.ndarray) -> np.ndarray:
    """``Z`` with each column's largest-magnitude entry positive (the SVD's sign is
    arbitrary; a stable sign keeps the previous tick's ``z`` a good warm start)."""
    r = Z.shape[1]
    if r == 1:  # the usual case (7-DOF arm, 6-D task): one self-motion direction
        return -Z if Z[int(np.abs(Z[:, 0]).argmax()), 0] < 0.0 else Z
    if r == 0:
        return Z
    flip = Z[np.abs(Z).argmax(axis=0), range(r)] < 0.0
    if not flip.any():
        return Z
    Z = Z.copy()
    Z[:, flip] *= -1.0
    return Z


def advance_cascade(
    level: Level | _LevelData, cascade: Cascade, qp: LevelQP, x: np.ndarray, settings: QPSettings = QPSettings()
) -> Cascade:
    """The cascade after ``level`` (whose QP is ``qp``) was solved with joint velocity ``x``.

    Removes from the free basis the directions the level owns (module
    docstring, items 1–3; all r×r work in z) and passes its constraints down,
    widened to contain ``x``.
    """
    n = x.shape[0]
    data = level if isinstance(level, _LevelData) else _validate_level(level, n, "level")
    Z, full = cascade.Z, cascade.full
    B = None  # orthonormal basis, in the current coordinates, of what stays free; None = all
    if qp.free_z is not None and qp.free_z.shape[1] < Z.shape[1]:
        B = qp.free_z
    if data.H is not None:
        M = Z.T @ data.H @ Z if full is False else data.H
        if B is not None:
            M = B.T @ M @ B
        if M.shape[0]:
            eigval, eigvec = np.linalg.eigh(0.5 * (M + M.T))
            big = eigval > settings.rank_tol * max(1.0, float(np.abs(eigval).max()))
            if big.any():
                B = eigvec[:, ~big] if B is None else B @ eigvec[:, ~big]
    grad = _objective_gradient(data, x) if data.H is not None or data.g is not None else None
    if grad is not None:  # (a pure task's gradient lies in its owned range already)
        p = grad if full else Z.T @ grad
        if B is not None:
            p = B.T @ p
        norm_p = float(np.linalg.norm(p))
        if p.shape[0] and norm_p > settings.gradient_tol * max(1.0, float(np.linalg.norm(grad))):
            Q = np.linalg.qr((p / norm_p)[:, None], mode="complete")[0][:, 1:]  # complement of p
            B = Q if B is None else B @ Q
    if B is not None:
        Z, full = _fix_signs(B if full else Z @ B), False
    C, l, u = cascade.C, cascade.l, cascade.u
    if data.C is not None:
        assert data.l is not None and data.u is not None  # rows come with both sides
        if C.shape[0]:
            C, l, u = np.vstack([C, data.C]), np.concatenate([l, data.l]), np.concatenate([u, data.u])
        else:
            C, l, u = data.C, data.l, data.u
    tol = settings.active_tol
    if C.shape[0]:
        l, u = _pass_down(l, C @ x, u, tol)
    lb, ub = _pass_down(cascade.lb, x, cascade.ub, tol)
    return Cascade(x=x, Z=Z, lb=lb, ub=ub, C=C, l=l, u=u, depth=cascade.depth + 1, full=full)


def _pass_down(lo: np.ndarray, value: np.ndarray, hi: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Interval a lower level inherits: widened to contain ``value`` (a violation never
    grows), and a side within ``tol`` of ``value`` moved onto it (exactly active), so an
    inexact solver's answer a hair inside a bound does not leave a sliver of a feasible set."""
    return np.where(value - lo < tol, value, lo), np.where(hi - value < tol, value, hi)


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
