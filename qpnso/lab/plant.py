"""The simulated robot: MuJoCo, compiled from the same URDF as the controller's Pinocchio model (docs/method.md §9).

One robot, two engines.  MuJoCo reads the robot's URDF; the model's reflected rotor inertias
(``model.armature``, :func:`qpnso.model.robot.load_robot`), its Coulomb sliding torques (``frictionloss`` =
the robot's ``friction.tau_max``) and its viscous damping (``damping`` = the URDF's ``<dynamics damping>``,
Pinocchio's ``model.damping``) are set on the MuJoCo joints, so the plant is the controller's model
unless a :class:`ModelMismatch` says otherwise.  The one declared difference: the plant's Coulomb friction is
set-valued (it holds any joint torque up to ``tau_coulomb`` at rest), the controller's is its smooth
approximation [M 23].

The Coulomb friction holds (:func:`friction_constraint`).  MuJoCo's ``frictionloss`` is a soft constraint: a
load below the friction level is not held but creeps, at a joint velocity of about
``(1 - d)/d · d_width · timeconst/2`` times the acceleration the load alone would give (MuJoCo's reference
acceleration ``a₁ + d·b·v = (1 - d)·a₀``, ``b = 2/(d_width·timeconst)``; a friction row's violation is
identically 0, so only ``d = solimp[0]``, ``d_width = solimp[1]`` and the time constant act).  With MuJoCo's
defaults (0.02 s, 0.9/0.95) a 1 N force at the gravity-compensated LWR4+ tool moves it 46 mm in 1 s, where a
1.5 N·m Coulomb law holds it.  The plant sets each joint's friction row as stiff as MuJoCo allows instead: the
impedance at MuJoCo's largest, 0.9999 (``mjMAXIMP``), and the time constant at twice the plant's step, the
floor below which MuJoCo's docs say the integration may go unstable (and its ``refsafe`` flag clamps to);
the creep is then ~10⁻⁴ of the default's (6 µm for that 1 N, tests/test_plant_friction.py).  Chosen over an
explicit stick–slip law because the seven joints' sticking torques are coupled through A(q): holding
them exactly is the box-constrained problem MuJoCo's constraint solver already solves each step, inside its
implicit integration; an explicit law would solve it again outside, one step late.

The plant integrates with MuJoCo's ``implicitfast`` integrator at ``timestep`` (default 0.5 ms: two steps
per 1 kHz control tick), the torque command held over each tick.  Contacts are off (the arm meets no
object but the hand); the joint limits are MuJoCo's (hard stops).  A site ``qpnso_tool`` sits at the
controller's tool point.  The surgeon's hand is a body of its own mass welded there
(:class:`qpnso.lab.surgeon.Subject`); its weight is carried by the surgeon (an upward force cancels it),
its arm impedance acts on it as an applied wrench.  A point mass at the tool keeps the dynamically
consistent projector consistent (Woodbury: ``J A'⁻¹ Nᵀ = 0`` when ``A' = A + Jᵀ M_h J``).

What the hand feels is computed on the plant (:meth:`Plant.felt`): the largest principal mass at the tool
[M 8] from MuJoCo's inertia matrix and tool Jacobian (without the hand), and the potential friction force
[M 15] with the plant's friction law (Coulomb + viscous).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
import pinocchio as pin

from qpnso.errors import ModelError as ModelFileError
from qpnso.model.costs import principal_masses
from qpnso.model.robot import Robot
from qpnso.settings import check, out_of_range
from qpnso.settings import from_dict as settings_from_dict

FRICTION_IMPEDANCE = mujoco.mjMAXIMP
"""MuJoCo's impedance ``d`` (``solimp[0]`` and ``solimp[1]``) of each joint's friction row: its largest value
(``mjMAXIMP``), the stiffest Coulomb friction MuJoCo can run."""
FRICTION_TIMECONST_STEPS = 2.0
"""The time constant of each joint's friction row, in plant steps: MuJoCo's stated floor (``refsafe``)."""
TOOL_SITE = "qpnso_tool"
"""Name of the MuJoCo site at the controller's tool point."""
HAND_BODY = "qpnso_hand"
"""Name of the MuJoCo body of the surgeon's hand."""


@dataclass(frozen=True)
class ModelMismatch:
    """How the plant is drawn from the nominal model (seeded; all zero: the plant is the model).

    Relative standard deviations (1 = 100 %) of normal draws, one per joint or link: ``mass`` scales each
    moving link's mass and inertia together (its centre of mass kept), ``friction`` each joint's Coulomb
    torque (the mass/friction paper's N(0, (10 %)²) is 0.1), ``armature`` each rotor inertia;
    ``torque_offset`` (N·m) is the standard deviation of a constant offset added to each joint's torque
    (torque-sensor bias, gravity-model residual).  A draw is clipped to factors >= 0.1.
    """

    mass: float = 0.0
    friction: float = 0.0
    armature: float = 0.0
    torque_offset: float = 0.0  # N·m
    seed: int = 0
    mass_factor: float = 1.0  # every link's mass and inertia times this before the draw (a known change of the
    # plant, e.g. the mass/friction experiment's positive control; the controller's model must be scaled alike)

    def __post_init__(self) -> None:
        check(self)
        for name in ("mass", "friction", "armature", "torque_offset"):
            if getattr(self, name) < 0:
                raise out_of_range(self, name, "must be >= 0")
        if not self.mass_factor > 0:
            raise out_of_range(self, "mass_factor", "must be > 0")

    @classmethod
    def from_dict(cls, values: dict, where: str = "") -> "ModelMismatch":
        """Build from plain data (a ``[model_error]`` table)."""
        return settings_from_dict(cls, values, where)

    @property
    def none(self) -> bool:
        """True when the plant is the nominal model."""
        return self.mass == self.friction == self.armature == self.torque_offset == 0.0 and self.mass_factor == 1.0


@dataclass(frozen=True)
class PlantParameters:
    """A plant drawn from a robot: per moving link ``mass_scale`` (mass and inertia), per joint
    ``tau_coulomb`` (N·m), ``damping`` (N·m·s/rad), ``armature`` (kg·m²) and ``torque_offset`` (N·m)."""

    mass_scale: np.ndarray
    tau_coulomb: np.ndarray
    damping: np.ndarray
    armature: np.ndarray
    torque_offset: np.ndarray

    @classmethod
    def draw(cls, robot: Robot, error: ModelMismatch | None = None) -> "PlantParameters":
        """The nominal parameters of ``robot``, perturbed by ``error`` (seeded)."""
        e = error or ModelMismatch()
        n = robot.nq
        rng = np.random.default_rng(e.seed)
        factor = lambda sd: np.maximum(0.1, 1.0 + sd * rng.standard_normal(n))  # noqa: E731
        return cls(
            mass_scale=e.mass_factor * factor(e.mass),
            tau_coulomb=robot.friction.tau_max * factor(e.friction),
            damping=np.array(robot.model.damping, dtype=float),
            armature=np.array(robot.model.armature, dtype=float) * factor(e.armature),
            torque_offset=e.torque_offset * rng.standard_normal(n),
        )

    def pinocchio_model(self, robot: Robot) -> pin.Model:
        """A copy of the robot's Pinocchio model with these parameters (the plant as Pinocchio sees it)."""
        model = robot.model.copy()
        for j in range(1, model.njoints):
            inertia = model.inertias[j]
            s = float(self.mass_scale[j - 1])
            model.inertias[j] = pin.Inertia(inertia.mass * s, inertia.lever.copy(), inertia.inertia * s)
        model.armature = self.armature.copy()
        model.damping = self.damping.copy()
        return model


def tool_site_spec(robot: Robot) -> mujoco.MjSpec:
    """MuJoCo's spec of the robot's URDF with a site :data:`TOOL_SITE` at the controller's tool point, on the
    body moved by the tool frame's joint; :class:`ModelFileError` when MuJoCo cannot read the URDF."""
    try:
        spec = mujoco.MjSpec.from_file(robot.source)
        plain = spec.compile()
    except Exception as exc:  # (MuJoCo raises ValueError for a file it cannot read or compile)
        raise ModelFileError(f"MuJoCo cannot load {robot.source!r}: {exc}") from None
    frame = robot.model.frames[robot.tool_frame_id]
    joint = robot.model.names[frame.parentJoint]
    if joint not in mujoco_joint_names(plain):
        raise ModelFileError(f"MuJoCo's model of {robot.source!r} has no joint {joint!r} (the tool frame's)")
    body = spec.body(plain.body(plain.jnt_bodyid[plain.joint(joint).id]).name)
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, frame.placement.rotation.ravel())
    body.add_site(name=TOOL_SITE, pos=frame.placement.translation, quat=quat)
    return spec


def friction_constraint(timestep: float) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo's ``(solref, solimp)`` of a joint's friction row at plant step ``timestep`` (s): time constant
    :data:`FRICTION_TIMECONST_STEPS` steps (damping ratio 1; MuJoCo ignores it on a friction row), impedance
    :data:`FRICTION_IMPEDANCE` at every violation (the row's violation is always 0; width, midpoint and power are
    MuJoCo's defaults, unused)."""
    solref = np.array([FRICTION_TIMECONST_STEPS * timestep, 1.0])
    solimp = np.array([FRICTION_IMPEDANCE, FRICTION_IMPEDANCE, 0.001, 0.5, 2.0])
    return solref, solimp


def mujoco_joint_names(model: mujoco.MjModel) -> list[str]:
    """The names of a compiled MuJoCo model's joints, in order."""
    return [model.joint(j).name for j in range(model.njnt)]


class Plant:
    """The robot in MuJoCo with parameters :class:`PlantParameters`, and the surgeon's hand at the tool.

    ``hand_mass`` (kg) and ``hand_inertia`` (kg·m², about each axis) make the hand body; ``timestep`` (s)
    is the integration step.  State: ``q`` (rad), ``dq`` (rad/s).
    """

    def __init__(
        self,
        robot: Robot,
        params: PlantParameters | None = None,
        timestep: float = 5e-4,
        hand_mass: float = 0.0,
        hand_inertia: float = 0.0,
    ) -> None:
        self.robot = robot
        self.params = params or PlantParameters.draw(robot)
        self.hand_mass = float(hand_mass)
        self.bare = self._compile(robot, 0.0, 0.0, timestep)
        self.model = self._compile(robot, self.hand_mass, float(hand_inertia), timestep) if hand_mass > 0 else self.bare
        self.data = mujoco.MjData(self.model)
        self._bare_data = mujoco.MjData(self.bare)
        self.site = self.model.site(TOOL_SITE).id
        self.hand = self.model.body(HAND_BODY).id if hand_mass > 0 else -1
        self._jac = np.zeros((6, self.model.nv))

    def _compile(self, robot: Robot, hand_mass: float, hand_inertia: float, timestep: float) -> mujoco.MjModel:
        spec = tool_site_spec(robot)
        spec.option.timestep = timestep
        spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
        spec.option.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
        spec.option.gravity = np.array(robot.model.gravity.linear)
        if hand_mass > 0:
            spec.compiler.fusestatic = False  # (else MuJoCo merges the hand, a body without joints, into the link)
            site = spec.site(TOOL_SITE)
            hand = site.parent.add_body(name=HAND_BODY, pos=site.pos, quat=site.quat)
            hand.mass, hand.inertia, hand.explicitinertial = hand_mass, [hand_inertia] * 3, True
        model = spec.compile()
        if mujoco_joint_names(model) != robot.joint_names:
            raise ModelFileError(f"MuJoCo's joints {mujoco_joint_names(model)} are not the model's {robot.joint_names}")
        p = self.params
        for k in range(robot.nq):
            model.body_mass[model.jnt_bodyid[k]] *= p.mass_scale[k]
            model.body_inertia[model.jnt_bodyid[k]] *= p.mass_scale[k]
        model.dof_armature[:] = p.armature
        model.dof_frictionloss[:] = p.tau_coulomb
        model.dof_solref[:], model.dof_solimp[:] = friction_constraint(timestep)
        model.dof_damping[:] = p.damping
        return model

    @property
    def q(self) -> np.ndarray:
        """Joint positions (rad), a copy."""
        return self.data.qpos.copy()

    @property
    def dq(self) -> np.ndarray:
        """Joint velocities (rad/s), a copy."""
        return self.data.qvel.copy()

    def reset(self, q: np.ndarray, dq: np.ndarray | None = None) -> None:
        """At ``q`` (rad) with ``dq`` (rad/s, default rest), time 0."""
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[:] = q
        self.data.qvel[:] = 0.0 if dq is None else dq
        mujoco.mj_forward(self.model, self.data)

    def tool_state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(p (m), R, v (m/s), ω (rad/s)) of the tool point, world frame, at the current state."""
        d = self.data
        mujoco.mj_jacSite(self.model, d, self._jac[:3], self._jac[3:], self.site)
        v = self._jac @ d.qvel
        return d.site_xpos[self.site].copy(), d.site_xmat[self.site].reshape(3, 3).copy(), v[:3], v[3:]

    def step(self, tau: np.ndarray, hand_wrench: np.ndarray | None = None) -> None:
        """One integration step with joint torques ``tau`` (N·m; the model error's offsets added) and the
        hand's arm wrench ``hand_wrench`` (N, N·m; world frame, at the tool point) on the hand body."""
        d = self.data
        d.qfrc_applied[:] = tau + self.params.torque_offset
        if self.hand >= 0:
            d.xfrc_applied[self.hand, :3] = -self.hand_mass * self.model.opt.gravity  # the surgeon carries it
            d.xfrc_applied[self.hand, 3:] = 0.0
            if hand_wrench is not None:
                d.xfrc_applied[self.hand] += hand_wrench
        mujoco.mj_step(self.model, d)

    # ------------------------------------------------------------- the plant's model, without the hand
    def dynamics(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(A(q) (kg·m²), g(q) (N·m), J(q) (6×nq, tool point, world frame))`` of the robot alone."""
        m, d = self.bare, self._bare_data
        d.qpos[:] = q
        d.qvel[:] = 0.0
        mujoco.mj_forward(m, d)
        a = np.zeros((m.nv, m.nv))
        mujoco.mj_fullM(m, d, a)
        jac = np.zeros((6, m.nv))
        mujoco.mj_jacSite(m, d, jac[:3], jac[3:], m.site(TOOL_SITE).id)
        return a, d.qfrc_bias.copy(), jac

    def friction_torque(self, dq: np.ndarray) -> np.ndarray:
        """The plant's sliding friction (N·m) at joint velocities ``dq`` (rad/s; (nq,) or (nq, k), one column
        per velocity): Coulomb + viscous."""
        p = self.params
        column = (slice(None),) + (None,) * (np.ndim(dq) - 1)
        return p.tau_coulomb[column] * np.sign(dq) + p.damping[column] * dq

    def felt(self, qs: np.ndarray, speed: float) -> tuple[np.ndarray, np.ndarray]:
        """What the hand feels at each configuration of ``qs`` (N, nq; rad): the largest principal mass (kg,
        1/λ_min(Jv A⁻¹ Jvᵀ) [M 8]) and the potential friction force (N, √Σ_i ‖J̄ᵀ τf(J̄ s e_i)‖² [M 15] with
        the plant's friction, ``speed`` s in m/s), each (N,)."""
        qs = np.atleast_2d(qs)
        lam_inv, force = np.empty((len(qs), 3, 3)), np.empty(len(qs))
        for k, q in enumerate(qs):
            a, _, jac = self.dynamics(q)
            jv = jac[:3]
            a_inv_jt = np.linalg.solve(a, jv.T)
            lam_inv[k] = jv @ a_inv_jt
            jbar = a_inv_jt @ np.linalg.inv(lam_inv[k])
            forces = jbar.T @ self.friction_torque(speed * jbar)
            force[k] = float(np.sqrt(np.sum(forces**2)))
        return principal_masses(lam_inv), force

    def describe(self) -> dict[str, object]:
        """The plant as plain data, for a run's summary: engine and version, integrator, step, parameters."""
        p = self.params
        return {
            "engine": "mujoco",
            "version": mujoco.__version__,
            "integrator": "implicitfast",
            "timestep_s": float(self.model.opt.timestep),
            "friction": "coulomb (MuJoCo frictionloss, the stiffest row MuJoCo allows) + viscous (damping)",
            "friction_solref": self.model.dof_solref[0].tolist(),
            "friction_solimp": self.model.dof_solimp[0].tolist(),
            "mass_scale": p.mass_scale.tolist(),
            "tau_coulomb_Nm": p.tau_coulomb.tolist(),
            "armature_kgm2": p.armature.tolist(),
            "torque_offset_Nm": p.torque_offset.tolist(),
            "hand_mass_kg": self.hand_mass,
        }
