"""The hierarchical QP (docs/method.md §7): levels, the line fast path, the general cascade and its
back ends.  Its modules, each using only those listed before it:

* :mod:`.settings` — :class:`QPSettings`, the cascade's tolerances and its back ends' budgets;
* :mod:`.levels` — :class:`Level`, one priority level, and the checks of a level's input;
* :mod:`.cascade` — the null-space cascade's arithmetic: one level's QP, what a level owns and passes
  down, the check of a level's answer (§7.5);
* :mod:`.cascade_state` — the cascade's state (a record and a buffer) and the kernels that build, check
  and advance a level on it, reading a tick's problem record or a caller's levels (§7.5);
* :mod:`.line` — the line fast path: level 1 in closed form, level 2 as a QP on the line (§7.3, §7.4);
* :mod:`.results` — :class:`LevelStatus`, :class:`LevelResult`, :class:`HQPResult`, ``HQPStats``;
* :mod:`.backends` — ProxSuite (persistent, warm-started), the DAQP fallback, qpsolvers (§7.5);
* :mod:`.solver` — :class:`HierarchicalQP`, which runs them (§7).
"""

from qpnso.qp.levels import Level
from qpnso.qp.results import HQPResult, LevelResult, LevelStatus
from qpnso.qp.settings import QPSettings
from qpnso.qp.solver import HierarchicalQP

__all__ = ["HQPResult", "HierarchicalQP", "Level", "LevelResult", "LevelStatus", "QPSettings"]
