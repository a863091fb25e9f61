"""Where each part of the replayed scene is (m, world frame unless a name says otherwise).

The links move with Pinocchio's forward kinematics: each joint's frame ``oMi`` at the recorded ``q``, and each
link capsule (:mod:`qpnso.model.collision`) fixed in the frame of the joint that carries its first end.  The
elbow is drawn on its circle about the shoulder–wrist line (:class:`~qpnso.elbow.arm_angle.ElbowCircle`, [E 2]–[E 4]
read backwards), in a frame whose x and y axes are ``u_cos`` and ``u_sin``: an arm angle ``ns`` is the point
``radius (cos ns, sin ns, 0)`` of that frame, and ROM_t and the continuity interval are arcs of it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from qpnso.elbow.arm_angle import ElbowCircle, elbow_circle, elbow_points
from qpnso.model.collision import link_capsules
from qpnso.model.robot import Robot

ARC_STEP_RAD = np.radians(3.0)
"""Angle between consecutive points of a drawn arc (rad)."""


@dataclass(frozen=True)
class CapsuleShape:
    """A link capsule as drawn: its axis ends ``a`` and ``b`` (m) in the frame of joint ``joint`` (0: the
    world), its ``radius`` (m) and ``name``."""

    joint: int
    a: np.ndarray
    b: np.ndarray
    radius: float
    name: str


def capsule_shapes(robot: Robot) -> tuple[CapsuleShape, ...]:
    """The arm's capsules, each in the frame of the joint holding its first chain point (the segment is rigid
    there: the joints between its ends turn about the segment itself, :mod:`qpnso.model.collision`)."""
    caps = link_capsules(robot)
    q = 0.5 * (robot.q_min + robot.q_max)
    pin.forwardKinematics(robot.model, robot.data, q)
    points = caps.points(robot, q)
    shapes = []
    for a, b, radius, name in zip(caps.a, caps.b, caps.radius, caps.names):
        joint = caps.anchors[a][0]
        frame = robot.data.oMi[joint]
        shapes.append(CapsuleShape(joint, frame.actInv(points[a]), frame.actInv(points[b]), radius, name))
    return tuple(shapes)


def inside_capsules(robot: Robot, q: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Which of ``points`` (k, 3; m, world) lie inside each link capsule at ``q`` (rad): (capsules, k) bool, a
    point inside when its distance to the capsule's axis segment (its projection clamped to the ends) is below
    the capsule's radius."""
    caps = link_capsules(robot)
    a, b = caps.segments(robot, q)
    axis = b - a
    rel = points[None, :, :] - a[:, None, :]
    length_sq = np.maximum(np.einsum("cx,cx->c", axis, axis), 1e-300)  # a sphere: an axis of length 0
    s = np.clip(np.einsum("ckx,cx->ck", rel, axis) / length_sq[:, None], 0.0, 1.0)
    gap = rel - s[..., None] * axis[:, None, :]
    return np.einsum("ckx,ckx->ck", gap, gap) < np.square(caps.radius)[:, None]


def capsules_holding(robot: Robot, qs: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Which link capsules hold at least one of ``points`` (k, 3; m, world) at some configuration of ``qs``
    (n, nq; rad): (capsules,) bool (:func:`inside_capsules`)."""
    held = np.zeros(link_capsules(robot).count, dtype=bool)
    for q in qs:
        held |= inside_capsules(robot, q, points).any(axis=1)
    return held


def joint_placements(robot: Robot, q: np.ndarray) -> list[pin.SE3]:
    """World poses of joints 1 … n's frames at ``q`` (rad): Pinocchio's ``oMi``."""
    pin.forwardKinematics(robot.model, robot.data, q)
    return [pin.SE3(robot.data.oMi[j]) for j in range(1, robot.model.njoints)]


def elbow_circle_at(robot: Robot, q: np.ndarray) -> ElbowCircle:
    """The elbow circle at ``q`` (rad): shoulder, elbow and wrist centres by forward kinematics."""
    pin.forwardKinematics(robot.model, robot.data, q)
    ps, pe, pw = elbow_points(robot).world(robot.data)
    return elbow_circle(ps, pe, pw)


def circle_frame(circle: ElbowCircle) -> pin.SE3:
    """The frame of the elbow circle: origin its centre, axes ``u_cos``, ``u_sin`` and the shoulder–wrist axis."""
    return pin.SE3(np.column_stack([circle.u_cos, circle.u_sin, circle.axis]), circle.centre)


def arc(lo: float, hi: float, radius: float, around: float) -> np.ndarray | None:
    """Points (k, 3) of the arc from arm angle ``lo`` to ``hi`` (rad, unwrapped like ``around``) at ``radius``
    (m), in the circle's frame, cut to half a turn either side of ``around`` (the current arm angle, rad: an
    unbounded end); None when an end or ``around`` is unknown (NaN) or nothing is left (``lo > hi``)."""
    if np.isnan(lo) or np.isnan(hi) or np.isnan(around):
        return None
    lo, hi = max(lo, around - np.pi), min(hi, around + np.pi)
    if lo > hi:
        return None
    a = np.linspace(lo, hi, max(2, int(np.ceil((hi - lo) / ARC_STEP_RAD)) + 1))
    return radius * np.column_stack([np.cos(a), np.sin(a), np.zeros_like(a)])


def unit_circle(around: float) -> np.ndarray:
    """The whole circle of radius 1 in its frame, from half a turn below ``around`` (rad) to half a turn above."""
    points = arc(around - np.pi, around + np.pi, 1.0, around)
    assert points is not None  # both ends finite
    return points


def framing_distance(points: np.ndarray, target: np.ndarray, direction: np.ndarray, fov: float) -> float:
    """The distance (m) from ``target`` along ``direction`` (a vector toward the camera) of a camera looking at
    ``target`` with world z up, from which every one of ``points`` (k, 3; m) is in view: within ``fov`` (rad)
    both across and up (a square field; a landscape window's wider one keeps them in view too)."""
    back = direction / np.linalg.norm(direction)
    right = np.cross(np.array([0.0, 0.0, 1.0]), back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    rel = points - target
    off_axis = np.maximum(np.abs(rel @ right), np.abs(rel @ up))
    return float(np.max(rel @ back + off_axis / np.tan(0.5 * fov)))


def polyline_segments(points: np.ndarray) -> np.ndarray:
    """A polyline (k, 3) as its k − 1 segments (k − 1, 2, 3)."""
    return np.stack([points[:-1], points[1:]], axis=1)
