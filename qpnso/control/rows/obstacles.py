"""Keep-out rows: every link capsule kept at least the margin ``d_s`` from every obstacle (docs/method.md §10).

A capsule–obstacle pair nearer than the influence distance ``d_i`` gives the velocity damper
``ḋ ≥ −ξ (d − d_s)/(d_i − d_s)`` on its distance ``d`` (the damper of :mod:`qpnso.control.rows.damper`, gain
ξ/(d_i − d_s), back out of the margin at most at the recovery speed), with the distance's exact gradient
``∇d = nᵀ((1 − t) J_a + t J_b)``: ``n`` the unit normal from the obstacle, ``t`` the witness on the capsule's
axis ``a + t(b − a)`` (a point of one link: its Jacobian is the ends' blend), ``J_a``, ``J_b`` the ends'
Jacobians from the tick's state.  The rows are level 2's (the tool's null space: level 1 keeps the tool),
beside the elbow rows, with a slack weight :attr:`~qpnso.control.config.ControllerConfig.obstacle_weight_ratio`
times theirs (the row scaled by its square root): above the mass/friction cost and the elbow.  When the
tool's own motion leaves the null space no way to keep a row, its slack says so: ``OBSTACLE``
(:func:`obstacle_bits`), with the least clearance in the report.
"""

from __future__ import annotations

import math

from numba import njit

from qpnso.control.flags import FLAG_OBSTACLE
from qpnso.control.memory import KEEP_OUT_ROWS
from qpnso.control.rows.damper import damper
from qpnso.elbow.clearance import pair_distance
from qpnso.linalg import dot

OBSTACLE_SLACK_REPORTED = 1e-4
"""m/s: a keep-out row violated by more than this (the null space cannot keep it) is flagged ``OBSTACLE``."""


@njit(cache=True)
def obstacle_rows(pb, s, P, r, m):
    """Append the keep-out rows (module docstring) to the problem ``pb``'s soft rows, from the state ``s``
    (chain points and their Jacobians), the params ``P`` (``P.geo``, the keep-out record) and write the least
    clearance (m) and its pair, and where the rows are, into the report ``r``, each row's distance (m) into
    the memory ``m`` (``keep_out_d``, for :func:`keep_out_torque`).  With no room left, a nearer pair takes the
    row of the farthest (the row with the least lower bound)."""
    G = P.geo
    r.clearance, r.clear_capsule, r.clear_obstacle = math.inf, -1, -1
    r.obstacle_first, r.obstacle_rows = pb.n_soft, 0
    room = min(pb.soft_C.shape[0] - 1, pb.n_soft + KEEP_OUT_ROWS)  # (one row kept for the elbow, after these)
    scale = G.row_scale
    for o in range(G.n_obstacles):
        for c in range(G.n_capsules):
            d, t, n0, n1, n2 = pair_distance(G, s.points, c, o)
            if d < r.clearance:
                r.clearance, r.clear_capsule, r.clear_obstacle = d, c, o
            if d >= G.influence:
                continue
            lo = damper(d, G.margin, math.inf, G.gain, G.recovery_speed)[0] * scale
            k = pb.n_soft
            if k >= room:
                k = weakest_row(pb, r.obstacle_first, pb.n_soft)
                if pb.soft_l[k] >= lo:
                    continue
            else:
                pb.n_soft, r.obstacle_rows = k + 1, r.obstacle_rows + 1
            Ja, Jb = s.points_J[G.cap_a[c]], s.points_J[G.cap_b[c]]
            for j in range(pb.soft_C.shape[1]):
                pb.soft_C[k, j] = scale * (
                    n0 * ((1 - t) * Ja[0, j] + t * Jb[0, j])
                    + n1 * ((1 - t) * Ja[1, j] + t * Jb[1, j])
                    + n2 * ((1 - t) * Ja[2, j] + t * Jb[2, j])
                )
            pb.soft_l[k], pb.soft_u[k] = lo, math.inf
            m.keep_out_d[k - r.obstacle_first] = d
            pb.slack_weight = P.slack_weight


@njit(cache=True)
def keep_out_torque(pb, r, P, m, dq_meas, tau_null):
    """Add to the null-space torque ``tau_null`` (N·m, in place) the keep-out rows' wall, ``f·∇d`` per row with
    ``f = D_ob·(l − ∇dᵀq̇)₊ + K_ob·(d_s − d)₊`` (N): a damper on a measured ``dq_meas`` (rad/s) that breaks the
    row (the link approaching faster than its damper allows) and a spring on a distance ``d`` (``m.keep_out_d``)
    inside the margin (D_ob = ``P.geo.damping``, N·s/m; K_ob = ``P.geo.stiffness``, N/m; ∇d in m/rad).  A
    strategy whose torque law follows its QP command (``qp``) meets the rows already (the term is about 0);
    the baselines' laws (the papers') do not see the rows, and without it their arms went into a known obstacle
    in the hands-on simulation.  The tick's ``Nᵀ`` keeps it off the tool."""
    G = P.geo
    scale = G.row_scale
    for k in range(r.obstacle_first, r.obstacle_first + r.obstacle_rows):
        force = G.damping * max((pb.soft_l[k] - dot(pb.soft_C[k], dq_meas)) / scale, 0.0)
        force += G.stiffness * max(G.margin - m.keep_out_d[k - r.obstacle_first], 0.0)
        if force > 0.0:
            for j in range(dq_meas.shape[0]):
                tau_null[j] += force * pb.soft_C[k, j] / scale


@njit(cache=True)
def weakest_row(pb, first, end):
    """The keep-out row among soft rows ``first … end − 1`` with the least lower bound (the farthest pair)."""
    k = first
    for i in range(first + 1, end):
        if pb.soft_l[i] < pb.soft_l[k]:
            k = i
    return k


@njit(cache=True)
def obstacle_bits(pb, x, r, P):
    """``OBSTACLE`` when a keep-out row is violated at the answer ``x`` (rad/s) by more than
    :data:`OBSTACLE_SLACK_REPORTED` m/s, or a capsule overlaps an obstacle (negative clearance); else 0."""
    if r.clearance < 0.0:
        return FLAG_OBSTACLE
    scale = P.geo.row_scale
    for k in range(r.obstacle_first, r.obstacle_first + r.obstacle_rows):
        if (pb.soft_l[k] - dot(pb.soft_C[k], x)) / scale > OBSTACLE_SLACK_REPORTED:
            return FLAG_OBSTACLE
    return 0


@njit(cache=True)
def soft_violation(pb, x, skip_first, skip_count):
    """The largest violation of a soft row at ``x`` (rad/s; rows ``skip_first … +skip_count`` left out: the
    keep-out rows, judged by :func:`obstacle_bits`); −1 with none."""
    worst = -1.0
    for k in range(pb.n_soft):
        if skip_first <= k < skip_first + skip_count:
            continue
        v = dot(pb.soft_C[k], x)
        worst = max(worst, pb.soft_l[k] - v, v - pb.soft_u[k], 0.0)
    return worst
