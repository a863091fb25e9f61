"""What the hierarchical QP reports (docs/method.md §7.5, §7.6).

Each level's outcome (:class:`LevelStatus`, :class:`LevelResult`), the cascade's (:class:`HQPResult`,
with :func:`level_failure` naming its first failed level) and counters across ticks
(:class:`HQPStats`).  Solver trouble is reported here, never raised and never NaN: the caller (the
controller, docs/method.md §7.6) chooses what to command from the status.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

__all__ = ["HQPResult", "HQPStats", "LevelResult", "LevelStatus"]


class LevelStatus(str, enum.Enum):
    """Outcome of one level."""

    SOLVED = "solved"
    INFEASIBLE = "infeasible"  # hard constraints cannot all hold
    MAX_ITER = "max_iter"
    INACCURATE = "inaccurate"  # solver said solved, but the answer failed verification
    SOLVER_ERROR = "solver_error"
    SKIPPED = "skipped"  # a higher level failed
    TIME_BUDGET = "time_budget"  # the cascade's time budget was spent before this level (not solved)

    def __str__(self) -> str:
        return self.value


@dataclass
class LevelResult:
    """One level: ``x`` the cascade's joint velocity after it (rad/s); ``residual``
    ``‖A x − b‖`` (units of b, unweighted) of its task; ``slack`` the violation
    (≥ 0) of each soft row at ``x``; ``solve_time_s`` wall time (build + solve +
    checks); ``iterations`` as the back end reports them (None if it does not)."""

    status: LevelStatus
    x: np.ndarray | None = None
    residual: float | None = None
    slack: np.ndarray | None = None
    iterations: int | None = None
    solve_time_s: float = 0.0
    message: str = ""

    @property
    def ok(self) -> bool:
        return self.status is LevelStatus.SOLVED


@dataclass
class HQPResult:
    """The cascade: ``x`` the last good level's answer (None if level 1 failed);
    ``ok`` all levels solved; ``status`` ``"solved"`` or which level failed and
    why; ``failed_level`` its 0-based index."""

    x: np.ndarray | None
    ok: bool
    status: str
    failed_level: int | None
    levels: list[LevelResult]
    solve_time_s: float

    @property
    def solve_time(self) -> float:
        """Alias of ``solve_time_s`` (s)."""
        return self.solve_time_s

    @property
    def out_of_time(self) -> bool:
        """The cascade stopped because its time budget was spent (:attr:`LevelStatus.TIME_BUDGET`)."""
        return self.failed_level is not None and self.levels[self.failed_level].status is LevelStatus.TIME_BUDGET


@dataclass
class HQPStats:
    """Counters across ticks: ``qp_created`` QP objects allocated (ProxSuite),
    ``solves`` calls of :meth:`HierarchicalQP.solve`, ``failures`` not ok,
    ``cold_retries`` failed warm-started ProxSuite solves retried cold, ``active_set_fallbacks``
    ProxSuite failures handed to DAQP (:func:`active_set_solve`)."""

    qp_created: int = 0
    solves: int = 0
    failures: int = 0
    cold_retries: int = 0
    active_set_fallbacks: int = 0


def level_failure(k: int, n_levels: int, result: LevelResult) -> str:
    """How :attr:`HQPResult.status` names the first failed level ``k`` (0-based) of ``n_levels``."""
    return f"level {k + 1} of {n_levels} {result.status}: {result.message}"
