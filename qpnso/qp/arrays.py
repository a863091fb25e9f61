"""The named groups of arrays the QP's kernels take and give (docs/method.md §7.3–7.5): a level's parts
(:class:`LevelParts`), one QP in its solver's variables (:class:`QPArrays`), the line of level 1's exact
solutions (:class:`Segment`) and what the higher levels leave to a level of the cascade (:class:`Basis`,
:class:`Inherited`), and whether a QP's data can be solved (:func:`qp_data_finite`).  Numba reads them by
field, at no cost between kernels; from Python, a kernel takes or returns them at the cost of typing (or
building) each group, so the kernels that Python calls per level return plain tuples."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit


class LevelParts(NamedTuple):
    """A level's parts over ``x`` (rad/s), absent parts with zero rows: the task ``‖A x − b‖²`` (weights
    folded in), ``½xᵀHx + gᵀx``, the rows ``l ≤ C x ≤ u`` of which the first ``n_slack`` are soft, their
    slack scaled by ``slack_scale`` = 1/√(2ρ) (unit curvature in the solver's variable)."""

    A: np.ndarray
    b: np.ndarray
    H: np.ndarray
    g: np.ndarray
    C: np.ndarray
    l: np.ndarray
    u: np.ndarray
    n_slack: int
    slack_scale: float


class QPArrays(NamedTuple):
    """``min ½vᵀHv + gᵀv`` s.t. ``l ≤ C v ≤ u`` and ``box_l ≤ v ≤ box_u`` (no box: both of length 0)."""

    H: np.ndarray
    g: np.ndarray
    C: np.ndarray
    l: np.ndarray
    u: np.ndarray
    box_l: np.ndarray
    box_u: np.ndarray


class Segment(NamedTuple):
    """Level 1's exact solutions ``x0 + t·d`` (rad/s), ``t ∈ [t_lo, t_hi]`` (``x0 ⊥ d``, ``d`` unit)."""

    x0: np.ndarray
    d: np.ndarray
    t_lo: float
    t_hi: float


class Basis(NamedTuple):
    """Where a cascade level moves: ``x = x_prev + Z z`` (``full``: ``Z`` is the identity; ``moved``: a
    level above has solved, ``x_prev`` may be non-zero)."""

    x_prev: np.ndarray
    Z: np.ndarray
    full: bool
    moved: bool


class Inherited(NamedTuple):
    """The constraints a cascade level inherits: the bounds ``lb ≤ x ≤ ub`` and the rows ``l ≤ C x ≤ u``."""

    lb: np.ndarray
    ub: np.ndarray
    C: np.ndarray
    l: np.ndarray
    u: np.ndarray


@njit(cache=True)
def qp_data_finite(qp):
    """Whether a QP's data (:class:`~qpnso.qp.arrays.QPArrays`) can be solved: ``H``, ``g``, ``C`` finite, no
    NaN in the bounds (±inf allowed)."""
    for a in (qp.H.ravel(), qp.g, qp.C.ravel()):
        for x in a:
            if not math.isfinite(x):
                return False
    for a in (qp.l, qp.u, qp.box_l, qp.box_u):
        for x in a:
            if x != x:
                return False
    return True


def rows_with_box(qp: QPArrays) -> QPArrays:
    """``qp`` with its box's finite entries appended to its rows as unit rows and no box (for a back end
    without a native box); no box: ``qp`` itself."""
    if not qp.box_l.shape[0]:
        return qp
    keep = np.isfinite(qp.box_l) | np.isfinite(qp.box_u)
    unit = np.eye(qp.g.shape[0])[keep]
    empty = np.zeros(0)
    return QPArrays(
        qp.H,
        qp.g,
        np.vstack([qp.C, unit]),
        np.concatenate([qp.l, qp.box_l[keep]]),
        np.concatenate([qp.u, qp.box_u[keep]]),
        empty,
        empty,
    )
