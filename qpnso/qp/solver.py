"""The hierarchical QP's solver, :class:`HierarchicalQP` (docs/method.md §7; §7.5 in general).

:meth:`HierarchicalQP.solve` checks the levels and bounds (:mod:`qpnso.qp.levels`), then takes the
line fast path (:mod:`qpnso.qp.line`) when there are at most two levels and the first is a full-rank
(n − 1)-row task whose exact solutions meet the bounds, else the general null-space cascade
(:mod:`qpnso.qp.cascade`): level after level, each QP solved by a back end
(:mod:`qpnso.qp.backends`) and its answer checked, stopping at the first failed level or before a
level that would overrun the optional time budget.  The last solved level's answer is then made
unique, the least-norm point of its optimal set, so that it never depends on what a solver's warm
start left along directions no level owns.  What it returns is in :mod:`qpnso.qp.results`.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from typing import Sequence

import numpy as np

from qpnso.errors import ConfigError, InputError
from qpnso.qp.arrays import Basis, QPArrays, Segment
from qpnso.qp.backends import _make_backend, _Raw, active_set_solve, finite_data_raw, not_finite_raw, solved_vector
from qpnso.qp.cascade import (
    _NO_VECTOR,
    Cascade,
    LevelQP,
    _c,
    _eye,
    advance_cascade,
    build_level_qp,
    level_answer,
    strictly_convex,
)
from qpnso.qp.levels import Level, _LevelData, _trusted_level, _validate_bounds, _validate_level
from qpnso.qp.line import (
    _OWNED_0,
    LINE_ANSWER_NOT_FINITE,
    LINE_ANSWER_OK,
    LINE_ANSWER_VIOLATED,
    LINE_CUT,
    LINE_NOT_FINITE,
    LINE_OK,
    LINE_SINGULAR,
    _Line,
    _line_level_qp,
    _task_line,
    checked_line_answer,
    least_norm_point,
    line_answer,
    line_dtype,
    line_setup,
)
from qpnso.qp.problem import SOLVED, STOPPED, TOOL_HELD, problem_levels
from qpnso.qp.results import HQPResult, HQPStats, LevelResult, LevelStatus, level_failure
from qpnso.qp.settings import NATIVE_BACKEND, QPSettings, tolerance_record
from qpnso.records import new_record

__all__ = ["HierarchicalQP"]


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
        self._tol = tolerance_record(self.settings)
        self._line: np.ndarray = np.zeros(0)  # line_setup's record, made for the problems of one record type
        self._line_for: np.dtype | None = None
        self._line_nv = self._line_p = np.zeros(0, dtype=np.int64)
        self._line_fast_path = settings.line_fast_path
        self._box_native = backend == NATIVE_BACKEND and settings.box_constraints
        self._line_views: dict[tuple[int, int], QPArrays] = {}

    def solve(
        self,
        levels: Sequence[Level],
        lb: np.ndarray | None = None,
        ub: np.ndarray | None = None,
        check: bool = True,
        time_budget: float | None = None,
    ) -> HQPResult:
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
        if (
            not isinstance(levels, (list, tuple))
            and (isinstance(levels, Level) or not isinstance(levels, Sequence))
            or len(levels) == 0
        ):
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
        line = _task_line(data[0], lo, hi, self.settings) if self.settings.line_fast_path and len(data) <= 2 else None
        results = self._solve_cascade(data, lo, hi, time_budget) if line is None else self._solve_on_line(data, line)
        return self._finish(results, len(data), t0)

    def _solve_cascade(
        self, data: list[_LevelData], lo: np.ndarray, hi: np.ndarray, time_budget: float | None = None
    ) -> list[LevelResult]:
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
                results.append(
                    LevelResult(
                        LevelStatus.TIME_BUDGET,
                        message=f"the cascade's time budget of {time_budget * 1e3:.3g} ms would be spent by this level",
                    )
                )
                break
            level_start = time.thread_time() if time_budget is not None else 0.0
            qp = build_level_qp(level, cascade, self.settings, self._tol)
            result = self._solve_level(k, level, qp)
            results.append(result)
            if not result.ok:
                break
            assert result.x is not None  # a solved level has its x
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
        qp = build_level_qp(data, cascade, self.settings, self._tol)
        raw = active_set_solve(qp.arrays, self.settings.max_iter_active_set)
        result = self._check(data, qp, raw)
        return result.x if result.ok and result.x is not None else cascade.x  # (solved: x is set)

    def reset(self) -> None:
        """Forget every warm start, persistent solver object and counter: from here the solver
        answers exactly as a new one."""
        self.stats = HQPStats()
        self._backend = _make_backend(self.backend, self.settings, self.stats)

    def warm_up(self, line: bool = True) -> None:
        """Load (or compile, once per machine) every kernel of the cascade by solving two small ones (a
        two-row task above a task, a cost and soft and hard rows: the general cascade; with ``line``, an
        (n−1)-row task above a cost with a soft row: :meth:`solve`'s line fast path), then :meth:`reset`: a
        control tick that first takes a path must not pay for it (loading two kernels took 30–60 ms,
        measured).  A :class:`~qpnso.control.controller.Controller` needs only the general cascade (its
        ticks' line is :meth:`solve_problem`'s, warmed by its own dry ticks): ``line=False``."""
        n = self.n
        eye = np.eye(n)
        self.solve(
            [
                Level(A=eye[:2], b=np.ones(2)),
                Level(A=eye[2:3], b=np.ones(1), H=eye, C=eye[:1], l=np.zeros(1), u=np.zeros(1), slack_weight=1.0),
                Level(g=np.ones(n), C=eye[1:2], l=-np.ones(1), u=np.ones(1)),
            ],
            -np.ones(n),
            np.ones(n),
        )
        if not line:
            self.reset()
            return
        self.solve(
            [
                Level(A=eye[: n - 1], b=np.zeros(n - 1)),  # the line fast path's kernels
                Level(H=eye, g=np.ones(n), C=eye[n - 1 :], l=np.zeros(1), u=np.zeros(1), slack_weight=1.0),
            ],
            -np.ones(n),
            np.ones(n),
        )
        self.reset()

    def _solve_on_line(self, data: list[_LevelData], line: _Line) -> list[LevelResult]:
        """Line fast path (:mod:`qpnso.qp.line`): level 1 in closed form, level 2 (if any) on the line."""
        t1 = time.perf_counter()
        x1 = least_norm_point(line.x0, line.direction, line.t_lo, line.t_hi)
        first = LevelResult(
            LevelStatus.SOLVED,
            x=x1,
            residual=_residual(data[0], x1),
            iterations=0,
            message="closed form: the task's exact solutions meet the bounds on a line",
        )
        t2 = time.perf_counter()
        first.solve_time_s = t2 - t1
        if len(data) == 1:
            return [first]
        level = data[1]
        qp = _line_level_qp(level, line, self._tol)
        arrays = qp.arrays
        raw = finite_data_raw(arrays) or self._line_raw(arrays, qp)
        second = self._line_result(raw, qp, line)
        if second.ok:
            assert second.x is not None  # a solved level has its x
            second.residual = _residual(level, second.x)
        second.solve_time_s = time.perf_counter() - t2
        return [first, second]

    def _line_raw(self, qp: QPArrays, level_qp: LevelQP | None = None) -> _Raw:
        """The back end's answer to a line's level 2 (``v = [t; σ]``) on its persistent level-2 object,
        unchecked; ``level_qp`` the same QP as a :class:`LevelQP` for a back end without a native box."""
        if self._box_native:
            return self._backend.solve_arrays(1, qp)
        if level_qp is None:
            H, g, C, l, u, box_l, box_u = qp
            level_qp = LevelQP(H, g, C, l, u, box_l, box_u, _NO_VECTOR, _NO_BASIS, _OWNED_0, None, C.shape[0], 0, 0)
            # (a back end reads H, g, the rows and the box only)
        return self._backend.solve(1, level_qp)

    def _line_result(self, raw: _Raw, qp: LevelQP, line: _Line) -> LevelResult:
        """A raw line answer judged (:func:`checked_line_answer`: box on ``t`` and hard rows within
        ``feasibility_tol``) with the soft rows' slack."""
        if raw.status is not LevelStatus.SOLVED:
            return LevelResult(raw.status, iterations=raw.iterations, message=raw.message)
        code, worst = LINE_ANSWER_NOT_FINITE, math.inf
        v = solved_vector(raw, qp.g.shape)
        if v is not None:
            segment = Segment(line.x0, line.direction, line.t_lo, line.t_hi)
            code, x, worst, slack = checked_line_answer(v, segment, qp.arrays, qp.n_slack, self._tol)
        if code != LINE_ANSWER_OK:
            return LevelResult(LevelStatus.INACCURATE, iterations=raw.iterations, message=_refusal(raw, code, worst))
        return LevelResult(
            LevelStatus.SOLVED, x=x, slack=slack if qp.n_slack else None, iterations=raw.iterations, message=raw.message
        )

    def solve_problem(self, problem: np.ndarray, solution: np.ndarray, time_budget: float | None = None) -> str:
        """Solve a control tick's problem record (:mod:`qpnso.qp.problem`) into ``solution``; returns ""
        or, when a level failed, why (as :attr:`HQPResult.status` words it).

        The line fast path (:func:`qpnso.qp.line.line_setup`) when level 1's exact solutions within the
        bounds and hard rows form a segment, level 2 then on ProxSuite's persistent object; else the
        general cascade on :func:`qpnso.qp.problem.problem_levels` (with ``time_budget``, :meth:`solve`).
        A failed level 2 leaves level 1's least-norm answer in ``solution.x`` (``TOOL_HELD``); a failed
        level 1 leaves zero (``STOPPED``)."""
        line = self._line if problem.dtype is self._line_for else self._line_record(problem)
        code = line_setup(problem, self._tol, line) if self._line_fast_path else LINE_SINGULAR
        if code == LINE_SINGULAR or code == LINE_CUT:
            return self._solve_problem_levels(problem, solution, time_budget)
        nv = self._line_nv[0]  # (views of the line record's sizes: a field read of the record costs 10x)
        if code == LINE_NOT_FINITE:
            raw = _Raw(None, LevelStatus.SOLVER_ERROR, 0, "non-finite QP data (NaN or inf in the problem)")
        elif nv:
            raw = self._line_raw(self._line_arrays(line, nv, self._line_p[0]))
        else:
            raw = _Raw(_NO_VECTOR, LevelStatus.SOLVED, 0, "")
        v = solved_vector(raw, (nv,)) if code == LINE_OK else None
        answer = line_answer(v, problem, line, self._tol, solution) if v is not None else LINE_ANSWER_NOT_FINITE
        ok = answer == LINE_ANSWER_OK
        self._count(ok)
        if ok:
            return ""
        S, L = solution[0], line[0]
        S["x"], S["x1"], S["outcome"], S["out_of_time"] = L["x1"], L["x1"], TOOL_HELD, 0
        status = raw.status if raw.status is not LevelStatus.SOLVED else LevelStatus.INACCURATE
        result = LevelResult(status, message=_refusal(raw, answer, float(S["violation"])))
        return level_failure(1, 2, result)

    def _line_record(self, problem: np.ndarray) -> np.ndarray:
        """The line record for problems of this one's record type (made once: its views go to ProxSuite)."""
        if problem.dtype is not self._line_for:
            line = new_record(line_dtype(self.n, problem.dtype["soft_l"].shape[0]))
            self._line, self._line_for, self._line_views = line, problem.dtype, {}
            self._line_nv, self._line_p = line["nv"], line["p"]
        return self._line

    def _line_arrays(self, line: np.ndarray, nv: int, p: int) -> QPArrays:
        """The line's level-2 QP as views of ``line`` of the QP's shape (made once per shape)."""
        views = self._line_views.get((nv, p))
        if views is None:
            L = line[0]
            views = self._line_views[(nv, p)] = QPArrays(
                L["H"][:nv, :nv],
                L["g"][:nv],
                L["C"][:p, :nv],
                L["l"][:p],
                L["u"][:p],
                L["box_l"][:nv],
                L["box_u"][:nv],
            )
        return views

    def _solve_problem_levels(self, problem: np.ndarray, solution: np.ndarray, time_budget: float | None) -> str:
        """The problem through the general cascade (:meth:`solve`'s, on its levels, unchecked), into ``solution``.
        Straight to the cascade: :func:`~qpnso.qp.line.line_setup` has found no line for this problem (or the
        line fast path is off), and :meth:`solve`'s own line test, on the same level 1, would find none either."""
        P, S = problem[0], solution[0]
        t0 = time.perf_counter()
        data = [_trusted_level(level) for level in problem_levels(problem)]
        result = self._finish(self._solve_cascade(data, P["lb"], P["ub"], time_budget), len(data), t0)
        first, last = result.levels[0], result.levels[-1]
        S["out_of_time"] = result.out_of_time
        S["x1"] = first.x if first.x is not None else 0.0
        S["tool_residual"] = -1.0 if first.residual is None else first.residual
        S["slack_max"] = last.slack.max() if last.slack is not None and last.slack.size else -1.0
        held = result.x is not None and bool(np.all(np.isfinite(result.x)))
        S["x"] = result.x if held else 0.0
        S["outcome"] = SOLVED if result.ok else (TOOL_HELD if held else STOPPED)
        return "" if result.ok else result.status

    def _count(self, ok: bool) -> None:
        """Count one cascade in ``stats``."""
        self.stats.solves += 1
        if not ok:
            self.stats.failures += 1

    def _solve_level(self, k: int, level: _LevelData, qp: LevelQP) -> LevelResult:
        """Back-end solve of one level's QP and verification of its answer."""
        t_level = time.perf_counter()
        if qp.H.shape[0] == 0 or qp.r == 0:  # nothing left to choose: x = x_prev, slack as it falls
            raw = _Raw(np.zeros(qp.H.shape[0]), LevelStatus.SOLVED, 0, "no free direction left")
        else:
            raw = self._backend.solve(k, qp) if qp.finite else not_finite_raw()
        result = self._check(level, qp, raw)
        result.solve_time_s = time.perf_counter() - t_level
        return result

    def _finish(self, results: list[LevelResult], n_levels: int, t0: float) -> HQPResult:
        """The cascade's result: the last good level's answer, the first failure named."""
        failed = None if results[-1].ok else len(results) - 1
        x_good = results[-1].x if failed is None else (results[-2].x if len(results) > 1 else None)
        results += [LevelResult(LevelStatus.SKIPPED) for _ in range(len(results), n_levels)]
        self._count(failed is None)
        status = "solved" if failed is None else level_failure(failed, n_levels, results[failed])
        return HQPResult(
            x=None if x_good is None else x_good.copy(),
            ok=failed is None,
            status=status,
            failed_level=failed,
            levels=results,
            solve_time_s=time.perf_counter() - t0,
        )

    def _check(self, level: _LevelData, qp: LevelQP, raw: _Raw) -> LevelResult:
        """Verify a level's answer: finite, and every bound and hard row (this level's and
        the inherited ones) within ``feasibility_tol`` (:func:`level_answer`); report residual and slack."""
        if raw.status is not LevelStatus.SOLVED:
            return LevelResult(raw.status, iterations=raw.iterations, message=raw.message)
        v = raw.v
        if v is None or v.shape != qp.g.shape or not math.isfinite(v.sum()):
            return LevelResult(
                LevelStatus.INACCURATE,
                iterations=raw.iterations,
                message=f"{raw.message}: non-finite or mis-shaped solution",
            )
        basis = Basis(_c(qp.x_prev), _c(qp.Z), qp.r == qp.Z.shape[0], True)
        x, worst, slack = level_answer(_c(v), basis, qp.arrays, qp.slack_start, qp.n_slack)
        if not worst <= self.settings.feasibility_tol:
            status = LevelStatus.INFEASIBLE if qp.r == 0 else LevelStatus.INACCURATE
            return LevelResult(
                status, iterations=raw.iterations, message=f"{raw.message}: bounds or hard rows violated by {worst:.3g}"
            )
        return LevelResult(
            LevelStatus.SOLVED,
            x=x,
            residual=_residual(level, x),
            slack=slack if qp.n_slack else None,
            iterations=raw.iterations,
            message=raw.message,
        )


_NO_BASIS = np.zeros((0, 0))


def _refusal(raw: _Raw, code: int, worst: float) -> str:
    """Why a line answer was refused (:func:`checked_line_answer`'s ``code``), after the back end's message."""
    if raw.status is not LevelStatus.SOLVED:
        return raw.message
    if code == LINE_ANSWER_VIOLATED:
        return f"{raw.message}: bounds or hard rows violated by {worst:.3g}"
    return f"{raw.message}: non-finite or mis-shaped solution"


def _out_of_time(start: float, level_start: float, budget: float) -> bool:
    """Whether the next level would overrun ``budget`` (s of CPU time since ``start``), judged by the
    last level's own time (since ``level_start``): the levels of one cascade cost about the same."""
    now = time.thread_time()
    return now - start + (now - level_start) > budget


def _residual(level: _LevelData, x: np.ndarray) -> float | None:
    """``‖A x − b‖`` (units of b, unweighted) of a level's task, None without one."""
    if level.A is None:
        return None
    e = level.A @ x - level.b
    return math.sqrt(float(e @ e))
