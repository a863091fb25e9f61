"""The forward simulation [M] V-A ran its active law through on the LWR 4+ (docs/method.md §8): a virtual arm
moved by [M 20]–[M 22] in the null space of its tool pose, that pose set to the measured one every tick.

[M] V-A: the robot's Cartesian pose "is set to the desired end effector pose in a dynamic simulation of the
system, which uses the rigid body dynamic library of the LWR ... and the control torques computed using (22)
to integrate the system one time step into the future"; the simulated joint angles ``q_D`` are then commanded
to the robot's null-space joint impedance (the strategy ``gradient-impedance``,
:class:`qpnso.control.strategies.GradientImpedance`).

Under (22) the posture force ``F_p = −k_d(q̇ − v_d ω_des)`` [M 20] acts through ``N_tᵀ`` with gravity and the
Coriolis terms compensated, so the virtual arm moves by ``q̈ = A⁻¹N_tᵀF_p = Z (ZᵀAZ)⁻¹ Zᵀ F_p`` (``Z`` an
orthonormal basis of ``ker J``, one direction ``z`` for a 7-joint arm): its self-motion velocity ``ν = zᵀq̇``
relaxes towards ``ν_t = zᵀv_dω_des`` as ``m ν̇ = −k_d(ν − ν_t)``, ``m = zᵀAz``.  :meth:`VirtualArm.advance`
integrates that exactly over a tick with
``A``, ``J`` and ``∇c`` frozen at its start ([M] used Dormand–Prince 5; the exact solution of the frozen
linear law is what any accurate integrator converges to, and it stays stable where an explicit step of
``k_d dt/m`` > 2 would not: 3.3 on the bare LWR 4+'s lightest self-motions).
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from qpnso.elbow.intervals import least_norm_step
from qpnso.linalg import least_norm_line
from qpnso.model.costs import CostModel
from qpnso.model.robot import Robot

ANCHOR_TOL = 1e-10
"""m and rad: the virtual arm's tool is taken to be at the measured pose within this."""
ANCHOR_ONE_STEP = 1e-4
"""m and rad: from a pose error below this one Newton step is taken and its residual (about the error squared,
1e-8 at most: the ≤ mm a tool moves in a tick gives far less) is left to the next tick."""
ANCHOR_ITERATIONS = 4
"""Newton steps at most to bring the virtual arm's tool to the measured pose (a virtual arm still off by more
than 1e-6 after them is restarted at the measured ``q``)."""


def saturated_gradient_velocity(gradient: np.ndarray, kp: float, kd: float, omega_max: float) -> np.ndarray:
    """``v_d ω_des`` of [M 20] (rad/s): ``ω_des = −k_p∇c/k_d`` scaled by ``v_d = min(1, ω_max/‖ω_des‖)``."""
    omega = -kp / kd * gradient
    norm = float(np.linalg.norm(omega))
    return omega * min(1.0, omega_max / norm) if norm > 0 else omega


class VirtualArm:
    """A virtual copy of ``robot`` (7 joints: its null space is one direction ``z``) driven by [M 20]–[M 22] with
    gains ``kp``, ``kd`` (N·m·s/rad) and ``omega_max`` (rad/s) on the cost ``cost`` (module docstring).  State
    ``q`` (rad) and ``dq`` (rad/s)."""

    def __init__(self, robot: Robot, cost: CostModel, kp: float, kd: float, omega_max: float) -> None:
        self.robot, self.cost = robot, cost
        self.kp, self.kd, self.omega_max = kp, kd, omega_max
        self._model, self._data = robot.model, robot.model.createData()  # (Pinocchio's, called directly: q is
        # the virtual arm's own, finite and within its limits, and robot's checks cost 6 µs a call)
        self._frame = robot.tool_frame_id
        self._no_twist = np.zeros(6)
        self.q = robot.sample_configuration()
        self.dq = np.zeros(robot.nq)
        self._jacobian_of: tuple[np.ndarray, np.ndarray, np.ndarray | None] | None = None  # (q, J(q), z(q) or
        # None): the last Jacobian taken and its null direction

    def reset(self, q: np.ndarray) -> None:
        """At the measured ``q`` (rad), at rest."""
        self.q = np.array(q, dtype=float)
        self.dq = np.zeros_like(self.q)

    def anchor(self, R: np.ndarray, p: np.ndarray) -> bool:
        """The virtual arm moved (least joint motion, Newton steps ``q ← q + J⁺e``, J⁺ the pseudo-inverse: a
        singular ``J`` takes the least-norm least-squares step) so that its tool is at the
        pose ``R`` (world ← tool), ``p`` (m): the measured one (:data:`ANCHOR_ONE_STEP`); its velocity keeps
        only its self-motion part there.  False (nothing changed) when it cannot get there within 1e-6 m/rad."""
        q = self.q
        error: np.ndarray | None = self._pose_error(q, R, p)
        for _ in range(ANCHOR_ITERATIONS):
            assert error is not None
            size = float(np.abs(error).max())
            if size < ANCHOR_TOL:
                break
            J = self._jacobian(q)
            q = q + least_norm_step(J, error)  # (J⁺e, defined at a singular J too)
            if size < ANCHOR_ONE_STEP:
                error = None  # (its residual is the next tick's)
                break
            error = self._pose_error(q, R, p)
        if not np.all(np.isfinite(q)) or (error is not None and np.abs(error).max() > 1e-6):
            return False
        z = self._null_direction(q)
        self.q, self.dq = q, z * (z @ self.dq)
        return True

    def advance(self, dt: float) -> None:
        """One tick of ``dt`` s of [M 20]–[M 22] (module docstring): the self-motion velocity relaxed exactly
        towards the saturated gradient velocity (:func:`saturated_gradient_velocity`; a cost gradient that is not
        finite, Λ undefined at a singular J, counts as zero, as in the tick), the position by its integral; a
        joint that would leave its limits stops there (the virtual arm at rest)."""
        q = self.q
        z = self._null_direction(q)
        upper = np.triu(pin.crba(self._model, self._data, q))  # (Pinocchio fills the upper triangle)
        inertia = float(2.0 * (z @ upper @ z) - np.diag(upper) @ (z * z))  # m = zᵀAz (kg·m²)
        gradient = self.cost.gradient(q)
        if not np.all(np.isfinite(gradient)):
            gradient = np.zeros_like(gradient)
        target = float(z @ saturated_gradient_velocity(gradient, self.kp, self.kd, self.omega_max))
        rate = self.kd / inertia  # 1/s
        away = float(z @ self.dq) - target
        step = z * (dt * target - away * np.expm1(-rate * dt) / rate)  # ∫₀^dt ν
        self.dq = z * (target + away * np.exp(-rate * dt))
        q_new = q + step
        inside = np.clip(q_new, self.robot.q_min, self.robot.q_max)
        if not (np.array_equal(inside, q_new) and np.all(np.isfinite(self.dq))):
            self.dq[:] = 0.0
        self.q = inside if np.all(np.isfinite(inside)) else q

    def _pose_error(self, q: np.ndarray, R: np.ndarray, p: np.ndarray) -> np.ndarray:
        """``(p − p(q), log₃(R R(q)ᵀ))`` (m, rad; world frame): how far the tool at ``q`` is from the pose."""
        pin.framesForwardKinematics(self._model, self._data, q)
        pose = self._data.oMf[self._frame]
        return np.concatenate([p - pose.translation, pin.log3(R @ pose.rotation.T)])

    def _jacobian(self, q: np.ndarray) -> np.ndarray:
        """The tool Jacobian at ``q`` (Pinocchio), taken once per configuration."""
        if self._jacobian_of is None or not np.array_equal(self._jacobian_of[0], q):
            J = pin.computeFrameJacobian(self._model, self._data, q, self._frame, pin.LOCAL_WORLD_ALIGNED)
            self._jacobian_of = (q.copy(), np.ascontiguousarray(J), None)
        return self._jacobian_of[1]

    def _null_direction(self, q: np.ndarray) -> np.ndarray:
        """The unit vector ``z`` of ``ker J(q)`` (:func:`qpnso.linalg.least_norm_line`; at a singular ``J`` the
        right singular vector of its least singular value, one of the null plane's), once per configuration."""
        J = self._jacobian(q)
        assert self._jacobian_of is not None
        z = self._jacobian_of[2]
        if z is None:
            _, z, sigma_floor = least_norm_line(J, self._no_twist)  # (Householder QR of Jᵀ, compiled)
            if sigma_floor == 0.0:  # (a singular J)
                z = np.linalg.svd(J)[2][-1]
            self._jacobian_of = (self._jacobian_of[0], J, z)
        return z
