"""The mass/friction paper's user experiment ([M] §V-B, V-C), with virtual surgeons on the MuJoCo plant.

Protocol (the paper's, with what it does not publish stated as ours):

* six targets on a surgical-target-sized dome (:func:`qpnso.lab.surgeon.dome_targets`: 5 cm radius, one at
  the top, five on a ring; the paper's layout is not published) above the work-area centre, the tool at
  scenario A's pose (0.65, 0, 0.5) m, rpy (180, 30, 180)° on the LWR4+;
* a trial visits the six targets in one of ``orders`` random orders (seeded, the same orders for every
  subject), minimum-jerk moves at a peak speed of 0.1 m/s × the subject's speed scale, 0.5 s at rest at each
  target, the rotation about the tool axis free; ``reps`` repetitions of each order, ``subjects`` subjects;
* strategies: ``damped`` (plain gravity compensation: no null-space torque, as the paper's), ``elbow-up``
  and ``fixed`` (a null-space joint impedance of 100 N·m/rad with damping ratio 0.1 towards the elbow-up
  arm angle or the fixed posture), ``active`` (qpnso's ``qp``: 50 % mass, 50 % friction force) and the
  ablation ``qp-zero`` (``qp`` with every cost weight 0: the ROM rows and damping only);
* the fixed posture is the cost optimum (50/50) on the self-motion of the work-area centre pose, inside the
  continuity interval of the elbow-up start (0.5° grid then bounded Brent): "pre-optimised for the work
  area"; fixed, active and the ablation start there, damped and elbow-up start elbow up (ns = 0);
* the damping ratio's inertia is the self-motion's: ``D = 2·0.1·√(100·uᵀA u)`` with ``u`` the unit
  null-space direction at the fixed posture;
* the plant has :data:`qpnso.lab.experiments.trials.EXPERIMENT_MODEL_ERROR` (one draw per run).

Per trial: |work| per metre ([M 24]: ∫|F·v + M·ω| dt / L), normalised per subject by the largest
per-strategy mean, and the mean moment orthogonal to the direction of motion (its Fig. 10b), normalised
the same way.  Statistics: :mod:`qpnso.lab.experiments.statistics`.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import pinocchio as pin
from scipy.optimize import minimize_scalar

from qpnso.errors import ConfigError
from qpnso.lab.experiments.trials import (
    ORDER_STREAM,
    PlantOptions,
    run_or_error,
    subject,
    subject_record,
    trial_row,
)
from qpnso.lab.parallel import job_rng

STRATEGIES = ("damped", "elbow-up", "fixed", "active", "qp-zero")
"""The trial strategies, in the order of the paper's Table I, then the ablation."""
PAPER_STRATEGIES = STRATEGIES[:4]


@dataclass(frozen=True)
class MassFrictionOptions(PlantOptions):
    """Size and fixed parameters of the experiment (see the module docstring)."""

    subjects: int = 8
    orders: int = 5
    reps: int = 3
    moves: int = 6
    robot: str = "lwr4p"
    center: tuple[float, float, float] = (0.65, 0.0, 0.5)
    rpy_deg: tuple[float, float, float] = (180.0, 30.0, 180.0)
    dome_radius: float = 0.05  # m
    peak_speed: float = 0.1  # m/s
    dwell: float = 0.5  # s
    posture_stiffness: float = 100.0  # N·m/rad
    damping_ratio: float = 0.1

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("subjects", "orders", "reps"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 2 <= self.moves <= 12:
            raise ConfigError(f"moves must be in [2, 12], got {self.moves}")

    @property
    def n_jobs(self) -> int:
        return self.subjects * self.orders * self.reps * len(STRATEGIES)

    def job(self, index: int) -> tuple[int, int, int, str]:
        """``(subject, order, rep, strategy)`` of job ``index``."""
        grid = itertools.product(range(self.subjects), range(self.orders), range(self.reps), STRATEGIES)
        return next(itertools.islice(grid, index, None))

    def pose(self) -> pin.SE3:
        """The work-area centre pose (world frame)."""
        return pin.SE3(pin.rpy.rpyToMatrix(*np.radians(self.rpy_deg)), np.asarray(self.center, dtype=float))


@dataclass(frozen=True)
class WorkArea:
    """The work area's postures (rad): elbow up (ns = 0) and the fixed optimum, its arm angle (rad), the
    null-space damping (N·m·s/rad) of the fixed and elbow-up impedance, and the experiment's premise measured
    on the controller's model (:func:`work_area_summary`)."""

    q_up: np.ndarray
    q_opt: np.ndarray
    ns_opt: float
    damping: float
    premise: dict[str, float]


ELBOW_UP_BRANCH = (-1, 1, -1)
"""Branch (signs of joints 2, 4, 6) of the work-area postures: scenario A's."""


_AREAS: dict[str, WorkArea] = {}


def work_area(opts: MassFrictionOptions) -> WorkArea:
    """The postures of :class:`WorkArea`, computed once per process and options."""
    key = repr(sorted(asdict(opts).items()))
    if key not in _AREAS:
        _AREAS[key] = _work_area(opts)
    return _AREAS[key]


def _work_area(opts: MassFrictionOptions) -> WorkArea:
    from qpnso.elbow.intervals import continuity_interval
    from qpnso.elbow.srs import Branch, ik
    from qpnso.model.costs import CostModel

    robot = opts.load_robot(opts.robot)
    pose, b = opts.pose(), Branch(*ELBOW_UP_BRANCH)
    q_up = ik(robot, pose, 0.0, b)
    iv = continuity_interval(robot, q_up)
    cost = CostModel(robot)  # (the controller's cost: default weights, 50 % mass, 50 % friction force)
    value = lambda ns: cost.value(ik(robot, pose, ns, b))  # noqa: E731
    grid = np.arange(iv.lo + 1e-3, iv.hi - 1e-3, math.radians(0.5))
    k = int(np.argmin([value(ns) for ns in grid]))
    lo, hi = grid[max(0, k - 1)], grid[min(len(grid) - 1, k + 1)]
    ns = float(minimize_scalar(value, bounds=(lo, hi), method="bounded", options={"xatol": 1e-9}).x)
    q_opt = ik(robot, pose, ns, b)
    u = np.linalg.svd(robot.jacobian(q_opt))[2][-1]  # the unit null-space direction
    inertia = float(u @ robot.mass_matrix(q_opt) @ u)
    damping = 2.0 * opts.damping_ratio * math.sqrt(opts.posture_stiffness * inertia)
    premise = {
        "fixed_arm_angle_deg": math.degrees(ns),
        "mass_elbow_up_kg": cost.principal_mass(q_up),
        "mass_fixed_kg": cost.principal_mass(q_opt),
        "friction_elbow_up_N": cost.friction_force_magnitude(q_up),
        "friction_fixed_N": cost.friction_force_magnitude(q_opt),
        "posture_stiffness_Nm_per_rad": opts.posture_stiffness,
        "nullspace_damping_Nms_per_rad": damping,
    }
    return WorkArea(q_up, q_opt, ns, damping, premise)


def work_area_summary(opts: MassFrictionOptions) -> dict[str, float]:
    """The experiment's premise, measured on the controller's model: the fixed posture's arm angle (deg), the
    felt mass (kg) and friction force (N) at the elbow-up and at the fixed posture, and their impedance."""
    return dict(work_area(opts).premise)


def controller_values(strategy: str, area: WorkArea, opts: MassFrictionOptions) -> dict[str, Any]:
    """The controller settings of ``strategy`` in this experiment."""
    impedance = {"posture_stiffness": opts.posture_stiffness, "joint_damping": area.damping}
    values: dict[str, dict[str, Any]] = {
        "damped": {"strategy": "damped", "joint_damping": 0.0},
        "elbow-up": {"strategy": "elbow-up", **impedance},
        "fixed": {"strategy": "fixed", "fixed_posture": tuple(area.q_opt.tolist()), **impedance},
        "active": {"strategy": "qp"},
        "qp-zero": {"strategy": "qp", "weights": {"mass": 0.0, "friction_force": 0.0}},
    }
    return values[strategy]


def mass_friction_job(index: int, seed: int, opts: MassFrictionOptions) -> dict[str, Any]:
    """One trial: subject, order and repetition of job ``index``, one strategy; its row."""
    from qpnso.control.config import ControllerConfig
    from qpnso.control.controller import Controller
    from qpnso.lab.simulation import simulate
    from qpnso.lab.surgeon import dome_targets, point_to_point_motion

    s, order, rep, strategy = opts.job(index)
    area = work_area(opts)
    person = subject(seed, s)
    pose = opts.pose()
    targets = dome_targets(pose.translation, opts.dome_radius, opts.moves)
    perm = job_rng(seed, ORDER_STREAM + order).permutation(opts.moves)
    motion = point_to_point_motion(pose, targets[perm], opts.peak_speed * person.speed_scale, opts.dwell)
    robot = opts.load_robot(opts.robot)
    q0 = area.q_up if strategy in ("damped", "elbow-up") else area.q_opt
    sim = opts.simulation(seed, index, person)
    ctrl = Controller(robot, ControllerConfig.from_dict(controller_values(strategy, area, opts)))
    summary, error = run_or_error(lambda: simulate(ctrl, motion, q0, sim))
    return {
        "subject": s,
        "strategy": strategy,
        "order": order,
        "rep": rep,
        "targets": "".join(str(int(i) + 1) for i in perm),
        **trial_row(summary, error),
        **subject_record(person),
    }
