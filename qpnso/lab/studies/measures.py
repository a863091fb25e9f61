"""The measures the studies follow along ``q``: mass [M 8], friction [M 15], their weighted sum [M 18].

:func:`curve_function` evaluates them at many configurations at once (one CasADi map);
:class:`Workbench` holds one worker's robot, cost model and those functions, built once per
process (:func:`workbench`); the objectives turn :class:`Measures` into the value minimised.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import casadi as ca
import numpy as np

from qpnso.model.codegen import FastFunction
from qpnso.model.costs import CostModel, principal_masses, smooth_coulomb
from qpnso.model.robot import Robot, load_robot_with_armature


# --------------------------------------------------------- measures along q
def curve_function(cost: CostModel) -> ca.Function:
    """``q → (c_m, Λv⁻¹, G)``: mass measure [M 8], Λv⁻¹ [M 2] (1/kg) and the friction Gram matrix.

    ``c_f = τmaxᵀ G τmax`` [M 13], [M 15] with ``G = Σ_i M_iᵀ M_i``,
    ``M_i = J̄vᵀ diag(a_i)``, ``a_i = (2/π) atan(β s J̄v e_i)``: the smooth Coulomb
    torque [M 23] is linear in ``τmax``, so one evaluation of ``G`` gives the
    friction cost of any sliding torques (the uncertainty study needs this).
    """
    tool = cost.tool
    a = smooth_coulomb(cost.potential_speed * tool.jbar_v, np.ones(cost.robot.nq), cost.robot.friction.beta)
    gram = ca.SX.zeros(cost.robot.nq, cost.robot.nq)
    for i in range(3):
        m = ca.mtimes(tool.jbar_v.T, ca.diag(a[:, i]))
        gram += ca.mtimes(m.T, m)
    return cost.sym.function(
        "study_measures",
        {
            "mass": -ca.det(tool.lambda_inv_v),
            "lambda_inv_v": ca.reshape(tool.lambda_inv_v, 9, 1),
            "gram": ca.reshape(0.5 * (gram + gram.T), cost.robot.nq**2, 1),
        },
    )


@dataclass(frozen=True)
class Measures:
    """Measures at N configurations ``q`` (N×nq, rad)."""

    q: np.ndarray
    mass_cost: np.ndarray  # c_m = −det Λv⁻¹ (kg⁻³), (N,)
    lambda_inv_v: np.ndarray  # (N, 3, 3), 1/kg, world axes
    gram: np.ndarray  # (N, nq, nq), c_f = τᵀ G τ (N² per (N·m)²)

    def friction_cost(self, tau_max: np.ndarray) -> np.ndarray:
        """c_f (N²) for joint sliding torques ``tau_max`` (N·m)."""
        return np.einsum("i,nij,j->n", tau_max, self.gram, tau_max)

    def friction_force(self, tau_max: np.ndarray) -> np.ndarray:
        """Magnitude √c_f (N) of the stacked potential friction forces."""
        return np.sqrt(np.maximum(self.friction_cost(tau_max), 0.0))

    def principal_mass(self) -> np.ndarray:
        """Largest principal mass (kg): 1/λ_min(Λv⁻¹)."""
        return principal_masses(self.lambda_inv_v)


class Workbench:
    """Per-worker state: the robot (rotor inertia ``armature_kgm2`` kg·m² on every joint; None: the model's),
    its normalised cost model and the measure functions."""

    def __init__(self, robot_name: str = "lwr4p", compile: str = "off", armature_kgm2: float | None = None) -> None:
        self.robot: Robot = load_robot_with_armature(robot_name, armature_kgm2)
        self.cost = CostModel(self.robot, compile=compile)
        self._fn = curve_function(self.cost)
        self._one = FastFunction(self._fn, compile)
        self._maps: dict[int, ca.Function] = {}

    def measures(self, q: np.ndarray) -> Measures:
        """:class:`Measures` at configurations ``q`` (N×nq)."""
        q = np.atleast_2d(q)
        n, nq = q.shape
        if n == 1:
            mass, lam, gram = self._one(q[0])
            mass, lam, gram = np.array([mass]), np.asarray(lam)[:, None], np.asarray(gram)[:, None]
        else:
            fn = self._maps.get(n)
            if fn is None:
                fn = self._maps[n] = self._fn.map(n)
            mass, lam, gram = (np.asarray(x) for x in fn(q.T))
        return Measures(
            q,
            np.asarray(mass).reshape(-1),
            lam.T.reshape(n, 3, 3).transpose(0, 2, 1),
            gram.T.reshape(n, nq, nq).transpose(0, 2, 1),
        )

    def tau_max(self) -> np.ndarray:
        return self.robot.friction.tau_max


_BENCHES: dict[tuple[str, str, float | None], Workbench] = {}


def workbench(robot: str = "lwr4p", compile: str = "off", armature_kgm2: float | None = None) -> Workbench:
    """The worker's :class:`Workbench` (built once per process)."""
    key = (robot, compile, armature_kgm2)
    if key not in _BENCHES:
        _BENCHES[key] = Workbench(robot, compile, armature_kgm2)
    return _BENCHES[key]


# ----------------------------------------------------------- objectives
Objective = Callable[[Measures], np.ndarray]


def mass_objective(m: Measures) -> np.ndarray:
    """c_m [M 8]."""
    return m.mass_cost


def friction_objective(tau_max: np.ndarray) -> Objective:
    """c_f [M 15] with sliding torques ``tau_max`` (N·m)."""
    return lambda m: m.friction_cost(tau_max)


def weighted_objective(mass_share: float, scales: dict[str, float], tau_max: np.ndarray) -> Objective:
    """``w c_m/s_m + (1 − w) c_f/s_f`` [M 18], the normalisation of :class:`CostModel`."""
    wm, wf = mass_share / scales["mass"], (1.0 - mass_share) / scales["friction_force"]
    return lambda m: wm * m.mass_cost + wf * m.friction_cost(tau_max)
