"""The back ends that solve one level's QP (docs/method.md §7.5 *Solvers*, docs/qp-notes.md).

* ProxSuite's dense ProxQP (:class:`_ProxSuiteBackend`, :data:`~qpnso.qp.settings.NATIVE_BACKEND`):
  one persistent object per (level, QP shape), updated and warm-started every tick, with a budget in
  iterations so that answers do not depend on the machine's load;
* DAQP (:func:`active_set_solve`), a dual active-set method, exact to round-off on these small QPs:
  the fallback when ProxQP fails, which then answers that QP alone for ``QPSettings.active_set_hold``
  solves; it also finds the cascade's least-norm answer;
* any installed ``qpsolvers`` back end (:class:`_QpsolversBackend`), solved cold (comparisons).

A back end answers with a :class:`_Raw` (vector, status, iterations, message), judged afterwards
(:func:`solved_vector`, :func:`~qpnso.qp.cascade.level_answer`).  QP data that are not finite never
reach a back end (:func:`qp_data_finite`, :func:`finite_data_raw`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import daqp
import numpy as np

from qpnso.errors import SolverError
from qpnso.qp.arrays import QPArrays, qp_data_finite, rows_with_box
from qpnso.qp.results import HQPStats, LevelStatus
from qpnso.qp.settings import NATIVE_BACKEND, QPSettings


@dataclass(slots=True)
class _Raw:
    v: np.ndarray | None
    status: LevelStatus
    iterations: int | None
    message: str = ""


def not_finite_raw() -> _Raw:
    """The failure a QP whose data cannot be solved (:func:`qp_data_finite`) reports: a NaN never reaches a
    back end (one once ran ProxQP for 1.5 M iterations, 9 s, measured)."""
    return _Raw(None, LevelStatus.SOLVER_ERROR, 0, "non-finite QP data (NaN or inf in the problem)")


def finite_data_raw(qp: QPArrays) -> _Raw | None:
    """None when a QP's data can be solved (:func:`qp_data_finite`), else :func:`not_finite_raw`."""
    return None if qp_data_finite(qp) else not_finite_raw()


_DAQP_SOLVED = (1, 2)  # DAQP's exit flags: optimal, optimal with soft constraints


def active_set_solve(qp: QPArrays, iter_limit: int = 1000) -> _Raw:
    """``min ½vᵀHv + gᵀv`` s.t. ``l ≤ C v ≤ u`` (and the box) by DAQP, a dual active-set method:
    finite termination, exact to round-off on the small QPs of a tick (about 20 µs, measured), a
    semi-definite ``H`` handled by proximal-point iterations (``eps_prox=1e-6``, to ``eta_prox=1e-12``:
    its automatic choice stalled for 5000 iterations along a flat direction that a bound cut, and its
    default 1e-6 tolerance left level 1's residual at 7e-8, both measured).  The recovery of
    :class:`_ProxSuiteBackend` when ProxQP fails (docs/qp-notes.md: ProxQP can stall on degenerate problems)."""
    H, g, C = qp.H, qp.g, qp.C
    upper, lower = np.concatenate([qp.box_u, qp.u]), np.concatenate([qp.box_l, qp.l])  # the box first: bounds
    try:
        x, _, flag, info = daqp.solve(
            np.ascontiguousarray(H),
            g,
            np.ascontiguousarray(C),
            upper,
            lower,
            eps_prox=1e-6,
            eta_prox=1e-12,
            iter_limit=iter_limit,
        )
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

    qp: Any  # proxsuite.proxqp.dense.QP and its members (ProxSuite has no type information)
    settings: Any
    results: Any
    info: Any
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
        self._warm = (
            guess.WARM_START_WITH_PREVIOUS_RESULT if settings.warm_start else guess.EQUALITY_CONSTRAINED_INITIAL_GUESS
        )
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

    def solve_arrays(self, k: int, qp: QPArrays, warm: bool = True) -> _Raw:
        """``min ½vᵀHv + gᵀv`` s.t. ``l ≤ C v ≤ u`` (and ``box_l ≤ v ≤ box_u`` if ``qp`` has a box) on the
        persistent object of level ``k`` and this shape, warm-started (``QPSettings.warm_start``) unless
        ``warm`` is False: the line fast path's level 2, whose variable is re-parametrised every tick (a new
        point and direction of level 1's line), so the previous answer is no guess for it; its equality-
        constrained guess took 8 % fewer instructions a tick, held and moving (callgrind, 1000 ticks).

        The budget is in iterations, so that answers do not depend on the machine's load: ProxQP's
        ``max_iter`` × ``max_iter_in`` (it cannot be interrupted on time), then, if ``active_set_fallback``,
        DAQP (:func:`active_set_solve`, at most ``max_iter_active_set`` iterations; counted in
        ``stats.active_set_fallbacks``).  DAQP then answers this QP alone for its next
        ``active_set_hold`` solves (counted likewise): a QP that ProxQP could not finish warm is usually
        as hard on the next ticks (a pull against the bounds), and a failed attempt costs as much as the
        DAQP solve itself (measured); after the hold ProxQP starts cold.  Without the fallback a failed
        warm solve is retried cold at once.  The data are finite (:func:`finite_data_raw` refuses others
        first).  A box goes to ProxQP as its native box if ``QPSettings.box_constraints``, else as rows."""
        if qp.box_l.shape[0] and not self._settings.box_constraints:
            qp = rows_with_box(qp)
        H, g, C, lo, hi, box_l, box_u = qp
        box = box_l.shape[0] > 0
        key = (k, H.shape[0], C.shape[0], box)
        entry = self._qps.get(key)
        if entry is not None and entry.held:
            entry.held -= 1
            self._stats.active_set_fallbacks += 1
            raw = active_set_solve(qp, self._settings.max_iter_active_set)
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
            entry.settings.initial_guess = self._warm if warm and not entry.cold_next else self._cold
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
        raw = active_set_solve(qp, self._settings.max_iter_active_set)
        raw.message = f"{message}; {raw.message}"
        return raw

    def _message(self, out: Any) -> str:
        """``proxsuite <status name>``, formatted once per status."""
        message = self._messages.get(out)
        if message is None:
            message = self._messages[out] = f"proxsuite {out.name}"
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

    def solve_arrays(self, k: int, qp: QPArrays, warm: bool = True) -> _Raw:
        """The QP of :meth:`_ProxSuiteBackend.solve_arrays`, one shot (``warm`` has no meaning here)."""
        _, _, C, lo, hi, _, _ = rows_with_box(qp)
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
            f"(native ProxSuite) or one of qpsolvers.available_solvers = {sorted(qpsolvers.available_solvers)}"
        )
    return _QpsolversBackend(backend, settings)


def solved_vector(raw: _Raw, shape: tuple[int, ...]) -> np.ndarray | None:
    """A back end's solution vector if it reports success with a vector of ``shape``, else None
    (what is left to check is the vector's values)."""
    if raw.status is not LevelStatus.SOLVED or raw.v is None or raw.v.shape != shape:
        return None
    return raw.v
