"""Joint-limit continuity intervals of the arm angle (METHOD §5, [E 7]–[E 9]).

With the tool pose and the branch held, each joint is a function ``θ_k(ns)``
(:class:`qpnso.elbow.SelfMotion`).  ``Ψ_k`` is the set of arm angles where joint
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
therefore never crossed.

Arc convention: an arc is ``(lo, hi)`` with ``-π ≤ lo < π`` and
``lo < hi ≤ lo + 2π``; an arc crossing ±π is *not* split (its ``hi`` exceeds
π).  The full circle is ``(-π, π)``.

Numerical (other arms, e.g. the Panda): the self-motion is followed from ``q``
in both directions with null-space steps and Newton pose correction; a limit
crossing is then solved exactly (the crossing joint pinned at its limit, the
other six solving the tool pose by Newton to 1e-12), so the ends are accurate
to about 1e-9 rad.  Excursions past a limit shorter than one step
(``NumericalOptions.step_rad``) can be missed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

from qpnso.elbow import (
    SelfMotion,
    _TAN,
    _branch_of,
    _checked,
    _self_motion,
    _status_after_fk,
    srs_geometry,
    arm_angle,
    arm_angle_gradient,
    arm_angle_status,
    as_pose,
    branch,
    is_srs,
    self_motion,
)
from qpnso.errors import SingularityError
from qpnso.robot import Robot

TWO_PI = 2.0 * math.pi
SINGULAR_TOL = 1e-12
"""A cosine-type joint whose ``cos θ`` reaches 1 − SINGULAR_TOL passes through 0 (singular cut)."""
_MERGE_TOL = 1e-12
_FEASIBLE_TOL = 1e-10
_ALL_JOINTS = np.arange(7)
_PLUS_MINUS = np.array([[1.0], [-1.0]])


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


def wrap(angle):  # type: ignore[no-untyped-def]
    """Angle(s) (rad, float or array) wrapped into [-π, π)."""
    return (angle + math.pi) % TWO_PI - math.pi


# ----------------------------------------------------------------- cut points
_BOUNDS = ("min", "max")


@dataclass(frozen=True)
class _RowTable:
    """Limit rows that can bind for one robot's limits and one branch (cached).

    ``joint``/``bound`` (0 min, 1 max) per row, ``tangent`` mask, ``cos_phi``,
    ``sin_phi`` (φ = sign·θ_limit), ``cz`` = (0, 0, cos θ_limit) and
    ``rate_sign``: dθ/dns has the sign of ``rate_sign · d(residual)/dns`` at a genuine root.
    """

    joint: np.ndarray
    bound: np.ndarray
    tangent: np.ndarray
    cos_phi: np.ndarray
    sin_phi: np.ndarray
    cz: np.ndarray
    rate_sign: np.ndarray
    cosine: np.ndarray
    is_max: np.ndarray


_TABLES: dict[tuple, _RowTable] = {}


def _row_table(sm: SelfMotion, q_min: np.ndarray, q_max: np.ndarray) -> _RowTable:
    key = (q_min.tobytes(), q_max.tobytes(), sm.sign.tobytes(), sm.kind.tobytes())
    table = _TABLES.get(key)
    if table is None:
        joint = np.repeat(_ALL_JOINTS[sm.kind != 2], 2)
        bound = np.tile([0, 1], joint.size // 2)
        theta = np.where(bound == 1, q_max[joint], q_min[joint])
        tangent = sm.kind[joint] == _TAN
        keep = tangent | (theta * sm.sign[joint] >= 0)  # θ = s·acos(x) never reaches a bound of the other sign
        joint, bound, theta, tangent = joint[keep], bound[keep], theta[keep], tangent[keep]
        phi = sm.sign[joint] * theta
        cz = np.zeros((joint.size, 3))
        cz[:, 2] = np.cos(theta)
        rate = np.where(tangent, sm.sign[joint], -sm.sign[joint])
        table = _RowTable(
            joint, bound, tangent[:, None], np.cos(phi)[:, None], np.sin(phi)[:, None], cz, rate, ~tangent, bound == 1
        )
        _TABLES[key] = table
    return table


def _residual_coefficients(sm: SelfMotion, t: _RowTable) -> np.ndarray:
    """Rows ``e`` with ``e·(sin ns, cos ns, 1) = 0`` exactly at the limit crossings.

    Tangent type: ``atan2(num, den) = φ`` ⇔ ``num cos φ − den sin φ = 0``;
    cosine type: ``den − cos θ_limit = 0``.
    """
    num, den = sm.num[t.joint], sm.den[t.joint]
    return np.where(t.tangent, num * t.cos_phi - den * t.sin_phi, den - t.cz)


def _solve_sin_cos(a: np.ndarray, b: np.ndarray, c: np.ndarray, with_slope: bool = False):  # type: ignore[no-untyped-def]
    """Roots of ``a sin x + b cos x = c`` (vectorised): shape (2, n), NaN where none.

    ``atan2(a, b) ± acos(c/r)`` (r = √(a²+b²)), then one Newton step on the
    residual.  With ``with_slope``, also the residual's slope ``∓ r sin δ`` at each root.
    """
    r = np.hypot(a, b)
    ok = (r > 1e-14) & (np.abs(c) <= r)
    delta = np.arccos(np.clip(c / np.maximum(r, 1e-14), -1.0, 1.0))
    base = np.arctan2(a, b)
    roots = base + _PLUS_MINUS * delta
    f = a * np.sin(roots) + b * np.cos(roots) - c
    df = a * np.cos(roots) - b * np.sin(roots)
    steep = np.abs(df) > 1e-6 * r
    step = np.where(steep, f / np.where(steep, df, 1.0), 0.0)
    roots = np.where(ok, roots - step, np.nan)
    if not with_slope:
        return roots
    return roots, -_PLUS_MINUS * (r * np.sin(delta))


def _cuts(sm: SelfMotion, q_min: np.ndarray, q_max: np.ndarray, joints: np.ndarray):  # type: ignore[no-untyped-def]
    """Sorted, de-duplicated cut points in [-π, π) and a function naming each cut's cause.

    Returns ``(angles, labels, hard, cause)``: ``labels[i]`` indexes the limit
    row, or is ``-1 − k`` for a singular cut of joint k; ``hard`` marks singular cuts.
    """
    t = _row_table(sm, q_min, q_max)
    rows = np.flatnonzero(np.isin(t.joint, joints))
    e = _residual_coefficients(sm, t)[rows]
    roots = _solve_sin_cos(e[:, 0], e[:, 1], -e[:, 2])
    joint, bound = t.joint, t.bound
    angles = [roots.reshape(-1)]
    labels = [np.tile(rows, 2)]
    for k in (1, 5):  # joints 2 and 6 through 0: singular cuts
        if k in joints:
            sa, cb, c0 = sm.den[k]
            if c0 + math.hypot(sa, cb) >= 1.0 - SINGULAR_TOL:
                angles.append(np.array([math.atan2(sa, cb)]))
                labels.append(np.array([-1 - k]))
    ang, lab = np.concatenate(angles), np.concatenate(labels)
    keep = np.isfinite(ang)
    ang, lab = wrap(ang[keep]), lab[keep]
    order = np.lexsort((lab >= 0, ang))  # singular first among equal angles
    ang, lab = ang[order], lab[order]
    if ang.size > 1:
        distinct = np.concatenate([[True], np.diff(ang) > _MERGE_TOL])
        ang, lab = ang[distinct], lab[distinct]
        if ang[-1] - ang[0] > TWO_PI - _MERGE_TOL:
            ang, lab = ang[:-1], lab[:-1]

    def cause(label: int) -> Cause:
        if label < 0:
            return Cause("singular", -1 - label)
        return Cause("limit", int(joint[label]), _BOUNDS[bound[label]])

    return ang, lab, lab < 0, cause


def _arcs(sm: SelfMotion, q_min: np.ndarray, q_max: np.ndarray, joints: np.ndarray):  # type: ignore[no-untyped-def]
    """Feasible arcs ``[(lo, hi, lo_cause, hi_cause)]`` for the given joints (0-based).

    The full circle is ``(-π, π, None, None)``.
    """
    cuts, labels, hard, cause = _cuts(sm, q_min, q_max, joints)
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
        arcs.append((float(cuts[i]), end, cause(int(labels[i])), cause(int(labels[(j + 1) % m]))))
    return sorted(arcs, key=lambda arc: arc[0])


def _closed_form_interval(sm: SelfMotion, ns0: float, q_min: np.ndarray, q_max: np.ndarray) -> Interval:
    """[E 9] directly: the nearest genuine exit crossing (or singular cut) on each side of ``ns0``.

    Valid because the configuration at ``ns0`` is within all limits: moving away
    from it, the first limit crossing of any joint is where that joint leaves.
    A tangent-type root is genuine when ``(num, den)`` points along φ (not
    φ + π); at root ``atan2(a,b) ∓ acos(c/r)`` the residual's slope is ``∓ r sin δ``,
    which gives the direction in which the joint leaves its bound.
    """
    t = _row_table(sm, q_min, q_max)
    num, den = sm.num[t.joint], sm.den[t.joint]
    e = _residual_coefficients(sm, t)
    roots, slope = _solve_sin_cos(e[:, 0], e[:, 1], -e[:, 2], with_slope=True)
    g = num * t.sin_phi + den * t.cos_phi
    along = g[:, 0] * np.sin(roots) + g[:, 1] * np.cos(roots) + g[:, 2]
    ok = (t.cosine | (along > 0)) & np.isfinite(roots)
    up = (slope * t.rate_sign > 0) == t.is_max
    ahead = (roots - ns0) % TWO_PI  # behind = 2π − ahead; ends within 1e-9 of ns0 count as 0
    behind = np.where(ok & ~up, np.where(ahead < 1e-9, 0.0, TWO_PI - ahead), np.inf).reshape(-1)
    ahead = np.where(ok & up, np.where(ahead > TWO_PI - 1e-9, 0.0, ahead), np.inf).reshape(-1)
    i_hi, i_lo = int(np.argmin(ahead)), int(np.argmin(behind))
    n = t.joint.size
    hi = (float(ahead[i_hi]), ("limit", int(t.joint[i_hi % n]), _BOUNDS[t.bound[i_hi % n]]))
    lo = (float(behind[i_lo]), ("limit", int(t.joint[i_lo % n]), _BOUNDS[t.bound[i_lo % n]]))
    for k in (1, 5):  # joints 2 and 6 through 0: singular cuts end the interval on both sides
        sa, cb, c0 = sm.den[k]
        if c0 + math.hypot(sa, cb) >= 1.0 - SINGULAR_TOL:
            x = math.atan2(sa, cb)
            hi = min(hi, ((x - ns0) % TWO_PI, ("singular", k, "")))
            lo = min(lo, ((ns0 - x) % TWO_PI, ("singular", k, "")))
    if math.isinf(hi[0]) and math.isinf(lo[0]):
        return Interval(ns0 - math.pi, ns0 + math.pi, True, "closed_form")
    return Interval(ns0 - lo[0], ns0 + hi[0], False, "closed_form", Cause(*lo[1]), Cause(*hi[1]))


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
    sm = self_motion(robot, as_pose(pose), branch_)
    everything = _arcs(sm, robot.q_min, robot.q_max, _ALL_JOINTS)
    psi = [(lo, hi) for lo, hi, _, _ in everything]
    if not per_joint:
        return psi
    per = {k: [(lo, hi) for lo, hi, _, _ in _arcs(sm, robot.q_min, robot.q_max, np.array([k]))] for k in range(7)}
    return psi, per


def continuity_interval(robot: Robot, q: object, options: "NumericalOptions | None" = None) -> Interval:
    """The continuity interval [E 9] holding the arm angle of ``q`` (rad, unwrapped).

    Closed form for S-R-S arms, else :func:`numerical_interval`.  Raises
    JointLimitError if ``q`` is outside its limits and SingularityError if the
    arm angle or branch of ``q`` is undefined.
    """
    qv = robot.check_q(q)
    if not is_srs(robot):
        return numerical_interval(robot, qv, options)
    pin.framesForwardKinematics(robot.model, robot.data, qv)
    ns = _checked(_status_after_fk(robot))
    pose = robot.data.oMf[robot.tool_frame_id]
    sm = _self_motion(srs_geometry(robot), pose, _branch_of(qv))
    return _closed_form_interval(sm, ns, robot.q_min, robot.q_max)


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


def _correct(robot: Robot, q: np.ndarray, target: pin.SE3, tol: float, free: np.ndarray | None = None) -> np.ndarray:
    """Newton iterations on the tool pose, moving only the ``free`` joints."""
    cols = np.arange(robot.nq) if free is None else free
    q = q.copy()
    for _ in range(30):
        err = _pose_error(robot, q, target)
        if np.abs(err).max() < tol:
            return q
        jac = robot.jacobian(q)[:, cols]
        q[cols] += np.linalg.lstsq(jac, err, rcond=None)[0]
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


def _crossing(robot: Robot, q_in: np.ndarray, q_out: np.ndarray, target: pin.SE3, tol: float) -> tuple[np.ndarray, Cause]:
    """Exact first limit crossing between a feasible and an infeasible configuration."""
    over = np.maximum(q_out - robot.q_max, 0) + np.maximum(robot.q_min - q_out, 0)
    frac = np.full(robot.nq, np.inf)
    for k in np.flatnonzero(over > 0):
        limit = robot.q_max[k] if q_out[k] > robot.q_max[k] else robot.q_min[k]
        frac[k] = (limit - q_in[k]) / (q_out[k] - q_in[k])
    k = int(np.argmin(frac))
    bound = "max" if q_out[k] > robot.q_max[k] else "min"
    q = q_in + frac[k] * (q_out - q_in)
    q[k] = robot.q_max[k] if bound == "max" else robot.q_min[k]
    q = _correct(robot, q, target, tol, free=np.delete(np.arange(robot.nq), k))
    return q, Cause("limit", k, bound)


def _walk(robot: Robot, q0: np.ndarray, ns0: float, direction: np.ndarray, target: pin.SE3,
          opt: NumericalOptions) -> tuple[float, Cause | None, np.ndarray]:
    """Follow the self-motion from ``q0`` along ``direction``: unwrapped ns at the end, its cause, q there."""
    q, ns, d = q0.copy(), ns0, direction
    for _ in range(opt.max_steps):
        q_new = _correct(robot, q + opt.step_rad * d, target, opt.pose_tol)
        status = arm_angle_status(robot, q_new)
        if np.any(q_new > robot.q_max) or np.any(q_new < robot.q_min):
            q_end, cause = _crossing(robot, q, q_new, target, opt.pose_tol)
            return ns + wrap(arm_angle_status(robot, q_end).value - ns), cause, q_end
        d_new = _null_direction(robot, q_new, d, opt.sigma_min)
        if d_new is None or not status.ok:
            end = ns + wrap(status.value - ns) if math.isfinite(status.value) else ns
            return end, Cause("singular", -1), q_new
        ns += wrap(status.value - ns)
        q, d = q_new, d_new
        if abs(ns - ns0) >= TWO_PI:
            return ns, None, q
    return ns, Cause("unfinished", -1), q  # max_steps reached: an end that is not a limit


def numerical_interval(robot: Robot, q: object, options: NumericalOptions | None = None) -> Interval:
    """Continuity interval by following the self-motion numerically (any 7-DOF arm).

    Accuracy: limit ends to ~1e-9 rad (exact crossing solve); singular ends to
    one step (``options.step_rad`` in joint space).
    """
    opt = options or NumericalOptions()
    qv = robot.check_q(q)
    ns0 = arm_angle(robot, qv)
    target = robot.tool_pose(qv)
    grad = arm_angle_gradient(robot, qv)
    d = _null_direction(robot, qv, grad, opt.sigma_min)
    if d is None:
        raise SingularityError("the tool Jacobian is singular at q: the self-motion is not defined")
    if abs(d @ grad) < 1e-12:
        raise SingularityError("the self-motion does not change the arm angle at q")
    hi, hi_c, hi_q = _walk(robot, qv, ns0, d, target, opt)
    if hi_c is None and hi - ns0 >= TWO_PI:
        return Interval(ns0 - math.pi, ns0 + math.pi, True, "numerical")
    lo, lo_c, lo_q = _walk(robot, qv, ns0, -d, target, opt)
    if hi - lo > TWO_PI:
        lo = hi - TWO_PI
    return Interval(min(lo, ns0), max(hi, ns0), False, "numerical", lo_c, hi_c, lo_q, hi_q)

