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
from qpnso.qp.arrays import QPArrays, Segment
from qpnso.qp.backends import _make_backend, _Raw, active_set_solve, finite_data_raw, not_finite_raw, solved_vector
from qpnso.qp.cascade import _NO_VECTOR, level_parts
from qpnso.qp.cascade_state import (
    LEVEL_ADVANCED,
    LEVEL_NOT_FINITE,
    LEVEL_UNIQUE,
    LEVEL_VIOLATED,
    CascadeState,
    build_level,
    build_problem_level,
    check_level,
    finish_level,
    finish_problem_level,
    least_norm_level,
    problem_levels_count,
)
from qpnso.qp.levels import Level, _LevelData, _trusted_level, _validate_bounds, _validate_level
from qpnso.qp.line import (
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
from qpnso.qp.problem import SOLVED, STOPPED, TOOL_HELD, new_solution
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
        self._state: CascadeState | None = None  # the cascade record for problems of one record type
        self._state_for: np.dtype | None = None
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
        if line is not None:
            return self._finish(self._solve_on_line(data, line), len(data), t0)
        results = self._solve_cascade(_CallerLevels(data, self.n, self._tol), lo, hi, time_budget)
        return self._finish(results, len(data), t0)

    def _solve_cascade(
        self, levels: "_Levels", lo: np.ndarray, hi: np.ndarray, time_budget: float | None = None
    ) -> list[LevelResult]:
        """Level after level in the null-space basis, on ``levels``' cascade record
        (:mod:`qpnso.qp.cascade_state`: two kernel calls and a back-end solve a level); stops at the first
        failed level, or before a level that would overrun ``time_budget`` (s of CPU time, :meth:`solve`).
        The last solved level's answer is then made unique: the least-norm point of its optimal set
        (:meth:`_least_norm`), never whatever a solver's warm start left along the directions no level owns."""
        state = levels.state
        state.start(lo, hi)
        results: list[LevelResult] = []
        free = 0  # directions left free after the last level that advanced the state (0: none advanced)
        count = levels.count
        start = level_start = time.thread_time() if time_budget is not None else 0.0
        for k in range(count):
            if k and time_budget is not None and _out_of_time(start, level_start, time_budget):
                results.append(
                    LevelResult(
                        LevelStatus.TIME_BUDGET,
                        message=f"the cascade's time budget of {time_budget * 1e3:.3g} ms would be spent by this level",
                    )
                )
                break
            level_start = time.thread_time() if time_budget is not None else 0.0
            t_level = time.perf_counter()
            nv, m, box, finite, r = levels.build(k)
            if nv == 0 or r == 0:  # nothing left to choose: x = x_prev, slack as it falls
                raw = _Raw(np.zeros(nv), LevelStatus.SOLVED, 0, "no free direction left")
            else:
                raw = self._backend.solve_arrays(k, state.qp(nv, m, box)) if finite else not_finite_raw()
            result, code, left = self._judge(levels, k, raw, r, k == count - 1)
            result.solve_time_s = time.perf_counter() - t_level
            results.append(result)
            if code == LEVEL_UNIQUE:
                return results  # its answer is unique already: no optimal set left to search
            if not result.ok:
                break
            free = left
        if free:
            last = results[-1] if results[-1].ok else results[-2]
            last.x = self._least_norm(state)
        return results

    def _judge(self, levels: "_Levels", k: int, raw: _Raw, r: int, last: bool) -> tuple[LevelResult, int, int]:
        """A back end's answer to level ``k`` checked and, if accepted, the state advanced
        (:func:`~qpnso.qp.cascade_state.finish_level`): the level's result, the kernel's code and the
        directions left free."""
        if raw.status is not LevelStatus.SOLVED or raw.v is None:
            status = raw.status if raw.status is not LevelStatus.SOLVED else LevelStatus.INACCURATE
            return LevelResult(status, iterations=raw.iterations, message=raw.message), LEVEL_NOT_FINITE, 0
        code, left = levels.finish(k, raw.v, last)
        if code == LEVEL_NOT_FINITE or code == LEVEL_VIOLATED:
            return _refused(raw, code, r, levels.state), code, 0
        state = levels.state
        x = state.xk.copy()
        ns = int(state.n_slack[0])
        result = LevelResult(
            LevelStatus.SOLVED,
            x=x,
            residual=levels.residual(k, x),
            slack=state.slack[:ns].copy() if ns else None,
            iterations=raw.iterations,
            message=raw.message,
        )
        return result, code, left

    def _least_norm(self, state: CascadeState) -> np.ndarray:
        """The least-norm joint velocity (rad/s) of the optimal set ``x + Z z`` that the cascade leaves
        (bounds and inherited rows kept): ``min ½‖x + Z z‖²``, strictly convex in ``z``, solved by DAQP
        (:func:`active_set_solve`: exact, finite).  The state's ``x`` itself if that fails (it is feasible)."""
        level = least_norm_level(self.n)
        nv, m, box, _, _ = build_level(state.record, state.buffer, level, state.tol)
        raw = active_set_solve(state.qp(nv, m, box), self.settings.max_iter_active_set)
        ok = raw.status is LevelStatus.SOLVED and raw.v is not None
        if ok and check_level(state.record, state.buffer, level, raw.v, state.tol) == LEVEL_ADVANCED:
            return state.xk.copy()
        return state.x

    def reset(self) -> None:
        """Forget every warm start, persistent solver object and counter: from here the solver
        answers exactly as a new one."""
        self.stats = HQPStats()
        self._backend = _make_backend(self.backend, self.settings, self.stats)

    def warm_up(self, line: bool = True, problem: np.ndarray | None = None) -> None:
        """Load (or compile, once per machine) every kernel of the cascade by solving small ones (a
        two-row task above a task with a soft row, above a linear cost with a hard row: the general cascade
        and its least-norm step; with ``line``, an
        (n−1)-row task above a cost with a soft row: :meth:`solve`'s line fast path; with ``problem``, a tick's
        problem record of that record type through the general cascade, :meth:`solve_problem`'s kernels being
        compiled per record type), then :meth:`reset`: a control tick that first takes a path must not pay for
        it (loading two kernels took 30–60 ms, measured).  A :class:`~qpnso.control.controller.Controller`
        warms its problem's cascade here and its line with its own dry ticks: ``line=False``."""
        n = self.n
        eye = np.eye(n)
        self.solve(
            [
                Level(A=eye[:2], b=np.ones(2)),
                Level(A=eye[2:3], b=np.ones(1), C=eye[:1], l=np.zeros(1), u=np.zeros(1), slack_weight=1.0),
                Level(g=np.ones(n), C=eye[1:2], l=-np.ones(1), u=np.ones(1)),  # (three directions left: least norm)
            ],
            -np.ones(n),
            np.ones(n),
        )
        if problem is not None:
            self._solve_problem_levels(_warm_up_problem(problem), new_solution(n), None)
        if line:
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
        raw = finite_data_raw(qp) or self._backend.solve_arrays(1, qp, warm=False)  # (a new line each tick)
        second = self._line_result(raw, qp, level.n_slack, line)
        if second.ok:
            assert second.x is not None  # a solved level has its x
            second.residual = _residual(level, second.x)
        second.solve_time_s = time.perf_counter() - t2
        return [first, second]

    def _line_result(self, raw: _Raw, qp: QPArrays, n_slack: int, line: _Line) -> LevelResult:
        """A raw line answer judged (:func:`checked_line_answer`: box on ``t`` and hard rows within
        ``feasibility_tol``) with the soft rows' slack."""
        if raw.status is not LevelStatus.SOLVED:
            return LevelResult(raw.status, iterations=raw.iterations, message=raw.message)
        code, worst = LINE_ANSWER_NOT_FINITE, math.inf
        v = solved_vector(raw, qp.g.shape)
        if v is not None:
            segment = Segment(line.x0, line.direction, line.t_lo, line.t_hi)
            code, x, worst, slack = checked_line_answer(v, segment, qp, n_slack, self._tol)
        if code != LINE_ANSWER_OK:
            return LevelResult(LevelStatus.INACCURATE, iterations=raw.iterations, message=_refusal(raw, code, worst))
        return LevelResult(
            LevelStatus.SOLVED, x=x, slack=slack if n_slack else None, iterations=raw.iterations, message=raw.message
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
            raw = self._backend.solve_arrays(1, self._line_arrays(line, nv, self._line_p[0]), warm=False)
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
        """The problem through the general cascade, its levels read from the record by the kernels
        (:func:`~qpnso.qp.cascade_state.problem_level`), into ``solution``.  Straight to the cascade:
        :func:`~qpnso.qp.line.line_setup` has found no line for this problem (or the line fast path is off)."""
        P, S = problem[0], solution[0]
        t0 = time.perf_counter()
        levels = _ProblemLevels(problem, self._problem_state(problem))
        result = self._finish(self._solve_cascade(levels, P["lb"], P["ub"], time_budget), levels.count, t0)
        first, last = result.levels[0], result.levels[-1]
        S["out_of_time"] = result.out_of_time
        S["x1"] = first.x if first.x is not None else 0.0
        S["tool_residual"] = -1.0 if first.residual is None else first.residual
        S["slack_max"] = last.slack.max() if last.slack is not None and last.slack.size else -1.0
        held = result.x is not None and bool(np.all(np.isfinite(result.x)))
        S["x"] = result.x if held else 0.0
        S["outcome"] = SOLVED if result.ok else (TOOL_HELD if held else STOPPED)
        return "" if result.ok else result.status

    def _problem_state(self, problem: np.ndarray) -> CascadeState:
        """The cascade record for problems of this one's record type (made once per type)."""
        state = self._state
        if state is None or problem.dtype is not self._state_for:
            rows, soft = problem.dtype["hard_l"].shape[0], problem.dtype["soft_l"].shape[0]
            state = self._state = CascadeState(self.n, rows + soft, soft, self._tol)
            self._state_for = problem.dtype
        return state

    def _count(self, ok: bool) -> None:
        """Count one cascade in ``stats``."""
        self.stats.solves += 1
        if not ok:
            self.stats.failures += 1

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


def _warm_up_problem(problem: np.ndarray) -> np.ndarray:
    """A problem record of ``problem``'s type whose general cascade runs every kernel: level 1 two task rows
    and a hard row (five directions left free), level 2 a one-row task, a linear term and a soft row (two
    more owned), then the least-norm step on the three left."""
    p = np.zeros_like(problem)
    P = p[0]
    n = P["lb"].shape[0]
    P["A1"][:2] = np.eye(n)[:2]
    P["lb"], P["ub"] = -np.ones(n), np.ones(n)
    P["n_hard"], P["hard_C"][0], P["hard_l"][0], P["hard_u"][0] = 1, np.eye(n)[2], -1.0, 1.0
    P["has_level2"], P["m2"], P["A2"][0], P["b2"][0] = 1, 1, np.eye(n)[3], 0.5
    P["use_H2"], P["H2"], P["use_g2"], P["g2"] = 0, np.eye(n), 1, np.ones(n)
    P["n_soft"], P["soft_C"][0], P["soft_l"][0], P["soft_u"][0], P["slack_weight"] = 1, np.eye(n)[4], -1.0, 1.0, 1.0
    return p


class _CallerLevels:
    """A caller's levels (:meth:`HierarchicalQP.solve`) as the cascade runs them: their parts passed to the
    kernels (:func:`~qpnso.qp.cascade.level_parts`), on a cascade record sized for them."""

    def __init__(self, data: list[_LevelData], n: int, tol: np.ndarray) -> None:
        self.data, self.count = data, len(data)
        self.parts = [level_parts(level, n) for level in data]
        rows = sum(0 if level.C is None else level.C.shape[0] for level in data)
        self.state = CascadeState(n, rows, max(level.n_slack for level in data), tol)

    def build(self, k: int) -> tuple[int, int, int, int, int]:
        return build_level(self.state.record, self.state.buffer, self.parts[k], self.state.tol)

    def finish(self, k: int, v: np.ndarray, last: bool) -> tuple[int, int]:
        return finish_level(self.state.record, self.state.buffer, self.parts[k], v, last, self.state.tol)

    def residual(self, k: int, x: np.ndarray) -> float | None:
        return _residual(self.data[k], x)


class _ProblemLevels:
    """A tick's problem record as the cascade runs it: the kernels read its levels from the record
    (:func:`~qpnso.qp.cascade_state.problem_level`); level 1's residual is the tool's (weight 1)."""

    def __init__(self, problem: np.ndarray, state: CascadeState) -> None:
        self.problem, self.state = problem, state
        self.count = problem_levels_count(problem)

    def build(self, k: int) -> tuple[int, int, int, int, int]:
        return build_problem_level(self.state.record, self.state.buffer, self.problem, k, self.state.tol)

    def finish(self, k: int, v: np.ndarray, last: bool) -> tuple[int, int]:
        return finish_problem_level(self.state.record, self.state.buffer, self.problem, k, v, last, self.state.tol)

    def residual(self, k: int, x: np.ndarray) -> float | None:
        value = float(self.state.residual[0])
        return None if value < 0.0 else value


_Levels = _CallerLevels | _ProblemLevels


def _refused(raw: _Raw, code: int, r: int, state: CascadeState) -> LevelResult:
    """The result of a level whose answer :func:`~qpnso.qp.cascade_state.finish_level` refused: not finite or
    mis-shaped, or a bound or hard row violated (infeasible when no direction was free, else inaccurate)."""
    if code == LEVEL_NOT_FINITE:
        return LevelResult(
            LevelStatus.INACCURATE,
            iterations=raw.iterations,
            message=f"{raw.message}: non-finite or mis-shaped solution",
        )
    worst = float(state.worst[0])
    return LevelResult(
        LevelStatus.INFEASIBLE if r == 0 else LevelStatus.INACCURATE,
        iterations=raw.iterations,
        message=f"{raw.message}: bounds or hard rows violated by {worst:.3g}",
    )


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
