"""The papers' studies, reproduced: workspace, trade-off, uncertainty, scenarios.

Mass/friction paper, section IV (docs/method.md §3, §9):

* ``workspace`` (IV-A, Fig. 2): random non-singular LWR4+ configurations; with
  the tool pose held, the arm is moved along its self-motion from the start
  configuration to the local minimum and the local maximum of the mass measure
  ``c_m`` [M 8] and of the friction-force measure ``c_f`` [M 15]; reported: the
  reduction of the largest principal mass (kg) between the local-max and
  local-min mass postures and of the friction-force magnitude ``√c_f`` (N)
  between the local-max and local-min friction postures, each
  ``(max − min)/max · 100`` %.
* ``tradeoff`` (IV-B, Figs. 4, 5a): the weighted cost ``w c_m/s_m + (1−w) c_f/s_f``
  [M 18] (``s`` = :attr:`CostModel.scales`) for mass shares ``w`` = 0.9, 0.5,
  0.1 against the single optima, and the joint distance between the mass and
  friction optima.
* ``uncertainty`` (IV-C, Fig. 6): per pose, trials with every joint's sliding
  torque scaled by ``1 + 0.1·ε``, ``ε ~ N(0, 1)`` (multiplicative on
  ``tau_max``, i.e. ``τf,e ~ N(τf, (0.1 τf)²)``); optimise with the perturbed
  model, evaluate the true friction there; reported: the % increase over the
  true optimum.

Elbow paper: ``scenarios`` runs scenarios A and B × strategies through
:func:`qpnso.lab.scenarios.run_scenario` and writes the layout of its Table I.

How an optimum is found.  The paper follows the null-space gradient from the
start posture until it stops.  Here the self-motion is parametrised exactly by
the arm angle ``ns`` (closed-form IK, :func:`qpnso.elbow.srs.self_motion`) over the
continuity interval of the start [E 9]: the cost is sampled on a grid of arm
angles (``grid_step_deg``, ``ns0`` and the interval ends on the grid), followed
downhill (or uphill) from ``ns0`` to the first grid minimum (maximum), and
refined by bounded Brent on the two neighbouring grid cells (``xatol`` 1e-9
rad).  An interval end (a joint limit, or joint 2 or 6 through 0) stops the
search, as it stops the robot.  A bump narrower than one grid cell can be
stepped over (a gradient flow would stop in front of it); the tests compare
against 0.01° sampling.

Non-singular start: ``σ_min(J Jᵀ) ≥ singular_threshold`` (default 1e-4, i.e. the
smallest singular value of the 6×7 tool Jacobian ≥ 0.01 m/rad or rad/rad; it
rejects about 5 % of uniform draws on the LWR4+) and a defined arm angle
(:func:`qpnso.elbow.arm_angle.arm_angle_status`); singular draws are redrawn and counted.

Every study writes into ``OUT``: ``checkpoint.jsonl`` (see
:mod:`qpnso.lab.parallel`), ``results.csv``, a PNG and, last, ``summary.json``.
Entry point: :func:`run_study`.

Modules: :mod:`.options` (:class:`StudyOptions`), :mod:`.measures` (the measures along
``q``, the worker's :class:`Workbench`, the objectives), :mod:`.curves` (the self-motion
of a start configuration, the extremum search, the random starts), :mod:`.jobs` (one job
of each study), :mod:`.reports` (summaries, ``results.csv``, figures, Table I) and
:mod:`.runner` (the registry :data:`STUDIES` and :func:`run_study`).
"""

from __future__ import annotations

from qpnso.lab.studies.curves import Extremum, SelfMotionCurve, arm_angle_grid, descend, sample_start
from qpnso.lab.studies.jobs import (
    SCENARIO_JOBS,
    reduction_pct,
    scenarios_job,
    tradeoff_job,
    uncertainty_job,
    workspace_job,
)
from qpnso.lab.studies.measures import (
    Measures,
    Objective,
    Workbench,
    curve_function,
    friction_objective,
    mass_objective,
    weighted_objective,
    workbench,
)
from qpnso.lab.studies.options import StudyOptions
from qpnso.lab.studies.reports import (
    PAPER,
    csv_rows,
    plot_study,
    scenarios_summary,
    scenarios_table,
    stats,
    tradeoff_summary,
    uncertainty_summary,
    workspace_summary,
)
from qpnso.lab.studies.runner import STUDIES, Study, run_study

__all__ = [
    "StudyOptions",
    "Measures",
    "Objective",
    "Workbench",
    "curve_function",
    "friction_objective",
    "mass_objective",
    "weighted_objective",
    "workbench",
    "Extremum",
    "SelfMotionCurve",
    "arm_angle_grid",
    "descend",
    "sample_start",
    "SCENARIO_JOBS",
    "reduction_pct",
    "scenarios_job",
    "tradeoff_job",
    "uncertainty_job",
    "workspace_job",
    "PAPER",
    "csv_rows",
    "plot_study",
    "scenarios_summary",
    "scenarios_table",
    "stats",
    "tradeoff_summary",
    "uncertainty_summary",
    "workspace_summary",
    "STUDIES",
    "Study",
    "run_study",
]
