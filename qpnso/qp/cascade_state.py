"""The general cascade's state and the kernels that run a level on it (docs/method.md §7.5).

What the levels above leave to the next one (their answer ``x``, the orthonormal basis ``Z`` of the
directions they leave free, the bounds and inherited rows widened to contain ``x``), the QP of the level
being solved and that level's checked answer live in a record of scalars (:data:`STATE_DTYPE`) and one
buffer of floats (:class:`StateArrays`): one Numba type for every size, so each kernel compiles once.  A
level is two kernel calls around its back end's solve: :func:`build_level` writes its QP
(:func:`~qpnso.qp.cascade.level_qp_arrays`), :func:`finish_level` checks the back end's answer
(:func:`~qpnso.qp.cascade.level_answer`) and, unless it was the last level and strictly convex, advances
the state (:func:`~qpnso.qp.cascade.advance_basis`, :func:`~qpnso.qp.cascade.pass_down`).  A control
tick's problem record (:mod:`qpnso.qp.problem`) is read by the kernels themselves (:func:`problem_level`);
a caller's levels come as :class:`~qpnso.qp.arrays.LevelParts`.  :class:`CascadeState` is what Python
holds: the record, the buffer, and the views of the QP that a back end gets.

The QP is kept in compact (top-left, row-major) layouts, so that the views given to the back end are
contiguous: one view per QP shape, made once.  (Before these kernels the cascade was Python around them:
p50 309 → 127 µs of thread CPU a tick on 4085 captured general-cascade problems, answers bit-identical,
docs/benchmarks.md.)
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from qpnso.linalg import dot, matvec
from qpnso.qp.arrays import Basis, Inherited, LevelParts, QPArrays
from qpnso.qp.cascade import advance_basis, level_answer, level_qp_arrays, pass_down, strictly_convex
from qpnso.records import new_record

__all__ = ["CascadeState", "STATE_DTYPE", "StateArrays"]

LEVEL_ADVANCED, LEVEL_UNIQUE, LEVEL_VIOLATED, LEVEL_NOT_FINITE = 0, 1, 2, 3
""":func:`finish_level`'s codes: the answer is accepted and the state advanced; accepted and the level was
the last and strictly convex (nothing left to choose: the state is not advanced); refused, a bound or hard
row violated by more than ``feasibility_tol`` (``worst``); refused, not finite or of the wrong length."""


STATE_DTYPE = np.dtype(
    [
        (name, np.int64)
        for name in (
            "n",
            "rows",
            "slack",
            "r",
            "full",
            "depth",
            "p",
            "nv",
            "m",
            "box",
            "finite",
            "n_slack",
            "slack_start",
            "owned",
            "has_task",
        )
    ]
    + [("worst", np.float64), ("residual", np.float64)]
)
"""The cascade's scalars: its capacity (``n`` joint velocities, ``rows`` rows of all levels, at most ``slack``
soft rows a level), the state (``r`` free directions, ``full``: Z is the identity, ``depth`` levels solved,
``p`` inherited rows), the level's QP (``nv`` variables, ``m`` rows, ``box``, ``finite``, its soft rows from
``slack_start``, ``owned`` task directions, ``has_task``) and its answer (``worst`` violation, weighted task
``residual``, −1 without a task).  One type for every capacity: the arrays are in a separate buffer
(:func:`state_arrays`), so that the kernels compile once."""


class StateArrays(NamedTuple):
    """The cascade's arrays, views of its buffer: the answer so far ``x`` (rad/s) and the free basis ``Z``
    (n×r, flat), the bounds, the inherited rows ``l ≤ C x ≤ u`` (the first ``p``); the level's QP in compact
    row-major layouts (``H`` nv×nv, ``g``, ``A`` m×nv, ``lo``, ``hi``, the box), ``V`` = [owned | free] task
    directions in z (r×r, flat); the level's answer ``xk`` and the slack of its soft rows."""

    x: np.ndarray
    Z: np.ndarray
    lb: np.ndarray
    ub: np.ndarray
    C: np.ndarray
    l: np.ndarray
    u: np.ndarray
    H: np.ndarray
    g: np.ndarray
    A: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    box_l: np.ndarray
    box_u: np.ndarray
    V: np.ndarray
    xk: np.ndarray
    slack: np.ndarray


@njit(cache=True)
def _sizes(n, rows, slack):
    """The length of each of :class:`StateArrays`' arrays in the buffer, in order (``C``: rows × n)."""
    nv, m = n + slack, rows + n
    return (n, n * n, n, n, rows * n, rows, rows, nv * nv, nv, m * nv, m, m, nv, nv, n * n, n, slack)


def buffer_size(n: int, rows: int, slack: int) -> int:
    """The buffer's length (floats) for a cascade of this capacity."""
    return int(sum(_sizes(n, rows, slack)))


@njit(cache=True)
def state_arrays(S, buf):
    """:class:`StateArrays` of the state ``S`` (a :data:`STATE_DTYPE` record) in its buffer ``buf``."""
    n, rows = S.n, S.rows
    sizes = _sizes(n, rows, S.slack)
    o = np.zeros(len(sizes) + 1, dtype=np.int64)
    for i in range(len(sizes)):
        o[i + 1] = o[i] + sizes[i]
    return StateArrays(
        buf[o[0] : o[1]],
        buf[o[1] : o[2]],
        buf[o[2] : o[3]],
        buf[o[3] : o[4]],
        buf[o[4] : o[5]].reshape((rows, n)),
        buf[o[5] : o[6]],
        buf[o[6] : o[7]],
        buf[o[7] : o[8]],
        buf[o[8] : o[9]],
        buf[o[9] : o[10]],
        buf[o[10] : o[11]],
        buf[o[11] : o[12]],
        buf[o[12] : o[13]],
        buf[o[13] : o[14]],
        buf[o[14] : o[15]],
        buf[o[15] : o[16]],
        buf[o[16] : o[17]],
    )


@njit(cache=True)
def _start(S, a):
    """The state before the first level: ``x = 0``, ``Z = I``, no rows (the bounds are written by
    :meth:`CascadeState.start`, which marks the state to be started with ``depth = −1``)."""
    n = S.n
    a.x[:] = 0.0
    a.Z[: n * n] = np.eye(n).ravel()
    S.r, S.full, S.depth, S.p = n, 1, 0, 0


@njit(cache=True)
def _basis(S, a):
    """(x, Z) of the state: the answer so far and the free basis (n, r), as views."""
    n, r = S.n, S.r
    return a.x, a.Z[: n * r].reshape((n, r))


@njit(cache=True)
def qp_views(a, nv, m, box):
    """A level's QP of ``nv`` variables and ``m`` rows as :class:`~qpnso.qp.arrays.QPArrays` views of the
    buffer's arrays ``a`` (compact row-major layouts; no ``box``: empty box arrays)."""
    nb = nv if box else 0
    return QPArrays(
        a.H[: nv * nv].reshape((nv, nv)), a.g[:nv], a.A[: m * nv].reshape((m, nv)), a.lo[:m], a.hi[:m],
        a.box_l[:nb], a.box_u[:nb],
    )  # fmt: skip


@njit(cache=True)
def build_level(state, buf, level, tol):
    """The QP of ``level`` (:class:`~qpnso.qp.arrays.LevelParts`) in the state's free coordinates
    (:func:`~qpnso.qp.cascade.level_qp_arrays`), written into the buffer.  Returns ``(nv, m, box, finite, r)``:
    its shape, whether the bounds are a box (Z the identity), whether its data can be solved, and the number
    of free directions it was built in."""
    S = state[0]
    a = state_arrays(S, buf)
    if S.depth < 0:
        _start(S, a)
    x, Z = _basis(S, a)
    p = S.p
    inherited = Inherited(a.lb, a.ub, a.C[:p], a.l[:p], a.u[:p])
    qp, box, owned_z, free_z, has_task, finite = level_qp_arrays(
        level, Basis(x, Z, S.full != 0, S.depth > 0), inherited, tol
    )
    H, g, C, lo, hi, box_l, box_u = qp
    nv, m, r, k = g.shape[0], lo.shape[0], Z.shape[1], owned_z.shape[1]
    a.H[: nv * nv] = H.ravel()
    a.g[:nv] = g
    a.A[: m * nv] = C.ravel()
    a.lo[:m], a.hi[:m] = lo, hi
    a.box_l[:nv], a.box_u[:nv] = box_l, box_u
    S.nv, S.m, S.box, S.finite = nv, m, box, finite
    S.n_slack, S.slack_start = level.n_slack, p
    V = a.V[: r * r].reshape((r, r))
    V[:, :k] = owned_z
    V[:, k:] = free_z
    S.owned, S.has_task = k, has_task
    return nv, m, box, finite, r


@njit(cache=True)
def check_level(state, buf, level, v, tol):
    """The back end's answer ``v = [z; σ]`` to the state's QP checked in joint space
    (:func:`~qpnso.qp.cascade.level_answer`): ``xk``, ``slack``, ``worst`` and ``residual`` written.
    Returns :data:`LEVEL_NOT_FINITE`, :data:`LEVEL_VIOLATED` or :data:`LEVEL_ADVANCED` (accepted)."""
    S = state[0]
    if v.shape[0] != S.nv or not math.isfinite(v.sum()):
        S.worst = math.inf
        return LEVEL_NOT_FINITE
    a = state_arrays(S, buf)
    x_prev, Z = _basis(S, a)
    basis = Basis(x_prev, Z, Z.shape[1] == Z.shape[0], True)
    x, worst, slack = level_answer(v, basis, qp_views(a, S.nv, S.m, S.box), S.slack_start, S.n_slack)
    T = tol[0]
    if T.feasibility_tol < worst <= T.bound_repair_tol:
        worst = repair_bounds(x, a.lb, a.ub, Inherited(a.lb, a.ub, a.C[: S.p], a.l[: S.p], a.u[: S.p]), level, slack)
    a.xk[:], S.worst = x, worst
    a.slack[: slack.shape[0]] = slack
    if level.A.shape[0]:
        e = matvec(level.A, x) - level.b
        S.residual = math.sqrt(dot(e, e))
    else:
        S.residual = -1.0
    return LEVEL_ADVANCED if worst <= tol[0].feasibility_tol else LEVEL_VIOLATED


@njit(cache=True)
def row_violation(C, l, u, x, i):
    """How far row ``i`` of ``l ≤ C x ≤ u`` is violated at ``x`` (≤ 0: it holds)."""
    row = dot(C[i], x)
    return max(l[i] - row, row - u[i])


@njit(cache=True)
def repair_bounds(x, lb, ub, inherited, level, slack):
    """An answer ``x`` (rad/s) a little off its bounds, projected onto them in place (clipped to
    ``[lb, ub]``); returns its worst violation of the hard rows (inherited and the level's own, joint space) at the
    projected ``x`` and rewrites the soft rows' ``slack``.  Why: a bound row of a joint the free directions barely
    move (``Z_i`` ~ 1e-6, a joint at its bound after level 1) makes the level's answer hinge on round-off: DAQP
    met such a row to 3.4e-6 only, on one CPU and not on another (issue 31).  Clipping moves the joint by
    less than ``bound_repair_tol``; the tool by ``J·δ`` — what a solver's tolerance on the bounds allows anyway."""
    for i in range(x.shape[0]):
        x[i] = min(max(x[i], lb[i]), ub[i])
    worst = 0.0
    for i in range(inherited.C.shape[0]):
        worst = max(worst, row_violation(inherited.C, inherited.l, inherited.u, x, i))
    for i in range(level.C.shape[0]):
        violation = row_violation(level.C, level.l, level.u, x, i)
        if i < level.n_slack:
            slack[i] = max(violation, 0.0)
        else:
            worst = max(worst, violation)
    return worst


@njit(cache=True)
def advance_state(state, buf, level, x, tol):
    """The state after ``level`` (whose QP is the state's) was solved with joint velocity ``x`` (rad/s): the
    directions it owns removed from ``Z`` (:func:`~qpnso.qp.cascade.advance_basis`), its rows appended to the
    inherited ones, rows and bounds widened to contain ``x`` (:func:`~qpnso.qp.cascade.pass_down`)."""
    S = state[0]
    a = state_arrays(S, buf)
    n = S.n
    _, Z = _basis(S, a)
    r, k = Z.shape[1], S.owned
    free_z = a.V[: r * r].reshape((r, r))[:, k:] if S.has_task else np.eye(r)
    Z_next, changed = advance_basis(level, Z.copy(), S.full != 0, np.ascontiguousarray(free_z), x, tol)
    if changed:
        c = Z_next.shape[1]
        a.Z[: n * c] = Z_next.ravel()
        S.r, S.full = c, 0
    p, q = S.p, level.C.shape[0]
    a.C[p : p + q], a.l[p : p + q], a.u[p : p + q] = level.C, level.l, level.u
    p += q
    S.p = p
    T = tol[0]
    if p:
        pass_down(a.l[:p], matvec(a.C[:p], x), a.u[:p], T.active_tol)
    pass_down(a.lb, x, a.ub, T.active_tol)
    a.x[:] = x
    S.depth += 1


@njit(cache=True)
def finish_level(state, buf, level, v, last, tol):
    """:func:`check_level`, then, if the answer is accepted, :func:`advance_state` — unless the level is the
    ``last`` and its QP strictly convex (:func:`~qpnso.qp.cascade.strictly_convex`: its answer is unique,
    :data:`LEVEL_UNIQUE`).  Returns the code (module constants) and the free directions ``r`` left after it."""
    S = state[0]
    code = check_level(state, buf, level, v, tol)
    if code != LEVEL_ADVANCED:
        return code, S.r
    a = state_arrays(S, buf)
    if last:
        nv = S.nv
        if strictly_convex(a.H[: nv * nv].reshape((nv, nv)), S.r, tol[0].rank_tol):
            return LEVEL_UNIQUE, S.r
    advance_state(state, buf, level, a.xk.copy(), tol)
    return LEVEL_ADVANCED, S.r


@njit(cache=True)
def problem_levels_count(problem):
    """How many levels a tick's problem record has (1 or 2): level 2 when it has an objective or soft rows
    (:func:`qpnso.qp.problem.problem_levels`)."""
    pb = problem[0]
    if pb.has_level2:
        return 2 if pb.m2 or pb.use_H2 or pb.use_g2 or pb.n_soft else 1
    return 2 if pb.n_soft else 1


@njit(cache=True)
def problem_level(problem, k):
    """Level ``k`` (0 or 1) of a tick's problem record as :class:`~qpnso.qp.arrays.LevelParts` (fresh arrays):
    level 1 the tool task with the hard rows, level 2 its objective (``H2`` symmetrised) with the soft rows,
    the slack scaled by 1/√(2ρ); soft rows without an objective get the least-norm ``½‖x‖²``
    (:func:`qpnso.qp.problem.problem_levels` gives the same levels as :class:`~qpnso.qp.levels.Level`)."""
    pb = problem[0]
    n = pb.lb.shape[0]
    none2, none1 = np.zeros((0, n)), np.zeros(0)
    if k == 0:
        nh = pb.n_hard
        return LevelParts(pb.A1[:].copy(), pb.b1[:].copy(), none2, none1, pb.hard_C[:nh].copy(),
                          pb.hard_l[:nh].copy(), pb.hard_u[:nh].copy(), 0, 0.0)  # fmt: skip
    own, ns = pb.has_level2 != 0, pb.n_soft
    m = pb.m2 if own else 0
    H = none2
    if pb.use_H2 or not own:
        H = 0.5 * (pb.H2[:] + pb.H2[:].T)
    return LevelParts(
        pb.A2[:m].copy(),
        pb.b2[:m].copy(),
        H,
        pb.g2[:].copy() if pb.use_g2 and own else none1,
        pb.soft_C[:ns].copy(),
        pb.soft_l[:ns].copy(),
        pb.soft_u[:ns].copy(),
        ns,
        1.0 / math.sqrt(2.0 * pb.slack_weight) if ns else 0.0,
    )


@njit(cache=True)
def build_problem_level(state, buf, problem, k, tol):
    """:func:`build_level` on level ``k`` of a tick's problem record (:func:`problem_level`)."""
    return build_level(state, buf, problem_level(problem, k), tol)


@njit(cache=True)
def finish_problem_level(state, buf, problem, k, v, last, tol):
    """:func:`finish_level` on level ``k`` of a tick's problem record (:func:`problem_level`)."""
    return finish_level(state, buf, problem_level(problem, k), v, last, tol)


def least_norm_level(n: int) -> LevelParts:
    """The level ``min ½‖x‖²`` (no task, no rows) whose optimum over the state's optimal set is the cascade's
    unique answer, as the kernels take a caller's level (built once per ``n``)."""
    level = _LEAST_NORM.get(n)
    if level is None:
        rows, vector = np.zeros((0, n)), np.zeros(0)
        level = _LEAST_NORM[n] = LevelParts(rows, vector, np.eye(n), vector, rows, vector, vector, 0, 0.0)
    return level


_LEAST_NORM: dict[int, LevelParts] = {}


class CascadeState:
    """A cascade over ``n`` joint velocities whose levels have ``rows`` rows in all and at most ``slack`` soft
    rows each: its record (:data:`STATE_DTYPE`) and buffer (:class:`StateArrays`), the views of its QP a back
    end gets (one per shape, made once) and the tolerances ``tol`` its kernels read
    (:func:`qpnso.qp.settings.tolerance_record`)."""

    def __init__(self, n: int, rows: int, slack: int, tol: np.ndarray) -> None:
        self.record = record = new_record(STATE_DTYPE)
        S = record[0]
        S["n"], S["rows"], S["slack"] = n, max(rows, 1), max(slack, 1)
        self.buffer = np.zeros(buffer_size(n, max(rows, 1), max(slack, 1)))
        self.tol = tol
        self.arrays = StateArrays(*state_arrays(S, self.buffer))  # views of the buffer
        self._views: dict[tuple[int, int, int], QPArrays] = {}
        # views of the record's scalars (a field read of a record from Python costs 10x a view's)
        self.n_slack, self.worst, self.residual = record["n_slack"], record["worst"], record["residual"]
        self._depth = record["depth"]

    def start(self, lb: np.ndarray, ub: np.ndarray) -> None:
        """Before the first level, under ``lb ≤ x ≤ ub`` (rad/s): the first :func:`build_level` starts the rest."""
        self.arrays.lb[:], self.arrays.ub[:] = lb, ub
        self._depth[0] = -1

    def qp(self, nv: int, m: int, box: int) -> QPArrays:
        """The level's QP (shape ``nv``, ``m``, ``box`` as :func:`build_level` returned it) as views of the
        buffer (:func:`qp_views`, made once per shape)."""
        key = (nv, m, int(box))
        views = self._views.get(key)
        if views is None:
            views = self._views[key] = QPArrays(*qp_views(self.arrays, nv, m, key[2]))
        return views

    def build(self, level: LevelParts) -> tuple[QPArrays, bool]:
        """:func:`build_level` on ``level``: the QP's views and whether its data can be solved."""
        nv, m, box, finite, _ = build_level(self.record, self.buffer, level, self.tol)
        return self.qp(nv, m, box), bool(finite)

    def advance(self, level: LevelParts, x: np.ndarray) -> None:
        """:func:`advance_state` with the answer ``x`` (rad/s) of the level just built."""
        advance_state(self.record, self.buffer, level, np.array(x, dtype=float), self.tol)

    @property
    def xk(self) -> np.ndarray:
        """The last checked level's answer (rad/s), a view."""
        return self.arrays.xk

    @property
    def slack(self) -> np.ndarray:
        """The slack of its soft rows, a view."""
        return self.arrays.slack

    @property
    def x(self) -> np.ndarray:
        """The answer of the levels solved (rad/s), a copy (after :meth:`start`, valid from the first build)."""
        return self.arrays.x.copy()

    @property
    def Z(self) -> np.ndarray:
        """The orthonormal basis (n, r) of the directions they leave free, a copy (valid from the first build)."""
        n, r = self.arrays.x.shape[0], int(self.record[0]["r"])
        return self.arrays.Z[: n * r].reshape(n, r).copy()
