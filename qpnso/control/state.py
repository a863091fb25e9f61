"""What every strategy needs to know about the arm at one control tick.

One compiled CasADi function evaluates, from ``q`` alone, the tool pose, the
tool Jacobian, the weighted cost and its exact gradient, the arm angle with its
exact gradient and singularity measures, the dynamics a torque command needs
(``A(q)``, ``g(q)``), and the tool's second-order motion ``J̇(q, q̇)q̇`` along the
command predicted for the tick (level 1's second-order term, :func:`predicted_velocity`): one call per tick instead of
eight (:class:`StateEvaluator`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import casadi as ca
import numpy as np
from numba import njit

from qpnso.control.flags import FLAG_COST_UNDEFINED, FLAG_INTERNAL_ERROR
from qpnso.elbow.arm_angle import arm_angle_expression, elbow_points
from qpnso.model.codegen import FastFunction
from qpnso.model.costs import CostModel


@dataclass
class TickState:
    """The arm at one tick.  Frames: world; tool point; units rad, m, s."""

    q: np.ndarray  # (nq,) rad
    tool_rotation: np.ndarray  # (3, 3) world ← tool
    tool_position: np.ndarray  # (3,) m, world
    jacobian: np.ndarray  # (6, nq) world-aligned at the tool point, linear rows first
    cost: float  # weighted total [M 18]
    cost_gradient: np.ndarray  # (nq,) per rad
    arm_angle: float  # ns [E 2], rad
    arm_angle_gradient: np.ndarray  # (nq,) ∂ns/∂q
    wrist_sin: float  # |p_sw × z0| / |p_sw|: sine of the wrist's angle to the vertical
    elbow_offset: float  # distance (m) of the elbow centre from the shoulder–wrist line
    pose: np.ndarray  # (12,) rotation entries (column-major) then position (m): for cheap comparisons
    mass_matrix: np.ndarray  # (nq, nq) A(q), kg·m² (Pinocchio's crba)
    gravity: np.ndarray  # (nq,) g(q), N·m (Pinocchio's computeGeneralizedGravity)
    tool_drift: np.ndarray  # (6,) J̇(q, q̇)q̇ at the predicted q̇ (m/s², rad/s²; world-aligned, tool point)
    flags: int = 0  # status bits of sanitize_state: what was not finite and made safe


class StateEvaluator:
    """Evaluates :class:`TickState` from ``q`` with one CasADi call.

    The function has a single output, every quantity stacked in one vector (``R``, ``J`` and ``A``
    column-major) at the offsets :attr:`offsets`; :func:`state_views` cuts it into the state's
    fields, views of the one array a tick copies (or, for the compiled tick, reads in place).
    """

    def __init__(self, cost: CostModel, compile: str | None = None) -> None:
        robot = cost.robot
        sym = cost.sym
        tool = sym.frame_placement(robot.tool_frame_id)
        ns, measures = arm_angle_expression(sym, elbow_points(robot))
        total = cost.expression
        J = sym.frame_jacobian(robot.tool_frame_id)
        dq, twist = ca.SX.sym("dq", robot.nq), ca.SX.sym("twist", 6)
        parts = [
            tool.R,
            tool.p,
            J,
            total,
            ca.gradient(total, sym.q),
            ns,
            ca.gradient(ns, sym.q),
            measures,
            sym.mass_matrix(),
            sym.gravity_torque(),
            tool_drift(sym.q, J, predicted_velocity(J, dq, twist)),
        ]
        stacked = ca.vertcat(*[ca.vec(part) for part in parts])
        self.robot = robot
        self._zero_velocity = np.zeros(robot.nq)
        self._fn = FastFunction(
            ca.Function(f"tick_{robot.name}", [ca.vertcat(sym.q, dq, twist)], [stacked], ["q_dq_twist"], ["state"]),
            compile,
        )  # one input: one copy a tick
        self._zero_twist = np.zeros(6)
        self.offsets = np.cumsum([0] + [part.numel() for part in parts])
        """Start of each part in the stacked vector, and its length at the end (in the order of
        :func:`state_views`)."""

    def wait_compiled(self, timeout: float | None = None) -> bool:
        """Block until compiled code is used (benchmarks call this)."""
        return self._fn.wait(timeout)

    def __call__(self, q: np.ndarray, dq: np.ndarray | None = None, twist: np.ndarray | None = None) -> TickState:
        """State at ``q`` (rad; assumed validated by the caller); the drift along the velocity predicted
        from the previous command ``dq`` (rad/s; None: 0) and this tick's tool ``twist`` (m/s, rad/s; None:
        ``dq``'s own, so the drift is along ``dq`` itself) — :func:`predicted_velocity`."""
        dq = self._zero_velocity if dq is None else dq
        if twist is None:
            twist = self._zero_twist if dq is self._zero_velocity else self.robot.jacobian(q) @ dq
        return self.state(q, self._fn.evaluate_in_place(q, dq, twist).copy())

    def raw(self, q: np.ndarray, dq: np.ndarray, twist: np.ndarray) -> np.ndarray:
        """The stacked state at ``q`` (rad), the previous command ``dq`` (rad/s) and the tool ``twist``
        (validated by the caller) in the evaluator's own buffer: read it before the next call, which
        overwrites it (the compiled tick's in-place read)."""
        return self._fn.evaluate_in_place(q, dq, twist)

    def state(self, q: np.ndarray, flat: np.ndarray) -> TickState:
        """The :class:`TickState` of a stacked state ``flat`` (views of it) at ``q``, made safe first
        (:func:`sanitize_state`, in place: an undefined cost is 0, an undefined arm angle
        singular; :attr:`TickState.flags` says so)."""
        flags = sanitize_state(flat, self.offsets)
        R, p, J, c, dc, ns, dns, wrist_sin, elbow_offset, A, g, drift = state_views(flat, self.offsets)
        return TickState(q, R, p, J, c, dc, ns, dns, wrist_sin, elbow_offset, flat[:12], A, g, drift, flags)


PREDICTION_DAMPING = 1e-2
"""ε (m/rad) of the damped pseudo-inverse in :func:`predicted_velocity`: near a singularity the predicted
tool part stays within ``|v|/(2ε)`` rad/s (the hierarchical QP's default damping threshold)."""


def predicted_velocity(J: ca.SX, dq: ca.SX, twist: ca.SX) -> ca.SX:
    """This tick's joint velocity as predicted before it is solved (rad/s): the previous command ``dq``
    with its tool part replaced by this tick's ``twist``, ``dq + Jᵀ(JJᵀ + ε²I)⁻¹(v − J dq)``
    (damped least squares, ε = :data:`PREDICTION_DAMPING`).  The null-space motion changes little from
    one tick to the next, the tool's can jump (a surgeon's pull that stops): the second-order term along
    the previous command alone left a held tool 1–2 µm off after a 2 m/s pull (the fuzz, measured)."""
    return dq + ca.mtimes(
        J.T, ca.solve(ca.mtimes(J, J.T) + PREDICTION_DAMPING**2 * ca.SX.eye(6), twist - ca.mtimes(J, dq))
    )


def tool_drift(q: ca.SX, J: ca.SX, velocity: ca.SX) -> ca.SX:
    """``J̇(q, q̇)q̇`` at ``q̇ = velocity`` (m/s², rad/s²; world-aligned, tool point): ``∂(J w)/∂q · w`` by
    forward mode with ``w`` held constant, then ``w = velocity`` (which may itself depend on ``q``)."""
    w = ca.SX.sym("w", J.shape[1])
    along = ca.Function("drift", [q, w], [ca.jtimes(ca.mtimes(J, w), q, w)])
    return along(q, velocity)


@njit(cache=True)
def state_views(flat, offsets):
    """The stacked state cut at ``offsets`` (:attr:`StateEvaluator.offsets`): ``(R, p, J, c, ∇c, ns, ∇ns,
    wrist_sin, elbow_offset, A, g, J̇q̇)``, arrays as views (column-major parts: F-ordered), scalars as floats."""
    o = offsets
    n = o[5] - o[4]
    R = flat[o[0] : o[1]].reshape((3, 3)).T
    J = flat[o[2] : o[3]].reshape((n, 6)).T
    A = flat[o[8] : o[9]].reshape((n, n)).T
    return (
        R,
        flat[o[1] : o[2]],
        J,
        flat[o[3]],
        flat[o[4] : o[5]],
        flat[o[5]],
        flat[o[6] : o[7]],
        flat[o[7]],
        flat[o[7] + 1],
        A,
        flat[o[9] : o[10]],
        flat[o[10] : o[11]],
    )


@njit(cache=True)
def sanitize_state(flat, offsets):
    """Make a stacked state (:func:`qpnso.control.state.state_views`) safe to act on, in place; returns status
    bits.  A cost or cost gradient that is not finite (the tool Jacobian singular: Λ undefined) is set
    to 0 (``COST_UNDEFINED``: no cost step this tick); an arm angle or gradient that is not finite marks
    the arm angle singular (its sine measure set to 0: the elbow rows are dropped).  Anything else not
    finite (pose, J, A, g) is ``INTERNAL_ERROR``: the caller must not act on it."""
    o = offsets
    bits = 0
    for i in range(o[3], o[5]):
        if not math.isfinite(flat[i]):
            flat[o[3] : o[5]] = 0.0
            bits |= FLAG_COST_UNDEFINED
            break
    for i in range(o[5], o[8]):
        if not math.isfinite(flat[i]):
            flat[o[5] : o[8]] = 0.0  # wrist sine 0: singular
            break
    for i in range(o[0], o[3]):
        if not math.isfinite(flat[i]):
            return bits | FLAG_INTERNAL_ERROR
    for i in range(o[8], o[10]):
        if not math.isfinite(flat[i]):
            return bits | FLAG_INTERNAL_ERROR
    return bits
