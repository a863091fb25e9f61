"""The arm angle within ROM_t as a velocity row (docs/method.md §7.2, [E 10], [E 11]): its value is the arm
angle unwrapped along the run (:mod:`qpnso.control.memory`), its gradient the exact ∂ns/∂q of the tick's
state, its bounds ROM_t of this tick; the ``qp`` strategy keeps it soft in level 2."""

from __future__ import annotations

from numba import njit

from qpnso.control.rows.damper import damper


@njit(cache=True)
def elbow_row(pb, s, r, P):
    """Append the elbow row ``damper(ns, ROM_t)`` ≤ ``∇nsᵀ q̇`` (rad/s) to the problem ``pb``'s soft rows,
    from the state ``s``, the report ``r`` (ns, ROM_t) and the params ``P`` (ξ = ``elbow_gain``, the
    recovery speed, the slack weight ρ)."""
    k = pb.n_soft
    pb.soft_C[k] = s.arm_angle_gradient
    pb.soft_l[k], pb.soft_u[k] = damper(r.ns, r.rom_lo, r.rom_hi, P.elbow_gain, P.recovery_speed)
    pb.n_soft, pb.slack_weight = k + 1, P.slack_weight
