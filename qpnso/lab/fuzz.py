"""The closed-loop fuzzer: random control loops over every strategy, checked independently (issue 13).

``run_fuzz(FuzzConfig(ticks=N, seed=S))`` runs episodes of a *kinematic closed
loop* (``q ← q + dt·cmd.dq``: the plant follows the velocity command exactly,
as a position-controlled arm; the offline solve's model), one strategy per
episode in turn, each on its cached :class:`~qpnso.control.controller.Controller`:

* a random start: uniform within the limits, near one or two limits (0–3°
  inside), or near a singular arm angle (straight elbow, wrist over the
  shoulder);
* phases: the tool held (``tool_twist=None``), random smooth twists (up to
  0.3 m/s and 1 rad/s, kept near the start pose), violent pulls (2 m/s and 1 rad/s
  for 20 ticks, then held), the joint nearest a limit pushed past it by up to 2°
  when within 5° of it (then held);
* bad inputs interleaved in bursts (:data:`PROBE_KINDS`: NaN, inf, complex,
  wrong shape or type in ``q``, ``dq``, ``tool_twist``, ``tool_pose``; ``q`` in
  degrees; ``q`` outside its limits by a little and by a lot): each must raise a
  :class:`~qpnso.errors.QpnsoError` (a ``q`` less than ``far_outside_deg``
  outside may instead be accepted, as documented, and its command is checked),
  and the loop goes on from the same ``q``.

Every command is checked by :class:`TickChecker` with Pinocchio and the
robot's limits only (never qpnso's own state evaluator): finite ``dq``,
``q_des``, ``tau``; ``|dq| ≤ dq_max``; ``q + dt·dq`` and ``q_des`` within the
limits (or, from outside, not further out); ``|tau| ≤ tau_limit``; solver time
≤ ``solve_time_max`` (1 ms) unless the solver's own CPU time was below it (:class:`SolverClock`:
then the tick was preempted, counted apart); and, reported but not must-hold lines, the
preempted ticks and the arm angle leaving ROM_t further without ``ELBOW_SLACK`` or ``ROM_EMPTY``.  The fuzzer integrates the tool reference itself (the
controller's rule: ``p += dt·v``, ``R ← exp₃(dt·ω) R``) and measures the tool's
pose error by Pinocchio forward kinematics: held-tool drift (held phases of
episodes from non-singular starts, once the tool has settled within the
tolerance; ticks flagged ``TOOL_LIMITED`` or ``Q_OUT_OF_LIMITS`` excused) and
recovery (ticks after a pull, an overshoot or a bad-input burst that began
from an OK state, until ``cmd.ok`` and the error is below 1e-4 m or closing at half the capped
correction speed; not counted when the reference is out of reach or the arm angle is undefined at
the held pose; the 20 ticks after accepted bad inputs are no drift).  With ``freeze_gc`` the
controllers are built first and the garbage collector is frozen for the run (:func:`realtime_gc`).

:class:`FuzzReport` counts each must-hold line (:data:`CHECKS`), keeps the worst
example of each (seed, episode, tick, strategy, start, phase, the input) and
the tick-time percentiles; ``table()`` is Markdown, ``failures()`` lists the
lines violated.  An episode is reproduced alone by
``run_fuzz(FuzzConfig(seed=S, first_episode=E, ticks=episode_ticks), observe=...)``,
``observe(where, inputs, cmd, error)`` seeing every valid tick.
``qpnso bench fuzz -n N`` is the command line.
"""

from __future__ import annotations

import contextlib
import gc
import math
import time
from array import array
import traceback
import warnings
from dataclasses import asdict, dataclass, field, replace
from typing import Callable, Iterator

import numpy as np
import pinocchio as pin

from qpnso.control.controller import STRATEGIES, Command, Controller, ControllerConfig, Status
from qpnso.elbow.arm_angle import ELBOW_OFFSET_MIN_M, WRIST_CONE_DEG, elbow_points
from qpnso.errors import ConfigError, QpnsoError
from qpnso.model.robot import Robot, load_robot
from qpnso.control.strategies import clip_norm

Progress = Callable[[int, int], None]
Observer = Callable[["Where", dict, "Command | None", "tuple[float, float]"], None]

START_KINDS = ("uniform", "near_limit", "elbow_straight", "wrist_over_shoulder")
PROBE_KINDS = (
    "q_nan", "q_inf", "q_complex", "q_shape", "q_type", "q_degrees", "q_out_little", "q_out_far",
    "dq_nan", "dq_inf", "dq_complex", "dq_shape",
    "twist_nan", "twist_inf", "twist_complex", "twist_shape",
    "pose_nan", "pose_inf", "pose_not_rotation", "pose_not_se3",
)
"""Bad inputs sent between two valid ticks (one ``step`` call each, the plant does not move)."""

_EXCUSE_DRIFT = Status.TOOL_LIMITED | Status.Q_OUT_OF_LIMITS
"""Flags under which the tool may legitimately move while held (joint bounds or a singular Jacobian)."""
_EXCUSE_ROM = Status.ELBOW_SLACK | Status.ROM_EMPTY


@dataclass(frozen=True)
class Check:
    """One check: ``key`` in the counters, ``text`` its line (formatted with the config; the must-hold
    lines are issue 13's), the unit of the worst value."""

    key: str
    text: str
    unit: str
    must_hold: bool = True  # False: counted and shown, not a failure


CHECKS = (
    Check("non_finite", "0 non-finite commands (dq, q_des, tau)", "entries"),
    Check("limit_crossing", "0 joint-limit crossings (q + dt·dq or q_des; from outside: not further out)", "rad"),
    Check("velocity", "0 commands above the velocity limits (abs(dq) ≤ dq_max + {joint_tol:g})", "× dq_max"),
    Check("torque", "0 torques above the effort limits (abs(tau) ≤ tau_limit)", "× tau_limit"),
    Check("foreign_exception", "0 exceptions that are not QpnsoError", ""),
    Check("valid_refused", "0 valid closed-loop ticks refused with a QpnsoError", ""),
    Check("bad_accepted", "every bad input refused with a QpnsoError", ""),
    Check("drift", "held-tool drift < {drift_tol_m:g} m / {drift_tol_rad:g} rad from non-singular starts",
          "m or rad"),
    Check("solve_time", "0 ticks over {solve_time_max:g} s of solver time (cmd.solve_time, unless the solver "
          "used less CPU time than that: then the machine preempted it, counted below)", "s"),
    Check("preempted", "ticks over {solve_time_max:g} s of solver wall time in which the solver used less CPU "
          "time than that (time.thread_time: the machine, not the code; reported, not a must-hold line)", "s",
          must_hold=False),
    Check("rom_excursion", "0 ticks with the arm angle outside ROM_t and moving away without "
          "ELBOW_SLACK/ROM_EMPTY (strategies {rom_strategies}; reported, not a must-hold line)", "rad",
          must_hold=False),
    Check("recovery", "recovery to OK (cmd.ok, the tool within {recovery_tol_m:g} m or closing at ≥ half the "
          "capped correction speed) within {recovery_ticks} ticks after a disturbance that leaves a reachable "
          "reference", "ticks"),
)
CHECK_KEYS = tuple(c.key for c in CHECKS)


@dataclass
class FuzzConfig:
    """Every setting of a fuzz run (rad, m, s; degrees where marked ``_deg``)."""

    seed: int = 0
    ticks: int = 10_000  # valid closed-loop ticks in all (bad-input calls come on top)
    strategies: tuple[str, ...] = STRATEGIES
    episode_ticks: int = 600
    first_episode: int = 0  # replay: FuzzConfig(seed=S, first_episode=E, ticks=episode_ticks)
    robot: str = "lwr4p"
    tool_offset: tuple[float, float, float] = (0.0, 0.0, 0.1)
    tool_frame: str | None = None
    compile: str | None = None  # ControllerConfig.compile (None: QPNSO_COMPILE or background)
    # starts (the rest uniform within the limits)
    p_start_near_limit: float = 0.3
    p_start_singular: float = 0.3
    near_limit_deg: float = 3.0
    near_singular_deg: float = 3.0
    # phases: probabilities of each kind when a phase is drawn (the rest: held)
    p_twist: float = 0.4
    p_pull: float = 0.15
    p_overshoot: float = 0.05
    twist_max_linear: float = 0.3  # m/s
    twist_max_angular: float = 1.0  # rad/s
    twist_spring: float = 2.0  # 1/s, pulls the twist's reference back towards the episode's start pose
    pull_speed: float = 2.0  # m/s
    pull_angular_speed: float = 1.0  # rad/s
    pull_ticks: int = 20
    settle_ticks: int = 150  # the held phase after a pull or an overshoot
    overshoot_max_deg: float = 2.0  # the joint nearest a limit is pushed past it by up to this...
    overshoot_within_deg: float = 5.0  # ...when it is within this of the limit (else no overshoot)
    # bad inputs
    p_probe_burst: float = 0.01  # per valid tick
    probe_burst_max: int = 4
    probe_kinds: tuple[str, ...] = PROBE_KINDS
    far_outside_deg: float = 10.0  # a q further outside its limits is a bad input (must be refused)
    p_dq_none: float = 0.5  # per episode: step(q, dq=None) instead of the plant's velocity
    episode_seconds: float = 120.0  # wall time after which an episode is cut short (seconds-long ticks)
    max_seconds: float | None = None  # wall time after which the run stops (then a failure: ticks short)
    freeze_gc: bool = True  # build every controller first, then gc.collect(); gc.freeze() for the run
    solver_time_budget: float | None = None  # s: every controller's ControllerConfig.solver_time_budget
    # thresholds of the checks
    joint_tol: float = 1e-9  # rad, rad/s
    torque_tol: float = 1e-9  # N·m
    drift_tol_m: float = 1e-6
    drift_tol_rad: float = 1e-6
    solve_time_max: float = 1e-3  # s
    recovery_ticks: int = 100
    recovery_tol_m: float = 1e-4
    rom_strategies: tuple[str, ...] = ("qp", "rom")  # strategies that keep the elbow in ROM_t
    rom_tol: float = 1e-9  # rad

    def __post_init__(self) -> None:
        self.strategies = tuple(self.strategies)
        self.probe_kinds = tuple(self.probe_kinds)
        self.rom_strategies = tuple(self.rom_strategies)
        self.tool_offset = tuple(float(x) for x in self.tool_offset)  # type: ignore[assignment]
        unknown = [s for s in self.strategies if s not in STRATEGIES]
        if unknown or not self.strategies:
            raise ConfigError(f"unknown or no strategies {unknown}; choose from {STRATEGIES}")
        bad = [k for k in self.probe_kinds if k not in PROBE_KINDS]
        if bad or not self.probe_kinds:
            raise ConfigError(f"unknown or no probe kinds {bad}; choose from {PROBE_KINDS}")
        if self.probe_burst_max < 1:
            raise ConfigError("probe_burst_max must be >= 1 (p_probe_burst = 0 sends no bad inputs)")
        if self.ticks < 1 or self.episode_ticks < 1:
            raise ConfigError("ticks and episode_ticks must be >= 1")
        if self.p_start_near_limit + self.p_start_singular > 1 or self.p_twist + self.p_pull + self.p_overshoot > 1:
            raise ConfigError("start and phase probabilities must each sum to <= 1")

    def to_dict(self) -> dict:
        return asdict(self)


# ---------------------------------------------------------------- the report
@dataclass
class Where:
    """Where a tick happened: enough to replay its episode (``first_episode=episode``)."""

    seed: int
    episode: int
    strategy: str
    start: str  # START_KINDS, with " (singular)" when the start measured singular
    tick: int = 0  # valid tick within the episode
    phase: str = ""  # hold | twist | pull | overshoot; "probe <kind>" for a bad input
    recent: str = ""  # the last disturbance before this tick

    def short(self) -> str:
        return (f"{self.strategy}, seed {self.seed} episode {self.episode} tick {self.tick}, start {self.start}, "
                f"phase {self.phase}" + (f", after {self.recent}" if self.recent else ""))


@dataclass
class Example:
    """The worst case of one check: its value, where, the input of the tick (rad, rad/s, m/s) and what was seen."""

    value: float
    where: Where
    input: dict
    detail: str = ""


def _jsonable(x: object) -> object:
    """Plain JSON data of an input (arrays as lists; non-finite and complex numbers as strings)."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (bool, np.bool_)) or x is None or isinstance(x, str):
        return bool(x) if isinstance(x, np.bool_) else x
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else str(float(x))
    return repr(x)


@dataclass
class FuzzReport:
    """Counters of every check (:data:`CHECKS`), the worst example of each, per-strategy counts, the
    recovery distribution, bad-input outcomes and tick-time percentiles of one fuzz run."""

    config: FuzzConfig
    ticks: int = 0
    probes: int = 0
    episodes: int = 0
    counts: dict[str, int] = field(default_factory=lambda: dict.fromkeys(CHECK_KEYS, 0))
    worst: dict[str, Example] = field(default_factory=dict)
    first: dict[str, Example] = field(default_factory=dict)  # the first violation of each check (often the cause)
    by_strategy: dict[str, dict[str, int]] = field(default_factory=dict)
    start_kinds: dict[str, int] = field(default_factory=dict)
    probe_outcomes: dict[str, dict[str, int]] = field(default_factory=dict)
    recovery: list[int] = field(default_factory=list)  # ticks to recover, every measured disturbance
    recovery_censored: int = 0  # the episode ended or another disturbance came first (< the limit)
    recovery_unreachable: int = 0  # over the limit but the reference was not reachable (not counted)
    recovery_elbow_undefined: int = 0  # over the limit, elbow dropped, the arm angle undefined at the held pose
    drift_checked: int = 0  # held ticks checked for drift (settled, not excused)
    deadline_ticks: int = 0  # valid ticks whose cascade ran out of solver_time_budget (Status.QP_DEADLINE)
    episodes_cut: int = 0  # episodes cut short after episode_seconds
    completed: bool | None = None  # after a run: whether it ran every tick asked for
    exceptions: list[dict] = field(default_factory=list)  # the first foreign exceptions with tracebacks
    build_seconds: dict[str, float] = field(default_factory=dict)
    wall_seconds: float = 0.0
    solve_times: array = field(default_factory=lambda: array("d"), repr=False)  # s, every valid tick
    tick_times: array = field(default_factory=lambda: array("d"), repr=False)
    tick_cpu_times: array = field(default_factory=lambda: array("d"), repr=False)  # s, CPU of the whole step

    max_exceptions_kept = 20

    def record(self, key: str, value: float, where: Where, inputs: dict, detail: str = "") -> None:
        """Count one violation of check ``key``; keep it as the worst example if its value is the largest."""
        self.counts[key] += 1
        per = self.by_strategy.setdefault(where.strategy, {})
        per[key] = per.get(key, 0) + 1
        best = self.worst.get(key)
        if best is None or value > best.value:
            self.worst[key] = Example(float(value), replace(where), _jsonable(inputs), detail)  # type: ignore[arg-type]
        if key not in self.first:
            self.first[key] = Example(float(value), replace(where), _jsonable(inputs), detail)  # type: ignore[arg-type]

    def count_tick(self, strategy: str) -> None:
        self.ticks += 1
        per = self.by_strategy.setdefault(strategy, {})
        per["ticks"] = per.get("ticks", 0) + 1

    def count_probe(self, kind: str, outcome: str) -> None:
        self.probes += 1
        per = self.probe_outcomes.setdefault(kind, {})
        per[outcome] = per.get(outcome, 0) + 1

    # ------------------------------------------------------------ summaries
    def percentiles(self) -> dict[str, dict[str, float]]:
        """Solver and whole-tick times (s): p50, p99, p99.9, max and the count over ``solve_time_max``;
        recovery ticks: p50, p99, max."""
        out: dict[str, dict[str, float]] = {}
        for name, values in (("solve_time", self.solve_times), ("tick_time", self.tick_times),
                             ("tick_cpu_time", self.tick_cpu_times)):
            a = np.asarray(values, dtype=float)
            if a.size:
                p50, p99, p999 = np.percentile(a, [50, 99, 99.9])
                out[name] = {"p50": float(p50), "p99": float(p99), "p99.9": float(p999), "max": float(a.max()),
                             "over_max": int(np.count_nonzero(a > self.config.solve_time_max)), "n": int(a.size)}
        if self.recovery:
            r = np.asarray(self.recovery, dtype=float)
            p50, p99 = np.percentile(r, [50, 99])
            out["recovery_ticks"] = {"p50": float(p50), "p99": float(p99), "max": float(r.max()), "n": int(r.size)}
        return out

    def failures(self) -> list[str]:
        """Every must-hold line violated, with its count and worst example; and a run that stopped short."""
        out = []
        if self.completed is False:
            out.append(f"the run stopped after {self.ticks} of {self.config.ticks} ticks "
                       f"({self.wall_seconds:.0f} s; max_seconds {self.config.max_seconds})")
        for check in CHECKS:
            n = self.counts[check.key]
            if n and check.must_hold:
                ex = self.worst.get(check.key)
                worst = f"; worst {ex.value:.4g} {check.unit} ({ex.where.short()}){_detail(ex)}" if ex else ""
                out.append(f"{self._text(check)}: {n} violations{worst}")
        return out

    def _text(self, check: Check) -> str:
        return check.text.format(**asdict(self.config))

    def table(self) -> str:
        """Markdown: one row per check (count, worst example), then timings, recovery and bad inputs."""
        cfg = self.config
        lines = [f"### qpnso fuzz: {self.ticks} ticks, {self.probes} bad inputs, {self.episodes} episodes, "
                 f"seed {cfg.seed}, {cfg.robot}, strategies {','.join(cfg.strategies)}"
                 + (", garbage collector frozen after the controllers were built (realtime_gc)" if cfg.freeze_gc
                    else ""), "",
                 "| check | count | worst |", "|---|---|---|"]
        for check in CHECKS:
            ex = self.worst.get(check.key)
            worst = f"{ex.value:.4g} {check.unit}: {ex.where.short()}{_detail(ex)}" if ex else "—"
            lines.append(f"| {self._text(check)} | {self.counts[check.key]} | {worst.replace('|', '/')} |")
        lines += ["", f"| time | p50 µs | p99 µs | p99.9 µs | max µs | over {1e3 * cfg.solve_time_max:g} ms |",
                  "|---|---|---|---|---|---|"]
        pct = self.percentiles()
        for name in ("solve_time", "tick_time", "tick_cpu_time"):
            if name in pct:
                p = pct[name]
                lines.append(f"| {name} | {1e6 * p['p50']:.0f} | {1e6 * p['p99']:.0f} | {1e6 * p['p99.9']:.0f} | "
                             f"{1e6 * p['max']:.0f} | {p['over_max']} |")
        r = pct.get("recovery_ticks")
        lines += ["", f"recovery: {len(self.recovery)} measured"
                  + (f", p50 {r['p50']:.0f}, p99 {r['p99']:.0f}, max {r['max']:.0f} ticks" if r else "")
                  + f"; {self.recovery_censored} censored; {self.recovery_unreachable} with an unreachable reference"
                  + f"; {self.recovery_elbow_undefined} with the arm angle undefined at the held pose (not counted: "
                    "the wrist centre fixes it, no self-motion changes it)"]
        refused = sum(v.get("refused", 0) for v in self.probe_outcomes.values())
        accepted = sum(v.get("accepted", 0) for v in self.probe_outcomes.values())
        lines.append(f"bad inputs: {self.probes} sent, {refused} refused, {accepted} accepted")
        per = ", ".join(f"{s} {v.get('ticks', 0)}" for s, v in sorted(self.by_strategy.items()))
        lines.append(f"ticks per strategy: {per}; held ticks checked for drift {self.drift_checked}; "
                     f"ticks out of solver_time_budget ({cfg.solver_time_budget}) {self.deadline_ticks}; "
                     f"episodes cut short (over {cfg.episode_seconds:g} s) {self.episodes_cut}; "
                     f"wall {self.wall_seconds:.1f} s")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """Plain JSON data (no per-tick arrays)."""
        return _jsonable({
            "config": self.config.to_dict(), "ticks": self.ticks, "probes": self.probes, "episodes": self.episodes,
            "checks": {c.key: self._text(c) for c in CHECKS}, "counts": self.counts,
            "failures": self.failures(),
            "worst": {k: asdict(v) for k, v in self.worst.items()},
            "first": {k: asdict(v) for k, v in self.first.items()}, "by_strategy": self.by_strategy,
            "start_kinds": self.start_kinds, "probe_outcomes": self.probe_outcomes,
            "percentiles": self.percentiles(), "recovery_censored": self.recovery_censored,
            "recovery_unreachable": self.recovery_unreachable,
            "recovery_elbow_undefined": self.recovery_elbow_undefined, "drift_checked": self.drift_checked,
            "deadline_ticks": self.deadline_ticks,
            "episodes_cut": self.episodes_cut, "completed": self.completed, "exceptions": self.exceptions,
            "build_seconds": self.build_seconds, "wall_seconds": self.wall_seconds,
        })  # type: ignore[return-value]


def _detail(ex: Example) -> str:
    return f" — {ex.detail}" if ex.detail else ""


# ---------------------------------------------------------------- the checks
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
    def command(self, cmd: Command, q: np.ndarray, where: Where, inputs: dict, timed: bool = True,
                cpu_time: float = math.inf, solver_cpu_time: float = math.inf) -> bool:
        """Check one command given at ``q`` (rad): finite, velocity, joint limits, torque, solver time
        (``cpu_time``, s: the CPU time of the whole ``step`` call; ``solver_cpu_time`` the solver's, from
        :class:`SolverClock`: a tick over ``solve_time_max`` in wall time but not in the solver's CPU time
        was preempted).  Returns whether ``dq`` is finite (the plant can apply it)."""
        rep, cfg = self.report, self.config
        dq = np.asarray(cmd.dq, dtype=float)
        q_des = np.asarray(cmd.q_des, dtype=float)
        tau = np.asarray(cmd.tau, dtype=float)
        if timed:
            rep.solve_times.append(cmd.solve_time)
            rep.tick_times.append(cmd.tick_time)
            if math.isfinite(cpu_time):
                rep.tick_cpu_times.append(cpu_time)
        if cmd.solve_time > cfg.solve_time_max:
            key = "solve_time" if solver_cpu_time > cfg.solve_time_max else "preempted"
            rep.record(key, cmd.solve_time, where, inputs,
                       f"status {cmd.status}, tick_time {cmd.tick_time:.4g} s, tick CPU time {cpu_time:.4g} s, "
                       f"solver CPU time {solver_cpu_time:.4g} s")
        shapes = dq.shape == q_des.shape == tau.shape == q.shape
        bad = 0 if shapes else q.size
        if shapes:
            bad = int(np.count_nonzero(~np.isfinite(dq)) + np.count_nonzero(~np.isfinite(q_des))
                      + np.count_nonzero(~np.isfinite(tau)))
        if bad:
            rep.record("non_finite", bad, where, inputs,
                       f"dq {dq.tolist()}, q_des {q_des.tolist()}, tau {tau.tolist()}, status {cmd.status}")
            return False
        self._magnitude("velocity", "dq", "rad/s", dq, self.dq_max, self.config.joint_tol, cmd, where, inputs)
        if not self._limits(q, q + self.dt * dq, "q + dt·dq", cmd, where, inputs):
            self._limits(q, q_des, "q_des", cmd, where, inputs)  # one count per command
        self._magnitude("torque", "tau", "N·m", tau, self.tau_limit, self.config.torque_tol, cmd, where, inputs)
        return True

    def _magnitude(self, key: str, name: str, unit: str, values: np.ndarray, limit: np.ndarray, tol: float,
                   cmd: Command, where: Where, inputs: dict) -> None:
        """``abs(values) ≤ limit + tol`` per joint; the worst excess recorded under ``key`` (× the limit)."""
        over = np.abs(values) - limit
        j = int(np.argmax(over))
        if over[j] > tol:
            self.report.record(key, abs(values[j]) / limit[j], where, inputs,
                               f"joint {j + 1}: {name} {values[j]:.9g} {unit}, limit {limit[j]:.9g} (over by "
                               f"{over[j]:.3g}); status {cmd.status}")

    def _limits(self, q: np.ndarray, q_next: np.ndarray, what: str, cmd: Command, where: Where,
                inputs: dict) -> bool:
        """A joint crosses a limit (inside at ``q``) or moves further out (outside at ``q``)."""
        low = np.minimum(q, self.q_min) - q_next
        high = q_next - np.maximum(q, self.q_max)
        over = np.maximum(low, high)
        j = int(np.argmax(over))
        if over[j] <= self.config.joint_tol:
            return False
        side = "below q_min" if low[j] >= high[j] else "above q_max"
        self.report.record("limit_crossing", over[j], where, inputs,
                           f"joint {j + 1}: {what} {q_next[j]:.9g} {side} by {over[j]:.3g} rad from q {q[j]:.9g} "
                           f"(limits [{self.q_min[j]:.6g}, {self.q_max[j]:.6g}]); status {cmd.status}")
        return True

    # ----------------------------------------------------------------- ROM
    def rom(self, cmd: Command, previous: float | None, where: Where, inputs: dict) -> float:
        """How far the arm angle is outside ROM_t (rad, 0 inside); an excursion that grows from
        ``previous`` without ``ELBOW_SLACK``/``ROM_EMPTY`` is counted."""
        lo, hi = cmd.rom
        out = max(lo - cmd.arm_angle, cmd.arm_angle - hi, 0.0)
        if not math.isfinite(out):
            return 0.0
        if previous is not None and out > 0.0 and out > previous + self.config.rom_tol \
                and not cmd.status & _EXCUSE_ROM:
            self.report.record("rom_excursion", out, where, inputs,
                               f"arm angle {cmd.arm_angle:.6g} rad outside ROM_t [{lo:.6g}, {hi:.6g}] by {out:.3g} "
                               f"(previous tick {previous:.3g}); status {cmd.status}")
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

    def drift(self, monitor: HoldMonitor, error: tuple[float, float], previous: Status | None, where: Where,
              inputs: dict) -> None:
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
            self.report.record("drift", max(error), where, inputs,
                               f"tool {error[0]:.3g} m / {error[1]:.3g} rad from the held pose after settling; "
                               f"previous status {previous}")

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


# ---------------------------------------------------------------- recovery
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


def update_recovery(pending: Recovery | None, tick: int, cmd: Command | None, error_m: float,
                    checker: TickChecker, q: np.ndarray, reference: tuple[np.ndarray, np.ndarray],
                    inputs: dict) -> Recovery | None:
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
        rep.record("recovery", elapsed, replace(pending.where, tick=tick), inputs,
                   f"{pending.kind}: not recovered after {elapsed} ticks; tool error {error_m:.3g} m, "
                   f"status {None if cmd is None else cmd.status}, cmd.tool_error "
                   f"{None if cmd is None else cmd.tool_error}")
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
    if ex is not None and ex.where.episode == pending.where.episode and ex.where.strategy == pending.where.strategy \
            and elapsed >= ex.value:
        ex.value = float(elapsed)
        ex.detail = f"{pending.kind}: {what}; " + ex.detail.split("; ", 1)[-1]


# ---------------------------------------------------------------- starts
def _arm_measures(checker: TickChecker, q: np.ndarray) -> tuple[float, float]:
    """(sine of the shoulder–wrist line's angle from the vertical, elbow distance from that line in m)."""
    pin.forwardKinematics(checker.model, checker.data, q)
    ps, pe, pw = elbow_points(checker.robot).world(checker.data)
    sw = pw - ps
    n = float(np.linalg.norm(sw))
    return float(np.linalg.norm(np.cross([0.0, 0.0, 1.0], sw))) / n, float(np.linalg.norm(np.cross(sw, pe - ps))) / n


def arm_angle_undefined(checker: TickChecker, q: np.ndarray) -> bool:
    """Whether the arm angle is undefined at ``q`` (Pinocchio's kinematics): the shoulder–wrist line within
    :data:`WRIST_CONE_DEG` of the vertical or the elbow within :data:`ELBOW_OFFSET_MIN_M` of that line.  Both
    depend on the wrist centre alone, which the held tool pose fixes: no self-motion leaves this set, so
    ``ELBOW_DROPPED`` there is not a failure to recover (OK is out of reach while the tool is held)."""
    wrist_sin, offset = _arm_measures(checker, q)
    return wrist_sin < math.sin(math.radians(WRIST_CONE_DEG)) or offset < ELBOW_OFFSET_MIN_M


def start_is_singular(checker: TickChecker, q: np.ndarray) -> bool:
    """Within twice the arm angle's singular zones (:data:`WRIST_CONE_DEG`, :data:`ELBOW_OFFSET_MIN_M`),
    or the tool Jacobian's smallest singular value below 0.02."""
    wrist_sin, offset = _arm_measures(checker, q)
    if wrist_sin < math.sin(math.radians(2 * WRIST_CONE_DEG)) or offset < 2 * ELBOW_OFFSET_MIN_M:
        return True
    jac = pin.computeFrameJacobian(checker.model, checker.data, q, checker.tool, pin.LOCAL_WORLD_ALIGNED)
    return float(np.linalg.svd(jac, compute_uv=False)[-1]) < 0.02


def _near_limit(rng: np.random.Generator, robot: Robot, q: np.ndarray, deg: float) -> np.ndarray:
    """One or two joints moved within ``deg`` inside one of their limits."""
    q = q.copy()
    for j in rng.choice(robot.nq, size=int(rng.integers(1, 3)), replace=False):
        inside = math.radians(rng.uniform(0.0, deg))
        q[j] = robot.q_min[j] + inside if rng.random() < 0.5 else robot.q_max[j] - inside
    return q


def _wrist_over_shoulder(rng: np.random.Generator, checker: TickChecker, q: np.ndarray, deg: float) -> np.ndarray:
    """Joint 2 chosen so the wrist is (nearly) on the vertical through the shoulder, joint 3 near 0 (the arm
    planar), then moved by up to ``deg``; or, one time in three, joints 2 and 4 both near 0."""
    q = q.copy()
    q[2] = math.radians(rng.uniform(-deg, deg))
    if rng.random() < 1 / 3:
        q[1], q[3] = (math.radians(rng.uniform(-deg, deg)) for _ in range(2))
        return q
    grid = np.linspace(checker.q_min[1], checker.q_max[1], 241)
    best = grid[0]
    for _ in range(3):  # grid, then two finer grids around the best
        values = []
        for x in grid:
            q[1] = x
            values.append(_arm_measures(checker, q)[0])
        best = grid[int(np.argmin(values))]
        step = grid[1] - grid[0]
        grid = np.linspace(best - step, best + step, 41)
    q[1] = best + math.radians(rng.uniform(-deg, deg))
    return q


def random_start(rng: np.random.Generator, checker: TickChecker) -> tuple[str, np.ndarray]:
    """A start kind (:data:`START_KINDS`) and its configuration, clipped to the limits (rad)."""
    cfg, robot = checker.config, checker.robot
    q = robot.random_q(rng, margin=0.05)
    r = rng.random()
    if r < cfg.p_start_near_limit:
        kind, q = "near_limit", _near_limit(rng, robot, q, cfg.near_limit_deg)
    elif r < cfg.p_start_near_limit + cfg.p_start_singular and robot.nq >= 4:
        if rng.random() < 0.5:
            kind = "elbow_straight"
            q[3] = math.radians(rng.uniform(-cfg.near_singular_deg, cfg.near_singular_deg))
        else:
            kind, q = "wrist_over_shoulder", _wrist_over_shoulder(rng, checker, q, cfg.near_singular_deg)
    else:
        kind = "uniform"
    return kind, np.clip(q, robot.q_min, robot.q_max)


# ---------------------------------------------------------------- phases
@dataclass
class Phase:
    """A stretch of an episode: ``kind`` hold | twist | pull | overshoot (an instant: the joint nearest a limit
    pushed past it, when near one; then held), ``ticks`` long;
    twists are smooth random sinusoids (``amp`` (6,), ``freq`` Hz, ``phi`` rad) or a constant pull (``amp``)."""

    kind: str
    ticks: int
    amp: np.ndarray | None = None
    freq: np.ndarray | None = None
    phi: np.ndarray | None = None


def plan_phases(rng: np.random.Generator, config: FuzzConfig, ticks: int) -> list[Phase]:
    """Random phases covering ``ticks``: a held start, then held, twist, pull (+ settle) and overshoot (+ settle)."""
    phases = [Phase("hold", int(rng.integers(50, 200)))]
    total = phases[0].ticks
    while total < ticks:
        r = rng.random()
        if r < config.p_pull:
            lin = _unit(rng) * config.pull_speed
            ang = _unit(rng) * config.pull_angular_speed
            new = [Phase("pull", config.pull_ticks, amp=np.concatenate([lin, ang])),
                   Phase("hold", config.settle_ticks)]
        elif r < config.p_pull + config.p_overshoot:
            new = [Phase("overshoot", 0), Phase("hold", config.settle_ticks)]
        elif r < config.p_pull + config.p_overshoot + config.p_twist:
            amp = np.concatenate([rng.uniform(-1, 1, 3) * config.twist_max_linear,
                                  rng.uniform(-1, 1, 3) * config.twist_max_angular])
            new = [Phase("twist", int(rng.integers(100, 600)), amp=amp, freq=rng.uniform(0.3, 2.0, 6),
                         phi=rng.uniform(0, 2 * np.pi, 6))]
        else:
            new = [Phase("hold", int(rng.integers(50, 300)))]
        phases += new
        total += sum(p.ticks for p in new)
    return phases


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def twist_at(phase: Phase, k: int, dt: float, config: FuzzConfig, reference: tuple[np.ndarray, np.ndarray],
             home: tuple[np.ndarray, np.ndarray]) -> np.ndarray | None:
    """The tool twist (m/s, rad/s, world) of tick ``k`` of ``phase``: None when held; a pull's constant; a
    twist's sinusoids with a spring back to the episode's start pose, under a sin² envelope, clipped."""
    if phase.kind == "pull":
        return phase.amp.copy()  # type: ignore[union-attr]
    if phase.kind != "twist":
        return None
    t = k * dt
    envelope = math.sin(math.pi * (k + 1) / (phase.ticks + 1)) ** 2
    wave = phase.amp * np.sin(2 * np.pi * phase.freq * t + phase.phi)  # type: ignore[operator]
    spring = -config.twist_spring * np.concatenate([reference[1] - home[1],
                                                    pin.log3(reference[0] @ home[0].T)])
    v = envelope * (wave + spring)
    return np.concatenate([clip_norm(v[:3], config.twist_max_linear), clip_norm(v[3:], config.twist_max_angular)])


def advance_reference(reference: tuple[np.ndarray, np.ndarray], twist: np.ndarray | None,
                      dt: float) -> tuple[np.ndarray, np.ndarray]:
    """The controller's documented rule: ``p += dt·v``, ``R ← exp₃(dt·ω) R`` (held: unchanged)."""
    if twist is None or not np.any(twist):
        return reference
    return pin.exp3(dt * twist[3:]) @ reference[0], reference[1] + dt * twist[:3]


# ---------------------------------------------------------------- bad inputs
@dataclass
class Probe:
    """A bad input: the ``step`` keyword arguments, whether it must be refused, the real ``q`` (rad) its
    command is checked at if it is accepted (None: not checkable), and a description."""

    kind: str
    kwargs: dict
    must_refuse: bool
    q: np.ndarray | None
    description: str


def _bad_vector(kind: str, rng: np.random.Generator, v: np.ndarray) -> tuple[object, str]:
    """``v`` spoilt: ``nan``, ``inf``, ``complex``, ``shape`` or ``type``."""
    v = v.copy()
    i = int(rng.integers(v.size))
    if kind == "nan":
        v[i] = np.nan
        return v, f"NaN at {i}"
    if kind == "inf":
        v[i] = np.inf if rng.random() < 0.5 else -np.inf
        return v, f"inf at {i}"
    if kind == "complex":
        return v + 1j * rng.uniform(0.01, 0.1, v.size), "complex with imaginary parts 0.01–0.1"
    if kind == "shape":
        options = [v[:-1], np.append(v, 0.0), np.tile(v, (2, 1)), v[0], np.empty(0)]
        k = int(rng.integers(len(options)))
        return options[k], f"shape {np.shape(options[k])}"
    options = [None, ["x"] * v.size, ",".join(str(x) for x in v), {"q": v}]
    k = int(rng.integers(len(options)))
    return options[k], f"type {type(options[k]).__name__}"


def _outside(rng: np.random.Generator, robot: Robot, q: np.ndarray, lo_deg: float, hi_deg: float,
             nearest: bool = False) -> np.ndarray:
    """``q`` with one joint outside a limit by ``lo_deg``–``hi_deg`` degrees: a random joint and side, or
    (``nearest``) the joint and side nearest to a limit, as an encoder overshoot."""
    q = q.copy()
    if nearest:
        low, high = q - robot.q_min, robot.q_max - q
        j = int(np.argmin(np.minimum(low, high)))
        below = low[j] <= high[j]
    else:
        j, below = int(rng.integers(robot.nq)), rng.random() < 0.5
    out = math.radians(rng.uniform(lo_deg, hi_deg))
    q[j] = robot.q_min[j] - out if below else robot.q_max[j] + out
    return q


def limit_distance(robot: Robot, q: np.ndarray) -> float:
    """Distance (rad) of the joint nearest to one of its limits (negative outside)."""
    return float(np.min(np.minimum(q - robot.q_min, robot.q_max - q)))


def make_probe(kind: str, rng: np.random.Generator, q: np.ndarray, dq: np.ndarray, robot: Robot,
               config: FuzzConfig) -> Probe:
    """The bad input ``kind`` (:data:`PROBE_KINDS`) at the plant's ``q`` (rad) and velocity ``dq`` (rad/s)."""
    what, _, how = kind.partition("_")
    far = math.radians(config.far_outside_deg)
    if kind == "q_degrees":
        qd = np.degrees(q)
        out = float(np.max(np.maximum(robot.q_min - qd, qd - robot.q_max)))
        return Probe(kind, {"q": qd}, out > far, qd, f"q in degrees (outside by up to {out:.3g} rad)")
    if kind == "q_out_little":
        qo = _outside(rng, robot, q, 0.01, config.overshoot_max_deg, nearest=True)
        return Probe(kind, {"q": qo}, False, qo, f"q: the joint nearest a limit past it by < "
                     f"{config.overshoot_max_deg}°")
    if kind == "q_out_far":
        qo = _outside(rng, robot, q, config.far_outside_deg + 1.0, 180.0) if rng.random() < 0.9 \
            else np.full(robot.nq, 1e6)
        return Probe(kind, {"q": qo}, True, qo, f"q outside its limits by > {config.far_outside_deg}°")
    if what == "pose":
        return _pose_probe(kind, how, rng, q, robot)
    base = {"q": q, "dq": dq, "twist": np.zeros(6)}[what]
    bad, desc = _bad_vector(how, rng, base)
    name = {"q": "q", "dq": "dq", "twist": "tool_twist"}[what]
    kwargs: dict = {"q": q, name: bad}
    return Probe(kind, kwargs, True, None if what == "q" else q, f"{name}: {desc}")


def _pose_probe(kind: str, how: str, rng: np.random.Generator, q: np.ndarray, robot: Robot) -> Probe:
    pose = robot.tool_pose(q)
    if how in ("nan", "inf"):
        p = pose.translation.copy()
        p[int(rng.integers(3))] = np.nan if how == "nan" else np.inf
        bad: object = pin.SE3(pose.rotation, p)
        desc = f"SE3 with translation {p.tolist()}"
    elif how == "not_rotation":
        m = pose.rotation * rng.uniform(1.5, 3.0) if rng.random() < 0.5 else rng.normal(size=(3, 3))
        bad, desc = pin.SE3(m, pose.translation), "SE3 whose rotation is not a rotation"
    else:
        options = [pose.homogeneous, (pose.rotation, pose.translation), pose.translation, "pose"]
        k = int(rng.integers(len(options)))
        bad, desc = options[k], f"tool_pose of type {type(options[k]).__name__}"
    return Probe(kind, {"q": q, "tool_pose": bad}, True, q, desc)


def send_probe(ctrl: Controller, probe: Probe, checker: TickChecker, where: Where,
               clock: SolverClock | None = None) -> str:
    """Call ``ctrl.step`` with a bad input: ``refused`` (a QpnsoError), ``foreign`` (another exception,
    counted with its traceback) or ``accepted`` (counted if it had to be refused; its command checked, with
    its CPU times when ``clock`` is the controller's :class:`SolverClock`)."""
    rep = checker.report
    where = replace(where, phase=f"probe {probe.kind}")
    inputs = {"probe": probe.kind, "description": probe.description, **probe.kwargs}
    if clock is not None:
        clock.take(0.0)
    cpu = time.thread_time()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cmd = ctrl.step(**probe.kwargs)
    except QpnsoError:
        outcome = "refused"
    except Exception as exc:  # noqa: BLE001 - the point: anything that is not a QpnsoError is a failure
        outcome = "foreign"
        record_exception(rep, exc, where, inputs)
    else:
        outcome = "accepted"
        if probe.must_refuse:
            rep.record("bad_accepted", 1.0, where, inputs, f"{probe.description}: accepted, status {cmd.status}")
        cpu = time.thread_time() - cpu
        if probe.q is not None and np.all(np.isfinite(probe.q)):
            checker.command(cmd, np.asarray(probe.q, dtype=float), where, inputs, timed=False, cpu_time=cpu,
                            solver_cpu_time=math.inf if clock is None else clock.take(cpu))
    rep.count_probe(probe.kind, outcome)
    return outcome


def record_exception(report: FuzzReport, exc: BaseException, where: Where, inputs: dict) -> None:
    """Count an exception that is not a QpnsoError; keep its traceback (the first ones)."""
    text = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
    report.record("foreign_exception", 1.0, where, inputs, f"{type(exc).__name__}: {exc}")
    if len(report.exceptions) < report.max_exceptions_kept:
        report.exceptions.append({"where": asdict(where), "type": type(exc).__name__, "message": str(exc),
                                  "input": _jsonable(inputs), "traceback": text})


# ---------------------------------------------------------------- episodes
class SolverClock:
    """The CPU time (``time.thread_time``, s) a controller spends in ``HierarchicalQP.solve`` (the general
    path's solver time is that call's wall time), measured by wrapping the controller's solver object."""

    def __init__(self, qp: object) -> None:
        self.seconds, self.calls = 0.0, 0
        solve = qp.solve  # type: ignore[attr-defined]

        def timed(*args: object, **kwargs: object) -> object:
            start = time.thread_time()
            try:
                return solve(*args, **kwargs)
            finally:
                self.seconds += time.thread_time() - start
                self.calls += 1

        qp.solve = timed  # type: ignore[attr-defined]

    def take(self, tick_cpu: float) -> float:
        """The solver's CPU time since the last call: the wrapped solve's if it ran, else ``tick_cpu`` (the
        compiled tick's solver time spans most of its step: the whole step's CPU time bounds it)."""
        seconds = self.seconds if self.calls else tick_cpu
        self.seconds, self.calls = 0.0, 0
        return seconds


class Episode:
    """One closed loop of one strategy from one random start (see the module doc)."""

    def __init__(self, fuzzer: "Fuzzer", index: int, ticks: int) -> None:
        cfg = fuzzer.config
        self.fuzzer, self.config, self.checker, self.report = fuzzer, cfg, fuzzer.checker, fuzzer.report
        self.rng = np.random.default_rng([cfg.seed, index])
        self.strategy = cfg.strategies[index % len(cfg.strategies)]
        self.ctrl = fuzzer.controller(self.strategy)
        self.clock = fuzzer.clocks[self.strategy]
        self.dt = self.ctrl.config.dt
        kind, self.q = random_start(self.rng, self.checker)
        singular = start_is_singular(self.checker, self.q)
        self.where = Where(cfg.seed, index, self.strategy, kind + (" (singular)" if singular else ""))
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
        self.recovered = False  # the last valid tick was OK with the tool on its reference
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

    def _reset(self) -> bool:
        try:
            self.ctrl.reset(self.q)
        except Exception as exc:  # noqa: BLE001 - a start within the limits must be accepted
            if isinstance(exc, QpnsoError):
                self.report.record("valid_refused", 1.0, self.where, {"q0": self.q}, f"reset: {exc}")
            else:
                record_exception(self.report, exc, replace(self.where, phase="reset"), {"q0": self.q})
            return False
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
                self._disturbed(f"pull at {np.linalg.norm(phase.amp[:3]):.3g} m/s ending at tick {self.tick}",
                                self.pull_from_ok)

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
                self.config.overshoot_within_deg):
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
        outcomes = [send_probe(self.ctrl, make_probe(kind, self.rng, self.q, self.dq, self.checker.robot, cfg),
                               self.checker, self.where, self.clock) for kind in kinds]
        what = f"bad inputs {','.join(kinds)} before tick {self.tick}"
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
        self.clock.take(0.0)  # bad inputs may have called the solver: not this tick's
        cpu = time.thread_time()
        cmd = self._step(twist, dq_in, inputs)
        cpu = time.thread_time() - cpu
        self.report.count_tick(self.strategy)
        if cmd is not None and cmd.status & Status.QP_DEADLINE:
            self.report.deadline_ticks += 1
        finite = cmd is not None and chk.command(cmd, self.q, where, inputs, cpu_time=cpu,
                                                 solver_cpu_time=self.clock.take(cpu))
        self.failures_in_row = 0 if finite else self.failures_in_row + 1
        if cmd is not None and self.strategy in cfg.rom_strategies:
            self.rom_out = chk.rom(cmd, self.rom_out, where, inputs)
        self.recovered = cmd is not None and cmd.ok and error[0] < cfg.recovery_tol_m
        self.pending = update_recovery(self.pending, self.tick, cmd, error[0], chk, self.q, self.reference, inputs)
        if self.fuzzer.observe is not None:
            self.fuzzer.observe(where, inputs, cmd, error)
        self.previous = None if cmd is None else cmd.status
        self.dq = np.array(cmd.dq, dtype=float) if finite else np.zeros(self.q.size)  # type: ignore[union-attr]
        self.q = self.q + self.dt * self.dq
        self.reference = advance_reference(self.reference, twist, self.dt)
        self.tick += 1

    def _step(self, twist: np.ndarray | None, dq_in: np.ndarray | None, inputs: dict) -> Command | None:
        try:
            cmd = self.ctrl.step(self.q, dq=dq_in, tool_twist=twist)
        except QpnsoError as exc:
            self.report.record("valid_refused", 1.0, self.where, inputs, f"{type(exc).__name__}: {exc}")
        except Exception as exc:  # noqa: BLE001
            record_exception(self.report, exc, self.where, inputs)
        else:
            return cmd
        return None


class Fuzzer:
    """The run: the robot, a cached controller per strategy, the checker and the report."""

    def __init__(self, config: FuzzConfig, observe: Observer | None = None) -> None:
        self.config, self.observe = config, observe
        self.robot = load_robot(config.robot, tool_frame=config.tool_frame, tool_offset=list(config.tool_offset))
        self.report = FuzzReport(config)
        self.checker = TickChecker(self.robot, config, self.report)
        self._controllers: dict[str, Controller] = {}
        self.clocks: dict[str, SolverClock] = {}  # each controller's solver CPU time

    def controller(self, strategy: str) -> Controller:
        """The strategy's controller, built once (its constructor compiles or loads the Numba kernels)."""
        ctrl = self._controllers.get(strategy)
        if ctrl is None:
            t0 = time.perf_counter()
            ctrl = Controller(self.robot, ControllerConfig(strategy=strategy, compile=self.config.compile,
                                                           solver_time_budget=self.config.solver_time_budget))
            ctrl.cost.wait_compiled()
            ctrl.evaluate.wait_compiled()
            self.report.build_seconds[strategy] = time.perf_counter() - t0
            self.checker.dt = ctrl.config.dt
            self.checker.correction_speed = ctrl.config.pose_correction_speed
            self._controllers[strategy] = ctrl
            self.clocks[strategy] = SolverClock(ctrl.qp)
        return ctrl

    def run(self, progress: Progress | None = None) -> FuzzReport:
        """Every episode; with ``freeze_gc`` the controllers are built first and the garbage collector's
        generations frozen for the run (:func:`realtime_gc`, as a real-time loop does), then unfrozen."""
        cfg = self.config
        if not cfg.freeze_gc:
            return self._run(progress)
        for strategy in cfg.strategies:
            self.controller(strategy)
        with realtime_gc():
            return self._run(progress)

    def _run(self, progress: Progress | None) -> FuzzReport:
        cfg, rep = self.config, self.report
        t0 = time.perf_counter()
        deadline = math.inf if cfg.max_seconds is None else t0 + cfg.max_seconds
        index = cfg.first_episode

        def tick_done() -> None:
            if progress is not None:
                progress(rep.ticks, cfg.ticks)

        while rep.ticks < cfg.ticks:
            if time.perf_counter() > deadline:
                break
            before = rep.ticks
            Episode(self, index, min(cfg.episode_ticks, cfg.ticks - rep.ticks)).run(tick_done, deadline)
            rep.episodes += 1
            index += 1
            if rep.ticks == before and rep.episodes > 10 * (1 + cfg.ticks // cfg.episode_ticks):
                break  # every start refused: nothing more to learn
        rep.wall_seconds = time.perf_counter() - t0
        rep.completed = rep.ticks >= cfg.ticks
        return rep


@contextlib.contextmanager
def realtime_gc() -> Iterator[None]:
    """``gc.collect(); gc.freeze()`` for the block, ``gc.unfreeze()`` after: what a real-time loop does once
    its controllers are built.  A full collection scans every tracked object, and qpnso's dependencies leave
    about 130 000 (80 ms of CPU for one, measured; a young one took 1.4 ms): inside a tick it is a stall
    that no solver setting can prevent.  Frozen, 30 000 fuzzed ticks saw 6 young collections of at most
    0.07 ms (measured).  The README's real-time section says the same to users."""
    gc.collect()
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def run_fuzz(config: FuzzConfig, progress: Progress | None = None, observe: Observer | None = None) -> FuzzReport:
    """Run ``config.ticks`` fuzzed closed-loop ticks (module doc); ``progress(done, total)`` after each tick;
    ``observe(where, inputs, cmd, error)`` after each valid tick (``cmd`` None when it raised; ``error`` the
    tool's pose error (m, rad) at its start), to trace an episode."""
    return Fuzzer(config, observe).run(progress)
