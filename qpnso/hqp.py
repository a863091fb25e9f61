"""Hierarchical (lexicographic) QP over joint velocities, solved every tick (METHOD §7).

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

**Null-space form** (not the fragile equality form of QP-NOTES): level ``k``
moves the answer of the levels above only inside ``range(N_k)``, the n×n
orthogonal projector onto the directions that no higher level owns:
``x = x_{k−1} + N_k d``.  The answer is always formed through ``N_k``, so a
higher task's residual is preserved by construction, whatever the solver's
tolerance.  Each level's QP (:class:`LevelQP`, variable ``d`` ∈ Rⁿ plus one
scaled slack per soft row) has the SAME shape every tick, so its ProxSuite
object is created once and updated in place; ``d`` is in joint coordinates
(not a basis that may flip sign between ticks), so the last tick's answer is a
good warm start.  Two equivalent constraint forms are handed to the back ends:

* ProxSuite (native): ``(I − N_k) d = 0`` as n homogeneous equalities (``d = 0``
  is always feasible) and the bounds as its native box on ``d``;
* active-set back ends (DAQP, quadprog, …; they fail on that rank-deficient
  equality — measured): ``d = N_k z`` substituted, the bounds as rows ``N_k z``.

The Hessian carries ``(I − N_k)`` (zero on the feasible set, keeps it
positive definite) and a tie-break ``½ μ ‖d‖²`` only in the directions that the
level's own task leaves free (``μ = QPSettings.regularization``: 1e-7 for the
active-set back ends, which need a positive-definite H — DAQP failed at 1e-8 on
a level without curvature, 1e-6 biased answers by 2.5e-6, measured; 0 for
ProxQP, whose proximal iterations handle a semi-definite H and which lost
accuracy and hit max_iter with a tiny curvature at tight tolerances,
measured).  μ must stay small: with bounds active, moving along a task's null
space can still lower its residual (it changes which bounds bind).

A level *owns* (removes from ``N`` for the levels below it):

1. the right singular vectors of ``W^½ A N_k`` with ``σ > rank_tol·max(1, σ_max)``
   — so lower levels change a higher equality task's residual by at most
   ``rank_tol·‖d‖`` (≈1e-10·‖d‖, exactly zero for an exactly singular row);
2. the range of ``N H N`` (eigenvalues above ``rank_tol·max(1, ‖H‖)``);
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

**Singular tasks** ([M 20]-style damped least squares, singular-value
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
import time
from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np
from scipy.linalg import lapack as _lapack

from qpnso.errors import ConfigError, InputError, SolverError

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
    steps: a warm start can stop after zero iterations, see QP-NOTES).
    ``solver_options`` are passed verbatim to ``qpsolvers.solve_problem``.
    """

    eps_abs: float = 1e-11
    eps_rel: float = 0.0
    eps_primal_inf: float = 1e-12
    eps_dual_inf: float = 1e-12
    max_iter: int = 1000
    warm_start: bool = True  # ProxSuite: WARM_START_WITH_PREVIOUS_RESULT every tick
    box_constraints: bool = True  # ProxSuite: bounds as its native box (else as rows)
    regularization: float | None = None  # μ on the directions a task leaves free; None: 0 for
    # native ProxSuite (its proximal method handles a semi-definite H), 1e-7 for qpsolvers back ends
    rank_tol: float = 1e-10  # relative singular value below which a direction is null
    damping_threshold: float = 1e-2  # ε, units of A (m/rad, rad/rad); 0 disables damping
    gradient_tol: float = 1e-7  # relative size of a projected gradient that a level owns
    feasibility_tol: float = 1e-6  # accepted violation of bounds / hard rows (units of the row)
    active_tol: float = 1e-7  # a higher level's bound/row this close to its answer is active below
    solver_options: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.regularization is not None and not (np.isfinite(self.regularization) and self.regularization >= 0):
            raise ConfigError(f"QPSettings.regularization must be >= 0 or None, got {self.regularization!r}")
        for name in ("eps_abs", "eps_rel", "eps_primal_inf", "eps_dual_inf",
                     "rank_tol", "damping_threshold", "gradient_tol", "feasibility_tol", "active_tol"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value >= 0):
                raise ConfigError(f"QPSettings.{name} must be a finite number >= 0, got {value!r}")
        if not (isinstance(self.max_iter, int) and self.max_iter > 0):
            raise ConfigError(f"QPSettings.max_iter must be a positive integer, got {self.max_iter!r}")
        if not isinstance(self.solver_options, dict):
            raise ConfigError("QPSettings.solver_options must be a dict")


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


@dataclass(frozen=True)
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
    """``value`` as a float array of ``ndim`` dimensions without NaN (and without inf unless allowed)."""
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a numeric array, got {type(value).__name__}") from None
    if arr.ndim != ndim:
        raise InputError(f"{name} must be {ndim}-D, got shape {arr.shape}")
    total = float(arr.sum())  # one reduction: finite sum <=> no NaN/inf (overflow → detailed check)
    if total - total != 0.0:
        if np.isnan(arr).any():
            raise InputError(f"{name} contains NaN")
        if not allow_inf and np.isinf(arr).any():
            raise InputError(f"{name} contains inf")
    return arr


def _check_shape(arr: np.ndarray, shape: tuple, name: str) -> None:
    if arr.shape != shape:
        raise InputError(f"{name} has shape {arr.shape}, expected {shape}")


def _check_interval(lo: np.ndarray, hi: np.ndarray, lo_name: str, hi_name: str) -> None:
    if not ((lo <= hi).all() and lo.max(initial=-np.inf) < np.inf and hi.min(initial=np.inf) > -np.inf):
        bad = ~(lo <= hi) | np.isposinf(lo) | np.isneginf(hi)
        i = int(np.argmax(bad))
        raise InputError(f"{lo_name}[{i}] = {lo[i]!r} > {hi_name}[{i}] = {hi[i]!r}, or an infinite bound "
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


def _validate_bounds(lb: object, ub: object, n: int) -> tuple[np.ndarray, np.ndarray]:
    lo = np.full(n, -np.inf) if lb is None else _array(lb, "lb", 1, allow_inf=True)
    hi = np.full(n, np.inf) if ub is None else _array(ub, "ub", 1, allow_inf=True)
    _check_shape(lo, (n,), "lb")
    _check_shape(hi, (n,), "ub")
    _check_interval(lo, hi, "lb", "ub")
    return lo, hi


# ------------------------------------------------------------------ cascade
@dataclass(frozen=True)
class Cascade:
    """What the higher levels leave to the next one.

    ``x`` (n,) their solution (rad/s); ``N`` (n, n) the projector onto the
    directions they leave free;
    ``lb``/``ub`` the bounds and ``C``/``l``/``u`` the inherited rows, widened
    to contain ``x`` (see module docstring).
    """

    x: np.ndarray
    N: np.ndarray
    lb: np.ndarray
    ub: np.ndarray
    C: np.ndarray
    l: np.ndarray
    u: np.ndarray
    depth: int = 0  # number of levels already solved

    @classmethod
    def start(cls, lb: np.ndarray, ub: np.ndarray) -> "Cascade":
        n = lb.shape[0]
        return cls(np.zeros(n), np.eye(n), lb, ub, np.zeros((0, n)), np.zeros(0), np.zeros(0))


@dataclass(frozen=True)
class LevelQP:
    """The QP of one level in ``v = [d; σ]`` (n + n_slack), ``d = x − x_prev`` (rad/s):

    ``min ½ vᵀ H v + gᵀ v``  s.t.  ``E v = 0`` (d stays in the free directions),
    ``l ≤ C v ≤ u`` (inherited and own rows), ``box_l ≤ v ≤ box_u`` (the bounds on
    d; ∓inf on σ).  ``E`` is the projector form ``[I − N, 0]`` (n rows, rank k,
    fixed shape for a persistent solver; 0 rows on the first level); see
    :meth:`nullspace_rows` for the equivalent form without it.  The scaled slack ``σ = √(2ρ)·s`` has unit curvature.
    ``x_of(v) = x_prev + N d`` keeps the null-space form exact even if a solver
    meets ``E v = 0`` only to its tolerance.  ``owned`` (n, r): the task
    directions this level takes from the null space.
    """

    H: np.ndarray
    g: np.ndarray
    E: np.ndarray
    C: np.ndarray
    l: np.ndarray
    u: np.ndarray
    box_l: np.ndarray
    box_u: np.ndarray
    x_prev: np.ndarray
    N: np.ndarray
    owned: np.ndarray
    n_slack: int

    def x_of(self, v: np.ndarray) -> np.ndarray:
        """Joint velocity (rad/s) of a QP solution ``v``."""
        n = self.N.shape[0]
        return self.x_prev + self.N @ v[:n]

    def nullspace_rows(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All constraints as rows ``l ≤ C v ≤ u`` of the equivalent equality-free
        z-form (``d = N z``: the box becomes rows ``N z``), for active-set solvers,
        which handle the rank-deficient ``E v = 0`` badly.  Same ``H``, ``g``."""
        n, nv = self.N.shape[0], self.H.shape[0]
        box = np.zeros((n, nv))
        box[:, :n] = self.N
        return (np.vstack([self.C, box]), np.concatenate([self.l, self.box_l[:n]]),
                np.concatenate([self.u, self.box_u[:n]]))


@functools.lru_cache(maxsize=16)
def _eye(n: int) -> np.ndarray:
    """A read-only n×n identity (cached: this is on the per-tick path)."""
    eye = np.eye(n)
    eye.flags.writeable = False
    return eye


def _task_terms(data: _LevelData, cascade: Cascade, settings: QPSettings):
    """Damped least squares ``‖W^½(A x − b)‖²`` in d: Hessian, gradient, owned directions (n, r)."""
    first = cascade.depth == 0
    At = data.Aw if first else data.Aw @ cascade.N
    r0 = -data.bw if first else data.Aw @ cascade.x - data.bw
    _, sigma, vt, info = _lapack.dgesdd(At, compute_uv=1, full_matrices=0)  # np.linalg.svd, less overhead
    if info != 0:
        _, sigma, vt = np.linalg.svd(At, full_matrices=False)
    keep = sigma > settings.rank_tol * max(1.0, float(sigma[0]))
    vk = vt[keep]
    curvature = 2.0 * np.maximum(sigma[keep] ** 2, settings.damping_threshold ** 2)
    return (vk.T * curvature) @ vk, 2.0 * (At.T @ r0), vk.T


def build_level_qp(level: Level | _LevelData, cascade: Cascade, settings: QPSettings = QPSettings()) -> LevelQP:
    """The QP of ``level`` given what higher levels left (``cascade``); pure.

    Hessian in d: ``N(2AᵀWA + H)N`` (damped, module docstring) ``+ μ N_free +
    (I − N)`` (the last term is zero on the feasible set and keeps H positive
    definite); slack block ``I``.  Rows: inherited and own rows, in d.
    """
    n = cascade.x.shape[0]
    data = level if isinstance(level, _LevelData) else _validate_level(level, n, "level")
    N, xp, first = cascade.N, cascade.x, cascade.depth == 0
    ns = data.n_slack
    nv = n + ns
    Hv = np.zeros((nv, nv))
    gv = np.zeros(nv)
    P, q = Hv[:n, :n], gv[:n]  # views
    owned = np.zeros((n, 0))
    if data.Aw is not None:
        P_task, q[:], owned = _task_terms(data, cascade, settings)
        P += P_task
    linear = None  # gradient of ½xᵀHx + gᵀx at x_prev; the task's is already in range(N)
    if data.H is not None:
        P += data.H if first else N @ data.H @ N
        if not first:
            linear = data.H @ xp
    if data.g is not None:
        linear = data.g if linear is None else linear + data.g
    if linear is not None:
        q += linear if first else N @ linear
    mu = settings.regularization or 0.0  # tie-break on the directions the task leaves free
    if first:
        P += (mu * _eye(n) - (mu * owned) @ owned.T) if owned.shape[1] else mu * _eye(n)
    else:
        P += _eye(n) - (1.0 - mu) * N - (mu * owned) @ owned.T
    Hv[:n, :n] = 0.5 * (P + P.T)
    if ns:
        Hv[n:, n:] = _eye(ns)
    # --- equality: d in range(N)
    if first:
        E = np.zeros((0, nv))
    else:
        E = np.zeros((n, nv))
        E[:, :n] = _eye(n) - N
    # --- rows in d: inherited + own (own soft rows get + σ/√(2ρ))
    blocks_C, blocks_l, blocks_u = [], [], []
    if cascade.C.shape[0]:
        blocks_C.append(cascade.C @ N)
        cx = cascade.C @ xp
        blocks_l.append(cascade.l - cx)
        blocks_u.append(cascade.u - cx)
    if data.C is not None:
        if first:
            blocks_C.append(data.C)
            blocks_l.append(data.l)
            blocks_u.append(data.u)
        else:
            blocks_C.append(data.C @ N)
            cx = data.C @ xp
            blocks_l.append(data.l - cx)
            blocks_u.append(data.u - cx)
    n_in = sum(c.shape[0] for c in blocks_C)
    Cv = np.zeros((n_in, nv))
    if n_in:
        Cv[:, :n] = blocks_C[0] if len(blocks_C) == 1 else np.vstack(blocks_C)
        lo = blocks_l[0] if len(blocks_l) == 1 else np.concatenate(blocks_l)
        hi = blocks_u[0] if len(blocks_u) == 1 else np.concatenate(blocks_u)
    else:
        lo = hi = np.zeros(0)
    if ns:
        Cv[n_in - ns:, n:] = _eye(ns) * (1.0 / np.sqrt(2.0 * data.rho))
        box_l = np.concatenate([cascade.lb - xp, np.full(ns, -np.inf)])
        box_u = np.concatenate([cascade.ub - xp, np.full(ns, np.inf)])
    else:
        box_l, box_u = cascade.lb - xp, cascade.ub - xp
    return LevelQP(Hv, gv, E, Cv, lo, hi, box_l, box_u, xp, N, owned, ns)


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


def advance_cascade(level: Level | _LevelData, cascade: Cascade, qp: LevelQP, x: np.ndarray,
                    settings: QPSettings = QPSettings()) -> Cascade:
    """The cascade after ``level`` (whose QP is ``qp``) was solved with joint velocity ``x``.

    Removes from ``N`` the directions the level owns (module docstring, items
    1–3) and passes its constraints down, widened to contain ``x``.
    """
    n = x.shape[0]
    data = level if isinstance(level, _LevelData) else _validate_level(level, n, "level")
    N = cascade.N - qp.owned @ qp.owned.T
    if data.H is not None:
        M = N @ data.H @ N
        eigval, eigvec = np.linalg.eigh(0.5 * (M + M.T))
        big = eigval > settings.rank_tol * max(1.0, float(np.abs(eigval).max()))
        N = N - eigvec[:, big] @ eigvec[:, big].T
    grad = _objective_gradient(data, x) if data.H is not None or data.g is not None else None
    if grad is not None:  # (a pure task's gradient lies in its owned range already)
        p = N @ grad
        norm_p = float(np.linalg.norm(p))
        if norm_p > settings.gradient_tol * max(1.0, float(np.linalg.norm(grad))):
            p /= norm_p
            N = N - np.outer(p, p)
    C, l, u = cascade.C, cascade.l, cascade.u
    if data.C is not None:
        if C.shape[0]:
            C, l, u = np.vstack([C, data.C]), np.concatenate([l, data.l]), np.concatenate([u, data.u])
        else:
            C, l, u = data.C, data.l, data.u
    tol = settings.active_tol
    if C.shape[0]:
        cx = C @ x
        l, u = _pass_down(l, cx, u, tol)
    lb, ub = _pass_down(cascade.lb, x, cascade.ub, tol)
    return Cascade(x=x, N=0.5 * (N + N.T), lb=lb, ub=ub, C=C, l=l, u=u, depth=cascade.depth + 1)


def _pass_down(lo: np.ndarray, value: np.ndarray, hi: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Interval a lower level inherits: widened to contain ``value`` (a violation never
    grows), and a side within ``tol`` of ``value`` moved onto it (exactly active), so an
    inexact solver's answer a hair inside a bound does not leave a sliver of a feasible set."""
    return np.where(value - lo < tol, value, lo), np.where(hi - value < tol, value, hi)


def _violation(lo: np.ndarray, value: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Per-row distance of ``value`` outside ``[lo, hi]`` (0 inside)."""
    return np.maximum(np.maximum(lo - value, value - hi), 0.0)


# ------------------------------------------------------------------- results
class LevelStatus(str, enum.Enum):
    """Outcome of one level."""

    SOLVED = "solved"
    INFEASIBLE = "infeasible"  # hard constraints cannot all hold
    MAX_ITER = "max_iter"
    INACCURATE = "inaccurate"  # solver said solved, but the answer failed verification
    SOLVER_ERROR = "solver_error"
    SKIPPED = "skipped"  # a higher level failed

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


@dataclass
class HQPStats:
    """Counters across ticks: ``qp_created`` QP objects allocated (ProxSuite),
    ``solves`` calls of :meth:`HierarchicalQP.solve`, ``failures`` not ok,
    ``cold_retries`` failed warm-started ProxSuite solves retried cold."""

    qp_created: int = 0
    solves: int = 0
    failures: int = 0
    cold_retries: int = 0


# ------------------------------------------------------------------ backends
@dataclass
class _Raw:
    v: np.ndarray | None
    status: LevelStatus
    iterations: int | None
    message: str = ""


class _ProxSuiteBackend:
    """ProxSuite dense ProxQP, one persistent object per (level, shape), warm-started."""

    def __init__(self, settings: QPSettings, stats: HQPStats) -> None:
        import proxsuite

        self._px = proxsuite.proxqp
        self._settings = settings
        self._stats = stats
        self._qps: dict[tuple, list] = {}  # key -> [QP object, solve cold next time]
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

    def _create(self, nv: int, n_eq: int, n_in: int):
        s = self._settings
        obj = self._px.dense.QP(nv, n_eq, n_in, s.box_constraints)
        st = obj.settings
        st.eps_abs, st.eps_rel = s.eps_abs, s.eps_rel
        st.eps_primal_inf, st.eps_dual_inf = s.eps_primal_inf, s.eps_dual_inf
        st.max_iter = s.max_iter
        st.primal_infeasibility_solving = False  # infeasible must be reported, not hidden
        st.verbose = False
        self._stats.qp_created += 1
        return obj

    def solve(self, k: int, qp: LevelQP) -> _Raw:
        nv, n_eq = qp.H.shape[0], qp.E.shape[0]
        C, lo, hi = qp.C, qp.l, qp.u
        data = {}
        if self._settings.box_constraints:
            data.update(l_box=qp.box_l, u_box=qp.box_u)
        else:
            C = np.vstack([C, _eye(nv)])
            lo, hi = np.concatenate([lo, qp.box_l]), np.concatenate([hi, qp.box_u])
        if n_eq:
            data.update(A=qp.E, b=np.zeros(n_eq))
        if C.shape[0]:
            data.update(C=C, l=lo, u=hi)
        key = (k, nv, n_eq, C.shape[0])
        entry = self._qps.get(key)
        if entry is None:
            obj = self._create(nv, n_eq, C.shape[0])
            obj.settings.initial_guess = self._cold
            obj.init(H=qp.H, g=qp.g, **data)
            self._qps[key] = entry = [obj, False]
        else:
            obj = entry[0]
            obj.settings.initial_guess = self._cold if entry[1] else self._warm
            obj.update(H=qp.H, g=qp.g, **data)
        obj.solve()
        status = self._status.get(obj.results.info.status, LevelStatus.SOLVER_ERROR)
        if status is not LevelStatus.SOLVED and obj.settings.initial_guess == self._warm:
            self._stats.cold_retries += 1  # a warm start can fail where a cold one does not (measured)
            obj.settings.initial_guess = self._cold
            obj.init(H=qp.H, g=qp.g, **data)  # same object; resets its adapted penalties too
            obj.solve()
            status = self._status.get(obj.results.info.status, LevelStatus.SOLVER_ERROR)
        info = obj.results.info
        entry[1] = status is not LevelStatus.SOLVED  # a failed result is a bad warm start
        return _Raw(np.array(obj.results.x), status, int(info.iter), f"proxsuite {info.status.name}")

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
        C, lo, hi = qp.nullspace_rows()
        up, down = np.isfinite(hi), np.isfinite(lo)
        G = np.vstack([C[up], -C[down]])
        h = np.concatenate([hi[up], -lo[down]])
        problem = self._qpsolvers.Problem(qp.H, qp.g, G if h.size else None, h if h.size else None)
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
    """Lexicographic cascade of :class:`Level` over ``n`` joint velocities (METHOD §7).

    ``backend="proxsuite"``: native dense ProxQP, one object per level created
    at the first solve and updated/warm-started every tick; any other name is a
    ``qpsolvers`` back end solved cold.  ``stats.qp_created`` counts ProxSuite
    allocations (constant across ticks of fixed shapes).
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
              ub: np.ndarray | None = None) -> HQPResult:
        """Solve the cascade under the hard bounds ``lb ≤ x ≤ ub`` (rad/s, ∓inf allowed).

        Raises :class:`InputError` on bad input (before solving anything);
        solver trouble is reported in the result, never raised, never NaN.
        """
        t0 = time.perf_counter()
        if isinstance(levels, Level) or not isinstance(levels, Sequence) or len(levels) == 0:
            raise InputError("levels must be a non-empty sequence of Level")
        data = [_validate_level(level, self.n, f"levels[{k}]") for k, level in enumerate(levels)]
        lo, hi = _validate_bounds(lb, ub, self.n)
        cascade = Cascade.start(lo, hi)
        results: list[LevelResult] = []
        x_good, failed = None, None
        for k, level in enumerate(data):
            t_level = time.perf_counter()
            qp = build_level_qp(level, cascade, self.settings)
            raw = self._backend.solve(k, qp)
            result = self._check(level, qp, raw)
            result.solve_time_s = time.perf_counter() - t_level
            results.append(result)
            if not result.ok:
                failed = k
                break
            x_good = result.x
            if k + 1 < len(data):
                cascade = advance_cascade(level, cascade, qp, result.x, self.settings)
        results += [LevelResult(LevelStatus.SKIPPED) for _ in range(len(results), len(data))]
        self.stats.solves += 1
        if failed is None:
            status = "solved"
        else:
            self.stats.failures += 1
            status = f"level {failed + 1} of {len(data)} {results[failed].status}: {results[failed].message}"
        return HQPResult(x=None if x_good is None else x_good.copy(), ok=failed is None, status=status,
                         failed_level=failed, levels=results, solve_time_s=time.perf_counter() - t0)

    def _check(self, level: _LevelData, qp: LevelQP, raw: _Raw) -> LevelResult:
        """Verify a level's answer: finite, and every bound and hard row (this level's and
        the inherited ones) within ``feasibility_tol``; report residual and slack."""
        if raw.status is not LevelStatus.SOLVED:
            return LevelResult(raw.status, iterations=raw.iterations, message=raw.message)
        v = raw.v
        if v is None or v.shape != qp.g.shape or not np.isfinite(v.sum()):
            return LevelResult(LevelStatus.INACCURATE, iterations=raw.iterations,
                               message=f"{raw.message}: non-finite or mis-shaped solution")
        n, ns = qp.N.shape[0], qp.n_slack
        d = qp.N @ v[:n]  # x − x_prev, exactly in the free directions
        worst, slack = 0.0, None
        if qp.l.shape[0]:
            rows = qp.C[:, :n] @ d  # on the projected d, without the slack
            lo, hi = qp.l, qp.u
            if ns:
                slack = _violation(lo[-ns:], rows[-ns:], hi[-ns:])
                rows, lo, hi = rows[:-ns], lo[:-ns], hi[:-ns]
            if rows.shape[0]:
                worst = max(float((lo - rows).max()), float((rows - hi).max()))
        worst = max(worst, float((qp.box_l[:n] - d).max()), float((d - qp.box_u[:n]).max()))
        if not worst <= self.settings.feasibility_tol:
            return LevelResult(LevelStatus.INACCURATE, iterations=raw.iterations,
                               message=f"{raw.message}: bounds or hard rows violated by {worst:.3g}")
        x = qp.x_prev + d
        residual = None if level.A is None else float(np.linalg.norm(level.A @ x - level.b))
        return LevelResult(LevelStatus.SOLVED, x=x, residual=residual, slack=slack,
                           iterations=raw.iterations, message=raw.message)
