"""The elbow of a 7-DOF arm: the arm angle and its gradient (docs/method.md §4).

Arm angle [E 2]–[E 4], world frame, ``z0`` the world vertical::

    u_sin = z0 × p_sw / |z0 × p_sw|,   u_cos = p_sw × u_sin / |p_sw × u_sin|
    ns    = atan2(p_se · u_sin, p_se · u_cos)          (rad, ns = 0: elbow up)

``p_s``, ``p_e``, ``p_w`` are the shoulder, elbow and wrist centres
(:class:`ElbowPoints`).  ``ns`` is undefined when the wrist is on the vertical
through the shoulder and meaningless when the elbow is straight; both are
reported (:func:`arm_angle_status`) and :func:`arm_angle` raises
:class:`~qpnso.errors.SingularityError` rather than returning NaN.

The S-R-S geometry, the branch and the closed-form self-motion and IK are in
:mod:`qpnso.elbow.srs` (it builds on the points and helpers here; S-R-S arms take
their elbow points from it).
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import casadi as ca
import numpy as np
import pinocchio as pin

from qpnso.errors import ModelError, SingularityError
from qpnso.model.robot import Robot, as_vector
from qpnso.model.symbolic import SymbolicModel

Z0 = np.array([0.0, 0.0, 1.0])
"""World vertical used as the arm-angle reference [E 3]."""
WRIST_CONE_DEG = 2.0
"""Default half-angle (deg) of the cone around the vertical through the shoulder
inside which the arm angle is reported singular (``"wrist_vertical"``)."""
ELBOW_OFFSET_MIN_M = 0.005
"""Default minimum distance (m) of the elbow from the shoulder–wrist line below
which the arm angle is reported singular (``"elbow_straight"``)."""


# ----------------------------------------------------------------- arm angle
def _tcross(a, b) -> tuple[float, float, float]:
    """Cross product of two 3-sequences as a tuple (plain floats: fast for one pair)."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of 3-vectors as an array (faster than ``np.cross`` for one pair)."""
    return np.array(_tcross(a, b))


def _dot(a, b) -> float:
    return float(a[0] * b[0] + a[1] * b[1] + a[2] * b[2])


_FLOAT_OPS = (
    lambda a, b: (a[0] - b[0], a[1] - b[1], a[2] - b[2]),
    _tcross,
    _dot,
    lambda a: math.sqrt(_dot(a, a)),
    math.atan2,
)
_CASADI_OPS = (lambda a, b: a - b, ca.cross, ca.dot, ca.norm_2, ca.atan2)


def _arm_angle_terms(ps, pe, pw, z0, ops):
    """[E 2]–[E 4] written once for NumPy and CasADi.

    Returns ``(ns, wrist_sin, elbow_offset)``: the arm angle (rad), the sine of
    the angle between ``p_sw`` and ``z0``, and the distance (m) of the elbow
    from the line ``p_s p_w``.  With ``u_sin = z_x/|z_x|`` (``z_x = z0 × p_sw``)
    and ``u_cos = p_sw × z_x/(|z_x| |p_sw|)`` the common positive factor
    ``1/|z_x|`` drops out of the atan2, so the expression has no division.
    """
    sub, cross, dot, norm, atan2 = ops
    p_sw = sub(pw, ps)
    p_se = sub(pe, ps)
    n_sw = norm(p_sw)
    z_x = cross(z0, p_sw)
    ns = atan2(n_sw * dot(p_se, z_x), dot(p_se, cross(p_sw, z_x)))
    return ns, norm(z_x) / n_sw, norm(cross(p_sw, p_se)) / n_sw


@dataclass(frozen=True)
class ElbowPoints:
    """Shoulder, elbow and wrist centres, each a point fixed to a joint's frame.

    ``*_joint`` are Pinocchio joint indices (1-based); ``*_offset`` the point in
    that joint's frame (m).  For S-R-S arms they are derived from the model
    (:func:`elbow_points`); for other arms they are a documented choice.
    """

    shoulder_joint: int
    elbow_joint: int
    wrist_joint: int
    shoulder_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    elbow_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    wrist_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def world(self, data: pin.Data) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World positions (m) of ``p_s, p_e, p_w`` after ``pin.forwardKinematics``."""
        return tuple(
            data.oMi[j].act(np.asarray(off)) if any(off) else data.oMi[j].translation
            for j, off in (
                (self.shoulder_joint, self.shoulder_offset),
                (self.elbow_joint, self.elbow_offset),
                (self.wrist_joint, self.wrist_offset),
            )
        )

    def symbolic(self, sym: SymbolicModel) -> tuple[ca.SX, ca.SX, ca.SX]:
        """World positions of ``p_s, p_e, p_w`` as CasADi expressions of ``sym.q``."""
        return (
            sym.oMi[self.shoulder_joint].point(np.asarray(self.shoulder_offset)),
            sym.oMi[self.elbow_joint].point(np.asarray(self.elbow_offset)),
            sym.oMi[self.wrist_joint].point(np.asarray(self.wrist_offset)),
        )


@dataclass(frozen=True)
class ElbowCircle:
    """The circle the elbow turns on about the shoulder–wrist line, parametrised by the arm angle: [E 2]–[E 4]
    read backwards, ``point(ns) = centre + radius (cos ns · u_cos + sin ns · u_sin)`` (m, world frame), so that
    :func:`arm_angle` of the elbow at ``point(ns)`` is ``ns``.  For an S-R-S arm it is the elbow's whole
    self-motion at the current shoulder and wrist; for another arm the circle through the current elbow."""

    centre: np.ndarray
    u_cos: np.ndarray
    u_sin: np.ndarray
    radius: float

    @property
    def axis(self) -> np.ndarray:
        """Unit vector from the shoulder towards the wrist (``u_cos × u_sin``)."""
        return np.cross(self.u_cos, self.u_sin)

    def point(self, ns: object) -> np.ndarray:
        """The elbow at arm angle(s) ``ns`` (rad): shape ``(3,)`` or ``(len(ns), 3)``, m, world frame."""
        a = np.asarray(ns, dtype=float)[..., None]
        return self.centre + self.radius * (np.cos(a) * self.u_cos + np.sin(a) * self.u_sin)


def elbow_circle(ps: np.ndarray, pe: np.ndarray, pw: np.ndarray) -> ElbowCircle:
    """The :class:`ElbowCircle` of shoulder, elbow and wrist centres ``ps, pe, pw`` (m, world frame), with
    ``u_sin = z0 × p_sw/|·|`` and ``u_cos = p_sw × u_sin/|·|`` as in [E 3]; a SingularityError where the arm
    angle is undefined (the wrist on the vertical through the shoulder, or wrist on the shoulder)."""
    p_sw, p_se = np.asarray(pw, float) - ps, np.asarray(pe, float) - ps
    z_x = _cross(Z0, p_sw)
    if not np.linalg.norm(z_x) > 1e-12:
        raise SingularityError("the elbow circle is undefined: the wrist is on the vertical through the shoulder")
    u_sin = z_x / np.linalg.norm(z_x)
    u_cos = _cross(p_sw, u_sin)
    u_cos /= np.linalg.norm(u_cos)
    axis = p_sw / np.linalg.norm(p_sw)
    along = float(p_se @ axis)
    return ElbowCircle(np.asarray(ps, float) + along * axis, u_cos, u_sin, float(np.linalg.norm(p_se - along * axis)))


@dataclass(frozen=True)
class ArmAngle:
    """Arm angle with its singularity measures.

    ``value`` (rad, in (-π, π]) is NaN only when ``status != "ok"`` *and* the
    formula is undefined; ``wrist_sin`` = |p_sw × z0|/|p_sw|; ``elbow_offset_m``
    the elbow's distance from the shoulder–wrist line (m).
    """

    value: float
    status: str  # "ok" | "wrist_vertical" | "elbow_straight"
    wrist_sin: float
    elbow_offset_m: float

    @property
    def ok(self) -> bool:
        return self.status == "ok"


def _cached(cache: weakref.WeakKeyDictionary, robot: Robot, build):
    value = cache.get(robot)
    if value is None:
        value = build(robot)
        cache[robot] = value
    return value


_POINTS_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_GRADIENT_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def elbow_points(robot: Robot) -> ElbowPoints:
    """Shoulder/elbow/wrist centres of ``robot`` (cached per robot).

    S-R-S arms: from :func:`~qpnso.elbow.srs.srs_geometry` (points fixed to joints 2, 4, 6).
    Other 7-DOF arms (e.g. the Panda), a documented choice: shoulder = origin of
    joint 2 (on the axis of joint 1), elbow = origin of joint 4, wrist = origin
    of the last joint (on its axis, so it stays fixed in the world while the tool
    pose is held and the arm moves in its self-motion).
    """
    return _cached(_POINTS_CACHE, robot, _build_elbow_points)


def _build_elbow_points(robot: Robot) -> ElbowPoints:
    from qpnso.elbow.srs import is_srs, srs_geometry  # srs builds on this module: imported when first needed

    if is_srs(robot):
        return srs_geometry(robot).points
    if robot.model.njoints - 1 < 4:
        raise ModelError(f"{robot.name}: an arm angle needs at least 4 joints")
    return ElbowPoints(shoulder_joint=2, elbow_joint=4, wrist_joint=robot.model.njoints - 1)


def arm_angle_expression(sym: SymbolicModel, points: ElbowPoints) -> tuple[ca.SX, ca.SX]:
    """Arm angle [E 2]–[E 4] as CasADi SX in ``sym.q``, and its singularity measures.

    Returns ``(ns, measures)`` with ``measures = [wrist_sin, elbow_offset_m]``
    (SX 2×1): compare them with sin(:data:`WRIST_CONE_DEG`) and
    :data:`ELBOW_OFFSET_MIN_M` before trusting ``ns`` or its gradient.
    """
    ps, pe, pw = points.symbolic(sym)
    ns, wrist_sin, offset = _arm_angle_terms(ps, pe, pw, ca.DM(Z0), _CASADI_OPS)
    return ns, ca.vertcat(wrist_sin, offset)


def arm_angle_status(
    robot: Robot,
    q: object,
    wrist_cone_deg: float = WRIST_CONE_DEG,
    elbow_offset_min: float = ELBOW_OFFSET_MIN_M,
) -> ArmAngle:
    """Arm angle of configuration ``q`` (rad) with a singularity status (docs/method.md §4)."""
    qv = as_vector(q, robot.nq, "q")
    pin.forwardKinematics(robot.model, robot.data, qv)
    return _status_after_fk(robot, wrist_cone_deg, elbow_offset_min)


def _status_after_fk(
    robot: Robot, wrist_cone_deg: float = WRIST_CONE_DEG, elbow_offset_min: float = ELBOW_OFFSET_MIN_M
) -> ArmAngle:
    """:func:`arm_angle_status` from ``robot.data`` after forward kinematics."""
    ps, pe, pw = (p.tolist() for p in elbow_points(robot).world(robot.data))
    ns, wrist_sin, offset = _arm_angle_terms(ps, pe, pw, (0.0, 0.0, 1.0), _FLOAT_OPS)
    if not wrist_sin >= math.sin(math.radians(wrist_cone_deg)):
        return ArmAngle(ns if wrist_sin > 0 else math.nan, "wrist_vertical", wrist_sin, offset)
    if not offset >= elbow_offset_min:
        return ArmAngle(ns, "elbow_straight", wrist_sin, offset)
    return ArmAngle(ns, "ok", wrist_sin, offset)


def arm_angle(robot: Robot, q: object) -> float:
    """Arm angle ``ns`` (rad, in (-π, π]) of ``q``; SingularityError where undefined."""
    return _checked(arm_angle_status(robot, q))


def _checked(state: ArmAngle) -> float:
    if not state.ok:
        raise SingularityError(
            f"arm angle undefined at this configuration ({state.status}: wrist_sin = "
            f"{state.wrist_sin:.3g}, elbow offset = {state.elbow_offset_m * 1e3:.3g} mm)"
        )
    return state.value


def _build_gradient_function(robot: Robot) -> ca.Function:
    sym = SymbolicModel(robot.model)
    ns, measures = arm_angle_expression(sym, elbow_points(robot))
    return ca.Function("arm_angle", [sym.q], [ns, ca.jacobian(ns, sym.q).T, measures])


def arm_angle_gradient(robot: Robot, q: object) -> np.ndarray:
    """Exact gradient ∂ns/∂q (rad/rad, shape (nq,)) by CasADi AD; SingularityError where undefined."""
    qv = as_vector(q, robot.nq, "q")
    arm_angle(robot, qv)  # raises on singular configurations
    fun = _cached(_GRADIENT_CACHE, robot, _build_gradient_function)
    return np.asarray(fun(qv)[1], dtype=float).reshape(-1)
