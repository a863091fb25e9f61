"""The levels of the hierarchical QP and the checks of their input (docs/method.md §7.5).

A cascade of levels over ``x`` ∈ Rⁿ (joint velocities, rad/s).  Level ``k``
minimises its objective over the optimal set of levels ``0 … k−1``; the hard
bounds ``lb ≤ x ≤ ub`` hold on every level.  One level may combine

* an equality task ``weight · ‖A x − b‖²`` (least squares, damped near
  singularities),
* a quadratic objective ``½ xᵀ H x + gᵀ x`` (``H`` symmetric positive
  semi-definite),
* inequalities ``l ≤ C x ≤ u``, hard, or soft with a free slack ``s`` per row
  (``l ≤ C x + s ≤ u``, cost ``slack_weight · ‖s‖²``) so that an unreachable
  elbow constraint never makes the QP infeasible.

:class:`Level` is what a caller gives.  :func:`_validate_level` and :func:`_validate_bounds` check it
(shapes, NaN/inf, intervals) so that bad input raises :class:`~qpnso.errors.InputError` naming the
field before anything is solved; :func:`_trusted_level` takes it as given (``solve(check=False)``).
Both fold the weight into the task and symmetrise ``H`` (:class:`_LevelData`), the form the cascade
(:mod:`qpnso.qp.cascade`) and the line fast path (:mod:`qpnso.qp.line`) work on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from qpnso.errors import InputError

__all__ = ["Level"]


@dataclass
class Level:
    """One priority level (see the module docstring for the cost).

    ``weight`` is a scalar or one non-negative weight per row of ``A``.
    ``slack_weight=None`` makes ``l ≤ C x ≤ u`` hard; a positive value makes it
    soft with cost ``slack_weight·‖s‖²``.  ``l``/``u`` may hold ∓inf.
    """

    A: np.ndarray | None = None
    b: np.ndarray | None = None
    weight: float | np.ndarray = 1.0
    H: np.ndarray | None = None
    g: np.ndarray | None = None
    C: np.ndarray | None = None
    l: np.ndarray | None = None
    u: np.ndarray | None = None
    slack_weight: float | None = None
    name: str = ""


@dataclass(slots=True)
class _LevelData:
    """A validated level: float arrays, weights folded into the task."""

    A: np.ndarray | None  # (m, n) raw, for the reported residual
    b: np.ndarray | None
    Aw: np.ndarray | None  # W^½ A
    bw: np.ndarray | None  # W^½ b
    H: np.ndarray | None
    g: np.ndarray | None
    C: np.ndarray | None
    l: np.ndarray | None
    u: np.ndarray | None
    rho: float | None  # slack weight, None = hard rows

    @property
    def n_slack(self) -> int:
        return 0 if self.C is None or self.rho is None else self.C.shape[0]


def _array(value: object, name: str, ndim: int, allow_inf: bool = False) -> np.ndarray:
    """``value`` as a float array of ``ndim`` dimensions without NaN/inf; ``allow_inf``: an interval
    side, checked (NaN included) by :func:`_check_interval`, which must follow."""
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a numeric array, got {type(value).__name__}") from None
    if arr.ndim != ndim:
        raise InputError(f"{name} must be {ndim}-D, got shape {arr.shape}")
    if allow_inf:
        return arr
    total = float(np.add.reduce(arr, axis=None))  # one reduction: finite sum <=> no NaN/inf (overflow → detailed check)
    if total - total != 0.0:
        if np.isnan(arr).any():
            raise InputError(f"{name} contains NaN")
        if np.isinf(arr).any():
            raise InputError(f"{name} contains inf")
    return arr


def _check_shape(arr: np.ndarray, shape: tuple, name: str) -> None:
    if arr.shape != shape:
        raise InputError(f"{name} has shape {arr.shape}, expected {shape}")


def _check_interval(lo: np.ndarray, hi: np.ndarray, lo_name: str, hi_name: str) -> None:
    if not (hi - lo >= 0.0).all():  # False for NaN, lo > hi, and lo = hi = ±inf (a side on the wrong side)
        for arr, name in ((lo, lo_name), (hi, hi_name)):
            if np.isnan(arr).any():
                raise InputError(f"{name} contains NaN")
        bad = ~(lo <= hi) | np.isposinf(lo) | np.isneginf(hi)
        i = int(np.argmax(bad))
        raise InputError(
            f"{lo_name}[{i}] = {float(lo[i])!r} > {hi_name}[{i}] = {float(hi[i])!r}, or an infinite bound "
            f"on the wrong side"
        )


def _validate_level(level: Level, n: int, name: str) -> _LevelData:
    """Shape/NaN/interval checks of one level; raises :class:`InputError` naming the field.

    Only the symmetric part of ``H`` matters (``xᵀHx = xᵀ½(H + Hᵀ)x``), so it is used.
    """
    if not isinstance(level, Level):
        raise InputError(f"{name} must be a Level, got {type(level).__name__}")
    if level.A is None and level.H is None and level.g is None and level.C is None:
        raise InputError(f"{name} is empty: give A/b, H/g or C/l/u")
    A = b = Aw = bw = None
    if (level.A is None) != (level.b is None):
        raise InputError(f"{name}: A and b go together")
    if level.A is not None:
        A = _array(level.A, f"{name}.A", 2)
        if A.shape[1] != n or A.shape[0] == 0:
            raise InputError(f"{name}.A has shape {A.shape}, expected (m >= 1, {n})")
        b = _array(level.b, f"{name}.b", 1)
        _check_shape(b, (A.shape[0],), f"{name}.b")
        Aw, bw = A, b
        if not (isinstance(level.weight, (int, float)) and level.weight == 1):
            w = _array(level.weight, f"{name}.weight", np.ndim(level.weight))
            if w.ndim > 1 or (w.ndim == 1 and w.shape != (A.shape[0],)) or (w < 0).any():
                raise InputError(f"{name}.weight must be a scalar or ({A.shape[0]},) array, all >= 0")
            sw = np.sqrt(w)
            Aw, bw = (sw * A.T).T if w.ndim else sw * A, sw * b
    H = g = None
    if level.H is not None:
        H = _array(level.H, f"{name}.H", 2)
        _check_shape(H, (n, n), f"{name}.H")
        H = 0.5 * (H + H.T)
    if level.g is not None:
        g = _array(level.g, f"{name}.g", 1)
        _check_shape(g, (n,), f"{name}.g")
    C = l = u = rho = None
    if level.C is not None:
        C = _array(level.C, f"{name}.C", 2)
        if C.shape[1] != n or C.shape[0] == 0:
            raise InputError(f"{name}.C has shape {C.shape}, expected (p >= 1, {n})")
        if level.l is None or level.u is None:
            raise InputError(f"{name}: C needs both l and u (use -inf/inf for a one-sided row)")
        l = _array(level.l, f"{name}.l", 1, allow_inf=True)
        u = _array(level.u, f"{name}.u", 1, allow_inf=True)
        _check_shape(l, (C.shape[0],), f"{name}.l")
        _check_shape(u, (C.shape[0],), f"{name}.u")
        _check_interval(l, u, f"{name}.l", f"{name}.u")
        if level.slack_weight is not None:
            rho = float(level.slack_weight)
            if not (np.isfinite(rho) and rho > 0):
                raise InputError(f"{name}.slack_weight must be > 0 and finite (or None for hard rows)")
    elif level.l is not None or level.u is not None:
        raise InputError(f"{name}: l/u given without C")
    return _LevelData(A, b, Aw, bw, H, g, C, l, u, rho)


def _trusted_level(level: Level) -> _LevelData:
    """A level taken as given (``solve(check=False)``): float arrays of the right shapes
    assumed, only the weight folded in and ``H`` symmetrised, as in :func:`_validate_level`."""
    f = np.asarray
    A = None if level.A is None else f(level.A, dtype=float)
    b = None if level.b is None else f(level.b, dtype=float)
    Aw, bw = A, b
    if A is not None and not (isinstance(level.weight, (int, float)) and level.weight == 1):
        sw = np.sqrt(f(level.weight, dtype=float))
        Aw, bw = (sw * A.T).T if sw.ndim else sw * A, sw * b
    H = None if level.H is None else f(level.H, dtype=float)
    if H is not None:
        H = 0.5 * (H + H.T)
    C = None if level.C is None else f(level.C, dtype=float)
    rho = None if C is None or level.slack_weight is None else float(level.slack_weight)
    return _LevelData(
        A,
        b,
        Aw,
        bw,
        H,
        None if level.g is None else f(level.g, dtype=float),
        C,
        None if C is None else f(level.l, dtype=float),
        None if C is None else f(level.u, dtype=float),
        rho,
    )


def _validate_bounds(lb: object, ub: object, n: int) -> tuple[np.ndarray, np.ndarray]:
    lo = np.full(n, -np.inf) if lb is None else _array(lb, "lb", 1, allow_inf=True)
    hi = np.full(n, np.inf) if ub is None else _array(ub, "ub", 1, allow_inf=True)
    _check_shape(lo, (n,), "lb")
    _check_shape(hi, (n,), "ub")
    _check_interval(lo, hi, "lb", "ub")
    return lo, hi
