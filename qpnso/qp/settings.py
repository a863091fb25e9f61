"""Settings of the hierarchical QP (docs/method.md §7.5, docs/qp-notes.md).

:class:`QPSettings` holds the tolerances of the cascade (rank, damping, gradient, feasibility and
activity thresholds, the tie-break ``μ``) and the budgets of its back ends (ProxQP's iterations and
tolerances, DAQP's fallback and hold); :data:`NATIVE_BACKEND` names the back end used unless
another is asked for.  They are one frozen dataclass, checked on construction, so that a
``[qp_settings]`` table of a configuration file gives the same object as code does.  The reason
for each default is in the comment beside it and in docs/qp-notes.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from qpnso.records import new_record
from qpnso.settings import keywords_checked

__all__ = ["QPSettings"]

NATIVE_BACKEND = "proxsuite"


@keywords_checked
@dataclass(frozen=True)
class QPSettings:
    """Tolerances of the cascade and of its QP back ends.

    ``eps_abs``/``eps_rel``/``eps_primal_inf``/``eps_dual_inf``/``max_iter``
    are ProxQP's (the defaults 1e-5/0/1e-4 are too loose for 1 ms velocity
    steps: a warm start can stop after zero iterations, see docs/qp-notes.md).
    ``solver_options`` are passed verbatim to ``qpsolvers.solve_problem``.
    """

    eps_abs: float = 1e-11
    eps_rel: float = 0.0
    eps_primal_inf: float = 1e-12
    eps_dual_inf: float = 1e-12
    max_iter: int = 5  # ProxQP's outer iterations per attempt (a tick's QP needs 2–13 inner ones in all, measured)
    max_iter_in: int = 5  # ProxQP's inner iterations per outer one: an attempt is at most ~30 iterations, then DAQP
    max_iter_active_set: int = 1000  # DAQP's iterations in the fallback (a tick's QP needs 2–10, measured)
    mu_in: float = 1e-3  # ProxQP default_mu_in: its 0.1 took 3.5 warm iterations per controller tick, 1e-3 took 2.2
    warm_start: bool = True  # ProxSuite: WARM_START_WITH_PREVIOUS_RESULT every tick
    box_constraints: bool = True  # ProxSuite: bounds as its native box (else as rows)
    regularization: float | None = None  # μ on the directions a task leaves free; None: 0 for
    # native ProxSuite (its proximal method handles a semi-definite H), 1e-7 for qpsolvers back ends
    rank_tol: float = 1e-10  # relative singular value below which a direction is null
    damping_threshold: float = 1e-2  # ε, units of A (m/rad, rad/rad); 0 disables damping
    gradient_tol: float = 1e-7  # relative size of a projected gradient that a level owns
    feasibility_tol: float = 1e-6  # accepted violation of bounds / hard rows (units of the row)
    bound_repair_tol: float = 1e-4  # rad/s: an answer off its bounds by at most this (hard rows within
    # feasibility_tol) is projected onto them instead of refused (qpnso.qp.cascade_state.repair_bounds)
    active_tol: float = 1e-7  # a higher level's bound/row this close to its answer is active below
    line_fast_path: bool = True  # a full-rank (n−1)-row first task: its exact solutions form a line (qpnso.qp.line)
    active_set_fallback: bool = True  # a failed ProxQP solve is handed to DAQP (active set, exact)
    active_set_hold: int = 100  # after a fallback, DAQP alone answers that QP's next solves (0: ProxQP every time)
    solver_options: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        """Types first (:func:`qpnso.settings.check`), then ranges."""
        from qpnso.settings import check, out_of_range

        check(self)
        if self.regularization is not None and self.regularization < 0:
            raise out_of_range(self, "regularization", "must be >= 0 or None")
        for name in (
            "eps_abs",
            "eps_rel",
            "eps_primal_inf",
            "eps_dual_inf",
            "mu_in",
            "rank_tol",
            "damping_threshold",
            "gradient_tol",
            "feasibility_tol",
            "bound_repair_tol",
            "active_tol",
        ):
            if getattr(self, name) < 0:
                raise out_of_range(self, name, "must be >= 0")
        for name in ("max_iter", "max_iter_in", "max_iter_active_set"):
            if getattr(self, name) <= 0:
                raise out_of_range(self, name, "must be > 0")
        if self.active_set_hold < 0:
            raise out_of_range(self, "active_set_hold", "must be >= 0")

    @classmethod
    def from_dict(cls, values: dict, where: str = "") -> "QPSettings":
        """Build from plain data (a ``[qp_settings]`` table); unknown keys are listed with the valid ones."""
        from qpnso.settings import from_dict

        return from_dict(cls, values, where)


TOLERANCE_DTYPE = np.dtype(
    [
        ("rank_tol", np.float64),
        ("damping_threshold", np.float64),
        ("regularization", np.float64),
        ("feasibility_tol", np.float64),
        ("bound_repair_tol", np.float64),
        ("gradient_tol", np.float64),
        ("active_tol", np.float64),
    ]
)
"""The tolerances the cascade's and the line fast path's kernels read, by name."""


def tolerance_record(settings: QPSettings) -> np.ndarray:
    """``settings``' tolerances as a :data:`TOLERANCE_DTYPE` record (1-element array; a ``None``
    regularisation is 0: the solver resolves it before)."""
    record = new_record(TOLERANCE_DTYPE)
    s = settings
    record[0] = (
        s.rank_tol,
        s.damping_threshold,
        s.regularization or 0.0,
        s.feasibility_tol,
        s.bound_repair_tol,
        s.gradient_tol,
        s.active_tol,
    )
    return record
