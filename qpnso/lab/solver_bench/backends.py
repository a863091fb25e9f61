"""The QP back ends and their options: the accuracy settings (:class:`BenchSettings`, :data:`DEFAULT`,
:data:`HIGH_ACCURACY`) and each solver's tolerance options (:func:`solver_options`, qpbenchmark's
mapping), ProxSuite's native warm-started path as the controller uses it (``_Native``), the cold one-shot
``qpsolvers`` call, and which requested solvers are installed (:func:`available`).

One place knows how to call a solver; the runs, the reference and the closed loop only name them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Iterable

import numpy as np

from qpnso.lab.solver_bench.problems import BenchProblem, StandardForm

NATIVE = "proxsuite"
"""Name of ProxSuite's native warm-started path (the controller's ``qp_backend`` name)."""


TIME_LIMIT_S = 10e-3
"""A solve longer than this fails; a failure is charged this time in the SGM (ten 1 kHz ticks)."""


@dataclass(frozen=True)
class BenchSettings:
    """One accuracy setting: ``eps_abs`` handed to the solvers (None: each solver's
    defaults) and the ``tolerance`` the residuals and gap are checked against."""

    name: str
    eps_abs: float | None
    tolerance: float
    time_limit_s: float = TIME_LIMIT_S


DEFAULT = BenchSettings("default", None, 1e-3)
"""Solvers' own defaults, validated at 1e-3 (qpbenchmark's low-accuracy check; its 1.0 would accept
useless joint velocities)."""
HIGH_ACCURACY = BenchSettings("high_accuracy", 1e-9, 1e-9)
"""qpbenchmark's high accuracy: eps_abs = 1e-9, eps_rel = 0, validated at 1e-9."""


def solver_options(solver: str, settings: BenchSettings) -> dict:
    """``qpsolvers`` keyword options of ``solver`` at ``settings`` — qpbenchmark's
    ``SolverSettings.set_eps_abs`` / ``set_eps_rel`` mapping (eps_rel = 0); solvers
    without a tolerance option (quadprog, pyqpmad) get none."""
    eps = settings.eps_abs
    if eps is None:
        return {}
    table = {
        "clarabel": {"tol_feas": eps, "tol_gap_abs": eps, "tol_gap_rel": 0.0},
        "cvxopt": {"feastol": eps},
        "daqp": {"dual_tol": eps, "primal_tol": eps},
        "ecos": {"feastol": eps},
        "highs": {"dual_feasibility_tolerance": eps, "primal_feasibility_tolerance": eps},
        "kvxopt": {"feastol": eps},
        "osqp": {"eps_abs": eps, "eps_rel": 0.0},
        "piqp": {"eps_abs": eps, "eps_rel": 0.0, "eps_duality_gap_abs": eps, "eps_duality_gap_rel": 0.0},
        "proxqp": {"eps_abs": eps, "eps_rel": 0.0, "eps_duality_gap_abs": eps, "eps_duality_gap_rel": 0.0},
        "qpalm": {"eps_abs": eps, "eps_rel": 0.0},
        "scs": {"eps_abs": eps, "eps_rel": 0.0},
        "sip": {"eps_abs": eps, "eps_rel": 0.0},
    }
    return dict(table.get(solver, {}))


class _Native:
    """ProxSuite's dense API as the controller uses it: one QP object per (sequence, level,
    shape), created and ``init``-ed at its first problem, then ``update`` + ``solve`` warm-started
    with the previous result (a failed warm solve is retried cold, timed too); the two-sided rows
    and the native box as given."""

    def __init__(self, settings: BenchSettings) -> None:
        import proxsuite

        self._px = proxsuite.proxqp
        self._settings = settings
        self._qps: dict[tuple, Any] = {}  # ProxSuite's QP objects (no type information)

    def solve(self, p: BenchProblem):
        box = p.box_l is not None
        key = (p.sequence, p.level, p.nv, p.C.shape[0], box)
        data: dict[str, np.ndarray | None] = dict(H=p.P, g=p.q)
        if p.C.shape[0]:
            data.update(C=p.C, l=p.l, u=p.u)
        if box:
            data.update(l_box=p.box_l, u_box=p.box_u)
        obj = self._qps.get(key)
        t0 = time.perf_counter()
        if obj is None:
            obj = self._px.dense.QP(p.nv, 0, p.C.shape[0], box)
            self._configure(obj.settings)
            obj.settings.initial_guess = self._px.InitialGuess.EQUALITY_CONSTRAINED_INITIAL_GUESS
            obj.init(**data)
            obj.solve()
            # warm start from the next problem on (set before the first solve, ProxSuite 0.8 segfaults)
            obj.settings.initial_guess = self._px.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT
            self._qps[key] = obj
        else:
            obj.update(**data)
            obj.solve()
            if obj.results.info.status != self._px.QPSolverOutput.PROXQP_SOLVED:  # as qpnso.qp.backends: retry cold
                obj.settings.initial_guess = self._px.InitialGuess.EQUALITY_CONSTRAINED_INITIAL_GUESS
                obj.init(**data)
                obj.solve()
                obj.settings.initial_guess = self._px.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT
        elapsed = time.perf_counter() - t0
        res = obj.results
        status = res.info.status
        found = status == self._px.QPSolverOutput.PROXQP_SOLVED
        z = np.array(res.z)
        m = p.C.shape[0]
        return found, f"proxsuite {status.name}", elapsed, np.array(res.x), z[:m], (z[m:] if box else None)

    def _configure(self, st) -> None:
        st.verbose = False
        eps = self._settings.eps_abs
        if eps is not None:
            st.eps_abs, st.eps_rel = eps, 0.0
            st.eps_duality_gap_abs, st.eps_duality_gap_rel = eps, 0.0


def available(solvers: Iterable[str] | None = None) -> tuple[list[str], dict[str, str]]:
    """``(usable, skipped)``: the requested solvers (default: native ProxSuite and every
    installed ``qpsolvers`` back end) split into those installed and those skipped, with why."""
    import qpsolvers

    installed = list(qpsolvers.available_solvers)
    try:
        import proxsuite  # noqa: F401

        native = True
    except ImportError:
        native = False
    wanted = ([NATIVE] + sorted(installed)) if solvers is None else list(solvers)
    usable: list[str] = []
    skipped: dict[str, str] = {}
    for s in wanted:
        if s == NATIVE:
            (usable.append(s) if native else skipped.__setitem__(s, "proxsuite is not installed"))
        elif s in installed:
            usable.append(s)
        else:
            skipped[s] = "not an installed qpsolvers back end"
    return usable, skipped


def _qpsolvers_solve(sf: StandardForm, solver: str, options: dict):
    import qpsolvers

    t0 = time.perf_counter()
    try:
        sol = qpsolvers.solve_problem(sf.problem, solver=solver, **options)
    except Exception as exc:  # a back end's failure is a failed problem, not a crash
        elapsed = time.perf_counter() - t0
        return False, f"error: {type(exc).__name__}: {str(exc)[:80]}", elapsed, None, None, None, None
    elapsed = time.perf_counter() - t0
    status = _status_text(sol)
    if not sol.found or sol.x is None:
        return False, status, elapsed, None, None, None, None
    return True, status, elapsed, np.asarray(sol.x, dtype=float), sol.y, sol.z, sol.z_box


def _status_text(sol) -> str:
    """The back end's own status word when ``qpsolvers`` passes one on, else found / not found."""
    extras = sol.extras or {}
    for key in ("status", "infostring", "info", "model_status", "exitflag"):
        value = extras.get(key)
        if isinstance(value, dict):
            value = value.get("infostring", value.get("status"))
        value = getattr(value, "status", value)
        value = getattr(value, "name", value)
        if isinstance(value, (str, int)) and str(value):
            return str(value).splitlines()[0][:40]
    return "found" if sol.found else "no solution"
