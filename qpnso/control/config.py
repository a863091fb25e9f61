"""The controller's settings and outputs: :class:`ControllerConfig` (every setting, typed), the
per-tick :class:`Command` with its :class:`Status` flags, and :class:`ElbowState` (docs/method.md §7).

The status bits are defined once, in :mod:`qpnso.control.tick` (its kernels set them); :class:`Status`
names them for users.
"""

from __future__ import annotations

import enum
import math
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from qpnso.control.flags import (
    FLAG_COST_UNDEFINED,
    FLAG_ELBOW_DROPPED,
    FLAG_ELBOW_OUTSIDE_ROM,
    FLAG_ELBOW_SLACK,
    FLAG_INTERNAL_ERROR,
    FLAG_INTERVAL_STALE,
    FLAG_OBSTACLE,
    FLAG_Q_OUT_OF_LIMITS,
    FLAG_QP_DEADLINE,
    FLAG_QP_FAILED,
    FLAG_QP_FALLBACK,
    FLAG_ROM_EMPTY,
    FLAG_TOOL_LIMITED,
    FLAG_TORQUE_SATURATED,
)
from qpnso.elbow.rom import ElbowConfig
from qpnso.model.costs import CostWeights
from qpnso.model.obstacles import Obstacle
from qpnso.qp import QPSettings
from qpnso.settings import SettingError, check, keywords_checked, out_of_range
from qpnso.settings import from_dict as settings_from_dict

_NOT_OK_BITS = FLAG_QP_FAILED | FLAG_ELBOW_DROPPED | FLAG_INTERNAL_ERROR
STRATEGIES = ("qp", "damped", "fixed", "elbow-up", "gradient", "rom", "gradient-impedance")


class Status(enum.Flag):
    """What happened in a tick; several flags may be set at once."""

    OK = 0
    QP_FAILED = FLAG_QP_FAILED  # a QP level failed: safe fallback command
    ELBOW_DROPPED = FLAG_ELBOW_DROPPED  # arm angle singular: elbow constraints dropped
    ELBOW_SLACK = FLAG_ELBOW_SLACK  # elbow bounds not met this tick: moving back
    ROM_EMPTY = FLAG_ROM_EMPTY  # ROM ∩ interval (with margin) empty: the nearest point kept
    Q_OUT_OF_LIMITS = FLAG_Q_OUT_OF_LIMITS  # q outside its limits: velocity bounds push it back
    INTERVAL_STALE = FLAG_INTERVAL_STALE  # the continuity interval could not be updated
    TOOL_LIMITED = FLAG_TOOL_LIMITED  # level 1 residual not zero (bounds or singularity)
    COST_UNDEFINED = FLAG_COST_UNDEFINED  # the cost or its gradient is not finite here: no cost step
    TORQUE_SATURATED = FLAG_TORQUE_SATURATED  # τ clipped to the model's effort limits
    QP_FALLBACK = FLAG_QP_FALLBACK  # ProxQP did not solve within its iteration budget: DAQP answered
    ELBOW_OUTSIDE_ROM = FLAG_ELBOW_OUTSIDE_ROM  # the arm angle is outside ROM_t this tick
    INTERNAL_ERROR = FLAG_INTERNAL_ERROR  # a tick could not be computed: joints brought to rest at ddq_max, τ = g(q)
    QP_DEADLINE = FLAG_QP_DEADLINE  # the cascade's time budget was spent: lower levels skipped (with QP_FAILED)
    OBSTACLE = FLAG_OBSTACLE  # a link is inside its margin of an obstacle (or overlaps it), whatever the cause,
    # or cannot keep its margin (the tool's or the obstacle's motion forces it): Command.clearance and the message
    # say which link and obstacle


@keywords_checked
@dataclass
class ControllerConfig:
    """Every setting of the controller.  Angles in degrees where marked ``_deg``.

    The defaults are the papers' where they give one (ROM, margin, stiffness,
    DP damping, FOP stiffness, gradient gains), ours otherwise.
    """

    dt: float = 1e-3  # s, tick length
    strategy: str = "qp"
    weights: CostWeights = field(default_factory=CostWeights)
    potential_speed: float = 0.05  # m/s, s of [M 13]
    potential_angular_speed: float = 0.5  # rad/s
    rom_half_width_deg: float = 50.0  # Δns [E 5]
    safety_margin_deg: float = 10.0  # d_sg [E 10], [E 11]
    stiffness_min: float = 10.0  # N·m/rad [E 6]
    stiffness_max: float = 30.0  # N·m/rad
    stiffness_slope: float | None = None  # α (1/rad) of [E 6]; None: rom.py's default
    stiffness_inflection_deg: float | None = None  # d of [E 6]; None: rom.py's default
    pose_gain: float = 200.0  # 1/s, K_p of level 1
    pose_correction_speed: float = 0.1  # m/s: the largest speed at which the tool point returns to its reference
    pose_correction_angular_speed: float = 1.0  # rad/s: the same for the tool's orientation
    cost_gain: float = 10.0  # rad²/s per unit cost: level-2 step -gain·∇c
    nullspace_speed_max: float = (
        1.0  # rad/s, saturation of the cost step (as [M 20]) and of the baselines' posture steps
    )
    cost_filter_time: float = 0.1  # s, low-pass of the cost step (0: none): no velocity steps
    posture_filter_time: float = 0.1  # s, the same low-pass of the baselines' kinematic posture steps (0: none)
    elbow_gain: float = 5.0  # 1/s, velocity damper of the elbow bounds
    joint_limit_gain: float = 20.0  # 1/s, velocity damper of the joint limits (≤ 1/dt)
    slack_weight: float = 1e6  # weight of the elbow constraints' slack
    joint_damping: float = 10.0  # N·m·s/rad, null-space damping (DP, FOP, elbow-up, rom, qp), at most
    # nullspace_damping_margin·m/dt in the tick
    nullspace_damping_margin: float = 0.5  # μ (unitless, in (0, 2)): every strategy's null-space damping is at
    # most μ·m/dt, m (kg·m²) the self-motion's inertia this tick (1: deadbeat; 2: unstable), and at least K·dt for
    # a stiffness K (N·m/rad), cut to D/dt where the two meet (control/selfmotion.py; Command.nullspace_damping)
    friction_compensation: float = 1.0  # in [0, 1]: the fraction of the controller's friction model [M 23]
    # compensated along the measured velocity's self-motion part N q̇ (never along the surgeon's motion); 0: off,
    # as for a plant without joint friction (its slope at rest, τ_max·β·2/π = 19 N·m·s/rad on the LWR4+, would
    # then drive the self-motion)
    friction_compensation_speed: float | None = None  # rad/s: the self-motion speed at which the compensation
    # reaches half the model's sliding torque τ_max (the law [M 23] with β = 1/speed); None: the model's own β
    # (1/20 s/rad = 0.05 rad/s on the LWR4+).  The plant's friction is hard Coulomb: a slower transition breaks
    # joints the self-motion turns slowly out of their stiction (control/selfmotion.py)
    posture_stiffness: float = 30.0  # N·m/rad, FOP / elbow-up
    posture_gain: float = 2.0  # 1/s, kinematic rate towards a posture
    fixed_posture: tuple[float, ...] | None = None  # rad; None: the reset posture
    gradient_kp: float = 50.0  # [M 20]
    gradient_kd: float = 10.0  # [M 20], [M 22]
    gradient_omega_max: float = 10.0  # rad/s [M 20]
    gradient_impedance_stiffness: float = 100.0  # N·m/rad: the joint impedance [M] V-A commanded the forward-
    # simulated posture with (strategy gradient-impedance)
    gradient_impedance_damping_ratio: float = 0.1  # and its damping ratio, in the self-motion's inertia
    elbow_up_angle_deg: float = 0.0  # arm angle the elbow-up strategy holds
    interval_period: int = 10  # ticks between interval updates while the tool moves
    interval_steps_per_tick: int = 1  # an arm without the closed form (the Panda): pieces of its numerical
    # continuity interval per tick (NumericalWalk: a Newton iteration or the rest of a self-motion step, about
    # 0.1 ms each; a whole walk took 35 ms median)
    q_limit_tolerance_deg: float = 2.0  # deg (>= 0): how far outside its limits a measured joint
    # may be and still be brought back (Status.Q_OUT_OF_LIMITS); beyond it the tick raises
    recovery_speed: float = 0.2  # rad/s (> 0): the largest speed bringing a joint back inside its limits
    ddq_max: float | tuple[float, ...] | None = None  # rad/s² (> 0), one for all joints or one per joint: a
    # command's change from one tick to the next is at most ddq_max·dt on each joint, whatever the strategy, and
    # the safe fallbacks too (they slow the joints down at this rate); None: the robot's (Robot.ddq_max,
    # models/acceleration.json)
    dq_tolerance_factor: float = 5.0  # (>= 1): a measured dq beyond this multiple of the velocity limit raises
    # (a hand can push a torque-controlled arm past its rated speed; deg/s for rad/s is 57×)
    tool_speed_accepted: float = 5.0  # m/s (> 0): a tool twist whose linear speed is above this is refused
    # (InputError): 2.5× the 2 m/s of a violent pull; mm/s given for m/s is 1000×
    tool_angular_speed_accepted: float = 20.0  # rad/s (> 0): the same for its angular speed (deg/s for rad/s: 57×)
    qp_backend: str = "proxsuite"
    qp_settings: QPSettings = field(default_factory=QPSettings)
    solver_time_budget: float | None = None  # s of the control thread's CPU time for the general cascade: a
    # lower level that would overrun it does not start (Status.QP_DEADLINE, tool held); None: no budget, answers
    # independent of timing (HierarchicalQP.solve's time_budget; README "Real-time use" gives the measurement)
    compile: str | None = None  # CasADi evaluation: background|sync|off (codegen.py)
    obstacles: tuple[Obstacle, ...] = ()  # keep-out volumes, world frame: qpnso.Sphere, Capsule, Box (or their
    # tables, [[obstacles]] in TOML); movable between ticks (Controller.set_obstacles)
    obstacle_margin: float = 0.03  # m, d_s: the clearance every link capsule keeps from every obstacle
    obstacle_influence: float = 0.15  # m, d_i: a link–obstacle pair nearer than this has a row in level 2
    obstacle_speed: float = 0.5  # m/s, ξ: the approach speed the rows' damper allows at d_i (0 at d_s)
    obstacle_recovery_speed: float = 0.05  # m/s: the largest speed of a link back out of the margin
    obstacle_weight_ratio: float = 100.0  # the obstacle rows' slack weight over the elbow rows' (slack_weight)
    obstacle_damping: float = 500.0  # N·s/m: the torque command's wall on a link approaching an obstacle faster
    # than its row allows (every strategy's torque; rows.obstacles.keep_out_torque)
    obstacle_stiffness: float = 1e4  # N/m: and on a link inside the margin: 300 N (the gradient law's 100 N·m at
    # 0.33 m) is held 3 cm in, within the margin

    def __post_init__(self) -> None:
        """Types first (:func:`qpnso.settings.check`: ``weights``/``qp_settings`` may be dicts),
        then ranges; a :class:`qpnso.settings.SettingError` names the key, value and range."""
        check(self)
        if self.strategy not in STRATEGIES:
            raise SettingError(
                type(self).__name__,
                "strategy",
                f"unknown strategy {self.strategy!r}; choose one of {', '.join(STRATEGIES)}",
            )
        if not 0 < self.dt <= 0.1:
            raise out_of_range(self, "dt", "must be in (0, 0.1] s")
        positive = (
            "pose_gain",
            "cost_gain",
            "nullspace_speed_max",
            "elbow_gain",
            "joint_limit_gain",
            "slack_weight",
            "posture_gain",
            "gradient_kd",
            "gradient_omega_max",
            "rom_half_width_deg",
            "recovery_speed",
            "pose_correction_speed",
            "pose_correction_angular_speed",
            "obstacle_speed",
            "obstacle_recovery_speed",
            "obstacle_weight_ratio",
            "tool_speed_accepted",
            "tool_angular_speed_accepted",
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise out_of_range(self, name, "must be > 0")
        if self.joint_limit_gain * self.dt > 1.0:
            raise out_of_range(
                self, "joint_limit_gain", f"must be <= 1/dt = {1 / self.dt:g} 1/s (else a joint could cross its limit)"
            )
        for name in (
            "cost_filter_time",
            "posture_filter_time",
            "gradient_impedance_stiffness",
            "gradient_impedance_damping_ratio",
            "safety_margin_deg",
            "q_limit_tolerance_deg",
            "obstacle_damping",
            "obstacle_stiffness",
        ):
            if getattr(self, name) < 0:
                raise out_of_range(self, name, "must be >= 0")
        if not 0 < self.nullspace_damping_margin < 2:
            raise out_of_range(
                self, "nullspace_damping_margin", "must be in (0, 2): D·dt/m at 2 or above is unstable (1: deadbeat)"
            )
        if not 0 <= self.friction_compensation <= 1:
            raise out_of_range(self, "friction_compensation", "must be in [0, 1] (0: off)")
        if self.friction_compensation_speed is not None and not self.friction_compensation_speed > 0:
            raise out_of_range(self, "friction_compensation_speed", "must be > 0 rad/s, or None (the model's slope)")
        if self.interval_period < 1:
            raise out_of_range(self, "interval_period", "must be >= 1 tick")
        if self.interval_steps_per_tick < 1:
            raise out_of_range(self, "interval_steps_per_tick", "must be >= 1 step")
        if self.ddq_max is not None and not all(a > 0 for a in np.atleast_1d(self.ddq_max)):
            raise out_of_range(self, "ddq_max", "must be > 0 rad/s² on every joint, or None (the robot's)")
        if self.dq_tolerance_factor < 1:
            raise out_of_range(self, "dq_tolerance_factor", "must be >= 1")
        if not 0 <= self.obstacle_margin < self.obstacle_influence:
            raise out_of_range(self, "obstacle_margin", "must be >= 0 m and below obstacle_influence")
        if self.obstacle_speed / (self.obstacle_influence - self.obstacle_margin) * self.dt > 1.0:
            raise out_of_range(self, "obstacle_speed", "must be <= (obstacle_influence - obstacle_margin)/dt")
        if self.solver_time_budget is not None and not self.solver_time_budget > 0:
            raise out_of_range(self, "solver_time_budget", "must be > 0 s or None")

    @classmethod
    def from_dict(cls, values: dict, where: str = "") -> "ControllerConfig":
        """Build from plain data (a TOML table; ``weights``/``qp_settings`` as tables): an unknown
        key is named with the valid ones, a wrong type or range with key and value; errors name
        ``where`` (e.g. the file; default: the class)."""
        return settings_from_dict(cls, values, where)

    def to_dict(self) -> dict:
        """Plain data (nested settings as dicts, obstacles as their tables); ``from_dict(to_dict())`` gives an
        equal config."""
        return asdict(self) | {"obstacles": [ob.to_dict() for ob in self.obstacles]}

    def elbow(self) -> ElbowConfig:
        """The ROM/stiffness settings as :class:`qpnso.elbow.rom.ElbowConfig`."""
        d = None if self.stiffness_inflection_deg is None else np.radians(self.stiffness_inflection_deg)
        return ElbowConfig(
            half_width_deg=self.rom_half_width_deg,
            safety_margin_deg=self.safety_margin_deg,
            stiffness_min=self.stiffness_min,
            stiffness_max=self.stiffness_max,
            alpha=self.stiffness_slope,
            d=d,
        )


@dataclass
class Command:
    """The controller's output for one tick (rad, rad/s, N·m, s; world frame)."""

    dq: np.ndarray  # joint velocity command, rad/s
    q_des: np.ndarray  # joint set-point q + dt·dq, rad
    tau: np.ndarray  # torque command: g(q) + Nᵀ τ_null, N·m
    stiffness: float  # null-space stiffness the strategy applies (K(ns) [E 6] for qp/rom), N·m/rad, after its
    # bound from the self-motion's inertia (0 on a stop)
    arm_angle: float  # ns, rad, unwrapped along the run
    rom: tuple[float, float]  # ROM_t [E 10], [E 11], rad (same unwrapping)
    interval: tuple[float, float]  # continuity interval [E 9], rad
    cost: float  # weighted cost [M 18] at q
    status: Status
    solve_time: float  # s, QP time of this tick
    tick_time: float  # s, the whole step()
    tool_error: tuple[float, float]  # (m, rad) pose error before this tick's correction
    message: str = ""
    clearance: float = math.inf  # m: the least distance of a link capsule to an obstacle (inf: no obstacle)
    nullspace_inertia: float = 0.0  # kg·m²: the self-motion's inertia 1/trace(N A⁻¹) this tick (0: not formed)
    nullspace_damping: float = 0.0  # N·m·s/rad: the null-space damping applied, at most
    # nullspace_damping_margin·nullspace_inertia/dt

    @property
    def ok(self) -> bool:
        return not (self.status & _NOT_OK)


_NOT_OK = Status(_NOT_OK_BITS)


@dataclass
class ElbowState:
    """The elbow's quantities at one tick (rad, unwrapped along the run)."""

    ns: float
    rom: tuple[float, float]
    interval: tuple[float, float]
    stiffness: float
    status: Status
    dropped: bool = False  # arm angle singular: no elbow constraint this tick


def _status(bits: int) -> "Status":
    """The :class:`Status` of a kernel's status bits (``Status.OK``, without a lookup, for none; a NumPy integer
    read from a record, as the kernels give it without the JIT, made a Python int: ``Flag`` refuses a composite
    ``numpy.int64``)."""
    return Status(int(bits)) if bits else Status.OK


_NOT_FINITE_MESSAGE = "the command was not finite: joints brought to rest at ddq_max"


def _stamped(cmd: Command, bits: int, t0: float) -> Command:
    """A finished command (:func:`qpnso.control.tick.finish_command` done) given its status ``bits``, the stop
    message if they say the command was not finite, and its tick time since ``t0``."""
    if bits & FLAG_INTERNAL_ERROR and not cmd.message:
        cmd.message = _NOT_FINITE_MESSAGE
    cmd.status = cmd.status | _status(bits) if bits else cmd.status
    cmd.tick_time = time.perf_counter() - t0
    return cmd
