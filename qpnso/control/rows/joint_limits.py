"""The joint limits as the QP's bounds (docs/method.md §7.2): the damper on each joint angle, within the
joint's velocity limit and the speed from which it can still stop before the limit; and the bound on a
command's change from one tick to the next (the joint acceleration limit ``ddq_max``)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from qpnso.control.rows.braking import braking_speed
from qpnso.control.rows.damper import damper


@njit(cache=True)
def velocity_bounds(q, P):
    """``(lb, ub)`` (rad/s) on q̇: the damper (:func:`~qpnso.control.rows.damper.damper`) on each joint,
    ``γ(q_min − q) ≤ q̇ ≤ γ(q_max − q)`` (γ = ``P.joint_limit_gain``), no faster towards a limit than
    :func:`braking_speed` (``P.ddq_max``), clipped to ``±dq_max`` with ``ub ≥ lb``.
    A joint outside a limit is pushed back at rate γ and moves at most at ``P.recovery_speed`` rad/s
    either way (the damper caps the return; the joint's other side is capped here): never at its velocity
    limit."""
    n = q.shape[0]
    lb, ub = np.empty(n), np.empty(n)
    recovery = P.recovery_speed
    for i in range(n):
        lo, hi = damper(q[i], P.q_min[i], P.q_max[i], P.joint_limit_gain, recovery)
        if q[i] < P.q_min[i]:  # outside: no faster the other way either
            hi = min(hi, recovery)
        elif q[i] > P.q_max[i]:
            lo = max(lo, -recovery)
        else:  # inside: slow enough to stop before either limit at the acceleration bound
            hi = min(hi, braking_speed(P.q_max[i] - q[i], P.ddq_max[i], P.dt))
            lo = max(lo, -braking_speed(q[i] - P.q_min[i], P.ddq_max[i], P.dt))
        dq_max = P.dq_max[i]
        lo, hi = min(max(lo, -dq_max), dq_max), min(max(hi, -dq_max), dq_max)
        lb[i], ub[i] = lo, max(hi, lo)
    return lb, ub


@njit(cache=True)
def change_box(q, dq_prev, i, P):
    """``(lo, hi)`` (rad/s): the speeds joint ``i`` may take this tick, ``dq_prev ± ddq_max·dt`` around its previous
    command — widened to reach 0 at once when the joint is measured past a limit and moving out (an external
    push or an overshoot: the limit before the bound; it then stops moving out at once, and turns back at
    ``ddq_max``).  ``ddq_max`` ≤ 0: no bound (±inf)."""
    step = P.ddq_max[i] * P.dt
    if step <= 0.0:
        return -math.inf, math.inf
    lo, hi = dq_prev - step, dq_prev + step
    if q > P.q_max[i]:
        lo = min(lo, 0.0)
    elif q < P.q_min[i]:
        hi = max(hi, 0.0)
    return lo, hi


@njit(cache=True)
def acceleration_bounds(lb, ub, dq_prev, q, P):
    """The bounds ``lb ≤ q̇ ≤ ub`` (rad/s) narrowed, in place, to each joint's :func:`change_box` around the
    previous command: where they meet, their intersection; where they do not (a joint to be pushed back faster
    than it can change speed), the point of the box nearest them — the command's change is bounded first."""
    for i in range(lb.shape[0]):
        lo, hi = change_box(q[i], dq_prev[i], i, P)
        lb[i] = min(max(lb[i], lo), hi)
        ub[i] = max(min(ub[i], hi), lo)


@njit(cache=True)
def bounded_change(q, c, dq_prev, P):
    """The command record ``c``'s ``dq`` (rad/s) moved, in place, into each joint's :func:`change_box` and
    ``±dq_max``, ``q_des = q + dt·dq`` following: every command, a fallback's or a stop's too, changes each
    joint's speed by at most ``ddq_max·dt`` per tick (a stop then slows the joints down at ``ddq_max``), but for
    a joint past its limit stopping its way out.  Returns whether it moved an entry."""
    moved = False
    for i in range(q.shape[0]):
        lo, hi = change_box(q[i], dq_prev[i], i, P)
        v = min(max(c.dq[i], lo), hi)
        v = min(max(v, -P.dq_max[i]), P.dq_max[i])
        if v != c.dq[i]:
            c.dq[i] = v
            c.q_des[i] = q[i] + P.dt * v
            moved = True
    return moved
