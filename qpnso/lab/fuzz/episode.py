"""One episode: a kinematic closed loop (``q ← q + dt·cmd.dq``) of one robot, dt and strategy from one random
start, through its phases, with bad-input bursts interleaved; every valid tick is stepped, timed (the whole
``step`` call's thread CPU time), checked (the command, its change from the previous one, the kernels it
compiled), and fed to the drift and recovery bookkeeping.  :class:`SolverClock` measures the solver's own CPU
time, so a tick that was slow only because the machine preempted it is told apart from a slow solve.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from typing import TYPE_CHECKING, Callable, Iterator

import numpy as np

from qpnso.control.config import Command, Status
from qpnso.errors import QpnsoError
from qpnso.lab.fuzz.checker import CommandHistory, HoldMonitor, Recovery, end_recovery, update_recovery
from qpnso.lab.fuzz.config import Where
from qpnso.lab.fuzz.phases import Phase, advance_reference, plan_phases, twist_at
from qpnso.lab.fuzz.probes import _outside, limit_distance, make_probe, send_probe
from qpnso.lab.fuzz.report import record_exception
from qpnso.lab.fuzz.starts import random_start, start_is_singular

if TYPE_CHECKING:  # the runner imports the episode
    from qpnso.lab.fuzz.runner import Fuzzer


class SolverClock:
    """The CPU time (``time.thread_time``, s) a controller spends in its solver's ``solve_problem`` — the call
    every tick's QP goes through, both passes of a tick solved twice — measured by wrapping the controller's
    solver object.  (Until issue 13's fifth session this wrapped ``solve``, which no tick has called since the
    one tick path of issue 15: every tick then fell back to the whole step's CPU time.)"""

    def __init__(self, qp: object) -> None:
        self.seconds = 0.0
        solve_problem = qp.solve_problem  # type: ignore[attr-defined]

        def timed(*args: object, **kwargs: object) -> object:
            start = time.thread_time()
            try:
                return solve_problem(*args, **kwargs)
            finally:
                self.seconds += time.thread_time() - start

        qp.solve_problem = timed  # type: ignore[attr-defined]

    def take(self) -> float:
        """The solver's CPU time since the last call (0 when it did not run)."""
        seconds, self.seconds = self.seconds, 0.0
        return seconds


class Episode:
    """One closed loop of one strategy from one random start (see the package doc, :mod:`qpnso.lab.fuzz`)."""

    def __init__(self, fuzzer: "Fuzzer", index: int, ticks: int) -> None:
        cfg = fuzzer.config
        self.fuzzer, self.config, self.report = fuzzer, cfg, fuzzer.report
        self.rng = np.random.default_rng([cfg.seed, index])
        robot, dt, self.strategy = cfg.setting(index)
        self.ctrl = fuzzer.controller(robot, dt, self.strategy)
        self.clock = fuzzer.clocks[robot, dt, self.strategy]
        self.checker = fuzzer.checker(robot)
        self.dt = self.checker.dt = self.ctrl.config.dt
        self.checker.correction_speed = self.ctrl.config.pose_correction_speed
        self.history = CommandHistory(getattr(self.ctrl, "ddq_max", None), self.dt, keep=cfg.reversal_ticks)
        self.cpu_by_tick: list[float] = []  # s, each valid tick's whole step (read by replays)
        self.kernels_by_tick: dict[int, list[str]] = {}  # kernel signatures added by each tick's step
        kind, self.q = random_start(self.rng, self.checker)
        singular = start_is_singular(self.checker, self.q)
        start = kind + (" (singular)" if singular else "")
        self.where = Where(cfg.seed, index, self.strategy, start, robot=robot, dt=dt)
        self.check_drift = not singular
        self.ticks = ticks
        self.phases = plan_phases(self.rng, cfg, ticks)
        self.dq_none = self.rng.random() < cfg.p_dq_none
        self.dq = np.zeros(self.q.size)
        self.reference = self.home = self.checker.tool_pose(self.q)
        self.hold = HoldMonitor()
        self.pending: Recovery | None = None
        self.rom_out: float | None = None
        self.previous: Status | None = None
        self.recovered = False  # the last valid tick was OK with the tool on its reference (on_reference)
        self.pull_from_ok = False
        self.failures_in_row = 0
        self.tick = 0
        self.report.start_kinds[self.where.start] = self.report.start_kinds.get(self.where.start, 0) + 1

    def run(self, progress: Callable[[], None], deadline: float = math.inf) -> None:
        """All the episode's ticks; fewer when the controller fails 20 ticks in a row (refused, raised or
        non-finite: the rest would repeat it), after ``episode_seconds`` (seconds-long ticks) or at the run's
        ``deadline`` (``time.perf_counter()``)."""
        if not self._reset():
            return
        cut = time.perf_counter() + self.config.episode_seconds
        for phase, k in self._schedule():
            if self.failures_in_row >= 20 or time.perf_counter() > deadline:
                break
            if time.perf_counter() > cut:
                self.report.episodes_cut += 1
                break
            self._valid_tick(phase, k)
            progress()
        end_recovery(self.pending, self.tick, self.report)
        self.checker.kernels_added(
            self.fuzzer.kernels.added(full=True), replace(self.where, phase="episode end"), {}
        )  # (kernels of a module first imported in the episode)

    def _reset(self) -> bool:
        self.history.reset()
        try:
            self.ctrl.reset(self.q)
        except Exception as exc:  # noqa: BLE001 - a start within the limits must be accepted
            if isinstance(exc, QpnsoError):
                self.report.record("valid_refused", 1.0, self.where, {"q0": self.q}, f"reset: {exc}")
            else:
                record_exception(self.report, exc, replace(self.where, phase="reset"), {"q0": self.q})
            return False
        finally:
            self.checker.kernels_added(self.fuzzer.kernels.added(), replace(self.where, phase="reset"), {"q0": self.q})
        return True

    def _schedule(self) -> Iterator[tuple[Phase, int]]:
        """(phase, tick within it) for each valid tick; disturbances begin and end here."""
        for phase in self.phases:
            self._begin(phase)
            for k in range(phase.ticks):
                if self.tick >= self.ticks:
                    return
                yield phase, k
            if phase.kind == "pull":
                assert phase.amp is not None  # a pull has its twist
                self._disturbed(
                    f"pull at {np.linalg.norm(phase.amp[:3]):.3g} m/s ending at tick {self.tick}", self.pull_from_ok
                )

    def _begin(self, phase: Phase) -> None:
        self.where.phase = phase.kind
        if phase.kind == "hold" and self.check_drift:
            self.hold.start()
        else:
            self.hold.stop()
        if phase.kind == "pull":
            end_recovery(self.pending, self.tick, self.report)
            self.pending, self.pull_from_ok = None, self.recovered
        robot = self.checker.robot
        if phase.kind == "overshoot" and 0 <= limit_distance(robot, self.q) < math.radians(
            self.config.overshoot_within_deg
        ):
            self.q = _outside(self.rng, robot, self.q, 0.01, self.config.overshoot_max_deg, nearest=True)
            self.dq = np.zeros(self.q.size)
            self._disturbed(f"overshoot past a limit at tick {self.tick}", self.recovered)

    def _disturbed(self, what: str, measure: bool) -> None:
        """A disturbance ended: recovery is measured from the next valid tick if ``measure`` (the controller was
        OK with the tool on its reference when the disturbance began: else there is nothing to recover to)."""
        end_recovery(self.pending, self.tick, self.report)
        self.where.recent = what
        self.pending = Recovery(what, self.tick, replace(self.where)) if measure else None

    def _probe_burst(self) -> None:
        """1 to ``probe_burst_max`` bad inputs at the plant's ``q``; recovery is measured after them."""
        cfg = self.config
        size = int(self.rng.integers(1, cfg.probe_burst_max + 1))
        kinds = [cfg.probe_kinds[int(i)] for i in self.rng.integers(len(cfg.probe_kinds), size=size)]
        outcomes = [
            send_probe(
                self.ctrl,
                make_probe(kind, self.rng, self.q, self.dq, self.checker.robot, cfg),
                self.checker,
                self.where,
                self.clock,
                self.history,
            )
            for kind in kinds
        ]
        what = f"bad inputs {','.join(kinds)} before tick {self.tick}"
        self.checker.kernels_added(
            self.fuzzer.kernels.added(), replace(self.where, phase=f"probes {','.join(kinds)}"), {"probes": kinds}
        )
        if "accepted" in outcomes:  # the controller acted on a q the plant never had; a refused one must not count
            self.hold.glitch()
        if self.pending is None:
            self._disturbed(what, self.recovered)
        else:  # already recovering from another disturbance: that one's clock runs on
            self.where.recent = what

    def _valid_tick(self, phase: Phase, k: int) -> None:
        """One tick of the closed loop: the drift check (of the previous command's motion), maybe a burst of
        bad inputs, ``step``, the command's checks, the plant, the reference."""
        cfg, chk = self.config, self.checker
        where = self.where
        where.tick = self.tick
        twist = twist_at(phase, k, self.dt, cfg, self.reference, self.home)
        dq_in = None if self.dq_none else self.dq
        inputs = {"q": self.q, "dq": dq_in, "tool_twist": twist}
        error = chk.tool_error(self.q, *self.reference)
        chk.drift(self.hold, error, self.previous, where, inputs)
        if self.rng.random() < cfg.p_probe_burst:
            self._probe_burst()
        self.clock.take()  # bad inputs may have called the solver: not this tick's
        cmd, cpu = self._step(twist, dq_in, inputs)
        solver_cpu = self.clock.take()
        self.report.count_tick(where)
        if cmd is not None and cmd.status & Status.QP_DEADLINE:
            self.report.deadline_ticks += 1
        self._timed(cmd, cpu, solver_cpu, inputs)
        finite = cmd is not None and chk.command(
            cmd, self.q, where, inputs, cpu_time=cpu, solver_cpu_time=solver_cpu, history=self.history
        )
        if cmd is not None and finite:
            chk.motion(self.history, np.asarray(cmd.dq, dtype=float), cmd, where, inputs, q=self.q)
        else:  # no command the plant can apply: the next one has none to be compared with
            self.history.reset()
        self.failures_in_row = 0 if finite else self.failures_in_row + 1
        if cmd is not None and self.strategy in cfg.rom_strategies:
            self.rom_out = chk.rom(cmd, self.rom_out, where, inputs)
        self.recovered = on_reference(cmd, error[0], cfg.recovery_tol_m)
        self.pending = update_recovery(self.pending, self.tick, cmd, error[0], chk, self.q, self.reference, inputs)
        if self.fuzzer.observe is not None:
            self.fuzzer.observe(where, inputs, cmd, error)
        self.previous = None if cmd is None else cmd.status
        self.dq = np.array(cmd.dq, dtype=float) if finite else np.zeros(self.q.size)  # type: ignore[union-attr]
        self.q = self.q + self.dt * self.dq
        self.reference = advance_reference(self.reference, twist, self.dt)
        self.tick += 1

    def _step(self, twist: np.ndarray | None, dq_in: np.ndarray | None, inputs: dict) -> tuple[Command | None, float]:
        """The tick's ``step`` call: its command (None when it raised) and its thread CPU time (s)."""
        start = time.thread_time_ns()
        try:
            cmd = self.ctrl.step(self.q, dq=dq_in, tool_twist=twist)
        except QpnsoError as exc:
            cpu = 1e-9 * (time.thread_time_ns() - start)
            self.report.record("valid_refused", 1.0, self.where, inputs, f"{type(exc).__name__}: {exc}")
        except Exception as exc:  # noqa: BLE001
            cpu = 1e-9 * (time.thread_time_ns() - start)
            record_exception(self.report, exc, self.where, inputs)
        else:
            return cmd, 1e-9 * (time.thread_time_ns() - start)
        return None, cpu

    def _timed(self, cmd: Command | None, cpu: float, solver_cpu: float, inputs: dict) -> None:
        """The tick's whole-step CPU time (s) and the kernel signatures its step added, each checked; what the
        tick was (status, solver CPU time, kernels) goes with a slow tick's count."""
        added = self.fuzzer.kernels.added()
        self.checker.kernels_added(added, self.where, inputs)
        self.cpu_by_tick.append(cpu)
        if added:
            self.kernels_by_tick[self.tick] = added

        def what() -> str:
            status = "raised" if cmd is None else f"status {cmd.status}, solve_time {cmd.solve_time:.4g} s"
            return f"{status}, solver CPU time {solver_cpu:.4g} s" + (f"; added {', '.join(added)}" if added else "")

        self.checker.tick_cpu(cpu, self.where, inputs, what)


def on_reference(cmd: Command | None, error_m: float, tol_m: float) -> bool:
    """Whether a tick left the controller in a state to recover to: ``cmd.ok``, the tool within ``tol_m`` (m) of
    its reference, and not ``TOOL_LIMITED``.  A limited tool is already falling behind a reference that it cannot
    follow (a twist beyond the joint velocity limits near a singularity): a disturbance then has nothing to be
    recovered from, and counting one measured the twist, not the recovery (seed 1, episode 844: bad inputs,
    refused, at a tick whose tool was 98 µm off and limited, the error growing by 7 µm a tick before and after)."""
    return cmd is not None and cmd.ok and not cmd.status & Status.TOOL_LIMITED and error_m < tol_m
