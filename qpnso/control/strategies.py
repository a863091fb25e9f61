"""Redundancy strategies: qpnso's QP and the papers' baselines (docs/method.md §7–8).

Every tick a strategy fills in what is its own (:meth:`Strategy.fill`), on the tick's records
(:class:`qpnso.control.controller.TickRecords`): level 2 of the problem record (what the arm does in the
tool's null space; :mod:`qpnso.qp.problem`) and the command record's null-space impedance, whose gains
:func:`qpnso.control.tick.finish_tick` bounds by the self-motion's inertia
(:func:`qpnso.control.selfmotion.impedance_gains`) before it projects the torque into the dynamically
consistent null space and adds it to gravity compensation.  The ``qp`` strategy does both in one kernel
(:func:`qpnso.control.tick.qp_level2`); the papers' baselines, written in Python, say them as

* ``level2(state, elbow)``: a :class:`~qpnso.qp.Level` (task, quadratic, linear term) or None for "nothing";
* ``nullspace_law(state, elbow)``: their joint impedance (:class:`NullspaceLaw`: stiffness, set-point,
  damping, damping ratio, the damper's target velocity), which does not depend on the command;
  ``nullspace_torque(state, elbow, dq_meas)`` is its torque (N·m) before the tick's bounds.

Level 1 (the tool), the joint bounds and the solver are the same for every strategy, so the strategies
differ only where the papers differ.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from qpnso.control.state import TickState
from qpnso.control.tick import low_pass, qp_level2
from qpnso.control.virtual_arm import VirtualArm, saturated_gradient_velocity
from qpnso.elbow.closed_form import SRS_OK, branch_signs, srs_ik
from qpnso.elbow.srs import is_srs, srs_geometry
from qpnso.errors import ConfigError
from qpnso.linalg import nullspace_factors, selfmotion_inertia
from qpnso.qp import Level
from qpnso.qp.problem import set_level2

if TYPE_CHECKING:
    from qpnso.control.config import ControllerConfig, ElbowState
    from qpnso.control.controller import Controller, TickRecords


@dataclass(frozen=True)
class NullspaceLaw:
    """A strategy's null-space joint impedance: ``τ_null = K·offset + D·(velocity − q̇)`` (N·m) with
    ``D = damping + 2·damping_ratio·√(K·m)``, ``m`` the self-motion's inertia (kg·m²), before the tick bounds
    ``K`` and ``D`` by ``m`` (:func:`qpnso.control.selfmotion.impedance_gains`).  ``stiffness`` K (N·m/rad),
    ``offset`` the set-point minus ``q`` (rad; None: none), ``damping`` (N·m·s/rad), ``damping_ratio`` (ζ),
    ``velocity`` the damper's target (rad/s; None: rest)."""

    stiffness: float = 0.0
    offset: np.ndarray | None = None
    damping: float = 0.0
    damping_ratio: float = 0.0
    velocity: np.ndarray | None = None

    def torque(self, dq: np.ndarray, inertia: float = 0.0) -> np.ndarray:
        """The law's torque (N·m) at the joint velocity ``dq`` (rad/s) on a self-motion of ``inertia``
        (kg·m²; it enters only through ``damping_ratio``), unbounded."""
        ratio = self.damping_ratio
        damping = self.damping + (2.0 * ratio * math.sqrt(self.stiffness * inertia) if ratio > 0.0 else 0.0)
        spring = 0.0 if self.offset is None else self.stiffness * self.offset
        target = 0.0 if self.velocity is None else self.velocity
        return spring + damping * (target - dq)

    def write(self, command: np.void) -> None:
        """Into the tick's command record (:func:`qpnso.control.tick.command_dtype`): the law, without the
        ``qp`` strategy's terms along the command (``spring_cmd`` and ``damp_cmd`` 0)."""
        command["offset"] = 0.0 if self.offset is None else self.offset
        command["velocity"] = 0.0 if self.velocity is None else self.velocity
        command["stiffness"], command["damping"], command["damping_ratio"] = (
            self.stiffness,
            self.damping,
            self.damping_ratio,
        )
        command["spring_cmd"], command["damp_cmd"] = 0.0, 0.0


def state_inertia(state: "TickState") -> float:
    """The self-motion's inertia (kg·m²) at ``state``: :func:`qpnso.linalg.selfmotion_inertia` of its mass
    matrix (upper triangle) and Jacobian; 0 when it cannot be formed."""
    LA, W, LL, ok = nullspace_factors(state.mass_matrix, state.jacobian)
    return float(selfmotion_inertia(LA, W, LL)) if ok else 0.0


class Strategy:
    """Base: no level 2, null-space damping only (the damped posture, DP)."""

    name = "damped"

    def __init__(self, controller: "Controller") -> None:
        self.ctrl = controller
        self.cfg = controller.config
        self._identity = np.eye(controller.robot.nq)
        self._target: np.ndarray | None = None  # the low-passed kinematic target; None: at rest

    def reset(self, q0: np.ndarray, state: "TickState") -> None:
        """Called by ``Controller.reset``: from rest (a subclass calls this first)."""
        self._target = None

    def posture_target(self, velocity: np.ndarray) -> np.ndarray:
        """A baseline's kinematic level-2 target (rad/s, or rad/s of the arm angle): :func:`capped`, then
        low-passed with ``posture_filter_time`` from rest, as the ``qp`` strategy's cost step is
        (``cost_filter_time``): no velocity steps.  A step from rest to 3 rad/s of self-motion in one tick
        moved the held tool by 1.02 µrad (the second-order term along the previous command cannot see it
        coming; the fuzz, measured)."""
        v = capped(velocity, self.cfg)
        previous = self._target if self._target is not None and self._target.shape == v.shape else np.zeros_like(v)
        self._target = low_pass(previous, v, filter_alpha(self.cfg.posture_filter_time, self.cfg.dt))
        return self._target.copy()

    def fill(self, tick: "TickRecords") -> None:
        """Level 2 into ``tick.problem`` (:func:`qpnso.qp.problem.set_level2` of :meth:`level2`) and the
        impedance into ``tick.command`` (:meth:`nullspace_law`; the tick bounds its gains)."""
        state, elbow = TickState.of(tick.q, tick.state), tick.elbow()
        set_level2(tick.problem, self.level2(state, elbow))
        self.nullspace_law(state, elbow).write(tick.command[0])

    def level2(self, state: "TickState", elbow: "ElbowState") -> Level | None:
        return None

    def nullspace_law(self, state: "TickState", elbow: "ElbowState") -> NullspaceLaw:
        """DP: τ = −D q̇ with D = ``joint_damping`` (10 N·m·s/rad, the elbow paper's)."""
        return NullspaceLaw(damping=self.cfg.joint_damping)

    def nullspace_torque(self, state: "TickState", elbow: "ElbowState", dq_meas: np.ndarray) -> np.ndarray:
        """The torque (N·m) of :meth:`nullspace_law` at the measured ``dq_meas`` (rad/s), before the tick bounds
        its gains by the self-motion's inertia."""
        law = self.nullspace_law(state, elbow)
        return law.torque(dq_meas, state_inertia(state) if law.damping_ratio else 0.0)


class Damped(Strategy):
    """Damped posture (DP): gravity compensation and null-space damping."""


class FixedPosture(Strategy):
    """Fixed optimal posture (FOP): constant stiffness towards a posture ([E], [M]).

    The posture is ``config.fixed_posture`` (rad) or the reset configuration.
    Kinematically: level 2 asks ``q̇ = posture_gain·(q_ref − q)`` in the null space.
    """

    name = "fixed"

    def reset(self, q0: np.ndarray, state: "TickState") -> None:
        super().reset(q0, state)
        ref = self.cfg.fixed_posture
        self.q_ref = q0.copy() if ref is None else self.ctrl.robot.check_q(ref, "fixed_posture")

    def level2(self, state: "TickState", elbow: "ElbowState") -> Level:
        return Level(A=self._identity, b=self.posture_target(self.cfg.posture_gain * (self.q_ref - state.q)))

    def nullspace_law(self, state, elbow) -> NullspaceLaw:
        """``K_P (q_ref − q) − D q̇``."""
        return NullspaceLaw(self.cfg.posture_stiffness, self.q_ref - state.q, self.cfg.joint_damping)


def clip_norm(v: np.ndarray, limit: float) -> np.ndarray:
    """``v`` scaled to Euclidean norm at most ``limit`` (``v`` itself when within it)."""
    norm = float(np.sqrt(v @ v))
    return v * (limit / norm) if norm > limit else v


def capped(velocity: np.ndarray, cfg: "ControllerConfig") -> np.ndarray:
    """A kinematic level-2 target (rad/s) scaled to norm at most ``nullspace_speed_max``, as the ``qp``
    strategy's cost step is: a posture far away is approached at a bounded speed (an elbow-up return
    once asked 6 rad/s of the arm angle, and dragged the held tool by 8 µm)."""
    return clip_norm(velocity, cfg.nullspace_speed_max)


def filter_alpha(time_constant: float, dt: float) -> float:
    """Per-tick factor ``dt/max(τ, dt)`` of a first-order low-pass of time constant ``τ`` (s; 0: no filter)."""
    return dt / max(time_constant, dt) if time_constant > 0 else 0.0


def arm_angle_step(state: "TickState", delta_ns: float) -> np.ndarray:
    """Smallest joint displacement (rad) that changes the arm angle by ``delta_ns`` (first order)."""
    g = state.arm_angle_gradient
    return g * (delta_ns / max(float(g @ g), 1e-12))


class ElbowUp(Strategy):
    """Elbow up: a constant null-space posture that keeps the elbow high ([M]).

    The arm angle is driven to ``elbow_up_angle_deg`` (0 = elbow up) with the FOP
    stiffness, through the smallest joint motion that changes it.
    """

    name = "elbow-up"

    def _delta(self, elbow: "ElbowState") -> float:
        target = np.radians(self.cfg.elbow_up_angle_deg)
        return float((target - elbow.ns + np.pi) % (2 * np.pi) - np.pi)

    def level2(self, state, elbow) -> Level:
        row = state.arm_angle_gradient.reshape(1, -1)
        rate = self.cfg.posture_gain * self._delta(elbow)  # rad/s of the arm angle
        return Level(A=row, b=self.posture_target(np.array([rate])))

    def nullspace_law(self, state, elbow) -> NullspaceLaw:
        """``K_P δq(Δns) − D q̇``."""
        step = arm_angle_step(state, self._delta(elbow))
        return NullspaceLaw(self.cfg.posture_stiffness, step, self.cfg.joint_damping)


class Gradient(Strategy):
    """The mass/friction paper's velocity-saturated null-space gradient [M 20]–[M 22].

    ``ω_des = −k_p ∇c / k_d``, ``v_d = min(1, ω_max/‖ω_des‖)``,
    ``F_p = −k_d (q̇ − v_d ω_des)``; kinematically level 2 asks ``q̇ = v_d ω_des`` (:func:`capped` at
    ``nullspace_speed_max``: the torque law keeps [M 20]'s ω_max, but a kinematic jump from rest to 10 rad/s
    in one tick dragged the held tool by 4 µm in the fuzz).
    """

    name = "gradient"

    def desired_velocity(self, state: "TickState") -> np.ndarray:
        """``v_d ω_des`` (rad/s) at the state's cost gradient
        (:func:`qpnso.control.virtual_arm.saturated_gradient_velocity`)."""
        cfg = self.cfg
        return saturated_gradient_velocity(
            state.cost_gradient, cfg.gradient_kp, cfg.gradient_kd, cfg.gradient_omega_max
        )

    def level2(self, state, elbow) -> Level:
        return Level(A=self._identity, b=self.posture_target(self.desired_velocity(state)))

    def nullspace_law(self, state, elbow) -> NullspaceLaw:
        """``F_p = −k_d (q̇ − v_d ω_des)``: a damper ``k_d`` towards the desired velocity."""
        return NullspaceLaw(damping=self.cfg.gradient_kd, velocity=self.desired_velocity(state))


class GradientImpedance(Strategy):
    """[M]'s active law as [M] V-A ran it on the LWR 4+: [M 20]–[M 22] forward simulated on a virtual arm whose
    tool pose is set to the measured one every tick (:class:`qpnso.control.virtual_arm.VirtualArm`, gains
    ``gradient_kp``, ``gradient_kd``, ``gradient_omega_max``), its joint angles ``q_D`` commanded as a null-space
    joint impedance ``K(q_D − q) − D q̇`` with ``K = gradient_impedance_stiffness`` (100 N·m/rad) and ``D`` of
    damping ratio ``gradient_impedance_damping_ratio`` (0.1) in the self-motion's inertia (the KUKA impedance
    damps the measured velocity).  Kinematically level 2 asks ``q̇ = target(q̇_D + posture_gain (q_D − q))``
    (:meth:`Strategy.posture_target`).  A virtual arm that cannot be brought to the measured pose restarts at
    the measured ``q``, at rest.  The virtual arm advances once per tick (:meth:`fill` asks :meth:`level2` and
    :meth:`nullspace_law` with the same state)."""

    name = "gradient-impedance"

    def __init__(self, controller: "Controller") -> None:
        super().__init__(controller)
        cfg = self.cfg
        self.arm = VirtualArm(
            controller.robot, controller.cost, cfg.gradient_kp, cfg.gradient_kd, cfg.gradient_omega_max
        )
        self._advanced_at: TickState | None = None  # the state the virtual arm last advanced at

    def reset(self, q0: np.ndarray, state: "TickState") -> None:
        super().reset(q0, state)
        self.arm.reset(q0)
        self._advanced_at = None

    def virtual(self, state: "TickState") -> tuple[np.ndarray, np.ndarray]:
        """``(q_D, q̇_D)`` (rad, rad/s) of this tick: the virtual arm anchored at the state's tool pose and
        advanced one tick, once per state."""
        if self._advanced_at is not state:
            if not self.arm.anchor(state.tool_rotation, state.tool_position):
                self.arm.reset(state.q)
            self.arm.advance(self.cfg.dt)
            self._advanced_at = state
        return self.arm.q, self.arm.dq

    def level2(self, state, elbow) -> Level:
        q_d, dq_d = self.virtual(state)
        return Level(A=self._identity, b=self.posture_target(dq_d + self.cfg.posture_gain * (q_d - state.q)))

    def nullspace_law(self, state, elbow) -> NullspaceLaw:
        """``K (q_D − q) − D q̇``, ``D = 2ζ√(K·m)``."""
        cfg = self.cfg
        q_d, _ = self.virtual(state)
        return NullspaceLaw(
            cfg.gradient_impedance_stiffness, q_d - state.q, damping_ratio=cfg.gradient_impedance_damping_ratio
        )


class RomModulation(Strategy):
    """The elbow paper's set-point modulation (NSO) [E 1], [E 5], [E 6], [E 10], [E 11].

    ``ns_des`` follows ``ns`` inside ROM_t and saturates at its ends; the
    set-point ``q_des`` is the closed-form IK at ``ns_des`` (S-R-S arms: the kernel
    :func:`qpnso.elbow.closed_form.srs_ik` on the branch of ``q``) or, where it has none (another arm, a
    singular or unreachable pose), the first-order step towards it; ``τ = K(ns)(q_des − q) − D q̇``.
    Inside the ROM the null space is only damped, as in the paper.  A tick's set-point is computed once
    (:meth:`fill` asks :meth:`level2` and :meth:`nullspace_law` with the same state).
    """

    name = "rom"

    def __init__(self, controller: "Controller") -> None:
        super().__init__(controller)
        robot = controller.robot
        self._geometry = srs_geometry(robot).record[0] if is_srs(robot) else None  # (None: no closed form)
        self._q_set = np.zeros(robot.nq)  # rad: the closed-form set-point, written by the kernel
        self._step_of: tuple[TickState, tuple[float, float, float], np.ndarray | None] | None = None  # (state,
        # (ns, ROM_t), the set-point step there)

    def _setpoint_step(self, state: "TickState", elbow: "ElbowState") -> np.ndarray | None:
        """``q_des − q`` (rad) at the saturated arm angle, or None inside ROM_t; computed once per state and
        elbow (arm angle, ROM_t)."""
        lo, hi = elbow.rom
        key = (elbow.ns, lo, hi)
        if self._step_of is not None and self._step_of[0] is state and self._step_of[1] == key:
            return self._step_of[2]
        target = min(max(elbow.ns, lo), hi)
        step = None if target == elbow.ns else self._ik_step(state, elbow, target)
        self._step_of = (state, key, step)
        return step

    def _ik_step(self, state: "TickState", elbow: "ElbowState", target: float) -> np.ndarray:
        """``q_des − q`` (rad) towards the arm angle ``target`` (rad): the closed-form IK's set-point on the branch
        of ``q`` at the tool's pose (:func:`setpoint_ik`), else :func:`arm_angle_step`."""
        if self._geometry is not None and setpoint_ik(self._geometry, state, target, self._q_set):
            return self._q_set - state.q
        return arm_angle_step(state, target - elbow.ns)

    def level2(self, state, elbow) -> Level | None:
        """Towards the set-point while ``ns`` is outside ROM_t; inside, nothing once the low-passed target
        has decayed below 1e-9 rad/s (it decays over ``posture_filter_time`` instead of stopping at once)."""
        step = self._setpoint_step(state, elbow)
        if step is None and self._target is None:
            return None
        target = self.posture_target(self.cfg.posture_gain * step if step is not None else np.zeros(state.q.size))
        if step is None and float(np.abs(target).max()) < 1e-9:
            self._target = None
            return None
        return Level(A=self._identity, b=target)

    def nullspace_law(self, state, elbow) -> NullspaceLaw:
        """``K(ns)(q_des − q) − D q̇`` (inside ROM_t ``q_des = q``)."""
        return NullspaceLaw(elbow.stiffness, self._setpoint_step(state, elbow), self.cfg.joint_damping)


def setpoint_ik(geometry: np.void, state: "TickState", ns: float, out: np.ndarray) -> bool:
    """The closed-form IK (:func:`qpnso.elbow.closed_form.srs_ik`, the S-R-S geometry record ``geometry``) at the
    tool pose of ``state``, on the branch of its ``q``, at the arm angle ``ns`` (rad, wrapped into [−π, π)) into
    ``out`` (7,); False where it has none (a joint 2, 4 or 6 exactly 0, ``ns`` not finite, the pose out of reach
    or its arm angle undefined): what :func:`qpnso.elbow.srs.ik` raises there."""
    s2, s4, s6, defined = branch_signs(state.q)
    if not (defined and math.isfinite(ns)):
        return False
    wrapped = (ns + math.pi) % (2.0 * math.pi) - math.pi
    code, _ = srs_ik(geometry, state.tool_rotation, state.tool_position, s2, s4, s6, wrapped, out)
    return bool(code == SRS_OK)


class QPStrategy(Strategy):
    """qpnso: minimise the weighted mass/friction cost in the null space, with the
    elbow kept in ROM_t (docs/method.md §7, level 2).

    Objective ``½‖q̇‖² + k ∇c(q)ᵀ q̇`` (the step ``−k∇c`` saturated to
    ``nullspace_speed_max`` as in [M 20]); elbow rows
    ``ξ(ns_lo − ns) ≤ ∇nsᵀ q̇ ≤ ξ(ns_hi − ns)`` (velocity dampers, soft with a
    heavy slack) so an elbow outside ROM_t is brought back at rate ξ.
    The torque is the null-space impedance ``K(ns)·dt·q̇_cmd + D(q̇_cmd − q̇)``.
    """

    name = "qp"

    def fill(self, tick: "TickRecords") -> None:
        """Level 2 and the impedance in one kernel: :func:`qpnso.control.tick.qp_level2`."""
        qp_level2(tick.tick)


_STRATEGIES = {
    cls.name: cls for cls in (Damped, FixedPosture, ElbowUp, Gradient, GradientImpedance, RomModulation, QPStrategy)
}


def make_strategy(name: str, controller: "Controller") -> Strategy:
    """The strategy called ``name`` (``qp``, ``damped``, ``fixed``, ``elbow-up``, ``gradient``,
    ``gradient-impedance``, ``rom``)."""
    try:
        return _STRATEGIES[name](controller)
    except KeyError:
        raise ConfigError(f"unknown strategy {name!r}; choose one of {sorted(_STRATEGIES)}") from None
