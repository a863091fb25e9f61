"""The joint limits as the QP's bounds (docs/method.md §7.2): the damper on each joint angle, within the
joint's velocity limit."""

from __future__ import annotations

import numpy as np
from numba import njit

from qpnso.control.rows.damper import damper


@njit(cache=True)
def velocity_bounds(q, P):
    """``(lb, ub)`` (rad/s) on q̇: the damper (:func:`~qpnso.control.rows.damper.damper`) on each joint,
    ``γ(q_min − q) ≤ q̇ ≤ γ(q_max − q)`` (γ = ``P.joint_limit_gain``), clipped to ``±dq_max`` with ``ub ≥ lb``.
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
        dq_max = P.dq_max[i]
        lo, hi = min(max(lo, -dq_max), dq_max), min(max(hi, -dq_max), dq_max)
        lb[i], ub[i] = lo, max(hi, lo)
    return lb, ub
