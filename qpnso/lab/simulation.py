"""Hands-on guidance simulation: a virtual surgeon's hand moves the tool of a simulated robot, the
controller compensates gravity and applies a strategy's null-space torque (docs/method.md §9).

The plant is MuJoCo (:class:`qpnso.lab.plant.Plant`), compiled from the robot's URDF with the model's
armature and friction, drawn from it by ``model_error`` (default: none, so the plant is the controller's
model).  The surgeon (:class:`qpnso.lab.surgeon.Subject`) intends a motion
(:class:`qpnso.lab.surgeon.IntendedMotion`) and pulls the tool towards it through the arm's impedance,
with the force of the hand's physiological tremor (:class:`qpnso.lab.surgeon.Tremor`; ``SimulationConfig.tremor``
turns it off); the hand's force is applied at every plant step, the controller's torque
held over each control tick.  The controller runs in hands-on mode: its level-1 reference is the tool's
measured pose and twist, so it never fights the hand.

Recorded per tick: what the controller returned (:class:`qpnso.control.offline.Recorder`), the measured
joint velocities, ``hand_wrench`` (N, N·m; world frame, tool point): the wrench the hand exerts on the tool,
i.e. the arm's impedance wrench and tremor force minus the hand's own inertia times the tool's acceleration over
the tick (what a force sensor between handle and flange would read), ``tool_twist`` (m/s, rad/s).
Felt mass and friction (``mass``, ``friction_force``) are the plant's (:meth:`Plant.felt`), the
controller's estimates beside them (``mass_model``, ``friction_model``), every 10 ticks.

With keep-out volumes in the room, every tick's distance of each link capsule to each of them is
measured independently of the controller, with coal (:func:`qpnso.model.collision.clearances`), at the
configuration the tick starts from; the room may hold obstacles the controller was not given.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace

import numpy as np
import pinocchio as pin

from qpnso.control.config import Status
from qpnso.control.controller import Controller
from qpnso.control.offline import Recorder, RunResult, scene_record
from qpnso.control.trajectory import Trajectory
from qpnso.errors import QpnsoError
from qpnso.lab.metrics import clearance_summary, hand_summary, segment_smoothness
from qpnso.lab.plant import ModelMismatch, Plant, PlantParameters
from qpnso.lab.surgeon import IntendedMotion, Subject, Tremor
from qpnso.model.obstacles import Obstacle, as_obstacles
from qpnso.model.robot import Robot
from qpnso.settings import check, out_of_range
from qpnso.settings import from_dict as settings_from_dict


class SimulationError(QpnsoError):
    """The integration diverged."""


SMOOTHNESS_CUTOFF_HZ = 6.0
"""Hz: the low-pass cut-off of the tool positions before the smoothness [E 14] is taken (the common choice
for human movement records, Winter; fixed before any result was seen)."""


@dataclass
class SimulationConfig:
    """Settings of the hands-on simulation: the plant's step (s; a divisor of the control period), the
    surgeon (a :class:`Subject` or a dict), the plant's :class:`ModelMismatch` (or a dict), the tremor's
    seed (``noise_seed``) and the smoothness filter's cut-off (Hz).  ``tremor`` False turns the surgeon's
    physiological tremor off for the run (the same subject otherwise: S with the noise on and off).
    ``plant_friction`` False takes the joints' friction out of the plant (not out of the controller's model):
    an experiment that isolates the null-space projector."""

    timestep: float = 1e-3
    surgeon: Subject = field(default_factory=Subject)
    model_error: ModelMismatch = field(default_factory=ModelMismatch)
    noise_seed: int = 0
    smoothness_cutoff_hz: float = SMOOTHNESS_CUTOFF_HZ
    plant_friction: bool = True
    tremor: bool = True

    def __post_init__(self) -> None:
        """Types first (:func:`qpnso.settings.check`), then ranges."""
        check(self)
        if not self.timestep > 0:
            raise out_of_range(self, "timestep", "must be > 0 s")
        if not self.smoothness_cutoff_hz > 0:
            raise out_of_range(self, "smoothness_cutoff_hz", "must be > 0 Hz")

    @classmethod
    def from_dict(cls, values: dict, where: str = "") -> "SimulationConfig":
        """Build from plain data (``surgeon``, ``model_error`` as tables)."""
        return settings_from_dict(cls, values, where)


def simulate(
    controller: Controller,
    motion: IntendedMotion | Trajectory,
    q0: np.ndarray,
    config: SimulationConfig | None = None,
    progress=None,
    room: Sequence[Obstacle] | None = None,
) -> RunResult:
    """Simulate hands-on guidance: the surgeon intends ``motion`` (a bare :class:`Trajectory` is one
    segment, tool axis held) from ``q0`` (rad), the robot at rest there.

    Returns the per-tick arrays of :data:`qpnso.control.offline.RESULT_KEYS` plus ``dq_measured``
    (rad/s), ``hand_wrench`` (N, N·m), ``tool_twist`` (m/s, rad/s) (``ref_position`` is the intended position),
    ``mass_model`` (kg) and ``friction_model`` (N), and the run's summary: the metrics of docs/method.md §9,
    the smoothness per segment (``smoothness_segment_k``, ``smoothness`` their median; positions low-passed
    at ``smoothness_cutoff_hz``), the intended motion's own (``intended_smoothness_segment_k``,
    ``intended_smoothness``: :func:`intended_smoothness`), :func:`qpnso.lab.metrics.hand_summary` (``hand_work_J``,
    ``user_work_per_metre_N`` over the measured path, ``user_work_per_nominal_metre_N`` over the intended one,
    ``intended_path_length_m``), felt mass and friction.
    ``RunResult.setup`` names the plant (engine, version, parameters) and the surgeon.

    ``room``: the keep-out volumes of the room (world frame, m; default: the controller's own).  When there are
    any, each tick records ``link_clearance`` (links, obstacles), m, coal's distances at the tick's ``q``, and
    ``controller_clearance`` (m), the controller's own least clearance (``Command.clearance``; inf when it was not
    given the obstacles); the summary gets :func:`qpnso.lab.metrics.clearance_summary`'s keys (from coal's
    distances) with ``room_obstacles`` and ``controller_obstacles`` (how many the controller was given).
    """
    cfg = config or SimulationConfig()
    if isinstance(motion, Trajectory):
        motion = IntendedMotion(motion, ((float(motion.t[0]), float(motion.t[-1])),))
    robot = controller.robot
    room = controller.obstacles if room is None else as_obstacles(room)
    measure, links = clearance_meter(robot, room)
    dt = controller.config.dt
    n_ticks = int(np.floor(motion.duration / dt + 1e-9)) + 1
    q = robot.check_q(q0, "q0").copy()
    plant = make_plant(robot, cfg, dt)
    plant.reset(q)
    controller.reset(q)
    hand = HandOnTool(plant, cfg.surgeon, motion, n_ticks, dt, cfg.noise_seed if cfg.tremor else None)
    recorder = Recorder(controller, feel_every=10, felt=lambda qs: plant.felt(qs, controller.cost.potential_speed))
    t0 = float(motion.trajectory.t[0])
    for k in range(n_ticks):
        q, dq, tool = plant.q, plant.dq, hand.tool
        twist = np.concatenate([tool[2], tool[3]])
        pose = pin.SE3(tool[1], tool[0])
        cmd = controller.step(q, dq, tool_twist=twist, tool_pose=pose)
        measured = {"link_clearance": measure(q), "controller_clearance": np.asarray(cmd.clearance)} if measure else {}
        on_tool = hand.tick(k, cmd.tau)
        extra = {"dq_measured": dq, "hand_wrench": on_tool, "tool_twist": twist, **measured}
        recorder.add(t0 + k * dt, q, cmd, pose, hand.intended_pose(k), **extra)
        if progress is not None:
            progress(k + 1, n_ticks)
    result = recorder.result()
    result.scene = scene_record(controller, room)
    summarise(result, motion, cfg)
    result.setup["plant"] = {**plant.describe(), "friction_on": cfg.plant_friction}
    if measure:
        a = result.arrays
        result.summary.update(
            clearance_summary(a["t"], a["link_clearance"], links, a["status"], Status.OBSTACLE.value),
            room_obstacles=len(room),
            controller_obstacles=len(controller.obstacles),
        )
    return result


def make_plant(robot: Robot, cfg: SimulationConfig, dt: float) -> Plant:
    """The plant of a run: the robot drawn with ``cfg.model_error`` (its joint friction removed when
    ``cfg.plant_friction`` is False), the surgeon's hand at the tool, ``cfg.timestep`` a divisor of ``dt``."""
    substeps = max(1, round(dt / cfg.timestep))
    if abs(substeps * cfg.timestep - dt) > 1e-12:
        raise SimulationError(f"the plant's step {cfg.timestep} s must divide the control period {dt} s")
    params = PlantParameters.draw(robot, cfg.model_error)
    if not cfg.plant_friction:
        params = replace(params, tau_coulomb=0.0 * params.tau_coulomb, damping=0.0 * params.damping)
    return Plant(robot, params, dt / substeps, cfg.surgeon.mass, cfg.surgeon.rotational_inertia)


class HandOnTool:
    """The surgeon's hand on the plant's tool: every plant step, the arm impedance towards the intended
    motion (sampled once for the whole run) moved by the voluntary correction (:meth:`Subject.correct`) and the
    tremor's force (:class:`Tremor`, seeded by ``tremor_seed``;
    None: no tremor) act on the hand body; the controller's torque is held over the tick.  The plant must be at
    its start (:meth:`Plant.reset`)."""

    def __init__(
        self,
        plant: Plant,
        surgeon: Subject,
        motion: IntendedMotion,
        n_ticks: int,
        dt: float,
        tremor_seed: int | None,
    ) -> None:
        self.plant, self.surgeon, self.free_axis = plant, surgeon, motion.free_tool_axis
        self.dt = dt
        self.substeps = max(1, round(dt / plant.model.opt.timestep))
        h = dt / self.substeps
        n = n_ticks * self.substeps
        self.intended = motion.trajectory.samples(float(motion.trajectory.t[0]) + h * np.arange(n))
        self.tremor = None if tremor_seed is None else Tremor(surgeon, h, n, np.random.default_rng(tremor_seed))
        self.inertia = np.array([surgeon.mass] * 3 + [surgeon.rotational_inertia] * 3)
        self.tool = plant.tool_state()
        self.correction = np.zeros(3)  # m: the voluntary correction of the impedance's equilibrium point

    def intended_pose(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(rotation, position) the surgeon intends at the start of tick ``k`` (world frame)."""
        j = k * self.substeps
        return self.intended[1][j], self.intended[0][j]

    def tick(self, k: int, tau: np.ndarray) -> np.ndarray:
        """Advance the plant over tick ``k`` with the torque ``tau`` (N·m) held; returns the wrench the hand
        exerted on the tool at the tick's start (N, N·m; world frame): the impedance wrench and tremor minus the
        hand's inertia times the tool's acceleration over the tick, what a handle's force sensor reads."""
        start = np.concatenate([self.tool[2], self.tool[3]])
        applied = None
        for i in range(self.substeps):
            j = k * self.substeps + i
            p_d, r_d, v_d, w_d = (x[j] for x in self.intended)
            self.correction = self.surgeon.correct(self.correction, p_d - self.tool[0], self.dt / self.substeps)
            wrench = self.surgeon.wrench((p_d + self.correction, r_d, v_d, w_d), self.tool, self.free_axis)
            if self.tremor is not None:
                wrench[:3] += self.tremor(j)
            applied = wrench if applied is None else applied
            self.plant.step(tau, wrench)
            self.tool = self.plant.tool_state()
        if not (np.all(np.isfinite(self.plant.data.qpos)) and np.all(np.isfinite(self.plant.data.qvel))):
            raise SimulationError(f"the simulation diverged at t = {k * self.dt:.3f} s")
        assert applied is not None  # (one step at least)
        return applied - self.inertia * (np.concatenate([self.tool[2], self.tool[3]]) - start) / self.dt


def summarise(result: RunResult, motion: IntendedMotion, cfg: SimulationConfig) -> None:
    """A simulation's summary beyond :class:`~qpnso.control.offline.Recorder`'s: S per segment (the whole
    record's S grows like K² over K segments: removed), the intended motion's own S per segment
    (:func:`intended_smoothness`), :func:`qpnso.lab.metrics.hand_summary` (the work per metre of the measured
    and of the intended path), and the run's set-up (plant, surgeon, model error, tremor on or off) in
    ``result.setup``."""
    a = result.arrays
    result.summary.pop("smoothness", None)
    result.summary.update(segment_smoothness(a["t"], a["tool_position"], motion.segments, cfg.smoothness_cutoff_hz))
    result.summary.update(intended_smoothness(a["t"], motion, cfg.smoothness_cutoff_hz))
    intended = motion.trajectory.samples(a["t"])[0]
    result.summary.update(hand_summary(a["t"], a["hand_wrench"], a["tool_twist"], a["tool_position"], intended))
    result.setup.update(surgeon=asdict(cfg.surgeon), model_error=asdict(cfg.model_error), tremor_on=cfg.tremor)


def intended_smoothness(t: np.ndarray, motion: IntendedMotion, cutoff_hz: float) -> dict[str, float]:
    """The smoothness S [E 14] of the noise-free intended motion itself, per segment, as a run's record is scored
    (:func:`qpnso.lab.metrics.segment_smoothness` of ``motion``'s trajectory sampled at the record's uniform times
    ``t`` (s), low-passed at ``cutoff_hz``): ``intended_smoothness_segment_<k>`` and ``intended_smoothness`` (their
    median).  A threshold on S that these exceed cannot be met by any controller."""
    positions = motion.trajectory.samples(np.asarray(t, dtype=float))[0]
    scores = segment_smoothness(t, positions, motion.segments, cutoff_hz)
    return {f"intended_{k}": v for k, v in scores.items()}


def clearance_meter(
    robot: Robot, room: Sequence[Obstacle]
) -> tuple[Callable[[np.ndarray], np.ndarray] | None, tuple[str, ...]]:
    """``(measure, links)``: ``measure(q)`` the distances (m) of every link capsule to every obstacle of ``room``
    at ``q`` (rad), (links, obstacles), by coal (:func:`qpnso.model.collision.clearances`), and the links' names;
    ``(None, ())`` for an empty room."""
    if not room:
        return None, ()
    from qpnso.model.collision import clearances, geometry_model

    geom = geometry_model(robot)
    return (lambda q: clearances(robot, q, room, geom)), tuple(o.name for o in geom.geometryObjects)
