"""QP solver comparison on the controller's own QPs (docs/method.md §7; methodology of qpbenchmark).

Three parts:

* **Problem sets**: the QPs of every level, tick by tick, recorded from real
  controller runs by wrapping ``ctrl.qp.solve`` of one instance
  (:class:`QPRecorder`) and rebuilding each level with the cascade's public
  functions (:func:`qpnso.qp.hqp.build_level_qp`, :func:`qpnso.qp.hqp.advance_cascade`),
  advanced with the controller's own answer of the level above: the benchmark
  solves exactly the QPs the controller solved.  Stored form (:class:`BenchProblem`):
  ``min ½vᵀPv + qᵀv  s.t.  l ≤ Cv ≤ u,  box_l ≤ v ≤ box_u`` (∓inf allowed), the
  form ProxSuite gets; :func:`standard_form` gives every other solver
  ``Gv ≤ h, Av = b, lb ≤ v ≤ ub`` (two-sided rows split, rows with ``l = u`` as
  equalities, a box with an infinite side folded into ``G``).
* **Runner** (:func:`run_problems`): every installed ``qpsolvers`` back end (cold
  one-shot solves) and ProxSuite's native dense API (``"proxsuite"``: one
  ``proxqp.dense.QP`` per problem sequence, level and shape, ``update`` + ``solve``
  warm-started with the previous result, as :mod:`qpnso.qp.hqp` uses it), on the
  same problems, problem-major (all solvers interleaved on each problem).
  Metrics as qpbenchmark defines them (see :func:`kkt_residuals`): success =
  the solver says solved AND primal residual, dual residual and duality gap
  ≤ the settings' tolerance AND time ≤ the time limit; the shifted geometric
  mean of the time (shift :data:`SGM_SHIFT_US`, failures charged the time
  limit) normalised by the best solver.
* **Closed loop** (:func:`closed_loop`): the controller run with each back end
  as ``qp_backend`` on one scenario.

Entry point: :func:`run_solver_benchmark` (``report.md``, ``results.csv``,
``closed_loop.csv``, ``solver_bench.png``).
"""

from __future__ import annotations

import csv
import json
import math
import platform
import time
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from qpnso.errors import ConfigError, InputError
from qpnso.qp.hqp import Cascade, Level, LevelQP, QPSettings, advance_cascade, build_level_qp

__all__ = [
    "BenchProblem", "BenchSettings", "Outcome", "QPRecorder", "StandardForm", "CSV_COLUMNS", "DEFAULT",
    "HIGH_ACCURACY", "NATIVE", "closed_loop", "compute_reference", "kkt_residuals", "level_problems",
    "load_problems", "record_problem_set", "run_problems", "run_solver_benchmark", "save_problems",
    "shifted_geometric_mean", "solver_options", "standard_form", "summarize",
]

NATIVE = "proxsuite"
"""Name of ProxSuite's native warm-started path (the controller's ``qp_backend`` name)."""
SGM_SHIFT_US = 10.0
"""Shift of the shifted geometric mean of solve times, µs (qpbenchmark's 10, in our time unit)."""
TIME_LIMIT_S = 10e-3
"""A solve longer than this fails; a failure is charged this time in the SGM (ten 1 kHz ticks)."""
BENCH_REGULARIZATION = 1e-7
"""μ the recorded problems are built with: the controller's value for every ``qpsolvers`` back end
(strictly convex levels, unique reference solution); the native path ships with μ = 0."""
CSV_COLUMNS = ("solver", "settings", "success_rate", "runtime_sgm", "runtime_median_us",
               "primal_residual", "dual_residual", "duality_gap")
"""First columns of ``results.csv`` (more follow)."""
PROBLEM_DIR = Path(__file__).resolve().parents[2] / "solvers" / "problems"
"""Where the committed problem sets are (``solvers/problems`` of the checkout)."""


# ================================================================ problems
@dataclass
class BenchProblem:
    """One level's QP of one tick, in the variable ``v = [z; σ]`` of :class:`qpnso.qp.hqp.LevelQP`.

    ``min ½vᵀPv + qᵀv`` s.t. ``l ≤ Cv ≤ u`` and ``box_l ≤ v ≤ box_u`` (None: no box).
    ``x_prev`` (n,) and ``Z`` (n, r) decode a solution into joint velocity
    ``x = x_prev + Z v[:r]`` (rad/s); ``x_controller`` is what the controller's
    solver answered for this level (rad/s).  ``ref_v``/``ref_obj``: high-accuracy
    reference solution and cost (:func:`compute_reference`).  ``sequence`` groups
    consecutive ticks of one run (one warm-started ProxSuite object per sequence and level).
    """

    name: str
    sequence: str
    level: int  # 1-based
    tick: int
    P: np.ndarray
    q: np.ndarray
    C: np.ndarray
    l: np.ndarray
    u: np.ndarray
    box_l: np.ndarray | None
    box_u: np.ndarray | None
    x_prev: np.ndarray
    Z: np.ndarray
    x_controller: np.ndarray | None = None
    ref_v: np.ndarray | None = None
    ref_obj: float | None = None
    ref_solver: str = ""
    ref_spread: float | None = None  # largest |cost − ref_obj| of the cross-checking solvers

    @property
    def nv(self) -> int:
        return self.P.shape[0]

    def objective(self, v: np.ndarray) -> float:
        """``½vᵀPv + qᵀv``."""
        return float(0.5 * v @ self.P @ v + self.q @ v)

    def decode(self, v: np.ndarray) -> np.ndarray:
        """Joint velocity (rad/s) of a solution ``v``."""
        return self.x_prev + self.Z @ v[:self.Z.shape[1]]


def level_problems(n: int, levels: Sequence[Level], lb: np.ndarray | None, ub: np.ndarray | None, result,
                   settings: QPSettings, sequence: str = "", tick: int = 0) -> list[BenchProblem]:
    """The QP of each level (``n`` joint velocities) the controller's solver was asked (docs/method.md §7).

    Rebuilds the cascade with :func:`build_level_qp` / :func:`advance_cascade`,
    advanced with the controller's own answer ``result.levels[k].x`` (an
    :class:`qpnso.qp.hqp.HQPResult`), so each problem is the one the back end got.
    Levels with no free direction (no QP was solved) and levels after a
    failed one are left out.
    """
    lo = np.full(n, -np.inf) if lb is None else np.asarray(lb, dtype=float).copy()
    hi = np.full(n, np.inf) if ub is None else np.asarray(ub, dtype=float).copy()
    cascade = Cascade.start(lo, hi)
    out: list[BenchProblem] = []
    for k, (level, res) in enumerate(zip(levels, result.levels)):
        if not res.ok:
            break
        qp = build_level_qp(level, cascade, settings)
        if qp.H.shape[0] and qp.r:
            out.append(_from_level_qp(qp, f"{sequence}/t{tick:05d}/L{k + 1}", sequence, k + 1, tick, res.x))
        if k + 1 < len(levels):
            cascade = advance_cascade(level, cascade, qp, res.x, settings)
    return out


def _from_level_qp(qp: LevelQP, name: str, sequence: str, level: int, tick: int,
                   x_controller: np.ndarray | None) -> BenchProblem:
    c = lambda a: None if a is None else np.array(a, dtype=float)  # noqa: E731 (copies: no aliasing)
    P = 0.5 * (qp.H + qp.H.T)  # symmetric to the last bit (it is up to ~1e-17; sip refuses otherwise)
    return BenchProblem(name, sequence, level, tick, P, c(qp.g), c(qp.C), c(qp.l), c(qp.u),
                        c(qp.box_l), c(qp.box_u), c(qp.x_prev), c(qp.Z), c(x_controller))


class QPRecorder:
    """Records every QP a controller's hierarchical solver is asked, by wrapping
    ``ctrl.qp.solve`` of that instance (nothing else is patched); while it records, the
    controller's compiled tick is off (``ctrl.compiled_tick``: it would bypass ``solve``;
    the general path gives the same QPs and answers, tests/test_tick.py).

    Use as a context manager; ``problems`` collects :class:`BenchProblem` of
    the ticks ``k`` with ``keep(k)`` true (default all), sequence name
    ``f"{source}/c{chunk(k)}"``.  ``regularization`` rebuilds the levels with
    another μ (None: the controller's own settings).
    """

    def __init__(self, ctrl, source: str, keep: Callable[[int], bool] = lambda k: True,
                 chunk: Callable[[int], int] = lambda k: 0, regularization: float | None = None) -> None:
        self.ctrl, self.source, self.keep, self.chunk = ctrl, source, keep, chunk
        settings = ctrl.qp.settings
        self.settings = settings if regularization is None else replace(settings, regularization=regularization)
        self.problems: list[BenchProblem] = []
        self.ticks = 0

    def __enter__(self) -> "QPRecorder":
        original = self.ctrl.qp.solve

        def solve(levels, lb=None, ub=None, check=True, time_budget=None):
            result = original(levels, lb, ub, check, time_budget)
            if self.keep(self.ticks):
                self.problems += level_problems(self.ctrl.qp.n, levels, lb, ub, result, self.settings,
                                                f"{self.source}/c{self.chunk(self.ticks)}", self.ticks)
            self.ticks += 1
            return result

        self.ctrl.qp.solve = solve  # instance attribute shadows the method
        self._compiled, self.ctrl.compiled_tick = self.ctrl.compiled_tick, False
        return self

    def __exit__(self, *exc) -> None:
        del self.ctrl.qp.solve
        self.ctrl.compiled_tick = self._compiled


# ----------------------------------------------------------- standard form
@dataclass
class StandardForm:
    """``qpsolvers.Problem`` of a :class:`BenchProblem` and how its rows map back.

    ``g_src``/``g_sign``: each row of ``G`` is ``g_sign·C[g_src]`` (``g_src ≥ 0``)
    or ``g_sign·e_j`` of a folded box entry ``j = −1 − g_src``; ``a_src``: the
    ``C`` row of each equality; ``box``: the box is ``lb/ub`` of the problem.
    """

    problem: object
    g_src: np.ndarray
    g_sign: np.ndarray
    a_src: np.ndarray
    box: bool

    def duals(self, z_rows: np.ndarray, z_box: np.ndarray | None):
        """``(y, z, z_box)`` of the standard form from two-sided duals (ProxSuite's sign:
        ``> 0`` upper side active, ``< 0`` lower side active)."""
        zb = np.zeros(0) if z_box is None else z_box
        src = np.where(self.g_src >= 0, z_rows[np.maximum(self.g_src, 0)] if z_rows.size else 0.0,
                       zb[np.maximum(-1 - self.g_src, 0)] if zb.size else 0.0)
        z = np.maximum(self.g_sign * src, 0.0)
        y = z_rows[self.a_src]
        return (y if y.size else None), (z if z.size else None), (z_box if self.box else None)


def standard_form(p: BenchProblem) -> StandardForm:
    """``Gv ≤ h, Av = b, lb ≤ v ≤ ub`` of a two-sided problem (finite sides only).

    A box with an infinite side (a slack) is folded into ``G`` (quadprog & co.
    turn a box into rows, where ∓inf breaks them); a finite box stays a box.
    """
    import qpsolvers

    eq = np.isfinite(p.l) & (p.l == p.u)
    up = np.isfinite(p.u) & ~eq
    down = np.isfinite(p.l) & ~eq
    rows = [p.C[up], -p.C[down]]
    h = [p.u[up], -p.l[down]]
    g_src = [np.flatnonzero(up), np.flatnonzero(down)]
    g_sign = [np.ones(up.sum()), -np.ones(down.sum())]
    box = p.box_l is not None and bool(np.isfinite(p.box_l).all() and np.isfinite(p.box_u).all())
    if p.box_l is not None and not box:
        eye = np.eye(p.nv)
        for side, bound, sign in ((np.isfinite(p.box_u), p.box_u, 1.0), (np.isfinite(p.box_l), p.box_l, -1.0)):
            idx = np.flatnonzero(side)
            rows.append(sign * eye[idx])
            h.append(sign * bound[idx])
            g_src.append(-1 - idx)
            g_sign.append(np.full(idx.size, sign))
    G, hv = np.vstack(rows), np.concatenate(h)
    A, b = p.C[eq], p.l[eq]
    problem = qpsolvers.Problem(p.P, p.q, G if hv.size else None, hv if hv.size else None,
                                A if b.size else None, b if b.size else None,
                                p.box_l if box else None, p.box_u if box else None)
    return StandardForm(problem, np.concatenate(g_src).astype(int), np.concatenate(g_sign),
                        np.flatnonzero(eq), box)


def kkt_residuals(sf: StandardForm, x: np.ndarray | None, y, z, z_box) -> tuple[float, float, float]:
    """qpbenchmark's (qpsolvers') primal residual, dual residual and duality gap:

    ``r_p = max(‖Ax − b‖∞, [Gx − h]⁺, [lb − x]⁺, [x − ub]⁺)``,
    ``r_d = ‖Px + q + Aᵀy + Gᵀz + z_box‖∞``,
    ``r_g = |xᵀPx + qᵀx + bᵀy + hᵀz + lbᵀz_box⁻ + ubᵀz_box⁺|``;
    ``inf`` when ``x`` or a needed dual is missing.
    """
    import qpsolvers

    if x is None or not np.all(np.isfinite(x)):
        return math.inf, math.inf, math.inf
    sol = qpsolvers.Solution(sf.problem, found=True, x=np.asarray(x, dtype=float), y=y, z=z, z_box=z_box)
    with np.errstate(all="ignore"):
        out = (float(sol.primal_residual()), float(sol.dual_residual()), float(sol.duality_gap()))
    return tuple(v if math.isfinite(v) else math.inf for v in out)  # type: ignore[return-value]


# ------------------------------------------------------------- storage
_ARRAYS = ("P", "q", "C", "l", "u", "box_l", "box_u", "x_prev", "Z", "x_controller", "ref_v")
_SCALARS = ("name", "sequence", "level", "tick", "ref_obj", "ref_solver", "ref_spread")


def save_problems(path: Path, problems: Sequence[BenchProblem], meta: dict | None = None) -> Path:
    """Write a problem set as one compressed ``.npz`` (each field's arrays concatenated, no pickle)."""
    if not problems:
        raise InputError("no problems to save")
    data: dict[str, np.ndarray] = {}
    for name in _ARRAYS:
        arrays = [getattr(p, name) for p in problems]
        shapes = np.array([(-1, -1) if a is None else (a.shape + (1,))[:2] if a.ndim == 1 else a.shape
                           for a in arrays], dtype=np.int64)
        ndims = np.array([0 if a is None else a.ndim for a in arrays], dtype=np.int8)
        data[f"{name}__data"] = np.concatenate([np.zeros(0)] + [a.ravel() for a in arrays if a is not None])
        data[f"{name}__shape"], data[f"{name}__ndim"] = shapes, ndims
    table = [{k: getattr(p, k) for k in _SCALARS} for p in problems]
    data["__index"] = np.array(json.dumps(table))
    data["__meta"] = np.array(json.dumps(meta or {}))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **data)
    return path


def load_problems(path: Path) -> tuple[list[BenchProblem], dict]:
    """Read a set written by :func:`save_problems`: ``(problems, meta)``."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"problem set not found: {path}")
    with np.load(path, allow_pickle=False) as f:
        table = json.loads(str(f["__index"]))
        meta = json.loads(str(f["__meta"]))
        columns = {}
        for name in _ARRAYS:
            flat, shapes, ndims = f[f"{name}__data"], f[f"{name}__shape"], f[f"{name}__ndim"]
            col, pos = [], 0
            for (r, c), nd in zip(shapes, ndims):
                if nd == 0:
                    col.append(None)
                    continue
                size = int(r * c)
                a = flat[pos:pos + size]
                col.append(a.reshape(r, c) if nd == 2 else a.copy())
                pos += size
            columns[name] = col
    problems = [BenchProblem(**{**row, **{k: columns[k][i] for k in _ARRAYS}}) for i, row in enumerate(table)]
    return problems, meta


# =============================================================== settings
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


# ================================================================= runner
@dataclass
class Outcome:
    """One solve: ``time_s`` wall time of the call (``qpsolvers.solve_problem``, or
    ProxSuite ``init``/``update`` + ``solve``); residuals ``inf`` without a solution."""

    solver: str
    settings: str
    problem: str
    found: bool
    status: str  # "solved", "not found (…)", "error: <exception>", "inaccurate: primal/dual/gap", "timeout"
    time_s: float
    primal: float
    dual: float
    gap: float
    cost_error: float
    x_error: float  # ‖decode(v) − decode(ref_v)‖∞, rad/s
    success: bool
    time_limit_s: float = TIME_LIMIT_S
    detail: str = ""  # the solver's own status word and the offending residuals
    level: int = 0  # of the problem (1-based)


class _Native:
    """ProxSuite's dense API as the controller uses it: one QP object per (sequence, level,
    shape), created and ``init``-ed at its first problem, then ``update`` + ``solve`` warm-started
    with the previous result (a failed warm solve is retried cold, timed too); the two-sided rows
    and the native box as given."""

    def __init__(self, settings: BenchSettings) -> None:
        import proxsuite

        self._px = proxsuite.proxqp
        self._settings = settings
        self._qps: dict[tuple, object] = {}

    def solve(self, p: BenchProblem):
        box = p.box_l is not None
        key = (p.sequence, p.level, p.nv, p.C.shape[0], box)
        data = dict(H=p.P, g=p.q)
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
            if obj.results.info.status != self._px.QPSolverOutput.PROXQP_SOLVED:  # as qpnso.qp.hqp: retry cold
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
    usable, skipped = [], {}
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


def run_problems(problems: Sequence[BenchProblem], solvers: Iterable[str] | None = None,
                 settings: Sequence[BenchSettings] = (DEFAULT, HIGH_ACCURACY)
                 ) -> tuple[list[Outcome], dict[str, str]]:
    """Solve every problem with every usable solver at every setting, problem-major
    (each problem: all settings × solvers in turn, so machine load hits all alike).

    Returns ``(outcomes, skipped)``; ``skipped`` names each requested solver that
    is not installed and why.  A solver failing a problem (exception, not
    solved, residual above tolerance, slower than the time limit) is an
    :class:`Outcome` with ``success=False`` and its status.
    """
    usable, skipped = available(solvers)
    forms = [standard_form(p) for p in problems]
    natives = {s.name: _Native(s) for s in settings} if NATIVE in usable else {}
    options = {(solver, s.name): solver_options(solver, s) for solver in usable for s in settings}
    outcomes: list[Outcome] = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for p, sf in zip(problems, forms):
            for s in settings:
                for solver in usable:
                    if solver == NATIVE:
                        found, status, t, x, z_rows, z_box = natives[s.name].solve(p)
                        y, z, zb = sf.duals(z_rows, z_box) if found else (None, None, None)
                    else:
                        found, status, t, x, y, z, zb = _qpsolvers_solve(sf, solver, options[(solver, s.name)])
                    outcomes.append(_outcome(p, sf, s, solver, found, status, t, x, y, z, zb))
    return outcomes, skipped


def _outcome(p: BenchProblem, sf: StandardForm, s: BenchSettings, solver: str, found: bool, status: str,
             t: float, x, y, z, zb) -> Outcome:
    if found and x is not None and x.shape == (p.nv,):
        primal, dual, gap = kkt_residuals(sf, x, y, z, zb)
        cost_error = abs(p.objective(x) - p.ref_obj) if p.ref_obj is not None else math.nan
        x_error = float(np.max(np.abs(p.decode(x) - p.decode(p.ref_v)))) if p.ref_v is not None else math.nan
    else:
        found, primal, dual, gap, cost_error, x_error = False, math.inf, math.inf, math.inf, math.nan, math.nan
    tol = s.tolerance
    over = [k for k, v in (("primal", primal), ("dual", dual), ("gap", gap)) if not v <= tol]
    detail = status
    if not found:
        status = ":".join(status.split(":")[:2]) if status.startswith("error") else f"not found ({status})"
    elif over:
        status = "inaccurate: " + "/".join(over)
        detail += f"; r_p {primal:.1e}, r_d {dual:.1e}, r_g {gap:.1e} (tolerance {tol:g})"
    elif t > s.time_limit_s:
        status = "timeout"
        detail += f"; {t * 1e3:.1f} ms > {s.time_limit_s * 1e3:g} ms"
    else:
        status = "solved"
    success = status == "solved"
    if not success:  # a rejected answer's errors are not reported as the solver's accuracy
        cost_error = x_error = math.nan
    return Outcome(solver, s.name, p.name, found, status, t, primal, dual, gap, cost_error, x_error, success,
                   s.time_limit_s, detail, p.level)


# ================================================================ summary
def shifted_geometric_mean(values: Sequence[float], shift: float) -> float:
    """``exp(mean(log(v + shift))) − shift`` (qpbenchmark's runtime/residual summary)."""
    v = np.asarray(values, dtype=float)
    if v.size == 0 or np.any(v < 0) or not np.all(np.isfinite(v)):
        raise InputError("shifted_geometric_mean needs finite values >= 0")
    return float(np.exp(np.mean(np.log(v + shift))) - shift)


def summarize(outcomes: Sequence[Outcome], reference_solver: str = "proxqp") -> list[dict]:
    """One row per (solver, settings), columns :data:`CSV_COLUMNS` then extras.

    ``success_rate`` in %; ``runtime_sgm`` shifted geometric mean of the time
    (µs, shift :data:`SGM_SHIFT_US`, a failure charged its setting's time limit)
    divided by the best solver's at the same setting; ``runtime_median_us``
    median time of all solves; residuals, gap and cost error: medians over the
    problems the solver returned a solution for (NaN if none), cost error and
    ``x_error`` over its successes only; ``*_max`` their worst; ``failures``
    counts per status; ``dq_error_max_L2`` the worst joint-velocity difference (rad/s)
    to the reference on the last level (the command; on level 1 the direction level 2
    decides is nearly flat, so its difference says nothing);
    ``time_ratio_to_<ref>`` median time / the reference solver's.
    """
    groups: dict[tuple[str, str], list[Outcome]] = {}
    for o in outcomes:
        groups.setdefault((o.solver, o.settings), []).append(o)
    rows = []
    for (solver, setting), group in groups.items():
        limit_us = group[0].time_limit_s * 1e6
        charged = [o.time_s * 1e6 if o.success else limit_us for o in group]
        found = [o for o in group if o.found]
        good = [o for o in group if o.success]

        def stat(fn, key: str, among: list[Outcome]) -> float:
            return float(fn([getattr(o, key) for o in among])) if among else math.nan
        failures: dict[str, int] = {}
        for o in group:
            if not o.success:
                failures[o.status] = failures.get(o.status, 0) + 1
        rows.append({
            "solver": solver, "settings": setting,
            "success_rate": 100.0 * sum(o.success for o in group) / len(group),
            "runtime_sgm": shifted_geometric_mean(charged, SGM_SHIFT_US),
            "runtime_median_us": float(np.median([o.time_s for o in group]) * 1e6),
            "primal_residual": stat(np.median, "primal", found), "dual_residual": stat(np.median, "dual", found),
            "duality_gap": stat(np.median, "gap", found),
            "cost_error": stat(np.median, "cost_error", good), "cost_error_max": stat(np.max, "cost_error", good),
            "dq_error_max_L2": stat(np.max, "x_error", [o for o in good if o.level == 2]), "primal_residual_max": stat(np.max, "primal", found),
            "runtime_p99_us": float(np.percentile([o.time_s for o in group], 99) * 1e6),
            "problems": len(group), "found": len(found),
            "failures": "; ".join(f"{n}× {s}" for s, n in sorted(failures.items(), key=lambda kv: -kv[1])),
        })
    for setting in {r["settings"] for r in rows}:
        same = [r for r in rows if r["settings"] == setting]
        best = min(r["runtime_sgm"] for r in same)
        ref = next((r["runtime_median_us"] for r in same if r["solver"] == reference_solver), None)
        for r in same:
            r["runtime_sgm"] = r["runtime_sgm"] / best if best > 0 else math.nan
            r[f"time_ratio_to_{reference_solver}"] = r["runtime_median_us"] / ref if ref else math.nan
    order = {"default": 0, "high_accuracy": 1}
    rows.sort(key=lambda r: (order.get(r["settings"], 9), r["runtime_sgm"]))
    return rows


def write_results_csv(rows: Sequence[dict], path: Path) -> Path:
    """``results.csv``: :data:`CSV_COLUMNS` first, then the extra columns of :func:`summarize`."""
    if not rows:
        raise InputError("no result rows to write")
    extra = [k for k in rows[0] if k not in CSV_COLUMNS]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(CSV_COLUMNS) + extra)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    return path


# ============================================================== reference
REFERENCE_SOLVERS = ("daqp", "quadprog", "proxqp")


def compute_reference(problems: Sequence[BenchProblem], solvers: Sequence[str] = REFERENCE_SOLVERS,
                      eps: float = 1e-12) -> None:
    """Fill ``ref_v``/``ref_obj`` with the most accurate of ``solvers`` at ``eps``
    (smallest ``max(r_p, r_d, r_g)``; DAQP and quadprog are exact active-set methods,
    ProxQP at 1e-12) and ``ref_spread`` with the largest cost difference to the
    others that reached 1e-8 (the cross-check)."""
    usable, _ = available([s for s in solvers if s != NATIVE])
    if not usable:
        raise ConfigError(f"none of the reference solvers {list(solvers)} is installed")
    setting = BenchSettings("reference", eps, eps)
    for p in problems:
        sf = standard_form(p)
        candidates = []
        for solver in usable:
            found, _, _, x, y, z, zb = _qpsolvers_solve(sf, solver, solver_options(solver, setting))
            if found:
                kkt = max(kkt_residuals(sf, x, y, z, zb))
                candidates.append((kkt, solver, x))
        if not candidates:
            continue
        kkt, solver, x = min(candidates, key=lambda c: c[0])
        p.ref_v, p.ref_obj, p.ref_solver = x, p.objective(x), solver
        good = [c for c in candidates if c[0] <= 1e-8]
        p.ref_spread = max((abs(p.objective(c[2]) - p.ref_obj) for c in good), default=math.nan)


# ============================================================== recording
@dataclass(frozen=True)
class RecordPlan:
    """How many ticks to run per source and which to keep: chunks of ``chunk_ticks``
    consecutive ticks starting every ``period`` ticks after ``skip``."""

    ticks: int
    chunk_ticks: int
    period: int
    skip: int = 0

    def keep(self, k: int) -> bool:
        return k >= self.skip and (k - self.skip) % self.period < self.chunk_ticks

    def chunk(self, k: int) -> int:
        return (k - self.skip) // self.period


QUICK_PLAN = RecordPlan(ticks=1300, chunk_ticks=20, period=600, skip=100)
FULL_PLAN = RecordPlan(ticks=6000, chunk_ticks=50, period=1000, skip=100)


def _track(ctrl, traj, q0: np.ndarray, ticks: int) -> None:
    """Offline tracking of ``traj`` (as :func:`qpnso.control.offline.solve_trajectory`: twist
    feed-forward, pose reference, ``q ← q + dt·q̇``) for ``ticks`` ticks at most."""
    import pinocchio as pin

    dt = ctrl.config.dt
    ctrl.reset(q0)
    q = np.array(q0, dtype=float)
    n = min(ticks, int(np.floor(traj.duration / dt + 1e-9)) + 1)
    for k in range(n):
        p, r, v, w = traj.sample(traj.t[0] + k * dt)
        cmd = ctrl.step(q, tool_twist=np.concatenate([v, w]), tool_pose=pin.SE3(r, p))
        q = q + dt * cmd.dq


def _sources(seed: int):
    """``(name, robot name, controller settings, trajectory factory, q0 factory)`` of each recorded run:
    scenarios A and B (guidance), the guidance path on the iiwa14, held tools at random postures."""
    from qpnso.lab.scenarios import load_scenario
    from qpnso.control.offline import initial_configuration
    from qpnso.control.trajectory import guidance_path, hold

    out = []
    for name in ("A", "B"):
        sc = load_scenario(name)
        out.append((f"scenario{name}", sc.robot, sc.controller, lambda robot, sc=sc: sc.path(),
                    lambda robot, traj, sc=sc: sc.start(robot)))

    def iiwa_path(robot):
        q = np.radians([0.0, 40.0, 0.0, -80.0, 0.0, 60.0, 0.0])
        return guidance_path(robot.tool_pose(q), size=0.08, speed=0.05)

    out.append(("guidance_iiwa14", "iiwa14", {}, iiwa_path,
                lambda robot, traj: initial_configuration(robot, traj.pose(traj.t[0]))))
    rng = np.random.default_rng(seed)
    for robot_name in ("lwr4p", "iiwa14"):
        for i in range(2):
            u = rng.uniform(0.15, 0.85, 7)  # fraction of each joint range: away from the limits
            out.append((f"hold_{robot_name}_{i}", robot_name, {},
                        lambda robot, u=u: hold(robot.tool_pose(robot.q_min + u * (robot.q_max - robot.q_min)), 5.0),
                        lambda robot, traj, u=u: robot.q_min + u * (robot.q_max - robot.q_min)))
    return out


def record_problem_set(path: Path, full: bool = False, seed: int = 0, progress: Callable[[str], None] | None = None,
                       regularization: float = BENCH_REGULARIZATION) -> Path:
    """Run the controller (default ``qp`` strategy, native ProxSuite) on every source of
    :func:`_sources`, record the QPs of the ticks the plan keeps, compute their references,
    save them to ``path``.  Deterministic for a given ``seed``."""
    from qpnso.control.controller import Controller, ControllerConfig
    from qpnso.model.robot import load_robot

    plan = FULL_PLAN if full else QUICK_PLAN
    problems: list[BenchProblem] = []
    for name, robot_name, controller, make_traj, make_q0 in _sources(seed):
        robot = load_robot(robot_name)
        ctrl = Controller(robot, ControllerConfig.from_dict(dict(controller)))
        traj = make_traj(robot)
        with QPRecorder(ctrl, name, plan.keep, plan.chunk, regularization) as rec:
            _track(ctrl, traj, make_q0(robot, traj), plan.ticks)
        problems += rec.problems
        if progress:
            progress(f"{name}: {rec.ticks} ticks, {len(rec.problems)} problems kept")
    compute_reference(problems)
    meta = {"plan": plan.__dict__, "seed": seed, "regularization": regularization,
            "recorded_with": "qpnso.lab.solver_bench.record_problem_set", "qp_backend": NATIVE}
    return save_problems(path, problems, meta)


# ============================================================ closed loop
CLOSED_LOOP_KEYS = ("tool_position_error_max_m", "tool_rotation_error_max_deg", "constraint_proximity_deg",
                    "rom_proximity_deg", "tick_time_median_us", "tick_time_p99_us", "solve_time_median_us",
                    "solve_time_p99_us", "status_QP_FAILED_ticks", "status_ELBOW_SLACK_ticks")


def closed_loop(backends: Sequence[str], scenario: str = "A", seconds: float = 2.0,
                options: Callable[[str], dict] | None = None) -> list[dict]:
    """The scenario's guidance path (first ``seconds`` s, offline tracking) solved by the controller
    with each back end as ``qp_backend``; the run metrics per back end (:data:`CLOSED_LOOP_KEYS`),
    ``dq_diff_max`` = max |dq − dq of the first back end| over the run (rad/s) and the run's
    first controller message (e.g. why a QP failed).

    ``options(backend)`` gives ``QPSettings.solver_options`` (default: none, each solver's
    defaults, i.e. what ``ControllerConfig(qp_backend=name)`` does).  A back end the
    controller refuses is reported with its error.
    """
    from qpnso.control.controller import ControllerConfig
    from qpnso.model.robot import load_robot
    from qpnso.lab.scenarios import load_scenario
    from qpnso.control.offline import solve_trajectory

    sc = load_scenario(scenario)
    robot = load_robot(sc.robot)
    path = sc.path()
    path = path.window(path.t[0], min(path.t[-1], path.t[0] + seconds))
    q0 = sc.start(robot)
    base = ControllerConfig.from_dict(dict(sc.controller))
    rows, first_dq = [], None
    for backend in backends:
        settings = replace(base.qp_settings, solver_options=(options(backend) if options else {}))
        cfg = replace(base, qp_backend=backend, qp_settings=settings)
        row: dict = {"backend": backend}
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                run = solve_trajectory(robot, path, q0, cfg)
        except Exception as exc:  # noqa: BLE001 - one back end's trouble is a row, not a crash
            row["error"] = f"{type(exc).__name__}: {exc}"[:120]
            rows.append(row)
            continue
        row.update({k: run.summary.get(k, math.nan) for k in CLOSED_LOOP_KEYS})
        dq = run.arrays["dq"]
        if first_dq is None:
            first_dq = dq
        row["dq_diff_max"] = float(np.max(np.abs(dq - first_dq))) if dq.shape == first_dq.shape else math.nan
        row["ticks"] = len(dq)
        row["first_message"] = run.messages[0][:160] if run.messages else ""
        rows.append(row)
    return rows


# ================================================================= report
def _fmt(v) -> str:
    if isinstance(v, float):
        if math.isnan(v):
            return "–"
        if math.isinf(v):
            return "inf"
        return f"{v:.3g}" if abs(v) >= 1e-3 or v == 0 else f"{v:.1e}"
    return str(v)


def _table(rows: Sequence[dict], columns: Sequence[str]) -> str:
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(_fmt(r.get(c, "")) for c in columns) + " |" for r in rows]
    return "\n".join(lines)


def _versions(solvers: Sequence[str]) -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    dist = {"proxsuite": "proxsuite", "proxqp": "proxsuite", "highs": "highspy", "sip": "sip-qp-python",
            "pyqpmad": "pyqpmad"}
    out = {}
    for s in list(solvers) + ["qpsolvers"]:
        try:
            out[s] = version(dist.get(s, s))
        except PackageNotFoundError:
            out[s] = "?"
    return out


def write_report(path: Path, rows: Sequence[dict], loop_rows: Sequence[dict], skipped: dict[str, str],
                 meta: dict, n_problems: int, command: str, elapsed_s: float, solvers: Sequence[str],
                 problem_set: Path, loop_info: str) -> Path:
    versions = _versions(solvers)
    cols = list(CSV_COLUMNS) + ["time_ratio_to_proxqp", "cost_error", "cost_error_max", "dq_error_max_L2"]
    parts = [
        "# QP solver benchmark on the controller's QPs", "",
        f"Command: `{command}` ({elapsed_s:.0f} s, {platform.processor() or platform.machine()}, "
        f"Python {platform.python_version()}).", "",
        f"Problem set: `{problem_set.name}`, {n_problems} QPs (levels 1 and 2, consecutive ticks of "
        f"recorded runs; built with μ = {meta.get('regularization')}).  Solvers (version): "
        + ", ".join(f"{s} {versions[s]}" for s in solvers) + f"; qpsolvers {versions['qpsolvers']}.",
        "",
    ]
    if skipped:
        parts += ["Skipped: " + "; ".join(f"`{s}` ({why})" for s, why in skipped.items()) + ".", ""]
    parts += [
        "`proxsuite` = ProxSuite's native dense API warm-started in place (as the controller); "
        "`proxqp` = the same solver through qpsolvers, cold.  success_rate in %; runtime_sgm = shifted "
        f"geometric mean of the time (shift {SGM_SHIFT_US:g} µs, a failure charged "
        f"{TIME_LIMIT_S * 1e3:g} ms) / the best; residuals, gap, cost error (|cost − reference|) "
        "= medians over returned solutions (cost error over successes), dq_error_max_L2 = worst "
        "joint-velocity difference (rad/s) to the reference on level 2, whose answer is the command.  default: each solver's defaults, checked at 1e-3; high_accuracy: "
        "eps_abs 1e-9, eps_rel 0 (qpbenchmark's mapping), checked at 1e-9.", "",
        "## Results", "", _table(rows, cols), "",
        "## Failures", "",
    ]
    fails = [r for r in rows if r["failures"]]
    parts += [f"* {r['solver']} / {r['settings']}: {r['failures']}" for r in fails] or ["none"]
    parts += ["", "## Closed loop", "", loop_info, ""]
    loop_cols = ["backend"] + list(CLOSED_LOOP_KEYS) + ["dq_diff_max"]
    if any("error" in r for r in loop_rows):
        loop_cols.append("error")
    parts += [_table(loop_rows, loop_cols), ""]
    notes = [f"* {r['backend']}: {r['first_message']}" for r in loop_rows if r.get("first_message")]
    if notes:
        parts += ["First controller message of each run that had one:", ""] + notes + [""]
    path.write_text("\n".join(parts))
    return path


def plot_results(rows: Sequence[dict], loop_rows: Sequence[dict], path: Path) -> Path | None:
    """Median solve time and success rate per solver and setting, and the closed loop's
    tick time; None when matplotlib is missing."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    solvers = sorted({r["solver"] for r in rows}, key=lambda s: min(
        r["runtime_median_us"] for r in rows if r["solver"] == s))
    width = 0.4
    for i, setting in enumerate(("default", "high_accuracy")):
        vals = [next((r for r in rows if r["solver"] == s and r["settings"] == setting), None) for s in solvers]
        xs = np.arange(len(solvers)) + (i - 0.5) * width
        axes[0].bar(xs, [v["runtime_median_us"] if v else 0 for v in vals], width, label=setting)
        for x, v in zip(xs, vals):
            if v:
                axes[0].text(x, v["runtime_median_us"], f"{v['success_rate']:.0f}%", ha="center",
                             va="bottom", fontsize=6, rotation=90)
    axes[0].set_xticks(range(len(solvers)), solvers, rotation=45, ha="right")
    axes[0].set_yscale("log")
    axes[0].set_ylabel("median solve time per QP (µs), label: success %")
    axes[0].legend()
    ok = [r for r in loop_rows if "error" not in r]
    axes[1].bar([r["backend"] for r in ok], [r["tick_time_median_us"] for r in ok], label="median")
    axes[1].plot([r["backend"] for r in ok], [r["tick_time_p99_us"] for r in ok], "k_", markersize=12, label="p99")
    axes[1].set_yscale("log")
    axes[1].set_ylabel("closed loop: controller tick time (µs)")
    axes[1].tick_params(axis="x", rotation=45)
    axes[1].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def run_solver_benchmark(out: Path, quick: bool = False, solvers: Sequence[str] | None = None,
                         problems: Path | None = None, progress: Callable[[str], None] | None = None) -> Path:
    """Benchmark the QP solvers on the controller's QPs; returns the path of ``report.md``.

    Writes into ``out``: ``report.md`` (tables), ``results.csv`` (one row per solver ×
    settings, :data:`CSV_COLUMNS` first), ``closed_loop.csv``, ``solver_bench.png``.
    ``quick``: the committed small set (``solvers/problems/quick.npz``) and a 0.3 s closed
    loop (under a minute on 2 cores); otherwise ``solvers/problems/full.npz`` (recorded into
    ``out`` when absent) and a 3 s closed loop.  ``solvers``: names to run (default: native
    ProxSuite and every installed ``qpsolvers`` back end; unknown ones are skipped with a note).
    """
    t0 = time.perf_counter()
    say = progress or (lambda msg: None)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if problems is None:
        problems = PROBLEM_DIR / ("quick.npz" if quick else "full.npz")
        if not problems.is_file():
            problems = out / problems.name
            if not problems.is_file():
                say(f"recording {problems} ...")
                record_problem_set(problems, full=not quick, progress=say)
    items, meta = load_problems(problems)
    say(f"{len(items)} problems from {problems}")
    usable, skipped = available(solvers)
    outcomes, _ = run_problems(items, usable)
    rows = summarize(outcomes)
    write_results_csv(rows, out / "results.csv")
    say("closed loop ...")
    seconds = 0.3 if quick else 3.0
    loop_rows = closed_loop(usable, "A", seconds)
    _write_rows_csv(loop_rows, out / "closed_loop.csv")
    plot_results(rows, loop_rows, out / "solver_bench.png")
    command = f"qpnso bench solvers{' --quick' if quick else ''} --out {out}"
    info = (f"Scenario A guidance path, first {seconds:g} s offline (`solve_trajectory`), one run per "
            "back end as `ControllerConfig.qp_backend` with its default options; `proxsuite` is the "
            "shipped controller (native, warm, eps_abs 1e-11).  dq_diff_max: max |dq − dq of the first "
            "row| (rad/s).  Times in µs.")
    return write_report(out / "report.md", rows, loop_rows, skipped, meta, len(items), command,
                        time.perf_counter() - t0, usable, problems, info)


def _write_rows_csv(rows: Sequence[dict], path: Path) -> Path:
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    return path
