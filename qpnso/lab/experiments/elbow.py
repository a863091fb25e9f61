"""The elbow paper's user experiment ([E] §II-D, §III), with virtual surgeons on the MuJoCo plant.

Protocol: scenarios A and B (``examples/scenarios/A.toml``, ``B.toml``), each guided along the elbow
paper's path (three lemniscates and a parabola, each timed by the two-thirds power law and ending at rest,
:func:`qpnso.lab.surgeon.guidance_motion`) by ``subjects`` virtual surgeons, ``trials`` times each, with
every strategy:

* ``DP`` (``damped``): null-space damping 10 N·m·s/rad;
* ``FOP`` (``fixed``): 30 N·m/rad towards the initial posture (and the same damping);
* ``NSO`` (``rom``): the set-point modulation, stiffness 10–30 N·m/rad, d_sg 10° (the scenario files');
* ``qp``: qpnso.

The plant has :data:`qpnso.lab.experiments.trials.EXPERIMENT_MODEL_ERROR` (one draw per run).  Per trial:
Δ [E 12], Δc [E 13] and S [E 14] per segment on positions low-passed at 6 Hz
(:data:`qpnso.lab.simulation.SMOOTHNESS_CUTOFF_HZ`).  Statistics: Kruskal–Wallis across strategies per
scenario, Bartlett on variances (:mod:`qpnso.lab.experiments.statistics`), on the trials with the tremor on;
``quiet_trials`` more per scenario, subject and strategy run with the tremor off (S with the noise on and off).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, replace
from typing import Any

from qpnso.errors import ConfigError
from qpnso.lab.experiments.trials import (
    PlantOptions,
    run_or_error,
    subject,
    subject_record,
    trial_row,
)

SCENARIOS = ("A", "B")
STRATEGIES = {"DP": "damped", "FOP": "fixed", "NSO": "rom", "qp": "qp"}
"""The paper's names of the strategies (and qpnso's), in table order."""


@dataclass(frozen=True)
class ElbowOptions(PlantOptions):
    """Size of the experiment; ``duration_scale`` < 1 runs only the start of each path (quick checks)."""

    subjects: int = 3
    trials: int = 3
    duration_scale: float = 1.0
    quiet_trials: int = 1  # per scenario, subject and strategy: trials with the tremor off (S without noise)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.subjects < 1 or self.trials < 1 or self.quiet_trials < 0:
            raise ConfigError(
                f"subjects and trials must be >= 1 and quiet_trials >= 0, got {self.subjects}, {self.trials}, "
                f"{self.quiet_trials}"
            )
        if not 0 < self.duration_scale <= 1:
            raise ConfigError(f"duration_scale must be in (0, 1], got {self.duration_scale}")

    @property
    def n_jobs(self) -> int:
        return len(SCENARIOS) * self.subjects * (self.trials + self.quiet_trials) * len(STRATEGIES)

    def job(self, index: int) -> tuple[str, int, int, str]:
        """``(scenario, subject, trial, strategy)`` of job ``index`` (the paper's strategy name); trials from
        ``trials`` on are the quiet ones (tremor off)."""
        grid = itertools.product(SCENARIOS, range(self.subjects), range(self.trials + self.quiet_trials), STRATEGIES)
        return next(itertools.islice(grid, index, None))


def elbow_job(index: int, seed: int, opts: ElbowOptions) -> dict[str, Any]:
    """One trial of job ``index``: its row."""
    from qpnso.lab.scenarios import load_scenario, simulate_scenario

    scenario, s, trial, name = opts.job(index)
    person = subject(seed, s)
    tremor = trial < opts.trials
    sim = replace(opts.simulation(seed, index, person), tremor=tremor)
    sc = load_scenario(scenario)
    robot = opts.load_robot(sc.robot)
    summary, error = run_or_error(
        lambda: simulate_scenario(scenario, STRATEGIES[name], opts.duration_scale, simulation=sim, robot=robot)
    )
    margin = float(sc.controller.get("safety_margin_deg", 10.0))
    return {
        "scenario": scenario,
        "strategy": name,
        "subject": s,
        "trial": trial,
        "tremor": "on" if tremor else "off",
        "safety_margin_deg": margin,
        **trial_row(summary, error),
        **subject_record(person),
    }
