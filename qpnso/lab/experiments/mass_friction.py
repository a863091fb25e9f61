"""The mass/friction paper's user experiment ([M] §V-B, V-C), with virtual surgeons on the MuJoCo plant.

Protocol (the paper's, with what it does not publish stated as ours):

* the work areas are pre-registered (:mod:`.work_areas`, ``docs/preregistration/mass-friction.toml``): chosen
  from the model alone where the fixed posture differs from elbow up; subject ``s`` works in area
  ``s mod len(areas)``; six targets on a 5 cm dome above the area's centre (:func:`qpnso.lab.surgeon.dome_targets`);
* a trial visits the six targets in one of ``orders`` random orders (seeded, the same orders for every
  subject), minimum-jerk moves at a peak speed of 0.1 m/s × the subject's speed scale, 0.5 s at rest at each
  target, the rotation about the tool axis free; ``reps`` repetitions of each order, ``subjects`` subjects;
* strategies (:data:`STRATEGIES`): ``damped`` (plain gravity compensation: no null-space torque, as the
  paper's), ``elbow-up`` and ``fixed`` (a null-space joint impedance of 100 N·m/rad with damping ratio 0.1
  towards the elbow-up arm angle or the fixed posture), ``active`` ([M]'s law as the paper ran it on the robot:
  the gradient law [M 20]–[M 22] forward simulated and commanded as that impedance, :data:`ACTIVE_STRATEGY`),
  ``qp`` (qpnso: 50 % mass, 50 % friction force) and the ablation ``qp-zero`` (``qp`` with every cost weight
  0: the ROM rows and damping only);
* controls (:data:`CONTROLS`, run on the first ``control_reps`` repetitions, by default all three: the groups'
  own size): ``damped-again`` (damped once more, other
  noise draws: the negative control, a strategy against itself) and ``damped-light`` (damped on the robot with
  every link's mass and inertia times :data:`LIGHT_MASS_FACTOR`, controller and plant alike: a known change in
  felt mass, the positive control);
* the fixed posture is the cost optimum on the self-motion of the area's centre pose inside the continuity
  interval of elbow up (:func:`.work_areas.fixed_posture`), at the run's rotor inertia; fixed, active, qp and
  the ablation start there, damped, the controls and elbow-up start elbow up (ns = 0);
* the paper's four strategies run as the paper ran them, without qpnso's compensation of the self-motion's
  friction (:data:`AS_THE_PAPER_RAN`); qp and the ablation with it (qpnso's default);
* the damping ratio's inertia is the self-motion's: ``D = 2·0.1·√(100·uᵀA u)`` with ``u`` the unit
  null-space direction at the fixed posture;
* the plant has :data:`qpnso.lab.experiments.trials.EXPERIMENT_MODEL_ERROR` (one draw per run).

Per trial: |work| of the hand ([M 24]: ∫|F·v + M·ω| dt) over the measured and over the intended path length
(the two readings of [M 24]), normalised per subject by the largest per-strategy mean of the paper's four, the
total hand work (J), the tool's path (m), and the mean moment orthogonal to the direction of motion (its Fig.
10b), normalised the same way.  Statistics: :mod:`qpnso.lab.experiments.statistics`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
import pinocchio as pin

from qpnso.errors import ConfigError
from qpnso.lab.experiments import work_areas
from qpnso.lab.experiments.trials import (
    ORDER_STREAM,
    PlantOptions,
    run_or_error,
    subject,
    subject_record,
    trial_row,
)
from qpnso.lab.parallel import job_rng

STRATEGIES = ("damped", "elbow-up", "fixed", "active", "qp", "qp-zero")
"""The trial strategies: the paper's four in the order of its Table I, then qpnso's and the ablation."""
PAPER_STRATEGIES = STRATEGIES[:4]
CONTROLS = ("damped-again", "damped-light")
"""The controls: negative (damped against itself) and positive (damped on a lighter robot)."""
ACTIVE_STRATEGY = "gradient-impedance"
"""qpnso's name of [M]'s active law as the paper ran it (the gradient law commanded as a joint impedance)."""
AS_THE_PAPER_RAN = {"friction_compensation": 0.0}
"""The paper's four strategies ran without qpnso's compensation of the self-motion's friction (and damped, with
no null-space damping, would be driven by it wherever the plant's friction is below the model's)."""
LIGHT_MASS_FACTOR = 0.7
"""The positive control's link masses and inertias (controller and plant; not the rotor inertias): felt mass
−30 % where the rotor inertia is 0, the default (issue 32); less with a rotor inertia (the report prints the
measured ratio)."""


@dataclass(frozen=True)
class MassFrictionOptions(PlantOptions):
    """Size and fixed parameters of the experiment (see the module docstring); ``strategies`` and ``controls``
    choose the groups (a sweep may run fewer), ``control_reps`` the repetitions the controls and the ablation
    run (the first ones)."""

    subjects: int = 8
    orders: int = 5
    reps: int = 3
    moves: int = work_areas.MOVES
    robot: str = "lwr4p"
    dome_radius: float = work_areas.DOME_RADIUS  # m
    peak_speed: float = 0.1  # m/s
    dwell: float = 0.5  # s
    posture_stiffness: float = 100.0  # N·m/rad
    damping_ratio: float = 0.1
    strategies: tuple[str, ...] = STRATEGIES
    controls: tuple[str, ...] = CONTROLS
    control_reps: int = 3  # the controls and the ablation run the first control_reps repetitions (pre-registration
    # v2: the groups' own size; v1 ran 1, and its positive control lacked the power to be detected)

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("subjects", "orders", "reps", "control_reps"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 2 <= self.moves <= 12:
            raise ConfigError(f"moves must be in [2, 12], got {self.moves}")
        object.__setattr__(self, "strategies", tuple(self.strategies))
        object.__setattr__(self, "controls", tuple(self.controls))
        for name in self.strategies + self.controls:
            if name not in STRATEGIES + CONTROLS:
                raise ConfigError(f"unknown group {name!r}; choose among {list(STRATEGIES + CONTROLS)}")
        if "damped" not in self.strategies:
            raise ConfigError("the strategies must include 'damped' (the reference of the controls and guards)")

    @cached_property
    def jobs(self) -> list[tuple[int, int, int, str]]:
        """Every ``(subject, order, rep, group)``; the controls and the ablation on the first ``control_reps``."""
        short = set(self.controls) | {"qp-zero"}
        return [
            (s, o, r, g)
            for s in range(self.subjects)
            for o in range(self.orders)
            for r in range(self.reps)
            for g in self.strategies + self.controls
            if g not in short or r < self.control_reps
        ]

    @property
    def n_jobs(self) -> int:
        return len(self.jobs)

    def job(self, index: int) -> tuple[int, int, int, str]:
        """``(subject, order, rep, group)`` of job ``index``."""
        return self.jobs[index]


@dataclass(frozen=True)
class WorkArea:
    """A work area's postures (rad) at the run's rotor inertia: elbow up (ns = 0) and the fixed optimum, its arm
    angle (rad), the null-space damping (N·m·s/rad) of the fixed and elbow-up impedance, and the experiment's
    premise measured on the plant (:func:`work_area_summary`)."""

    pose: pin.SE3
    q_up: np.ndarray
    q_opt: np.ndarray
    ns_opt: float
    damping: float
    premise: dict[str, Any] = field(default_factory=dict)


PREREGISTERED_TOLERANCE_DEG = 0.1
"""deg: how far the fixed posture computed now may be from the pre-registered one."""

_AREAS: dict[str, list[WorkArea]] = {}


def work_areas_of(opts: MassFrictionOptions) -> list[WorkArea]:
    """The pre-registered work areas' postures at the run's rotor inertia, computed once per process and options."""
    key = repr((opts.robot, opts.armature_kgm2, opts.posture_stiffness, opts.damping_ratio))
    if key not in _AREAS:
        robot = opts.load_robot(opts.robot)
        _AREAS[key] = [_work_area(robot, spec, opts) for spec in work_areas.load_preregistration()]
    return _AREAS[key]


def _work_area(robot, spec: work_areas.WorkAreaSpec, opts: MassFrictionOptions) -> WorkArea:
    pose = spec.pose()
    p = work_areas.postures(robot, pose)
    armature = float(robot.model.armature[0])
    recorded = spec.fixed_arm_angle_deg.get(armature)
    if recorded is not None and abs(recorded - math.degrees(p.ns_fixed)) > PREREGISTERED_TOLERANCE_DEG:
        raise ConfigError(
            f"the model gives the fixed posture of the work area at {spec.center} m at "
            f"{math.degrees(p.ns_fixed):.2f}°, "
            f"the pre-registration {recorded:.2f}° (rotor inertia {armature} kg·m²): the model changed since"
        )
    u = np.linalg.svd(robot.jacobian(p.q_fixed))[2][-1]  # the unit null-space direction
    inertia = float(u @ robot.mass_matrix(p.q_fixed) @ u)
    damping = 2.0 * opts.damping_ratio * math.sqrt(opts.posture_stiffness * inertia)
    premise = {
        "center_m": list(spec.center),
        "pitch_deg": spec.pitch_deg,
        **p.record(),
        "posture_stiffness_Nm_per_rad": opts.posture_stiffness,
        "nullspace_damping_Nms_per_rad": damping,
        "preregistered": recorded is not None,
    }
    return WorkArea(pose, p.q_up, p.q_fixed, p.ns_fixed, damping, premise)


def work_area_summary(opts: MassFrictionOptions) -> list[dict[str, Any]]:
    """The experiment's premise in each work area at the run's rotor inertia, measured on the plant: the fixed
    posture's arm angle (deg), the felt mass (kg) and friction force (N) at elbow up and at the fixed posture,
    whether they differ enough (:attr:`.work_areas.Postures.discriminates`), and their impedance."""
    return [dict(a.premise) for a in work_areas_of(opts)]


def controller_values(strategy: str, area: WorkArea, opts: MassFrictionOptions) -> dict[str, Any]:
    """The controller settings of ``strategy`` (or control) in this experiment."""
    impedance = {"posture_stiffness": opts.posture_stiffness, "joint_damping": area.damping, **AS_THE_PAPER_RAN}
    values: dict[str, dict[str, Any]] = {
        "damped": {"strategy": "damped", "joint_damping": 0.0, **AS_THE_PAPER_RAN},
        "elbow-up": {"strategy": "elbow-up", **impedance},
        "fixed": {"strategy": "fixed", "fixed_posture": tuple(area.q_opt.tolist()), **impedance},
        "active": {"strategy": ACTIVE_STRATEGY, **AS_THE_PAPER_RAN},
        "qp": {"strategy": "qp"},
        "qp-zero": {"strategy": "qp", "weights": {"mass": 0.0, "friction_force": 0.0}},
    }
    values["damped-again"] = values["damped-light"] = values["damped"]  # (the controls: damped, as the paper's)
    return values[strategy]


def light_robot(robot, factor: float = LIGHT_MASS_FACTOR):
    """``robot`` with every link's mass and rotational inertia times ``factor`` (centres of mass kept; the plant's
    :class:`~qpnso.lab.plant.ModelMismatch` ``mass_factor`` draw, as Pinocchio sees it): its felt mass is
    ``factor`` times the robot's where the rotor inertia is 0 (A(q) scales)."""
    from qpnso.lab.plant import ModelMismatch, PlantParameters
    from qpnso.model.robot import Robot

    model = PlantParameters.draw(robot, ModelMismatch(mass_factor=factor)).pinocchio_model(robot)
    return Robot(robot.name, model, robot.tool_frame_id, robot.friction, robot.source)


def mass_friction_job(index: int, seed: int, opts: MassFrictionOptions) -> dict[str, Any]:
    """One trial: subject, order and repetition of job ``index``, one strategy or control; its row."""
    from dataclasses import replace

    from qpnso.control.config import ControllerConfig
    from qpnso.control.controller import Controller
    from qpnso.lab.simulation import simulate
    from qpnso.lab.surgeon import dome_targets, point_to_point_motion

    s, order, rep, group = opts.job(index)
    areas = work_areas_of(opts)
    k = s % len(areas)
    area = areas[k]
    person = subject(seed, s)
    targets = dome_targets(area.pose.translation, opts.dome_radius, opts.moves)
    perm = job_rng(seed, ORDER_STREAM + order).permutation(opts.moves)
    motion = point_to_point_motion(area.pose, targets[perm], opts.peak_speed * person.speed_scale, opts.dwell)
    robot = opts.load_robot(opts.robot)
    sim = opts.simulation(seed, index, person)
    if group == "damped-light":
        robot = light_robot(robot)
        sim = replace(sim, model_error=replace(sim.model_error, mass_factor=LIGHT_MASS_FACTOR))
    q0 = area.q_opt if group in ("fixed", "active", "qp", "qp-zero") else area.q_up
    ctrl = Controller(robot, ControllerConfig.from_dict(controller_values(group, area, opts)))
    summary, error = run_or_error(lambda: simulate(ctrl, motion, q0, sim))
    return {
        "subject": s,
        "area": k,
        "strategy": group,
        "order": order,
        "rep": rep,
        "targets": "".join(str(int(i) + 1) for i in perm),
        **trial_row(summary, error),
        **subject_record(person),
    }
