"""What the control tick remembers across ticks, as one named record (docs/method.md §5–7), and the elbow
kernels that read and advance it: the arm angle unwrapped along the run, the cached continuity interval
[E 9] with its age and the tool pose it was computed at (:func:`elbow_advance`; renewed by
:func:`renew_interval`), ROM_t [E 10], [E 11] and
the stiffness K(ns) [E 6] (:func:`elbow_bounds`); also the ROM centre, the tool's reference pose (advanced
along the tool twist by :func:`advance_reference`) and the ``qp`` strategy's filtered cost step.
:func:`new_memory` is a run's start: ``Controller.reset`` makes a new one, so nothing survives a reset."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from qpnso.elbow.clearance import clear_interval
from qpnso.elbow.closed_form import SRS_OK, branch_signs, srs_interval
from qpnso.elbow.rom import clipped_bounds, sigmoid_stiffness
from qpnso.records import new_record

TWO_PI = 2.0 * math.pi

KEEP_OUT_ROWS = 16
"""Keep-out rows a tick holds at most (the nearest pairs within the influence distance;
:mod:`qpnso.control.rows.obstacles`): their distances are in the memory, and the problem has room for them."""

KNOWN_NONE, KNOWN, KNOWN_STALE = 0.0, 1.0, 2.0
"""``iv_known``: no continuity interval yet; one computed; one whose renewal failed (stale)."""


def memory_dtype(n: int) -> np.dtype:
    """The record type of :func:`new_memory` for ``n`` joints."""
    f8 = np.float64
    return np.dtype(
        [
            ("ns", f8),  # rad: the last arm angle, unwrapped along the run
            ("ns0", f8),  # rad: the ROM's centre
            ("iv_lo", f8),  # rad: the cached continuity interval, around the arm angle it was computed at
            ("iv_hi", f8),
            ("iv_full", f8),  # 1: it is the full circle
            ("iv_known", f8),  # KNOWN_NONE, KNOWN, KNOWN_STALE
            ("iv_age", f8),  # ticks since it was computed (or last attempted)
            ("iv_R", f8, (3, 3)),  # the tool pose it was computed at: rotation (world ← tool)
            ("iv_p", f8, 3),  # and position (m, world)
            ("advanced", f8),  # 1: this tick's elbow step is done (the interval was due, then renewed)
            ("ref_R", f8, (3, 3)),  # the tool's reference rotation (world ← tool)
            ("ref_p", f8, 3),  # and position (m, world)
            ("cost_step", f8, n),  # rad/s: the qp strategy's low-passed cost step
            ("dq_prev", f8, n),  # rad/s: the previous tick's command (zero after a reset: from rest)
            ("keep_out_d", f8, KEEP_OUT_ROWS),  # m: this tick's keep-out rows' distances (rows.obstacles)
        ]
    )


def new_memory(n: int, ns: float, ns0: float, R_ref: np.ndarray, p_ref: np.ndarray) -> np.ndarray:
    """A run's memory at arm angle ``ns`` (rad) with its ROM centred on ``ns0`` (rad) and the tool's
    reference pose ``R_ref``, ``p_ref`` (m): no interval known (computed at the first tick), the cost
    step at rest.  A 1-element record array."""
    memory = new_record(memory_dtype(n))
    m = memory[0]
    m["ns"], m["ns0"], m["iv_age"] = ns, ns0, math.inf
    m["ref_R"], m["ref_p"] = R_ref, p_ref
    return memory


@njit(cache=True)
def interval_failed(m):
    """The continuity interval could not be computed: the one cached in the memory record ``m`` (or, before
    any, the full circle) stands, marked stale, and the next attempt comes ``interval_period`` ticks later (a
    failing attempt costs about 1 ms in the numerical method: one per tick stalled every tick near a
    singularity)."""
    if m.iv_known != KNOWN_NONE:
        m.iv_known = KNOWN_STALE
    m.iv_age = 0.0


@njit(cache=True)
def store_interval(m, lo, hi, full_circle, R, p):
    """Cache a continuity interval (rad) computed at the tool pose ``R``, ``p`` (m) in the memory record ``m``;
    its age restarts."""
    m.iv_lo, m.iv_hi, m.iv_full, m.iv_known, m.iv_age = lo, hi, 1.0 if full_circle else 0.0, KNOWN, 0.0
    m.iv_R[:] = R
    m.iv_p[:] = p


@njit(cache=True)
def renew_interval(q, q_within, s, m, P):
    """The continuity interval [E 9] renewed in the memory record ``m`` at the state ``s`` (its tool pose, the
    memory's arm angle ``m.ns``) by the closed form (:func:`qpnso.elbow.closed_form.srs_interval`; the arm's
    geometry ``P.srs``), cut where a link would come within the margin of an obstacle
    (:func:`qpnso.elbow.clearance.clear_interval`, the keep-out record ``P.geo``) — or, when ``q`` (rad) is
    not ``q_within`` its limits, its branch is undefined (joint 2, 4 or 6 exactly 0) or the closed form has
    none, marked failed (:func:`interval_failed`)."""
    s2, s4, s6, defined = branch_signs(q)
    if q_within and defined:
        code, lo, hi, full, _, _, _ = srs_interval(P.srs, s.R, s.p, s2, s4, s6, m.ns, P.q_min, P.q_max)
        if code == SRS_OK:
            below, above = (math.inf, math.inf) if full else (m.ns - lo, hi - m.ns)
            below, above, lo_cut, hi_cut = clear_interval(P.geo, s.points, below, above)
            if lo_cut or hi_cut:
                lo, hi, full = m.ns - below, m.ns + above, False
            store_interval(m, lo, hi, full, s.R, s.p)
            return
    interval_failed(m)


@njit(cache=True)
def interval_stale(m):
    """Whether the memory record ``m`` holds no continuity interval, or one whose renewal failed
    (:func:`interval_failed`): ``INTERVAL_STALE`` on every tick until a renewal succeeds."""
    return m.iv_known != KNOWN


@njit(cache=True)
def pose_moved(m, R, p):
    """``max |Δ|`` over the entries of the tool pose ``R``, ``p`` against the one the interval was computed at."""
    worst = 0.0
    for i in range(3):
        worst = max(worst, abs(p[i] - m.iv_p[i]))
        for j in range(3):
            worst = max(worst, abs(R[i, j] - m.iv_R[i, j]))
    return worst


@njit(cache=True)
def arm_angle_singular(s, P):
    """Whether the arm angle of the state ``s`` is undefined (wrist near the vertical through the shoulder,
    or a straight elbow; thresholds in the params record ``P``): the elbow constraints are dropped."""
    return s.wrist_sin < P.wrist_sin_min or s.elbow_offset < P.elbow_offset_min


@njit(cache=True)
def elbow_advance(s, m, P):
    """One tick of the memory ``m`` at the state ``s``: the arm angle unwrapped along the run (rad), the
    interval aged.  Returns whether the continuity interval must be recomputed (none known and the last
    attempt ``interval_period`` ticks old, or the tool moved by more than ``tool_moved_tol`` and the
    interval is ``interval_period`` ticks old)."""
    m.ns = m.ns + (s.arm_angle - m.ns + math.pi) % TWO_PI - math.pi
    m.iv_age += 1.0
    if m.iv_known == KNOWN_NONE:
        return m.iv_age >= P.interval_period
    return not (m.iv_age < P.interval_period or pose_moved(m, s.R, s.p) <= P.tool_moved_tol)


@njit(cache=True)
def elbow_bounds(m, P):
    """``(rom_lo, rom_hi, empty, iv_lo, iv_hi, K)`` at the memory's arm angle (rad): the cached continuity
    interval moved by whole turns to be expressed around it (none known, or a full circle: the circle
    centred on it) [E 9], ROM_t clipped to it [E 10], [E 11] (:func:`qpnso.elbow.rom.clipped_bounds`) and
    the stiffness K(ns) [E 6] (N·m/rad)."""
    ns = m.ns
    full = m.iv_known == KNOWN_NONE or m.iv_full != 0.0
    if full:
        lo, hi = ns - math.pi, ns + math.pi
    else:
        k = round((ns - 0.5 * (m.iv_lo + m.iv_hi)) / TWO_PI)
        lo, hi = m.iv_lo + TWO_PI * k, m.iv_hi + TWO_PI * k
    rom_lo, rom_hi, empty = clipped_bounds(m.ns0, P.rom_half_width, lo, hi, full, P.safety_margin)
    return rom_lo, rom_hi, empty, lo, hi, elbow_stiffness(ns, m, P)


@njit(cache=True)
def elbow_stiffness(ns, m, P):
    """K(ns) [E 6] (N·m/rad) about the ROM centre (:func:`qpnso.elbow.rom.sigmoid_stiffness`)."""
    return sigmoid_stiffness(ns, m.ns0, P.stiffness_min, P.stiffness_max, P.stiffness_slope, P.stiffness_inflection)


@njit(cache=True)
def advance_reference(m, twist, dt):
    """The tool's reference pose in the memory record ``m`` moved along ``twist`` (m/s then rad/s, world frame)
    for one tick of ``dt`` s: ``p ← p + dt·v``, ``R ← exp(dt·ω) R`` (Rodrigues' formula, ``1 − cos θ`` as
    ``2 sin²(θ/2)``; a zero twist changes nothing)."""
    R, p = m.ref_R, m.ref_p
    for i in range(3):
        p[i] += dt * twist[i]
    wx, wy, wz = dt * twist[3], dt * twist[4], dt * twist[5]
    theta = math.sqrt(wx * wx + wy * wy + wz * wz)
    if theta == 0.0:
        return
    a = math.sin(theta) / theta
    h = math.sin(0.5 * theta) / theta
    b = 2.0 * h * h
    K = np.array([[0.0, -wz, wy], [wz, 0.0, -wx], [-wy, wx, 0.0]])
    E = np.eye(3)
    for i in range(3):
        for j in range(3):
            E[i, j] += a * K[i, j] + b * (K[i, 0] * K[0, j] + K[i, 1] * K[1, j] + K[i, 2] * K[2, j])
    old = R.copy()
    for i in range(3):
        for j in range(3):
            R[i, j] = E[i, 0] * old[0, j] + E[i, 1] * old[1, j] + E[i, 2] * old[2, j]
