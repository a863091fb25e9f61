"""The independent checks of every command: :class:`TickChecker` judges ``dq``, ``q_des``, ``tau``, the
solver time, the arm angle against ROM_t and the tool pose with Pinocchio and the robot's limits only (never
qpnso's own state evaluator); :class:`HoldMonitor` and :class:`Recovery` keep the held-tool drift and the
recovery after a disturbance across ticks.

Independence is the point: a check that reused the controller's own kinematics would share its bugs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
import pinocchio as pin

from qpnso.control.config import Command, ControllerConfig, Status
from qpnso.lab.fuzz.config import FuzzConfig, Where
from qpnso.lab.fuzz.report import FuzzReport
from qpnso.lab.fuzz.starts import arm_angle_undefined
from qpnso.model.robot import Robot

_EXCUSE_DRIFT = Status.TOOL_LIMITED | Status.Q_OUT_OF_LIMITS
"""Flags under which the tool may legitimately move while held (joint bounds or a singular Jacobian)."""
_EXCUSE_ROM = Status.ELBOW_SLACK | Status.ROM_EMPTY


@dataclass
class HoldMonitor:
    """Held-tool drift: while active (a held phase of an episode from a non-singular start), once the tool
    has settled within the tolerance of the held reference, any later pose error above it is drift.  A tick
    whose command was excused (``TOOL_LIMITED``, ``Q_OUT_OF_LIMITS``) unsettles it."""

    active: bool = False
    settled: bool = False
    quiet: int = 0  # ticks left in which a glitch's transient is not drift

    def start(self) -> None:
        self.active, self.settled = True, False

    def glitch(self, ticks: int = 20) -> None:
        """Bad inputs came in (some accepted, a q a little outside its limits): settle again after
        ``ticks`` (the controller acted on a q the plant never had)."""
        self.settled, self.quiet = False, ticks

    def stop(self) -> None:
        self.active = self.settled = False


class TickChecker:
    """The independent checks of one command, with Pinocchio and the robot's limits only."""

    def __init__(self, robot: Robot, config: FuzzConfig, report: FuzzReport) -> None:
        self.robot, self.config, self.report = robot, config, report
        self.model = robot.model
        self.data = robot.model.createData()  # our own: qpnso's robot.data is not touched
        self.tool = robot.tool_frame_id
        self.q_min, self.q_max = robot.q_min.copy(), robot.q_max.copy()
        self.dq_max, self.tau_limit = robot.dq_max.copy(), robot.tau_limit.copy()
        self.dt = 1e-3
        self.correction_speed = ControllerConfig().pose_correction_speed  # m/s; the built controller's, once built

    # ------------------------------------------------------------- command
    def command(
        self,
        cmd: Command,
        q: np.ndarray,
        where: Where,
        inputs: dict,
        timed: bool = True,
        cpu_time: float = math.inf,
        solver_cpu_time: float = math.inf,
        history: "CommandHistory | None" = None,
    ) -> bool:
        """Check one command given at ``q`` (rad): finite, velocity, joint limits, torque, solver time
        (``cpu_time``, s: the CPU time of the whole ``step`` call, shown; ``solver_cpu_time`` the solver's, from
        :class:`SolverClock`: a tick over ``solve_time_max`` in wall time but not in the solver's CPU time
        was preempted; ``history`` the controller's previous commands, for a joint outside its limit that may still
        move out while it brakes at ``ddq_max``).  Returns whether ``dq`` is finite (the plant can apply it)."""
        rep, cfg = self.report, self.config
        dq = np.asarray(cmd.dq, dtype=float)
        q_des = np.asarray(cmd.q_des, dtype=float)
        tau = np.asarray(cmd.tau, dtype=float)
        if timed:
            rep.solve_times.append(cmd.solve_time)
            rep.tick_times.append(cmd.tick_time)
        if cmd.solve_time > cfg.solve_time_max:
            key = "solve_time" if solver_cpu_time > cfg.solve_time_max else "preempted"
            rep.record(
                key,
                cmd.solve_time,
                where,
                inputs,
                f"status {cmd.status}, tick_time {cmd.tick_time:.4g} s, tick CPU time {cpu_time:.4g} s, "
                f"solver CPU time {solver_cpu_time:.4g} s",
            )
        shapes = dq.shape == q_des.shape == tau.shape == q.shape
        bad = 0 if shapes else q.size
        if shapes:
            bad = int(
                np.count_nonzero(~np.isfinite(dq))
                + np.count_nonzero(~np.isfinite(q_des))
                + np.count_nonzero(~np.isfinite(tau))
            )
        if bad:
            rep.record(
                "non_finite",
                bad,
                where,
                inputs,
                f"dq {dq.tolist()}, q_des {q_des.tolist()}, tau {tau.tolist()}, status {cmd.status}",
            )
            return False
        self._magnitude("velocity", "dq", "rad/s", dq, self.dq_max, self.config.joint_tol, cmd, where, inputs)
        braking = braking_joints(dq, history)
        if not self._limits(q, q + self.dt * dq, "q + dt·dq", cmd, where, inputs, braking):
            self._limits(q, q_des, "q_des", cmd, where, inputs, braking)  # one count per command
        self._magnitude("torque", "tau", "N·m", tau, self.tau_limit, self.config.torque_tol, cmd, where, inputs)
        return True

    def _magnitude(
        self,
        key: str,
        name: str,
        unit: str,
        values: np.ndarray,
        limit: np.ndarray,
        tol: float,
        cmd: Command,
        where: Where,
        inputs: dict,
    ) -> None:
        """``abs(values) ≤ limit + tol`` per joint; the worst excess recorded under ``key`` (× the limit)."""
        over = np.abs(values) - limit
        j = int(np.argmax(over))
        if over[j] > tol:
            self.report.record(
                key,
                abs(values[j]) / limit[j],
                where,
                inputs,
                f"joint {j + 1}: {name} {values[j]:.9g} {unit}, limit {limit[j]:.9g} (over by "
                f"{over[j]:.3g}); status {cmd.status}",
            )

    def _limits(
        self, q: np.ndarray, q_next: np.ndarray, what: str, cmd: Command, where: Where, inputs: dict, braking=None
    ) -> bool:
        """A joint crosses a limit (inside at ``q``) or moves further out (outside at ``q``) — unless it is outside
        and ``braking`` (:func:`braking_joints`): slowing down at its acceleration bound, the most a command's
        bounded change allows (a joint measured past its limit while moving out cannot stop in one tick)."""
        low = np.minimum(q, self.q_min) - q_next
        high = q_next - np.maximum(q, self.q_max)
        over = np.maximum(low, high)
        if braking is not None:
            outside = (q < self.q_min) | (q > self.q_max)
            over = np.where(outside & braking, -np.inf, over)
        j = int(np.argmax(over))
        if over[j] <= self.config.joint_tol:
            return False
        side = "below q_min" if low[j] >= high[j] else "above q_max"
        self.report.record(
            "limit_crossing",
            over[j],
            where,
            inputs,
            f"joint {j + 1}: {what} {q_next[j]:.9g} {side} by {over[j]:.3g} rad from q {q[j]:.9g} "
            f"(limits [{self.q_min[j]:.6g}, {self.q_max[j]:.6g}]); status {cmd.status}",
        )
        return True

    # ------------------------------------------------------- CPU, kernels
    def tick_cpu(self, seconds: float, where: Where, inputs: dict, what: Callable[[], str]) -> None:
        """A valid tick's whole ``step`` call took ``seconds`` of thread CPU time: kept in its robot and
        strategy's group, and counted when over ``tick_cpu_max`` (the line holds a fraction of the ticks), with
        ``what()`` the tick was."""
        self.report.add_tick_cpu(where, seconds)
        if seconds > self.config.tick_cpu_max:
            self.report.record("tick_cpu", seconds, where, inputs, what())

    def kernels_added(self, added: list[str], where: Where, inputs: dict) -> None:
        """Kernel signatures (:class:`~qpnso.lab.fuzz.kernels.KernelWatch`) added by the step calls at ``where``:
        one count each (nothing may compile after the constructor)."""
        for signature in added:
            self.report.record("compile", 1.0, where, inputs, f"added {signature}")
            self.report.kernels_added[signature] = self.report.kernels_added.get(signature, 0) + 1

    # -------------------------------------------------- command to command
    def motion(self, history: CommandHistory, dq: np.ndarray, cmd: Command, where: Where, inputs: dict, q=None) -> None:
        """The controller's new command ``dq`` (rad/s) given at ``q`` (rad) against its previous ones since its
        reset (``history``, which then takes ``dq``): a joint's change beyond ``ddq_max·dt`` (when the controller
        has a ``ddq_max``; a joint measured past a limit may also stop its way out at once) and a joint reversed
        from beyond ``reversal_speed`` one way to beyond it the other way within ``reversal_ticks`` ticks (counted
        on the tick it arrives, once per tick)."""
        recent = history.recent
        if recent:
            if history.ddq_max is None:
                self.report.accel_unbounded += 1
            else:
                self._accel_bound(dq - recent[-1], history, cmd, where, inputs, self._stops_out(q, dq, recent[-1]))
            self._reversal(dq, recent, cmd, where, inputs)
        history.push(dq)

    def _stops_out(self, q, dq: np.ndarray, previous: np.ndarray) -> np.ndarray:
        """Per joint: measured past a limit (at ``q``) and its command slowed from ``previous`` towards zero without
        passing it (stopping its way out at once, which the bound allows there); all False without ``q``."""
        if q is None:
            return np.zeros(dq.shape, dtype=bool)
        q = np.asarray(q, dtype=float)
        out = (q > self.q_max) & (previous > 0.0) | (q < self.q_min) & (previous < 0.0)
        return out & (dq * previous >= 0.0) & (np.abs(dq) <= np.abs(previous))

    def _accel_bound(
        self, step: np.ndarray, history: CommandHistory, cmd: Command, where: Where, inputs: dict, excused=None
    ) -> None:
        cfg = self.config
        self.report.accel_checked += 1
        ddq_max = np.asarray(history.ddq_max, dtype=float)
        bound = ddq_max * history.dt
        over = np.abs(step) - (bound * (1.0 + cfg.accel_rtol) + cfg.accel_atol)
        if excused is not None:
            over = np.where(excused, -np.inf, over)
        j = int(np.argmax(over))
        if over[j] > 0.0:
            self.report.record(
                "accel_bound",
                abs(step[j]) / bound[j],
                where,
                inputs,
                f"joint {j + 1}: command changed by {step[j]:.6g} rad/s in one tick, bound ddq_max·dt "
                f"{bound[j]:.6g} (ddq_max {ddq_max[j]:.6g} rad/s², dt {history.dt:g} s); status {cmd.status}",
            )

    def _reversal(self, dq: np.ndarray, recent: list[np.ndarray], cmd: Command, where: Where, inputs: dict) -> None:
        v = self.config.reversal_speed
        before = np.array(recent[-self.config.reversal_ticks :])
        for sign in (1.0, -1.0):  # arrived beyond -v this tick, from beyond +v within the window (and the mirror)
            arrived = (sign * dq < -v) & (sign * before[-1] >= -v)
            came_from = np.any(sign * before > v, axis=0)
            joints = np.flatnonzero(arrived & came_from)
            if joints.size:
                j = int(joints[np.argmax(np.abs(dq[joints]))])
                swing = float(np.max(sign * before[:, j]) - sign * dq[j])
                self.report.record(
                    "reversal",
                    swing,
                    where,
                    inputs,
                    f"joint {j + 1}: command {before[:, j].round(4).tolist()} then {dq[j]:.4g} rad/s (a swing of "
                    f"{swing:.4g} rad/s within {before.shape[0]} ticks); status {cmd.status}",
                )
                return

    # ----------------------------------------------------------------- ROM
    def rom(self, cmd: Command, previous: float | None, where: Where, inputs: dict) -> float:
        """How far the arm angle is outside ROM_t (rad, 0 inside); an excursion that grows from
        ``previous`` without ``ELBOW_SLACK``/``ROM_EMPTY`` is counted."""
        lo, hi = cmd.rom
        out = max(lo - cmd.arm_angle, cmd.arm_angle - hi, 0.0)
        if not math.isfinite(out):
            return 0.0
        if previous is not None and out > 0.0 and out > previous + self.config.rom_tol and not cmd.status & _EXCUSE_ROM:
            self.report.record(
                "rom_excursion",
                out,
                where,
                inputs,
                f"arm angle {cmd.arm_angle:.6g} rad outside ROM_t [{lo:.6g}, {hi:.6g}] by {out:.3g} "
                f"(previous tick {previous:.3g}); status {cmd.status}",
            )
        return out

    # ---------------------------------------------------------------- tool
    def tool_pose(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rotation and position (m) of the tool frame in the world, by Pinocchio forward kinematics."""
        pin.framesForwardKinematics(self.model, self.data, q)
        m = self.data.oMf[self.tool]
        return m.rotation.copy(), m.translation.copy()

    def tool_error(self, q: np.ndarray, rotation: np.ndarray, position: np.ndarray) -> tuple[float, float]:
        """Pose error (m, rad) of the tool at ``q`` from the reference ``(rotation, position)``."""
        r, p = self.tool_pose(q)
        return float(np.linalg.norm(position - p)), float(np.linalg.norm(pin.log3(rotation @ r.T)))

    def drift(
        self, monitor: HoldMonitor, error: tuple[float, float], previous: Status | None, where: Where, inputs: dict
    ) -> None:
        """Held-tool drift at the start of a tick (``error`` from :meth:`tool_error`, ``previous`` the status
        of the command that moved the tool here)."""
        if not monitor.active:
            return
        cfg = self.config
        if (previous is not None and previous & _EXCUSE_DRIFT) or monitor.quiet > 0:
            monitor.settled = False
            monitor.quiet = max(monitor.quiet - 1, 0)
            return
        within = error[0] <= cfg.drift_tol_m and error[1] <= cfg.drift_tol_rad
        if not monitor.settled:
            monitor.settled = within
            return
        self.report.drift_checked += 1
        if not within:
            self.report.record(
                "drift",
                max(error),
                where,
                inputs,
                f"tool {error[0]:.3g} m / {error[1]:.3g} rad from the held pose after settling; "
                f"previous status {previous}",
            )

    def reachable(self, q: np.ndarray, rotation: np.ndarray, position: np.ndarray, iterations: int = 300) -> bool:
        """Whether damped least squares from ``q`` within the joint limits reaches the pose (1e-5 m, 1e-4 rad):
        a recovery over the limit counts only when it does."""
        q = np.clip(np.asarray(q, dtype=float), self.q_min, self.q_max)
        for _ in range(iterations):
            r, p = self.tool_pose(q)
            e = np.concatenate([position - p, pin.log3(rotation @ r.T)])
            if np.linalg.norm(e[:3]) < 1e-5 and np.linalg.norm(e[3:]) < 1e-4:
                return True
            jac = pin.computeFrameJacobian(self.model, self.data, q, self.tool, pin.LOCAL_WORLD_ALIGNED)
            step = jac.T @ np.linalg.solve(jac @ jac.T + 1e-4 * np.eye(6), e)
            q = np.clip(q + step, self.q_min, self.q_max)
        return False


def braking_joints(dq: np.ndarray, history: "CommandHistory | None") -> np.ndarray | None:
    """Per joint, whether the command ``dq`` (rad/s) slows the joint down from the previous command by the whole
    ``ddq_max·dt`` (1e-9 relative) without reversing, or stops it: the most the acceleration bound allows.  None
    without a previous command or an acceleration bound."""
    if history is None or history.ddq_max is None or not history.recent:
        return None
    previous = history.recent[-1]
    slowest = np.maximum(np.abs(previous) - np.asarray(history.ddq_max) * history.dt, 0.0)
    return (np.abs(dq) <= slowest * (1.0 + 1e-9) + 1e-12) & (dq * previous >= 0.0)


@dataclass
class CommandHistory:
    """The joint commands (rad/s) a controller gave since its last reset, newest last (the last
    ``keep`` of them), with its acceleration bound ``ddq_max`` (rad/s², None when it has none) and ``dt`` (s):
    what :meth:`TickChecker.motion` compares a new command with."""

    ddq_max: np.ndarray | None
    dt: float
    keep: int = 2
    recent: list[np.ndarray] = field(default_factory=list)

    def push(self, dq: np.ndarray) -> None:
        self.recent = [*self.recent, np.array(dq, dtype=float)][-self.keep :]

    def reset(self) -> None:
        """The controller was reset (or its last step gave no command): the next command has no previous one."""
        self.recent = []


@dataclass
class Recovery:
    """A disturbance that ended at valid tick ``end`` and awaits ``cmd.ok`` with a small tool error."""

    kind: str
    end: int
    where: Where
    overdue: bool = False  # counted over the limit; still watched for the eventual recovery time
    last_error: float = math.inf  # m, the tool error at the previous valid tick


def closing(pending: Recovery, error_m: float, speed: float, dt: float) -> bool:
    """Whether the tool error (m) shrank by at least half of what the capped pose correction can do in a tick
    (``ControllerConfig.pose_correction_speed``): a large error returns at that speed, by design.  False on the
    first tick after the disturbance (no previous error to compare with: not evidence of closing)."""
    return math.isfinite(pending.last_error) and error_m <= pending.last_error - 0.5 * speed * dt


def update_recovery(
    pending: Recovery | None,
    tick: int,
    cmd: Command | None,
    error_m: float,
    checker: TickChecker,
    q: np.ndarray,
    reference: tuple[np.ndarray, np.ndarray],
    inputs: dict,
) -> Recovery | None:
    """Advance a pending recovery by one valid tick; returns it while still pending."""
    if pending is None:
        return None
    cfg, rep = checker.config, checker.report
    elapsed = tick - pending.end
    speed, dt = checker.correction_speed, checker.dt
    on_track = closing(pending, error_m, speed, dt)
    pending.last_error = error_m
    if cmd is not None and cmd.ok and (error_m < cfg.recovery_tol_m or on_track):
        rep.recovery.append(elapsed)
        if pending.overdue:
            _note_recovery(rep, pending, elapsed, f"recovered after {elapsed} ticks")
        return None
    if elapsed >= cfg.recovery_ticks and not pending.overdue:
        if not checker.reachable(q, *reference):
            rep.recovery_unreachable += 1
            return None
        if cmd is not None and cmd.status & Status.ELBOW_DROPPED and arm_angle_undefined(checker, q):
            rep.recovery_elbow_undefined += 1
            return None
        pending.overdue = True
        rep.record(
            "recovery",
            elapsed,
            replace(pending.where, tick=tick),
            inputs,
            f"{pending.kind}: not recovered after {elapsed} ticks; tool error {error_m:.3g} m, "
            f"status {None if cmd is None else cmd.status}, cmd.tool_error "
            f"{None if cmd is None else cmd.tool_error}",
        )
    return pending


def end_recovery(pending: Recovery | None, tick: int, report: FuzzReport) -> None:
    """The episode ended or another disturbance began: an overdue recovery keeps its count, another is censored."""
    if pending is None:
        return
    if pending.overdue:
        _note_recovery(report, pending, tick - pending.end, f"not recovered after {tick - pending.end} ticks")
    else:
        report.recovery_censored += 1


def _note_recovery(report: FuzzReport, pending: Recovery, elapsed: int, what: str) -> None:
    """Update the worst recovery example with the eventual time of an overdue one."""
    ex = report.worst.get("recovery")
    if (
        ex is not None
        and ex.where.episode == pending.where.episode
        and ex.where.strategy == pending.where.strategy
        and elapsed >= ex.value
    ):
        ex.value = float(elapsed)
        ex.detail = f"{pending.kind}: {what}; " + ex.detail.split("; ", 1)[-1]
