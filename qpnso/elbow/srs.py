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

Only atan2/acos forms are used (no half-angle formulas).  The coefficients are computed by the kernel
:func:`qpnso.elbow.closed_form.self_motion_rows` on the geometry's record (:attr:`SrsGeometry.record`), the
one implementation the control tick runs too.  The arm angle ``ns`` itself, its points and its gradient are in
:mod:`qpnso.elbow.arm_angle`.
"""

from __future__ import annotations

import itertools
import weakref
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
import pinocchio as pin

from qpnso.elbow.arm_angle import Z0, ElbowPoints, _cached, _cross
from qpnso.elbow.closed_form import (
    KIND,
    SRS_ELBOW_STRAIGHT,
    SRS_UNREACHABLE,
    SRS_WRIST_VERTICAL,
    joints_along,
    self_motion_rows,
    srs_dtype,
)
from qpnso.errors import InputError, ModelError, SingularityError, UnreachableError
from qpnso.model.robot import POSE_NOT_FINITE, POSE_NOT_ROTATION, Robot, as_vector, pose_defect
from qpnso.model.symbolic import joint_kind_and_axis
from qpnso.records import new_record

GEOMETRY_TOL = 1e-9
"""Tolerance (m, or unit-vector components) of the S-R-S structure check."""

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
    ``vertical`` the world vertical in canonical coordinates; ``record`` all of it for the kernels of
    :mod:`qpnso.elbow.closed_form` (:func:`~qpnso.elbow.closed_form.srs_dtype`, a 1-element record).
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
    record: np.ndarray


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
    shoulder_from_world = np.column_stack([frame.T, -frame.T @ p_s])
    vertical = _floats3(frame.T @ Z0)
    record = new_record(srs_dtype())
    for name, value in (
        ("shoulder_from_world", shoulder_from_world),
        ("tool_to_wrist", tool_to_wrist),
        ("upper_arm_m", upper),
        ("forearm_m", fore),
        ("vertical", vertical),
        ("axis_sign", axis_sign),
    ):
        record[name] = value
    return SrsGeometry(
        frame=frame,
        axis_sign=axis_sign,
        upper_arm_m=upper,
        forearm_m=fore,
        p_s=p_s,
        wrist_in_tool=wrist_in_tool,
        tool_rotation0=o_t.rotation.copy(),
        points=points,
        shoulder_from_world=shoulder_from_world,
        tool_to_wrist=tool_to_wrist,
        vertical=vertical,
        record=record,
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
        flat = np.ascontiguousarray(arr.reshape(-1))
        q = np.empty((flat.size, 7))
        joints_along(self.num, self.den, self.sign, float(self.q4), flat, q)  # (the kernel the rom tick runs too)
        return q[0] if arr.ndim == 0 else q


_Vec = tuple[float, float, float]


def _floats3(v: Sequence[float]) -> _Vec:
    """A 3-vector as a tuple of plain floats."""
    return (float(v[0]), float(v[1]), float(v[2]))


def raise_unless_reached(code: int, dist: float, g: SrsGeometry) -> None:
    """Raise what a code of :func:`~qpnso.elbow.closed_form.self_motion_rows` means (shoulder–wrist distance
    ``dist``, m): UnreachableError or SingularityError; nothing for ``SRS_OK``."""
    l1, l2 = g.upper_arm_m, g.forearm_m
    if code == SRS_UNREACHABLE:
        gap = dist - (l1 + l2) if dist > l1 + l2 else abs(l1 - l2) - dist
        raise UnreachableError(
            f"pose out of reach: shoulder–wrist distance {dist:.6f} m is outside "
            f"[{abs(l1 - l2):.6f}, {l1 + l2:.6f}] m (by {gap:.3g} m)"
        )
    if code == SRS_WRIST_VERTICAL:
        raise SingularityError("arm angle undefined: the wrist centre is on the vertical through the shoulder")
    if code == SRS_ELBOW_STRAIGHT:
        raise SingularityError("arm angle undefined: the elbow is straight (joint 4 = 0) for this pose")


def pose_arrays(pose: pin.SE3) -> tuple[np.ndarray, np.ndarray]:
    """A pose's rotation and translation (m) as C-ordered float arrays: the one argument type of the kernels."""
    return np.ascontiguousarray(pose.rotation, dtype=float), np.ascontiguousarray(pose.translation, dtype=float)


def branch_floats(b: Branch) -> tuple[float, float, float]:
    """A branch's signs as floats, the kernels' one argument type (the tick passes floats too)."""
    return float(b.s2), float(b.s4), float(b.s6)


def _self_motion(g: SrsGeometry, pose: pin.SE3, b: Branch) -> SelfMotion:
    """:class:`SelfMotion` from the kernel :func:`~qpnso.elbow.closed_form.self_motion_rows`."""
    num, den, sign = np.empty((7, 3)), np.empty((7, 3)), np.empty(7)
    code, q4, dist = self_motion_rows(g.record[0], *pose_arrays(pose), *branch_floats(b), num, den, sign)
    raise_unless_reached(code, dist, g)
    return SelfMotion(num, den, KIND, sign, q4, b)


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
