"""The arm's clearance from the keep-out volumes, and the arm angles that keep it (docs/method.md §10).

The *keep-out record* (:func:`keep_out_record`) holds what the control tick's kernels need: the link
capsules (:mod:`qpnso.model.collision`), the obstacles (:mod:`qpnso.model.obstacles`) and the settings of
their rows (:class:`KeepOut`).  :func:`pair_distance` is a capsule's distance to an obstacle; the rows of
:mod:`qpnso.control.rows.obstacles` and the clearance reported every tick come from it.

Obstacle-aware arm-angle intervals (S-R-S arms).  With the tool pose held, the self-motion turns the upper
arm and the forearm rigidly about the shoulder–wrist axis (``R₀³(ψ) = R(u_sw, ψ − ns) R₀³(ns)``; joint 4 is
constant) and leaves the base and the hand where they are: a chain point of links 3–5 rotates about the
axis, every other chain point is fixed (checked for each arm when its record is built: :func:`point_motion`).
The clearance ``c(ψ)`` (the least distance of a moving capsule to an obstacle, minus the margin) is then
Lipschitz in ψ with constant ρ, the largest distance of a moving chain point from the axis.
:func:`next_crossing` follows ψ from a start with steps ``max(|c|/ρ, MIN_STEP_RAD)`` (*conservative
advancement*: no sign change of c lies within a step of ``|c|/ρ``) and bisects a sign change to
:data:`END_TOL_RAD`; only a margin violation narrower than :data:`MIN_STEP_RAD` (depth under
``ρ·MIN_STEP_RAD/2``, 0.2 mm on the LWR4+) can be stepped over.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pinocchio as pin
from numba import njit

from qpnso.model.collision import LinkCapsules
from qpnso.model.distance import segment_obstacle
from qpnso.model.obstacles import Obstacle, obstacle_arrays
from qpnso.model.robot import Robot
from qpnso.records import new_record

OBSTACLE_ROOM = 8
"""Obstacles a controller's records hold at least (more given: room for them, another record type)."""

TWO_PI = 2.0 * math.pi

MIN_STEP_RAD = 1e-3
"""rad: the smallest step of :func:`next_crossing`."""
END_TOL_RAD = 1e-7
"""rad: an obstacle end of an arm-angle interval is bisected to this."""
MOTION_TOL = 1e-6
"""m: a chain point is fixed (rotating) when it is within this of its predicted place at another arm angle
(the closed-form IK's round-off is far below)."""

OBSTACLE_END = -1000
"""End code of an interval ended by an obstacle: ``OBSTACLE_END − (100·capsule + obstacle)``."""


@dataclass(frozen=True)
class KeepOut:
    """The settings of the keep-out rows (from :class:`~qpnso.control.config.ControllerConfig`): ``margin`` d_s
    (m), ``influence`` d_i (m), ``speed`` ξ (m/s: the approach speed the damper allows at d_i), the largest
    ``recovery_speed`` (m/s) back out of the margin, the rows' slack weight relative to the elbow rows', and
    the ``damping`` (N·s/m) and ``stiffness`` (N/m) of the torque wall
    (:func:`qpnso.control.rows.obstacles.keep_out_torque`)."""

    margin: float = 0.03
    influence: float = 0.15
    speed: float = 0.5
    recovery_speed: float = 0.05
    weight_ratio: float = 100.0
    damping: float = 500.0
    stiffness: float = 1e4

    @classmethod
    def of(cls, config) -> "KeepOut":
        return cls(
            config.obstacle_margin,
            config.obstacle_influence,
            config.obstacle_speed,
            config.obstacle_recovery_speed,
            config.obstacle_weight_ratio,
            config.obstacle_damping,
            config.obstacle_stiffness,
        )


def keep_out_dtype(points: int, capsules: int, room: int) -> np.dtype:
    """The record type of :func:`keep_out_record`: ``points`` chain points, ``capsules``, room for ``room``
    obstacles."""
    f8, i8 = np.float64, np.int64
    k, c, o = max(points, 1), max(capsules, 1), max(room, 1)
    return np.dtype(
        [
            ("margin", f8),  # d_s (m)
            ("influence", f8),  # d_i (m)
            ("gain", f8),  # ξ/(d_i − d_s) (1/s)
            ("recovery_speed", f8),  # m/s
            ("row_scale", f8),  # √(weight ratio): the rows' scale in level 2 (slack weight × ratio)
            ("damping", f8),  # D_ob (N·s/m): the torque wall on a row the measured motion breaks
            ("stiffness", f8),  # K_ob (N/m): the torque wall on a link inside the margin
            ("n_capsules", i8),
            ("n_obstacles", i8),
            ("cap_a", i8, c),  # chain points of each capsule's ends
            ("cap_b", i8, c),
            ("cap_radius", f8, c),  # m
            ("cap_moves", f8, c),  # 1: an end turns with the arm angle
            ("pt_moves", f8, k),  # 1: the chain point turns about the shoulder–wrist axis with the arm angle
            ("shoulder", i8),  # the chain points at the shoulder and the wrist centre (−1: none)
            ("wrist", i8),
            ("sense", f8),  # ±1: the arm angle turns the elbow about (wrist − shoulder) by +sense·Δψ
            ("arcs", f8),  # 1: the rotation above holds (obstacle-aware intervals in closed form)
            ("ob_kind", f8, o),  # qpnso.model.distance SPHERE, CAPSULE, BOX
            ("ob_center", f8, (o, 3)),  # m, world
            ("ob_second", f8, (o, 3)),  # a capsule's other end (m, world)
            ("ob_R", f8, (o, 3, 3)),  # a box's rotation, world ← box
            ("ob_half", f8, (o, 3)),  # a box's half extents (m)
            ("ob_radius", f8, o),  # a sphere's or capsule's radius (m)
            ("ob_velocity", f8, (o, 3)),  # m/s, world: the velocity of its centre (obstacle_centre); 0: still
            ("ob_omega", f8, (o, 3)),  # rad/s, world: its angular velocity about that centre
            ("ob_hold", f8, o),  # ticks the two above still hold (inf: until the next placement); then zeroed
        ]
    )


def keep_out_record(
    robot: Robot,
    capsules: LinkCapsules,
    room: int,
    obstacles: Sequence[Obstacle] = (),
    settings: KeepOut = KeepOut(),
) -> np.ndarray:
    """The keep-out record of ``robot``'s ``capsules`` with room for ``room`` obstacles, ``obstacles`` in it
    (:func:`set_obstacles`), ``settings`` (:class:`KeepOut`): a 1-element array."""
    rec = new_record(keep_out_dtype(capsules.points_count, capsules.count, room))
    g = rec[0]
    s = settings
    g["margin"], g["influence"], g["recovery_speed"] = s.margin, s.influence, s.recovery_speed
    g["gain"] = s.speed / (s.influence - s.margin)
    g["row_scale"] = math.sqrt(s.weight_ratio)
    g["damping"], g["stiffness"] = s.damping, s.stiffness
    g["n_capsules"] = capsules.count
    g["cap_a"][: capsules.count], g["cap_b"][: capsules.count] = capsules.a, capsules.b
    g["cap_radius"][: capsules.count] = capsules.radius
    moves, shoulder, wrist, sense = point_motion(robot, capsules)
    g["arcs"] = 1.0 if moves is not None else 0.0
    g["shoulder"], g["wrist"], g["sense"] = shoulder, wrist, sense
    if moves is not None:
        g["pt_moves"][: capsules.points_count] = moves
        g["cap_moves"][: capsules.count] = [max(moves[a], moves[b]) for a, b in zip(capsules.a, capsules.b)]
    set_obstacles(rec, obstacles)
    return rec


def set_obstacles(
    rec: np.ndarray,
    obstacles: Sequence[Obstacle],
    velocities: np.ndarray | None = None,
    hold: np.ndarray | None = None,
) -> None:
    """Write ``obstacles`` into the keep-out record ``rec`` (in place; SettingError beyond its room, nothing
    written) with their ``velocities`` (len(obstacles), 6): each centre's linear velocity (m/s) then the angular
    velocity (rad/s), world frame (:func:`qpnso.model.obstacles.placement_velocity`), each for ``hold``
    (len(obstacles),) more ticks (inf: until the next placement; :func:`motion_tick` counts them down); None:
    all still."""
    g = rec[0]
    room = g["ob_kind"].shape[0]
    arrays = obstacle_arrays(obstacles, room)
    motion, ticks = np.zeros((room, 6)), np.zeros(room)
    if velocities is not None:
        motion[: len(obstacles)] = velocities
        ticks[: len(obstacles)] = math.inf if hold is None else hold
    arrays["ob_velocity"], arrays["ob_omega"], arrays["ob_hold"] = motion[:, :3], motion[:, 3:], ticks
    for name, value in arrays.items():
        g[name] = value
    g["n_obstacles"] = len(obstacles)


def still_obstacles(rec: np.ndarray) -> None:
    """The keep-out record ``rec``'s obstacles taken as still from now on (their velocities zero; in place)."""
    g = rec[0]
    g["ob_velocity"] = 0.0
    g["ob_omega"] = 0.0
    g["ob_hold"] = 0.0


def point_motion(robot: Robot, capsules: LinkCapsules) -> tuple[np.ndarray | None, int, int, float]:
    """How the chain points move with the arm angle (module docstring): ``(moves, shoulder, wrist, sense)`` —
    ``moves`` (k,) 1.0 for a point that turns about the shoulder–wrist axis, 0.0 for a fixed one, checked by
    the closed-form IK at four arm angles on the sample configuration's pose; None (and −1, −1, 1.0) when the
    arm is not S-R-S or a point does neither."""
    from qpnso.elbow.arm_angle import arm_angle
    from qpnso.elbow.intervals import closed_form_applies
    from qpnso.elbow.srs import branch, ik, srs_geometry

    none = (None, -1, -1, 1.0)
    if not closed_form_applies(robot):
        return none
    q = robot.sample_configuration()
    pose, ns, b = robot.tool_pose(q), arm_angle(robot, q), branch(robot, q)
    ref = capsules.points(robot, q)
    pin_points = srs_geometry(robot).points.world(robot.data)  # (after points(): the data is at q)
    shoulder, wrist = (_index_of(ref, p) for p in (pin_points[0], pin_points[2]))
    if shoulder < 0 or wrist < 0:
        return none
    moves = np.zeros(len(ref))
    for sense in (1.0, -1.0):
        ok = True
        for delta in (0.3, -0.7, 1.1, 2.5):
            p = capsules.points(robot, ik(robot, pose, ns + delta, b))
            turned = rotated(ref, ref[shoulder], ref[wrist], sense * delta)
            fixed, turns = _near(p, ref), _near(p, turned)
            if not np.all(fixed | turns):
                ok = False
                break
            moves = np.where(turns & ~fixed, 1.0, moves)
        if ok:
            return moves, shoulder, wrist, sense
        moves[:] = 0.0
    return none


def _near(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.norm(a - b, axis=1) < MOTION_TOL


def _index_of(points: np.ndarray, p: np.ndarray) -> int:
    d = np.linalg.norm(points - p, axis=1)
    return int(np.argmin(d)) if d.min() < 1e-9 else -1


def rotated(points: np.ndarray, s: np.ndarray, w: np.ndarray, angle: float) -> np.ndarray:
    """``points`` (k, 3) turned by ``angle`` (rad) about the axis from ``s`` to ``w`` (``pinocchio.exp3``): the
    independent check of :func:`turn_points`' Rodrigues formula when an arm's record is built."""
    u = (w - s) / np.linalg.norm(w - s)
    return s + (points - s) @ pin.exp3(angle * u).T


@njit(cache=True)
def pair_distance(G, points, c, o):
    """``(d, t, n0, n1, n2)``: capsule ``c``'s surface distance (m) to obstacle ``o`` (negative: they overlap)
    with its axis at the chain ``points`` (k, 3), the witness parameter ``t`` on the axis and the unit normal
    from the obstacle (:func:`qpnso.model.distance.segment_obstacle`); ``G`` the keep-out record."""
    a, b = points[G.cap_a[c]], points[G.cap_b[c]]
    d, t, n0, n1, n2 = segment_obstacle(
        a, b, int(G.ob_kind[o]), G.ob_center[o], G.ob_second[o], G.ob_R[o], G.ob_half[o], G.ob_radius[o]
    )
    return d - G.cap_radius[c], t, n0, n1, n2


@njit(cache=True)
def obstacle_approach(G, points, c, o, t, n0, n1, n2):
    """m/s: how fast obstacle ``o``'s surface moves toward capsule ``c`` along the pair's unit normal
    ``n`` = (n0, n1, n2) (from the obstacle toward the witness ``p = a + t(b − a)`` on the capsule's axis, the
    chain ``points`` (k, 3) m; :func:`pair_distance`): ``n·(v + ω × (p − c_o))``, ``v`` and ``ω`` its velocity
    and angular velocity (``G.ob_velocity``, m/s; ``G.ob_omega``, rad/s; world) and ``c_o`` its centre, the
    midpoint of ``ob_center`` and ``ob_second`` (:attr:`qpnso.model.obstacles.Obstacle.centre`).  Every point of
    the normal line gives the same value (``n·(ω × n) = 0``): the obstacle's own witness moves along ``n`` as
    fast.  0 for a still obstacle."""
    a, b = points[G.cap_a[c]], points[G.cap_b[c]]
    v, w, c1, c2 = G.ob_velocity[o], G.ob_omega[o], G.ob_center[o], G.ob_second[o]
    r0 = a[0] + t * (b[0] - a[0]) - 0.5 * (c1[0] + c2[0])
    r1 = a[1] + t * (b[1] - a[1]) - 0.5 * (c1[1] + c2[1])
    r2 = a[2] + t * (b[2] - a[2]) - 0.5 * (c1[2] + c2[2])
    return (
        n0 * (v[0] + w[1] * r2 - w[2] * r1) + n1 * (v[1] + w[2] * r0 - w[0] * r2) + n2 * (v[2] + w[0] * r1 - w[1] * r0)
    )


@njit(cache=True)
def motion_tick(G):
    """One tick of the obstacles' velocities gone by (in place on the keep-out record ``G``): each one's
    ``ob_hold`` counts down, and a velocity whose ticks are spent is zeroed (the obstacle is still until it is
    placed again).  An estimated velocity holds for the ticks it was measured over, so a volume placed once
    and then left moves, as the rows see it, no farther than it did."""
    for o in range(G.n_obstacles):
        if G.ob_hold[o] > 0.0:
            G.ob_hold[o] -= 1.0
            if G.ob_hold[o] <= 0.0:
                G.ob_hold[o] = 0.0
                G.ob_velocity[o, :] = 0.0
                G.ob_omega[o, :] = 0.0


@njit(cache=True)
def least_clearance(G, points, moving_only):
    """``(d, c, o)``: the least surface distance (m) of a capsule (``moving_only``: one that turns with the arm
    angle) to an obstacle, and which pair (``inf, −1, −1`` with none)."""
    best, bc, bo = math.inf, -1, -1
    for c in range(G.n_capsules):
        if moving_only and G.cap_moves[c] == 0.0:
            continue
        for o in range(G.n_obstacles):
            d = pair_distance(G, points, c, o)[0]
            if d < best:
                best, bc, bo = d, c, o
    return best, bc, bo


@njit(cache=True)
def record_clearance(rec, points, moving_only):
    """:func:`least_clearance` of the keep-out record array ``rec`` (1 element): the cheap entry from Python,
    called once a walk step (typing a record element, ``rec[0]``, costs about 50 µs a call; the array 1.6 µs)."""
    return least_clearance(rec[0], points, moving_only)


@njit(cache=True)
def turn_points(G, points, angle, out):
    """The chain ``points`` after the arm angle changes by ``angle`` (rad), into ``out``: the moving ones
    turned about the shoulder–wrist axis (Rodrigues), the others as they are."""
    s, w = points[G.shoulder], points[G.wrist]
    u = w - s
    u = u / math.sqrt(u[0] ** 2 + u[1] ** 2 + u[2] ** 2)
    c, si = math.cos(G.sense * angle), math.sin(G.sense * angle)
    for k in range(points.shape[0]):
        if G.pt_moves[k] == 0.0:
            out[k] = points[k]
            continue
        v = points[k] - s
        along = v[0] * u[0] + v[1] * u[1] + v[2] * u[2]
        cr0, cr1, cr2 = u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]
        out[k, 0] = s[0] + v[0] * c + cr0 * si + u[0] * along * (1 - c)
        out[k, 1] = s[1] + v[1] * c + cr1 * si + u[1] * along * (1 - c)
        out[k, 2] = s[2] + v[2] * c + cr2 * si + u[2] * along * (1 - c)


@njit(cache=True)
def axis_radius(G, points):
    """ρ (m): the largest distance of a moving chain point from the shoulder–wrist axis (the Lipschitz
    constant of the clearance in the arm angle), at least 1 mm."""
    s, w = points[G.shoulder], points[G.wrist]
    u = w - s
    u = u / math.sqrt(u[0] ** 2 + u[1] ** 2 + u[2] ** 2)
    rho = 1e-3
    for k in range(points.shape[0]):
        if G.pt_moves[k] != 0.0:
            v = points[k] - s
            along = v[0] * u[0] + v[1] * u[1] + v[2] * u[2]
            rho = max(rho, math.sqrt(max(v[0] ** 2 + v[1] ** 2 + v[2] ** 2 - along * along, 0.0)))
    return rho


@njit(cache=True)
def gap_at(G, points, angle, buf):
    """``(c(ψ), capsule, obstacle)``: the moving capsules' least clearance minus the margin (m) with the arm
    angle changed by ``angle`` (rad) from ``points``'; ``buf`` a (k, 3) scratch array."""
    turn_points(G, points, angle, buf)
    d, c, o = least_clearance(G, buf, True)
    return d - G.margin, c, o


@njit(cache=True)
def next_crossing(G, points, start, stop):
    """The first sign change of the clearance ``c(ψ)`` (:func:`gap_at`) going from ``start`` to ``stop``
    (rad, offsets of the arm angle from ``points``', either order): ``(found, at, code)`` — ``at`` the crossing
    bisected to :data:`END_TOL_RAD` on the side of ``start``'s sign, ``code`` :data:`OBSTACLE_END` −
    (100·capsule + obstacle) of the pair that crosses; ``found`` False: no change before ``stop``."""
    buf = np.empty_like(points)
    rho = axis_radius(G, points)
    direction = 1.0 if stop >= start else -1.0
    g0, c, o = gap_at(G, points, start, buf)
    inside = g0 >= 0.0
    x = start
    while True:
        step = max(abs(g0) / rho, MIN_STEP_RAD)
        y = x + direction * step
        if direction * (y - stop) > 0.0:
            y = stop
        g, c, o = gap_at(G, points, y, buf)
        if (g >= 0.0) != inside:
            a, b = x, y  # (a: start's side)
            while abs(b - a) > END_TOL_RAD:
                mid = 0.5 * (a + b)
                gm, cm, om = gap_at(G, points, mid, buf)
                if (gm >= 0.0) == inside:
                    a = mid
                else:
                    b, c, o = mid, cm, om
            return True, a, OBSTACLE_END - (100 * c + o)
        if y == stop:
            return False, stop, 0
        x, g0 = y, g


@njit(cache=True)
def clear_interval(G, points, below, above):
    """The continuity interval's distances ``below`` and ``above`` the current arm angle (rad; ``inf``: none)
    cut where a moving capsule comes within the margin of an obstacle: ``(below, above, lo_cut, hi_cut)``
    with the cuts' end codes (0: not cut).  Unchanged when there is no obstacle, the arm has no rotation
    record (``G.arcs`` 0) or the arm is within the margin already (the rows move it out)."""
    if G.n_obstacles == 0 or G.arcs == 0.0:
        return below, above, 0, 0
    buf = np.empty_like(points)
    if gap_at(G, points, 0.0, buf)[0] < 0.0:
        return below, above, 0, 0
    lo_cut, hi_cut = 0, 0
    found, at, code = next_crossing(G, points, 0.0, min(above, TWO_PI))
    if found:
        above, hi_cut = at, code
    found, at, code = next_crossing(G, points, 0.0, -min(below, TWO_PI - min(above, TWO_PI)))
    if found:
        below, lo_cut = -at, code
    elif hi_cut:
        below = min(below, TWO_PI - above)  # (the circle's other way round to the same crossing)
    return below, above, lo_cut, hi_cut
