"""The self-motion's own torque terms, compiled with Numba (docs/method.md §7.7): the null-space impedance's
gains bounded by the self-motion's inertia, and the compensation of the friction the self-motion meets.

**Gains from the self-motion's inertia.**  A torque ``Nᵀτ_null`` moves the arm by ``q̈ = A⁻¹Nᵀτ_null =
Z(ZᵀAZ)⁻¹Zᵀτ_null`` (``Z`` an orthonormal basis of ``ker J``), so along a self-motion of inertia ``m``
(kg·m², :func:`qpnso.linalg.selfmotion_inertia`) a joint impedance ``K`` (N·m/rad), ``D`` (N·m·s/rad) acts
as ``m ν̇ = −K x − D ν``.  The tick holds its torque over ``dt`` from the state measured at the tick's start;
with ``a = K dt²/m`` and ``b = D dt/m`` that loop is ``x⁺ = x + dt ν − ½dt(a x/dt + b ν)``,
``ν⁺ = ν − a x/dt − b ν``, whose poles are inside the unit circle if and only if ``a/2 < b < 2``: a damper
alone is deadbeat at ``D = m/dt``, rings (a pole on the negative axis) beyond and is unstable beyond
``2m/dt``; a spring's half-tick lag takes ``K dt/2`` of the damping.  :func:`impedance_gains` bounds both
from ``m`` every tick: ``D ≥ K·dt`` (at most half the damping lost to the lag) and ``D ≤ μ·m/dt`` (μ =
``ControllerConfig.nullspace_damping_margin``, 0.5: the damper's pole at ``1 − μ``), the stiffness cut to
``D/dt`` when the two meet (``ω_n dt ≤ √μ``).  ``joint_damping`` = 10 N·m·s/rad is 3.3 ``m/dt`` on the bare
LWR4+'s lightest self-motions (``m`` ≈ 0.003 kg·m² at 1 ms): unstable.

**Friction compensation of the self-motion** (:func:`selfmotion_friction`): ``τ_fc = f̂(N q̇)`` with ``f̂`` the
controller's smooth Coulomb model [M 23] (:func:`smooth_friction`) at the *measured* velocity's self-motion
part, added to the command without projection.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from qpnso.linalg import project_velocity


@njit(cache=True)
def smooth_friction(dq, tau_max, beta):
    """``τf = τmax·(2/π)·atan(β·q̇)`` (N·m) [M 23] at ``dq`` (rad/s), per joint (``tau_max`` N·m, ``beta``
    s/rad): the controller's friction model (:class:`qpnso.model.robot.JointFriction`)."""
    out = np.empty(dq.shape[0])
    for i in range(dq.shape[0]):
        out[i] = tau_max[i] * (2.0 / math.pi) * math.atan(beta[i] * dq[i])
    return out


@njit(cache=True)
def impedance_gains(stiffness, damping, damping_ratio, inertia, dt, margin):
    """``(K, D)`` (N·m/rad, N·m·s/rad) a tick applies to the self-motion of inertia ``inertia`` (kg·m²) for a
    strategy's ``stiffness`` K, ``damping`` and ``damping_ratio`` ζ: ``D = damping + 2ζ√(K·m)``, at least
    ``K·dt`` and at most ``margin·m/dt``; ``K`` at most ``D/dt`` (module docstring).  No inertia (0: the
    projector could not be formed): no impedance."""
    if not inertia > 0.0:
        return 0.0, 0.0
    d = damping + (2.0 * damping_ratio * math.sqrt(stiffness * inertia) if damping_ratio > 0.0 else 0.0)
    d = min(max(d, stiffness * dt), margin * inertia / dt)
    return min(stiffness, d / dt), d


@njit(cache=True)
def selfmotion_friction(J, W, LL, dq_meas, tau_max, beta, fraction):
    """``fraction·f̂(N q̇)`` (N·m): the controller's friction model (:func:`smooth_friction`) at the self-motion
    part ``N q̇`` of the measured ``dq_meas`` (rad/s; :func:`qpnso.linalg.project_velocity`, the factors of
    :func:`qpnso.linalg.nullspace_factors`).

    Added to the command *without* projection, which is what cancels the friction's push on the held tool:
    the plant's friction ``f(q̇)`` enters ``A q̈ = τ + Jᵀf_hand − f(q̇)``, and the tool's acceleration gets
    ``−J A⁻¹ f``, which the hand must hold with ``J̄ᵀf`` (``J̄ = A⁻¹JᵀΛ``); with ``τ_fc ≈ f`` un-projected that
    term is ``J A⁻¹(τ_fc − f) ≈ 0``, and in the null space the self-motion's friction is taken off too.  A
    projected ``Nᵀτ_fc`` would leave the tool's part, ``J A⁻¹ f``, whole (the hold protocol, ``qp``: 46 mm and 8.2 J
    projected, 8.3 mm and 0.13 J un-projected, 32 mm and 0.94 J without compensation).  The surgeon keeps the
    friction of the motion they cause ([M]): the velocity a tool force gives the arm is in the range of ``J̄``,
    where ``N q̇ = 0``.
    Where the plant's friction is below the model's, the difference drives the self-motion (``fraction`` < 1
    leaves a margin)."""
    return fraction * smooth_friction(project_velocity(J, W, LL, dq_meas), tau_max, beta)
