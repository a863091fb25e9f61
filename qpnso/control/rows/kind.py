"""The contract of a constraint row kind (docs/method.md §7.2), and the kernel that puts every row of the
kinds a controller was given into the tick's problem.

A kind is a :class:`RowKind`: :meth:`RowKind.values` gives ``h(q)`` (m rows, a CasADi expression over the
symbolic model: its exact gradient is taken in the tick's one CasADi call, :mod:`qpnso.control.state`) and
:meth:`RowKind.bounds` the interval ``[h_lo, h_hi]`` it keeps ``h`` in.  Each tick, :func:`add_rows` turns
each row into ``∇h(q)ᵀ q̇`` within the velocity damper (:func:`~qpnso.control.rows.damper.damper`, gain
:attr:`RowKind.gain`): a hard row binds every level (the tool gives way: ``TOOL_LIMITED``) and the line fast
path folds it into its segment; a soft row is level 2's, with the elbow rows' slack weight.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import casadi as ca
import numpy as np
from numba import njit

from qpnso.control.rows.damper import damper
from qpnso.control.rows.joint_limits import braking_speed
from qpnso.linalg import dot, least_norm_line


@dataclass(frozen=True)
class RowKind:
    """A kind of constraint row ``h_lo ≤ h(q) ≤ h_hi`` (a subclass gives :meth:`values` and :meth:`bounds`).

    ``gain`` (1/s): the velocity damper's γ (γ·dt ≤ 1: h never crosses a bound); ``soft``: level 2's
    (with slack) instead of hard on every level."""

    gain: float = 20.0
    soft: bool = False

    @property
    def name(self) -> str:
        return type(self).__name__

    def values(self, model, robot) -> ca.SX:
        """``h(q)`` (m,): CasADi over ``model`` (:class:`qpnso.model.symbolic.SymbolicModel`, its ``q``)."""
        raise NotImplementedError

    def bounds(self, robot) -> tuple[np.ndarray, np.ndarray]:
        """``(h_lo, h_hi)`` (m,) each, ∓inf for an open side, in the units of :meth:`values`."""
        raise NotImplementedError


ROOM = 2
"""Rows of each kind (hard, soft) the tick's records hold at least: controllers with up to this many rows of
each share one record type, so Numba compiles the tick once for them (a new record type: ~60 s cold)."""


def row_counts(rows: Sequence[RowKind], robot) -> tuple[int, int, int, int]:
    """``(hard, soft, hard_room, soft_room)``: the rows of ``rows`` (hard, soft) and the room the records
    keep for them (at least :data:`ROOM` each)."""
    hard = sum(np.size(kind.bounds(robot)[0]) for kind in rows if not kind.soft)
    soft = sum(np.size(kind.bounds(robot)[0]) for kind in rows if kind.soft)
    return hard, soft, max(hard, ROOM), max(soft, ROOM)


ROW_BRAKING_SHARE = 0.5
"""The share of the self-motion's acceleration bound a row brakes with: the rest is left to the tool's own
changes of speed and to the row's direction turning as the arm moves (braking at the whole bound, a hard elbow
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
    acceleration along the self-motion, :data:`ROW_BRAKING_SHARE` of ``|∇h·d|·s̈_max``
    (:func:`self_motion_acceleration`): a held tool's arm
    slows a row down only through its self-motion.  ``rate`` 0 or a row the self-motion does not move: unchanged."""
    a = ROW_BRAKING_SHARE * abs(dot(gradient, d)) * rate
    if a <= 0.0:
        return lo, hi
    return max(lo, -braking_speed(h - h_lo, a, dt)), min(hi, braking_speed(h_hi - h, a, dt))


@njit(cache=True)
def add_rows(pb, s, P):
    """Every row of the controller's row kinds into the problem ``pb``: ``damper(h, h_lo, h_hi)`` ≤
    ``∇hᵀ q̇`` from the state ``s`` (``rows``, ``rows_gradient``) and the params ``P`` (``row_lo``,
    ``row_hi``, ``row_gain``, ``row_soft``, ``n_rows``; the recovery speed), hard rows after the problem's
    hard rows, soft ones after its soft rows.  Inside its bounds a row also approaches them no faster than it can
    stop at the joints' acceleration bound (:func:`row_braking`)."""
    if P.n_rows == 0:
        return
    d, rate = self_motion_acceleration(s.J, P)
    for i in range(P.n_rows):
        h, gradient = s.rows[i], s.rows_gradient[i]
        lo, hi = damper(h, P.row_lo[i], P.row_hi[i], P.row_gain[i], P.recovery_speed)
        if P.row_lo[i] <= h <= P.row_hi[i]:
            lo, hi = row_braking(h, gradient, P.row_lo[i], P.row_hi[i], lo, hi, d, rate, P.dt)
        if P.row_soft[i]:
            k = pb.n_soft
            pb.soft_C[k], pb.soft_l[k], pb.soft_u[k] = gradient, lo, hi
            pb.n_soft, pb.slack_weight = k + 1, P.slack_weight
        else:
            k = pb.n_hard
            pb.hard_C[k], pb.hard_l[k], pb.hard_u[k] = gradient, lo, hi
            pb.n_hard = k + 1
