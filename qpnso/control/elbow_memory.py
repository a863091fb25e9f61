"""The elbow's memory across ticks (docs/method.md §5–6): one array that the tick's Numba kernels read and
advance — the arm angle unwrapped along the run, the cached continuity interval [E 9] with its age and the
tool pose it was computed at — and the kernels that turn it into ROM_t [E 10], [E 11] and the stiffness
K(ns) [E 6] each tick (:func:`elbow_advance`, :func:`elbow_bounds`)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from qpnso.elbow.rom import clipped_bounds, sigmoid_stiffness

TOOL_MOVED_TOL = 1e-6
"""m (position) and unitless (rotation-matrix entries ≈ rad): a tool pose change below this keeps the
cached continuity interval (its ends move by ~1e-6 rad at most, against a safety margin of degrees)."""
TWO_PI = 2.0 * math.pi


@njit(cache=True)
def max_abs_difference(a, b):
    """``max |a − b|`` over the entries of two vectors of the same length."""
    worst = 0.0
    for i in range(a.shape[0]):
        worst = max(worst, abs(a[i] - b[i]))
    return worst


# The elbow's state across ticks, one array (elbow_memory) that the kernels read and advance:
NS, IV_LO, IV_HI, IV_FULL, IV_KNOWN, IV_AGE, IV_POSE = 0, 1, 2, 3, 4, 5, 6
"""Indices: the last arm angle (rad, unwrapped along the run); the cached continuity interval (rad,
around that angle), full circle (1/0), known (1; 2: known but its renewal failed, stale; 0: none), its age
(ticks), and from IV_POSE the 12 entries
of the tool pose (:attr:`qpnso.control.state.TickState.pose`) it was computed at."""


def elbow_memory(ns: float) -> np.ndarray:
    """A fresh elbow memory at arm angle ``ns`` (rad): no interval known (computed at the first tick)."""
    memory = np.zeros(IV_POSE + 12)
    memory[NS] = ns
    memory[IV_AGE] = math.inf
    return memory


def interval_failed(memory: np.ndarray) -> None:
    """The continuity interval could not be computed: the one cached (or, before any, the full circle)
    stands, marked stale (``IV_KNOWN`` 2), and the next attempt comes ``period`` ticks later (a failing
    attempt costs about 1 ms: one per tick stalled every tick near a singularity)."""
    if memory[IV_KNOWN] != 0.0:
        memory[IV_KNOWN] = 2.0
    memory[IV_AGE] = 0.0


@njit(cache=True)
def interval_stale(memory):
    """Whether the elbow memory holds no continuity interval, or one whose renewal failed
    (:func:`interval_failed`): ``INTERVAL_STALE`` on every tick until a renewal succeeds."""
    return memory[IV_KNOWN] != 1.0


def store_interval(memory: np.ndarray, lo: float, hi: float, full_circle: bool, pose: np.ndarray) -> None:
    """Cache a continuity interval (rad) computed at the tool pose ``pose`` (12,); its age restarts."""
    memory[IV_LO], memory[IV_HI], memory[IV_FULL], memory[IV_KNOWN], memory[IV_AGE] = lo, hi, full_circle, 1.0, 0.0
    memory[IV_POSE:] = pose


P_HALF_WIDTH, P_MARGIN, P_K_MIN, P_K_MAX, P_ALPHA, P_D, P_WRIST_SIN_MIN, P_OFFSET_MIN, P_PERIOD, P_MOVED_TOL = range(10)
"""Indices of :func:`elbow_parameters`."""


def elbow_parameters(
    half_width: float,
    margin: float,
    k_min: float,
    k_max: float,
    alpha: float,
    d: float,
    wrist_sin_min: float,
    elbow_offset_min: float,
    period: int,
) -> np.ndarray:
    """The elbow kernels' constants in one array (indices ``P_*``): ROM half width Δns and safety
    margin d_sg (rad), stiffness K_min, K_max (N·m/rad), α (1/rad), d (rad) [E 6], the singularity
    thresholds (sine, m), the interval's update period (ticks) and :data:`TOOL_MOVED_TOL`."""
    return np.array(
        [half_width, margin, k_min, k_max, alpha, d, wrist_sin_min, elbow_offset_min, period, TOOL_MOVED_TOL]
    )


@njit(cache=True)
def arm_angle_singular(wrist_sin, elbow_offset, params):
    """Whether the arm angle is undefined this tick (wrist near the vertical through the shoulder,
    or a straight elbow): the elbow constraints are dropped."""
    return wrist_sin < params[P_WRIST_SIN_MIN] or elbow_offset < params[P_OFFSET_MIN]


@njit(cache=True)
def elbow_advance(ns_wrapped, pose, memory, period, moved_tol):
    """One tick of the elbow memory: the arm angle unwrapped along the run (rad), the interval aged.
    Returns ``(ns, recompute)``: whether the continuity interval must be recomputed (none known and the
    last attempt ``period`` ticks old, or the tool moved by more than ``moved_tol`` and the interval is
    ``period`` ticks old)."""
    ns = memory[NS] + (ns_wrapped - memory[NS] + math.pi) % TWO_PI - math.pi
    memory[NS] = ns
    memory[IV_AGE] += 1.0
    if memory[IV_KNOWN] == 0.0:
        return ns, memory[IV_AGE] >= period
    fresh = memory[IV_AGE] < period or max_abs_difference(pose, memory[IV_POSE:]) <= moved_tol
    return ns, not fresh


@njit(cache=True)
def elbow_bounds(ns, memory, ns0, params):
    """``(rom_lo, rom_hi, empty, iv_lo, iv_hi, K)`` at arm angle ``ns`` (rad): the cached continuity
    interval moved by whole turns to be expressed around ``ns`` (none known, or a full circle: the
    circle centred on ``ns``) [E 9], ROM_t clipped to it [E 10], [E 11] (:func:`qpnso.elbow.rom.clipped_bounds`)
    and the stiffness K(ns) [E 6] (N·m/rad)."""
    full = memory[IV_KNOWN] == 0.0 or memory[IV_FULL] != 0.0
    if full:
        lo, hi = ns - math.pi, ns + math.pi
    else:
        k = round((ns - 0.5 * (memory[IV_LO] + memory[IV_HI])) / TWO_PI)
        lo, hi = memory[IV_LO] + TWO_PI * k, memory[IV_HI] + TWO_PI * k
    rom_lo, rom_hi, empty = clipped_bounds(ns0, params[P_HALF_WIDTH], lo, hi, full, params[P_MARGIN])
    k = sigmoid_stiffness(ns, ns0, params[P_K_MIN], params[P_K_MAX], params[P_ALPHA], params[P_D])
    return rom_lo, rom_hi, empty, lo, hi, k
