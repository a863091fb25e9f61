"""QP solver comparison on the controller's own QPs (docs/method.md §7; methodology of qpbenchmark).

Three parts:

* **Problem sets**: the QPs of every level, tick by tick, recorded from real
  controller runs by wrapping ``ctrl.qp.solve`` of one instance
  (:class:`QPRecorder`) and rebuilding each level on the cascade's record
  (:class:`qpnso.qp.cascade_state.CascadeState`: ``build``, ``advance``),
  advanced with the controller's own answer of the level above: the benchmark
  solves exactly the QPs the controller solved.  Stored form (:class:`BenchProblem`):
  ``min ½vᵀPv + qᵀv  s.t.  l ≤ Cv ≤ u,  box_l ≤ v ≤ box_u`` (∓inf allowed), the
  form ProxSuite gets; :func:`standard_form` gives every other solver
  ``Gv ≤ h, Av = b, lb ≤ v ≤ ub`` (two-sided rows split, rows with ``l = u`` as
  equalities, a box with an infinite side folded into ``G``).
* **Runner** (:func:`run_problems`): every installed ``qpsolvers`` back end (cold
  one-shot solves) and ProxSuite's native dense API (``"proxsuite"``: one
  ``proxqp.dense.QP`` per problem sequence, level and shape, ``update`` + ``solve``
  warm-started with the previous result, as :mod:`qpnso.qp.backends` uses it), on the
  same problems, problem-major (all solvers interleaved on each problem).
  Metrics as qpbenchmark defines them (see :func:`kkt_residuals`): success =
  the solver says solved AND primal residual, dual residual and duality gap
  ≤ the settings' tolerance AND time ≤ the time limit; the shifted geometric
  mean of the time (shift :data:`SGM_SHIFT_US`, failures charged the time
  limit) normalised by the best solver.
* **Closed loop** (:func:`closed_loop`): the controller run with each back end
  as ``qp_backend`` on one scenario.

Entry point: :func:`run_solver_benchmark` (``report.md``, ``results.csv``,
``closed_loop.csv``, ``solver_bench.png``).

The package, one concept per module; each imports only those listed above it:

* :mod:`~qpnso.lab.solver_bench.problems`: :class:`BenchProblem`, :class:`StandardForm` and
  :func:`standard_form`, the problem-set files (:func:`save_problems`, :func:`load_problems`);
* :mod:`~qpnso.lab.solver_bench.backends`: :class:`BenchSettings` (:data:`DEFAULT`, :data:`HIGH_ACCURACY`),
  :func:`solver_options`, the native ProxSuite path (:data:`NATIVE`), the ``qpsolvers`` call, ``available``;
* :mod:`~qpnso.lab.solver_bench.metrics`: :func:`kkt_residuals`, :class:`Outcome`,
  :func:`shifted_geometric_mean`, :func:`summarize` and ``results.csv`` (:data:`CSV_COLUMNS`);
* :mod:`~qpnso.lab.solver_bench.runs`: :func:`run_problems`, :func:`compute_reference`, :func:`closed_loop`;
* :mod:`~qpnso.lab.solver_bench.record`: :class:`QPRecorder`, :func:`level_problems`, the recording plans and
  :func:`record_problem_set`;
* :mod:`~qpnso.lab.solver_bench.report`: ``report.md``, the figure, and :func:`run_solver_benchmark`.
"""

from __future__ import annotations

from qpnso.lab.solver_bench.backends import DEFAULT, HIGH_ACCURACY, NATIVE, BenchSettings, solver_options
from qpnso.lab.solver_bench.metrics import CSV_COLUMNS, Outcome, kkt_residuals, shifted_geometric_mean, summarize
from qpnso.lab.solver_bench.problems import BenchProblem, StandardForm, load_problems, save_problems, standard_form
from qpnso.lab.solver_bench.record import QPRecorder, level_problems, record_problem_set
from qpnso.lab.solver_bench.report import run_solver_benchmark
from qpnso.lab.solver_bench.runs import closed_loop, compute_reference, run_problems

__all__ = [
    "BenchProblem",
    "BenchSettings",
    "Outcome",
    "QPRecorder",
    "StandardForm",
    "CSV_COLUMNS",
    "DEFAULT",
    "HIGH_ACCURACY",
    "NATIVE",
    "closed_loop",
    "compute_reference",
    "kkt_residuals",
    "level_problems",
    "load_problems",
    "record_problem_set",
    "run_problems",
    "run_solver_benchmark",
    "save_problems",
    "shifted_geometric_mean",
    "solver_options",
    "standard_form",
    "summarize",
]
