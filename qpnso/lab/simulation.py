"""Hands-on guidance simulation: the surgeon's hand pulls the tool, the robot
compensates gravity and applies a strategy's null-space torque (docs/method.md §9).

Joint dynamics ``A(q) q̈ + h(q, q̇) = τ + Jᵀ w_hand − τf(q̇)`` are integrated
at ``substeps`` × the control rate by a linearly implicit Euler step (Pinocchio's
CRBA and non-linear effects; velocity first, then position: :func:`_integrate`), the torque command
held over a control tick (zero-order hold).  Joint friction is the robot's smooth Coulomb model [M 23].
Each joint gets a reflected rotor inertia (``armature``, 0.1 kg·m² by default:
the URDF links alone give the wrist joints ~1e-4 kg·m², which no 1 kHz
null-space damping of 10 N·m·s/rad could hold stable; real drives add it).
The hand is a Cartesian spring–damper (world frame, tool point) towards the
guidance path; its wrench is what the surgeon feels and does work against
([M 24]).  The controller runs in hands-on mode: its level-1 reference is the
tool's measured pose and twist, so it never fights the hand.

With keep-out volumes in the room, every tick's distance of each link capsule to
each of them is measured independently of the controller, with coal
(:func:`qpnso.model.collision.clearances`), at the configuration the tick starts
from: the controller's own distances (:mod:`qpnso.model.distance`) are what is
being checked, and the room may hold obstacles the controller was not given.
Every tick is measured (its cost: docs/benchmarks.md, "Keep-out volumes").
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

from qpnso.control.config import Status
from qpnso.control.controller import Controller
from qpnso.control.offline import Recorder, RunResult
from qpnso.control.trajectory import Trajectory
from qpnso.errors import QpnsoError
from qpnso.lab.metrics import clearance_summary
from qpnso.model.obstacles import Obstacle, as_obstacles
from qpnso.model.robot import Robot
from qpnso.settings import check, out_of_range
from qpnso.settings import from_dict as settings_from_dict


class SimulationError(QpnsoError):
    """The integration diverged."""


@dataclass
class HandModel:
    """The surgeon's hand: a spring–damper on the tool pose (world frame)."""

    stiffness: float = 600.0  # N/m
    damping: float = 60.0  # N·s/m
    rotational_stiffness: float = 30.0  # N·m/rad
    rotational_damping: float = 3.0  # N·m·s/rad

    def __post_init__(self) -> None:
        """Types first (finite numbers, :func:`qpnso.settings.check`), then each gain >= 0."""
        check(self)
        for name in ("stiffness", "damping", "rotational_stiffness", "rotational_damping"):
            if getattr(self, name) < 0:
                raise out_of_range(self, name, "must be >= 0")

    @classmethod
    def from_dict(cls, values: dict, where: str = "") -> "HandModel":
        """Build from plain data (a ``[hand]`` table); unknown keys are listed with the valid ones."""
        return settings_from_dict(cls, values, where)

    def wrench(self, ref: tuple, tool: tuple) -> np.ndarray:
        """Force (N) and moment (N·m) on the tool, world frame.

        ``ref`` = (p, R, v, ω) of the path; ``tool`` = (p, R, v, ω) of the tool.
        """
        p_ref, r_ref, v_ref, w_ref = ref
        p, r, v, w = tool
        force = self.stiffness * (p_ref - p) + self.damping * (v_ref - v)
        moment = self.rotational_stiffness * pin.log3(r_ref @ r.T) + self.rotational_damping * (w_ref - w)
        return np.concatenate([force, moment])


@dataclass
class SimulationConfig:
    """Settings of the hands-on simulation; ``hand`` may be given as a dict."""

    substeps: int = 2  # integration steps per control tick
    hand: HandModel = field(default_factory=HandModel)
    armature: float = 0.1  # kg·m², reflected rotor inertia added to each joint

    def __post_init__(self) -> None:
        """Types first (:func:`qpnso.settings.check`), then ranges."""
        check(self)
        if self.substeps < 1:
            raise out_of_range(self, "substeps", "must be >= 1")
        if self.armature < 0:
            raise out_of_range(self, "armature", "must be >= 0 kg·m²")

    @classmethod
    def from_dict(cls, values: dict, where: str = "") -> "SimulationConfig":
        """Build from plain data (``hand`` as a table); unknown keys are listed with the valid ones."""
        return settings_from_dict(cls, values, where)


def simulate(
    controller: Controller,
    path: Trajectory,
    q0: np.ndarray,
    config: SimulationConfig | None = None,
    progress=None,
    room: Sequence[Obstacle] | None = None,
) -> RunResult:
    """Simulate hands-on guidance of the tool along ``path`` from ``q0`` (rad).

    Returns the per-tick arrays of :data:`qpnso.control.offline.RESULT_KEYS` plus
    ``dq_measured`` (rad/s), ``hand_wrench`` (N, N·m) and ``tool_twist``
    (m/s, rad/s), and the run's summary (metrics of docs/method.md §9, felt mass and
    friction every 10 ticks).

    ``room``: the keep-out volumes of the room (world frame, m; default: the controller's own).  When there are
    any, each tick records ``link_clearance`` (links, obstacles), m, coal's distances at the tick's ``q``, and
    ``controller_clearance`` (m), the controller's own least clearance (``Command.clearance``; inf when it was not
    given the obstacles); the summary gets :func:`qpnso.lab.metrics.clearance_summary`'s keys (from coal's
    distances) with ``room_obstacles`` and ``controller_obstacles`` (how many the controller was given).
    """
    cfg = config or SimulationConfig()
    robot = controller.robot
    room = controller.obstacles if room is None else as_obstacles(room)
    measure, links = clearance_meter(robot, room)
    model = robot.model.copy()
    if cfg.armature > 0:
        model.armature = np.full(model.nv, cfg.armature)
    data = model.createData()
    q = robot.check_q(q0, "q0").copy()
    dq = np.zeros(robot.nq)
    controller.reset(q)
    dt = controller.config.dt
    h = dt / cfg.substeps
    tool_id = robot.tool_frame_id
    recorder = Recorder(controller, feel_every=10)
    n_ticks = int(np.floor(path.duration / dt + 1e-9)) + 1
    for k in range(n_ticks):
        t = path.t[0] + k * dt
        tool = _tool_state(model, data, q, dq, tool_id)
        pose = pin.SE3(tool[1], tool[0])
        twist = np.concatenate([tool[2], tool[3]])
        cmd = controller.step(q, dq, tool_twist=twist, tool_pose=pose)
        ref = path.sample(t)
        wrench = cfg.hand.wrench(ref, tool)
        measured = {"link_clearance": measure(q), "controller_clearance": np.asarray(cmd.clearance)} if measure else {}
        recorder.add(
            t,
            q,
            cmd,
            pose,
            pin.SE3(ref[1], ref[0]),
            dq_measured=dq.copy(),
            hand_wrench=wrench,
            tool_twist=twist,
            **measured,
        )
        for _ in range(cfg.substeps):
            q, dq = _integrate(model, data, q, dq, cmd.tau, robot, tool_id, h, cfg.hand, ref)
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(dq))):
            raise SimulationError(f"the simulation diverged at t = {t:.3f} s (try more substeps)")
        if progress is not None:
            progress(k + 1, n_ticks)
    result = recorder.result()
    if measure:
        a = result.arrays
        result.summary.update(
            clearance_summary(a["t"], a["link_clearance"], links, a["status"], Status.OBSTACLE.value),
            room_obstacles=len(room),
            controller_obstacles=len(controller.obstacles),
        )
    return result


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


def _tool_state(model, data, q, dq, tool_id) -> tuple:
    """(p, R, v, ω) of the tool point, world frame."""
    pin.forwardKinematics(model, data, q, dq)
    pin.updateFramePlacement(model, data, tool_id)
    oMf = data.oMf[tool_id]
    vel = pin.getFrameVelocity(model, data, tool_id, pin.LOCAL_WORLD_ALIGNED)
    return oMf.translation.copy(), oMf.rotation.copy(), vel.linear.copy(), vel.angular.copy()


def _integrate(model, data, q, dq, tau, robot, tool_id, h, hand, ref) -> tuple[np.ndarray, np.ndarray]:
    """One linearly implicit Euler step: velocity-dependent forces (joint friction,
    the hand's damping) are taken at the new velocity to first order, so the stiff
    smooth-Coulomb slope (τmax·β·2/π ≈ 19 N·m·s/rad) does not need a tiny step.

    ``(A + h (∂τf/∂q̇ + Jᵀ D J)) Δq̇ = h (τ + Jᵀ w − τf(q̇) − h(q, q̇))``, then
    ``q ← q + h q̇_new``.
    """
    tool = _tool_state(model, data, q, dq, tool_id)
    wrench = hand.wrench(ref, tool)
    pin.computeJointJacobians(model, data, q)
    jac = pin.getFrameJacobian(model, data, tool_id, pin.LOCAL_WORLD_ALIGNED)
    a = pin.crba(model, data, q)
    a = np.triu(a) + np.triu(a, 1).T
    nle = pin.nonLinearEffects(model, data, q, dq)
    f = robot.friction
    slope = f.tau_max * f.beta * (2.0 / np.pi) / (1.0 + (f.beta * dq) ** 2)
    damping = np.diag(slope) + jac[:3].T @ jac[:3] * hand.damping + jac[3:].T @ jac[3:] * hand.rotational_damping
    rhs = tau + jac.T @ wrench - f.torque(dq) - nle
    dq_next = dq + np.linalg.solve(a + h * damping, h * rhs)
    return q + h * dq_next, dq_next
