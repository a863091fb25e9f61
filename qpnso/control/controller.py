"""The per-tick controller: what a user puts in a 1 kHz control loop (docs/method.md §7).

``Controller(robot, ControllerConfig(...))``, ``reset(q0)``, then every tick
``step(q, dq, tool_twist) -> Command``.  Each tick:

1. the arm's state from one CasADi call (:mod:`qpnso.control.state`);
2. the elbow: arm angle unwrapped along the run, continuity interval
   (:mod:`qpnso.elbow.intervals`, cached while the tool pose is unchanged), the ROM
   clipped to it with the safety margin, the stiffness sigmoid (:mod:`qpnso.elbow.rom`),
   kept across ticks in one elbow-memory array by the kernels of :mod:`qpnso.control.tick`;
3. the hierarchical QP (:mod:`qpnso.qp`): level 1 ``J q̇ = v_tool + K_p e_pose``,
   level 2 whatever the strategy asks (:mod:`qpnso.control.strategies`), hard joint
   position/velocity bounds on both;
4. the command: ``dq``, ``q_des = q + dt·dq`` and the torque
   ``τ = g(q) + Nᵀ τ_null`` with the dynamically consistent null-space projector.

For the ``qp`` strategy, whenever the QP's line fast path applies (a full-rank
tool Jacobian whose exact solutions meet the joint bounds: nearly every tick),
steps 2–4 run as the *compiled tick* (:mod:`qpnso.control.tick`): one Numba call from
the state (read in place) through the elbow to the level-2 QP, the same
persistent ProxSuite object, one Numba call for the checks, the command and the
torque — the general path's answer to round-off, at a fraction of its Python
overhead.  ``Controller.compiled_tick = False`` (or
``ControllerConfig(compiled_tick=False)``) always takes the general path.

A failed or infeasible QP never reaches the robot: the command falls back to
the level-1 solution (tool held, no null-space motion) or, if level 1 failed
too, to zero velocity, and ``Command.status`` says so.
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, cast

import numpy as np
import pinocchio as pin

from qpnso.compiled_cache import announce_numba_if_cold
from qpnso.control.compiled import compiled_step
from qpnso.control.config import Command, ControllerConfig, ElbowState, Status, _stamped, _status
from qpnso.control.elbow_memory import (
    NS,
    P_MOVED_TOL,
    P_PERIOD,
    arm_angle_singular,
    elbow_advance,
    elbow_bounds,
    elbow_memory,
    elbow_parameters,
    interval_failed,
    interval_stale,
    store_interval,
)
from qpnso.control.flags import FLAG_INTERNAL_ERROR, FLAG_INTERVAL_STALE, FLAG_QP_FAILED, FLAG_ROM_EMPTY
from qpnso.control.state import StateEvaluator, TickState
from qpnso.control.tick import (
    LineTickBuffers,
    answer_bits,
    finish_command,
    level1_target,
    limits_status,
    pose_error,
    velocity_bounds,
)
from qpnso.elbow.arm_angle import ELBOW_OFFSET_MIN_M, WRIST_CONE_DEG
from qpnso.elbow.intervals import continuity_interval
from qpnso.elbow.rom import stiffness
from qpnso.errors import ConfigError, InputError, QpnsoError
from qpnso.linalg import dynamically_consistent_projection
from qpnso.model.costs import CostModel
from qpnso.model.robot import Robot, as_vector, checked_pose, finite_scalar
from qpnso.qp import HierarchicalQP, Level

if TYPE_CHECKING:
    from qpnso.control.strategies import QPStrategy


def _answer_status(tool_residual: float | None, slack: np.ndarray | None) -> Status:
    """Flags of a solved tick: level 1's residual (``TOOL_LIMITED``) and the elbow rows' slack
    (``ELBOW_SLACK``) against what is reported (:func:`qpnso.control.tick.answer_bits`)."""
    return _status(
        answer_bits(
            -1.0 if tool_residual is None else tool_residual, slack.max() if slack is not None and slack.size else -1.0
        )
    )


def _norm(v: np.ndarray) -> float:
    """Euclidean norm of a small vector (cheaper than np.linalg.norm per call)."""
    return math.sqrt(float(v @ v))


_WRIST_SIN_MIN = float(np.sin(np.radians(WRIST_CONE_DEG)))


class Controller:
    """Hierarchical-QP null-space controller of a 7-DOF arm (docs/method.md §7)."""

    def __init__(self, robot: Robot, config: ControllerConfig | None = None) -> None:
        from qpnso.control.strategies import make_strategy

        robot.require_redundant_arm()  # ModelError naming the arm, instead of ROM_EMPTY ticks
        self.robot = robot
        self.config = config or ControllerConfig()
        cfg = self.config
        self.cost = CostModel(robot, cfg.weights, cfg.potential_speed, cfg.potential_angular_speed, compile=cfg.compile)
        self.evaluate = StateEvaluator(self.cost, compile=cfg.compile)
        self.elbow_config = ec = cfg.elbow()
        self._elbow_params = elbow_parameters(
            ec.half_width_rad,
            ec.safety_margin_rad,
            ec.stiffness_min,
            ec.stiffness_max,
            ec.alpha_per_rad,
            ec.d_rad,
            _WRIST_SIN_MIN,
            ELBOW_OFFSET_MIN_M,
            cfg.interval_period,
        )
        self.qp = HierarchicalQP(robot.nq, backend=cfg.qp_backend, settings=cfg.qp_settings)
        tolerance = math.radians(cfg.q_limit_tolerance_deg)
        self._q_accepted = (robot.q_min - tolerance, robot.q_max + tolerance)  # rad: beyond, InputError
        # rows: q as checked (rad, limits widened by 1e-9), q_min, q_max (rad), dq_max (rad/s), q accepted (rad)
        self._limits = np.array(
            [robot.q_min - 1e-9, robot.q_max + 1e-9, robot.q_min, robot.q_max, robot.dq_max, *self._q_accepted]
        )
        self._q_shape = (robot.nq,)
        self.strategy = make_strategy(cfg.strategy, self)
        self._can_compile = cfg.strategy == "qp" and self.qp.settings.line_fast_path
        qp_strategy = cast("QPStrategy", self.strategy)  # (read below only when _can_compile: strategy "qp")
        self.compiled_tick = cfg.compiled_tick and self._can_compile
        self._gains = np.array(
            [
                cfg.pose_gain,
                cfg.joint_limit_gain,
                cfg.cost_gain,
                cfg.nullspace_speed_max,
                qp_strategy.filter_alpha if self._can_compile else 0.0,
                cfg.elbow_gain,
                1.0 / math.sqrt(2.0 * cfg.slack_weight),
                cfg.recovery_speed,
                cfg.pose_correction_speed,
                cfg.pose_correction_angular_speed,
                0.5 * cfg.dt,
            ]
        )
        self._dq_accepted = cfg.dq_tolerance_factor * robot.dq_max  # rad/s: beyond, InputError
        limit = np.array(robot.tau_limit, dtype=float)
        self._tau_limit = np.where(np.isfinite(limit) & (limit > 0), limit, 0.0)  # N·m; 0: none given
        st = self.qp.settings
        self._qp_tol = np.array([st.rank_tol, st.damping_threshold, st.regularization or 0.0])
        self._line = LineTickBuffers(qp_strategy.filtered_step) if self._can_compile else None
        self._no_twist = np.zeros(6)  # never written (writable: a read-only array is another Numba type)
        self._warm_up()

    @property
    def compiled_tick(self) -> bool:
        """Whether ``step`` runs the compiled tick (:mod:`qpnso.control.tick`) when the line fast path applies;
        False: always the general path through :meth:`HierarchicalQP.solve`.  Only the ``qp``
        strategy with ``QPSettings.line_fast_path`` has one."""
        return self._compiled_tick

    @compiled_tick.setter
    def compiled_tick(self, value: bool) -> None:
        if value and not self._can_compile:
            raise ConfigError("the compiled tick needs strategy 'qp' and QPSettings.line_fast_path")
        self._compiled_tick = bool(value)

    def _warm_up(self) -> None:
        """Dry ticks at the robot's sample configuration, then forgotten: the Numba kernels of
        :mod:`qpnso.linalg`, :mod:`qpnso.qp` and :mod:`qpnso.control.tick` compile (seconds, once per machine, then
        cached on disk) or load here, for the compiled tick and the general path alike, never in a
        control tick."""
        announce_numba_if_cold()  # one line on stderr when the kernels compile now (empty cache)
        self.qp.warm_up()  # the general cascade's kernels (the dry ticks below may not reach it)
        stiffness(0.0, 0.0, self.elbow_config)  # the dropped elbow's K(ns), a kernel called from Python (_elbow)
        q = self.robot.sample_configuration()
        compiled = self.compiled_tick
        for path in {compiled, False}:
            self.compiled_tick = path
            self.reset(q)
            self.step(q)
        self.compiled_tick = compiled
        self._reset_done = False

    # ---------------------------------------------------------------- reset
    def reset(self, q0: object, ns0: float | None = None) -> None:
        """Start a run at ``q0`` (rad): holds its tool pose, centres the ROM on its arm angle.

        ``ns0`` (rad) overrides the ROM centre.
        """
        q = self.robot.check_q(q0, "q0")
        if ns0 is not None:
            ns0 = finite_scalar(ns0, "ns0")
        state = self.evaluate(q)
        self.q0 = q
        self.ref_rotation = state.tool_rotation.copy()
        self.ref_position = state.tool_position.copy()
        self.ns0 = float(state.arm_angle if ns0 is None else ns0)
        self._elbow_memory = elbow_memory(state.arm_angle)
        self._dq_prev = np.zeros(self.robot.nq)
        self.qp.reset()  # warm starts and solver objects: a reset controller answers as a new one
        self.strategy.reset(q, state)
        self._reset_done = True
        self.step_count = 0

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
        qv = (
            q
            if type(q) is np.ndarray
            and q.dtype == np.float64
            and q.shape == self._q_shape
            and q.flags.c_contiguous
            and q.flags.writeable
            else as_vector(q, self.robot.nq, "q")
        )
        if (tool_pose is not None or not self.compiled_tick) and limits_status(qv, *self._q_accepted):
            self._refuse_q(qv)  # (the compiled tick's qp_tick checks q first itself: TICK_Q_REFUSED)
        dq_meas = self._dq_prev if dq is None else self._checked_dq(dq)
        twist = self._no_twist if tool_twist is None else as_vector(tool_twist, 6, "tool_twist")
        if tool_pose is not None:
            self.ref_rotation, self.ref_position = checked_pose(tool_pose, "tool_pose")
        fallbacks = self.qp.stats.active_set_fallbacks
        try:
            cmd = self._compiled(qv, twist, dq_meas, t0) if self.compiled_tick else None
            if type(cmd) is not Command:
                cmd = self._general(qv, twist, dq_meas, t0, cmd)
        except QpnsoError:
            raise
        except Exception as exc:  # a bug must not reach the robot as a traceback: stop, say why
            cmd = self._stop(
                qv,
                self._gravity_or_zero(qv),
                FLAG_INTERNAL_ERROR,
                t0,
                f"internal error ({type(exc).__name__}: {exc}): joints stopped",
            )
        if self.qp.stats.active_set_fallbacks != fallbacks:
            cmd.status |= Status.QP_FALLBACK
        if tool_twist is not None:
            self._advance_reference(twist, tool_pose is not None)
        self._dq_prev = cmd.dq
        self.step_count += 1
        return cmd

    def _refuse_q(self, qv: np.ndarray) -> None:
        """Raise :class:`InputError` naming the first joint beyond its limits by more than
        ``q_limit_tolerance_deg``, with its value and limits in degrees and radians (or NaN/inf)."""
        as_vector(qv, self.robot.nq, "q")  # NaN or inf: raises, naming the entries
        lo, hi = self._q_accepted
        i = int(np.argmax((qv < lo) | (qv > hi)))
        r = self.robot
        raise InputError(
            f"q[{i}] ({r.joint_names[i]}) = {math.degrees(qv[i]):.4g}° ({qv[i]:.6g} rad) is outside its limits "
            f"[{math.degrees(r.q_min[i]):.4g}°, {math.degrees(r.q_max[i]):.4g}°] "
            f"([{r.q_min[i]:.6g}, {r.q_max[i]:.6g}] rad) by more than {self.config.q_limit_tolerance_deg:g}°; "
            f"q is in radians"
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

    def _stop(self, qv: np.ndarray, gravity: np.ndarray, bits: int, t0: float, message: str) -> Command:
        """The stop command of a tick that could not be computed: dq 0, q_des = q, τ = ``gravity`` (g(q))."""
        memory = self._elbow_memory
        ns = float(memory[NS])
        cmd = Command(
            np.zeros(self.robot.nq),
            qv.copy(),
            np.array(gravity, dtype=float),
            0.0,
            ns,
            (ns, ns),
            (ns - math.pi, ns + math.pi),
            0.0,
            Status.OK,
            0.0,
            0.0,
            (0.0, 0.0),
            message,
        )
        return self._finish(cmd, qv, cmd.tau, bits | FLAG_QP_FAILED, t0, True)

    def _gravity_or_zero(self, qv: np.ndarray) -> np.ndarray:
        """g(q) (N·m, Pinocchio) for the stop command after an unexpected exception; zero if that fails too
        (a second exception must not leave ``step``)."""
        try:
            return self.robot.gravity(qv)
        except Exception:
            return np.zeros(self.robot.nq)

    def _finish(
        self, cmd: Command, qv: np.ndarray, gravity: np.ndarray, bits: int, t0: float, dropped: bool
    ) -> Command:
        """Every tick's last step (:func:`qpnso.control.tick.finish_command`): τ within the effort limits, an
        arm angle outside ROM_t flagged, a non-finite command replaced by the stop command; the status
        and the tick time set."""
        bits |= finish_command(
            qv,
            cmd.dq,
            cmd.q_des,
            cmd.tau,
            gravity,
            self._tau_limit,
            self.robot.dq_max,
            self.config.dt,
            cmd.arm_angle,
            cmd.rom[0],
            cmd.rom[1],
            dropped,
        )
        return _stamped(cmd, bits, t0)

    def _general(
        self, qv: np.ndarray, twist: np.ndarray, dq_meas: np.ndarray, t0: float, started: tuple | None = None
    ) -> Command:
        """The tick through :meth:`HierarchicalQP.solve` with the strategy's levels (any strategy);
        ``started`` the ``(state, elbow, status)`` a compiled tick got to before the line fast path
        proved not to apply."""
        state, elbow, status = started or self._begin(qv, twist)
        if state.flags & FLAG_INTERNAL_ERROR:
            return self._stop(
                qv,
                state.gravity,
                status.value | FLAG_INTERNAL_ERROR,
                t0,
                "the arm's state is not finite: joints stopped",
            )
        error = self._pose_error(state)
        lb, ub = self._velocity_bounds(state.q)
        level1 = Level(A=state.jacobian, b=level1_target(twist, error, self._gains, state.tool_drift))
        level2 = self.strategy.level2(state, elbow)
        levels = [level1] if level2 is None else [level1, level2]
        result = self.qp.solve(levels, lb, ub, check=False, time_budget=self.config.solver_time_budget)  # arrays
        # built here; the answer is still checked
        dq_cmd, qp_status, message = self._command_velocity(result)
        tau = self._torque(state, dq_cmd, dq_meas, elbow)
        cmd = Command(
            dq=dq_cmd,
            q_des=qv + self.config.dt * dq_cmd,
            tau=tau,
            stiffness=self.strategy.stiffness(elbow),
            arm_angle=elbow.ns,
            rom=elbow.rom,
            interval=elbow.interval,
            cost=state.cost,
            status=status | qp_status if qp_status else status,
            solve_time=result.solve_time,
            tick_time=0.0,
            tool_error=(_norm(error[:3]), _norm(error[3:])),
            message=message,
        )
        return self._finish(cmd, qv, state.gravity, 0, t0, elbow.dropped)

    def _begin(self, qv: np.ndarray, twist: np.ndarray) -> tuple[TickState, ElbowState, Status]:
        """The general tick's start: ``q`` checked, the state (made safe; drift along the previous
        command with its tool part replaced by ``twist``: :func:`qpnso.control.state.predicted_velocity`), the elbow."""
        status = self._check_input(qv)
        state = self.evaluate(qv, self._dq_prev, twist)
        if state.flags:
            status |= _status(state.flags)
        elbow = self._elbow(state)
        return state, elbow, status | elbow.status if elbow.status else status

    def _compiled(self, qv: np.ndarray, twist: np.ndarray, dq_meas: np.ndarray, t0: float) -> Command | tuple | None:
        """The ``qp`` strategy's compiled tick: :func:`qpnso.control.compiled.compiled_step`."""
        return compiled_step(self, qv, twist, dq_meas, t0)

    # ------------------------------------------------------------- helpers
    def _check_input(self, qv: np.ndarray) -> Status:
        """NaN → InputError; outside the limits is recovered (flagged), not refused."""
        code = limits_status(qv, self._limits[0], self._limits[1])
        if code == 2:
            as_vector(qv, self.robot.nq, "q")  # raises, naming the entries
        return Status.Q_OUT_OF_LIMITS if code else Status.OK

    def _pose_error(self, state: TickState) -> np.ndarray:
        """(position error m, rotation error rad) of the reference w.r.t. the tool, world frame
        (:func:`qpnso.control.tick.pose_error`; ``pinocchio.log3`` for an angle near π)."""
        error, ok = pose_error(state.tool_rotation, state.tool_position, self.ref_rotation, self.ref_position)
        if not ok:
            error[3:] = pin.log3(self.ref_rotation @ state.tool_rotation.T)
        return error

    def _advance_reference(self, twist: np.ndarray, external: bool) -> None:
        if external or not np.any(twist):
            return
        dt = self.config.dt
        self.ref_position = self.ref_position + dt * twist[:3]
        self.ref_rotation = pin.exp3(dt * twist[3:]) @ self.ref_rotation

    def _velocity_bounds(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Joint velocity limits and a position damper (:func:`qpnso.control.tick.velocity_bounds`): q never
        crosses its limits; outside a limit the same rows push back at rate ``joint_limit_gain``."""
        r = self.robot
        return velocity_bounds(q, r.q_min, r.q_max, r.dq_max, self.config.joint_limit_gain, self.config.recovery_speed)

    def _elbow(self, state: TickState) -> ElbowState:
        """Arm angle (unwrapped), continuity interval, ROM_t [E 10], [E 11] and K(ns) [E 6]
        (:func:`qpnso.control.elbow_memory.elbow_advance`, :func:`qpnso.control.elbow_memory.elbow_bounds`).

        A singular arm angle (wrist near the vertical through the shoulder, or a
        straight elbow) drops the elbow constraints for the tick.
        """
        memory = self._elbow_memory
        params = self._elbow_params
        if arm_angle_singular(state.wrist_sin, state.elbow_offset, params):
            ns = float(memory[NS])
            k = float(stiffness(ns, self.ns0, self.elbow_config))
            return ElbowState(ns, (ns, ns), (ns - np.pi, ns + np.pi), k, Status.ELBOW_DROPPED, dropped=True)
        ns, recompute = elbow_advance(state.arm_angle, state.pose, memory, params[P_PERIOD], params[P_MOVED_TOL])
        if recompute:
            self._update_interval(state.q, state.pose)
        stale = interval_stale(memory)
        lo, hi, empty, iv_lo, iv_hi, k = elbow_bounds(ns, memory, self.ns0, params)
        bits = (FLAG_INTERVAL_STALE if stale else 0) | (FLAG_ROM_EMPTY if empty else 0)
        return ElbowState(ns, (lo, hi), (iv_lo, iv_hi), k, _status(bits))

    def _update_interval(self, q: np.ndarray, pose: np.ndarray) -> None:
        """Recompute the continuity interval [E 9] at ``q`` into the elbow memory; when it cannot be, the
        previous one (or, before any, the full circle) stands, marked stale
        (:func:`qpnso.control.elbow_memory.interval_stale`)."""
        try:
            interval = continuity_interval(self.robot, q)
        except QpnsoError:
            interval_failed(self._elbow_memory)
            return
        store_interval(self._elbow_memory, interval.lo, interval.hi, interval.full_circle, pose)

    def _command_velocity(self, result) -> tuple[np.ndarray, Status, str]:
        """The QP's answer, or the safe fallback: level-1 solution, else zero."""
        if result.ok:
            return result.x, _answer_status(result.levels[0].residual, result.levels[-1].slack), ""
        dq, status, message = self._fallback(result.status, result.x)
        return dq, status | Status.QP_DEADLINE if result.out_of_time else status, message

    def _fallback(self, why: str, x: np.ndarray | None) -> tuple[np.ndarray, Status, str]:
        """The safe command after a failed QP (``why`` as :attr:`HQPResult.status` words it): the
        level-1 answer ``x`` (tool held, no null-space motion: the least-norm point of level 1's
        optimal set, :meth:`HierarchicalQP.solve`) if finite, else zero (joints stopped)."""
        if x is None or not np.all(np.isfinite(x)):
            return np.zeros(self.robot.nq), Status.QP_FAILED, f"QP failed ({why}): joints stopped"
        return x, Status.QP_FAILED, f"QP failed ({why}): tool held, no null-space motion"

    def _torque(self, state: TickState, dq_cmd: np.ndarray, dq_meas: np.ndarray, elbow: ElbowState) -> np.ndarray:
        """τ = g(q) + Nᵀ τ_null with N = I − J̄J, J̄ = A⁻¹Jᵀ(JA⁻¹Jᵀ)⁻¹ (docs/method.md §2, §7;
        :func:`qpnso.linalg.dynamically_consistent_projection`; a singular A gives no null-space torque, never NaN)."""
        tau_null = self.strategy.nullspace_torque(state, elbow, dq_cmd, dq_meas)
        return state.gravity + dynamically_consistent_projection(state.mass_matrix, state.jacobian, tau_null)[0]

    def __repr__(self) -> str:
        return f"Controller({self.robot.name!r}, strategy={self.config.strategy!r}, dt={self.config.dt})"
