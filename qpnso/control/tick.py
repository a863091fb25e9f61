"""The control tick's arithmetic, compiled with Numba (docs/method.md §7).

Every tick, for every strategy, runs the same four steps on named records:

1. :func:`begin_tick` — from the arm's state (:mod:`qpnso.control.state`) and the memory
   (:mod:`qpnso.control.memory`): ``q`` checked, the elbow (arm angle, ROM_t, K(ns)), level 1
   ``J q̇ = v + K_p e − ½dt·J̇q̇`` and the joint bounds, written into the problem record
   (:mod:`qpnso.qp.problem`) and the report record (:func:`report_dtype`);
2. the strategy's level 2 (:mod:`qpnso.control.strategies`; the ``qp`` strategy's is the kernel
   :func:`qp_level2`);
3. the hierarchical QP solves the problem (:meth:`qpnso.qp.solver.HierarchicalQP.solve_problem`);
4. :func:`finish_tick` — the command ``q̇``, ``q_des = q + dt·q̇`` and ``τ = g(q) + Nᵀτ_null + τ_fc`` (the
   null-space impedance's gains bounded by the self-motion's inertia, the self-motion's friction compensated:
   :mod:`qpnso.control.selfmotion`) with its checks, into the command record (:func:`command_dtype`).

The small formulas are kernels of their own: :func:`pose_error`, :func:`level1_target`,
:func:`cost_step`, :func:`low_pass`, :func:`answer_bits`, :func:`finish_command`; the constraint rows (joint
limits, the elbow, the row kinds a controller is given) are :mod:`qpnso.control.rows`.
"""

from __future__ import annotations

import math
from typing import NamedTuple, get_type_hints

import numpy as np
from numba import njit

from qpnso.control.flags import (
    FLAG_ELBOW_DROPPED,
    FLAG_ELBOW_OUTSIDE_ROM,
    FLAG_ELBOW_SLACK,
    FLAG_INTERNAL_ERROR,
    FLAG_INTERVAL_STALE,
    FLAG_Q_OUT_OF_LIMITS,
    FLAG_QP_FAILED,
    FLAG_ROM_EMPTY,
    FLAG_TOOL_LIMITED,
    FLAG_TORQUE_SATURATED,
    PREDICTION_MISSED,
)
from qpnso.control.memory import (
    advance_reference,
    arm_angle_singular,
    elbow_advance,
    elbow_bounds,
    elbow_stiffness,
    interval_stale,
    memory_dtype,
    renew_interval,
)
from qpnso.control.params import params_dtype
from qpnso.control.rows.braking import braking_speed
from qpnso.control.rows.elbow import elbow_row
from qpnso.control.rows.joint_limits import acceleration_bounds, bounded_change, velocity_bounds
from qpnso.control.rows.kind import add_rows
from qpnso.control.rows.obstacles import keep_out_torque, obstacle_bits, obstacle_rows, soft_violation
from qpnso.control.selfmotion import impedance_gains, selfmotion_friction
from qpnso.control.state import sanitize_state, state_dtype
from qpnso.linalg import dot, matmul, nullspace_factors, nullspace_part, project_torque, selfmotion_inertia
from qpnso.qp.problem import SOLVED, STOPPED, problem_dtype, solution_dtype

LOG3_NEAR_PI = 0.75 * math.pi
"""rad: above this angle :func:`pose_error` takes the rotation's axis from its symmetric part (the
antisymmetric part, ``2 sin θ·a``, vanishes at π: from it, the rotation was off by 1.6e-9 at π − 1e-3;
from the symmetric part by 1e-15 from here to π, measured against ``pinocchio.exp3``)."""

(
    TICK_READY,
    TICK_NOT_FINITE,
    TICK_Q_REFUSED,
    TICK_STATE_NOT_FINITE,
    TICK_NEED_INTERVAL,
    TICK_TWIST_NOT_FINITE,
    TICK_TWIST_TOO_FAST,
) = range(7)
"""Codes of :func:`begin_tick`: the problem is ready; ``q`` has a NaN or an infinite entry, or is beyond
its limits by more than the accepted tolerance (nothing done: the caller raises); the state at ``q`` is not
finite (the caller stops the joints); the continuity interval is due and has no closed form (the memory
advanced: the caller renews it numerically, then calls :func:`begin_tick` again); the tool twist has a NaN
or an infinite entry, or is faster than the accepted tool speed (:func:`twist_status`; nothing done: the caller
raises)."""

TOOL_RESIDUAL_REPORTED = 1e-6
"""m/s and rad/s: a level-1 residual above this (joint bounds or a singular Jacobian stop
the tool's motion) is flagged ``TOOL_LIMITED``."""
ELBOW_SLACK_REPORTED = 1e-3
"""rad/s: an elbow row violated by more than this is flagged ``ELBOW_SLACK``.  A soft
row held by the cost is always violated by about (cost force)/(2·slack_weight) ≈ 1e-5."""
ELBOW_ROM_TOL = 1e-6
"""rad: an arm angle farther than this outside ROM_t is flagged ``ELBOW_OUTSIDE_ROM``."""


class Report(NamedTuple):
    """What a tick reports besides its command (:func:`begin_tick`), as Python reads it: status bits;
    ``dropped`` 1 when the arm angle is singular; the arm angle ``ns``, ROM_t and the continuity interval
    (rad, unwrapped along the run); K(ns) (N·m/rad); level 1's pose error (m, rad) and the cost [M 18]; the
    least clearance of a link capsule to an obstacle (m; inf: none) with the pair (capsule, obstacle; −1: none),
    and the keep-out rows' place among the soft rows (:mod:`qpnso.control.rows.obstacles`); then, from
    :func:`finish_tick`, the self-motion's inertia (kg·m²; 0: not formed) and the null-space stiffness
    (N·m/rad) and damping (N·m·s/rad) applied to it (:func:`qpnso.control.selfmotion.impedance_gains`)."""

    bits: int
    dropped: int
    ns: float
    rom_lo: float
    rom_hi: float
    iv_lo: float
    iv_hi: float
    stiffness: float
    e_pos: float
    e_rot: float
    cost: float
    clearance: float
    clear_capsule: int
    clear_obstacle: int
    obstacle_first: int
    obstacle_rows: int
    null_inertia: float
    null_stiffness: float
    null_damping: float


def report_dtype() -> np.dtype:
    """The record type of :class:`Report` (its fields, in order: ``Report._make(record.item())`` reads it)."""
    kinds = {int: np.int64, float: np.float64}
    return np.dtype([(name, kinds[kind]) for name, kind in get_type_hints(Report).items()])


def command_dtype(n: int) -> np.dtype:
    """A tick's command (:func:`finish_tick`): ``dq`` (rad/s), ``q_des`` (rad), ``tau`` (N·m); and the
    strategy's null-space impedance, which it writes before the QP is solved:
    ``τ_null = K·(offset + spring_cmd·dt·q̇_cmd) + D·(velocity + damp_cmd·q̇_cmd − q̇)`` with ``K`` the
    ``stiffness`` (N·m/rad), ``offset`` its set-point minus ``q`` (rad), ``D = damping + 2·damping_ratio·√(K·m)``
    (N·m·s/rad; ``m`` the self-motion's inertia), ``velocity`` the damper's target (rad/s), ``spring_cmd`` and
    ``damp_cmd`` 0 or 1; ``K`` and ``D`` bounded by :func:`qpnso.control.selfmotion.impedance_gains`."""
    f8 = np.float64
    vectors = [(name, f8, n) for name in ("dq", "q_des", "tau", "offset", "velocity")]
    scalars = [(name, f8) for name in ("stiffness", "spring_cmd", "damping", "damping_ratio", "damp_cmd")]
    return np.dtype(vectors + scalars)


def tick_dtype(
    n: int, rows: int = 0, hard: int = 0, soft: int = 0, points: int = 0, capsules: int = 0, obstacles: int = 0
) -> np.dtype:
    """The one record a tick reads and writes, for ``n`` joints and ``rows`` rows of row kinds (``hard`` of
    them hard, ``soft`` soft, keep-out rows among them; :mod:`qpnso.control.rows`), the collision capsules'
    ``points`` and ``capsules``, room for ``obstacles``: the arm's ``state``
    (:mod:`qpnso.control.state`, written by CasADi in place), the ``params`` (:mod:`qpnso.control.params`), the
    ``memory`` across ticks (:mod:`qpnso.control.memory`), the ``problem`` and its ``solution``
    (:mod:`qpnso.qp.problem`), the ``report`` and the ``command``."""
    return np.dtype(
        [
            ("state", state_dtype(n, rows, points)),
            ("params", params_dtype(n, rows, points, capsules, obstacles)),
            ("memory", memory_dtype(n)),
            ("problem", problem_dtype(n, hard, 1 + soft)),  # (+1: the elbow row)
            ("solution", solution_dtype(n)),
            ("report", report_dtype()),
            ("command", command_dtype(n)),
        ]
    )


@njit(cache=True)
def pose_error(R, p, R_ref, p_ref):
    """``e = (p_ref − p, log₃(R_ref Rᵀ))`` (6,), m then rad, world frame, as ``pinocchio.log3``: from the
    antisymmetric part of ``E = R_ref Rᵀ`` (``θ/(2 sin θ)``, its Taylor series near 0), or, above
    :data:`LOG3_NEAR_PI`, the axis from the symmetric part (:func:`log3_near_pi`)."""
    E = matmul(R_ref, R.T)
    e = np.empty(6)
    for i in range(3):
        e[i] = p_ref[i] - p[i]
    c = min(1.0, max(-1.0, 0.5 * (E[0, 0] + E[1, 1] + E[2, 2] - 1.0)))
    theta = math.acos(c)
    if theta > LOG3_NEAR_PI:
        sin = 0.5 * math.sqrt((E[2, 1] - E[1, 2]) ** 2 + (E[0, 2] - E[2, 0]) ** 2 + (E[1, 0] - E[0, 1]) ** 2)
        e[3:] = log3_near_pi(E, math.atan2(sin, c))  # (atan2: exact where acos is ill-conditioned)
        return e
    # θ/(2 sin θ), its Taylor series near 0 (relative error < 1e-17 below 1e-4 rad)
    half = 0.5 * (1.0 + theta * theta / 6.0) if theta < 1e-4 else 0.5 * theta / math.sin(theta)
    e[3] = half * (E[2, 1] - E[1, 2])
    e[4] = half * (E[0, 2] - E[2, 0])
    e[5] = half * (E[1, 0] - E[0, 1])
    return e


@njit(cache=True)
def log3_near_pi(E, theta):
    """``θ·a`` of a rotation ``E`` by ``θ`` near π: ``E = cos θ I + sin θ [a]× + (1 − cos θ) aaᵀ``, so
    ``a_i² = (E_ii − cos θ)/(1 − cos θ)`` for the largest, the others from ``E_ij + E_ji = 2(1 − cos θ)a_i a_j``,
    the sign from the antisymmetric part ``E_kj − E_jk = 2 sin θ a_i``."""
    c = math.cos(theta)
    i = 0
    for k in range(1, 3):
        if E[k, k] > E[i, i]:
            i = k
    j, k = (i + 1) % 3, (i + 2) % 3
    a = np.empty(3)
    a[i] = math.sqrt(max(E[i, i] - c, 0.0) / (1.0 - c))
    if E[k, j] - E[j, k] < 0.0:
        a[i] = -a[i]
    a[j] = (E[i, j] + E[j, i]) / (2.0 * (1.0 - c) * a[i])
    a[k] = (E[i, k] + E[k, i]) / (2.0 * (1.0 - c) * a[i])
    return theta * a / math.sqrt(dot(a, a))


@njit(cache=True)
def pose_correction(e, P):
    """Level 1's correction ``K_p·e`` (m/s, rad/s; world frame) of the pose error ``e`` (m, rad), its linear
    part scaled to at most ``P.pose_correction_speed`` m/s and its angular part to at most
    ``P.pose_correction_angular_speed`` rad/s: a tool knocked off its reference (a pull, a jump in the
    path, a joint slipped past its limit) comes back at a bounded speed, not with every joint at its
    velocity limit.  The caps bind only for errors above cap/K_p (0.5 mm at the defaults): a held tool's
    correction is unchanged.  Each part is also at most the speed from which the tool can stop on its reference
    at ``P.tool_braking`` (m/s², rad/s²; :func:`qpnso.control.rows.braking.braking_speed` of the error): K_p·e
    asks a deceleration of K_p times the speed (200 rad/s² at 1 rad/s), which joints changing speed by at most
    ``ddq_max·dt`` a tick cannot give — the orientation overshot, turned back and overshot again while the
    position error grew (the fuzz: 4 cm not closed after a 2 m/s pull)."""
    out = P.pose_gain * e
    for start, cap, braking in (
        (0, P.pose_correction_speed, P.tool_braking[0]),
        (3, P.pose_correction_angular_speed, P.tool_braking[1]),
    ):
        size = math.sqrt(e[start] ** 2 + e[start + 1] ** 2 + e[start + 2] ** 2)
        cap = min(cap, braking_speed(size, braking, P.dt))
        norm = math.sqrt(out[start] ** 2 + out[start + 1] ** 2 + out[start + 2] ** 2)
        if norm > cap:
            for i in range(start, start + 3):
                out[i] *= cap / norm
    return out


@njit(cache=True)
def level1_target(twist, e, P, drift):
    """Level 1's right-hand side ``v + K_p e − ½dt·J̇q̇`` (m/s, rad/s; world frame, tool point): the tool
    twist, the capped pose correction (:func:`pose_correction`) and the step's second-order term (``drift``
    J̇q̇ along the predicted command).  Over a tick at q̇ the tool moves by ``dt·J q̇ + ½dt²·J̇q̇``; with J̇q̇
    taken out, a null-space motion no longer drags a held tool (it did by about 1.2 µm·(|q̇|/(rad/s))²,
    8 µm and 2e-5 rad for elbow-up's returns in the fuzz), nor does a pull that stops
    (:func:`qpnso.control.state.predicted_velocity`)."""
    return twist + pose_correction(e, P) - P.half_dt * drift


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
def twist_status(twist, P):
    """:data:`TICK_READY` for a tool twist (m/s then rad/s) the arm can be asked to follow;
    :data:`TICK_TWIST_NOT_FINITE` for a NaN or inf entry; :data:`TICK_TWIST_TOO_FAST` for a linear speed above
    ``P.tool_speed_accepted`` m/s or an angular speed above ``P.tool_angular_speed_accepted`` rad/s (a twist in
    mm/s or deg/s, a runaway input: never chased at the joints' velocity limits)."""
    for i in range(6):
        if not math.isfinite(twist[i]):
            return TICK_TWIST_NOT_FINITE
    v = math.sqrt(twist[0] * twist[0] + twist[1] * twist[1] + twist[2] * twist[2])
    w = math.sqrt(twist[3] * twist[3] + twist[4] * twist[4] + twist[5] * twist[5])
    if v > P.tool_speed_accepted or w > P.tool_angular_speed_accepted:
        return TICK_TWIST_TOO_FAST
    return TICK_READY


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
def finish_command(q, c, gravity, P, r):
    """The last step of every tick, in place on the command record ``c`` (:func:`command_dtype`): ``dq``
    within ``±dq_max`` (a QP answer may exceed a bound by its feasibility tolerance; ``q_des`` follows), the
    torque saturated at the model's effort limits (``TORQUE_SATURATED``; a limit ≤ 0 means none given), an
    arm angle outside ROM_t flagged (``ELBOW_OUTSIDE_ROM``, unless ``r.dropped``), and a command that is not
    finite replaced by the stop command (dq 0, q_des = q, τ = ``gravity`` g(q), ``INTERNAL_ERROR``).
    ``P`` the params record, ``r`` the report.  Returns the bits."""
    dq, q_des, tau = c.dq, c.q_des, c.tau
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
        dq_max = P.dq_max[i]
        if abs(dq[i]) > dq_max:
            dq[i] = dq_max if dq[i] > 0.0 else -dq_max
            q_des[i] = q[i] + P.dt * dq[i]
    for i in range(tau.shape[0]):
        limit = P.tau_limit[i]
        if limit > 0.0 and abs(tau[i]) > limit:
            tau[i] = limit if tau[i] > 0.0 else -limit
            bits |= FLAG_TORQUE_SATURATED
    if not r.dropped and not (r.rom_lo - ELBOW_ROM_TOL <= r.ns <= r.rom_hi + ELBOW_ROM_TOL):
        bits |= FLAG_ELBOW_OUTSIDE_ROM
    return bits


@njit(cache=True)
def begin_tick(q, twist, tick, follow):
    """A tick up to its level 2, on the tick record (:func:`tick_dtype`) at ``q`` (rad) with the tool
    ``twist`` (m/s, rad/s): its state made safe, its memory advanced, level 1 and the bounds written into its
    problem (no level 2 yet) and its report; then, if ``follow``, the tool's reference advanced along the twist
    for the next tick (:func:`qpnso.control.memory.advance_reference`).

    In order: ``q`` checked (:data:`TICK_NOT_FINITE`, :data:`TICK_Q_REFUSED`; outside its limits but within
    the tolerance: ``Q_OUT_OF_LIMITS``), the twist (:data:`TICK_TWIST_NOT_FINITE`), the state
    (:data:`TICK_STATE_NOT_FINITE`, the reference advanced all the same), the elbow — dropped when
    the arm angle is singular (``ELBOW_DROPPED``), else advanced — the continuity interval renewed when due
    (:func:`qpnso.control.memory.renew_interval`; :data:`TICK_NEED_INTERVAL` for an arm without its closed
    form) — and bounded (:func:`qpnso.control.memory.elbow_bounds`) — then level 1's
    error (:func:`pose_error`) and target (:func:`level1_target`) and the joint bounds
    (:func:`qpnso.control.rows.joint_limits.velocity_bounds`), and the rows of the controller's row kinds
    (:func:`qpnso.control.rows.kind.add_rows`).  Returns :data:`TICK_READY` or why not."""
    t = tick[0]
    s, P, m, pb, r = t.state, t.params, t.memory, t.problem, t.report
    limit = limits_status(q, P.q_check_lo, P.q_check_hi)
    if limit == 2:
        return TICK_NOT_FINITE
    if limit == 1 and limits_status(q, P.q_accept_lo, P.q_accept_hi):
        return TICK_Q_REFUSED
    code = twist_status(twist, P)
    if code != TICK_READY:
        return code
    m.dq_prev[:] = t.command.dq  # (the last tick's command: this one's changes by at most ddq_max·dt)
    bits = sanitize_state(s) | (FLAG_Q_OUT_OF_LIMITS if limit == 1 else 0)
    r.bits = bits
    if bits & FLAG_INTERNAL_ERROR:
        if follow:
            advance_reference(m, twist, P.dt)
        return TICK_STATE_NOT_FINITE
    if arm_angle_singular(s, P):
        ns = m.ns
        r.dropped, r.ns, r.rom_lo, r.rom_hi = 1, ns, ns, ns
        r.iv_lo, r.iv_hi, r.stiffness = ns - math.pi, ns + math.pi, elbow_stiffness(ns, m, P)
        bits |= FLAG_ELBOW_DROPPED
    else:
        if m.advanced == 0.0 and elbow_advance(s, m, P):
            if P.closed_form_interval == 0.0:  # (no closed form: the caller renews it, numerically)
                m.advanced = 1.0
                return TICK_NEED_INTERVAL
            renew_interval(q, limit == 0, s, m, P)
        m.advanced = 0.0
        r.dropped, r.ns = 0, m.ns
        r.rom_lo, r.rom_hi, empty, r.iv_lo, r.iv_hi, r.stiffness = elbow_bounds(m, P)
        if empty:
            bits |= FLAG_ROM_EMPTY
        if interval_stale(m):
            bits |= FLAG_INTERVAL_STALE
    e = pose_error(s.R, s.p, m.ref_R, m.ref_p)  # level 1: J q̇ = twist + K_p e − ½dt J̇q̇
    r.e_pos = math.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
    r.e_rot = math.sqrt(e[3] * e[3] + e[4] * e[4] + e[5] * e[5])
    r.cost, r.bits = s.cost, bits
    pb.A1[:] = s.J
    pb.b1[:] = level1_target(twist, e, P, s.drift)
    pb.lb[:], pb.ub[:] = velocity_bounds(q, P)
    acceleration_bounds(pb.lb, pb.ub, m.dq_prev, q, P)
    pb.has_level2, pb.n_hard, pb.n_soft = 0, 0, 0
    add_rows(pb, s, P)  # the row kinds' rows (qpnso.control.rows)
    obstacle_rows(pb, s, P, r, m)  # the keep-out rows (qpnso.control.rows.obstacles)
    if follow:
        advance_reference(m, twist, P.dt)  # (after level 1 read it: the next tick's reference)
    return TICK_READY


@njit(cache=True)
def stop_tick(q, gravity, tick):
    """The stop command of a tick that could not be computed, into the tick record's command: dq 0,
    q_des = q, τ = ``gravity`` (g(q); saturated, zero where not finite: :func:`finish_command`); its report at
    the memory's arm angle with the elbow dropped.  Returns the bits, ``QP_FAILED`` among them."""
    t = tick[0]
    P, m, r, c = t.params, t.memory, t.report, t.command
    ns = m.ns
    r.ns, r.rom_lo, r.rom_hi, r.iv_lo, r.iv_hi = ns, ns, ns, ns - math.pi, ns + math.pi
    r.stiffness, r.e_pos, r.e_rot, r.cost, r.dropped = 0.0, 0.0, 0.0, 0.0, 1
    r.obstacle_rows = 0  # (the clearance: as begin_tick last found it)
    r.null_inertia, r.null_stiffness, r.null_damping = 0.0, 0.0, 0.0  # (no impedance)
    c.dq[:] = 0.0
    c.q_des[:] = q
    c.tau[:] = gravity
    bits = finish_command(q, c, gravity, P, r) | FLAG_QP_FAILED
    bounded_change(q, c, m.dq_prev, P)  # (slowing down at ddq_max from the last command, not a step to rest)
    return bits


@njit(cache=True)
def qp_level2(tick):
    """The ``qp`` strategy's level 2 (docs/method.md §7) into the tick record's problem: ``½‖q̇‖² + sᵀq̇``
    with ``s`` the cost step (:func:`cost_step`) low-passed in its memory, and — unless the elbow is
    dropped — the elbow row (:func:`qpnso.control.rows.elbow.elbow_row`), soft; and its null-space impedance
    ``τ_null = K(ns)·dt·q̇_cmd + D(q̇_cmd − q̇)`` (D = ``joint_damping``) into its command's torque law."""
    t = tick[0]
    s, P, m, r, pb, c = t.state, t.params, t.memory, t.report, t.problem, t.command
    c.offset[:] = 0.0
    c.velocity[:] = 0.0
    c.stiffness, c.spring_cmd, c.damping, c.damping_ratio, c.damp_cmd = r.stiffness, 1.0, P.joint_damping, 0.0, 1.0
    m.cost_step[:] = low_pass(
        m.cost_step, cost_step(s.J, s.cost_gradient, P.cost_gain, P.nullspace_speed_max), P.cost_filter_alpha
    )
    pb.has_level2, pb.m2, pb.use_H2, pb.use_g2 = 1, 0, 1, 1  # (H2 is the identity: new_problem)
    pb.g2[:] = m.cost_step
    if not r.dropped:
        elbow_row(pb, s, r, P)


@njit(cache=True)
def prediction_missed(dq, predicted, tolerance):
    """Whether a joint of the solved ``dq`` is farther than ``tolerance`` (rad/s; the tick's
    :func:`~qpnso.control.state.prediction_tolerance`) from the ``predicted`` velocity level 1's second-order
    term was taken along (no temporary array: every tick asks)."""
    for i in range(dq.shape[0]):
        if abs(dq[i] - predicted[i]) > tolerance:
            return True
    return False


@njit(cache=True)
def command_torque(dq_meas, t):
    """The command's torque ``τ = g(q) + Nᵀτ_null + τ_fc`` (N·m) into the tick record ``t``'s command, from one
    factorisation of the null space (:func:`qpnso.linalg.nullspace_factors`): the self-motion's inertia ``m``
    (:func:`qpnso.linalg.selfmotion_inertia`), the strategy's impedance with its gains bounded by ``m``
    (:func:`qpnso.control.selfmotion.impedance_gains`; the law of :func:`command_dtype`, against the
    measured ``dq_meas``, rad/s) and the keep-out rows' wall, projected with the dynamically consistent ``Nᵀ``
    (:func:`qpnso.linalg.project_torque`), and the self-motion's friction compensated, un-projected
    (:func:`qpnso.control.selfmotion.selfmotion_friction`; ``P.friction_compensation`` 0: none).  ``m``, ``K``
    and ``D`` into the report.  When the factorisation fails, ``τ = g(q)`` alone (an unprojected torque would
    push the tool)."""
    s, P, r, c = t.state, t.params, t.report, t.command
    dq = c.dq
    LA, W, LL, ok = nullspace_factors(s.A, s.J)
    inertia = selfmotion_inertia(LA, W, LL) if ok else 0.0
    K, D = impedance_gains(c.stiffness, c.damping, c.damping_ratio, inertia, P.dt, P.nullspace_damping_margin)
    r.null_inertia, r.null_stiffness, r.null_damping = inertia, K, D
    if not ok:
        c.tau[:] = s.g
        return
    tau_null = K * (c.offset + (c.spring_cmd * P.dt) * dq) + D * (c.velocity + c.damp_cmd * dq - dq_meas)
    keep_out_torque(t.problem, r, P, t.memory, dq_meas, tau_null)  # (the keep-out rows' wall: every strategy)
    tau = s.g + project_torque(s.J, W, LL, tau_null)
    if P.friction_compensation > 0.0:
        tau += selfmotion_friction(s.J, W, LL, dq_meas, P.friction_tau_max, P.friction_beta, P.friction_compensation)
    c.tau[:] = tau


@njit(cache=True)
def finish_tick(q, dq_meas, tick):
    """A tick after its QP, on the tick record: its solution's ``q̇`` (or the safe one the solver left after a
    failure), ``q_des = q + dt·q̇`` and ``τ = g(q) + Nᵀτ_null + τ_fc`` (:func:`command_torque`, against the
    measured ``dq_meas``), written into its command; then every tick's last step (:func:`finish_command`).
    Returns the status bits: the report's, :func:`answer_bits` of a solved QP and the finishing ones, and
    :data:`~qpnso.control.flags.PREDICTION_MISSED` (internal) when the solved ``q̇`` of a tool that is not limited
    is farther than :func:`~qpnso.control.state.prediction_tolerance` from the one level 1's second-order term
    was taken along (a limited tool is off its reference anyway)."""
    t = tick[0]
    s, P, S, r, c, pb = t.state, t.params, t.solution, t.report, t.command, t.problem
    dq = c.dq
    dq[:] = S.x
    if S.outcome != STOPPED:  # (an answer within the feasibility tolerance: exactly within the bounds)
        for i in range(dq.shape[0]):
            dq[i] = min(max(dq[i], pb.lb[i]), pb.ub[i])
    c.q_des[:] = q + P.dt * dq
    bounded_change(q, c, t.memory.dq_prev, P)  # (a stopped QP's zero: reached at ddq_max)
    command_torque(dq_meas, t)
    bits = r.bits
    if S.outcome == SOLVED:
        bits |= answer_bits(S.tool_residual, soft_violation(t.problem, dq, r.obstacle_first, r.obstacle_rows))
        if not bits & FLAG_TOOL_LIMITED and prediction_missed(S.x, s.predicted, P.prediction_tolerance):
            bits |= PREDICTION_MISSED
    bits |= obstacle_bits(pb, dq, r, P) | finish_command(q, c, s.g, P, r)
    bounded_change(q, c, t.memory.dq_prev, P)  # (a command replaced by the stop command: reached at ddq_max)
    return bits
