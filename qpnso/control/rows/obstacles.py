"""Keep-out rows: every link capsule kept at least the margin ``d_s`` from every obstacle (docs/method.md §10).

A capsule–obstacle pair nearer than the influence distance ``d_i`` gives the velocity damper
``ḋ ≥ −ξ (d − d_s)/(d_i − d_s)`` on its distance ``d`` (the damper of :mod:`qpnso.control.rows.damper`, gain
ξ/(d_i − d_s); inside the margin back out at most at the recovery speed and at least at :data:`EXIT_SPEED`:
:func:`keep_out_bound`).  ``ḋ`` is the relative velocity: with the obstacle moving, ``ḋ = ∇d·q̇ − n·v_ob``, so
the row is ``∇d·q̇ ≥ damper + n·v_ob``, ``n·v_ob`` how fast the obstacle's surface comes toward the link along
the normal (from its velocity and angular velocity in the keep-out record,
:func:`qpnso.elbow.clearance.obstacle_approach`; 0 for a still one).  Without that term a volume moving at
``v`` toward the arm held the link up to ``v/gain`` inside the margin (24 mm at 10 cm/s, measured).
``∇d = nᵀ((1 − t) J_a + t J_b)`` is the distance's exact gradient: ``n`` the unit normal from the obstacle,
``t`` the witness on the capsule's axis ``a + t(b − a)`` (a point of one link: its Jacobian is the ends'
blend), ``J_a``, ``J_b`` the ends' Jacobians from the tick's state.  The rows are level 2's (the tool's null
space: level 1 keeps the tool), beside the elbow rows, with a slack weight
:attr:`~qpnso.control.config.ControllerConfig.obstacle_weight_ratio` times theirs (the row scaled by its
square root): above the mass/friction cost and the elbow.  Every tick with a link inside its margin (or
overlapping an obstacle) says ``OBSTACLE``, whatever the cause, and so does one whose row the answer breaks
(the tool's or the obstacle's motion leaves the null space no way to keep it) (:func:`obstacle_bits`); the
report has the least clearance and its pair.
"""

from __future__ import annotations

import math

from numba import njit

from qpnso.control.flags import FLAG_OBSTACLE
from qpnso.control.memory import KEEP_OUT_ROWS
from qpnso.control.rows.damper import damper
from qpnso.elbow.clearance import motion_tick, obstacle_approach, pair_distance
from qpnso.linalg import dot

OBSTACLE_SLACK_REPORTED = 1e-4
"""m/s: a keep-out row violated by more than this (the null space cannot keep it) is flagged ``OBSTACLE``."""
EXIT_SPEED = 0.005
"""m/s: a link inside the margin is moved back out at least this fast (at most the recovery speed): the damper
alone, ``γ(d_s − d)``, only tends to the margin, and the link would stay inside it (and ``OBSTACLE``) for ever
by ever less; from 1 cm inside it is out in 0.75 s at the default gain (ours)."""


@njit(cache=True)
def obstacle_rows(pb, s, P, r, m):
    """Append the keep-out rows (module docstring) to the problem ``pb``'s soft rows, from the state ``s``
    (chain points and their Jacobians), the params ``P`` (``P.geo``, the keep-out record) and write the least
    clearance (m) and its pair, and where the rows are, into the report ``r``, each row's distance (m) into
    the memory ``m`` (``keep_out_d``, for :func:`keep_out_torque`); then one tick of the obstacles' velocities
    is spent (:func:`qpnso.elbow.clearance.motion_tick`).  With no room left, a more urgent pair
    takes the row of the least urgent (the row with the least lower bound: the farthest, or the one whose
    obstacle comes slowest)."""
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
            approach = obstacle_approach(G, s.points, c, o, t, n0, n1, n2)  # (m/s; 0: a still obstacle)
            lo = (keep_out_bound(d, G) + approach) * scale
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
    motion_tick(G)  # (this tick's rows took the obstacles' velocities)


@njit(cache=True)
def keep_out_bound(d, G):
    """m/s: the lower bound on ``ḋ`` of a pair ``d`` m apart, for a still obstacle: the damper
    ``−gain·(d − d_s)``, and inside the margin back out at least at :data:`EXIT_SPEED` and at most at the
    recovery speed (``G`` the keep-out record)."""
    lo = damper(d, G.margin, math.inf, G.gain, G.recovery_speed)[0]
    if d < G.margin:
        lo = max(lo, min(EXIT_SPEED, G.recovery_speed))
    return lo


@njit(cache=True)
def keep_out_torque(pb, r, P, m, dq_meas, tau_null):
    """Add to the null-space torque ``tau_null`` (N·m, in place) the keep-out rows' wall, ``f·∇d`` per row with
    ``f = D_ob·(l − ∇dᵀq̇)₊ + K_ob·(d_s − d)₊`` (N): a damper on a measured ``dq_meas`` (rad/s) that breaks the
    row (the link approaching faster than its damper allows; ``l`` the row's lower bound, the obstacle's own
    approach ``n·v_ob`` in it: the relative velocity) and a spring on a distance ``d`` (``m.keep_out_d``)
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
    """``OBSTACLE`` when a link is inside its margin of an obstacle this tick (the report's least clearance
    ``r.clearance`` < ``d_s``; negative: they overlap), whatever brought it there, or a keep-out row is violated
    at the answer ``x`` (rad/s) by more than :data:`OBSTACLE_SLACK_REPORTED` m/s (the tool's or the obstacle's
    motion leaves the null space no way to keep it); else 0."""
    if r.clearance < P.geo.margin:
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
