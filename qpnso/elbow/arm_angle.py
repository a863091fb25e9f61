"""The elbow of a 7-DOF arm: arm angle, S-R-S geometry and closed-form IK (docs/method.md §4).

Arm angle [E 2]–[E 4], world frame, ``z0`` the world vertical::

    u_sin = z0 × p_sw / |z0 × p_sw|,   u_cos = p_sw × u_sin / |p_sw × u_sin|
    ns    = atan2(p_se · u_sin, p_se · u_cos)          (rad, ns = 0: elbow up)

``p_s``, ``p_e``, ``p_w`` are the shoulder, elbow and wrist centres
(:class:`ElbowPoints`).  ``ns`` is undefined when the wrist is on the vertical
through the shoulder and meaningless when the elbow is straight; both are
reported (:func:`arm_angle_status`) and :func:`arm_angle` raises
:class:`~qpnso.errors.SingularityError` rather than returning NaN.

S-R-S arms (LWR4+, iiwa): the geometry is read from the Pinocchio model at
``q = 0`` (:func:`srs_geometry`): joints 1, 3, 5, 7 on one line, joints 2, 4, 6
perpendicular to it and parallel to each other, crossing it at the shoulder,
elbow and wrist centres.  For a tool pose and a branch (signs of joints 2, 4,
6) every joint is a closed-form function of ``ns`` (:class:`SelfMotion`):
the rotations ``R03`` (joints 1–3) and ``R47`` (joints 5–7) are affine in
``(cos ns, sin ns)`` (Shimizu et al., IEEE T-RO 2008), so

* joints 1, 3, 5, 7 are *tangent type*: ``σ·atan2(a·sin + b·cos + c, a'·sin + b'·cos + c')``;
* joints 2, 6 are *cosine type*: ``s·acos(a·sin + b·cos + c)``;
* joint 4 does not depend on ``ns``.

Only atan2/acos forms are used (no half-angle formulas).
"""

from __future__ import annotations

import itertools
import math
import weakref
from collections.abc import Sequence
from dataclasses import dataclass
import casadi as ca
import numpy as np
import pinocchio as pin

from qpnso.errors import InputError, ModelError, SingularityError, UnreachableError
from qpnso.model.robot import POSE_NOT_FINITE, POSE_NOT_ROTATION, Robot, as_vector, pose_defect
from qpnso.model.symbolic import SymbolicModel, joint_kind_and_axis

Z0 = np.array([0.0, 0.0, 1.0])
"""World vertical used as the arm-angle reference [E 3]."""
WRIST_CONE_DEG = 2.0
"""Default half-angle (deg) of the cone around the vertical through the shoulder
inside which the arm angle is reported singular (``"wrist_vertical"``)."""
ELBOW_OFFSET_MIN_M = 0.005
"""Default minimum distance (m) of the elbow from the shoulder–wrist line below
which the arm angle is reported singular (``"elbow_straight"``)."""
GEOMETRY_TOL = 1e-9
"""Tolerance (m, or unit-vector components) of the S-R-S structure check."""

_TAN, _COS, _CONST = 0, 1, 2


# ----------------------------------------------------------------- arm angle
def _tcross(a, b) -> tuple[float, float, float]:  # type: ignore[no-untyped-def]
    """Cross product of two 3-sequences as a tuple (plain floats: fast for one pair)."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of 3-vectors as an array (faster than ``np.cross`` for one pair)."""
    return np.array(_tcross(a, b))


def _dot(a, b) -> float:  # type: ignore[no-untyped-def]
    return float(a[0] * b[0] + a[1] * b[1] + a[2] * b[2])


_FLOAT_OPS = (
    lambda a, b: (a[0] - b[0], a[1] - b[1], a[2] - b[2]),
    _tcross,
    _dot,
    lambda a: math.sqrt(_dot(a, a)),
    math.atan2,
)
_CASADI_OPS = (lambda a, b: a - b, ca.cross, ca.dot, ca.norm_2, ca.atan2)


def _arm_angle_terms(ps, pe, pw, z0, ops):  # type: ignore[no-untyped-def]
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
        return tuple(  # type: ignore[return-value]
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


def _cached(cache: weakref.WeakKeyDictionary, robot: Robot, build):  # type: ignore[no-untyped-def]
    value = cache.get(robot)
    if value is None:
        value = build(robot)
        cache[robot] = value
    return value


_POINTS_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_GEOMETRY_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_GRADIENT_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def elbow_points(robot: Robot) -> ElbowPoints:
    """Shoulder/elbow/wrist centres of ``robot`` (cached per robot).

    S-R-S arms: from :func:`srs_geometry` (points fixed to joints 2, 4, 6).
    Other 7-DOF arms (e.g. the Panda), a documented choice: shoulder = origin of
    joint 2 (on the axis of joint 1), elbow = origin of joint 4, wrist = origin
    of the last joint (on its axis, so it stays fixed in the world while the tool
    pose is held and the arm moves in its self-motion).
    """
    return _cached(_POINTS_CACHE, robot, _build_elbow_points)


def _build_elbow_points(robot: Robot) -> ElbowPoints:
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


# ------------------------------------------------------------------- branch
@dataclass(frozen=True)
class Branch:
    """Configuration branch of an S-R-S arm: signs (±1) of joints 2, 4 and 6."""

    s2: int
    s4: int
    s6: int

    def __post_init__(self) -> None:
        for name in ("s2", "s4", "s6"):
            if getattr(self, name) not in (1, -1):
                raise InputError(f"branch sign {name} must be +1 or -1, got {getattr(self, name)!r}")

    @classmethod
    def coerce(cls, value: object) -> "Branch":
        """A :class:`Branch` from a Branch or a sequence of three ±1; InputError otherwise."""
        if isinstance(value, Branch):
            return value
        try:
            signs = [int(v) if float(v) == int(v) else v for v in value]  # type: ignore[union-attr]
        except (TypeError, ValueError):
            raise InputError(f"branch must be a Branch or three signs (±1, ±1, ±1), got {value!r}") from None
        if len(signs) != 3:
            raise InputError(f"branch must have three signs (joints 2, 4, 6), got {len(signs)}")
        return cls(*signs)

    def as_tuple(self) -> tuple[int, int, int]:
        return (self.s2, self.s4, self.s6)


def branch(robot: Robot, q: object) -> Branch:
    """Branch of ``q``: signs of joints 2, 4, 6; SingularityError if one is exactly 0."""
    qv = as_vector(q, robot.nq, "q")
    if robot.nq != 7:
        raise ModelError(f"{robot.name}: a branch (signs of joints 2, 4, 6) needs a 7-joint arm")
    return _branch_of(qv)


def _branch_of(qv: np.ndarray) -> Branch:
    v = qv.tolist()
    for k in (1, 3, 5):
        if v[k] == 0.0:
            raise SingularityError(f"joint {k + 1} is exactly 0: the configuration branch is undefined")
    return _BRANCHES[(v[1] > 0, v[3] > 0, v[5] > 0)]


_BRANCHES = {tuple(s > 0 for s in signs): Branch(*signs) for signs in itertools.product((1, -1), repeat=3)}


# ------------------------------------------------------------ S-R-S geometry
@dataclass(frozen=True)
class SrsGeometry:
    """S-R-S structure read from the model at ``q = 0`` (world frame, metres).

    ``frame`` has the canonical axes as columns: ``ez`` along the arm line
    (shoulder → elbow), ``ey`` along the axis of joint 2, ``ex = ey × ez``.
    ``axis_sign[k]`` is the sign of joint k's axis along ``ez`` (joints 1, 3, 5,
    7) or ``ey`` (joints 2, 4, 6).  ``upper_arm_m``/``forearm_m`` are the
    shoulder–elbow and elbow–wrist lengths, ``p_s`` the shoulder centre,
    ``wrist_in_tool`` the wrist centre in the tool frame, ``tool_rotation0``
    the tool orientation at ``q = 0``.  Derived, for the closed form:
    ``shoulder_from_world`` (3×4, ``[Fᵀ | −Fᵀ·p_s]``) maps world points to the
    shoulder frame (canonical axes), ``tool_to_wrist`` (4×4) is the wrist frame
    (canonical axes at ``q = 0``, origin at the wrist centre) in the tool frame, and
    ``vertical`` the world vertical in canonical coordinates.
    """

    frame: np.ndarray
    axis_sign: np.ndarray
    upper_arm_m: float
    forearm_m: float
    p_s: np.ndarray
    wrist_in_tool: np.ndarray
    tool_rotation0: np.ndarray
    points: ElbowPoints
    shoulder_from_world: np.ndarray
    tool_to_wrist: np.ndarray
    vertical: tuple[float, float, float]


def _line_point(origin: np.ndarray, ez: np.ndarray, o: np.ndarray, axis: np.ndarray, k: int, name: str) -> np.ndarray:
    """Where axis ``k`` (through ``o``, perpendicular to the arm line) crosses the line."""
    gap = abs(float((o - origin) @ _cross(ez, axis)))
    if gap > GEOMETRY_TOL:
        raise ModelError(f"{name}: axis of joint {k} misses the arm line by {gap:.3g} m (not S-R-S)")
    return origin + float((o - origin) @ ez) * ez


def _build_srs_geometry(robot: Robot) -> SrsGeometry:
    model, name = robot.model, robot.name
    if model.nq != 7 or model.njoints != 8:
        raise ModelError(f"{name}: the closed-form S-R-S kinematics needs 7 revolute joints")
    data = model.createData()
    pin.framesForwardKinematics(model, data, np.zeros(7))
    axes, origins = [], []
    for j in range(1, 8):
        kind, axis = joint_kind_and_axis(model.joints[j])
        if kind != "revolute":
            raise ModelError(f"{name}: joint {j} is not revolute (not S-R-S)")
        axes.append(data.oMi[j].rotation @ axis)
        origins.append(data.oMi[j].translation.copy())
    line_dir, origin = axes[0], origins[0]
    for k in (0, 2, 4, 6):  # joints 1, 3, 5, 7: on the arm line
        off = origins[k] - origin
        if np.linalg.norm(_cross(axes[k], line_dir)) > GEOMETRY_TOL or np.linalg.norm(_cross(off, line_dir)) > GEOMETRY_TOL:
            raise ModelError(f"{name}: axis of joint {k + 1} is not on the line of joint 1 at q = 0 (not S-R-S)")
    ey = axes[1]
    for k in (1, 3, 5):  # joints 2, 4, 6: perpendicular, parallel to each other
        if abs(float(axes[k] @ line_dir)) > GEOMETRY_TOL or np.linalg.norm(_cross(axes[k], ey)) > GEOMETRY_TOL:
            raise ModelError(f"{name}: axis of joint {k + 1} is not perpendicular to the arm line and parallel "
                             "to joint 2 at q = 0 (not S-R-S)")
    p_s, p_e, p_w = (_line_point(origin, line_dir, origins[k], axes[k], k + 1, name) for k in (1, 3, 5))
    upper, fore = float(np.linalg.norm(p_e - p_s)), float(np.linalg.norm(p_w - p_e))
    if upper < 1e-6 or fore < 1e-6:
        raise ModelError(f"{name}: zero upper-arm or forearm length (not S-R-S)")
    ez = (p_e - p_s) / upper
    if float((p_w - p_e) @ ez) < fore * (1 - 1e-9):
        raise ModelError(f"{name}: the elbow is not between shoulder and wrist at q = 0")
    frame = np.column_stack([_cross(ey, ez), ey, ez])
    axis_sign = np.array([np.sign(axes[k] @ (ey if k % 2 else ez)) for k in range(7)])
    tool = robot.model.frames[robot.tool_frame_id]
    if tool.parentJoint != 7:
        raise ModelError(f"{name}: the tool frame must be attached to joint 7 for the closed form")
    o_t = data.oMf[robot.tool_frame_id]
    points = ElbowPoints(
        2, 4, 6,
        *(tuple(float(x) for x in data.oMi[j].actInv(p)) for j, p in ((2, p_s), (4, p_e), (6, p_w))),
    )
    wrist_in_tool = o_t.rotation.T @ (p_w - o_t.translation)
    tool_to_wrist = np.eye(4)
    tool_to_wrist[:3, :3], tool_to_wrist[:3, 3] = o_t.rotation.T @ frame, wrist_in_tool
    return SrsGeometry(
        frame=frame, axis_sign=axis_sign, upper_arm_m=upper, forearm_m=fore, p_s=p_s,
        wrist_in_tool=wrist_in_tool, tool_rotation0=o_t.rotation.copy(), points=points,
        shoulder_from_world=np.column_stack([frame.T, -frame.T @ p_s]), tool_to_wrist=tool_to_wrist,
        vertical=tuple(float(x) for x in frame.T @ Z0),
    )


def srs_geometry(robot: Robot) -> SrsGeometry:
    """S-R-S geometry of ``robot`` (cached); ModelError if the arm is not S-R-S."""
    return _cached(_GEOMETRY_CACHE, robot, _build_srs_geometry)


def is_srs(robot: Robot) -> bool:
    """Whether the closed-form S-R-S kinematics applies to ``robot``."""
    try:
        srs_geometry(robot)
    except ModelError:
        return False
    return True


# ------------------------------------------------------- closed-form self-motion
def as_pose(pose: object) -> pin.SE3:
    """A ``pin.SE3`` from an SE3 or a 4×4 homogeneous matrix; InputError on NaN/shape."""
    if isinstance(pose, pin.SE3):
        h = pose.homogeneous
    else:
        try:
            h = np.asarray(pose, dtype=float)
        except (TypeError, ValueError):
            raise InputError(f"pose must be a pinocchio.SE3 or a 4x4 matrix, got {type(pose).__name__}") from None
        if h.shape != (4, 4):
            raise InputError(f"pose must be a pinocchio.SE3 or a 4x4 matrix, got shape {h.shape}")
    rot = h[:3, :3]
    defect = pose_defect(rot, h[:3, 3]) if np.all(np.isfinite(h[3])) else POSE_NOT_FINITE
    if defect == POSE_NOT_FINITE:
        raise InputError("pose contains NaN or inf")
    if defect == POSE_NOT_ROTATION:
        raise InputError("pose rotation is not a rotation matrix")
    return pin.SE3(rot.copy(), h[:3, 3].copy())


@dataclass(frozen=True)
class SelfMotion:
    """Every joint as a closed-form function of the arm angle (pose and branch held).

    Row k of ``num``/``den`` holds the coefficients ``(a, b, c)`` of
    ``a·sin ns + b·cos ns + c``.  Tangent type (``kind 0``):
    ``θ_k = sign_k·atan2(num_k, den_k)``; cosine type (``kind 1``):
    ``θ_k = sign_k·acos(den_k)``; constant (``kind 2``, joint 4): ``θ_k = const``.
    """

    num: np.ndarray
    den: np.ndarray
    kind: np.ndarray
    sign: np.ndarray
    q4: float
    branch: Branch

    def joints(self, ns: object) -> np.ndarray:
        """Joint angles (rad): shape (7,) for a scalar ``ns``, (N, 7) for N arm angles."""
        arr = np.asarray(ns, dtype=float)
        if not np.all(np.isfinite(arr)):
            raise InputError("arm angle ns contains NaN or inf")
        flat = arr.reshape(-1)
        basis = np.column_stack([np.sin(flat), np.cos(flat), np.ones_like(flat)])
        n, d = basis @ self.num.T, basis @ self.den.T
        q = np.where(self.kind == _TAN, np.arctan2(n, d), np.arccos(np.clip(d, -1.0, 1.0))) * self.sign
        q[:, 3] = self.q4
        return q[0] if arr.ndim == 0 else q


_Vec = tuple[float, float, float]


def _scaled(k: float, v: Sequence[float]) -> _Vec:
    return (k * v[0], k * v[1], k * v[2])


def _lin(a: float, v: Sequence[float], b: float, w: Sequence[float]) -> _Vec:
    return (a * v[0] + b * w[0], a * v[1] + b * w[1], a * v[2] + b * w[2])


def _r03_transposed(v: Sequence[float], sin_a: float, cos_a: float, k_x: float, k_y: float) -> tuple[_Vec, _Vec, _Vec]:
    """``R03ᵀ·v`` for ``v = (p, q, r)`` given in the arm-angle frame ``(u_sin, u_cos, u)``.

    Each of the three components as its ``(sin ns, cos ns, 1)`` coefficients:
    ``R03·ez = e1 = sin_a·(sin ns·u_sin + cos ns·u_cos) + cos_a·u`` (upper arm),
    ``R03·ex = k_x·e1 + k_y·u`` (= (e2 − e1 cos q4)/(σ4 sin q4), e2 = (d·u − l1·e1)/l2),
    ``R03·ey = e1 × R03·ex = k_y·(e1 × u)``.
    """
    p, q, r = v
    e = (sin_a * p, sin_a * q, cos_a * r)
    return (k_x * e[0], k_x * e[1], k_x * e[2] + k_y * r), (-k_y * e[1], k_y * e[0], 0.0), e


def _rotation_coefficients(g: SrsGeometry, pose: pin.SE3, b: Branch) -> tuple[tuple, tuple, float]:
    """Last column and last row of ``R03`` and ``R47`` (canonical frame), affine in ``(sin ns, cos ns, 1)``.

    Returns ``(r03, r47, q4)``: each block is ``(col, row)`` with ``col[i]`` the
    coefficients ``(sin, cos, 1)`` of ``M[i, 2]`` and ``row[i]`` those of
    ``M[2, i]`` — all that the Z-Y-Z angles need — and joint 4 (rad).
    ``R47 = R4ᵀ·R03ᵀ·T`` (T = R07, R4 = Ry(σ4·q4)).  Plain floats: NumPy's call
    overhead would dominate these few products.  Raises UnreachableError or
    SingularityError (wrist on the vertical, straight elbow).
    """
    l1, l2 = g.upper_arm_m, g.forearm_m
    a = g.shoulder_from_world @ pose.homogeneous @ g.tool_to_wrist  # [T | p_sw] in the shoulder frame
    p = a[:, 3].tolist()
    dist = math.sqrt(_dot(p, p))
    if dist > l1 + l2 or dist < abs(l1 - l2):
        gap = dist - (l1 + l2) if dist > l1 + l2 else abs(l1 - l2) - dist
        raise UnreachableError(
            f"pose out of reach: shoulder–wrist distance {dist:.6f} m is outside "
            f"[{abs(l1 - l2):.6f}, {l1 + l2:.6f}] m (by {gap:.3g} m)"
        )
    cos4 = (dist * dist - l1 * l1 - l2 * l2) / (2 * l1 * l2)
    sin4 = b.s4 * math.sqrt(max(0.0, 1.0 - cos4 * cos4))
    u = _scaled(1.0 / dist, p)
    z_x = _tcross(g.vertical, u)
    n_zx = math.sqrt(_dot(z_x, z_x))
    if n_zx < 1e-12:
        raise SingularityError("arm angle undefined: the wrist centre is on the vertical through the shoulder")
    if abs(sin4) < 1e-12:
        raise SingularityError("arm angle undefined: the elbow is straight (joint 4 = 0) for this pose")
    u_sin = _scaled(1.0 / n_zx, z_x)
    u_cos = _tcross(u, u_sin)
    cos_a = (l1 * l1 + dist * dist - l2 * l2) / (2 * l1 * dist)
    sin_a = math.sqrt(max(0.0, 1.0 - cos_a * cos_a))
    c4 = max(-1.0, min(1.0, cos4))
    s4 = float(g.axis_sign[3]) * sin4  # R4 = Ry(σ4·q4): cosine c4, sine s4
    k = (sin_a, cos_a, (-(l1 / l2) - cos4) / s4, (dist / l2) / s4)  # sin_a, cos_a, k_x, k_y
    col03 = tuple((sin_a * u_sin[i], sin_a * u_cos[i], cos_a * u[i]) for i in range(3))  # R03·ez = e1
    row03 = _r03_transposed((u_sin[2], u_cos[2], u[2]), *k)  # R03ᵀ·ez
    t_b = (a[:, :3].T @ np.array([u_sin, u_cos, u]).T).tolist()  # T's columns in the arm-angle frame
    x, y, e = _r03_transposed(t_b[2], *k)  # R03ᵀ·t2
    col47 = (_lin(c4, x, -s4, e), y, _lin(s4, x, c4, e))  # R4ᵀ·R03ᵀ·t2
    kappa, k_u = s4 * k[2] + c4, s4 * k[3]  # R03·R4·ez = κ·e1 + s4·k_y·u
    row47 = tuple((kappa * sin_a * p, kappa * sin_a * q, (kappa * cos_a + k_u) * r) for p, q, r in t_b)
    q4 = b.s4 * math.acos(c4)
    return (col03, row03), (col47, row47), q4


_ZERO = (0.0, 0.0, 0.0)


def _zyz_rows(col: tuple, row: tuple, sb: float) -> tuple[list[tuple], list[tuple]]:
    """``num`` and ``den`` rows of the three Z-Y-Z angles of ``M = Rz(σa·qa)·Ry(σb·qb)·Rz(σc·qc)``.

    ``qa = σa·atan2(sb·M12, sb·M02)``, ``qb = s·acos(M22)``,
    ``qc = σc·atan2(sb·M21, −sb·M20)``, ``sb = s·σb`` the sign of the middle Euler angle.
    """
    return [_scaled(sb, col[1]), _ZERO, _scaled(sb, row[1])], [_scaled(sb, col[0]), col[2], _scaled(-sb, row[0])]


_KIND = np.array([_TAN, _COS, _TAN, _CONST, _TAN, _COS, _TAN])
_BRANCH_TABLES: dict[tuple, tuple[float, float, np.ndarray]] = {}


def _branch_table(g: SrsGeometry, b: Branch) -> tuple[float, float, np.ndarray]:
    """Middle-angle signs ``sb`` of R03 and R47 and joint signs (7,) of a geometry and branch (cached)."""
    key = (g.axis_sign.tobytes(), b.s2, b.s4, b.s6)
    if key not in _BRANCH_TABLES:
        s_mid = np.array([b.s2, b.s2, b.s2, b.s4, b.s6, b.s6, b.s6], dtype=float)
        sign = np.where(_KIND == _COS, s_mid, g.axis_sign)
        _BRANCH_TABLES[key] = (float(b.s2 * g.axis_sign[1]), float(b.s6 * g.axis_sign[5]), sign)
    return _BRANCH_TABLES[key]


def _self_motion_rows(g: SrsGeometry, pose: pin.SE3, b: Branch) -> tuple[list[tuple], list[tuple], np.ndarray, float]:
    """:class:`SelfMotion`'s ``num``, ``den`` (7 rows of plain floats), ``sign`` and ``q4``."""
    r03, r47, q4 = _rotation_coefficients(g, pose, b)
    sb03, sb47, sign = _branch_table(g, b)
    (num03, den03), (num47, den47) = _zyz_rows(*r03, sb03), _zyz_rows(*r47, sb47)
    return num03 + [_ZERO] + num47, den03 + [_ZERO] + den47, sign, q4


def _self_motion(g: SrsGeometry, pose: pin.SE3, b: Branch) -> SelfMotion:
    num, den, sign, q4 = _self_motion_rows(g, pose, b)
    return SelfMotion(np.array(num), np.array(den), _KIND, sign, q4, b)


def self_motion(robot: Robot, pose: object, branch_: object) -> SelfMotion:
    """Closed-form joints-versus-arm-angle of an S-R-S arm for a tool pose and branch."""
    return _self_motion(srs_geometry(robot), as_pose(pose), Branch.coerce(branch_))


def ik(robot: Robot, pose: object, ns: object, branch_: object) -> np.ndarray:
    """Closed-form IK of an S-R-S arm (docs/method.md §4): joints (rad) for tool pose, arm angle, branch.

    ``ns`` may be a scalar (returns (7,)) or an array of N arm angles (returns
    (N, 7)).  Joint limits are not checked.  UnreachableError if the pose is out
    of reach; SingularityError if the arm angle is undefined for it.
    """
    try:
        arr = np.asarray(ns, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"arm angle ns must be a number or an array of numbers (rad), got {ns!r}") from None
    if not np.all(np.isfinite(arr)):
        raise InputError("arm angle ns contains NaN or inf")
    return self_motion(robot, pose, branch_).joints(arr)
