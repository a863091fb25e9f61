"""What a fuzz run is asked to do: :class:`FuzzConfig` (every setting and threshold), the kinds of start
and of bad input it draws from, and :class:`Where` (the coordinates of one tick, enough to replay its episode).

Kept apart from the machinery so the report, the checker, the probes and the runner all read one
definition of the run, and a replay needs nothing but a config and a :class:`Where`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Callable

from qpnso.control.config import STRATEGIES, Command
from qpnso.errors import ConfigError

ROBOTS = ("lwr4p", "iiwa14", "panda")
"""The fuzz's default robots (the Panda needs the optional example-robot-data: skipped, said so, without it)."""
DTS = (1e-3, 4e-3)
"""The fuzz's default tick lengths (s): every robot and strategy runs at each."""

Progress = Callable[[int, int], None]
Observer = Callable[["Where", dict, "Command | None", "tuple[float, float]"], None]

START_KINDS = ("uniform", "near_limit", "elbow_straight", "wrist_over_shoulder")
PROBE_KINDS = (
    "q_nan",
    "q_inf",
    "q_complex",
    "q_shape",
    "q_type",
    "q_degrees",
    "q_out_little",
    "q_out_far",
    "dq_nan",
    "dq_inf",
    "dq_complex",
    "dq_shape",
    "twist_nan",
    "twist_inf",
    "twist_complex",
    "twist_shape",
    "pose_nan",
    "pose_inf",
    "pose_not_rotation",
    "pose_not_se3",
)
"""Bad inputs sent between two valid ticks (one ``step`` call each, the plant does not move)."""


@dataclass
class FuzzConfig:
    """Every setting of a fuzz run (rad, m, s; degrees where marked ``_deg``)."""

    seed: int = 0
    ticks: int = 10_000  # valid closed-loop ticks in all (bad-input calls come on top)
    strategies: tuple[str, ...] = STRATEGIES
    robots: tuple[str, ...] = ROBOTS  # episode E runs setting(E): its robot, dt and strategy
    dts: tuple[float, ...] = DTS  # s, each controller's ControllerConfig.dt
    episode_ticks: int = 600
    first_episode: int = 0  # replay: the same config with first_episode=E, ticks=episode_ticks
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
    workers: int = 0  # 0: every episode in this process; N: shards in fresh (spawned) processes, N at a time,
    # and the slow ticks' episodes replayed in fresh processes too
    shard_ticks: int = 25_000  # with workers: ticks per fresh process (at least `workers` shards)
    setup: str | None = None  # "module:function" called first in every fresh process (a tracer, a test's fault)
    max_replayed_episodes: int = 40  # the slowest ticks' episodes replayed (the rest counted, not replayed)
    solver_time_budget: float | None = None  # s: every controller's ControllerConfig.solver_time_budget
    ddq_max: float | None = None  # rad/s²: every controller's ControllerConfig.ddq_max (None: the robot's)
    # thresholds of the checks
    joint_tol: float = 1e-9  # rad, rad/s
    torque_tol: float = 1e-9  # N·m
    drift_tol_m: float = 1e-6
    drift_tol_rad: float = 1e-6
    solve_time_max: float = 1e-3  # s
    tick_cpu_max: float = 1e-3  # s of thread CPU time for a whole Controller.step call...
    tick_cpu_fraction_max: float = 1e-3  # ...on fewer than this fraction of the valid ticks
    accel_rtol: float = 1e-9  # relative to ddq_max·dt: the acceleration bound's tolerance...
    accel_atol: float = 1e-12  # rad/s ...plus this
    reversal_speed: float = 0.5  # rad/s: a joint's command from above this to below minus this (or back)...
    reversal_ticks: int = 2  # ...within this many ticks is a reversal
    replays: int = 2  # each episode with a tick over solve_time_max is run again this many times (0: none)
    recovery_ticks: int = 100
    recovery_tol_m: float = 1e-4
    rom_strategies: tuple[str, ...] = ("qp", "rom")  # strategies that keep the elbow in ROM_t
    rom_tol: float = 1e-9  # rad

    def __post_init__(self) -> None:
        self.strategies = tuple(self.strategies)
        self.robots = tuple(self.robots)
        self.dts = tuple(float(dt) for dt in self.dts)
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
        if self.replays < 0:
            raise ConfigError("replays must be >= 0")
        if self.ticks < 1 or self.episode_ticks < 1 or self.shard_ticks < 1:
            raise ConfigError("ticks, episode_ticks and shard_ticks must be >= 1")
        if not self.robots or not self.dts or not all(0 < dt <= 0.1 for dt in self.dts):
            raise ConfigError(f"robots {self.robots} and dts {self.dts} (s) must be given, each dt in (0, 0.1]")
        if self.workers < 0 or self.reversal_ticks < 1 or self.max_replayed_episodes < 0:
            raise ConfigError("workers and max_replayed_episodes must be >= 0, reversal_ticks >= 1")
        if self.p_start_near_limit + self.p_start_singular > 1 or self.p_twist + self.p_pull + self.p_overshoot > 1:
            raise ConfigError("start and phase probabilities must each sum to <= 1")

    def to_dict(self) -> dict:
        return asdict(self)

    def setting(self, episode: int) -> tuple[str, float, str]:
        """Episode ``episode``'s robot, dt (s) and strategy: the strategies change every episode, the
        (robot, dt) pair every ``len(strategies)`` episodes, so any ``len(robots)·len(dts)·len(strategies)``
        consecutive episodes run every combination once."""
        strategy = self.strategies[episode % len(self.strategies)]
        pairs = [(robot, dt) for robot in self.robots for dt in self.dts]
        robot, dt = pairs[(episode // len(self.strategies)) % len(pairs)]
        return robot, dt, strategy

    def settings_of(self, first: int, stride: int) -> list[tuple[str, float, str]]:
        """Every setting the episodes ``first, first + stride, ...`` run (in the order they first come)."""
        period = len(self.robots) * len(self.dts) * len(self.strategies)
        return list(dict.fromkeys(self.setting(first + stride * k) for k in range(period)))


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
    robot: str = ""
    dt: float = 0.0  # s

    def short(self) -> str:
        robot = f"{self.robot} dt {1e3 * self.dt:g} ms " if self.robot else ""
        return (
            f"{robot}{self.strategy}, seed {self.seed} episode {self.episode} tick {self.tick}, start {self.start}, "
            f"phase {self.phase}" + (f", after {self.recent}" if self.recent else "")
        )
