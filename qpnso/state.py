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


class StateEvaluator:
    """Evaluates :class:`TickState` from ``q`` with one CasADi call."""

    def __init__(self, cost: CostModel, compile: str | None = None) -> None:
        robot = cost.robot
        sym = cost.sym
        tool = sym.frame_placement(robot.tool_frame_id)
        ns, measures = arm_angle_expression(sym, elbow_points(robot))
        total = cost.expression
        outputs = {
            "R": tool.R,
            "p": tool.p,
            "J": sym.frame_jacobian(robot.tool_frame_id),
            "c": total,
            "dc": ca.gradient(total, sym.q),
            "ns": ns,
            "dns": ca.gradient(ns, sym.q),
            "measures": measures,
        }
        self.robot = robot
        self._fn = FastFunction(sym.function(f"tick_{robot.name}", outputs), compile)

    def wait_compiled(self, timeout: float | None = None) -> bool:
        """Block until compiled code is used (benchmarks call this)."""
        return self._fn.wait(timeout)

    def __call__(self, q: np.ndarray) -> TickState:
        """State at ``q`` (rad; assumed validated by the caller)."""
        rot, pos, jac, c, dc, ns, dns, measures = self._fn(q)
        return TickState(q, rot, pos, jac, c, dc, ns, dns, float(measures[0]), float(measures[1]))
