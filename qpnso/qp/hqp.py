"""Hierarchical (lexicographic) QP over joint velocities, solved every tick (docs/method.md §7).

A cascade of levels over ``x`` ∈ Rⁿ (joint velocities, rad/s).  Level ``k``
minimises its objective over the optimal set of levels ``0 … k−1``; the hard
bounds ``lb ≤ x ≤ ub`` hold on every level.  One level may combine

* an equality task ``weight · ‖A x − b‖²`` (least squares, damped near
  singularities),
* a quadratic objective ``½ xᵀ H x + gᵀ x`` (``H`` symmetric positive
  semi-definite),
* inequalities ``l ≤ C x ≤ u``, hard, or soft with a free slack ``s`` per row
  (``l ≤ C x + s ≤ u``, cost ``slack_weight · ‖s‖²``) so that an unreachable
  elbow constraint never makes the QP infeasible.

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
previous tick's ``z`` stays a good warm start.  Measured on the controller's
problem (7-DOF, 6×7 J, soft elbow row, tight bounds), against the earlier
projector form with n equality rows ``(I − N) d = 0``: median 281 → 199 µs per
solve, 146 µs with ``solve(check=False)`` (2-core machine, interleaved runs).

**Line fast path** (``QPSettings.line_fast_path``, on by default): the
controller's first level is a plain task of n − 1 rows (6×7 tool Jacobian).
When all its singular values reach the damping threshold (nothing to damp),
its exact solutions form the line ``A⁺b + t·d`` (``d`` its unit null vector)
and, when that line meets the bounds, the level's optimal set is exactly the
segment ``t ∈ [t_lo, t_hi]`` (zero residual).  Level 1 is then known in closed
form (its reported answer: the segment's least-norm point) and level 2 is a QP
in ``t`` (plus its slacks) with the bounds as a box on ``t`` — the same QP that
:func:`build_level_qp` builds with ``Z = d``, solved by the same back end
(ProxSuite, persistent and warm-started).  Whenever a bound cuts the line (the
bounds bind the tool task), the task is near-singular, or there are more than
two levels, the general cascade below runs.  The small factorisations are
Numba kernels (:mod:`qpnso.linalg`).  Same answers as the general cascade
(tests); on 300 recorded controller ticks (``solve(check=False)``, interleaved
runs) 77–95 µs median per solve against 195–223 µs for the general cascade.
Level 2 on the line is :meth:`HierarchicalQP.solve_line_level`
(:meth:`~HierarchicalQP.line_level_raw`, then :meth:`~HierarchicalQP.line_level_result`); the
controller's compiled tick (:mod:`qpnso.control.tick`) builds its arrays in one kernel,
calls ``line_level_raw`` and judges the answer with the same kernel
(:func:`checked_line_answer`) in its own.

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
"""

from __future__ import annotations

import enum
import functools
import math
import time
from dataclasses import dataclass, field, replace
from typing import Sequence

import daqp
import numpy as np
from numba import njit
from scipy.linalg import lapack as _lapack

from qpnso.errors import ConfigError, InputError, SolverError
from qpnso.linalg import dot, least_norm_line, matmul, matvec

__all__ = [
    "Cascade",
    "HQPResult",
    "HQPStats",
    "HierarchicalQP",
    "Level",
    "LevelQP",
    "LevelResult",
    "LevelStatus",
    "QPSettings",
    "advance_cascade",
    "build_level_qp",
]

NATIVE_BACKEND = "proxsuite"


# ----------------------------------------------------------------- settings
@dataclass(frozen=True)
class QPSettings:
    """Tolerances of the cascade and of its QP back ends.

    ``eps_abs``/``eps_rel``/``eps_primal_inf``/``eps_dual_inf``/``max_iter``
    are ProxQP's (the defaults 1e-5/0/1e-4 are too loose for 1 ms velocity
    steps: a warm start can stop after zero iterations, see docs/qp-notes.md).
    ``solver_options`` are passed verbatim to ``qpsolvers.solve_problem``.
    """

    eps_abs: float = 1e-11
    eps_rel: float = 0.0
    eps_primal_inf: float = 1e-12
    eps_dual_inf: float = 1e-12
    max_iter: int = 5  # ProxQP's outer iterations per attempt (a tick's QP needs 2–13 inner ones in all, measured)
    max_iter_in: int = 5  # ProxQP's inner iterations per outer one: an attempt is at most ~30 iterations, then DAQP
    max_iter_active_set: int = 1000  # DAQP's iterations in the fallback (a tick's QP needs 2–10, measured)
    mu_in: float = 1e-3  # ProxQP default_mu_in: its 0.1 took 3.5 warm iterations per controller tick, 1e-3 took 2.2
    warm_start: bool = True  # ProxSuite: WARM_START_WITH_PREVIOUS_RESULT every tick
    box_constraints: bool = True  # ProxSuite: bounds as its native box (else as rows)
    regularization: float | None = None  # μ on the directions a task leaves free; None: 0 for
    # native ProxSuite (its proximal method handles a semi-definite H), 1e-7 for qpsolvers back ends
    rank_tol: float = 1e-10  # relative singular value below which a direction is null
    damping_threshold: float = 1e-2  # ε, units of A (m/rad, rad/rad); 0 disables damping
    gradient_tol: float = 1e-7  # relative size of a projected gradient that a level owns
    feasibility_tol: float = 1e-6  # accepted violation of bounds / hard rows (units of the row)
    active_tol: float = 1e-7  # a higher level's bound/row this close to its answer is active below
    line_fast_path: bool = True  # a full-rank (n−1)-row first task: its exact solutions form a line (module doc)
    active_set_fallback: bool = True  # a failed ProxQP solve is handed to DAQP (active set, exact)
    active_set_hold: int = 100  # after a fallback, DAQP alone answers that QP's next solves (0: ProxQP every time)
    solver_options: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        """Types first (:func:`qpnso.settings.check`), then ranges."""
        from qpnso.settings import check, out_of_range

        check(self)
        if self.regularization is not None and self.regularization < 0:
            raise out_of_range(self, "regularization", "must be >= 0 or None")
        for name in ("eps_abs", "eps_rel", "eps_primal_inf", "eps_dual_inf", "mu_in",
                     "rank_tol", "damping_threshold", "gradient_tol", "feasibility_tol", "active_tol"):
            if getattr(self, name) < 0:
                raise out_of_range(self, name, "must be >= 0")
        for name in ("max_iter", "max_iter_in", "max_iter_active_set"):
            if getattr(self, name) <= 0:
                raise out_of_range(self, name, "must be > 0")
        if self.active_set_hold < 0:
            raise out_of_range(self, "active_set_hold", "must be >= 0")

    @classmethod
    def from_dict(cls, values: dict, where: str = "") -> "QPSettings":
        """Build from plain data (a ``[qp_settings]`` table); unknown keys are listed with the valid ones."""
        from qpnso.settings import from_dict

        return from_dict(cls, values, where)


# -------------------------------------------------------------------- levels
@dataclass
class Level:
    """One priority level (see the module docstring for the cost).

    ``weight`` is a scalar or one non-negative weight per row of ``A``.
    ``slack_weight=None`` makes ``l ≤ C x ≤ u`` hard; a positive value makes it
    soft with cost ``slack_weight·‖s‖²``.  ``l``/``u`` may hold ∓inf.
    """

    A: np.ndarray | None = None
    b: np.ndarray | None = None
    weight: float | np.ndarray = 1.0
    H: np.ndarray | None = None
    g: np.ndarray | None = None
    C: np.ndarray | None = None
    l: np.ndarray | None = None
    u: np.ndarray | None = None
    slack_weight: float | None = None
    name: str = ""


@dataclass(slots=True)
class _LevelData:
    """A validated level: float arrays, weights folded into the task."""

    A: np.ndarray | None  # (m, n) raw, for the reported residual
    b: np.ndarray | None
    Aw: np.ndarray | None  # W^½ A
    bw: np.ndarray | None  # W^½ b
    H: np.ndarray | None
    g: np.ndarray | None
    C: np.ndarray | None
    l: np.ndarray | None
    u: np.ndarray | None
    rho: float | None  # slack weight, None = hard rows

    @property
    def n_slack(self) -> int:
        return 0 if self.C is None or self.rho is None else self.C.shape[0]


def _array(value: object, name: str, ndim: int, allow_inf: bool = False) -> np.ndarray:
    """``value`` as a float array of ``ndim`` dimensions without NaN/inf; ``allow_inf``: an interval
    side, checked (NaN included) by :func:`_check_interval`, which must follow."""
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a numeric array, got {type(value).__name__}") from None
    if arr.ndim != ndim:
        raise InputError(f"{name} must be {ndim}-D, got shape {arr.shape}")
    if allow_inf:
        return arr
    total = float(np.add.reduce(arr, axis=None))  # one reduction: finite sum <=> no NaN/inf (overflow → detailed check)
    if total - total != 0.0:
        if np.isnan(arr).any():
            raise InputError(f"{name} contains NaN")
        if np.isinf(arr).any():
            raise InputError(f"{name} contains inf")
    return arr


def _check_shape(arr: np.ndarray, shape: tuple, name: str) -> None:
    if arr.shape != shape:
        raise InputError(f"{name} has shape {arr.shape}, expected {shape}")


def _check_interval(lo: np.ndarray, hi: np.ndarray, lo_name: str, hi_name: str) -> None:
    if not (hi - lo >= 0.0).all():  # False for NaN, lo > hi, and lo = hi = ±inf (a side on the wrong side)
        for arr, name in ((lo, lo_name), (hi, hi_name)):
            if np.isnan(arr).any():
                raise InputError(f"{name} contains NaN")
        bad = ~(lo <= hi) | np.isposinf(lo) | np.isneginf(hi)
        i = int(np.argmax(bad))
        raise InputError(f"{lo_name}[{i}] = {float(lo[i])!r} > {hi_name}[{i}] = {float(hi[i])!r}, or an infinite bound "
                         f"on the wrong side")


def _validate_level(level: Level, n: int, name: str) -> _LevelData:
    """Shape/NaN/interval checks of one level; raises :class:`InputError` naming the field.

    Only the symmetric part of ``H`` matters (``xᵀHx = xᵀ½(H + Hᵀ)x``), so it is used.
    """
    if not isinstance(level, Level):
        raise InputError(f"{name} must be a Level, got {type(level).__name__}")
    if level.A is None and level.H is None and level.g is None and level.C is None:
        raise InputError(f"{name} is empty: give A/b, H/g or C/l/u")
    A = b = Aw = bw = None
    if (level.A is None) != (level.b is None):
        raise InputError(f"{name}: A and b go together")
    if level.A is not None:
        A = _array(level.A, f"{name}.A", 2)
        if A.shape[1] != n or A.shape[0] == 0:
            raise InputError(f"{name}.A has shape {A.shape}, expected (m >= 1, {n})")
        b = _array(level.b, f"{name}.b", 1)
        _check_shape(b, (A.shape[0],), f"{name}.b")
        Aw, bw = A, b
        if not (isinstance(level.weight, (int, float)) and level.weight == 1):
            w = _array(level.weight, f"{name}.weight", np.ndim(level.weight))
            if w.ndim > 1 or (w.ndim == 1 and w.shape != (A.shape[0],)) or (w < 0).any():
                raise InputError(f"{name}.weight must be a scalar or ({A.shape[0]},) array, all >= 0")
            sw = np.sqrt(w)
            Aw, bw = (sw * A.T).T if w.ndim else sw * A, sw * b
    H = g = None
    if level.H is not None:
        H = _array(level.H, f"{name}.H", 2)
        _check_shape(H, (n, n), f"{name}.H")
        H = 0.5 * (H + H.T)
    if level.g is not None:
        g = _array(level.g, f"{name}.g", 1)
        _check_shape(g, (n,), f"{name}.g")
    C = l = u = rho = None
    if level.C is not None:
        C = _array(level.C, f"{name}.C", 2)
        if C.shape[1] != n or C.shape[0] == 0:
            raise InputError(f"{name}.C has shape {C.shape}, expected (p >= 1, {n})")
        if level.l is None or level.u is None:
            raise InputError(f"{name}: C needs both l and u (use -inf/inf for a one-sided row)")
        l = _array(level.l, f"{name}.l", 1, allow_inf=True)
        u = _array(level.u, f"{name}.u", 1, allow_inf=True)
        _check_shape(l, (C.shape[0],), f"{name}.l")
        _check_shape(u, (C.shape[0],), f"{name}.u")
        _check_interval(l, u, f"{name}.l", f"{name}.u")
        if level.slack_weight is not None:
            rho = float(level.slack_weight)
            if not (np.isfinite(rho) and rho > 0):
                raise InputError(f"{name}.slack_weight must be > 0 and finite (or None for hard rows)")
    elif level.l is not None or level.u is not None:
        raise InputError(f"{name}: l/u given without C")
    return _LevelData(A, b, Aw, bw, H, g, C, l, u, rho)


def _trusted_level(level: Level) -> _LevelData:
    """A level taken as given (``solve(check=False)``): float arrays of the right shapes
    assumed, only the weight folded in and ``H`` symmetrised, as in :func:`_validate_level`."""
    f = np.asarray
    A = None if level.A is None else f(level.A, dtype=float)
    b = None if level.b is None else f(level.b, dtype=float)
    Aw, bw = A, b
    if A is not None and not (isinstance(level.weight, (int, float)) and level.weight == 1):
        sw = np.sqrt(f(level.weight, dtype=float))
        Aw, bw = (sw * A.T).T if sw.ndim else sw * A, sw * b
    H = None if level.H is None else f(level.H, dtype=float)
    if H is not None:
        H = 0.5 * (H + H.T)
    C = None if level.C is None else f(level.C, dtype=float)
    rho = None if C is None or level.slack_weight is None else float(level.slack_weight)
    return _LevelData(A, b, Aw, bw, H, None if level.g is None else f(level.g, dtype=float), C,
                      None if C is None else f(level.l, dtype=float),
                      None if C is None else f(level.u, dtype=float), rho)


def _validate_bounds(lb: object, ub: object, n: int) -> tuple[np.ndarray, np.ndarray]:
    lo = np.full(n, -np.inf) if lb is None else _array(lb, "lb", 1, allow_inf=True)
    hi = np.full(n, np.inf) if ub is None else _array(ub, "ub", 1, allow_inf=True)
    _check_shape(lo, (n,), "lb")
    _check_shape(hi, (n,), "ub")
    _check_interval(lo, hi, "lb", "ub")
    return lo, hi


# ------------------------------------------------------------------ cascade
@functools.lru_cache(maxsize=16)
def _eye(n: int) -> np.ndarray:
    """A read-only n×n identity (cached: this is on the per-tick path)."""
    eye = np.eye(n)
    eye.flags.writeable = False
    return eye


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
        return self.Z @ v[:self.r]

    def x_of(self, v: np.ndarray) -> np.ndarray:
        """Joint velocity (rad/s) of a QP solution ``v``."""
        return self.x_prev + self.d_of(v)

    def rows_with_box(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All constraints as rows ``l ≤ C v ≤ u``: the finite box entries appended as
        unit rows (for back ends without a native box); no box: ``C, l, u`` as they are."""
        if self.box_l is None:
            return self.C, self.l, self.u
        keep = np.isfinite(self.box_l) | np.isfinite(self.box_u)
        unit = _eye(self.H.shape[0])[keep]
        return (np.vstack([self.C, unit]), np.concatenate([self.l, self.box_l[keep]]),
                np.concatenate([self.u, self.box_u[keep]]))


def _task_svd(data: _LevelData, cascade: Cascade) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The level's weighted task in z, ``W^½ A Z`` (m, r), its singular values and right singular
    vectors ``Vᵀ`` (r, r), and its residual at the higher levels' answer ``W^½(A x_prev − b)``;
    empty arrays without a task or free direction."""
    Z, r = cascade.Z, cascade.Z.shape[1]
    if data.Aw is None or r == 0:
        return _no_rows(r), _NO_VECTOR, np.zeros((r, r)), _NO_VECTOR
    At = data.Aw if cascade.full else data.Aw @ Z
    r0 = -data.bw if cascade.depth == 0 else data.Aw @ cascade.x - data.bw
    _, sigma, vt, info = _lapack.dgesdd(At, compute_uv=1, full_matrices=1)  # np.linalg.svd, less overhead
    if info != 0:
        _, sigma, vt = np.linalg.svd(At, full_matrices=True)
    return _c(At), sigma, _c(vt), _c(r0)


def _c(a: np.ndarray) -> np.ndarray:
    """``a`` as a writable C-contiguous float array: the one array type the kernels are compiled for
    (another layout or a read-only array is another Numba signature, compiled in the tick that meets it)."""
    return a if a.flags.c_contiguous and a.flags.writeable else np.array(a, dtype=float, order="C")


@njit(cache=True)
def level_qp_arrays(At, sigma, vt, r0, H, g, C, l, u, n_slack, slack_scale, Z, full, x_prev, moved,  # type: ignore[no-untyped-def]
                    lb, ub, C_inh, l_inh, u_inh, reg, rank_tol, damping):
    """The arrays of :func:`build_level_qp` (absent level parts passed with zero rows; ``At`` the task
    in z with its SVD ``sigma``, ``vt``, and ``r0`` its residual at ``x_prev``, from :func:`_task_svd`).

    Returns ``H, g, C, l, u, box_l, box_u, has_box, owned_z, free_z, has_task``."""
    n, r = x_prev.shape[0], Z.shape[1]
    ns = n_slack
    nv = r + ns
    Hv = np.zeros((nv, nv))
    gv = np.zeros(nv)
    k = 0
    has_task = At.shape[0] > 0 and r > 0
    if has_task:  # damped least squares (module docstring): owned directions σ > rank_tol·max(1, σ_max)
        threshold = rank_tol * max(1.0, sigma[0])
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
    p_inh, p_own = C_inh.shape[0], C.shape[0]
    nb = 0 if full else n
    m = p_inh + p_own + nb
    Cv = np.zeros((m, nv))
    lo, hi = np.empty(m), np.empty(m)
    for start, Cp, lp, up in ((0, C_inh, l_inh, u_inh), (p_inh, C, l, u)):
        p = Cp.shape[0]
        if p:
            Cv[start:start + p, :r] = Cp if full else matmul(Cp, Z)
            cx = matvec(Cp, x_prev) if moved else np.zeros(p)
            lo[start:start + p] = lp - cx
            hi[start:start + p] = up - cx
    for i in range(ns):
        Cv[p_inh + i, r + i] = slack_scale
    has_box = nb == 0
    box_l, box_u = np.full(nv, -np.inf), np.full(nv, np.inf)
    if nb:
        Cv[m - n:, :r] = Z
        lo[m - n:] = lb - x_prev
        hi[m - n:] = ub - x_prev
    else:  # Z the identity: the bounds as a box on z (free slacks)
        box_l[:n] = lb - x_prev
        box_u[:n] = ub - x_prev
    return Hv, gv, Cv, lo, hi, box_l, box_u, has_box, owned_z, free_z, has_task


def build_level_qp(level: Level | _LevelData, cascade: Cascade, settings: QPSettings = QPSettings()) -> LevelQP:
    """The QP of ``level`` in the free coordinates ``z`` (``x = x_prev + Z z``); pure.

    Hessian: ``Zᵀ(2AᵀWA + H)Z`` (task part damped, module docstring) ``+ μ`` on
    the free directions the task leaves; slack block ``I``.  Rows: inherited and
    own rows in z, then the bounds ``Z z`` unless ``Z`` is the identity (box).
    The arithmetic is one kernel, :func:`level_qp_arrays`, after the task's SVD (:func:`_task_svd`).
    """
    n = cascade.x.shape[0]
    data = level if isinstance(level, _LevelData) else _validate_level(level, n, "level")
    ns = data.n_slack
    At, sigma, vt, r0 = _task_svd(data, cascade)
    H, g, C, lo, hi, box_l, box_u, has_box, owned_z, free_z, has_task = level_qp_arrays(
        At, sigma, vt, r0,
        _no_rows(n) if data.H is None else _c(data.H), _NO_VECTOR if data.g is None else _c(data.g),
        _no_rows(n) if data.C is None else _c(data.C), _NO_VECTOR if data.l is None else _c(data.l),
        _NO_VECTOR if data.u is None else _c(data.u), ns, 1.0 / math.sqrt(2.0 * data.rho) if ns else 0.0,
        _c(cascade.Z), cascade.full, _c(cascade.x), cascade.depth > 0, _c(cascade.lb), _c(cascade.ub),
        _c(cascade.C), _c(cascade.l), _c(cascade.u), settings.regularization or 0.0, settings.rank_tol,
        settings.damping_threshold)
    return LevelQP(H, g, C, lo, hi, box_l if has_box else None, box_u if has_box else None, cascade.x, cascade.Z,
                   owned_z, free_z if has_task else None, ns, cascade.C.shape[0], 0 if cascade.full else n)


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
    flip = Z[np.abs(Z).argmax(axis=0), range(r)] < 0.0 if r else None
    if r == 0 or not flip.any():
        return Z
    Z = Z.copy()
    Z[:, flip] *= -1.0
    return Z


def advance_cascade(level: Level | _LevelData, cascade: Cascade, qp: LevelQP, x: np.ndarray,
                    settings: QPSettings = QPSettings()) -> Cascade:
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


def _violation(lo: np.ndarray, value: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Per-row distance of ``value`` outside ``[lo, hi]`` (0 inside)."""
    return np.maximum(np.maximum(lo - value, value - hi), 0.0)


# ------------------------------------------------------------ line fast path
_OWNED_1 = np.ones((1, 1))
_OWNED_0 = np.zeros((1, 0))
_NO_VECTOR = np.zeros(0)


@functools.lru_cache(maxsize=16)
def _no_rows(n: int) -> np.ndarray:
    """A (0, n) array: an absent matrix part passed to a kernel (cached, any width).  Writable like every
    other array the kernels get: a read-only one is another Numba type, compiled (seconds) in the first
    tick that takes a rare path (the general path's line level with the elbow dropped did, in the fuzz)."""
    return np.zeros((0, n))


@dataclass(slots=True)
class _Line:
    """The optimal set of a plain first task of full rank n − 1 whose exact solutions
    meet the bounds: ``x0 + t·direction`` (rad/s), ``t ∈ [t_lo, t_hi]``, with
    ``x0 = A⁺b`` and ``direction`` the unit null vector of ``A`` (sign fixed)."""

    x0: np.ndarray
    direction: np.ndarray
    t_lo: float
    t_hi: float


@njit(cache=True)
def line_segment(x0, d, lb, ub):  # type: ignore[no-untyped-def]
    """``[t_lo, t_hi]`` where ``lb ≤ x0 + t·d ≤ ub`` (empty: ``t_lo > t_hi``); ``d`` made to have its
    largest-magnitude entry positive first.  A still joint (|d_i| ≤ 1e-12: the elbow of an S-R-S
    arm) must be within its bounds at ``x0``."""
    n = d.shape[0]
    big = np.argmax(np.abs(d))
    if d[big] < 0.0:
        d *= -1.0
    t_lo, t_hi = -np.inf, np.inf
    for i in range(n):
        if abs(d[i]) > 1e-12:
            a, c = (lb[i] - x0[i]) / d[i], (ub[i] - x0[i]) / d[i]
            t_lo, t_hi = max(t_lo, min(a, c)), min(t_hi, max(a, c))
        elif x0[i] < lb[i] or x0[i] > ub[i]:
            return 1.0, 0.0
    return t_lo, t_hi


LINE_OK = 0
LINE_SINGULAR = 1  # a singular value may be below the damping threshold: no line (damped cascade)
LINE_CUT = 2  # the bounds miss the line of exact solutions (a bound binds the task: the QP decides)


@njit(cache=True)
def task_line(A, b, lb, ub, rank_tol, damping):  # type: ignore[no-untyped-def]
    """``(code, x0, d, t_lo, t_hi)``: the exact solutions ``x0 + t·d``, ``t ∈ [t_lo, t_hi]``, of a
    plain (n−1)×n task ``A x = b`` within ``lb ≤ x ≤ ub`` (module docstring, *line fast path*);
    ``code`` :data:`LINE_SINGULAR` when ``σ_min`` may be below ``damping`` (``1/‖R⁻¹‖_F ≤ σ_min`` is
    the test: conservative by at most √(n−1)), :data:`LINE_CUT` when the bounds miss the line."""
    x0, d, sigma_floor = least_norm_line(A, b)
    if not sigma_floor >= max(damping, rank_tol * max(1.0, math.sqrt(np.sum(A * A)))):
        return LINE_SINGULAR, x0, d, 0.0, 0.0
    t_lo, t_hi = line_segment(x0, d, lb, ub)
    return (LINE_OK if t_lo <= t_hi else LINE_CUT), x0, d, t_lo, t_hi


@njit(cache=True)
def least_norm_point(x0, d, t_lo, t_hi):  # type: ignore[no-untyped-def]
    """The least-norm point of the segment ``x0 + t·d``, ``t ∈ [t_lo, t_hi]`` (``x0 ⊥ d``): level 1's answer."""
    return x0 + min(max(0.0, t_lo), t_hi) * d


def _task_line(data: _LevelData, lb: np.ndarray, ub: np.ndarray, settings: QPSettings) -> _Line | None:
    """Level 1 in closed form (:func:`task_line`), or None when it does not apply: not a plain task
    of n − 1 rows, a singular value that may be below the damping threshold, or bounds that miss the line."""
    Aw = data.Aw
    if Aw is None or data.H is not None or data.g is not None or data.C is not None \
            or Aw.shape[0] != Aw.shape[1] - 1:
        return None
    code, x0, d, t_lo, t_hi = task_line(Aw, data.bw, lb, ub, settings.rank_tol, settings.damping_threshold)
    return _Line(x0, d, t_lo, t_hi) if code == LINE_OK else None


@njit(cache=True)
def line_qp_arrays(d, x0, t_lo, t_hi, A, b, H, g, C, l, u, n_slack, slack_scale, reg, rank_tol, damping):  # type: ignore[no-untyped-def]
    """The arrays of :func:`_line_level_qp` (absent level parts passed with zero rows).

    Cost ``‖A x − b‖² + ½xᵀHx + gᵀx`` at ``x = x0 + t·d``: curvature and slope in ``t``
    with the damping and tie-break of :func:`level_qp_arrays` / :func:`build_level_qp` in one
    dimension; rows ``l − C x0 ≤ (C d) t + slack_scale·σ ≤ u − C x0``; box ``[t_lo, t_hi]`` on
    ``t``, free slacks.  Returns ``H, g, C, l, u, box_l, box_u`` and whether the task owns ``d``."""
    curvature, slope, owned = 0.0, 0.0, False
    if A.shape[0]:
        ad = matvec(A, d)
        s2 = dot(ad, ad)
        slope += 2.0 * dot(ad, matvec(A, x0) - b)
        if np.sqrt(s2) > rank_tol * max(1.0, np.sqrt(s2)):
            curvature, owned = 2.0 * max(s2, damping * damping), True
    if H.shape[0]:
        hd = matvec(H, d)
        curvature += dot(d, hd)
        slope += dot(hd, x0)
    if g.shape[0]:
        slope += dot(d, g)
    if reg > 0.0 and not owned:
        curvature += reg
    nv, p = 1 + n_slack, C.shape[0]
    Hq = np.eye(nv)
    Hq[0, 0] = curvature
    gq = np.zeros(nv)
    gq[0] = slope
    Cq = np.zeros((p, nv))
    lq, uq = np.empty(p), np.empty(p)
    for i in range(p):
        cd, cx = 0.0, 0.0
        for j in range(d.shape[0]):
            cd += C[i, j] * d[j]
            cx += C[i, j] * x0[j]
        Cq[i, 0] = cd
        lq[i], uq[i] = l[i] - cx, u[i] - cx
        if i < n_slack:
            Cq[i, 1 + i] = slack_scale
    box_l, box_u = np.full(nv, -np.inf), np.full(nv, np.inf)
    box_l[0], box_u[0] = t_lo, t_hi
    return Hq, gq, Cq, lq, uq, box_l, box_u, owned


def _line_level_qp(data: _LevelData, line: _Line, settings: QPSettings) -> LevelQP:
    """The QP of a level restricted to ``x = x0 + t·direction``: :func:`build_level_qp` with
    ``Z`` the line's direction (same damping and tie-break), the bounds folded into a box on ``t``."""
    d = line.direction
    n = d.shape[0]
    ns = data.n_slack
    H, g, C, lo, hi, box_l, box_u, owned = line_qp_arrays(
        d, line.x0, line.t_lo, line.t_hi,
        _no_rows(n) if data.Aw is None else data.Aw, _NO_VECTOR if data.bw is None else data.bw,
        _no_rows(n) if data.H is None else data.H, _NO_VECTOR if data.g is None else data.g,
        _no_rows(n) if data.C is None else data.C, _NO_VECTOR if data.l is None else data.l,
        _NO_VECTOR if data.u is None else data.u, ns, 1.0 / math.sqrt(2.0 * data.rho) if ns else 0.0,
        settings.regularization or 0.0, settings.rank_tol, settings.damping_threshold)
    return LevelQP(H, g, C, lo, hi, box_l, box_u, line.x0, d[:, None], _OWNED_1 if owned else _OWNED_0, None,
                   ns, 0, 0)


@njit(cache=True)
def level_answer(v, Z, identity, has_box, box_l, box_u, C, l, u, slack_start, n_slack, x_prev):  # type: ignore[no-untyped-def]
    """A level QP's answer ``v = [z; σ]`` checked: ``x = x_prev + Z z`` (``identity``: ``Z`` is I), the
    worst violation of the box on z and of the hard rows (rows taken without σ; the bound rows, if
    any, are ``Z z`` against ``lb − x_prev``), and each soft row's violation (its slack)."""
    r = Z.shape[1]
    z = v[:r]
    worst = 0.0
    if has_box:
        for i in range(r):
            worst = max(worst, box_l[i] - z[i], z[i] - box_u[i])
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
    d = z.copy() if identity else matvec(Z, z)
    return x_prev + d, worst, slack


LINE_ANSWER_OK, LINE_ANSWER_NOT_FINITE, LINE_ANSWER_VIOLATED = 0, 1, 2


@njit(cache=True)
def checked_line_answer(v, d, x0, box_l, box_u, C, l, u, n_slack, tol):  # type: ignore[no-untyped-def]
    """``(code, x, worst, slack)`` of :func:`level_answer` on the line (``Z = d``, box on ``t``), judged: :data:`LINE_ANSWER_NOT_FINITE` when ``t``
    (all that ``x`` depends on) is not finite, :data:`LINE_ANSWER_VIOLATED` when the box or a hard row is
    violated by more than ``tol``, else :data:`LINE_ANSWER_OK`."""
    if not math.isfinite(v[0]):
        return LINE_ANSWER_NOT_FINITE, x0.copy(), math.inf, np.zeros(n_slack)
    x, worst, slack = level_answer(v, d.reshape(d.shape[0], 1), False, True, box_l, box_u, C, l, u, 0, n_slack, x0)
    return (LINE_ANSWER_OK if worst <= tol else LINE_ANSWER_VIOLATED), x, worst, slack


# ------------------------------------------------------------------- results
class LevelStatus(str, enum.Enum):
    """Outcome of one level."""

    SOLVED = "solved"
    INFEASIBLE = "infeasible"  # hard constraints cannot all hold
    MAX_ITER = "max_iter"
    INACCURATE = "inaccurate"  # solver said solved, but the answer failed verification
    SOLVER_ERROR = "solver_error"
    SKIPPED = "skipped"  # a higher level failed
    TIME_BUDGET = "time_budget"  # the cascade's time budget was spent before this level (not solved)

    def __str__(self) -> str:
        return self.value


@dataclass
class LevelResult:
    """One level: ``x`` the cascade's joint velocity after it (rad/s); ``residual``
    ``‖A x − b‖`` (units of b, unweighted) of its task; ``slack`` the violation
    (≥ 0) of each soft row at ``x``; ``solve_time_s`` wall time (build + solve +
    checks); ``iterations`` as the back end reports them (None if it does not)."""

    status: LevelStatus
    x: np.ndarray | None = None
    residual: float | None = None
    slack: np.ndarray | None = None
    iterations: int | None = None
    solve_time_s: float = 0.0
    message: str = ""

    @property
    def ok(self) -> bool:
        return self.status is LevelStatus.SOLVED


@dataclass
class HQPResult:
    """The cascade: ``x`` the last good level's answer (None if level 1 failed);
    ``ok`` all levels solved; ``status`` ``"solved"`` or which level failed and
    why; ``failed_level`` its 0-based index."""

    x: np.ndarray | None
    ok: bool
    status: str
    failed_level: int | None
    levels: list[LevelResult]
    solve_time_s: float

    @property
    def solve_time(self) -> float:
        """Alias of ``solve_time_s`` (s)."""
        return self.solve_time_s

    @property
    def out_of_time(self) -> bool:
        """The cascade stopped because its time budget was spent (:attr:`LevelStatus.TIME_BUDGET`)."""
        return self.failed_level is not None and self.levels[self.failed_level].status is LevelStatus.TIME_BUDGET


@dataclass
class HQPStats:
    """Counters across ticks: ``qp_created`` QP objects allocated (ProxSuite),
    ``solves`` calls of :meth:`HierarchicalQP.solve`, ``failures`` not ok,
    ``cold_retries`` failed warm-started ProxSuite solves retried cold, ``active_set_fallbacks``
    ProxSuite failures handed to DAQP (:func:`active_set_solve`)."""

    qp_created: int = 0
    solves: int = 0
    failures: int = 0
    cold_retries: int = 0
    active_set_fallbacks: int = 0


# ------------------------------------------------------------------ backends
@dataclass(slots=True)
class _Raw:
    v: np.ndarray | None
    status: LevelStatus
    iterations: int | None
    message: str = ""


@njit(cache=True)
def qp_data_finite(H, g, C, lo, hi, box_l, box_u):  # type: ignore[no-untyped-def]
    """Whether a QP's data can be solved: ``H``, ``g``, ``C`` finite, no NaN in the bounds (±inf allowed)."""
    for a in (H.ravel(), g, C.ravel()):
        for x in a:
            if not math.isfinite(x):
                return False
    for a in (lo, hi, box_l, box_u):
        for x in a:
            if x != x:
                return False
    return True


def finite_data_raw(H: np.ndarray, g: np.ndarray, C: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                    box_l: np.ndarray | None, box_u: np.ndarray | None) -> _Raw | None:
    """None when a QP's data can be solved (:func:`qp_data_finite`), else the failure to report: a NaN
    never reaches a back end (one once ran ProxQP for 1.5 M iterations, 9 s, measured)."""
    if qp_data_finite(H, g, C, lo, hi, _NO_VECTOR if box_l is None else box_l, _NO_VECTOR if box_u is None else box_u):
        return None
    return _Raw(None, LevelStatus.SOLVER_ERROR, 0, "non-finite QP data (NaN or inf in the problem)")


_DAQP_SOLVED = (1, 2)  # DAQP's exit flags: optimal, optimal with soft constraints


def active_set_solve(H: np.ndarray, g: np.ndarray, C: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                     box_l: np.ndarray | None, box_u: np.ndarray | None, iter_limit: int = 1000) -> _Raw:
    """``min ½vᵀHv + gᵀv`` s.t. ``lo ≤ C v ≤ hi`` (and the box) by DAQP, a dual active-set method:
    finite termination, exact to round-off on the small QPs of a tick (about 20 µs, measured), a
    semi-definite ``H`` handled by proximal-point iterations (``eps_prox=1e-6``, to ``eta_prox=1e-12``:
    its automatic choice stalled for 5000 iterations along a flat direction that a bound cut, and its
    default 1e-6 tolerance left level 1's residual at 7e-8, both measured).  The recovery of
    :class:`_ProxSuiteBackend` when ProxQP fails (docs/qp-notes.md: ProxQP can stall on degenerate problems)."""
    if box_l is not None:
        upper, lower = np.concatenate([box_u, hi]), np.concatenate([box_l, lo])
    else:
        upper, lower = hi, lo
    try:
        x, _, flag, info = daqp.solve(np.ascontiguousarray(H), g, np.ascontiguousarray(C), upper, lower,
                                      eps_prox=1e-6, eta_prox=1e-12, iter_limit=iter_limit)
    except Exception as exc:  # its own failure becomes a level status
        return _Raw(None, LevelStatus.SOLVER_ERROR, None, f"daqp: {type(exc).__name__}: {exc}")
    if flag not in _DAQP_SOLVED:
        status = LevelStatus.INFEASIBLE if flag == -1 else LevelStatus.SOLVER_ERROR
        return _Raw(None, status, info.get("iterations"), f"daqp exit flag {flag}")
    return _Raw(np.asarray(x, dtype=float), LevelStatus.SOLVED, info.get("iterations"), "daqp")


@dataclass(slots=True)
class _ProxEntry:
    """A persistent ProxSuite object with its members held by reference (each access through the
    binding costs a call), whether its next solve must start cold (the last one failed), and how many
    more solves DAQP answers alone after a fallback (``QPSettings.active_set_hold``)."""

    qp: object
    settings: object
    results: object
    info: object
    cold_next: bool = False
    held: int = 0


class _ProxSuiteBackend:
    """ProxSuite dense ProxQP, one persistent object per (level, shape), warm-started."""

    def __init__(self, settings: QPSettings, stats: HQPStats) -> None:
        import proxsuite

        self._px = proxsuite.proxqp
        self._settings = settings
        self._stats = stats
        self._qps: dict[tuple, _ProxEntry] = {}  # (level, nv, rows, box) -> its persistent object
        out = self._px.QPSolverOutput
        self._status = {
            out.PROXQP_SOLVED: LevelStatus.SOLVED,
            out.PROXQP_PRIMAL_INFEASIBLE: LevelStatus.INFEASIBLE,
            out.PROXQP_SOLVED_CLOSEST_PRIMAL_FEASIBLE: LevelStatus.INFEASIBLE,
            out.PROXQP_MAX_ITER_REACHED: LevelStatus.MAX_ITER,
        }
        guess = self._px.InitialGuess
        self._warm = guess.WARM_START_WITH_PREVIOUS_RESULT if settings.warm_start \
            else guess.EQUALITY_CONSTRAINED_INITIAL_GUESS
        self._cold = guess.EQUALITY_CONSTRAINED_INITIAL_GUESS
        self._messages: dict = {}  # status -> "proxsuite <name>" (formatted once)
        self._solved = out.PROXQP_SOLVED  # (an enum singleton: compared by identity, the cheapest test)

    def _create(self, nv: int, n_in: int, box: bool):
        s = self._settings
        obj = self._px.dense.QP(nv, 0, n_in, box)
        st = obj.settings
        st.eps_abs, st.eps_rel = s.eps_abs, s.eps_rel
        st.eps_primal_inf, st.eps_dual_inf = s.eps_primal_inf, s.eps_dual_inf
        st.max_iter, st.max_iter_in = s.max_iter, s.max_iter_in
        st.default_mu_in = s.mu_in
        st.primal_infeasibility_solving = False  # infeasible must be reported, not hidden
        st.verbose = False
        self._stats.qp_created += 1
        return obj

    def solve(self, k: int, qp: LevelQP) -> _Raw:
        box = qp.box_l is not None and self._settings.box_constraints
        C, lo, hi = (qp.C, qp.l, qp.u) if box else qp.rows_with_box()
        return self.solve_arrays(k, qp.H, qp.g, C, lo, hi, qp.box_l if box else None, qp.box_u if box else None)

    def solve_arrays(self, k: int, H: np.ndarray, g: np.ndarray, C: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                     box_l: np.ndarray | None, box_u: np.ndarray | None) -> _Raw:
        """``min ½vᵀHv + gᵀv`` s.t. ``lo ≤ C v ≤ hi`` (and ``box_l ≤ v ≤ box_u`` if given) on the
        persistent object of level ``k`` and this shape, warm-started.

        The budget is in iterations, so that answers do not depend on the machine's load: ProxQP's
        ``max_iter`` × ``max_iter_in`` (it cannot be interrupted on time), then, if ``active_set_fallback``,
        DAQP (:func:`active_set_solve`, at most ``max_iter_active_set`` iterations; counted in
        ``stats.active_set_fallbacks``).  DAQP then answers this QP alone for its next
        ``active_set_hold`` solves (counted likewise): a QP that ProxQP could not finish warm is usually
        as hard on the next ticks (a pull against the bounds), and a failed attempt costs as much as the
        DAQP solve itself (measured); after the hold ProxQP starts cold.  Without the fallback a failed
        warm solve is retried cold at once.  The data are finite (:func:`finite_data_raw` refuses others
        first)."""
        box = box_l is not None
        key = (k, H.shape[0], C.shape[0], box)
        entry = self._qps.get(key)
        if entry is not None and entry.held:
            entry.held -= 1
            self._stats.active_set_fallbacks += 1
            raw = active_set_solve(H, g, C, lo, hi, box_l, box_u, self._settings.max_iter_active_set)
            if raw.status is LevelStatus.SOLVED:
                return raw
            entry.held, entry.cold_next = 0, True  # DAQP failed too: ProxQP tries, cold
        if C.shape[0]:
            data = dict(H=H, g=g, C=C, l=lo, u=hi, l_box=box_l, u_box=box_u) if box else dict(H=H, g=g, C=C, l=lo, u=hi)
        else:
            data = dict(H=H, g=g, l_box=box_l, u_box=box_u) if box else dict(H=H, g=g)
        if entry is None:
            obj = self._create(H.shape[0], C.shape[0], box)
            obj.settings.initial_guess = self._cold
            obj.init(**data)
            self._qps[key] = entry = _ProxEntry(obj, obj.settings, obj.results, obj.results.info)
        else:
            obj = entry.qp
            entry.settings.initial_guess = self._cold if entry.cold_next else self._warm
            obj.update(**data)
        obj.solve()
        info = entry.info
        out = info.status
        if out is self._solved:  # the usual tick: nothing else to look at
            entry.cold_next = False
            return _Raw(entry.results.x.copy(), LevelStatus.SOLVED, info.iter, self._message(out))  # x: a view
        settings = entry.settings
        fallback = self._settings.active_set_fallback
        if settings.initial_guess == self._warm and not fallback:
            self._stats.cold_retries += 1  # a warm start can fail where a cold one does not (measured)
            settings.initial_guess = self._cold
            obj.init(**data)  # same object; resets its adapted penalties too
            obj.solve()
            out = info.status
        entry.cold_next = out is not self._solved  # a failed result is a bad warm start
        message = self._message(out)
        if out is self._solved:
            return _Raw(entry.results.x.copy(), LevelStatus.SOLVED, info.iter, message)
        status = self._status.get(out, LevelStatus.SOLVER_ERROR)
        if not fallback:
            return _Raw(None, status, info.iter, message)
        self._stats.active_set_fallbacks += 1
        entry.held = self._settings.active_set_hold
        raw = active_set_solve(H, g, C, lo, hi, box_l, box_u, self._settings.max_iter_active_set)
        raw.message = f"{message}; {raw.message}"
        return raw

    def _message(self, out: object) -> str:
        """``proxsuite <status name>``, formatted once per status."""
        message = self._messages.get(out)
        if message is None:
            message = self._messages[out] = f"proxsuite {out.name}"  # type: ignore[attr-defined]
        return message

    @property
    def qp_objects(self) -> int:
        return len(self._qps)


class _QpsolversBackend:
    """Any installed ``qpsolvers`` back end, cold one-shot solves."""

    def __init__(self, solver: str, settings: QPSettings) -> None:
        import qpsolvers

        self._qpsolvers = qpsolvers
        self._solver = solver
        self._options = dict(settings.solver_options)

    def solve(self, k: int, qp: LevelQP) -> _Raw:
        C, lo, hi = qp.rows_with_box()
        up, down = np.isfinite(hi), np.isfinite(lo)
        G = np.vstack([C[up], -C[down]])
        h = np.concatenate([hi[up], -lo[down]])
        H = 0.5 * (qp.H + qp.H.T)  # exactly symmetric: some back ends (sip) check it bit for bit
        problem = self._qpsolvers.Problem(H, qp.g, G if h.size else None, h if h.size else None)
        try:
            sol = self._qpsolvers.solve_problem(problem, solver=self._solver, **self._options)
        except Exception as exc:  # a back end's own failure becomes a level status
            return _Raw(None, LevelStatus.SOLVER_ERROR, None, f"{self._solver}: {type(exc).__name__}: {exc}")
        if not sol.found or sol.x is None:
            return _Raw(None, LevelStatus.INFEASIBLE, None, f"{self._solver}: no solution found")
        return _Raw(np.asarray(sol.x, dtype=float), LevelStatus.SOLVED, None, self._solver)


def _make_backend(backend: str, settings: QPSettings, stats: HQPStats):
    if backend == NATIVE_BACKEND:
        return _ProxSuiteBackend(settings, stats)
    import qpsolvers

    if not isinstance(backend, str) or backend not in qpsolvers.available_solvers:
        raise SolverError(
            f"QP back end {backend!r} is unknown or not installed; use {NATIVE_BACKEND!r} "
            f"(native ProxSuite) or one of qpsolvers.available_solvers = {sorted(qpsolvers.available_solvers)}")
    return _QpsolversBackend(backend, settings)


# ------------------------------------------------------------------- solver
class HierarchicalQP:
    """Lexicographic cascade of :class:`Level` over ``n`` joint velocities (docs/method.md §7).

    ``backend="proxsuite"``: native dense ProxQP, one object per level and QP
    shape (the shape changes with the number of free directions, e.g. at a
    singularity) created at its first solve and updated/warm-started every tick;
    any other name is a ``qpsolvers`` back end solved cold.
    ``stats.qp_created`` counts ProxSuite allocations (constant across ticks of
    fixed shapes).
    """

    def __init__(self, n: int, backend: str = NATIVE_BACKEND, settings: QPSettings | None = None) -> None:
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise InputError(f"n must be a positive integer, got {n!r}")
        self.n = int(n)
        settings = QPSettings() if settings is None else settings
        if not isinstance(settings, QPSettings):
            raise ConfigError(f"settings must be QPSettings, got {type(settings).__name__}")
        if settings.regularization is None:
            settings = replace(settings, regularization=0.0 if backend == NATIVE_BACKEND else 1e-7)
        self.settings = settings
        self.backend = backend
        self.stats = HQPStats()
        self._backend = _make_backend(backend, self.settings, self.stats)

    def solve(self, levels: Sequence[Level], lb: np.ndarray | None = None,
              ub: np.ndarray | None = None, check: bool = True, time_budget: float | None = None) -> HQPResult:
        """Solve the cascade under the hard bounds ``lb ≤ x ≤ ub`` (rad/s, ∓inf allowed).

        Raises :class:`InputError` on bad input (before solving anything);
        solver trouble is reported in the result, never raised, never NaN.
        ``check=False`` skips the input validation (shapes, NaN, intervals) for a
        caller that builds float arrays of the right shapes itself; the answer is
        verified (finite, bounds, hard rows) either way.

        ``time_budget`` (s of this thread's CPU time, ``time.thread_time``; None: none): the general
        cascade starts a level only if the time spent so far plus the last level's own time fits in
        it — the first level always starts.  The levels solved stand (the least-norm point of their
        optimal set, as always), the next one is reported :attr:`LevelStatus.TIME_BUDGET` and the rest
        skipped: a deadline for a control tick, at the price of answers that depend on the CPU time a
        level took.  Each QP's own budget is
        in iterations (:class:`QPSettings`); the line fast path's two levels are not cut.
        """
        t0 = time.perf_counter()
        if not isinstance(levels, (list, tuple)) and (isinstance(levels, Level) or not isinstance(levels, Sequence)) \
                or len(levels) == 0:
            raise InputError("levels must be a non-empty sequence of Level")
        if time_budget is not None and not (isinstance(time_budget, (int, float)) and time_budget > 0):
            raise InputError(f"time_budget must be a positive number of seconds or None, got {time_budget!r}")
        if check:
            data = [_validate_level(level, self.n, f"levels[{k}]") for k, level in enumerate(levels)]
            lo, hi = _validate_bounds(lb, ub, self.n)
        else:
            data = [_trusted_level(level) for level in levels]
            lo = np.full(self.n, -np.inf) if lb is None else np.asarray(lb, dtype=float)
            hi = np.full(self.n, np.inf) if ub is None else np.asarray(ub, dtype=float)
        line = _task_line(data[0], lo, hi, self.settings) \
            if self.settings.line_fast_path and len(data) <= 2 else None
        results = self._solve_cascade(data, lo, hi, time_budget) if line is None else self._solve_on_line(data, line)
        return self._finish(results, len(data), t0)

    def _solve_cascade(self, data: list[_LevelData], lo: np.ndarray, hi: np.ndarray,
                       time_budget: float | None = None) -> list[LevelResult]:
        """Level after level in the null-space basis; stops at the first failed level, or before a level
        that would overrun ``time_budget`` (s of CPU time, :meth:`solve`).  The last solved level's answer is
        then made unique: the least-norm point of its optimal set (:meth:`_least_norm`), never whatever a
        solver's warm start left along the directions no level owns."""
        cascade = Cascade.start(lo, hi)
        results: list[LevelResult] = []
        solved = None  # the cascade after the last solved level
        start = level_start = time.thread_time() if time_budget is not None else 0.0
        for k, level in enumerate(data):
            if k and time_budget is not None and _out_of_time(start, level_start, time_budget):
                results.append(LevelResult(LevelStatus.TIME_BUDGET, message=f"the cascade's time budget of "
                                           f"{time_budget * 1e3:.3g} ms would be spent by this level"))
                break
            level_start = time.thread_time() if time_budget is not None else 0.0
            qp = build_level_qp(level, cascade, self.settings)
            result = self._solve_level(k, level, qp)
            results.append(result)
            if not result.ok:
                break
            if k == len(data) - 1 and strictly_convex(qp, self.settings.rank_tol):
                return results  # its answer is unique already: no optimal set left to search
            cascade = solved = advance_cascade(level, cascade, qp, result.x, self.settings)
        if solved is not None and solved.Z.shape[1]:
            last = results[-1] if results[-1].ok else results[-2]
            last.x = self._least_norm(solved)
        return results

    def _least_norm(self, cascade: Cascade) -> np.ndarray:
        """The least-norm joint velocity (rad/s) of the optimal set ``x + Z z`` that ``cascade`` leaves
        (bounds and inherited rows kept): ``min ½‖x + Z z‖²``, strictly convex in ``z``, solved by DAQP
        (:func:`active_set_solve`: exact, finite).  ``cascade.x`` itself if that fails (it is feasible)."""
        n = cascade.x.shape[0]
        data = _LevelData(None, None, None, None, _eye(n), None, None, None, None, None)
        qp = build_level_qp(data, cascade, self.settings)
        raw = active_set_solve(qp.H, qp.g, qp.C, qp.l, qp.u, qp.box_l, qp.box_u, self.settings.max_iter_active_set)
        result = self._check(data, qp, raw)
        return result.x if result.ok else cascade.x

    def reset(self) -> None:
        """Forget every warm start, persistent solver object and counter: from here the solver
        answers exactly as a new one."""
        self.stats = HQPStats()
        self._backend = _make_backend(self.backend, self.settings, self.stats)

    def warm_up(self) -> None:
        """Load (or compile, once per machine) every kernel of the cascade by solving two small ones (a
        two-row task above a task, a cost and soft and hard rows: the general cascade; an (n−1)-row task
        above a cost with a soft row: the line fast path), then :meth:`reset`: a control tick that first
        takes a path must not pay for it (loading two kernels took 30–60 ms, measured)."""
        n = self.n
        eye = np.eye(n)
        self.solve([Level(A=eye[:2], b=np.ones(2)),
                    Level(A=eye[2:3], b=np.ones(1), H=eye, C=eye[:1], l=np.zeros(1), u=np.zeros(1), slack_weight=1.0),
                    Level(g=np.ones(n), C=eye[1:2], l=-np.ones(1), u=np.ones(1))], -np.ones(n), np.ones(n))
        self.solve([Level(A=eye[:n - 1], b=np.zeros(n - 1)),  # the line fast path's kernels
                    Level(H=eye, g=np.ones(n), C=eye[n - 1:], l=np.zeros(1), u=np.zeros(1), slack_weight=1.0)],
                   -np.ones(n), np.ones(n))
        self.reset()

    def _solve_on_line(self, data: list[_LevelData], line: _Line) -> list[LevelResult]:
        """Line fast path (module docstring): level 1 in closed form, level 2 (if any) on the line."""
        t1 = time.perf_counter()
        x1 = least_norm_point(line.x0, line.direction, line.t_lo, line.t_hi)
        first = LevelResult(LevelStatus.SOLVED, x=x1, residual=_residual(data[0], x1), iterations=0,
                            message="closed form: the task's exact solutions meet the bounds on a line")
        t2 = time.perf_counter()
        first.solve_time_s = t2 - t1
        if len(data) == 1:
            return [first]
        level = data[1]
        qp = _line_level_qp(level, line, self.settings)
        second = self.solve_line_level(qp.H, qp.g, qp.C, qp.l, qp.u, qp.box_l, qp.box_u, line.x0, line.direction,
                                       qp.n_slack, qp)
        if second.ok:
            second.residual = _residual(level, second.x)
        second.solve_time_s = time.perf_counter() - t2
        return [first, second]

    def solve_line_level(self, H: np.ndarray, g: np.ndarray, C: np.ndarray, l: np.ndarray, u: np.ndarray,
                         box_l: np.ndarray, box_u: np.ndarray, x0: np.ndarray, direction: np.ndarray,
                         n_slack: int, qp: LevelQP | None = None) -> LevelResult:
        """Level 2 of the line fast path from the arrays of :func:`line_qp_arrays` (``v = [t; σ]``,
        ``x = x0 + t·direction``, rad/s): :meth:`line_level_raw`, then :meth:`line_level_result`
        (``residual`` is left to the caller).  The controller's compiled tick (:mod:`qpnso.control.tick`)
        calls the two parts itself and counts its ticks with :meth:`count_solve`."""
        raw = finite_data_raw(H, g, C, l, u, box_l, box_u) or \
            self.line_level_raw(H, g, C, l, u, box_l, box_u, x0, direction, n_slack, qp)
        return self.line_level_result(raw, direction, x0, box_l, box_u, C, l, u, n_slack)

    def line_level_raw(self, H: np.ndarray, g: np.ndarray, C: np.ndarray, l: np.ndarray, u: np.ndarray,
                       box_l: np.ndarray, box_u: np.ndarray, x0: np.ndarray, direction: np.ndarray,
                       n_slack: int, qp: LevelQP | None = None) -> _Raw:
        """The back end's answer to the line's level 2, on its persistent level-2 object, unchecked."""
        if isinstance(self._backend, _ProxSuiteBackend) and self.settings.box_constraints:
            return self._backend.solve_arrays(1, H, g, C, l, u, box_l, box_u)
        if qp is None:
            qp = LevelQP(H, g, C, l, u, box_l, box_u, x0, direction[:, None], _OWNED_0, None, n_slack, 0, 0)
        return self._backend.solve(1, qp)

    def line_level_result(self, raw: _Raw, direction: np.ndarray, x0: np.ndarray, box_l: np.ndarray,
                          box_u: np.ndarray, C: np.ndarray, l: np.ndarray, u: np.ndarray, n_slack: int) -> LevelResult:
        """A raw line answer judged (:func:`checked_line_answer`: box on ``t`` and hard rows within
        ``feasibility_tol``) with the soft rows' slack."""
        if raw.status is not LevelStatus.SOLVED:
            return LevelResult(raw.status, iterations=raw.iterations, message=raw.message)
        code = LINE_ANSWER_NOT_FINITE
        v = solved_vector(raw, box_l.shape)
        if v is not None:
            code, x, worst, slack = checked_line_answer(v, direction, x0, box_l, box_u, C, l, u, n_slack,
                                                        self.settings.feasibility_tol)
        if code == LINE_ANSWER_NOT_FINITE:
            return LevelResult(LevelStatus.INACCURATE, iterations=raw.iterations,
                               message=f"{raw.message}: non-finite or mis-shaped solution")
        if code == LINE_ANSWER_VIOLATED:
            return LevelResult(LevelStatus.INACCURATE, iterations=raw.iterations,
                               message=f"{raw.message}: bounds or hard rows violated by {worst:.3g}")
        return LevelResult(LevelStatus.SOLVED, x=x, slack=slack if n_slack else None, iterations=raw.iterations,
                           message=raw.message)

    def count_solve(self, ok: bool) -> None:
        """Count one cascade in ``stats`` (:meth:`solve` does; so does a caller that solves the
        line's level 2 itself through :meth:`line_level_raw`, the controller's compiled tick)."""
        self.stats.solves += 1
        if not ok:
            self.stats.failures += 1

    def _solve_level(self, k: int, level: _LevelData, qp: LevelQP) -> LevelResult:
        """Back-end solve of one level's QP and verification of its answer."""
        t_level = time.perf_counter()
        if qp.H.shape[0] == 0 or qp.r == 0:  # nothing left to choose: x = x_prev, slack as it falls
            raw = _Raw(np.zeros(qp.H.shape[0]), LevelStatus.SOLVED, 0, "no free direction left")
        else:
            raw = finite_data_raw(qp.H, qp.g, qp.C, qp.l, qp.u, qp.box_l, qp.box_u) or self._backend.solve(k, qp)
        result = self._check(level, qp, raw)
        result.solve_time_s = time.perf_counter() - t_level
        return result

    def _finish(self, results: list[LevelResult], n_levels: int, t0: float) -> HQPResult:
        """The cascade's result: the last good level's answer, the first failure named."""
        failed = None if results[-1].ok else len(results) - 1
        x_good = results[-1].x if failed is None else (results[-2].x if len(results) > 1 else None)
        results += [LevelResult(LevelStatus.SKIPPED) for _ in range(len(results), n_levels)]
        self.count_solve(failed is None)
        status = "solved" if failed is None else level_failure(failed, n_levels, results[failed])
        return HQPResult(x=None if x_good is None else x_good.copy(), ok=failed is None, status=status,
                         failed_level=failed, levels=results, solve_time_s=time.perf_counter() - t0)

    def _check(self, level: _LevelData, qp: LevelQP, raw: _Raw) -> LevelResult:
        """Verify a level's answer: finite, and every bound and hard row (this level's and
        the inherited ones) within ``feasibility_tol`` (:func:`level_answer`); report residual and slack."""
        if raw.status is not LevelStatus.SOLVED:
            return LevelResult(raw.status, iterations=raw.iterations, message=raw.message)
        v = raw.v
        if v is None or v.shape != qp.g.shape or not math.isfinite(v.sum()):
            return LevelResult(LevelStatus.INACCURATE, iterations=raw.iterations,
                               message=f"{raw.message}: non-finite or mis-shaped solution")
        box = qp.box_l is not None
        x, worst, slack = level_answer(_c(v), _c(qp.Z), qp.r == qp.Z.shape[0], box,
                                       qp.box_l if box else _NO_VECTOR, qp.box_u if box else _NO_VECTOR,
                                       qp.C, qp.l, qp.u, qp.slack_start, qp.n_slack, _c(qp.x_prev))
        if not worst <= self.settings.feasibility_tol:
            status = LevelStatus.INFEASIBLE if qp.r == 0 else LevelStatus.INACCURATE
            return LevelResult(status, iterations=raw.iterations,
                               message=f"{raw.message}: bounds or hard rows violated by {worst:.3g}")
        return LevelResult(LevelStatus.SOLVED, x=x, residual=_residual(level, x), slack=slack if qp.n_slack else None,
                           iterations=raw.iterations, message=raw.message)


def _out_of_time(start: float, level_start: float, budget: float) -> bool:
    """Whether the next level would overrun ``budget`` (s of CPU time since ``start``), judged by the
    last level's own time (since ``level_start``): the levels of one cascade cost about the same."""
    now = time.thread_time()
    return now - start + (now - level_start) > budget


def solved_vector(raw: _Raw, shape: tuple[int, ...]) -> np.ndarray | None:
    """A back end's solution vector if it reports success with a vector of ``shape``, else None
    (what is left to check is the vector's values)."""
    if raw.status is not LevelStatus.SOLVED or raw.v is None or raw.v.shape != shape:
        return None
    return raw.v


def level_failure(k: int, n_levels: int, result: LevelResult) -> str:
    """How :attr:`HQPResult.status` names the first failed level ``k`` (0-based) of ``n_levels``."""
    return f"level {k + 1} of {n_levels} {result.status}: {result.message}"


def _residual(level: _LevelData, x: np.ndarray) -> float | None:
    """``‖A x − b‖`` (units of b, unweighted) of a level's task, None without one."""
    if level.A is None:
        return None
    e = level.A @ x - level.b
    return math.sqrt(float(e @ e))
