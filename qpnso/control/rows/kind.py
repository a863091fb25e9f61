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

from dataclasses import dataclass
from typing import Sequence

import casadi as ca
import numpy as np
from numba import njit

from qpnso.control.rows.braking import row_braking, self_motion_acceleration
from qpnso.control.rows.damper import damper


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
