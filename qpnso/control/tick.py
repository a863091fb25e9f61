"""The control tick's arithmetic, compiled with Numba (docs/method.md §7).

Every per-tick formula of :mod:`qpnso.control.controller` and of the ``qp`` strategy
(:mod:`qpnso.control.strategies`) between the CasADi state and the QP is a small
kernel here, and the general Python path calls these same kernels one by one:

* :func:`pose_error` — level 1's error ``(p_ref − p, log₃(R_ref Rᵀ))`` (m, rad; world frame);
* :func:`velocity_bounds` — joint velocity limits with the position damper;
* :func:`cost_step` / :func:`low_pass` — the ``qp`` strategy's saturated, filtered cost step;
* :func:`qp_nullspace_torque` — its null-space impedance torque;
* the elbow's memory across ticks is :mod:`qpnso.control.elbow_memory` (unwrapped arm angle, the cached
  continuity interval's age, ROM_t and the stiffness K(ns)).

For the ``qp`` strategy with the hierarchical QP's line fast path
(:mod:`qpnso.qp.line`, module doc), :func:`qp_tick` composes them with the line
kernels into one call, from the stacked CasADi state (read in place) to the
level-2 line QP, and :func:`qp_tick_answer` judges the QP's answer and forms
the command and torque.  Python then only calls CasADi and ProxSuite (and the
continuity interval when it is due): the controller's *compiled tick*
(``ControllerConfig.compiled_tick``).  Its answers equal the general path's to
round-off (tests/test_tick.py).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from qpnso.control.elbow_memory import (
    NS,
    P_MOVED_TOL,
    P_PERIOD,
    arm_angle_singular,
    elbow_advance,
    elbow_bounds,
    interval_stale,
)
from qpnso.control.flags import (
    FLAG_ELBOW_OUTSIDE_ROM,
    FLAG_ELBOW_SLACK,
    FLAG_INTERNAL_ERROR,
    FLAG_INTERVAL_STALE,
    FLAG_Q_OUT_OF_LIMITS,
    FLAG_ROM_EMPTY,
    FLAG_TOOL_LIMITED,
    FLAG_TORQUE_SATURATED,
)
from qpnso.control.state import sanitize_state, state_views
from qpnso.linalg import dot, dynamically_consistent_projection, matmul, matvec, nullspace_part
from qpnso.qp.backends import qp_data_finite
from qpnso.qp.line import LINE_ANSWER_OK, LINE_OK, checked_line_answer, least_norm_point, line_qp_arrays, task_line

LOG3_MAX_ANGLE = math.pi - 1e-3
"""rad: :func:`pose_error` reports (``ok`` False) a rotation error closer to π than this, where
its axis is ill-conditioned; the caller then uses ``pinocchio.log3``."""

LINE_NO_POSE = 3
"""A code of :func:`qp_tick` besides those of :func:`qpnso.qp.line.task_line`: the rotation error is
too close to π for the kernel's log₃."""
TICK_NOT_FINITE = 4
"""A code of :func:`qp_tick`: ``q`` has a NaN or an infinite entry; nothing was done (the caller raises)."""
TICK_ELBOW_DROPPED = 5
"""A code of :func:`qp_tick`: the arm angle is singular; nothing was done (the general path drops the elbow)."""
TICK_STATE_NOT_FINITE = 7
"""A code of :func:`qp_tick`: the state at a finite ``q`` is not finite (:func:`sanitize_state`); nothing
was done (the caller stops the joints)."""
TICK_QP_NOT_FINITE = 8
"""A code of :func:`qp_tick`: the level-2 line QP is not finite; the elbow advanced, the general path goes on
(and refuses that QP)."""
TICK_Q_REFUSED = 9
"""A code of :func:`qp_tick`: ``q`` is beyond its limits by more than the accepted tolerance (rows 5, 6 of
``limits``); nothing was done (the caller raises :class:`~qpnso.errors.InputError`)."""
TICK_NEED_INTERVAL = 6
"""A code of :func:`qp_tick`: the elbow memory advanced and the continuity interval must be recomputed
(:func:`store_interval`), then :func:`qp_tick` called again with ``advance`` False."""


TOOL_RESIDUAL_REPORTED = 1e-6
"""m/s and rad/s: a level-1 residual above this (joint bounds or a singular Jacobian stop
the tool's motion) is flagged ``TOOL_LIMITED``."""
ELBOW_SLACK_REPORTED = 1e-3
"""rad/s: an elbow row violated by more than this is flagged ``ELBOW_SLACK``.  A soft
row held by the cost is always violated by about (cost force)/(2·slack_weight) ≈ 1e-5."""
ELBOW_ROM_TOL = 1e-6
"""rad: an arm angle farther than this outside ROM_t is flagged ``ELBOW_OUTSIDE_ROM``."""


@njit(cache=True)
def pose_error(R, p, R_ref, p_ref):
    """``(e, ok)``: ``e = (p_ref − p, log₃(R_ref Rᵀ))`` (6,), m then rad, world frame, as
    ``pinocchio.log3``; ``ok`` False when the angle exceeds :data:`LOG3_MAX_ANGLE` (``e`` then partial)."""
    E = matmul(R_ref, R.T)
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
def pose_correction(e, gains):
    """Level 1's correction ``K_p·e`` (m/s, rad/s; world frame) of the pose error ``e`` (m, rad), its linear
    part scaled to at most ``gains[8]`` m/s and its angular part to at most ``gains[9]`` rad/s
    (``ControllerConfig.pose_correction_speed``/``pose_correction_angular_speed``): a tool knocked off its
    reference (a pull, a jump in the path, a joint slipped past its limit) comes back at a bounded speed,
    not with every joint at its velocity limit.  The caps bind only for errors above cap/K_p (0.5 mm
    at the defaults): a held tool's correction is unchanged."""
    out = gains[0] * e
    for start, cap in ((0, gains[8]), (3, gains[9])):
        norm = math.sqrt(out[start] ** 2 + out[start + 1] ** 2 + out[start + 2] ** 2)
        if norm > cap:
            for i in range(start, start + 3):
                out[i] *= cap / norm
    return out


@njit(cache=True)
def level1_target(twist, e, gains, drift):
    """Level 1's right-hand side ``v + K_p e − ½dt·J̇q̇`` (m/s, rad/s; world frame, tool point): the tool
    twist, the capped pose correction (:func:`pose_correction`) and the step's second-order term (``drift``
    J̇q̇ along the predicted command, ``gains[10]`` = ½dt).  Over a tick at q̇ the tool moves by
    ``dt·J q̇ + ½dt²·J̇q̇``; with J̇q̇ taken out, a null-space motion no longer drags a held tool (it did by
    about 1.2 µm·(|q̇|/(rad/s))², 8 µm and 2e-5 rad for elbow-up's returns in the fuzz), nor does a pull
    that stops (:func:`qpnso.control.state.predicted_velocity`)."""
    return twist + pose_correction(e, gains) - gains[10] * drift


@njit(cache=True)
def limits_status(q, low, high):
    """0: ``q`` finite and within ``[low, high]``; 1: finite, some entry outside; 2: NaN or inf."""
    code = 0
    for i in range(q.shape[0]):
        if not math.isfinite(q[i]):
            return 2
        if q[i] < low[i] or q[i] > high[i]:
            code = 1
    return code


@njit(cache=True)
def velocity_bounds(q, q_min, q_max, dq_max, gain, recovery):
    """``(lb, ub)`` (rad/s): ``−γ(q − q_min) ≤ q̇ ≤ γ(q_max − q)`` clipped to ``±dq_max`` and
    ``ub ≥ lb`` (γ·dt ≤ 1: q never crosses a limit).  A joint outside a limit is pushed back at rate γ
    and moves at most at ``recovery`` rad/s (``ControllerConfig.recovery_speed``) either way, never at
    its velocity limit."""
    n = q.shape[0]
    lb, ub = np.empty(n), np.empty(n)
    for i in range(n):
        lo = min(max(gain * (q_min[i] - q[i]), -dq_max[i]), dq_max[i])
        hi = min(max(gain * (q_max[i] - q[i]), -dq_max[i]), dq_max[i])
        if q[i] < q_min[i]:  # outside: back at most at the recovery speed, and no faster the other way
            lo, hi = min(lo, recovery), min(hi, recovery)
        elif q[i] > q_max[i]:
            lo, hi = max(lo, -recovery), max(hi, -recovery)
        lb[i], ub[i] = lo, max(hi, lo)
    return lb, ub


@njit(cache=True)
def cost_step(J, cost_gradient, gain, speed_max):
    """The ``qp`` strategy's step ``k∇c`` (rad/s), scaled so that its part in ``ker J`` (what the
    null space can do) is at most ``speed_max`` rad/s (the saturation of [M 20])."""
    step = gain * cost_gradient
    free = nullspace_part(J, step)
    norm = math.sqrt(dot(free, free))
    if norm > speed_max:
        step *= speed_max / norm
    return step


@njit(cache=True)
def low_pass(previous, step, alpha):
    """First-order low-pass ``previous + α(step − previous)``; ``α ≤ 0``: no filter (``step``)."""
    if alpha <= 0.0:
        return step.copy()
    return previous + alpha * (step - previous)


@njit(cache=True)
def elbow_row_bounds(ns, rom_lo, rom_hi, gain, recovery):
    """``(l, u)`` (1,) of the elbow row ``ξ(ns_lo − ns) ≤ ∇nsᵀ q̇ ≤ ξ(ns_hi − ns)`` (rad/s): the velocity
    damper that keeps the arm angle in ROM_t, or brings it back at rate ξ but at most ``recovery``
    rad/s (a fast elbow return would drag the held tool: its second-order drift grows as q̇²)."""
    return np.array([min(gain * (rom_lo - ns), recovery)]), np.array([max(gain * (rom_hi - ns), -recovery)])


@njit(cache=True)
def answer_bits(tool_residual, slack_max):
    """Status bits of a solved tick: ``TOOL_LIMITED`` for level 1's residual (m/s, rad/s) above
    :data:`TOOL_RESIDUAL_REPORTED`, ``ELBOW_SLACK`` for an elbow row's slack (rad/s) above
    :data:`ELBOW_SLACK_REPORTED` (a negative value: nothing to report)."""
    bits = 0
    if tool_residual > TOOL_RESIDUAL_REPORTED:
        bits |= FLAG_TOOL_LIMITED
    if slack_max > ELBOW_SLACK_REPORTED:
        bits |= FLAG_ELBOW_SLACK
    return bits


@njit(cache=True)
def finish_command(q, dq, q_des, tau, gravity, tau_limit, dq_max, dt, ns, rom_lo, rom_hi, dropped):
    """The last step of every tick, in place: dq within ``±dq_max`` (a QP answer may exceed a bound by its
    feasibility tolerance; q_des follows), the torque saturated at the model's effort limits
    (``TORQUE_SATURATED``; a limit ≤ 0 means none given), an arm angle outside ROM_t flagged
    (``ELBOW_OUTSIDE_ROM``, unless the elbow is dropped), and a command that is not finite replaced
    by the stop command (dq 0, q_des = q, τ = g(q), ``INTERNAL_ERROR``).  Returns the bits."""
    bits = 0
    finite = True
    for i in range(dq.shape[0]):
        if not (math.isfinite(dq[i]) and math.isfinite(q_des[i]) and math.isfinite(tau[i])):
            finite = False
    if not finite:
        dq[:] = 0.0
        q_des[:] = q
        for i in range(tau.shape[0]):
            tau[i] = gravity[i] if math.isfinite(gravity[i]) else 0.0
        bits |= FLAG_INTERNAL_ERROR
    for i in range(dq.shape[0]):
        if abs(dq[i]) > dq_max[i]:
            dq[i] = dq_max[i] if dq[i] > 0.0 else -dq_max[i]
            q_des[i] = q[i] + dt * dq[i]
    for i in range(tau.shape[0]):
        limit = tau_limit[i]
        if limit > 0.0 and abs(tau[i]) > limit:
            tau[i] = limit if tau[i] > 0.0 else -limit
            bits |= FLAG_TORQUE_SATURATED
    if not dropped and not (rom_lo - ELBOW_ROM_TOL <= ns <= rom_hi + ELBOW_ROM_TOL):
        bits |= FLAG_ELBOW_OUTSIDE_ROM
    return bits


@njit(cache=True)
def qp_nullspace_torque(dq_cmd, dq_meas, stiffness, dt, damping):
    """The ``qp`` strategy's null-space impedance ``K(ns)·dt·q̇_cmd + D(q̇_cmd − q̇)`` (N·m)."""
    return stiffness * dt * dq_cmd + damping * (dq_cmd - dq_meas)


class LineTickBuffers:
    """The arrays :func:`qp_tick` writes, allocated once per controller (nothing is boxed
    per tick): ``step`` the cost step's filter state (rad/s, read and advanced), ``line`` (3, n)
    the rows ``x0``, ``d``, ``x1`` (rad/s), and the level-2 line QP ``H, g, C, l, u, box_l, box_u``
    (``v = [t; σ]``, one soft elbow row) in the shapes of :func:`qpnso.qp.line.line_qp_arrays`; and,
    read only, ``identity`` the Hessian of level 2's ``½‖q̇‖²``."""

    def __init__(self, step: np.ndarray) -> None:
        n = step.shape[0]
        self.step = step  # shared with the strategy's general path
        self.line = np.zeros((3, n))
        self.x0, self.d, self.x1 = self.line  # views
        self.H, self.g = np.zeros((2, 2)), np.zeros(2)
        self.C, self.l, self.u = np.zeros((1, 2)), np.zeros(1), np.zeros(1)
        self.box_l, self.box_u = np.zeros(2), np.zeros(2)
        self.identity = np.eye(n)

    def outputs(self) -> tuple:
        return self.step, self.line, self.H, self.g, self.C, self.l, self.u, self.box_l, self.box_u


@njit(cache=True)
def qp_torque(A, gravity, J, dq_cmd, dq_meas, stiffness, dt, damping):
    """``τ = g(q) + Nᵀ τ_null`` (N·m, docs/method.md §2, §7) with the ``qp`` strategy's impedance
    :func:`qp_nullspace_torque`; ``A`` read by its upper triangle."""
    tau_null = qp_nullspace_torque(dq_cmd, dq_meas, stiffness, dt, damping)
    return gravity + dynamically_consistent_projection(A, J, tau_null)[0]


@njit(cache=True)
def qp_command(flat, offsets, q, dq, dq_meas, stiffness, dt, damping):
    """The ``qp`` strategy's command for the velocity ``dq`` (rad/s): ``(q_des = q + dt·dq`` rad,
    ``τ`` N·m of :func:`qp_torque`), with A(q), g(q) and J from the stacked state ``flat``."""
    _, _, J, _, _, _, _, _, _, A, gravity, _ = state_views(flat, offsets)
    return q + dt * dq, qp_torque(A, gravity, J, dq, dq_meas, stiffness, dt, damping)


@njit(cache=True)
def qp_tick(
    q,
    flat,
    offsets,
    limits,
    R_ref,
    p_ref,
    twist,
    memory,
    ns0,
    elbow,
    advance,
    gains,
    qp_tol,
    identity,
    step,
    line,
    H,
    g,
    C,
    l,
    u,
    box_l,
    box_u,
):
    """The ``qp`` strategy's tick up to its level-2 QP, in one call: the compiled tick (module doc).

    ``flat`` the stacked CasADi state at ``q`` (:class:`qpnso.control.state.StateEvaluator`, cut at
    ``offsets``); ``limits`` (7, n) the rows q_low, q_high (``q`` as checked), q_min, q_max (rad),
    dq_max (rad/s), the accepted q_low, q_high (rad: beyond, :data:`TICK_Q_REFUSED`); ``memory``/``elbow``
    of :mod:`qpnso.control.elbow_memory` (its ``elbow_memory`` and ``elbow_parameters``); ``ns0`` the ROM
    centre (rad); ``advance`` False after :data:`TICK_NEED_INTERVAL` (the memory has advanced).
    ``gains`` = (pose gain K_p 1/s, joint-limit gain 1/s, cost gain, null-space speed max rad/s, filter α,
    elbow gain 1/s, slack scale 1/√(2ρ), recovery speed rad/s, pose correction's speed caps m/s and rad/s,
    ½dt s); ``qp_tol`` = (rank_tol, damping threshold, regularisation μ);
    ``identity`` (n, n) level 2's Hessian.

    In order: ``q`` checked (:data:`TICK_NOT_FINITE`), the arm angle's singularity
    (:data:`TICK_ELBOW_DROPPED`), the elbow (:mod:`qpnso.control.elbow_memory`), level 1's
    error (:func:`pose_error`; :data:`LINE_NO_POSE` near π), its line of exact solutions within the
    joint bounds (:func:`qpnso.qp.line.task_line`) and least-norm point ``x1`` (the safe fallback), the
    filtered cost step and the elbow row, and the level-2 line QP (:func:`qpnso.qp.line.line_qp_arrays`)
    written into the buffers of :class:`LineTickBuffers` (``step`` read and advanced).  Returns
    ``(code, ns, rom_lo, rom_hi, iv_lo, iv_hi, K, ‖e_p‖, ‖e_R‖, ‖J x1 − b1‖, cost, status bits)``;
    ``code`` is :data:`qpnso.qp.line.LINE_OK` when the line QP is ready; :data:`LINE_NO_POSE`,
    :data:`qpnso.qp.line.LINE_SINGULAR` or :data:`qpnso.qp.line.LINE_CUT` send the tick to the general path,
    the elbow advanced but no buffer written."""
    nothing = (0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0)
    limit = limits_status(q, limits[0], limits[1])
    if limit == 2:
        return (TICK_NOT_FINITE,) + nothing[1:]
    if limit == 1 and limits_status(q, limits[5], limits[6]):
        return (TICK_Q_REFUSED,) + nothing[1:]
    n = q.shape[0]
    unsafe = sanitize_state(flat, offsets)
    if unsafe & FLAG_INTERNAL_ERROR:
        return (TICK_STATE_NOT_FINITE,) + nothing[1:]
    R, p, J, cost, cost_gradient, ns_wrapped, ns_gradient, wrist_sin, elbow_offset, _, _, drift = state_views(
        flat, offsets
    )
    if arm_angle_singular(wrist_sin, elbow_offset, elbow):
        return (TICK_ELBOW_DROPPED,) + nothing[1:]
    if advance:
        _, recompute = elbow_advance(ns_wrapped, flat[:12], memory, elbow[P_PERIOD], elbow[P_MOVED_TOL])
        if recompute:
            return (TICK_NEED_INTERVAL,) + nothing[1:]
    ns = memory[NS]
    rom_lo, rom_hi, empty, iv_lo, iv_hi, k = elbow_bounds(ns, memory, ns0, elbow)
    bits = unsafe | (FLAG_Q_OUT_OF_LIMITS if limit == 1 else 0) | (FLAG_ROM_EMPTY if empty else 0)
    if interval_stale(memory):
        bits |= FLAG_INTERVAL_STALE
    e, ok = pose_error(R, p, R_ref, p_ref)  # level 1: J q̇ = twist + K_p e
    e_pos = math.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
    e_rot = math.sqrt(e[3] * e[3] + e[4] * e[4] + e[5] * e[5])
    if not ok:
        return LINE_NO_POSE, ns, rom_lo, rom_hi, iv_lo, iv_hi, k, e_pos, e_rot, 0.0, cost, bits
    b1 = level1_target(twist, e, gains, drift)
    rank_tol, damping, reg = qp_tol[0], qp_tol[1], qp_tol[2]
    lb, ub = velocity_bounds(q, limits[2], limits[3], limits[4], gains[1], gains[7])
    code, x0, d, t_lo, t_hi = task_line(J, b1, lb, ub, rank_tol, damping)
    if code != LINE_OK:
        return code, ns, rom_lo, rom_hi, iv_lo, iv_hi, k, e_pos, e_rot, 0.0, cost, bits
    x1 = least_norm_point(x0, d, t_lo, t_hi)  # level 1's answer, the safe fallback
    r = matvec(J, x1) - b1
    step[:] = low_pass(step, cost_step(J, cost_gradient, gains[2], gains[3]), gains[4])  # level 2
    lo, hi = elbow_row_bounds(ns, rom_lo, rom_hi, gains[5], gains[7])
    H[:], g[:], C[:], l[:], u[:], box_l[:], box_u[:], _ = line_qp_arrays(
        d,
        x0,
        t_lo,
        t_hi,
        np.zeros((0, n)),
        np.zeros(0),
        identity,
        step,
        ns_gradient.reshape(1, n),
        lo,
        hi,
        1,
        gains[6],
        reg,
        rank_tol,
        damping,
    )
    if not qp_data_finite(H, g, C, l, u, box_l, box_u):  # (a huge finite twist can overflow)
        return TICK_QP_NOT_FINITE, ns, rom_lo, rom_hi, iv_lo, iv_hi, k, e_pos, e_rot, 0.0, cost, bits
    line[0], line[1], line[2] = x0, d, x1
    return LINE_OK, ns, rom_lo, rom_hi, iv_lo, iv_hi, k, e_pos, e_rot, math.sqrt(dot(r, r)), cost, bits


@njit(cache=True)
def qp_tick_answer(
    v,
    line,
    box_l,
    box_u,
    C,
    l,
    u,
    feasibility_tol,
    flat,
    offsets,
    q,
    dq_meas,
    stiffness,
    dt,
    damping,
    residual,
    bits,
    tau_limit,
    dq_max,
    ns,
    rom_lo,
    rom_hi,
):
    """The compiled tick after its level-2 QP: the answer ``v = [t; σ]`` judged
    (:func:`qpnso.qp.line.checked_line_answer`), the command, and every tick's last step
    (:func:`finish_command`, g(q) from ``flat``).  Returns ``(code, dq rad/s, q_des rad, τ N·m, status
    bits)`` (``bits`` plus :func:`answer_bits` and the finishing bits); ``code`` ≠
    :data:`qpnso.qp.line.LINE_ANSWER_OK`: the answer is refused (the caller falls back), the arrays are then
    meaningless."""
    code, x, _, slack = checked_line_answer(v, line[1], line[0], box_l, box_u, C, l, u, 1, feasibility_tol)
    if code != LINE_ANSWER_OK:
        return code, x, x, x, bits
    q_des, tau = qp_command(flat, offsets, q, x, dq_meas, stiffness, dt, damping)
    bits |= answer_bits(residual, slack.max())
    bits |= finish_command(
        q, x, q_des, tau, flat[offsets[9] : offsets[10]], tau_limit, dq_max, dt, ns, rom_lo, rom_hi, False
    )
    return code, x, q_des, tau, bits
