"""The closed forms of S-R-S arms: geometry, branch, self-motion and IK (docs/method.md §4).

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

Only atan2/acos forms are used (no half-angle formulas).  The arm angle ``ns``
itself, its points and its gradient are in :mod:`qpnso.elbow.arm_angle`.
"""

from __future__ import annotations

import itertools
import math
import weakref
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
import pinocchio as pin

from qpnso.elbow.arm_angle import Z0, ElbowPoints, _cached, _cross, _dot, _tcross
from qpnso.errors import InputError, ModelError, SingularityError, UnreachableError
from qpnso.model.robot import POSE_NOT_FINITE, POSE_NOT_ROTATION, Robot, as_vector, pose_defect
from qpnso.model.symbolic import joint_kind_and_axis

GEOMETRY_TOL = 1e-9
"""Tolerance (m, or unit-vector components) of the S-R-S structure check."""

_TAN, _COS, _CONST = 0, 1, 2
_GEOMETRY_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


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
            # any object: one that is not a sequence of numbers raises TypeError or ValueError here
            signs = [int(v) if float(v) == int(v) else v for v in cast(Iterable[Any], value)]
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
        if (
            np.linalg.norm(_cross(axes[k], line_dir)) > GEOMETRY_TOL
            or np.linalg.norm(_cross(off, line_dir)) > GEOMETRY_TOL
        ):
            raise ModelError(f"{name}: axis of joint {k + 1} is not on the line of joint 1 at q = 0 (not S-R-S)")
    ey = axes[1]
    for k in (1, 3, 5):  # joints 2, 4, 6: perpendicular, parallel to each other
        if abs(float(axes[k] @ line_dir)) > GEOMETRY_TOL or np.linalg.norm(_cross(axes[k], ey)) > GEOMETRY_TOL:
            raise ModelError(
                f"{name}: axis of joint {k + 1} is not perpendicular to the arm line and parallel "
                "to joint 2 at q = 0 (not S-R-S)"
            )
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
        2,
        4,
        6,
        *(_floats3(data.oMi[j].actInv(p)) for j, p in ((2, p_s), (4, p_e), (6, p_w))),
    )
    wrist_in_tool = o_t.rotation.T @ (p_w - o_t.translation)
    tool_to_wrist = np.eye(4)
    tool_to_wrist[:3, :3], tool_to_wrist[:3, 3] = o_t.rotation.T @ frame, wrist_in_tool
    return SrsGeometry(
        frame=frame,
        axis_sign=axis_sign,
        upper_arm_m=upper,
        forearm_m=fore,
        p_s=p_s,
        wrist_in_tool=wrist_in_tool,
        tool_rotation0=o_t.rotation.copy(),
        points=points,
        shoulder_from_world=np.column_stack([frame.T, -frame.T @ p_s]),
        tool_to_wrist=tool_to_wrist,
        vertical=_floats3(frame.T @ Z0),
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


def _floats3(v: Sequence[float]) -> _Vec:
    """A 3-vector as a tuple of plain floats."""
    return (float(v[0]), float(v[1]), float(v[2]))


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


def _rotation_coefficients(
    g: SrsGeometry, pose: pin.SE3, b: Branch
) -> tuple[tuple[tuple, tuple], tuple[tuple, tuple], float]:
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
