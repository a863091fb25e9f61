"""Braking before a bound at the joints' acceleration bound (docs/method.md §7.2): the speed towards a joint limit or
a row's bound from which the arm can still stop in time, a command's change per tick being at most ``ddq_max·dt``."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from qpnso.linalg import dot, least_norm_line


@njit(cache=True)
def braking_speed(distance, ddq_max, dt):
    """The largest speed (rad/s) towards a limit ``distance`` rad away from which a joint slowed by ``h = a·dt``
    every tick (a = ``ddq_max``) stops before the limit: the larger of ``v`` with ``v(v + h)/(2a) = distance −
    h·dt/8`` and ``min(h, distance/dt)``.  From ``v = K·h`` the joint travels ``Σ_k (v − k·h)·dt = v(v + h)/(2a)``
    exactly; from a speed between two multiples, up to ``h·dt/8`` more (the last partial step), hence the margin;
    from ``v ≤ h`` it stops after one tick of ``v·dt``.  Viable: one tick at the first speed leaves
    ``braking_speed(distance − v·dt) ≥ v − h``, so slowing down at ``a`` always meets the next bound.
    ``ddq_max`` ≤ 0: none (inf); a joint at or past the limit: 0."""
    if ddq_max <= 0.0:
        return math.inf
    if distance <= 0.0:
        return 0.0
    h = ddq_max * dt
    one_tick = min(h, distance / dt)
    reach = distance - 0.125 * h * dt
    if reach <= 0.0:
        return one_tick
    half = 0.5 * h
    return max(math.sqrt(half * half + 2.0 * ddq_max * reach) - half, one_tick)


BRAKING_SHARE = 0.5
"""The share of an acceleration bound a row or the tool's pose correction brakes with (the self-motion's for a row,
the slowest joint's for the tool): the rest is left to the other motions and to the direction turning as the arm
moves (braking at the whole bound, a hard elbow
floor made the tool give way on 188 of 1500 ticks, by up to 1.3 mm; tests/test_rows.py)."""


@njit(cache=True)
def self_motion_acceleration(J, P):
    """``(d, s̈_max)``: the unit self-motion direction ``d`` (``J d = 0``, the tool's 6×7 Jacobian) and the largest
    rate (1/s²) at which the joints can change their speed along it, ``min_i ddq_max_i/|d_i|``: what a row can
    use to brake while the tool is held.  ``s̈_max`` 0 when ``J`` is singular (no single direction) or a joint
    has no acceleration bound (then rows are not braked)."""
    d = least_norm_line(J, np.zeros(J.shape[0]))[1]
    rate = math.inf
    for i in range(d.shape[0]):
        if P.ddq_max[i] <= 0.0:
            return d, 0.0
        if abs(d[i]) > 1e-12:
            rate = min(rate, P.ddq_max[i] / abs(d[i]))
    return d, rate if math.isfinite(rate) else 0.0


@njit(cache=True)
def row_braking(h, gradient, h_lo, h_hi, lo, hi, d, rate, dt):
    """A row's rate bounds ``(lo, hi)`` narrowed to the braking speed
    (:func:`~qpnso.control.rows.joint_limits.braking_speed`) of its distance to each bound, at the row's
    acceleration along the self-motion, :data:`BRAKING_SHARE` of ``|∇h·d|·s̈_max``
    (:func:`self_motion_acceleration`): a held tool's arm
    slows a row down only through its self-motion.  ``rate`` 0 or a row the self-motion does not move: unchanged."""
    a = BRAKING_SHARE * abs(dot(gradient, d)) * rate
    if a <= 0.0:
        return lo, hi
    return max(lo, -braking_speed(h - h_lo, a, dt)), min(hi, braking_speed(h_hi - h, a, dt))
