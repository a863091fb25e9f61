"""The runs: every problem solved by every usable back end at every setting (:func:`run_problems`,
problem-major, each solve judged into an :class:`~qpnso.lab.solver_bench.metrics.Outcome`), the
high-accuracy reference solution of each problem (:func:`compute_reference`), and the controller's
closed loop with each back end as ``qp_backend`` (:func:`closed_loop`).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import replace
from typing import Callable, Iterable, Sequence

import numpy as np

from qpnso.errors import ConfigError
from qpnso.lab.solver_bench.backends import (
    DEFAULT,
    HIGH_ACCURACY,
    NATIVE,
    BenchSettings,
    _Native,
    _qpsolvers_solve,
    available,
    solver_options,
)
from qpnso.lab.solver_bench.metrics import Outcome, kkt_residuals
from qpnso.lab.solver_bench.problems import BenchProblem, StandardForm, standard_form


def run_problems(
    problems: Sequence[BenchProblem],
    solvers: Iterable[str] | None = None,
    settings: Sequence[BenchSettings] = (DEFAULT, HIGH_ACCURACY),
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


def _outcome(
    p: BenchProblem, sf: StandardForm, s: BenchSettings, solver: str, found: bool, status: str, t: float, x, y, z, zb
) -> Outcome:
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
    return Outcome(
        solver,
        s.name,
        p.name,
        found,
        status,
        t,
        primal,
        dual,
        gap,
        cost_error,
        x_error,
        success,
        s.time_limit_s,
        detail,
        p.level,
    )


REFERENCE_SOLVERS = ("daqp", "quadprog", "proxqp")


def compute_reference(
    problems: Sequence[BenchProblem], solvers: Sequence[str] = REFERENCE_SOLVERS, eps: float = 1e-12
) -> None:
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


CLOSED_LOOP_KEYS = (
    "tool_position_error_max_m",
    "tool_rotation_error_max_deg",
    "constraint_proximity_deg",
    "rom_proximity_deg",
    "tick_time_median_us",
    "tick_time_p99_us",
    "solve_time_median_us",
    "solve_time_p99_us",
    "status_QP_FAILED_ticks",
    "status_ELBOW_SLACK_ticks",
)


def closed_loop(
    backends: Sequence[str], scenario: str = "A", seconds: float = 2.0, options: Callable[[str], dict] | None = None
) -> list[dict]:
    """The scenario's guidance path (first ``seconds`` s, offline tracking) solved by the controller
    with each back end as ``qp_backend``; the run metrics per back end (:data:`CLOSED_LOOP_KEYS`),
    ``dq_diff_max`` = max |dq − dq of the first back end| over the run (rad/s) and the run's
    first controller message (e.g. why a QP failed).

    ``options(backend)`` gives ``QPSettings.solver_options`` (default: none, each solver's
    defaults, i.e. what ``ControllerConfig(qp_backend=name)`` does).  A back end the
    controller refuses is reported with its error.
    """
    from qpnso.control.config import ControllerConfig
    from qpnso.control.offline import solve_trajectory
    from qpnso.lab.scenarios import load_scenario
    from qpnso.model.robot import load_robot

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
