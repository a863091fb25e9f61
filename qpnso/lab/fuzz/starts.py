"""Where an episode starts: uniform within the limits, within a few degrees of one or two limits, or near a
singular arm angle (straight elbow, wrist over the shoulder); and the arm's singular zones, measured with
Pinocchio (:func:`start_is_singular`: no drift check from there; :func:`arm_angle_undefined`: no recovery
expected there).

The hard starts are drawn on purpose: uniform samples almost never land where the arm angle or the joint
limits bite.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import pinocchio as pin

from qpnso.elbow.arm_angle import ELBOW_OFFSET_MIN_M, WRIST_CONE_DEG, elbow_points
from qpnso.model.robot import Robot

if TYPE_CHECKING:  # the checker imports arm_angle_undefined from here
    from qpnso.lab.fuzz.checker import TickChecker


def _arm_measures(checker: TickChecker, q: np.ndarray) -> tuple[float, float]:
    """(sine of the shoulder–wrist line's angle from the vertical, elbow distance from that line in m)."""
    pin.forwardKinematics(checker.model, checker.data, q)
    ps, pe, pw = elbow_points(checker.robot).world(checker.data)
    sw = pw - ps
    n = float(np.linalg.norm(sw))
    return float(np.linalg.norm(np.cross([0.0, 0.0, 1.0], sw))) / n, float(np.linalg.norm(np.cross(sw, pe - ps))) / n


def arm_angle_undefined(checker: TickChecker, q: np.ndarray) -> bool:
    """Whether the arm angle is undefined at ``q`` (Pinocchio's kinematics): the shoulder–wrist line within
    :data:`WRIST_CONE_DEG` of the vertical or the elbow within :data:`ELBOW_OFFSET_MIN_M` of that line.  Both
    depend on the wrist centre alone, which the held tool pose fixes: no self-motion leaves this set, so
    ``ELBOW_DROPPED`` there is not a failure to recover (OK is out of reach while the tool is held)."""
    wrist_sin, offset = _arm_measures(checker, q)
    return wrist_sin < math.sin(math.radians(WRIST_CONE_DEG)) or offset < ELBOW_OFFSET_MIN_M


def start_is_singular(checker: TickChecker, q: np.ndarray) -> bool:
    """Within twice the arm angle's singular zones (:data:`WRIST_CONE_DEG`, :data:`ELBOW_OFFSET_MIN_M`),
    or the tool Jacobian's smallest singular value below 0.02."""
    wrist_sin, offset = _arm_measures(checker, q)
    if wrist_sin < math.sin(math.radians(2 * WRIST_CONE_DEG)) or offset < 2 * ELBOW_OFFSET_MIN_M:
        return True
    jac = pin.computeFrameJacobian(checker.model, checker.data, q, checker.tool, pin.LOCAL_WORLD_ALIGNED)
    return float(np.linalg.svd(jac, compute_uv=False)[-1]) < 0.02


def _near_limit(rng: np.random.Generator, robot: Robot, q: np.ndarray, deg: float) -> np.ndarray:
    """One or two joints moved within ``deg`` inside one of their limits."""
    q = q.copy()
    for j in rng.choice(robot.nq, size=int(rng.integers(1, 3)), replace=False):
        inside = math.radians(rng.uniform(0.0, deg))
        q[j] = robot.q_min[j] + inside if rng.random() < 0.5 else robot.q_max[j] - inside
    return q


def _wrist_over_shoulder(rng: np.random.Generator, checker: TickChecker, q: np.ndarray, deg: float) -> np.ndarray:
    """Joint 2 chosen so the wrist is (nearly) on the vertical through the shoulder, joint 3 near 0 (the arm
    planar), then moved by up to ``deg``; or, one time in three, joints 2 and 4 both near 0."""
    q = q.copy()
    q[2] = math.radians(rng.uniform(-deg, deg))
    if rng.random() < 1 / 3:
        q[1], q[3] = (math.radians(rng.uniform(-deg, deg)) for _ in range(2))
        return q
    grid = np.linspace(checker.q_min[1], checker.q_max[1], 241)
    best = grid[0]
    for _ in range(3):  # grid, then two finer grids around the best
        values = []
        for x in grid:
            q[1] = x
            values.append(_arm_measures(checker, q)[0])
        best = grid[int(np.argmin(values))]
        step = grid[1] - grid[0]
        grid = np.linspace(best - step, best + step, 41)
    q[1] = best + math.radians(rng.uniform(-deg, deg))
    return q


def random_start(rng: np.random.Generator, checker: TickChecker) -> tuple[str, np.ndarray]:
    """A start kind (:data:`START_KINDS`) and its configuration, clipped to the limits (rad)."""
    cfg, robot = checker.config, checker.robot
    q = robot.random_q(rng, margin=0.05)
    r = rng.random()
    if r < cfg.p_start_near_limit:
        kind, q = "near_limit", _near_limit(rng, robot, q, cfg.near_limit_deg)
    elif r < cfg.p_start_near_limit + cfg.p_start_singular and robot.nq >= 4:
        if rng.random() < 0.5:
            kind = "elbow_straight"
            q[3] = math.radians(rng.uniform(-cfg.near_singular_deg, cfg.near_singular_deg))
        else:
            kind, q = "wrist_over_shoulder", _wrist_over_shoulder(rng, checker, q, cfg.near_singular_deg)
    else:
        kind = "uniform"
    return kind, np.clip(q, robot.q_min, robot.q_max)
