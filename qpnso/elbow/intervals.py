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
"""

from __future__ import annotations

import math
from collections.abc import Generator
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
from qpnso.errors import ModelError, SingularityError
from qpnso.model.robot import Robot

TWO_PI = 2.0 * math.pi
_MERGE_TOL = 1e-12
_FEASIBLE_TOL = 1e-10
_ALL_JOINTS = np.arange(7)


@dataclass(frozen=True)
class Cause:
    """What ends an interval: a joint limit (``"limit"``, ``bound`` "min"/"max"),
    a singular point (``"singular"``: joint 2 or 6 through 0 in the closed form;
    a rank-deficient Jacobian or undefined arm angle in the numerical method,
    ``joint = -1``) or, numerical method only, ``"unfinished"`` (step budget
    exhausted).  ``joint`` is 0-based."""

    kind: str
    joint: int
    bound: str = ""


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


def end_cause(code: int) -> Cause | None:
    """The :class:`Cause` of an end code of :mod:`qpnso.elbow.closed_form` (a limit ``2·joint + is_max``, a
    singular cut ``−1 − joint``, :data:`~qpnso.elbow.closed_form.NO_END`)."""
    if code == NO_END:
        return None
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

    The full circle is ``(-π, π, None, None)``.
    """
    cuts, labels, hard = _cuts(sm, q_min, q_max, joints)
    lo_lim, hi_lim = q_min[joints] - _FEASIBLE_TOL, q_max[joints] + _FEASIBLE_TOL
    m = cuts.size
    if m == 0:
        q = sm.joints(np.array([0.0]))[:, joints]
        return [(-math.pi, math.pi, None, None)] if np.all((q >= lo_lim) & (q <= hi_lim)) else []
    hi = np.append(cuts[1:], cuts[0] + TWO_PI)
    q = sm.joints(0.5 * (cuts + hi))[:, joints]
    feasible = np.all((q >= lo_lim) & (q <= hi_lim), axis=1).tolist()
    hard_l = hard.tolist()
    starts = [i for i in range(m) if feasible[i] and (hard_l[i] or not feasible[i - 1])]
    if not starts:
        return [(-math.pi, math.pi, None, None)] if all(feasible) else []
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


# --------------------------------------------------------------- public API
def feasible_intervals(
    robot: Robot, pose: object, branch_: object, per_joint: bool = False
) -> list[tuple[float, float]] | tuple[list[tuple[float, float]], dict[int, list[tuple[float, float]]]]:
    """Ψ [E 8]: arcs of arm angles (rad) where all joint limits hold (S-R-S, closed form).

    Arcs ``(lo, hi)``, sorted by ``lo``, ``-π ≤ lo < π``, ``lo < hi ≤ lo + 2π``
    (an arc crossing ±π is not split).  Singular points (joint 2 or 6 through 0)
    end arcs.  With ``per_joint=True`` also returns ``{k: Ψ_k}`` [E 7] for
    k = 0…6 (0-based; limits only, no singular cuts except for joints 2 and 6 themselves).
    """
    wide = _limits_beyond_pi(robot)
    if wide is not None:
        raise ModelError(
            f"closed-form arcs need joint limits inside ±π; joint {wide + 1} has "
            f"[{robot.q_min[wide]:.6g}, {robot.q_max[wide]:.6g}] rad (use continuity_interval, numerical)"
        )
    sm = self_motion(robot, as_pose(pose), branch_)
    everything = _arcs(sm, robot.q_min, robot.q_max, _ALL_JOINTS)
    psi = [(lo, hi) for lo, hi, _, _ in everything]
    if not per_joint:
        return psi
    per = {k: [(lo, hi) for lo, hi, _, _ in _arcs(sm, robot.q_min, robot.q_max, np.array([k]))] for k in range(7)}
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


def continuity_interval(robot: Robot, q: object, options: "NumericalOptions | None" = None) -> Interval:
    """The continuity interval [E 9] holding the arm angle of ``q`` (rad, unwrapped).

    Closed form (:func:`qpnso.elbow.closed_form.srs_interval`, the kernel the control tick runs) when
    :func:`closed_form_applies`, else :func:`numerical_interval`.  Raises
    JointLimitError if ``q`` is outside its limits and SingularityError if the
    arm angle or branch of ``q`` is undefined.
    """
    qv = robot.check_q(q)
    if not closed_form_applies(robot):
        return numerical_interval(robot, qv, options)
    pin.framesForwardKinematics(robot.model, robot.data, qv)
    ns = _checked(_status_after_fk(robot))
    branch_ = _branch_of(qv)
    g = srs_geometry(robot)
    R, p = pose_arrays(robot.data.oMf[robot.tool_frame_id])
    code, lo, hi, full, lo_code, hi_code, dist = srs_interval(
        g.record[0], R, p, *branch_floats(branch_), ns, robot.q_min, robot.q_max
    )
    raise_unless_reached(code, dist, g)
    return Interval(lo, hi, bool(full), "closed_form", end_cause(lo_code), end_cause(hi_code))


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
    """6-vector (world, linear first) that moves the tool from ``q``'s pose to ``target``."""
    cur = robot.tool_pose(q)
    return np.concatenate([target.translation - cur.translation, pin.log3(target.rotation @ cur.rotation.T)])


def _newton(
    robot: Robot, q: np.ndarray, target: pin.SE3, tol: float, free: np.ndarray | None = None
) -> Generator[None, None, np.ndarray]:
    """Newton iterations on the tool pose, moving only the ``free`` joints, yielding after each: returns the
    corrected configuration (SingularityError if 30 do not reach 1e-9)."""
    cols = np.arange(robot.nq) if free is None else free
    q = q.copy()
    for _ in range(30):
        err = _pose_error(robot, q, target)
        if np.abs(err).max() < tol:
            return q
        jac = robot.jacobian(q)[:, cols]
        q[cols] += np.linalg.lstsq(jac, err, rcond=None)[0]
        yield
    if np.abs(_pose_error(robot, q, target)).max() > 1e-9:
        raise SingularityError("pose correction did not converge while following the self-motion")
    return q


def _null_direction(robot: Robot, q: np.ndarray, prev: np.ndarray, sigma_min: float) -> np.ndarray | None:
    """Unit null-space direction of the tool Jacobian, oriented like ``prev``; None if singular."""
    _, s, vt = np.linalg.svd(robot.jacobian(q))
    if s[-1] < sigma_min:
        return None
    n = vt[-1]
    return n if n @ prev >= 0 else -n


def _crossing(
    robot: Robot, q_in: np.ndarray, q_out: np.ndarray, target: pin.SE3, tol: float
) -> Generator[None, None, tuple[np.ndarray, Cause]]:
    """Exact first limit crossing between a feasible and an infeasible configuration (the crossing joint pinned
    at its limit, the other six solving the pose: :func:`_newton`, yielding after each iteration)."""
    over = np.maximum(q_out - robot.q_max, 0) + np.maximum(robot.q_min - q_out, 0)
    frac = np.full(robot.nq, np.inf)
    for j in np.flatnonzero(over > 0):
        limit = robot.q_max[j] if q_out[j] > robot.q_max[j] else robot.q_min[j]
        frac[j] = (limit - q_in[j]) / (q_out[j] - q_in[j])
    k = int(np.argmin(frac))
    bound = "max" if q_out[k] > robot.q_max[k] else "min"
    q = q_in + frac[k] * (q_out - q_in)
    q[k] = robot.q_max[k] if bound == "max" else robot.q_min[k]
    q = yield from _newton(robot, q, target, tol, free=np.delete(np.arange(robot.nq), k))
    return q, Cause("limit", k, bound)


def _walk(
    robot: Robot, q0: np.ndarray, ns0: float, direction: np.ndarray, target: pin.SE3, opt: NumericalOptions
) -> Generator[None, None, tuple[float, Cause | None, np.ndarray]]:
    """Follow the self-motion from ``q0`` along ``direction``, yielding after each Newton iteration of a step's
    pose correction or of a limit crossing's exact solve and after each step (the limits, the arm angle and the
    next null-space direction), but the last: returns the unwrapped ns at the end, its cause and q there."""
    q, ns, d = q0.copy(), ns0, direction
    for _ in range(opt.max_steps):
        q_new = yield from _newton(robot, q + opt.step_rad * d, target, opt.pose_tol)
        status = arm_angle_status(robot, q_new)
        if np.any(q_new > robot.q_max) or np.any(q_new < robot.q_min):
            yield  # (this step found the crossing; its exact solve is the next pieces)
            q_end, cause = yield from _crossing(robot, q, q_new, target, opt.pose_tol)
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
    solve, or the rest of a step (``NumericalOptions.step_rad`` each: the limits, the arm angle, an SVD), about
    0.1 ms each on the Panda — and returns the :class:`Interval` once both walks have ended (None before).  The
    control tick of an arm without the closed form advances one a few pieces a tick
    (``ControllerConfig.interval_steps_per_tick``): a whole walk took 35 ms median on the Panda, and was renewed
    inside a tick every ``interval_period`` ticks of a moving tool.  Raises SingularityError where the self-motion
    is undefined at ``q`` (here) or JointLimitError for ``q`` outside its limits."""

    def __init__(self, robot: Robot, q: object, options: NumericalOptions | None = None) -> None:
        opt = options or NumericalOptions()
        qv = robot.check_q(q)
        self.ns0 = arm_angle(robot, qv)
        self.target = robot.tool_pose(qv)
        grad = arm_angle_gradient(robot, qv)
        d = _null_direction(robot, qv, grad, opt.sigma_min)
        if d is None:
            raise SingularityError("the tool Jacobian is singular at q: the self-motion is not defined")
        if abs(d @ grad) < 1e-12:
            raise SingularityError("the self-motion does not change the arm angle at q")
        self.steps = 0
        self._walks = self._both(robot, qv, d, opt)
        self._result: Interval | None = None

    def _both(
        self, robot: Robot, qv: np.ndarray, d: np.ndarray, opt: NumericalOptions
    ) -> Generator[None, None, Interval]:
        ns0, target = self.ns0, self.target
        hi, hi_c, hi_q = yield from _walk(robot, qv, ns0, d, target, opt)
        if hi_c is None and hi - ns0 >= TWO_PI:
            return Interval(ns0 - math.pi, ns0 + math.pi, True, "numerical")
        yield  # (the first walk's last step was this call's step)
        lo, lo_c, lo_q = yield from _walk(robot, qv, ns0, -d, target, opt)
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


def numerical_interval(robot: Robot, q: object, options: NumericalOptions | None = None) -> Interval:
    """Continuity interval by following the self-motion numerically (any 7-DOF arm): a
    :class:`NumericalWalk` to its end.

    Accuracy: limit ends to ~1e-9 rad (exact crossing solve); singular ends to
    one step (``options.step_rad`` in joint space).
    """
    interval = NumericalWalk(robot, q, options).advance(math.inf)
    assert interval is not None  # (a walk to the end has its interval)
    return interval
