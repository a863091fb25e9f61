"""The control tick's arithmetic, compiled with Numba (METHOD §7).

Every per-tick formula of :mod:`qpnso.controller` and of the ``qp`` strategy
(:mod:`qpnso.strategies`) between the CasADi state and the QP is a small
kernel here, and the general Python path calls these same kernels one by one:

* :func:`pose_error` — level 1's error ``(p_ref − p, log₃(R_ref Rᵀ))`` (m, rad; world frame);
* :func:`velocity_bounds` — joint velocity limits with the position damper;
* :func:`cost_step` / :func:`low_pass` — the ``qp`` strategy's saturated, filtered cost step;
* :func:`qp_nullspace_torque` — its null-space impedance torque.

For the ``qp`` strategy with the hierarchical QP's line fast path
(:mod:`qpnso.hqp`, module doc), :func:`qp_line_tick` composes them with the
line kernels into one call (state → level-2 line QP), and :func:`qp_torque`
forms the torque command.  Python then only calls CasADi, ProxSuite and Pinocchio: the
controller's *compiled tick* (``ControllerConfig.compiled_tick``).  Its answers
equal the general path's to round-off (tests/test_tick.py).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from qpnso.hqp import LINE_OK, least_norm_point, line_qp_arrays, task_line
from qpnso.linalg import dynamically_consistent_projection, nullspace_part

LOG3_MAX_ANGLE = math.pi - 1e-3
"""rad: :func:`pose_error` reports (``ok`` False) a rotation error closer to π than this, where
its axis is ill-conditioned; the caller then uses ``pinocchio.log3``."""

LINE_NO_POSE = 3
"""A code of :func:`qp_line_tick` besides those of :func:`qpnso.hqp.task_line`: the rotation error is
too close to π for the kernel's log₃."""


@njit(cache=True)
def pose_error(R, p, R_ref, p_ref):  # type: ignore[no-untyped-def]
    """``(e, ok)``: ``e = (p_ref − p, log₃(R_ref Rᵀ))`` (6,), m then rad, world frame, as
    ``pinocchio.log3``; ``ok`` False when the angle exceeds :data:`LOG3_MAX_ANGLE` (``e`` then partial)."""
    E = R_ref @ R.T
    e = np.empty(6)
    for i in range(3):
        e[i] = p_ref[i] - p[i]
    c = 0.5 * (E[0, 0] + E[1, 1] + E[2, 2] - 1.0)
    c = min(1.0, max(-1.0, c))
    theta = math.acos(c)
    if theta > LOG3_MAX_ANGLE:
        return e, False
    # θ/(2 sin θ), its Taylor series near 0 (relative error < 1e-17 below 1e-4 rad)
    half = 0.5 * (1.0 + theta * theta / 6.0) if theta < 1e-4 else 0.5 * theta / math.sin(theta)
    e[3] = half * (E[2, 1] - E[1, 2])
    e[4] = half * (E[0, 2] - E[2, 0])
    e[5] = half * (E[1, 0] - E[0, 1])
    return e, True


@njit(cache=True)
def limits_status(q, low, high):  # type: ignore[no-untyped-def]
    """0: ``q`` finite and within ``[low, high]``; 1: finite, some entry outside; 2: NaN or inf."""
    code = 0
    for i in range(q.shape[0]):
        if not math.isfinite(q[i]):
            return 2
        if q[i] < low[i] or q[i] > high[i]:
            code = 1
    return code


@njit(cache=True)
def max_abs_difference(a, b):  # type: ignore[no-untyped-def]
    """``max |a − b|`` over the entries of two vectors of the same length."""
    worst = 0.0
    for i in range(a.shape[0]):
        worst = max(worst, abs(a[i] - b[i]))
    return worst


@njit(cache=True)
def velocity_bounds(q, q_min, q_max, dq_max, gain):  # type: ignore[no-untyped-def]
    """``(lb, ub)`` (rad/s): ``−γ(q − q_min) ≤ q̇ ≤ γ(q_max − q)`` clipped to ``±dq_max`` and
    ``ub ≥ lb`` (γ·dt ≤ 1: q never crosses a limit; outside one, the rows push back at rate γ)."""
    n = q.shape[0]
    lb, ub = np.empty(n), np.empty(n)
    for i in range(n):
        lo = min(max(gain * (q_min[i] - q[i]), -dq_max[i]), dq_max[i])
        hi = min(max(gain * (q_max[i] - q[i]), -dq_max[i]), dq_max[i])
        lb[i], ub[i] = lo, max(hi, lo)
    return lb, ub


@njit(cache=True)
def cost_step(J, cost_gradient, gain, speed_max):  # type: ignore[no-untyped-def]
    """The ``qp`` strategy's step ``k∇c`` (rad/s), scaled so that its part in ``ker J`` (what the
    null space can do) is at most ``speed_max`` rad/s (the saturation of [M 21])."""
    step = gain * cost_gradient
    free = nullspace_part(J, step)
    norm = math.sqrt(free @ free)
    if norm > speed_max:
        step *= speed_max / norm
    return step


@njit(cache=True)
def low_pass(previous, step, alpha):  # type: ignore[no-untyped-def]
    """First-order low-pass ``previous + α(step − previous)``; ``α ≤ 0``: no filter (``step``)."""
    if alpha <= 0.0:
        return step.copy()
    return previous + alpha * (step - previous)


@njit(cache=True)
def elbow_row_bounds(ns, rom_lo, rom_hi, gain):  # type: ignore[no-untyped-def]
    """``(l, u)`` (1,) of the elbow row ``ξ(ns_lo − ns) ≤ ∇nsᵀ q̇ ≤ ξ(ns_hi − ns)`` (rad/s): the velocity
    damper that keeps the arm angle in ROM_t, or brings it back at rate ξ."""
    return np.array([gain * (rom_lo - ns)]), np.array([gain * (rom_hi - ns)])


@njit(cache=True)
def qp_nullspace_torque(dq_cmd, dq_meas, stiffness, dt, damping):  # type: ignore[no-untyped-def]
    """The ``qp`` strategy's null-space impedance ``K(ns)·dt·q̇_cmd + D(q̇_cmd − q̇)`` (N·m)."""
    return stiffness * dt * dq_cmd + damping * (dq_cmd - dq_meas)


class LineTickBuffers:
    """The arrays :func:`qp_line_tick` writes, allocated once per controller (nothing is boxed
    per tick): ``step`` the cost step's filter state (rad/s, read and advanced), ``line`` (3, n)
    the rows ``x0``, ``d``, ``x1`` (rad/s), and the level-2 line QP ``H, g, C, l, u, box_l, box_u``
    (``v = [t; σ]``, one soft elbow row) in the shapes of :func:`qpnso.hqp.line_qp_arrays`."""

    def __init__(self, step: np.ndarray) -> None:
        n = step.shape[0]
        self.step = step  # shared with the strategy's general path
        self.line = np.zeros((3, n))
        self.x0, self.d, self.x1 = self.line  # views
        self.H, self.g = np.zeros((2, 2)), np.zeros(2)
        self.C, self.l, self.u = np.zeros((1, 2)), np.zeros(1), np.zeros(1)
        self.box_l, self.box_u = np.zeros(2), np.zeros(2)

    def outputs(self) -> tuple:
        return self.step, self.line, self.H, self.g, self.C, self.l, self.u, self.box_l, self.box_u


@njit(cache=True)
def qp_line_tick(q, R, p, J, cost_gradient, arm_angle_gradient, R_ref, p_ref, twist, q_min, q_max, dq_max,
                 ns, rom_lo, rom_hi, gains, qp_tol,
                 step, line, H, g, C, l, u, box_l, box_u):  # type: ignore[no-untyped-def]
    """State → level-2 line QP of the ``qp`` strategy, in one call (module doc).

    ``gains`` = (pose gain 1/s, joint-limit gain 1/s, cost gain, null-space speed max rad/s,
    filter α, elbow gain 1/s, slack scale 1/√(2ρ)); ``qp_tol`` = (rank_tol, damping threshold,
    regularisation μ).  Writes the arrays of :class:`LineTickBuffers` (``step`` in and out) and
    returns ``(code, ‖e_p‖ m, ‖e_R‖ rad, ‖J x1 − b1‖)``: the pose error's norms and level 1's
    residual at its least-norm point ``x1`` (the safe fallback).  ``code`` ≠ :data:`LINE_OK`
    sends the tick to the general path; then nothing was written (``step`` not advanced)."""
    n = q.shape[0]
    e, ok = pose_error(R, p, R_ref, p_ref)
    e_pos = math.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
    e_rot = math.sqrt(e[3] * e[3] + e[4] * e[4] + e[5] * e[5])
    if not ok:
        return LINE_NO_POSE, e_pos, e_rot, 0.0
    b1 = twist + gains[0] * e
    rank_tol, damping, reg = qp_tol[0], qp_tol[1], qp_tol[2]
    lb, ub = velocity_bounds(q, q_min, q_max, dq_max, gains[1])
    code, x0, d, t_lo, t_hi = task_line(J, b1, lb, ub, rank_tol, damping)
    if code != LINE_OK:
        return code, e_pos, e_rot, 0.0
    x1 = least_norm_point(x0, d, t_lo, t_hi)
    r = J @ x1 - b1
    step[:] = low_pass(step, cost_step(J, cost_gradient, gains[2], gains[3]), gains[4])
    row = arm_angle_gradient.reshape(1, n).copy()
    lo, hi = elbow_row_bounds(ns, rom_lo, rom_hi, gains[5])
    empty, none = np.zeros(0), np.zeros((0, n))
    H[:], g[:], C[:], l[:], u[:], box_l[:], box_u[:], _ = line_qp_arrays(
        d, x0, t_lo, t_hi, none, empty, np.eye(n), step, row, lo, hi, 1, gains[6], reg, rank_tol, damping)
    line[0], line[1], line[2] = x0, d, x1
    return LINE_OK, e_pos, e_rot, math.sqrt(r @ r)


@njit(cache=True)
def qp_torque(A, gravity, J, dq_cmd, dq_meas, stiffness, dt, damping):  # type: ignore[no-untyped-def]
    """``τ = g(q) + Nᵀ τ_null`` (N·m, METHOD §2, §7) with the ``qp`` strategy's impedance
    :func:`qp_nullspace_torque`; ``A`` by its upper triangle (Pinocchio's ``crba``)."""
    tau_null = qp_nullspace_torque(dq_cmd, dq_meas, stiffness, dt, damping)
    return gravity + dynamically_consistent_projection(A, J, tau_null)[0]
