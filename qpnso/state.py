"""What every strategy needs to know about the arm at one control tick.

One compiled CasADi function evaluates, from ``q`` alone, the tool pose, the
tool Jacobian, the weighted cost and its exact gradient, and the arm angle with
its exact gradient and singularity measures — one call per tick instead of five
(:class:`StateEvaluator`).  Pinocchio adds the numeric dynamics a torque
command needs (``A(q)``, ``g(q)``) only when asked.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from qpnso.codegen import FastFunction
from qpnso.costs import CostModel
from qpnso.elbow import arm_angle_expression, elbow_points


@dataclass
class TickState:
    """The arm at one tick.  Frames: world; tool point; units rad, m, s."""

    q: np.ndarray  # (nq,) rad
    tool_rotation: np.ndarray  # (3, 3) world ← tool
    tool_position: np.ndarray  # (3,) m, world
    jacobian: np.ndarray  # (6, nq) world-aligned at the tool point, linear rows first
    cost: float  # weighted total [M 18]
    cost_gradient: np.ndarray  # (nq,) per rad
    arm_angle: float  # ns [E 2], rad
    arm_angle_gradient: np.ndarray  # (nq,) ∂ns/∂q
    wrist_sin: float  # |p_sw × z0| / |p_sw|: sine of the wrist's angle to the vertical
    elbow_offset: float  # distance (m) of the elbow centre from the shoulder–wrist line
    pose: np.ndarray  # (12,) rotation entries (column-major) then position (m): for cheap comparisons


class StateEvaluator:
    """Evaluates :class:`TickState` from ``q`` with one CasADi call.

    The function has a single output, every quantity stacked in one vector (``R`` and ``J``
    column-major), so a tick copies one array and the state's fields are views of it.
    """

    def __init__(self, cost: CostModel, compile: str | None = None) -> None:
        robot = cost.robot
        sym = cost.sym
        tool = sym.frame_placement(robot.tool_frame_id)
        ns, measures = arm_angle_expression(sym, elbow_points(robot))
        total = cost.expression
        parts = [tool.R, tool.p, sym.frame_jacobian(robot.tool_frame_id), total, ca.gradient(total, sym.q), ns,
                 ca.gradient(ns, sym.q), measures]
        stacked = ca.vertcat(*[ca.vec(part) for part in parts])
        self.robot = robot
        self._fn = FastFunction(sym.function(f"tick_{robot.name}", {"state": stacked}), compile)
        n = robot.nq
        ends = np.cumsum([9, 3, 6 * n, 1, n, 1, n, 2])
        self._slices = [slice(a, b) for a, b in zip(np.r_[0, ends[:-1]], ends)]

    def wait_compiled(self, timeout: float | None = None) -> bool:
        """Block until compiled code is used (benchmarks call this)."""
        return self._fn.wait(timeout)

    def __call__(self, q: np.ndarray) -> TickState:
        """State at ``q`` (rad; assumed validated by the caller)."""
        flat = self._fn.flat(q)
        rot, pos, jac, c, dc, ns, dns, measures = (flat[k] for k in self._slices)
        n = q.shape[0]
        return TickState(q, rot.reshape(3, 3, order="F"), pos, jac.reshape(6, n, order="F"), float(c[0]), dc,
                         float(ns[0]), dns, float(measures[0]), float(measures[1]), flat[:12])
