"""The per-tick controller: what a user puts in a 1 kHz control loop (docs/method.md §7).

``Controller(robot, ControllerConfig(...))``, ``reset(q0)``, then every tick
``step(q, dq, tool_twist) -> Command``.  Every tick, for every strategy, is the same four steps on
named records (:mod:`qpnso.control.tick`):

1. the arm's state from one CasADi call (:mod:`qpnso.control.state`), read in place;
2. :func:`~qpnso.control.tick.begin_tick`: the elbow — arm angle unwrapped along the run, continuity
   interval (:mod:`qpnso.elbow.closed_form`, renewed here when due), ROM_t with the safety margin, the
   stiffness sigmoid (:mod:`qpnso.control.memory`) — and level 1 ``J q̇ = v_tool + K_p e_pose − ½dt·J̇q̇``
   with the joint position/velocity bounds, into the problem record (:mod:`qpnso.qp.problem`);
3. the strategy's level 2 (:mod:`qpnso.control.strategies`), then the hierarchical QP
   (:meth:`~qpnso.qp.solver.HierarchicalQP.solve_problem`: the line fast path or the cascade);
4. :func:`~qpnso.control.tick.finish_tick`: ``dq``, ``q_des = q + dt·dq`` and the torque
   ``τ = g(q) + Nᵀ τ_null`` with the dynamically consistent null-space projector.  When the solved ``dq``
   misses the velocity level 1's second-order term was taken along, steps 3–4 run once more with the term
   along ``dq`` (:meth:`Controller._second_pass`; 0.8 % of fuzzed ticks, none of the main job).

A failed or infeasible QP never reaches the robot: the command falls back to
the level-1 solution (tool held, no null-space motion) or, if level 1 failed
too, to zero velocity, and ``Command.status`` says so.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pinocchio as pin

from qpnso.compiled_cache import announce_numba_if_cold
from qpnso.control.config import Command, ControllerConfig, ElbowState, Status, _stamped, _status
from qpnso.control.flags import (
    ELBOW_BITS,
    FLAG_ELBOW_DROPPED,
    FLAG_INTERNAL_ERROR,
    FLAG_OBSTACLE,
    FLAG_QP_DEADLINE,
    FLAG_QP_FAILED,
    PREDICTION_MISSED,
)
from qpnso.control.memory import KEEP_OUT_ROWS, interval_failed, new_memory, store_interval
from qpnso.control.params import interval_in_tick, tick_params
from qpnso.control.rows import RowKind
from qpnso.control.rows.kind import row_counts
from qpnso.control.state import StateEvaluator, sanitize_state
from qpnso.control.tick import (
    TICK_NEED_INTERVAL,
    TICK_NOT_FINITE,
    TICK_Q_REFUSED,
    TICK_STATE_NOT_FINITE,
    TICK_TWIST_NOT_FINITE,
    TICK_TWIST_TOO_FAST,
    Report,
    begin_tick,
    finish_tick,
    limits_status,
    stop_tick,
    tick_dtype,
)
from qpnso.elbow.clearance import OBSTACLE_ROOM, set_obstacles, still_obstacles
from qpnso.elbow.intervals import NumericalWalk, closed_form_applies
from qpnso.elbow.srs import pose_arrays
from qpnso.errors import ConfigError, InputError, QpnsoError
from qpnso.model.collision import has_capsules, link_capsules
from qpnso.model.costs import CostModel
from qpnso.model.obstacles import Obstacle, Sphere, as_obstacles, checked_velocities, placement_velocity
from qpnso.model.robot import Robot, as_vector, checked_pose, finite_scalar, tick_vector
from qpnso.qp import HierarchicalQP
from qpnso.qp.problem import STOPPED, new_problem
from qpnso.records import new_record


@dataclass(slots=True)
class TickRecords:
    """The controller's tick record (:func:`qpnso.control.tick.tick_dtype`, made once; its ``memory`` anew at
    every reset) and views of its parts, each a 1-element record: ``params`` (:mod:`qpnso.control.params`),
    ``memory`` (:mod:`qpnso.control.memory`), ``problem`` and ``solution`` (:mod:`qpnso.qp.problem`),
    ``report`` and ``command`` (:mod:`qpnso.control.tick`), ``state`` (:mod:`qpnso.control.state`, which
    the CasADi function writes); ``q`` and ``dq_meas`` (rad, rad/s) this tick's measurements."""

    tick: np.ndarray
    params: np.ndarray
    memory: np.ndarray
    problem: np.ndarray
    solution: np.ndarray
    report: np.ndarray
    command: np.ndarray
    state: np.ndarray
    q: np.ndarray
    dq_meas: np.ndarray

    def elbow(self) -> ElbowState:
        """The elbow of this tick's report (rad, N·m/rad)."""
        r = self.report[0]
        bits = int(r["bits"])
        return ElbowState(
            float(r["ns"]),
            (float(r["rom_lo"]), float(r["rom_hi"])),
            (float(r["iv_lo"]), float(r["iv_hi"])),
            float(r["stiffness"]),
            _status(bits & (ELBOW_BITS | FLAG_ELBOW_DROPPED)),
            dropped=bool(r["dropped"]),
        )


def checked_rows(rows: Sequence[RowKind], robot: Robot, dt: float) -> tuple[RowKind, ...]:
    """The row kinds, checked: each a :class:`RowKind` whose bounds are (m,) arrays with ``h_lo ≤ h_hi``,
    no NaN, and whose damper gain γ satisfies ``0 < γ·dt ≤ 1``; :class:`ConfigError` naming the kind."""
    out = tuple(rows)
    for kind in out:
        if not isinstance(kind, RowKind):
            raise ConfigError(f"rows: {kind!r} is not a RowKind (qpnso.control.rows)")
        lo, hi = (np.atleast_1d(np.asarray(b, dtype=float)) for b in kind.bounds(robot))
        if lo.ndim != 1 or lo.shape != hi.shape or np.isnan(lo).any() or np.isnan(hi).any() or (lo > hi).any():
            raise ConfigError(f"rows: {kind.name}.bounds must be two (m,) arrays with lo <= hi and no NaN")
        if not 0 < kind.gain * dt <= 1:
            raise ConfigError(f"rows: {kind.name}.gain = {kind.gain!r} must be in (0, 1/dt] 1/s")
    return out


STOPPING = "joints brought to rest at ddq_max"
"""What a stop command does: the joints slow down at their acceleration bound (a command's change per tick is
bounded), gravity compensated."""


class Controller:
    """Hierarchical-QP null-space controller of a 7-DOF arm (docs/method.md §7)."""

    def __init__(self, robot: Robot, config: ControllerConfig | None = None, rows: Sequence[RowKind] = ()) -> None:
        """``rows``: constraint row kinds beyond the joint limits and the elbow (:mod:`qpnso.control.rows`),
        kept by every strategy's tick."""
        from qpnso.control.strategies import make_strategy

        robot.require_redundant_arm()  # ModelError naming the arm, instead of ROM_EMPTY ticks
        announce_numba_if_cold()  # one line on stderr when the kernels compile now (empty cache): building the
        # params already runs some (the closed-form IK of the keep-out record)
        self.robot = robot
        self.config = config or ControllerConfig()
        cfg = self.config
        self.rows = checked_rows(rows, robot, cfg.dt)
        self.cost = CostModel(robot, cfg.weights, cfg.potential_speed, cfg.potential_angular_speed, compile=cfg.compile)
        _, _, self._hard_room, self._soft_room = row_counts(self.rows, robot)
        room = self._hard_room + self._soft_room
        self.capsules = link_capsules(robot) if has_capsules(robot) or cfg.obstacles else None
        self.evaluate = StateEvaluator(
            self.cost, compile=cfg.compile, rows=self.rows, room=room, capsules=self.capsules
        )
        self.elbow_config = cfg.elbow()
        self.qp = HierarchicalQP(robot.nq, backend=cfg.qp_backend, settings=cfg.qp_settings)
        n = robot.nq
        self._dq_accepted = cfg.dq_tolerance_factor * robot.dq_max  # rad/s: beyond, InputError
        self._time_budget = cfg.solver_time_budget
        self._no_twist = np.zeros(6)  # never written (writable: a read-only array is another Numba type)
        hard_room, soft_room = self._hard_room, self._soft_room
        caps = self.capsules
        points, count = (caps.points_count, caps.count) if caps else (0, 0)
        self._obstacle_room = max(OBSTACLE_ROOM, len(cfg.obstacles)) if caps else 0
        problem_soft = soft_room + (KEEP_OUT_ROWS if caps else 0)  # (the keep-out rows are soft rows too)
        self.tick = tick = new_record(tick_dtype(n, room, hard_room, problem_soft, points, count, self._obstacle_room))
        tick["params"] = tick_params(robot, cfg, self.rows, room, caps, self._obstacle_room)
        tick["problem"] = new_problem(n, hard_room, 1 + problem_soft)
        self.obstacles = tuple(cfg.obstacles)
        self.evaluate.bind(tick["state"])
        self.records = TickRecords(
            tick,
            tick["params"],
            tick["memory"],
            tick["problem"],
            tick["solution"],
            tick["report"],
            tick["command"],
            tick["state"],
            np.zeros(n),
            np.zeros(n),
        )
        command, memory = self.records.command, self.records.memory
        self._command_views = (command["dq"][0], command["q_des"][0], command["tau"][0])
        self._ref = (memory["ref_R"][0], memory["ref_p"][0])  # views (reset rewrites the memory in place)
        self.strategy = make_strategy(cfg.strategy, self)
        self._reset_done = False
        self._warm_up()

    def _warm_up(self) -> None:
        """Dry ticks at the robot's sample configuration, then forgotten: the Numba kernels of
        :mod:`qpnso.linalg`, :mod:`qpnso.qp` and :mod:`qpnso.control.tick` compile (seconds, once per machine,
        then cached on disk) or load here, never in a control tick — on the line fast path, the general
        cascade (:meth:`HierarchicalQP.warm_up`), with the elbow dropped and with the elbow outside its ROM (the
        ``rom`` strategy's closed-form set-point).  An arm whose tick may walk its continuity interval
        numerically (no closed form, or links that do not turn rigidly with the arm angle once obstacles are
        set) also walks here as a tick does (:meth:`_update_interval`): a walk to its end stored, with the
        controller's obstacles or one far away, and a walk that fails.  (A kernel given another argument type —
        Pinocchio's Fortran-ordered rotation once reached ``store_interval`` only when a tick's walk finished —
        compiles a new signature: 15–22 ms of CPU in a new process, about 1 s on a cold cache, inside a tick.)"""
        self.qp.warm_up(line=False, problem=self.records.problem)  # the general cascade's kernels (the dry ticks
        # below may not reach it)
        q = self.robot.sample_configuration()
        self.reset(q)
        self.step(q)
        self.step(q, tool_pose=self.robot.tool_pose(q))  # (the reference's own check of q)
        limits = self.records.params[0]
        wrist_sin_min = float(limits["wrist_sin_min"])
        limits["wrist_sin_min"] = 2.0  # every arm angle singular: the dropped elbow's tick
        try:
            self.step(q)
        finally:
            limits["wrist_sin_min"] = wrist_sin_min
        self.reset(q, ns0=float(self.records.memory[0]["ns"]) + math.pi)  # the ROM opposite the elbow
        self.step(q)
        geo = self.records.params["geo"][0] if self.capsules is not None else None
        if not closed_form_applies(self.robot) or (geo is not None and geo["arcs"] == 0.0):
            placed = self.obstacles
            if geo is not None and not placed:  # one 1 km away: the walk's clearance kernels load before the first
                self.obstacles = (Sphere(center=(1e3, 1e3, 1e3), radius=0.1),)  # set_obstacles
            try:
                self._update_interval(q, self.records.state, math.inf)  # a walk to its end, stored
            finally:
                self.obstacles = placed
            self._update_interval(self.robot.q_max + 1.0, self.records.state)  # a walk that cannot start
        self._stop(q, self.robot.gravity(q), 0, time.perf_counter(), "warm-up")  # the stop command's kernel
        self.reset(q)
        self._reset_done = False

    # ---------------------------------------------------------------- reset
    def reset(self, q0: object, ns0: float | None = None) -> None:
        """Start a run at ``q0`` (rad): holds its tool pose, centres the ROM on its arm angle.

        ``ns0`` (rad) overrides the ROM centre.  Everything a run remembers is made anew: the tick's
        memory record, the previous command and twist, the QP's warm starts, the strategy's filters.
        """
        q = self.robot.check_q(q0, "q0")
        if ns0 is not None:
            ns0 = finite_scalar(ns0, "ns0")
        state = self.evaluate(q)
        self.q0 = q
        centre = float(state.arm_angle if ns0 is None else ns0)
        self.records.memory[:] = new_memory(
            self.robot.nq, state.arm_angle, centre, state.tool_rotation, state.tool_position
        )
        report = self.records.report[0]  # (a stop tick reports the clearance begin_tick last found: none yet)
        report["clearance"], report["clear_capsule"], report["clear_obstacle"], report["obstacle_rows"] = (
            math.inf,
            -1,
            -1,
            0,
        )
        self._dq_prev = np.zeros(self.robot.nq)
        self.records.command["dq"] = 0.0  # (the tick bounds its command's change from the last one: from rest)
        self._twist_prev = np.zeros(6)  # m/s, rad/s: the previous tick's tool twist (its change is predicted)
        self._walk: NumericalWalk | None = None  # an arm without the closed form: its interval's walk under way
        if not self.records.params[0]["closed_form_interval"]:  # its first interval here, whole (a reset is no
            # tick): the first tick has it
            self._first_interval(q, state)
        self.qp.reset()  # warm starts and solver objects: a reset controller answers as a new one
        self._forget_obstacle_motion()
        self.strategy.reset(q, state)
        self._reset_done = True
        self.step_count = 0

    _placed: tuple[tuple[Obstacle, ...], int] | None  # the volumes' last placement and the step count then

    def set_obstacles(self, obstacles: Sequence[Obstacle], velocities: Sequence[object] | None = None) -> None:
        """Move, add or remove the keep-out volumes (world frame, m) between ticks: from the next tick the rows
        keep the links from these, and the continuity interval is renewed against them (it is the volumes'
        geometry as placed now: their motion does not enter it).  At most the room the controller was built
        with (``max(8, len(config.obstacles))``).

        A moving volume's velocity enters its rows (the relative velocity, docs/method.md §10), and the torque
        wall with them.  ``velocities``: one entry per volume, world frame — 3 numbers (its centre's velocity,
        m/s: a sphere's or box's centre, a capsule's midpoint), 6 (then its angular velocity about that centre,
        rad/s) or None.  Where not given (None, or no ``velocities``) it is estimated from this placement and the
        same entry of the previous call (matched by position in the list): the displacement over the ticks
        stepped between the two calls (at least one tick, ``dt`` each;
        :func:`qpnso.model.obstacles.placement_velocity`).  That assumes the volume is placed once a tick as it
        moves (or every N ticks: then its mean velocity); an estimated velocity holds for as many ticks as it
        was measured over and is then dropped (a volume placed once and left is still again), a given one until
        the next call.  The first call after the constructor or a ``reset``, a volume of another kind at that
        position, or one that jumped faster than ``PLACEMENT_JUMP_SPEED`` (2 m/s, a re-placement) is taken as
        still.  A :class:`qpnso.settings.SettingError` or :class:`~qpnso.errors.InputError` names what is wrong,
        and nothing changes."""
        if self.capsules is None:
            raise ConfigError(f"{self.robot.name}: no link capsules (models/collision.json): obstacles not supported")
        checked = as_obstacles(obstacles)
        given: list[np.ndarray | None] = [None] * len(checked)
        if velocities is not None:
            given = checked_velocities(velocities, len(checked))
        motion, hold = self._obstacle_motion(checked, given)
        params = self.records.params
        set_obstacles(params["geo"], checked, motion, hold)
        params[0]["closed_form_interval"] = interval_in_tick(self.robot, params)  # (links that do not turn
        # rigidly with the arm angle: the numerical walk, with the obstacles)
        self.obstacles = checked
        self._placed = (checked, self.step_count)
        self._walk = None  # (a walk under way knew the old obstacles)
        self.records.memory[0]["iv_age"] = math.inf  # (renewed at the next tick, against these)
        self.records.memory[0]["iv_p"][:] = math.inf  # (a held tool renews it too: its pose "moved")

    def _obstacle_motion(
        self, obstacles: tuple[Obstacle, ...], given: list[np.ndarray | None]
    ) -> tuple[np.ndarray, np.ndarray]:
        """The volumes' velocities (len, 6: m/s then rad/s, world) for :meth:`set_obstacles` and the ticks each
        holds for (len,): the ``given`` ones until the next placement (inf), the others estimated against the
        previous placement (``self._placed``: the volumes and the step count when they were placed; None after
        a reset) for as many ticks as that placement is old (at least one)."""
        out, hold = np.zeros((len(obstacles), 6)), np.zeros(len(obstacles))
        before, at = self._placed if self._placed is not None else ((), self.step_count)
        ticks = max(self.step_count - at, 1)
        for i, (obstacle, velocity) in enumerate(zip(obstacles, given)):
            if velocity is not None:
                out[i], hold[i] = velocity, math.inf
            elif i < len(before):
                out[i], hold[i] = placement_velocity(before[i], obstacle, self.config.dt * ticks), ticks
        return out, hold

    def _forget_obstacle_motion(self) -> None:
        """A new run (``reset``): the volumes' last placement forgotten, so the next :meth:`set_obstacles`
        takes them as still unless given their velocities, and until then they are still (velocities zero)."""
        self._placed = None
        if self.capsules is not None:
            still_obstacles(self.records.params["geo"])

    def info(self) -> dict[str, str]:
        """What runs this controller's ticks, as plain data: the robot, the strategy, the C++ core's build
        (``qpnso._core.build_info()``) and what evaluates the tick's CasADi state function now, "compiled C"
        (the model's library, compiled once per machine in the background) or "casadi runtime" (CasADi's own,
        until then or without a C compiler; :mod:`qpnso.model.codegen`)."""
        from qpnso import _core

        return {
            "robot": self.robot.name,
            "strategy": self.config.strategy,
            "core": _core.build_info(),
            "state_function": self.evaluate.runtime,
        }

    @property
    def ddq_max(self) -> np.ndarray:
        """The joint acceleration bounds (rad/s², a copy): every command changes each joint's speed by at most
        ``ddq_max·dt`` from the previous tick's (``ControllerConfig.ddq_max``, else ``Robot.ddq_max``)."""
        return self.records.params[0]["ddq_max"].copy()

    @property
    def ns0(self) -> float:
        """The ROM's centre (rad)."""
        return float(self.records.memory[0]["ns0"])

    @property
    def ref_rotation(self) -> np.ndarray:
        """The tool's reference rotation (world ← tool), a copy."""
        return self._ref[0].copy()

    @ref_rotation.setter
    def ref_rotation(self, value: np.ndarray) -> None:
        self._ref[0][:] = value

    @property
    def ref_position(self) -> np.ndarray:
        """The tool's reference position (m, world), a copy."""
        return self._ref[1].copy()

    @ref_position.setter
    def ref_position(self, value: np.ndarray) -> None:
        self._ref[1][:] = value

    # ----------------------------------------------------------------- step
    def step(
        self, q: object, dq: object = None, tool_twist: object = None, tool_pose: pin.SE3 | None = None
    ) -> Command:
        """One tick.

        ``q`` (rad) measured joints; ``dq`` (rad/s) measured joint velocity
        (None: the previous command is assumed); ``tool_twist`` (6,) the tool
        motion the surgeon or trajectory imposes, world frame, linear velocity of
        the tool point (m/s) then angular velocity (rad/s) — None holds the tool;
        ``tool_pose`` (``pinocchio.SE3``) a reference pose for this tick (offline
        tracking), otherwise the reference integrates ``tool_twist``.
        """
        t0 = time.perf_counter()
        if not self._reset_done:
            raise QpnsoError("call Controller.reset(q0) before step()")
        qv = tick_vector(q, self.robot.nq, "q")
        dq_meas = self._dq_prev if dq is None else self._checked_dq(dq)
        twist = self._no_twist if tool_twist is None else tick_vector(tool_twist, 6, "tool_twist")
        if tool_pose is not None:
            P = self.records.params[0]
            if limits_status(qv, P["q_accept_lo"], P["q_accept_hi"]):
                self._refuse_q(qv)  # before the reference changes: a refused tick changes nothing
            self.ref_rotation, self.ref_position = checked_pose(tool_pose, "tool_pose")
        fallbacks = self.qp.stats.active_set_fallbacks
        try:
            cmd = self._tick(qv, twist, dq_meas, t0, tool_pose is None)
        except QpnsoError:
            raise
        except Exception as exc:  # a bug must not reach the robot as a traceback: stop, say why
            cmd = self._stop(
                qv, self._gravity_or_zero(qv), FLAG_INTERNAL_ERROR, t0, f"internal error ({type(exc).__name__}: {exc})"
            )
        if self.qp.stats.active_set_fallbacks != fallbacks:
            cmd.status |= Status.QP_FALLBACK
        self._dq_prev = cmd.dq
        self._twist_prev[:] = twist  # (a copy: the caller may reuse its array)
        self.step_count += 1
        return cmd

    def _tick(self, qv: np.ndarray, twist: np.ndarray, dq_meas: np.ndarray, t0: float, follow: bool) -> Command:
        """The four steps of every tick (module docstring); ``follow``: the reference advances along the twist
        (no ``tool_pose`` given)."""
        rec, tick = self.records, self.tick
        state = self.evaluate.record(qv, self._dq_prev, twist, self._twist_prev)  # (rec.state: written in place)
        rec.q, rec.dq_meas = qv, dq_meas
        code = begin_tick(qv, twist, tick, follow)
        if code == TICK_NEED_INTERVAL:
            self._update_interval(qv, state)
            code = begin_tick(qv, twist, tick, follow)
        if code == TICK_NOT_FINITE or code == TICK_Q_REFUSED:
            self._refuse_q(qv)  # raises, naming the entries or the joint
        if code == TICK_TWIST_NOT_FINITE:
            as_vector(twist, 6, "tool_twist")  # raises, naming the entries
            raise InputError("tool_twist contains NaN or inf")  # (never reached: the kernel and as_vector agree)
        if code == TICK_TWIST_TOO_FAST:
            self._refuse_twist(twist)
        if code == TICK_STATE_NOT_FINITE:
            bits = int(rec.report[0]["bits"])
            return self._stop(qv, state[0]["g"].copy(), bits, t0, "the arm's state is not finite")
        self.strategy.fill(rec)
        t1 = time.perf_counter()
        why = self.qp.solve_problem(rec.problem, rec.solution, self._time_budget)
        solve_time = time.perf_counter() - t1
        bits = finish_tick(qv, dq_meas, tick)
        if bits & PREDICTION_MISSED:
            why, bits, again = self._second_pass(qv, dq_meas)
            solve_time += again
        message = ""
        if why:
            bits |= FLAG_QP_FAILED | (FLAG_QP_DEADLINE if rec.solution[0]["out_of_time"] else 0)
            stopped = rec.solution[0]["outcome"] == STOPPED
            message = f"QP failed ({why}): " + (STOPPING if stopped else "tool held, no null-space motion")
        return self._command(bits, t0, message, solve_time)

    def _second_pass(self, qv: np.ndarray, dq_meas: np.ndarray) -> tuple[str, int, float]:
        """Level 1's second-order term ``½dt·J̇q̇`` taken again along the solved ``q̇`` (the tick's first solve was
        farther than :func:`~qpnso.control.state.prediction_tolerance` from the predicted ``q̇``: a null-space
        step the prediction could not see, e.g. level 1 leaving the joint bounds when a pull stops), then the
        tick's problem solved and finished again (same level 2).  Returns the solve's failure (or ""), the
        status bits and the solve's wall time (s).  The state is evaluated along ``q̇`` (with no change of
        twist, the predicted velocity is ``q̇`` itself).  A drift that is not finite there, or a second solve that
        fails, keeps the first solve (a failure's safe command would stop the self-motion at once: a step)."""
        rec, tick = self.records, self.tick
        s, P, p = rec.state[0], rec.params[0], rec.problem[0]
        first_drift, first_b1, first_solution = s["drift"].copy(), p["b1"].copy(), rec.solution.copy()
        self.evaluate.record(qv, first_solution[0]["x"], self._no_twist, self._no_twist)
        sanitize_state(s)  # (q is the tick's: the rest of the state is as begin_tick left it)
        solve_time = 0.0
        if np.all(np.isfinite(s["drift"])):
            p["b1"] += P["half_dt"] * (first_drift - s["drift"])
            t0 = time.perf_counter()
            why = self.qp.solve_problem(rec.problem, rec.solution, self._time_budget)
            solve_time = time.perf_counter() - t0
            if not why:
                return why, finish_tick(qv, dq_meas, tick) & ~PREDICTION_MISSED, solve_time
        s["drift"], p["b1"], rec.solution[:] = first_drift, first_b1, first_solution
        return "", finish_tick(qv, dq_meas, tick) & ~PREDICTION_MISSED, solve_time

    def _command(self, bits: int, t0: float, message: str, solve_time: float) -> Command:
        """The :class:`Command` of this tick's records, stamped (:func:`qpnso.control.config._stamped`)."""
        dq, q_des, tau = self._command_views
        r = Report._make(self.records.report.item())  # (one read of the record: ~10x cheaper than by field)
        cmd = Command(
            dq.copy(),
            q_des.copy(),
            tau.copy(),
            r.null_stiffness,
            r.ns,
            (r.rom_lo, r.rom_hi),
            (r.iv_lo, r.iv_hi),
            r.cost,
            Status.OK,
            solve_time,
            0.0,
            (r.e_pos, r.e_rot),
            message or (self._obstacle_message(r) if bits & FLAG_OBSTACLE else ""),
            r.clearance,
            r.null_inertia,
            r.null_damping,
        )
        return _stamped(cmd, bits, t0)

    def _obstacle_message(self, r: Report) -> str:
        """What ``OBSTACLE`` means this tick: which link, how near which obstacle (the least clearance's pair),
        and whether it is inside its margin, overlaps the obstacle, or cannot keep its keep-out row."""
        link = self.capsules.names[r.clear_capsule] if self.capsules and r.clear_capsule >= 0 else "a link"
        margin = self.config.obstacle_margin
        where = f"obstacle: {link} is {r.clearance:.4f} m from obstacle {r.clear_obstacle}"
        if r.clearance < 0.0:
            return f"{where}: it overlaps the obstacle (margin {margin:g} m)"
        if r.clearance < margin:
            return f"{where}: inside its margin of {margin:g} m"
        return f"{where} (margin {margin:g} m) and the tool's or the obstacle's motion leaves no way round it"

    def _refuse_q(self, qv: np.ndarray) -> None:
        """Raise :class:`InputError` naming the first joint beyond its limits by more than
        ``q_limit_tolerance_deg``, with its value and limits in degrees and radians (or NaN/inf)."""
        as_vector(qv, self.robot.nq, "q")  # NaN or inf: raises, naming the entries
        P = self.records.params[0]
        i = int(np.argmax((qv < P["q_accept_lo"]) | (qv > P["q_accept_hi"])))
        r = self.robot
        raise InputError(
            f"q[{i}] ({r.joint_names[i]}) = {math.degrees(qv[i]):.4g}° ({qv[i]:.6g} rad) is outside its limits "
            f"[{math.degrees(r.q_min[i]):.4g}°, {math.degrees(r.q_max[i]):.4g}°] "
            f"([{r.q_min[i]:.6g}, {r.q_max[i]:.6g}] rad) by more than {self.config.q_limit_tolerance_deg:g}°; "
            f"q is in radians"
        )

    def _refuse_twist(self, twist: np.ndarray) -> None:
        """Raise :class:`InputError` for a tool twist faster than the accepted tool speeds, with its speeds."""
        cfg = self.config
        v, w = float(np.linalg.norm(twist[:3])), float(np.linalg.norm(twist[3:]))
        raise InputError(
            f"tool_twist: linear speed {v:.6g} m/s, angular speed {w:.6g} rad/s is beyond the accepted "
            f"{cfg.tool_speed_accepted:g} m/s, {cfg.tool_angular_speed_accepted:g} rad/s "
            f"(ControllerConfig.tool_speed_accepted, tool_angular_speed_accepted); tool_twist is in m/s then rad/s"
        )

    def _checked_dq(self, dq: object) -> np.ndarray:
        """The measured ``dq`` (rad/s) as a vector; :class:`InputError` naming the first joint faster than
        ``dq_tolerance_factor`` times its velocity limit."""
        v = as_vector(dq, self.robot.nq, "dq")
        over = np.abs(v) > self._dq_accepted
        if over.any():
            i = int(np.argmax(over))
            raise InputError(
                f"dq[{i}] = {v[i]:.6g} rad/s is beyond {self.config.dq_tolerance_factor:g} × its "
                f"velocity limit {self.robot.dq_max[i]:.6g} rad/s; dq is in rad/s"
            )
        return v

    def _stop(self, qv: np.ndarray, gravity: np.ndarray, bits: int, t0: float, why: str) -> Command:
        """The stop command of a tick that could not be computed (``why``): dq 0, q_des = q, τ = ``gravity``
        (g(q), saturated; zero where not finite), ``QP_FAILED`` with ``bits``."""
        self.records.memory[0]["dq_prev"] = self._dq_prev  # (the last command sent: the stop starts from it)
        bits |= stop_tick(qv, gravity, self.tick)
        return self._command(bits, t0, f"{why}: {STOPPING}", 0.0)

    def _gravity_or_zero(self, qv: np.ndarray) -> np.ndarray:
        """g(q) (N·m, Pinocchio) for the stop command after an unexpected exception; zero if that fails too
        (a second exception must not leave ``step``)."""
        try:
            return np.array(self.robot.gravity(qv), dtype=float)
        except Exception:
            return np.zeros(self.robot.nq)

    def _update_interval(self, q: np.ndarray, state: np.ndarray, steps: float | None = None) -> None:
        """Renew the continuity interval [E 9] of an arm without its closed form (the tick renews a closed-form one
        itself): the numerical walk (:class:`qpnso.elbow.intervals.NumericalWalk`) started at ``q`` when none is
        under way, advanced by ``steps`` pieces (None: ``interval_steps_per_tick``), stored with the tool pose it
        started at once it is done — until then the last interval stands (the memory asks again next tick).  When
        it cannot be computed, the last one (or, before any, the full circle) stands, marked stale
        (:func:`qpnso.control.memory.interval_failed`)."""
        m = self.records.memory[0]
        try:
            walk = self._walk = self._walk or self._new_walk(q)
            interval = walk.advance(self.config.interval_steps_per_tick if steps is None else steps)
        except QpnsoError:
            self._walk = None
            interval_failed(m)
            return
        if interval is not None:
            self._walk = None
            R, p = pose_arrays(walk.target)  # (the tool pose the walk started at: Pinocchio's rotation is
            # Fortran-ordered, another argument type for the kernel)
            store_interval(m, interval.lo, interval.hi, interval.full_circle, R, p)

    def _new_walk(self, q: np.ndarray) -> NumericalWalk:
        """The numerical walk from ``q`` (an arm without the closed form), ended at the obstacles too — unless a
        link is within the margin at ``q`` already (the rows move it out; the closed form's tick does the same).
        Its keep-out record has the controller's room, whatever the number of obstacles (one record type)."""
        try:
            return NumericalWalk(
                self.robot, q, obstacles=self.obstacles, margin=self.config.obstacle_margin, room=self._obstacle_room
            )
        except InputError:
            return NumericalWalk(self.robot, q)

    def _first_interval(self, q: np.ndarray, state) -> None:
        """A run's first continuity interval of an arm without the closed form, at ``q`` whole (9 ms median on
        the Panda); when it cannot be computed the tick tries again ``interval_period`` ticks later."""
        m = self.records.memory[0]
        try:
            interval = self._new_walk(q).advance(math.inf)
        except QpnsoError:
            return  # (none known: the first tick's elbow_advance asks again)
        assert interval is not None  # (advanced to the end)
        store_interval(m, interval.lo, interval.hi, interval.full_circle, state.tool_rotation, state.tool_position)

    def __repr__(self) -> str:
        return f"Controller({self.robot.name!r}, strategy={self.config.strategy!r}, dt={self.config.dt})"
