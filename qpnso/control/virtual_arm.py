"""The forward simulation [M] V-A ran its active law through on the LWR 4+ (docs/method.md §8): a virtual arm
moved by [M 20]–[M 22] in the null space of its tool pose, that pose set to the measured one every tick.

[M] V-A: the robot's Cartesian pose "is set to the desired end effector pose in a dynamic simulation of the
system, which uses the rigid body dynamic library of the LWR ... and the control torques computed using (22)
to integrate the system one time step into the future"; the simulated joint angles ``q_D`` are then commanded
to the robot's null-space joint impedance (the strategy ``gradient-impedance``,
:class:`qpnso.control.strategies.GradientImpedance`).

Under (22) the posture force ``F_p = −k_d(q̇ − v_d ω_des)`` [M 20] acts through ``N_tᵀ`` with gravity and the
Coriolis terms compensated, so the virtual arm moves by ``q̈ = A⁻¹N_tᵀF_p = Z (ZᵀAZ)⁻¹ Zᵀ F_p`` (``Z`` an
orthonormal basis of ``ker J``): its self-motion velocity ``ν = Zᵀq̇`` relaxes towards ``ν_t = Zᵀv_dω_des`` as
``ν̇ = −k_d M⁻¹(ν − ν_t)``, ``M = ZᵀAZ``.  :meth:`VirtualArm.advance` integrates that exactly over a tick with
``A``, ``J`` and ``∇c`` frozen at its start ([M] used Dormand–Prince 5; the exact solution of the frozen
linear law is what any accurate integrator converges to, and it stays stable where an explicit step of
``k_d dt/m`` > 2 would not: 3.3 on the bare LWR 4+'s lightest self-motions).
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from qpnso.model.costs import CostModel
from qpnso.model.robot import Robot

ANCHOR_TOL = 1e-10
"""m and rad: the virtual arm's tool is taken to be at the measured pose within this."""
ANCHOR_ITERATIONS = 4
"""Newton steps at most to bring the virtual arm's tool to the measured pose (one suffices for the ≤ mm a tool
moves in a tick; a virtual arm still off by more than 1e-6 after them is restarted at the measured ``q``)."""


def saturated_gradient_velocity(gradient: np.ndarray, kp: float, kd: float, omega_max: float) -> np.ndarray:
    """``v_d ω_des`` of [M 20] (rad/s): ``ω_des = −k_p∇c/k_d`` scaled by ``v_d = min(1, ω_max/‖ω_des‖)``."""
    omega = -kp / kd * gradient
    norm = float(np.linalg.norm(omega))
    return omega * min(1.0, omega_max / norm) if norm > 0 else omega


class VirtualArm:
    """A virtual copy of ``robot`` driven by [M 20]–[M 22] with gains ``kp``, ``kd`` (N·m·s/rad) and ``omega_max``
    (rad/s) on the cost ``cost`` (module docstring).  State ``q`` (rad) and ``dq`` (rad/s)."""

    def __init__(self, robot: Robot, cost: CostModel, kp: float, kd: float, omega_max: float) -> None:
        self.robot, self.cost = robot, cost
        self.kp, self.kd, self.omega_max = kp, kd, omega_max
        self.q = robot.sample_configuration()
        self.dq = np.zeros(robot.nq)

    def reset(self, q: np.ndarray) -> None:
        """At the measured ``q`` (rad), at rest."""
        self.q = np.array(q, dtype=float)
        self.dq = np.zeros_like(self.q)

    def anchor(self, R: np.ndarray, p: np.ndarray) -> bool:
        """The virtual arm moved (least joint motion, Newton steps ``q ← q + J⁺e``) so that its tool is at the
        pose ``R`` (world ← tool), ``p`` (m): the measured one; its velocity keeps only its self-motion part
        there.  False (nothing changed) when it cannot get there within 1e-6 m/rad."""
        q = self.q.copy()
        for _ in range(ANCHOR_ITERATIONS):
            error = self._pose_error(q, R, p)
            if np.abs(error).max() < ANCHOR_TOL:
                break
            q = q + np.linalg.lstsq(self.robot.jacobian(q), error, rcond=None)[0]
        error = self._pose_error(q, R, p)
        if not (np.all(np.isfinite(q)) and np.abs(error).max() < 1e-6):
            return False
        self.q = q
        z = self._null_basis(self.robot.jacobian(q))
        self.dq = z @ (z.T @ self.dq)
        return True

    def advance(self, dt: float) -> None:
        """One tick of ``dt`` s of [M 20]–[M 22] (module docstring): the self-motion velocity relaxed exactly
        towards the saturated gradient velocity (:func:`saturated_gradient_velocity`; a cost gradient that is not
        finite, Λ undefined at a singular J, counts as zero, as in the tick), the position by its integral; a
        joint that would leave its limits stops there (the virtual arm at rest)."""
        q = self.q
        z = self._null_basis(self.robot.jacobian(q))
        inertia = z.T @ self.robot.mass_matrix(q) @ z  # M = ZᵀAZ (kg·m²)
        gradient = self.cost.gradient(q)
        if not np.all(np.isfinite(gradient)):
            gradient = np.zeros_like(gradient)
        target = z.T @ saturated_gradient_velocity(gradient, self.kp, self.kd, self.omega_max)
        lam, vec = np.linalg.eigh(inertia)
        rate = self.kd / lam  # 1/s: the eigen-rates of k_d M⁻¹
        decay = vec @ np.diag(np.exp(-rate * dt)) @ vec.T
        moved = vec @ np.diag(-np.expm1(-rate * dt) / rate) @ vec.T  # ∫₀^dt of the decay
        nu = z.T @ self.dq - target
        step = z @ (dt * target + moved @ nu)
        self.dq = z @ (target + decay @ nu)
        q_new = q + step
        inside = np.clip(q_new, self.robot.q_min, self.robot.q_max)
        if not (np.array_equal(inside, q_new) and np.all(np.isfinite(self.dq))):
            self.dq[:] = 0.0
        self.q = inside if np.all(np.isfinite(inside)) else q

    def _pose_error(self, q: np.ndarray, R: np.ndarray, p: np.ndarray) -> np.ndarray:
        """``(p − p(q), log₃(R R(q)ᵀ))`` (m, rad; world frame): how far the tool at ``q`` is from the pose."""
        pose = self.robot.tool_pose(q)
        return np.concatenate([p - pose.translation, pin.log3(R @ pose.rotation.T)])

    def _null_basis(self, J: np.ndarray) -> np.ndarray:
        """An orthonormal basis (nq, nq − 6) of ``ker J``: the right singular vectors of its least singular
        values."""
        return np.linalg.svd(J)[2][J.shape[0] :].T
