"""The control tick's QP as one named record, and its answer (docs/method.md §7).

Every tick, whatever the strategy, states the same two-level problem over ``x = q̇`` (rad/s):

* **every level**: the joint bounds ``lb ≤ x ≤ ub`` and the hard rows ``hard_l ≤ hard_C x ≤ hard_u``
  (the first ``n_hard`` of them);
* **level 1**: the tool task ``A1 x = b1`` (6 rows: the tool twist, m/s then rad/s, world frame);
* **level 2** (if ``has_level2``): ``‖A2 x − b2‖²`` (its first ``m2`` rows) ``+ ½ xᵀH2x`` (if ``use_H2``)
  ``+ g2ᵀx`` (if ``use_g2``), and the soft rows ``soft_l ≤ soft_C x + s ≤ soft_u`` (the first
  ``n_soft``) with cost ``slack_weight·‖s‖²``; soft rows without ``has_level2`` make level 2 those rows
  with the least-norm ``½‖x‖²`` (``H2``, the identity, as :func:`new_problem` leaves it).

:func:`problem_dtype` is the record's NumPy type; the Numba kernels of the tick write it by field
(:mod:`qpnso.control.tick`), a Python strategy through :func:`set_level2`, and
:meth:`qpnso.qp.solver.HierarchicalQP.solve_problem` solves it: the line fast path (:mod:`qpnso.qp.line`)
when level 1's exact solutions form a segment, else the general cascade on :func:`problem_levels`.
The answer goes into a :func:`solution_dtype` record.
"""

from __future__ import annotations

import numpy as np

from qpnso.errors import InputError
from qpnso.qp.levels import Level
from qpnso.records import new_record

TASK_ROWS = 6
"""Rows of level 1: the tool twist."""

SOLVED, TOOL_HELD, STOPPED = 0, 1, 2
"""``solution.outcome``: every level solved; level 2 failed and ``x`` is level 1's least-norm answer
(the tool held, no null-space motion); level 1 failed too and ``x`` is zero."""


def problem_dtype(n: int, hard_rows: int = 1, soft_rows: int = 1) -> np.dtype:
    """The record type of a tick's problem over ``n`` joints with room for ``hard_rows`` hard and
    ``soft_rows`` soft rows (module docstring)."""
    f8, i8 = np.float64, np.int64
    return np.dtype(
        [
            ("A1", f8, (TASK_ROWS, n)),
            ("b1", f8, TASK_ROWS),
            ("lb", f8, n),
            ("ub", f8, n),
            ("hard_C", f8, (max(hard_rows, 1), n)),
            ("hard_l", f8, max(hard_rows, 1)),
            ("hard_u", f8, max(hard_rows, 1)),
            ("n_hard", i8),
            ("has_level2", i8),
            ("A2", f8, (n, n)),
            ("b2", f8, n),
            ("m2", i8),
            ("H2", f8, (n, n)),
            ("use_H2", i8),
            ("g2", f8, n),
            ("use_g2", i8),
            ("soft_C", f8, (max(soft_rows, 1), n)),
            ("soft_l", f8, max(soft_rows, 1)),
            ("soft_u", f8, max(soft_rows, 1)),
            ("n_soft", i8),
            ("slack_weight", f8),
        ]
    )


def new_problem(n: int, hard_rows: int = 1, soft_rows: int = 1) -> np.ndarray:
    """A zeroed problem record (a 1-element array: the form Numba reads cheaply), ``H2`` = I."""
    problem = new_record(problem_dtype(n, hard_rows, soft_rows))
    problem["H2"][0] = np.eye(n)
    return problem


def solution_dtype(n: int) -> np.dtype:
    """The answer to a problem: ``x`` the joint velocity to command (rad/s), ``x1`` level 1's
    least-norm answer (rad/s), ``outcome`` (:data:`SOLVED`, :data:`TOOL_HELD`, :data:`STOPPED`),
    ``tool_residual`` ``‖A1 x − b1‖`` (m/s, rad/s), ``slack_max`` the largest soft-row violation
    (−1: no soft row), ``violation`` the worst bound or hard-row violation of a refused answer,
    ``out_of_time`` the cascade's time budget was spent (1)."""
    f8, i8 = np.float64, np.int64
    return np.dtype(
        [
            ("x", f8, n),
            ("x1", f8, n),
            ("outcome", i8),
            ("tool_residual", f8),
            ("slack_max", f8),
            ("violation", f8),
            ("out_of_time", i8),
        ]
    )


def new_solution(n: int) -> np.ndarray:
    """A zeroed solution record (1-element array)."""
    return new_record(solution_dtype(n))


def set_level2(problem: np.ndarray, level: Level | None) -> None:
    """Write a strategy's level 2 (a :class:`Level`: task, quadratic, linear term; no rows) into
    ``problem`` (None: no level 2).  Its soft rows are left as they are (none unless a row kind wrote
    them)."""
    p = problem[0]
    if level is None:
        p["has_level2"] = 0
        return
    if level.C is not None or not (isinstance(level.weight, (int, float)) and level.weight == 1):
        raise InputError(
            "a strategy's level 2 is a task, a quadratic and a linear term, unweighted; rows are row kinds"
        )
    p["has_level2"] = 1
    m = 0 if level.A is None else np.shape(level.A)[0]
    if m > p["A2"].shape[0]:
        raise InputError(f"level 2's task has {m} rows; the problem has room for {p['A2'].shape[0]}")
    p["m2"] = m
    if m:
        p["A2"][:m] = level.A
        p["b2"][:m] = level.b
    p["use_H2"] = level.H is not None
    if level.H is not None:
        p["H2"][:] = level.H
    p["use_g2"] = level.g is not None
    if level.g is not None:
        p["g2"][:] = level.g


def problem_levels(problem: np.ndarray) -> list[Level]:
    """The problem as the general cascade's levels (:meth:`qpnso.qp.solver.HierarchicalQP.solve`): level 1
    the tool task with the hard rows (hard: they bind every level below), level 2 its objective with
    the soft rows.  Copies, so that the record can be written again while they are in use."""
    p = problem[0]
    nh, ns, m = int(p["n_hard"]), int(p["n_soft"]), int(p["m2"])
    first = Level(A=p["A1"].copy(), b=p["b1"].copy())
    if nh:
        first.C, first.l, first.u = p["hard_C"][:nh].copy(), p["hard_l"][:nh].copy(), p["hard_u"][:nh].copy()
    own = bool(p["has_level2"])
    if not own and not ns:
        return [first]
    m = m if own else 0
    second = Level(  # (soft rows without an objective: the least-norm ½‖q̇‖² with them, as qpnso.qp.line)
        A=p["A2"][:m].copy() if m else None,
        b=p["b2"][:m].copy() if m else None,
        H=p["H2"].copy() if p["use_H2"] or not own else None,
        g=p["g2"].copy() if p["use_g2"] and own else None,
    )
    if ns:
        second.C, second.l, second.u = p["soft_C"][:ns].copy(), p["soft_l"][:ns].copy(), p["soft_u"][:ns].copy()
        second.slack_weight = float(p["slack_weight"])
    if second.A is None and second.H is None and second.g is None and second.C is None:
        return [first]
    return [first, second]
