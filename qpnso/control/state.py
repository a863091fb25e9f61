"""What every strategy needs to know about the arm at one control tick.

One compiled CasADi function evaluates, from ``q`` alone, the tool pose, the
tool Jacobian, the weighted cost and its exact gradient, the arm angle with its
exact gradient and singularity measures, the dynamics a torque command needs
(``A(q)``, ``g(q)``), and the tool's second-order motion ``J̇(q, q̇)q̇`` along the
command predicted for the tick (level 1's second-order term, :func:`predicted_velocity`): one call per tick instead of
eight (:class:`StateEvaluator`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import casadi as ca
import numpy as np
from numba import njit

from qpnso.control.flags import FLAG_COST_UNDEFINED, FLAG_INTERNAL_ERROR
from qpnso.control.rows import RowKind
from qpnso.elbow.arm_angle import arm_angle_expression, elbow_points
from qpnso.model.codegen import FastFunction
from qpnso.model.collision import LinkCapsules, point_expressions
from qpnso.model.costs import CostModel
from qpnso.records import new_record


def state_dtype(n: int, rows: int = 0, points: int = 0) -> np.dtype:
    """The record type of the arm's state at one tick, ``n`` joints, ``rows`` rows of row kinds
    (:mod:`qpnso.control.rows`) and ``points`` chain points of the collision capsules
    (:mod:`qpnso.model.collision`), laid out as the CasADi function of :class:`StateEvaluator` writes it (so the
    record is a view of its output buffer).  Frames: world; tool point; units rad, m, s; matrices row-major."""
    f8, m, k = np.float64, max(rows, 1), max(points, 1)
    return np.dtype(
        [
            ("R", f8, (3, 3)),  # tool rotation, world ← tool
            ("p", f8, 3),  # tool point (m, world)
            ("J", f8, (6, n)),  # tool Jacobian, world-aligned at the tool point, linear rows first
            ("cost", f8),  # weighted total [M 18]
            ("cost_gradient", f8, n),  # per rad
            ("arm_angle", f8),  # ns [E 2], rad, wrapped to (−π, π]
            ("arm_angle_gradient", f8, n),  # ∂ns/∂q
            ("wrist_sin", f8),  # |p_sw × z0| / |p_sw|: sine of the wrist's angle to the vertical
            ("elbow_offset", f8),  # m: distance of the elbow centre from the shoulder–wrist line
            ("A", f8, (n, n)),  # A(q), kg·m² (Pinocchio's crba)
            ("g", f8, n),  # g(q), N·m (Pinocchio's computeGeneralizedGravity)
            ("drift", f8, 6),  # J̇(q, q̇)q̇ at the predicted q̇ (m/s², rad/s²; world-aligned, tool point)
            ("predicted", f8, n),  # q̇ predicted for the tick (rad/s, predicted_velocity): the drift's q̇
            ("rows", f8, m),  # h(q) of the row kinds' rows (their units; none: one 0)
            ("rows_gradient", f8, (m, n)),  # ∂h/∂q
            ("points", f8, (k, 3)),  # the collision capsules' chain points (m, world; none: one 0)
            ("points_J", f8, (k, 3, n)),  # ∂points/∂q (m/rad)
        ]
    )


@dataclass
class TickState:
    """The arm at one tick, as Python reads it (the strategies written in Python, tests).  Frames: world;
    tool point; units rad, m, s.  The fields of :func:`state_dtype` under these names."""

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
    mass_matrix: np.ndarray  # (nq, nq) A(q), kg·m² (Pinocchio's crba)
    gravity: np.ndarray  # (nq,) g(q), N·m (Pinocchio's computeGeneralizedGravity)
    tool_drift: np.ndarray  # (6,) J̇(q, q̇)q̇ at the predicted q̇ (m/s², rad/s²; world-aligned, tool point)
    predicted_velocity: np.ndarray  # (nq,) rad/s: the q̇ the drift is taken along (predicted_velocity)
    flags: int = 0  # status bits of sanitize_state: what was not finite and made safe

    @classmethod
    def of(cls, q: np.ndarray, state: np.ndarray, flags: int = 0) -> "TickState":
        """The fields of a state record (1-element array), as views of it."""
        s = state[0]
        return cls(
            q,
            s["R"],
            s["p"],
            s["J"],
            float(s["cost"]),
            s["cost_gradient"],
            float(s["arm_angle"]),
            s["arm_angle_gradient"],
            float(s["wrist_sin"]),
            float(s["elbow_offset"]),
            s["A"],
            s["g"],
            s["drift"],
            s["predicted"],
            flags,
        )


class StateEvaluator:
    """Evaluates the arm's state from ``q`` with one CasADi call.

    The function has a single output, every quantity stacked in one vector in the layout of
    :func:`state_dtype` (matrices row-major); :meth:`record` returns it as that record, a view of
    the function's own buffer (the tick reads it in place), ``__call__`` a :class:`TickState` copy.
    """

    def __init__(
        self,
        cost: CostModel,
        compile: str | None = None,
        rows: Sequence[RowKind] = (),
        room: int = 0,
        capsules: LinkCapsules | None = None,
    ) -> None:
        """``rows``: the row kinds whose ``h(q)`` and ``∇h`` the state holds, in ``room`` ≥ their rows
        (the rest zero); ``capsules``: the arm's collision capsules, whose chain points and their Jacobians it
        holds (None: one zero point)."""
        robot = cost.robot
        sym = cost.sym
        tool = sym.frame_placement(robot.tool_frame_id)
        ns, measures = arm_angle_expression(sym, elbow_points(robot))
        total = cost.expression
        J = sym.frame_jacobian(robot.tool_frame_id)
        dq, twist, twist_prev = ca.SX.sym("dq", robot.nq), ca.SX.sym("twist", 6), ca.SX.sym("twist_prev", 6)
        predicted = predicted_velocity(J, dq, twist, twist_prev)
        parts = [
            tool.R.T,  # (transposed: ca.vec is column-major, the record row-major)
            tool.p,
            J.T,
            total,
            ca.gradient(total, sym.q),
            ns,
            ca.gradient(ns, sym.q),
            measures,
            sym.mass_matrix().T,
            sym.gravity_torque(),
            tool_drift(sym.q, J, predicted),
            predicted,
            *row_parts(rows, sym, robot, room),
            *point_parts(capsules, sym, robot),
        ]
        stacked = ca.vertcat(*[ca.vec(part) for part in parts])
        self.robot = robot
        points = capsules.points_count if capsules else 0
        self.dtype = state_dtype(robot.nq, parts[-4].numel(), points)  # (the rows as padded by row_parts)
        assert stacked.numel() * 8 == self.dtype.itemsize  # the record is the output, field for field
        self._zero_velocity = np.zeros(robot.nq)
        self._fn = FastFunction(
            ca.Function(
                f"tick_{robot.name}", [ca.vertcat(sym.q, dq, twist, twist_prev)], [stacked], ["q_dq_twists"], ["state"]
            ),
            compile,
        )  # one input: one copy a tick
        self._zero_twist = np.zeros(6)
        self.bind(new_record(self.dtype))

    def wait_compiled(self, timeout: float | None = None) -> bool:
        """Block until compiled code is used (benchmarks call this)."""
        return self._fn.wait(timeout)

    def save(self, path: str | Path) -> Path:
        """Write the state function (CasADi's serialisation, ``Function.save``) to ``path``, for a C++ program on
        qpnso's C++ API (``qpnso::core::CasadiFunction::load_runtime``: examples/cpp/state_loop.cpp).  Its one
        input is ``(q, dq, twist, twist_prev)`` (rad, rad/s, m/s and rad/s), its one output the record of
        :func:`state_dtype`, field for field.  Returns the path."""
        path = Path(path)
        self._fn.function.save(str(path))
        return path

    @property
    def runtime(self) -> str:
        """What evaluates the state function now: "compiled C" or "casadi runtime" (:mod:`qpnso.model.codegen`)."""
        return self._fn.runtime

    def __call__(
        self,
        q: np.ndarray,
        dq: np.ndarray | None = None,
        twist: np.ndarray | None = None,
        twist_prev: np.ndarray | None = None,
    ) -> TickState:
        """State at ``q`` (rad; assumed validated by the caller), made safe (:func:`sanitize_state`), a copy;
        the drift along the velocity predicted from the previous command ``dq`` (rad/s; None: 0), this tick's
        tool ``twist`` and the previous tick's ``twist_prev`` (m/s, rad/s) — :func:`predicted_velocity`.
        ``twist`` None: the drift is along ``dq`` itself; ``twist_prev`` None: ``J dq`` (``dq``'s tool part is
        replaced by ``twist``)."""
        dq = self._zero_velocity if dq is None else dq
        if twist is None:
            twist = twist_prev = self._zero_twist
        elif twist_prev is None:
            twist_prev = self.robot.jacobian(q) @ dq
        state = self.record(q, dq, twist, twist_prev).copy()
        return TickState.of(q, state, sanitize_state(state[0]))

    def record(self, q: np.ndarray, dq: np.ndarray, twist: np.ndarray, twist_prev: np.ndarray) -> np.ndarray:
        """The state at ``q`` (rad), the previous command ``dq`` (rad/s), this tick's tool ``twist`` and the
        previous tick's ``twist_prev`` (validated by the caller) as a :func:`state_dtype` record (1-element
        array) in the record the evaluator writes (:meth:`bind`), not yet made safe: read it before the next
        call, which overwrites it."""
        self._fn.evaluate_in_place(q, dq, twist, twist_prev)
        return self._record

    def bind(self, record: np.ndarray) -> None:
        """Evaluate into ``record`` from now on (a :func:`state_dtype` record, 1 element; e.g. a field of the
        controller's tick record): the CasADi function writes it, no copy."""
        if record.dtype != self.dtype or record.shape != (1,):
            raise ValueError(f"bind needs a ({self.dtype}) record of one element")
        self._fn.use_output(0, record.view(np.float64))
        self._record = record


def row_parts(rows: Sequence[RowKind], sym, robot, room: int) -> tuple[ca.SX, ca.SX]:
    """The row kinds' values ``h(q)`` stacked (m,) and their exact Jacobian, transposed for the record's
    row-major layout (n, m), padded with zero rows to ``room`` rows (at least one)."""
    values = ca.vertcat(*[kind.values(sym, robot) for kind in rows]) if rows else ca.SX.zeros(0)
    gradient = ca.jacobian(values, sym.q) if rows else ca.SX.zeros(0, robot.nq)
    pad = max(room, values.numel(), 1) - values.numel()
    values, gradient = ca.vertcat(values, ca.SX.zeros(pad)), ca.vertcat(gradient, ca.SX.zeros(pad, robot.nq))
    return ca.densify(values), ca.densify(gradient.T)  # (a joint that cannot move h: a structural zero)


def point_parts(capsules: LinkCapsules | None, sym, robot) -> tuple[ca.SX, ca.SX]:
    """The chain points (k·3,) and their Jacobian in the record's row-major layout (k, 3, n)
    (:func:`qpnso.model.collision.point_expressions`); no capsules: one zero point."""
    if capsules is None:
        return ca.SX.zeros(3), ca.SX.zeros(3 * robot.nq)
    points, jacobian = point_expressions(sym, capsules)
    return ca.densify(points), ca.densify(jacobian.T)


PREDICTION_DAMPING = 1e-2
"""ε (m/rad) of the damped pseudo-inverse in :func:`predicted_velocity`: near a singularity the predicted
tool part stays within ``|v|/(2ε)`` rad/s (the hierarchical QP's default damping threshold)."""


PREDICTION_TOLERANCE = 0.05
"""rad/s at dt = 1 ms: a solved ``q̇`` farther than this from the predicted one (any joint) has level 1's
second-order term taken along the wrong velocity; the controller then takes it along the solved ``q̇`` and solves
again (:meth:`qpnso.control.controller.Controller._second_pass`).  The term's error is about
``½dt²·|J̇|·|Δq̇|``: 1.3 µrad for the 1.42 rad/s miss at the end of a 2 m/s pull (the fuzz, seed 1, episode 129),
under 0.1 µrad at this tolerance.  It grows as dt², so the tolerance a controller uses is this times
``(1 ms/dt)²`` (:func:`prediction_tolerance`): at 4 ms a 0.049 rad/s miss drifted a held Panda tool by 1.11 µrad
(the 10⁶-tick fuzz of issue 31, seed 1 episode 393)."""


def prediction_tolerance(dt: float) -> float:
    """rad/s: :data:`PREDICTION_TOLERANCE` for a tick of ``dt`` s, scaled by ``(1 ms/dt)²`` (the same drift)."""
    return PREDICTION_TOLERANCE * (1e-3 / dt) ** 2


def predicted_velocity(J: ca.SX, dq: ca.SX, twist: ca.SX, twist_prev: ca.SX) -> ca.SX:
    """This tick's joint velocity as predicted before it is solved (rad/s): the previous command ``dq`` with
    its tool part changed by the change of the tool twist, ``dq + Jᵀ(JJᵀ + ε²I)⁻¹(v − v_prev)`` (damped least
    squares, ε = :data:`PREDICTION_DAMPING`; ``v`` this tick's twist, ``v_prev`` the previous tick's).  The
    null-space motion changes little from one tick to the next, the tool's can jump (a surgeon's pull that
    stops): the second-order term along the previous command alone left a held tool 1–2 µm off after a 2 m/s
    pull (the fuzz, measured).  Changing the tool part by the twist's change rather than replacing it with
    ``v``: where level 1 does not meet ``v`` exactly (damped near a singularity), replacing it amplified the
    residual by up to 1/ε, and the prediction missed the solved command by 1–2 rad/s on every tick of a held
    tool near a singularity (the fuzz, seed 3)."""
    return dq + ca.mtimes(J.T, ca.solve(ca.mtimes(J, J.T) + PREDICTION_DAMPING**2 * ca.SX.eye(6), twist - twist_prev))


def tool_drift(q: ca.SX, J: ca.SX, velocity: ca.SX) -> ca.SX:
    """``J̇(q, q̇)q̇`` at ``q̇ = velocity`` (m/s², rad/s²; world-aligned, tool point): ``∂(J w)/∂q · w`` by
    forward mode with ``w`` held constant, then ``w = velocity`` (which may itself depend on ``q``)."""
    w = ca.SX.sym("w", J.shape[1])
    along = ca.Function("drift", [q, w], [ca.jtimes(ca.mtimes(J, w), q, w)])
    return along(q, velocity)


@njit(cache=True)
def sanitize_state(s):
    """Make a state record ``s`` (:func:`state_dtype`) safe to act on, in place; returns status bits.  A
    cost or cost gradient that is not finite (the tool Jacobian singular: Λ undefined) is set to 0
    (``COST_UNDEFINED``: no cost step this tick); an arm angle or gradient or singularity measure that is
    not finite marks the arm angle singular (all set to 0: the elbow rows are dropped).  Anything else not
    finite (pose, J, A, g, the drift) is ``INTERNAL_ERROR``: the caller must not act on it."""
    bits = 0
    if not (math.isfinite(s.cost) and all_finite(s.cost_gradient)):
        s.cost = 0.0
        s.cost_gradient[:] = 0.0
        bits |= FLAG_COST_UNDEFINED
    if not (
        math.isfinite(s.arm_angle)
        and all_finite(s.arm_angle_gradient)
        and math.isfinite(s.wrist_sin)
        and math.isfinite(s.elbow_offset)
    ):
        s.arm_angle, s.wrist_sin, s.elbow_offset = 0.0, 0.0, 0.0  # wrist sine 0: singular
        s.arm_angle_gradient[:] = 0.0
    finite = all_finite(s.R.ravel()) and all_finite(s.p) and all_finite(s.J.ravel())
    if not (finite and all_finite(s.A.ravel()) and all_finite(s.g) and all_finite(s.drift)):
        return bits | FLAG_INTERNAL_ERROR
    return bits


@njit(cache=True)
def all_finite(v):
    """Whether every entry of the vector ``v`` is finite."""
    for x in v:
        if not math.isfinite(x):
            return False
    return True
