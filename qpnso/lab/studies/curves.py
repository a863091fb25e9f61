"""The self-motion of a start configuration and the search for a measure's local extremum along it.

The self-motion is parametrised by the arm angle (closed-form IK) over the continuity
interval of the start; the cost is sampled on an arm-angle grid, followed downhill from the
start and refined by bounded Brent (see :mod:`qpnso.lab.studies`).  Random non-singular start
configurations: :func:`sample_start`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.optimize import minimize_scalar

from qpnso.elbow.arm_angle import arm_angle_status
from qpnso.elbow.intervals import Interval, continuity_interval
from qpnso.elbow.srs import SelfMotion, branch, self_motion
from qpnso.errors import InputError, ModelError, SingularityError
from qpnso.lab.studies.measures import Measures, Objective, Workbench
from qpnso.model.robot import Robot


# ------------------------------------------------------- extremum search
@dataclass(frozen=True)
class Extremum:
    """A local extremum along the self-motion: arm angle (rad, unwrapped), value, posture."""

    ns: float
    value: float
    measures: Measures
    at_end: bool  # stopped by an end of the continuity interval (joint limit or singular cut)

    @property
    def q(self) -> np.ndarray:
        return self.measures.q[0]


def arm_angle_grid(ns0: float, interval: Interval, step: float) -> tuple[np.ndarray, int, bool]:
    """Grid of arm angles (rad) over the continuity interval: ``(grid, index of ns0, cyclic)``.

    ``ns0`` and the interval ends are grid points; spacing ≤ ``step``.  A full
    circle gives a cyclic grid starting at ``ns0`` (the last point is not repeated).
    """
    if interval.full_circle:
        m = max(4, math.ceil(2 * math.pi / step))
        return ns0 + 2 * math.pi * np.arange(m) / m, 0, True

    def side(a: float, b: float) -> np.ndarray:
        if b - a <= 0:
            return np.array([a])
        return np.linspace(a, b, math.ceil((b - a) / step) + 1)

    left, right = side(interval.lo, ns0), side(ns0, interval.hi)
    left[-1] = right[0] = ns0
    return np.concatenate([left, right[1:]]), left.size - 1, False


def descend(values: np.ndarray, start: int, cyclic: bool, direction: int = 0) -> int:
    """Index where a walk from ``start`` to ever lower neighbours stops (a grid local minimum).

    ``direction`` (+1/−1) is the side on which the objective decreases at the
    start (the sign of −gradient, which the grid cannot resolve when the start
    is near an extremum); 0 takes the lower neighbour.
    """
    n = values.size

    def neighbour(i: int, d: int) -> int | None:
        j = i + d
        if cyclic:
            return j % n
        return j if 0 <= j < n else None

    if direction == 0:
        lower = [d for d in (-1, 1) if (j := neighbour(start, d)) is not None and values[j] < values[start]]
        if not lower:
            return start
        direction = min(lower, key=lambda d: values[neighbour(start, d)])
    i, d = start, direction
    while True:
        j = neighbour(i, d)
        if j is None or not values[j] < values[i]:
            return i
        i = j


class SelfMotionCurve:
    """The self-motion of a start configuration ``q0`` (tool pose held), sampled on an arm-angle grid."""

    def __init__(self, bench: Workbench, q0: np.ndarray, step_rad: float) -> None:
        robot = bench.robot
        self.bench = bench
        self.q0 = robot.check_q(q0, "q0")
        self.interval = continuity_interval(robot, self.q0)
        self.motion: SelfMotion = self_motion(robot, robot.tool_pose(self.q0), branch(robot, self.q0))
        state = arm_angle_status(robot, self.q0)
        self.ns0 = float(state.value)
        self.grid, self.start, self.cyclic = arm_angle_grid(self.ns0, self.interval, step_rad)
        self.samples = self.measure(self.grid)
        gap = float(np.abs(self.samples.q[self.start] - self.q0).max())
        if gap > 1e-6:
            raise ModelError(f"closed-form IK at the start arm angle misses q0 by {gap:.3g} rad")

    def measure(self, ns: np.ndarray) -> Measures:
        return self.bench.measures(self.motion.joints(np.asarray(ns, dtype=float).reshape(-1)))

    def _descent_side(self, f: Callable[[float], float], delta: float = 1e-6) -> int | None:
        """+1/−1: the side on which ``f`` decreases at ``ns0``; None if it decreases on neither side
        (the start is the extremum, or an interval end blocks the descent)."""
        iv = self.interval
        up = self.cyclic or self.ns0 + delta <= iv.hi
        down = self.cyclic or self.ns0 - delta >= iv.lo
        f0 = f(self.ns0)
        f_up = f(self.ns0 + delta) if up else math.inf
        f_down = f(self.ns0 - delta) if down else math.inf
        if min(f_up, f_down) >= f0:
            return None
        return 1 if f_up < f_down else -1

    def extremum(self, objective: Objective, sense: str = "min", xatol: float = 1e-9) -> Extremum:
        """Local minimum (``sense="min"``) or maximum of ``objective`` reached from ``ns0``."""
        if sense not in ("min", "max"):
            raise InputError(f"sense must be 'min' or 'max', got {sense!r}")
        sign = 1.0 if sense == "min" else -1.0

        def f(ns: float) -> float:
            return sign * float(objective(self.measure(np.array([ns])))[0])

        values = sign * objective(self.samples)
        direction = self._descent_side(f)
        if direction is None:  # the gradient flow does not leave the start
            return self._extremum_at(self.ns0, sign * f(self.ns0))
        i = descend(values, self.start, self.cyclic, direction)
        n, h = self.grid.size, 2 * math.pi / self.grid.size
        if self.cyclic:
            a, b = self.grid[i] - h, self.grid[i] + h
        else:
            a, b = self.grid[max(i - 1, 0)], self.grid[min(i + 1, n - 1)]
        if i == self.start:  # minimum within the first cell on the descent side
            a, b = (self.ns0, b) if direction > 0 else (a, self.ns0)
        best_ns, best = float(self.grid[i]), float(values[i])
        if b > a:
            res = minimize_scalar(f, bounds=(a, b), method="bounded", options={"xatol": xatol})
            if float(res.fun) < best:
                best_ns, best = float(res.x), float(res.fun)
        return self._extremum_at(best_ns, sign * best)

    def _extremum_at(self, ns: float, value: float) -> Extremum:
        at_end = not self.cyclic and min(ns - self.interval.lo, self.interval.hi - ns) < 1e-6
        return Extremum(ns, value, self.measure(np.array([ns])), at_end)


# ----------------------------------------------------------- start poses
def sample_start(
    robot: Robot, rng: np.random.Generator, threshold: float, max_draws: int = 10000
) -> tuple[np.ndarray, int]:
    """A uniform random configuration with ``σ_min(J Jᵀ) ≥ threshold`` and a defined arm angle.

    Returns ``(q, rejected draws)``.
    """
    for rejected in range(max_draws):
        q = robot.random_q(rng)
        jac = robot.jacobian(q)
        if np.linalg.svd(jac @ jac.T, compute_uv=False)[-1] >= threshold and arm_angle_status(robot, q).ok:
            return q, rejected
    raise SingularityError(f"no non-singular configuration in {max_draws} draws (threshold {threshold})")
