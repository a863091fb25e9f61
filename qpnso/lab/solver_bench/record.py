"""Recording the controller's QPs: :class:`QPRecorder` wraps ``ctrl.qp.solve_problem`` of one controller and
rebuilds each level's QP with the cascade's public functions (:func:`level_problems`), advanced with the
controller's own answer of the level above, so the benchmark solves exactly the QPs the controller solved;
:func:`record_problem_set` runs the shipped controller on every source and saves the set with its
reference solutions.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from qpnso.lab.solver_bench.backends import NATIVE
from qpnso.lab.solver_bench.problems import BenchProblem, save_problems
from qpnso.lab.solver_bench.runs import compute_reference
from qpnso.qp import Level, QPSettings
from qpnso.qp.arrays import QPArrays
from qpnso.qp.cascade import level_parts
from qpnso.qp.cascade_state import CascadeState
from qpnso.qp.levels import _validate_level
from qpnso.qp.problem import STOPPED, problem_levels
from qpnso.qp.results import HQPResult, LevelResult, LevelStatus
from qpnso.qp.settings import tolerance_record

BENCH_REGULARIZATION = 1e-7
"""μ the recorded problems are built with: the controller's value for every ``qpsolvers`` back end
(strictly convex levels, unique reference solution); the native path ships with μ = 0."""


def level_problems(
    n: int,
    levels: Sequence[Level],
    lb: np.ndarray | None,
    ub: np.ndarray | None,
    result,
    settings: QPSettings,
    sequence: str = "",
    tick: int = 0,
) -> list[BenchProblem]:
    """The QP of each level (``n`` joint velocities) the controller's solver was asked (docs/method.md §7).

    Rebuilds the cascade on its record (:class:`qpnso.qp.cascade_state.CascadeState`), advanced with the
    controller's own answer ``result.levels[k].x`` (an :class:`qpnso.qp.HQPResult`), so each problem is the
    one the back end got.  Levels with no free direction (no QP was solved) and levels after a failed one
    are left out.
    """
    lo = np.full(n, -np.inf) if lb is None else np.asarray(lb, dtype=float).copy()
    hi = np.full(n, np.inf) if ub is None else np.asarray(ub, dtype=float).copy()
    data = [_validate_level(level, n, f"levels[{k}]") for k, level in enumerate(levels)]
    rows = sum(0 if d.C is None else d.C.shape[0] for d in data)
    state = CascadeState(n, rows, max(d.n_slack for d in data), tolerance_record(settings))
    state.start(lo, hi)
    out: list[BenchProblem] = []
    for k, (level, res) in enumerate(zip(data, result.levels)):
        if not res.ok:
            break
        parts = level_parts(level, n)
        qp, _ = state.build(parts)
        x_prev, Z = state.x, state.Z  # (what the level was built in: building changes neither)
        if qp.H.shape[0] and Z.shape[1]:
            out.append(_from_level_qp(qp, x_prev, Z, f"{sequence}/t{tick:05d}/L{k + 1}", sequence, k + 1, tick, res.x))
        if k + 1 < len(levels):
            state.advance(parts, res.x)
    return out


def _from_level_qp(
    qp: QPArrays,
    x_prev: np.ndarray,
    Z: np.ndarray,
    name: str,
    sequence: str,
    level: int,
    tick: int,
    x_controller: np.ndarray | None,
) -> BenchProblem:
    P = 0.5 * (qp.H + qp.H.T)  # symmetric to the last bit (it is up to ~1e-17; sip refuses otherwise)
    box = qp.box_l.shape[0] > 0
    return BenchProblem(
        name,
        sequence,
        level,
        tick,
        P,
        _copy(qp.g),
        _copy(qp.C),
        _copy(qp.l),
        _copy(qp.u),
        _copy(qp.box_l) if box else None,
        _copy(qp.box_u) if box else None,
        x_prev,
        Z,
        _copy_or_none(x_controller),
    )


def _copy(a: np.ndarray) -> np.ndarray:
    """A float copy (no aliasing)."""
    return np.array(a, dtype=float)


def _copy_or_none(a: np.ndarray | None) -> np.ndarray | None:
    return None if a is None else _copy(a)


class QPRecorder:
    """Records every QP a controller's hierarchical solver is asked, by wrapping
    ``ctrl.qp.solve_problem`` of that instance (nothing else is patched): each tick's problem
    record as its levels (:func:`qpnso.qp.problem.problem_levels`), rebuilt with the answers
    the solver gave (:func:`level_problems`).

    Use as a context manager; ``problems`` collects :class:`BenchProblem` of
    the ticks ``k`` with ``keep(k)`` true (default all), sequence name
    ``f"{source}/c{chunk(k)}"``.  ``regularization`` rebuilds the levels with
    another μ (None: the controller's own settings).
    """

    def __init__(
        self,
        ctrl,
        source: str,
        keep: Callable[[int], bool] = lambda k: True,
        chunk: Callable[[int], int] = lambda k: 0,
        regularization: float | None = None,
    ) -> None:
        self.ctrl, self.source, self.keep, self.chunk = ctrl, source, keep, chunk
        settings = ctrl.qp.settings
        self.settings = settings if regularization is None else replace(settings, regularization=regularization)
        self.problems: list[BenchProblem] = []
        self.ticks = 0

    def __enter__(self) -> "QPRecorder":
        original = self.ctrl.qp.solve_problem

        def solve_problem(problem, solution, time_budget=None):
            levels = problem_levels(problem)
            lb, ub = problem[0]["lb"].copy(), problem[0]["ub"].copy()
            why = original(problem, solution, time_budget)
            if self.keep(self.ticks):
                self.problems += level_problems(
                    self.ctrl.qp.n,
                    levels,
                    lb,
                    ub,
                    _answers(solution, bool(why), len(levels)),
                    self.settings,
                    f"{self.source}/c{self.chunk(self.ticks)}",
                    self.ticks,
                )
            self.ticks += 1
            return why

        self.ctrl.qp.solve_problem = solve_problem  # instance attribute shadows the method
        return self

    def __exit__(self, *exc) -> None:
        del self.ctrl.qp.solve_problem


def _answers(solution: np.ndarray, failed: bool, n_levels: int) -> HQPResult:
    """The per-level answers of a solved problem record (:func:`qpnso.qp.problem.solution_dtype`), as
    :func:`level_problems` reads them: level 1's least-norm answer ``x1``, level 2's ``x`` (a failed
    level: not solved, the levels below it left out)."""
    S = solution[0]
    level1_ok = not (failed and S["outcome"] == STOPPED)
    levels = [LevelResult(LevelStatus.SOLVED if level1_ok else LevelStatus.INACCURATE, x=S["x1"].copy())]
    if n_levels > 1:
        levels.append(LevelResult(LevelStatus.INACCURATE if failed else LevelStatus.SOLVED, x=S["x"].copy()))
    return HQPResult(None if failed else S["x"].copy(), not failed, "", None, levels, 0.0)


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


_Source = tuple[str, str, dict, Callable[..., Any], Callable[..., Any]]
"""A recorded run: name, robot name, controller settings, trajectory factory (robot), q0 factory (robot, trajectory)."""


def _sources(seed: int) -> list[_Source]:
    """``(name, robot name, controller settings, trajectory factory, q0 factory)`` of each recorded run:
    scenarios A and B (guidance), the guidance path on the iiwa14, held tools at random postures."""
    from qpnso.control.offline import initial_configuration
    from qpnso.control.trajectory import guidance_path, hold
    from qpnso.lab.scenarios import load_scenario

    out: list[_Source] = []
    for name in ("A", "B"):
        sc = load_scenario(name)
        out.append(
            (
                f"scenario{name}",
                sc.robot,
                sc.controller,
                lambda robot, sc=sc: sc.path(),
                lambda robot, traj, sc=sc: sc.start(robot),
            )
        )

    def iiwa_path(robot):
        q = np.radians([0.0, 40.0, 0.0, -80.0, 0.0, 60.0, 0.0])
        return guidance_path(robot.tool_pose(q), size=0.08, speed=0.05)

    out.append(
        (
            "guidance_iiwa14",
            "iiwa14",
            {},
            iiwa_path,
            lambda robot, traj: initial_configuration(robot, traj.pose(traj.t[0])),
        )
    )
    rng = np.random.default_rng(seed)
    for robot_name in ("lwr4p", "iiwa14"):
        for i in range(2):
            u = rng.uniform(0.15, 0.85, 7)  # fraction of each joint range: away from the limits
            out.append(
                (
                    f"hold_{robot_name}_{i}",
                    robot_name,
                    {},
                    lambda robot, u=u: hold(robot.tool_pose(robot.q_min + u * (robot.q_max - robot.q_min)), 5.0),
                    lambda robot, traj, u=u: robot.q_min + u * (robot.q_max - robot.q_min),
                )
            )
    return out


def record_problem_set(
    path: Path,
    full: bool = False,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
    regularization: float = BENCH_REGULARIZATION,
) -> Path:
    """Run the controller (default ``qp`` strategy, native ProxSuite) on every source of
    :func:`_sources`, record the QPs of the ticks the plan keeps, compute their references,
    save them to ``path``.  Deterministic for a given ``seed``."""
    from qpnso.control.config import ControllerConfig
    from qpnso.control.controller import Controller
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
    meta = {
        "plan": plan.__dict__,
        "seed": seed,
        "regularization": regularization,
        "recorded_with": "qpnso.lab.solver_bench.record_problem_set",
        "qp_backend": NATIVE,
    }
    return save_problems(path, problems, meta)
