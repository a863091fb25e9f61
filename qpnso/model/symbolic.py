"""Symbolic twin of a Pinocchio model, in CasADi SX.

The PyPI ``pin`` wheel has no ``pinocchio.casadi``, so the kinematic tree is
rebuilt here from the Pinocchio model's own parameters (joint placements, joint
axes, link inertias, armature).  The expressions agree with Pinocchio to
round-off (``tests/test_symbolic.py``):

* joint and frame placements (forward kinematics);
* the frame Jacobian, ``LOCAL_WORLD_ALIGNED`` (linear rows first, world axes,
  at the frame origin), as in docs/method.md §2;
* the joint-space inertia matrix ``A(q) = Σ_b m_b Jc_bᵀ Jc_b + Jw_bᵀ R_b I_b R_bᵀ Jw_b
  + diag(armature)``;
* the generalised gravity ``g(q) = ∂V/∂q``, ``V = −Σ_b m_b g₀ᵀ c_b``.

Supported joints: revolute (aligned or unaligned axis) and prismatic.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np
import pinocchio as pin

from qpnso.errors import ModelError

_REVOLUTE_AXES = {"JointModelRX": (1.0, 0.0, 0.0), "JointModelRY": (0.0, 1.0, 0.0), "JointModelRZ": (0.0, 0.0, 1.0)}
_PRISMATIC_AXES = {"JointModelPX": (1.0, 0.0, 0.0), "JointModelPY": (0.0, 1.0, 0.0), "JointModelPZ": (0.0, 0.0, 1.0)}


@dataclass(frozen=True)
class SymPlacement:
    """A rigid placement as CasADi expressions: rotation ``R`` (3×3), origin ``p`` (3, m)."""

    R: ca.SX
    p: ca.SX

    def act(self, other: "SymPlacement") -> "SymPlacement":
        """Composition ``self * other``."""
        return SymPlacement(ca.mtimes(self.R, other.R), self.p + ca.mtimes(self.R, other.p))

    def point(self, local: np.ndarray) -> ca.SX:
        """World coordinates of a point given in this frame."""
        return self.p + ca.mtimes(self.R, ca.DM(local))


def _constant(se3: pin.SE3) -> SymPlacement:
    return SymPlacement(ca.SX(ca.DM(se3.rotation)), ca.SX(ca.DM(se3.translation)))


def _rotation(axis: np.ndarray, angle: ca.SX) -> ca.SX:
    """Rodrigues' formula: rotation by ``angle`` (rad) about unit ``axis``."""
    k = ca.DM([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return ca.DM.eye(3) + ca.sin(angle) * k + (1 - ca.cos(angle)) * ca.mtimes(k, k)


def joint_kind_and_axis(joint: pin.JointModel) -> tuple[str, np.ndarray]:
    """``("revolute" | "prismatic", unit axis in the joint frame)`` of a 1-DOF joint."""
    name = joint.shortname()
    if name in _REVOLUTE_AXES:
        return "revolute", np.array(_REVOLUTE_AXES[name])
    if name in _PRISMATIC_AXES:
        return "prismatic", np.array(_PRISMATIC_AXES[name])
    if name == "JointModelRevoluteUnaligned":
        return "revolute", np.array(joint.extract().axis, dtype=float)
    if name == "JointModelPrismaticUnaligned":
        return "prismatic", np.array(joint.extract().axis, dtype=float)
    raise ModelError(f"joint type {name} is not supported by the symbolic model")


class SymbolicModel:
    """CasADi expressions of a Pinocchio model in the joint variable ``q`` (SX, nq)."""

    def __init__(self, model: pin.Model) -> None:
        self.model = model
        self.nq = model.nq
        self.q = ca.SX.sym("q", model.nq)
        self._mass_matrix: ca.SX | None = None
        self._kinds: list[tuple[str, np.ndarray]] = [("fixed", np.zeros(3))]
        self.oMi: list[SymPlacement] = [_constant(pin.SE3.Identity())]
        for j in range(1, model.njoints):
            self._kinds.append(joint_kind_and_axis(model.joints[j]))
            parent = self.oMi[model.parents[j]]
            self.oMi.append(parent.act(_constant(model.jointPlacements[j])).act(self._motion(j)))

    def _motion(self, j: int) -> SymPlacement:
        kind, axis = self._kinds[j]
        qj = self.q[self.model.joints[j].idx_q]
        if kind == "revolute":
            return SymPlacement(_rotation(axis, qj), ca.SX.zeros(3))
        return SymPlacement(ca.SX.eye(3), ca.DM(axis) * qj)

    # ------------------------------------------------------------ kinematics
    def frame_placement(self, frame_id: int) -> SymPlacement:
        """World placement of a Pinocchio frame."""
        frame = self.model.frames[frame_id]
        return self.oMi[frame.parentJoint].act(_constant(frame.placement))

    def joint_axis_world(self, j: int) -> ca.SX:
        """Unit axis of joint ``j`` in world coordinates."""
        return ca.mtimes(self.oMi[j].R, ca.DM(self._kinds[j][1]))

    def point_jacobian(self, joint: int, point: ca.SX) -> ca.SX:
        """6×nq Jacobian of a point rigidly attached to ``joint``, world-aligned.

        Rows 0–2 map ``dq`` to the point's linear velocity (m/s), rows 3–5 to
        the body's angular velocity (rad/s), both in world coordinates.
        """
        jac = ca.SX.zeros(6, self.nq)
        for k in self.model.supports[joint][1:]:
            col = self.model.joints[k].idx_v
            a = self.joint_axis_world(k)
            if self._kinds[k][0] == "revolute":
                jac[0:3, col] = ca.cross(a, point - self.oMi[k].p)
                jac[3:6, col] = a
            else:
                jac[0:3, col] = a
        return jac

    def frame_jacobian(self, frame_id: int) -> ca.SX:
        """Frame Jacobian at the frame origin, ``LOCAL_WORLD_ALIGNED``."""
        joint = self.model.frames[frame_id].parentJoint
        return self.point_jacobian(joint, self.frame_placement(frame_id).p)

    # -------------------------------------------------------------- dynamics
    def mass_matrix(self) -> ca.SX:
        """Joint-space inertia matrix A(q) (nq×nq, kg·m²), symmetric by construction (Pinocchio's
        ``crba``).  Built once: every expression that uses it shares its nodes."""
        if self._mass_matrix is None:
            self._mass_matrix = self._build_mass_matrix()
        return self._mass_matrix

    def _build_mass_matrix(self) -> ca.SX:
        a = ca.SX(ca.DM(np.diag(np.asarray(self.model.armature, dtype=float))))
        for j in range(1, self.model.njoints):
            inertia = self.model.inertias[j]
            if inertia.mass <= 0.0:
                continue
            com = self.oMi[j].point(np.asarray(inertia.lever))
            jac = self.point_jacobian(j, com)
            jv, jw = jac[0:3, :], jac[3:6, :]
            rot = self.oMi[j].R
            i_world = ca.mtimes([rot, ca.DM(np.asarray(inertia.inertia)), rot.T])
            a += inertia.mass * ca.mtimes(jv.T, jv) + ca.mtimes([jw.T, i_world, jw])
        return a

    def gravity_torque(self) -> ca.SX:
        """Generalised gravity ``g(q) = ∂V/∂q`` (nq, N·m) with ``V = −Σ_b m_b g₀ᵀ c_b`` (J), ``g₀`` the
        model's gravity (m/s², world): Pinocchio's ``computeGeneralizedGravity``."""
        g0 = ca.DM(np.asarray(self.model.gravity.linear, dtype=float))
        potential = ca.SX(0)
        for j in range(1, self.model.njoints):
            inertia = self.model.inertias[j]
            if inertia.mass > 0.0:
                potential -= inertia.mass * ca.dot(g0, self.oMi[j].point(np.asarray(inertia.lever)))
        return ca.gradient(potential, self.q)

    def function(self, name: str, outputs: dict[str, ca.SX]) -> ca.Function:
        """A CasADi function of ``q`` with named outputs."""
        return ca.Function(name, [self.q], list(outputs.values()), ["q"], list(outputs.keys()))
