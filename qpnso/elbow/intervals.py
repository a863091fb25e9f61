"""Joint-limit continuity intervals of the arm angle (docs/method.md §5, [E 7]–[E 9]).

With the tool pose and the branch held, each joint is a function ``θ_k(ns)``
(:class:`qpnso.elbow.srs.SelfMotion`).  ``Ψ_k`` is the set of arm angles where joint
``k`` is within its limits [E 7], ``Ψ = ∩ Ψ_k`` [E 8], and the continuity
interval is the arc of ``Ψ`` that holds the current arm angle [E 9].

Closed form (S-R-S arms): every limit crossing solves ``A sin ns + B cos ns = C``
exactly (``atan2(A, B) ± acos(C/√(A²+B²))``, one Newton polish step); the points
where joint 2 or 6 passes through 0 (the closed form switches branch, joints
1/3 or 5/7 jump by π) are *singular cuts*.  The circle is cut at all these
points, each arc's midpoint is tested against every limit, and neighbouring
feasible arcs are merged unless a singular cut separates them.  Spurious roots
(``θ = θ_limit + π`` of the tangent-type equations) only add cuts that merge
away.  Tangent-type joints are represented in (-π, π]; limits beyond ±π are
therefore never crossed.  The arithmetic is the kernels of :mod:`qpnso.elbow.closed_form` (the control
tick's too); this module gives them their public form (:class:`Interval`, :class:`Cause`, the arcs).

Arc convention: an arc is ``(lo, hi)`` with ``-π ≤ lo < π`` and
``lo < hi ≤ lo + 2π``; an arc crossing ±π is *not* split (its ``hi`` exceeds
π).  The full circle is ``(-π, π)``.

Numerical (other arms, e.g. the Panda): the self-motion is followed from ``q``
in both directions with null-space steps and Newton pose correction; a limit
crossing is then solved exactly (the crossing joint pinned at its limit, the
other six solving the tool pose by Newton to 1e-12), so the ends are accurate
to about 1e-9 rad.  Excursions past a limit shorter than one step
(``NumericalOptions.step_rad``) can be missed.  The walk can be taken in pieces
(:class:`NumericalWalk`), as the control tick does.

Obstacles (docs/method.md §10).  Given keep-out volumes (:mod:`qpnso.model.obstacles`) and a margin d_s (m),
an arm angle is also feasible only where every link capsule (:mod:`qpnso.model.collision`) keeps at least
d_s from every obstacle.  Closed form: the upper arm and forearm turn rigidly about the shoulder–wrist axis,
and the kernels of :mod:`qpnso.elbow.clearance` find the clearance's sign changes (conservative advancement,
bisection to ``END_TOL_RAD`` = 1e-7 rad): :func:`continuity_interval` cuts the joint-limit interval with
``clear_interval`` (the control tick's kernel), :func:`feasible_intervals` splits every arc of Ψ with
``next_crossing``.  Numerical: the walk also ends where the least clearance drops below d_s, the end bisected
between the last two walk points (each midpoint put back on the self-motion by the pose correction) to
``END_TOL_RAD`` in arm angle.  An end at an obstacle has ``Cause("obstacle", -1, link=…, obstacle=…)``.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Generator, Sequence
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

from qpnso.elbow.arm_angle import (
    _checked,
    _status_after_fk,
    arm_angle,
    arm_angle_gradient,
    arm_angle_status,
)
from qpnso.elbow.clearance import (
    END_TOL_RAD,
    OBSTACLE_END,
    OBSTACLE_ROOM,
    clear_interval,
    gap_at,
    keep_out_record,
    least_clearance,
    next_crossing,
    pair_distance,
    record_clearance,
    set_obstacles,
)
from qpnso.elbow.closed_form import (
    MAX_ROWS,
    NO_END,
    ROW_FIELDS,
    crossings,
    limit_rows,
    singular_cut,
    srs_interval,
)
from qpnso.elbow.srs import (
    SelfMotion,
    _branch_of,
    as_pose,
    branch_floats,
    is_srs,
    pose_arrays,
    raise_unless_reached,
    self_motion,
    srs_geometry,
)
from qpnso.errors import InputError, ModelError, SingularityError
from qpnso.linalg import least_norm_line
from qpnso.model.collision import LinkCapsules, link_capsules
from qpnso.model.obstacles import Obstacle, as_obstacles
from qpnso.model.robot import Robot

TWO_PI = 2.0 * math.pi
_MERGE_TOL = 1e-12
_FEASIBLE_TOL = 1e-10
_ALL_JOINTS = np.arange(7)
_FULL_CIRCLE = (-math.pi, math.pi, None, None)


@dataclass(frozen=True)
class Cause:
    """What ends an interval: a joint limit (``"limit"``, ``bound`` "min"/"max"),
    a singular point (``"singular"``: joint 2 or 6 through 0 in the closed form;
    a rank-deficient Jacobian or undefined arm angle in the numerical method,
    ``joint = -1``), an obstacle (``"obstacle"``, ``joint = -1``: the capsule of ``link``,
    e.g. ``"link_2-link_3"``, comes within the margin of obstacle number ``obstacle``, 0-based)
    or, numerical method only, ``"unfinished"`` (step budget exhausted).  ``joint`` is 0-based."""

    kind: str
    joint: int
    bound: str = ""
    link: str = ""
    obstacle: int = -1


@dataclass(frozen=True)
class Interval:
    """Continuity interval [E 9] holding the current arm angle (rad, unwrapped).

    ``lo ≤ ns ≤ hi`` and ``hi - lo ≤ 2π``.  ``full_circle`` is True when no
    limit or singular point binds (then ``lo = ns - π``, ``hi = ns + π``).
    ``method`` is ``"closed_form"`` or ``"numerical"``.
    """

    lo: float
    hi: float
    full_circle: bool
    method: str = "closed_form"
    lo_cause: Cause | None = None
    hi_cause: Cause | None = None
    lo_q: np.ndarray | None = field(default=None, compare=False, repr=False)
    hi_q: np.ndarray | None = field(default=None, compare=False, repr=False)
    """Configurations (rad) at the ends: numerical method only (None for the closed form)."""

    @property
    def width(self) -> float:
        return self.hi - self.lo

    def contains(self, ns: float, tol: float = 0.0) -> bool:
        """Whether arm angle ``ns`` (rad, any unwrapping) lies in the interval."""
        if self.full_circle:
            return True
        return (ns - self.lo + tol) % TWO_PI <= self.hi - self.lo + 2 * tol


def wrap(angle):
    """Angle(s) (rad, float or array) wrapped into [-π, π)."""
    return (angle + math.pi) % TWO_PI - math.pi


# ----------------------------------------------------------------- cut points
_BOUNDS = ("min", "max")


def end_cause(code: int, capsules: Sequence[str] = ()) -> Cause | None:
    """The :class:`Cause` of an end code of :mod:`qpnso.elbow.closed_form` (a limit ``2·joint + is_max``, a
    singular cut ``−1 − joint``, :data:`~qpnso.elbow.closed_form.NO_END`) or of :mod:`qpnso.elbow.clearance`
    (``OBSTACLE_END − (100·capsule + obstacle)``, codes ≤ ``OBSTACLE_END``); ``capsules`` names the link
    capsules (:attr:`qpnso.model.collision.LinkCapsules.names`; a capsule beyond them is ``"capsule <i>"``)."""
    if code == NO_END:
        return None
    if code <= OBSTACLE_END:
        capsule, obstacle = divmod(OBSTACLE_END - code, 100)
        link = capsules[capsule] if capsule < len(capsules) else f"capsule {capsule}"
        return Cause("obstacle", -1, link=link, obstacle=obstacle)
    return Cause("limit", code // 2, _BOUNDS[code % 2]) if code >= 0 else Cause("singular", -1 - code)


def _cuts(sm: SelfMotion, q_min: np.ndarray, q_max: np.ndarray, joints: np.ndarray):
    """Sorted, de-duplicated cut points in [-π, π) and their end codes (:func:`end_cause`).

    Returns ``(angles, codes, hard)``: every limit crossing of the given joints (genuine or not) and every
    singular cut; ``hard`` marks singular cuts (negative codes).
    """
    rows, roots = np.empty((MAX_ROWS, ROW_FIELDS)), np.empty((2, 2))
    wanted = set(joints.tolist())
    first, second, codes = [], [], []  # all "+" roots, then all "−" roots
    for i in range(limit_rows(sm.sign, q_min, q_max, rows)):
        k = int(rows[i, 0])
        if k in wanted and crossings(rows[i], sm.num[k], sm.den[k], False, roots):
            first.append(roots[0, 0])
            second.append(roots[1, 0])
            codes.append(2 * k + int(rows[i, 6]))
    roots_ns, labels = first + second, codes * 2
    for k in (1, 5):
        if k in wanted:
            hit, x = singular_cut(sm.den, k)
            if hit:
                roots_ns.append(x)
                labels.append(-1 - k)
    ang, lab = wrap(np.array(roots_ns, dtype=float)), np.array(labels, dtype=int)
    order = np.lexsort((lab >= 0, ang))  # singular first among equal angles
    ang, lab = ang[order], lab[order]
    if ang.size > 1:
        distinct = np.concatenate([[True], np.diff(ang) > _MERGE_TOL])
        ang, lab = ang[distinct], lab[distinct]
        if ang[-1] - ang[0] > TWO_PI - _MERGE_TOL:
            ang, lab = ang[:-1], lab[:-1]
    return ang, lab, lab < 0


def _arcs(sm: SelfMotion, q_min: np.ndarray, q_max: np.ndarray, joints: np.ndarray):
    """Feasible arcs ``[(lo, hi, lo_cause, hi_cause)]`` for the given joints (0-based).

    The full circle is :data:`_FULL_CIRCLE` ``(-π, π, None, None)``.
    """
    cuts, labels, hard = _cuts(sm, q_min, q_max, joints)
    lo_lim, hi_lim = q_min[joints] - _FEASIBLE_TOL, q_max[joints] + _FEASIBLE_TOL
    m = cuts.size
    if m == 0:
        q = sm.joints(np.array([0.0]))[:, joints]
        return [_FULL_CIRCLE] if np.all((q >= lo_lim) & (q <= hi_lim)) else []
    hi = np.append(cuts[1:], cuts[0] + TWO_PI)
    q = sm.joints(0.5 * (cuts + hi))[:, joints]
    feasible = np.all((q >= lo_lim) & (q <= hi_lim), axis=1).tolist()
    hard_l = hard.tolist()
    starts = [i for i in range(m) if feasible[i] and (hard_l[i] or not feasible[i - 1])]
    if not starts:
        return [_FULL_CIRCLE] if all(feasible) else []
    arcs = []
    for i in starts:
        j = i
        while True:
            nxt = (j + 1) % m
            if not feasible[nxt] or hard_l[nxt] or nxt == i:
                break
            j = nxt
        end = float(hi[j]) if j >= i else float(hi[j]) + TWO_PI
        arcs.append((float(cuts[i]), end, end_cause(int(labels[i])), end_cause(int(labels[(j + 1) % m]))))
    return sorted(arcs, key=lambda arc: arc[0])


# ---------------------------------------------------------------- obstacles
@functools.lru_cache(maxsize=16)
def _keep_out_template(robot: Robot, room: int) -> np.ndarray:
    """The keep-out record (:func:`qpnso.elbow.clearance.keep_out_record`) of ``robot``'s link capsules with room
    for ``room`` obstacles and none in it, cached per robot and room (never written: :func:`_keep_out` copies)."""
    return keep_out_record(robot, link_capsules(robot), room)


def _keep_out(
    robot: Robot, obstacles: Sequence[Obstacle], margin: float, room: int = 0
) -> tuple[np.ndarray, LinkCapsules]:
    """A keep-out record holding ``obstacles`` (:func:`qpnso.elbow.clearance.set_obstacles`) and the margin d_s
    (m, finite, ≥ 0), with the link capsules it was built for; room for ``max(room, OBSTACLE_ROOM, len(obstacles))``
    obstacles (the room is part of the record's type: a caller whose number of obstacles changes gives its own)."""
    if not (math.isfinite(margin) and margin >= 0.0):
        raise InputError(f"the obstacle margin must be a finite number >= 0 m, got {margin!r}")
    obs = as_obstacles(obstacles)
    rec = _keep_out_template(robot, max(room, OBSTACLE_ROOM, len(obs))).copy()
    set_obstacles(rec, obs)
    rec[0]["margin"] = margin
    return rec, link_capsules(robot)


def _turns_rigidly(robot: Robot) -> bool:
    """Whether ``robot``'s chain points turn rigidly about the shoulder–wrist axis with the arm angle (the
    keep-out record's ``arcs``: the obstacle-aware intervals in closed form)."""
    return bool(_keep_out_template(robot, OBSTACLE_ROOM)[0]["arcs"])


def _raise_if_within_margin(G: np.void, points: np.ndarray, capsules: LinkCapsules) -> None:
    """InputError when a link capsule at the chain ``points`` (k, 3; m) is nearer an obstacle than the margin of
    the keep-out record ``G`` (:func:`qpnso.elbow.clearance.least_clearance`, every capsule)."""
    d, c, o = least_clearance(G, points, False)
    if d < G["margin"]:
        raise InputError(
            f"link {capsules.names[c]} is {d:.3g} m from obstacle {o}, within the margin {G['margin']:g} m: "
            "no obstacle-free interval holds q"
        )


def _fixed_clearance(G: np.void, points: np.ndarray) -> float:
    """The least distance (m) of a capsule that does NOT turn with the arm angle (base, hand) to an obstacle,
    at the chain ``points`` (:func:`qpnso.elbow.clearance.pair_distance`; ``inf`` with none)."""
    pairs = [(c, o) for c in range(G["n_capsules"]) if G["cap_moves"][c] == 0.0 for o in range(G["n_obstacles"])]
    return min((pair_distance(G, points, c, o)[0] for c, o in pairs), default=math.inf)


def _cut_at_obstacles(
    robot: Robot, q: np.ndarray, ns: float, interval: Interval, obstacles: Sequence[Obstacle], margin: float
) -> Interval:
    """The closed-form ``interval`` (rad, around the arm angle ``ns`` of ``q``) cut where a link capsule comes
    within ``margin`` (m) of an obstacle: :func:`qpnso.elbow.clearance.clear_interval`, the kernel the control
    tick runs, from the chain points at ``q``.  InputError when ``q`` is within the margin already."""
    rec, capsules = _keep_out(robot, obstacles, margin)
    G, points = rec[0], capsules.points(robot, q)
    _raise_if_within_margin(G, points, capsules)
    below, above = (math.inf, math.inf) if interval.full_circle else (ns - interval.lo, interval.hi - ns)
    cut_below, cut_above, lo_cut, hi_cut = clear_interval(G, points, below, above)
    if not (lo_cut or hi_cut):
        return interval
    names = capsules.names
    lo_cause = interval.lo_cause
    if lo_cut or cut_below < below:  # (no crossing below: the circle's other way round to the one above)
        lo_cause = end_cause(lo_cut or hi_cut, names)
    hi_cause = end_cause(hi_cut, names) if hi_cut else interval.hi_cause
    return Interval(ns - cut_below, ns + cut_above, False, "closed_form", lo_cause, hi_cause)


def _split_at_obstacles(G: np.void, points: np.ndarray, ref: float, arc: tuple, names: Sequence[str]) -> list[tuple]:
    """The parts of ``arc`` ``(lo, hi, lo_cause, hi_cause)`` (rad) where the moving capsules keep the margin of
    the keep-out record ``G``, ``points`` the chain points at the arm angle ``ref`` inside it: repeated
    :func:`qpnso.elbow.clearance.next_crossing` from ``lo`` to ``hi`` (offsets from ``ref``), each search
    resumed :data:`~qpnso.elbow.clearance.END_TOL_RAD` past the crossing it found (past the bisection's
    bracket); an end at a crossing is its bracket's side nearer ``lo``, within 1e-7 rad of it."""
    lo, hi, lo_cause, hi_cause = arc
    x, stop, buf = lo - ref, hi - ref, np.empty_like(points)
    free = gap_at(G, points, x, buf)[0] >= 0.0
    start, start_cause, parts = lo, lo_cause, []
    while True:
        found, at, code = next_crossing(G, points, x, stop)
        if not found:
            break
        cause = end_cause(code, names)
        if free:
            parts.append((start, ref + at, start_cause, cause))
        x = at + END_TOL_RAD
        if x >= stop:
            return parts
        free = gap_at(G, points, x, buf)[0] >= 0.0
        start, start_cause = ref + x, cause
    if free:
        parts.append((start, hi, start_cause, hi_cause))
    return parts


def _clear_arcs(robot: Robot, sm: SelfMotion, capsules: LinkCapsules, G: np.void, arcs: list[tuple]) -> list[tuple]:
    """``arcs`` ``[(lo, hi, lo_cause, hi_cause)]`` (rad, :func:`_arcs`' convention) intersected with the arm
    angles where every link capsule keeps the margin of the keep-out record ``G`` from every obstacle: each arc
    split at the clearance's sign changes (:func:`_split_at_obstacles`, the chain points from the closed-form
    IK ``sm`` of ``robot`` at the arc's midpoint); none when a capsule that does not turn with the arm angle is
    within the margin.  A full circle's first and last parts join across ±π."""
    parts: list[tuple] = []
    for arc in arcs:
        ref = 0.5 * (arc[0] + arc[1])
        points = capsules.points(robot, sm.joints(ref))
        if _fixed_clearance(G, points) < G["margin"]:
            return []
        parts += _split_at_obstacles(G, points, ref, arc, capsules.names)
    if arcs == [_FULL_CIRCLE] and len(parts) > 1 and parts[0][0] == -math.pi and parts[-1][1] == math.pi:
        first, last = parts[0], parts.pop()
        parts[0] = (last[0], first[1] + TWO_PI, last[2], first[3])
    parts = [(lo - TWO_PI, hi - TWO_PI, a, b) if lo >= math.pi else (lo, hi, a, b) for lo, hi, a, b in parts]
    return sorted(parts, key=lambda part: part[0])


# --------------------------------------------------------------- public API
Arcs = list[tuple[float, float]]


def feasible_intervals(
    robot: Robot,
    pose: object,
    branch_: object,
    per_joint: bool = False,
    obstacles: Sequence[Obstacle] = (),
    margin: float = 0.03,
) -> Arcs | tuple[Arcs, dict[int | str, Arcs]]:
    """Ψ [E 8]: arcs of arm angles (rad) where all joint limits hold (S-R-S, closed form) and, with
    ``obstacles``, where every link capsule keeps at least ``margin`` (m) from every obstacle.

    Arcs ``(lo, hi)``, sorted by ``lo``, ``-π ≤ lo < π``, ``lo < hi ≤ lo + 2π``
    (an arc crossing ±π is not split).  Singular points (joint 2 or 6 through 0)
    end arcs.  An end at an obstacle is within 1e-7 rad of the clearance's sign change (module docstring); a
    capsule that does not turn with the arm angle (base, hand) within the margin empties Ψ.  With
    ``per_joint=True`` also returns ``{k: Ψ_k}`` [E 7] for k = 0…6 (0-based; limits only, no singular cuts
    except for joints 2 and 6 themselves) and, with ``obstacles``, ``"obstacles"``: the arcs where the
    capsules keep the margin, joint limits left out.  ModelError for an arm whose chain points do not turn
    rigidly with the arm angle (then use :func:`continuity_interval`).
    """
    wide = _limits_beyond_pi(robot)
    if wide is not None:
        raise ModelError(
            f"closed-form arcs need joint limits inside ±π; joint {wide + 1} has "
            f"[{robot.q_min[wide]:.6g}, {robot.q_max[wide]:.6g}] rad (use continuity_interval, numerical)"
        )
    sm = self_motion(robot, as_pose(pose), branch_)
    everything = _arcs(sm, robot.q_min, robot.q_max, _ALL_JOINTS)
    if obstacles:
        if not _turns_rigidly(robot):
            raise ModelError(f"{robot.name}: the links do not turn rigidly with the arm angle (no obstacle arcs)")
        rec, capsules = _keep_out(robot, obstacles, margin)
        everything = _clear_arcs(robot, sm, capsules, rec[0], everything)
    psi = [(lo, hi) for lo, hi, _, _ in everything]
    if not per_joint:
        return psi
    per: dict[int | str, Arcs] = {
        k: [(lo, hi) for lo, hi, _, _ in _arcs(sm, robot.q_min, robot.q_max, np.array([k]))] for k in range(7)
    }
    if obstacles:
        per["obstacles"] = [(lo, hi) for lo, hi, _, _ in _clear_arcs(robot, sm, capsules, rec[0], [_FULL_CIRCLE])]
    return psi, per


def _limits_beyond_pi(robot: Robot) -> int | None:
    """The first joint (0-based) whose limits reach ±π or beyond, else None.  The closed form reads a limit
    through its sine and cosine (or as an angle of atan2 in (−π, π]): such a limit aliases (limits of ±7 rad
    bounded the LWR4+'s interval at ±0.24 rad) or never binds consistently (at exactly ±π)."""
    wide = np.flatnonzero(~((robot.q_min > -math.pi) & (robot.q_max < math.pi)))
    return int(wide[0]) if wide.size else None


def closed_form_applies(robot: Robot) -> bool:
    """Whether the continuity interval of ``robot`` has the closed form: an S-R-S arm whose joint limits are
    inside ±π (:func:`_limits_beyond_pi`)."""
    return is_srs(robot) and _limits_beyond_pi(robot) is None


def continuity_interval(
    robot: Robot,
    q: object,
    options: "NumericalOptions | None" = None,
    obstacles: Sequence[Obstacle] = (),
    margin: float = 0.03,
) -> Interval:
    """The continuity interval [E 9] holding the arm angle of ``q`` (rad, unwrapped), with ``obstacles`` also
    ended where a link capsule would come within ``margin`` (m) of one.

    Closed form (:func:`qpnso.elbow.closed_form.srs_interval`, the kernel the control tick runs, then
    :func:`qpnso.elbow.clearance.clear_interval`, the tick's too) when :func:`closed_form_applies`, else
    :func:`numerical_interval`.  Raises JointLimitError if ``q`` is outside its limits, SingularityError if the
    arm angle or branch of ``q`` is undefined and InputError if a link at ``q`` is within the margin already.
    """
    qv = robot.check_q(q)
    if not closed_form_applies(robot) or (obstacles and not _turns_rigidly(robot)):
        return numerical_interval(robot, qv, options, obstacles, margin)
    pin.framesForwardKinematics(robot.model, robot.data, qv)
    ns = _checked(_status_after_fk(robot))
    branch_ = _branch_of(qv)
    g = srs_geometry(robot)
    R, p = pose_arrays(robot.data.oMf[robot.tool_frame_id])
    code, lo, hi, full, lo_code, hi_code, dist = srs_interval(
        g.record[0], R, p, *branch_floats(branch_), ns, robot.q_min, robot.q_max
    )
    raise_unless_reached(code, dist, g)
    interval = Interval(lo, hi, bool(full), "closed_form", end_cause(lo_code), end_cause(hi_code))
    return _cut_at_obstacles(robot, qv, ns, interval, obstacles, margin) if obstacles else interval


# ---------------------------------------------------------------- numerical
@dataclass(frozen=True)
class NumericalOptions:
    """Self-motion following for non-S-R-S arms.

    ``step_rad``: joint-space step length (rad); ``sigma_min``: smallest
    singular value of the tool Jacobian below which the walk stops (singular
    end); ``max_steps`` per direction; ``pose_tol``: Newton pose tolerance (m, rad).
    """

    step_rad: float = 0.03
    sigma_min: float = 1e-4
    max_steps: int = 2000
    pose_tol: float = 1e-12


def _pose_error(robot: Robot, q: np.ndarray, target: pin.SE3) -> np.ndarray:
    """6-vector (world, linear first) that moves the tool from ``q``'s pose to ``target``; ``q`` (rad) already
    checked (a walk's own configurations: Pinocchio directly, without ``Robot.tool_pose``'s checks and copy)."""
    pin.framesForwardKinematics(robot.model, robot.data, q)
    cur = robot.data.oMf[robot.tool_frame_id]
    return np.concatenate([target.translation - cur.translation, pin.log3(target.rotation @ cur.rotation.T)])


def _tool_jacobian(robot: Robot, q: np.ndarray) -> np.ndarray:
    """``Robot.jacobian`` for a checked ``q`` (rad): 6×nq, world-aligned at the tool point, linear rows first,
    C-ordered (the argument type of :func:`qpnso.linalg.least_norm_line` everywhere)."""
    jac = pin.computeFrameJacobian(robot.model, robot.data, q, robot.tool_frame_id, pin.LOCAL_WORLD_ALIGNED)
    return np.ascontiguousarray(jac)


def _newton(
    robot: Robot, q: np.ndarray, target: pin.SE3, tol: float, free: np.ndarray | None = None
) -> Generator[None, None, np.ndarray]:
    """Newton iterations on the tool pose, moving only the ``free`` joints (all: the least-norm step
    :func:`least_norm_step`; six: :func:`_square_step`), yielding after each: returns the corrected
    configuration (SingularityError if 30 do not reach 1e-9)."""
    q = q.copy()
    for _ in range(30):
        err = _pose_error(robot, q, target)
        if np.abs(err).max() < tol:
            return q
        jac = _tool_jacobian(robot, q)
        if free is None:
            q += least_norm_step(jac, err)
        else:
            q[free] += _square_step(jac[:, free], err)
        yield
    if np.abs(_pose_error(robot, q, target)).max() > 1e-9:
        raise SingularityError("pose correction did not converge while following the self-motion")
    return q


def least_norm_step(jac: np.ndarray, err: np.ndarray) -> np.ndarray:
    """``J⁺ err`` (rad) for the 6×7 tool Jacobian ``jac`` (C-ordered): the Householder QR kernel
    :func:`qpnso.linalg.least_norm_line` (1 µs of arithmetic, where ``np.linalg.lstsq`` spends ~50 µs in Python),
    ``np.linalg.lstsq`` where that finds ``J`` rank-deficient."""
    if jac.shape[1] == jac.shape[0] + 1:  # (the kernel's shape: one redundant joint)
        x, _, sigma_floor = least_norm_line(jac, err)
        if sigma_floor > 0.0:
            return x
    return np.linalg.lstsq(jac, err, rcond=None)[0]


def _square_step(jac: np.ndarray, err: np.ndarray) -> np.ndarray:
    """``J⁻¹ err`` (rad) for a square Jacobian ``jac`` (the six joints a limit crossing leaves free) by LU
    (``np.linalg.solve``, a third of ``lstsq``'s time), ``np.linalg.lstsq`` where ``J`` is singular."""
    try:
        return np.linalg.solve(jac, err)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(jac, err, rcond=None)[0]


def _null_direction(robot: Robot, q: np.ndarray, prev: np.ndarray, sigma_min: float) -> np.ndarray | None:
    """Unit null-space direction of the tool Jacobian at ``q`` (rad, checked), oriented like ``prev``; None if
    singular (its least singular value below ``sigma_min``).  The null vector and a floor on that value from
    :func:`qpnso.linalg.least_norm_line` (QR); the exact value from an SVD only where the floor (conservative by at
    most √6) is below ``sigma_min``."""
    jac = _tool_jacobian(robot, q)
    n, sigma_floor = np.zeros(jac.shape[1]), 0.0
    if jac.shape[1] == jac.shape[0] + 1:  # (the kernel's shape: one redundant joint)
        _, n, sigma_floor = least_norm_line(jac, np.zeros(jac.shape[0]))
    if sigma_floor < sigma_min:
        _, s, vt = np.linalg.svd(jac)
        if s[-1] < sigma_min:
            return None
        n = vt[-1]
    return n if n @ prev >= 0 else -n


def _crossing(
    robot: Robot, q_in: np.ndarray, q_out: np.ndarray, target: pin.SE3, tol: float
) -> Generator[None, None, tuple[np.ndarray, Cause]]:
    """Exact first limit crossing between a feasible and an infeasible configuration (the crossing joint pinned
    at its limit, the other six solving the pose: :func:`_newton`, yielding after each iteration).  The chord's
    first point at a limit is at the fraction :func:`_limit_fraction` of each joint beyond its limit at ``q_out``."""
    frac = np.full(robot.nq, np.inf)
    for j in np.flatnonzero((q_out > robot.q_max) | (q_out < robot.q_min)):
        limit = robot.q_max[j] if q_out[j] > robot.q_max[j] else robot.q_min[j]
        frac[j] = _limit_fraction(float(q_in[j]), float(q_out[j]), float(limit))
    k = int(np.argmin(frac))
    bound = "max" if q_out[k] > robot.q_max[k] else "min"
    q = q_in + frac[k] * (q_out - q_in)
    q[k] = robot.q_max[k] if bound == "max" else robot.q_min[k]
    q = yield from _newton(robot, q, target, tol, free=np.delete(np.arange(robot.nq), k))
    return q, Cause("limit", k, bound)


def _limit_fraction(inside: float, beyond: float, limit: float) -> float:
    """Where on the chord from ``inside`` to ``beyond`` (rad, ``beyond`` past ``limit``) the joint reaches its
    limit, as a fraction in [0, 1]: 0 when ``inside`` is not strictly inside it — a walk may start up to
    ``check_q``'s 1e-9 rad past a limit (a controller's measured q), and a joint the step left where it was is then
    beyond at both ends (the division by its zero motion was a divide-by-zero warning, and a start past the limit
    a negative fraction, extrapolating the chord backwards)."""
    if (limit - inside) * (beyond - limit) <= 0.0:  # inside is at or past the limit, on beyond's side
        return 0.0
    return (limit - inside) / (beyond - inside)


class _Clearance:
    """The numerical walk's obstacles: a keep-out record (:func:`_keep_out`: the obstacles, the margin d_s) and
    the link capsules of ``robot``."""

    def __init__(self, robot: Robot, obstacles: Sequence[Obstacle], margin: float, room: int = 0) -> None:
        self.robot = robot
        rec, self.capsules = _keep_out(robot, obstacles, margin, room)
        self.rec, self.G = rec, rec[0]

    def gap(self, q: np.ndarray) -> tuple[float, int]:
        """``(d − d_s, code)`` at ``q`` (rad): the least distance (m) of a link capsule to an obstacle minus the
        margin (:func:`qpnso.elbow.clearance.least_clearance`, every capsule) and the pair's end code
        (:func:`end_cause`)."""
        d, c, o = record_clearance(self.rec, self.capsules.points(self.robot, q), False)
        return d - self.G["margin"], OBSTACLE_END - (100 * c + o)

    def raise_if_within_margin(self, q: np.ndarray) -> None:
        """InputError when a link at ``q`` is within the margin (:func:`_raise_if_within_margin`)."""
        _raise_if_within_margin(self.G, self.capsules.points(self.robot, q), self.capsules)


def _obstacle_end(
    robot: Robot, q_in: np.ndarray, q_out: np.ndarray, target: pin.SE3, tol: float, clear: _Clearance
) -> Generator[None, None, tuple[np.ndarray, Cause]]:
    """Where the clearance (:meth:`_Clearance.gap`) changes sign between the self-motion configurations ``q_in``
    (clear) and ``q_out`` (within the margin): bisection on the joint-space chord, each midpoint put back on the
    self-motion by :func:`_newton` (yielding after each of its iterations and each halving), until their arm
    angles are :data:`~qpnso.elbow.clearance.END_TOL_RAD` apart.  Returns the clear side and the pair's cause."""
    ns_in, ns_out = arm_angle(robot, q_in), arm_angle(robot, q_out)
    code = clear.gap(q_out)[1]
    for _ in range(60):
        if abs(wrap(ns_out - ns_in)) <= END_TOL_RAD:
            break
        q_mid = yield from _newton(robot, 0.5 * (q_in + q_out), target, tol)
        gap, mid_code = clear.gap(q_mid)
        if gap >= 0.0:
            q_in, ns_in = q_mid, arm_angle(robot, q_mid)
        else:
            q_out, ns_out, code = q_mid, arm_angle(robot, q_mid), mid_code
        yield
    cause = end_cause(code, clear.capsules.names)
    assert cause is not None  # (an obstacle code: never NO_END)
    return q_in, cause


def _walk(
    robot: Robot,
    q0: np.ndarray,
    ns0: float,
    direction: np.ndarray,
    target: pin.SE3,
    opt: NumericalOptions,
    clear: _Clearance | None = None,
) -> Generator[None, None, tuple[float, Cause | None, np.ndarray]]:
    """Follow the self-motion from ``q0`` along ``direction``, yielding after each Newton iteration of a step's
    pose correction or of a limit crossing's exact solve and after each step (the limits, the arm angle and the
    next null-space direction), but the last: returns the unwrapped ns at the end, its cause and q there.  With
    ``clear`` the walk also ends where a link comes within the margin of an obstacle (:func:`_obstacle_end`,
    checked at every step's end and at a limit crossing: a violation shorter than a step can be missed)."""
    q, ns, d = q0.copy(), ns0, direction
    for _ in range(opt.max_steps):
        q_new = yield from _newton(robot, q + opt.step_rad * d, target, opt.pose_tol)
        pin.forwardKinematics(robot.model, robot.data, q_new)
        status = _status_after_fk(robot)  # (arm_angle_status without checking q: a walk's own configuration)
        beyond = bool(np.any(q_new > robot.q_max) or np.any(q_new < robot.q_min))
        if beyond or (clear is not None and clear.gap(q_new)[0] < 0.0):
            yield  # (this step found the crossing; its exact solve is the next pieces)
            q_end, cause = q_new, None
            if beyond:
                q_end, cause = yield from _crossing(robot, q, q_new, target, opt.pose_tol)
            if clear is not None and clear.gap(q_end)[0] < 0.0:  # (an obstacle before the limit)
                q_end, cause = yield from _obstacle_end(robot, q, q_end, target, opt.pose_tol, clear)
            return ns + wrap(arm_angle_status(robot, q_end).value - ns), cause, q_end
        d_new = _null_direction(robot, q_new, d, opt.sigma_min)
        if d_new is None or not status.ok:
            end = ns + wrap(status.value - ns) if math.isfinite(status.value) else ns
            return end, Cause("singular", -1), q_new
        ns += wrap(status.value - ns)
        q, d = q_new, d_new
        if abs(ns - ns0) >= TWO_PI:
            return ns, None, q
        yield
    return ns, Cause("unfinished", -1), q  # max_steps reached: an end that is not a limit


class NumericalWalk:
    """The numerical continuity interval at ``q`` (rad) computed in pieces: :meth:`advance` takes at most a given
    number of pieces — one Newton iteration of a self-motion step's pose correction or of a limit crossing's exact
    solve, or the rest of a step (``NumericalOptions.step_rad`` each: the limits, the arm angle, the next null
    direction), 16 µs median and 0.24 ms p99.9 of CPU on the Panda (docs/changelog.md, issue 31) — and returns the
    :class:`Interval` once both walks have ended (None before).  The control tick of an arm without the closed form
    advances one a few pieces a tick (``ControllerConfig.interval_steps_per_tick``): a whole walk takes 9 ms median
    on the Panda, and was once renewed inside a tick every ``interval_period`` ticks of a moving tool.  With
    ``obstacles`` the walks also end where a link capsule comes within ``margin`` (m) of one (:func:`_walk`);
    ``room``: the keep-out record's room for obstacles (:func:`_keep_out`; the control tick gives its own, so the
    record's type does not change with the number of obstacles).  Raises SingularityError where the self-motion is
    undefined at ``q`` (here), JointLimitError for ``q`` outside its limits or InputError for a link at ``q``
    within the margin."""

    def __init__(
        self,
        robot: Robot,
        q: object,
        options: NumericalOptions | None = None,
        obstacles: Sequence[Obstacle] = (),
        margin: float = 0.03,
        room: int = 0,
    ) -> None:
        opt = options or NumericalOptions()
        qv = robot.check_q(q)
        clear = _Clearance(robot, obstacles, margin, room) if obstacles else None
        if clear is not None:
            clear.raise_if_within_margin(qv)
        self.ns0 = arm_angle(robot, qv)
        self.target = robot.tool_pose(qv)
        grad = arm_angle_gradient(robot, qv)
        d = _null_direction(robot, qv, grad, opt.sigma_min)
        if d is None:
            raise SingularityError("the tool Jacobian is singular at q: the self-motion is not defined")
        if abs(d @ grad) < 1e-12:
            raise SingularityError("the self-motion does not change the arm angle at q")
        self.steps = 0
        self._walks = self._both(robot, qv, d, opt, clear)
        self._result: Interval | None = None

    def _both(
        self, robot: Robot, qv: np.ndarray, d: np.ndarray, opt: NumericalOptions, clear: _Clearance | None
    ) -> Generator[None, None, Interval]:
        ns0, target = self.ns0, self.target
        hi, hi_c, hi_q = yield from _walk(robot, qv, ns0, d, target, opt, clear)
        if hi_c is None and hi - ns0 >= TWO_PI:
            return Interval(ns0 - math.pi, ns0 + math.pi, True, "numerical")
        yield  # (the first walk's last step was this call's step)
        lo, lo_c, lo_q = yield from _walk(robot, qv, ns0, -d, target, opt, clear)
        if hi - lo > TWO_PI:
            lo = hi - TWO_PI
        return Interval(min(lo, ns0), max(hi, ns0), False, "numerical", lo_c, hi_c, lo_q, hi_q)

    def advance(self, steps: float) -> Interval | None:
        """At most ``steps`` more pieces (``math.inf``: to the end); the interval once it is done."""
        taken = 0
        while self._result is None and taken < steps:
            taken += 1
            self.steps += 1
            try:
                next(self._walks)
            except StopIteration as done:
                self._result = done.value
        return self._result


def numerical_interval(
    robot: Robot,
    q: object,
    options: NumericalOptions | None = None,
    obstacles: Sequence[Obstacle] = (),
    margin: float = 0.03,
) -> Interval:
    """Continuity interval by following the self-motion numerically (any 7-DOF arm): a
    :class:`NumericalWalk` to its end (with ``obstacles``: also ended where a link capsule comes within
    ``margin``, m, of one).

    Accuracy: limit ends to ~1e-9 rad (exact crossing solve); obstacle ends to 1e-7 rad in arm angle
    (bisection); singular ends to one step (``options.step_rad`` in joint space).
    """
    interval = NumericalWalk(robot, q, options, obstacles, margin).advance(math.inf)
    assert interval is not None  # (a walk to the end has its interval)
    return interval
