"""The line fast path of the hierarchical QP (docs/method.md §7.3, §7.4).

**Line fast path** (``QPSettings.line_fast_path``, on by default): the
controller's first level is a plain task of n − 1 rows (6×7 tool Jacobian).
When all its singular values reach the damping threshold (nothing to damp),
its exact solutions form the line ``A⁺b + t·d`` (``d`` its unit null vector)
and, when that line meets the bounds, the level's optimal set is exactly the
segment ``t ∈ [t_lo, t_hi]`` (zero residual).  Level 1 is then known in closed
form (its reported answer: the segment's least-norm point) and level 2 is a QP
in ``t`` (plus its slacks) with the bounds as a box on ``t`` — the same QP that
:func:`~qpnso.qp.cascade.level_qp_arrays` builds with ``Z = d``, solved by the same back end
(ProxSuite, persistent and warm-started).  Whenever a bound cuts the line (the
bounds bind the tool task), the task is near-singular, or there are more than
two levels, the general cascade (:mod:`qpnso.qp.cascade`) runs.  The small factorisations are
Numba kernels (:mod:`qpnso.linalg`).  Same answers as the general cascade
(tests; its measured time: docs/changelog.md).
Level 2 on the line is :meth:`~qpnso.qp.solver.HierarchicalQP.solve_line_level`
(:meth:`~qpnso.qp.solver.HierarchicalQP.line_level_raw`, then
:meth:`~qpnso.qp.solver.HierarchicalQP.line_level_result`); the
controller's compiled tick (:mod:`qpnso.control.tick`) builds its arrays in one kernel,
calls ``line_level_raw`` and judges the answer with the same kernel
(:func:`checked_line_answer`) in its own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from qpnso.linalg import dot, least_norm_line, matvec
from qpnso.qp.arrays import Basis, LevelParts, QPArrays, Segment, qp_data_finite
from qpnso.qp.cascade import level_answer, level_parts
from qpnso.qp.levels import _LevelData
from qpnso.qp.settings import QPSettings


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
def line_segment(x0, d, lb, ub):
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
LINE_CUT = 2  # the bounds or a hard row miss the line of exact solutions (they bind the task: the QP decides)
LINE_NOT_FINITE = 3  # the line's level-2 QP is not finite (a huge finite twist can overflow): not solved


@njit(cache=True)
def task_line(A, b, lb, ub, rank_tol, damping):
    """``(code, x0, d, t_lo, t_hi)``: the exact solutions ``x0 + t·d``, ``t ∈ [t_lo, t_hi]``, of a
    plain (n−1)×n task ``A x = b`` within ``lb ≤ x ≤ ub`` (module docstring, *line fast path*);
    ``code`` :data:`LINE_SINGULAR` when ``σ_min`` may be below ``damping`` (``1/‖R⁻¹‖_F ≤ σ_min`` is
    the test: conservative by at most √(n−1)) or the line is not finite (a NaN or inf in ``A`` or ``b``:
    the general cascade then refuses the level's data), :data:`LINE_CUT` when the bounds miss the line."""
    x0, d, sigma_floor = least_norm_line(A, b)
    if not sigma_floor >= max(damping, rank_tol * max(1.0, math.sqrt(np.sum(A * A)))):
        return LINE_SINGULAR, x0, d, 0.0, 0.0
    if not np.all(np.isfinite(x0)):
        return LINE_SINGULAR, x0, d, 0.0, 0.0
    t_lo, t_hi = line_segment(x0, d, lb, ub)
    return (LINE_OK if t_lo <= t_hi else LINE_CUT), x0, d, t_lo, t_hi


@njit(cache=True)
def fold_rows(x0, d, t_lo, t_hi, C, l, u):
    """``[t_lo, t_hi]`` narrowed so that the hard rows ``l ≤ C(x0 + t·d) ≤ u`` hold on the segment:
    each row is an interval on ``t``, as a bound is (:func:`line_segment`); a row that ``d`` does not
    move (|C d| ≤ 1e-12·‖C_i‖) must hold at ``x0``.  Empty: ``t_lo > t_hi``."""
    for i in range(C.shape[0]):
        cd, cx, size = 0.0, 0.0, 0.0
        for j in range(d.shape[0]):
            cd += C[i, j] * d[j]
            cx += C[i, j] * x0[j]
            size = max(size, abs(C[i, j]))
        if abs(cd) > 1e-12 * size:
            a, c = (l[i] - cx) / cd, (u[i] - cx) / cd
            t_lo, t_hi = max(t_lo, min(a, c)), min(t_hi, max(a, c))
        elif cx < l[i] or cx > u[i]:
            return 1.0, 0.0
    return t_lo, t_hi


@njit(cache=True)
def least_norm_point(x0, d, t_lo, t_hi):
    """The least-norm point of the segment ``x0 + t·d``, ``t ∈ [t_lo, t_hi]`` (``x0 ⊥ d``): level 1's answer."""
    return x0 + min(max(0.0, t_lo), t_hi) * d


def _task_line(data: _LevelData, lb: np.ndarray, ub: np.ndarray, settings: QPSettings) -> _Line | None:
    """Level 1 in closed form (:func:`task_line`), or None when it does not apply: not a plain task
    of n − 1 rows, a singular value that may be below the damping threshold, or bounds that miss the line."""
    Aw = data.Aw
    if Aw is None or data.H is not None or data.g is not None or data.C is not None or Aw.shape[0] != Aw.shape[1] - 1:
        return None
    code, x0, d, t_lo, t_hi = task_line(Aw, data.bw, lb, ub, settings.rank_tol, settings.damping_threshold)
    return _Line(x0, d, t_lo, t_hi) if code == LINE_OK else None


@njit(cache=True)
def line_qp_arrays(segment, level, tol):
    """The QP of a level (:class:`~qpnso.qp.arrays.LevelParts`) restricted to the line ``x = x0 + t·d`` of
    ``segment``, in ``v = [t; σ]``: :func:`~qpnso.qp.cascade.level_qp_arrays`' with ``Z = d`` in one dimension.

    Cost ``‖A x − b‖² + ½xᵀHx + gᵀx``: curvature and slope in ``t`` with the damping and tie-break of
    :func:`~qpnso.qp.cascade.level_qp_arrays` (``tol``: :func:`qpnso.qp.settings.tolerance_record`); rows
    ``l − C x0 ≤ (C d) t + slack_scale·σ ≤ u − C x0``; box ``[t_lo, t_hi]`` on ``t``, free slacks.
    Returns the :class:`~qpnso.qp.arrays.QPArrays`."""
    x0, d = segment.x0, segment.d
    A, H, g, C = level.A, level.H, level.g, level.C
    T = tol[0]
    curvature, slope, owned = 0.0, 0.0, False
    if A.shape[0]:
        ad = matvec(A, d)
        s2 = dot(ad, ad)
        slope += 2.0 * dot(ad, matvec(A, x0) - level.b)
        if np.sqrt(s2) > T.rank_tol * max(1.0, np.sqrt(s2)):
            curvature, owned = 2.0 * max(s2, T.damping_threshold**2), True
    if H.shape[0]:
        hd = matvec(H, d)
        curvature += dot(d, hd)
        slope += dot(hd, x0)
    if g.shape[0]:
        slope += dot(d, g)
    if T.regularization > 0.0 and not owned:
        curvature += T.regularization
    nv, p = 1 + level.n_slack, C.shape[0]
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
        lq[i], uq[i] = level.l[i] - cx, level.u[i] - cx
        if i < level.n_slack:
            Cq[i, 1 + i] = level.slack_scale
    box_l, box_u = np.full(nv, -np.inf), np.full(nv, np.inf)
    box_l[0], box_u[0] = segment.t_lo, segment.t_hi
    return QPArrays(Hq, gq, Cq, lq, uq, box_l, box_u)


def _line_level_qp(data: _LevelData, line: _Line, tol: np.ndarray) -> QPArrays:
    """The QP of a level restricted to ``x = x0 + t·direction``: :func:`~qpnso.qp.cascade.level_qp_arrays` with
    ``Z`` the line's direction (same damping and tie-break), the bounds folded into a box on ``t``;
    ``tol`` the solver's tolerances (:func:`qpnso.qp.settings.tolerance_record`)."""
    d = line.direction
    return QPArrays(*line_qp_arrays(Segment(line.x0, d, line.t_lo, line.t_hi), level_parts(data, d.shape[0]), tol))


LINE_ANSWER_OK, LINE_ANSWER_NOT_FINITE, LINE_ANSWER_VIOLATED = 0, 1, 2


@njit(cache=True)
def checked_line_answer(v, segment, qp, n_slack, tol):
    """``(code, x, worst, slack)`` of :func:`level_answer` on the line of ``segment`` (``Z = d``, the box on
    ``t`` of ``qp``), judged: :data:`LINE_ANSWER_NOT_FINITE` when ``t`` (all that ``x`` depends on) is not
    finite, :data:`LINE_ANSWER_VIOLATED` when the box or a hard row is violated by more than
    ``tol``'s ``feasibility_tol``, else :data:`LINE_ANSWER_OK`."""
    x0, d = segment.x0, segment.d
    if not math.isfinite(v[0]):
        return LINE_ANSWER_NOT_FINITE, x0.copy(), math.inf, np.zeros(n_slack)
    basis = Basis(x0, d.reshape(d.shape[0], 1), False, True)
    x, worst, slack = level_answer(v, basis, qp, 0, n_slack)
    return (LINE_ANSWER_OK if worst <= tol[0].feasibility_tol else LINE_ANSWER_VIOLATED), x, worst, slack


def line_dtype(n: int, soft_rows: int) -> np.dtype:
    """The record of a problem's line (:func:`line_setup`): ``x0``, ``d``, ``[t_lo, t_hi]`` the segment of
    level 1's exact solutions (rad/s), ``x1`` its least-norm point; and level 2's line QP in
    ``v = [t; σ]`` (``nv`` = 1 + its soft rows, ``p`` rows; the arrays' top-left parts), the form
    ProxSuite gets."""
    f8, i8, m = np.float64, np.int64, max(soft_rows, 1)
    return np.dtype(
        [
            ("x0", f8, n),
            ("d", f8, n),
            ("x1", f8, n),
            ("t_lo", f8),
            ("t_hi", f8),
            ("nv", i8),
            ("p", i8),
            ("H", f8, (m + 1, m + 1)),
            ("g", f8, m + 1),
            ("C", f8, (m, m + 1)),
            ("l", f8, m),
            ("u", f8, m),
            ("box_l", f8, m + 1),
            ("box_u", f8, m + 1),
        ]
    )


@njit(cache=True)
def line_setup(problem, tol, line):
    """Level 1 of a tick's problem (:mod:`qpnso.qp.problem`) in closed form, and level 2's QP on its line,
    into ``line`` (:func:`line_dtype`); ``tol`` the solver's tolerances (:func:`qpnso.qp.settings.tolerance_record`).

    Level 1's exact solutions within the bounds (:func:`task_line`) and the hard rows (:func:`fold_rows`),
    their least-norm point ``x1``; level 2 (task, quadratic, linear term, soft rows with the slack
    scaled by 1/√(2ρ)) restricted to the line (:func:`line_qp_arrays`).  Returns :data:`LINE_OK`, or why
    the line does not apply (:data:`LINE_SINGULAR`, :data:`LINE_CUT`) or its QP is not finite
    (:data:`LINE_NOT_FINITE`)."""
    pb, L, T = problem[0], line[0], tol[0]
    code, x0, d, t_lo, t_hi = task_line(pb.A1, pb.b1, pb.lb, pb.ub, T.rank_tol, T.damping_threshold)
    if code != LINE_OK:
        return code
    nh = pb.n_hard
    t_lo, t_hi = fold_rows(x0, d, t_lo, t_hi, pb.hard_C[:nh], pb.hard_l[:nh], pb.hard_u[:nh])
    if t_lo > t_hi:
        return LINE_CUT
    L.x0[:], L.d[:], L.t_lo, L.t_hi = x0, d, t_lo, t_hi
    L.x1[:] = least_norm_point(x0, d, t_lo, t_hi)
    L.nv, L.p = 0, 0
    p = pb.n_soft
    if not pb.has_level2 and not p:
        return LINE_OK
    n, own = d.shape[0], pb.has_level2 != 0  # (soft rows without an objective: the least-norm ½‖q̇‖² with them)
    m = pb.m2 if own else 0
    level = LevelParts(
        pb.A2[:m],
        pb.b2[:m],
        pb.H2[: n if pb.use_H2 or not own else 0],
        pb.g2[: n if pb.use_g2 and own else 0],
        pb.soft_C[:p],
        pb.soft_l[:p],
        pb.soft_u[:p],
        p,
        1.0 / math.sqrt(2.0 * pb.slack_weight) if p else 0.0,
    )
    qp = line_qp_arrays(Segment(x0, d, t_lo, t_hi), level, tol)
    if not qp_data_finite(qp):
        return LINE_NOT_FINITE
    H, g, C, lo, hi, box_l, box_u = qp
    nv = p + 1
    L.nv, L.p = nv, p
    L.H[:nv, :nv], L.g[:nv], L.C[:p, :nv], L.l[:p], L.u[:p] = H, g, C, lo, hi
    L.box_l[:nv], L.box_u[:nv] = box_l, box_u
    return LINE_OK


@njit(cache=True)
def line_answer(v, problem, line, tol, solution):
    """The back end's answer ``v = [t; σ]`` to :func:`line_setup`'s QP judged
    (:func:`checked_line_answer`) and, if accepted, written into ``solution``
    (:func:`qpnso.qp.problem.solution_dtype`: ``x``, the slack, level 1's residual at ``x1``); an empty ``v``:
    no level 2, ``x = x1``.  Returns the :func:`checked_line_answer` code (``solution.violation``: the
    worst violation of the box or a hard row when refused)."""
    pb, L, S = problem[0], line[0], solution[0]
    nv, p = L.nv, L.p
    S.x1[:] = L.x1
    r = matvec(pb.A1, L.x1) - pb.b1
    S.tool_residual = math.sqrt(dot(r, r))
    S.slack_max = -1.0
    S.out_of_time = 0
    if nv == 0:
        S.x[:], S.outcome = L.x1, 0
        return LINE_ANSWER_OK
    qp = QPArrays(L.H[:nv, :nv], L.g[:nv], L.C[:p, :nv], L.l[:p], L.u[:p], L.box_l[:nv], L.box_u[:nv])
    code, x, worst, slack = checked_line_answer(v, Segment(L.x0, L.d, L.t_lo, L.t_hi), qp, p, tol)
    if code != LINE_ANSWER_OK:
        S.violation = worst
        return code
    S.x[:], S.outcome = x, 0
    if p:
        S.slack_max = slack.max()
    return code
