"""The papers' user experiments, with virtual surgeons on the MuJoCo plant (docs/method.md §9).

* ``mass-friction`` (:mod:`.mass_friction`): point-to-point moves between six targets in pre-registered work
  areas (:mod:`.work_areas`), the paper's four strategies, qpnso's ``qp``, an ablation and two controls; work
  per metre under both readings normalised per subject [M 24], the orthogonal moment (its Fig. 10b);
  Kolmogorov–Smirnov, Kruskal–Wallis, Dunn–Šidák (its Table I); three-valued verdicts
  (:mod:`.mass_friction_analysis`).
* ``elbow`` (:mod:`.elbow`): scenarios A and B × DP, FOP, NSO and qp; Δ, Δc, S per segment (its Fig. 6 and
  Table I); Kruskal–Wallis and Bartlett.

:func:`run_experiment` runs one on the studies' parallel runner (:mod:`qpnso.lab.parallel`: process pool or
Dask, seeded, resumable) and writes into ``OUT``: ``checkpoint.jsonl``, ``trials.csv`` (one row per trial),
``stats.json`` (statistics and verdicts), ``report.md`` (tables and verdicts) and ``figures.png``.
Modules: :mod:`.trials` (seeds, subjects, rows), :mod:`.statistics`, :mod:`.analysis`.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict
from functools import partial
from pathlib import Path
from typing import Any

from qpnso.errors import ConfigError
from qpnso.lab.experiments.elbow import STRATEGIES as ELBOW_STRATEGIES
from qpnso.lab.experiments.elbow import ElbowOptions, elbow_job
from qpnso.lab.experiments.mass_friction import MassFrictionOptions, mass_friction_job, work_area_summary
from qpnso.lab.parallel import RunSpec, run_jobs

EXPERIMENTS = ("mass-friction", "elbow")


def run_experiment(
    name: str,
    out: Path | str,
    options: dict[str, Any] | None = None,
    seed: int = 0,
    workers: int | None = None,
    scheduler: Any = None,
    progress: bool = False,
) -> dict[str, Any]:
    """Run (or resume) experiment ``name`` into ``out``; returns ``stats.json``'s content.

    ``options``: fields of :class:`MassFrictionOptions` or :class:`ElbowOptions`.
    """
    from qpnso.lab.experiments import analysis
    from qpnso.lab.studies.reports import _atomic_bytes, _csv_bytes

    if name not in EXPERIMENTS:
        raise ConfigError(f"unknown experiment {name!r}; choose one of {list(EXPERIMENTS)}")
    opts: MassFrictionOptions | ElbowOptions
    if name == "mass-friction":
        opts = MassFrictionOptions(**(options or {}))
        job = partial(mass_friction_job, opts=opts)
    else:
        opts = ElbowOptions(**(options or {}))
        job = partial(elbow_job, opts=opts)
    out = Path(out)
    t0 = time.perf_counter()
    rows = run_jobs(
        RunSpec(name, opts.n_jobs, int(seed), asdict(opts)),
        job,
        out,
        workers=workers,
        scheduler=scheduler,
        progress=progress,
    )
    header = f"Experiment {name}, seed {seed}, {opts.n_jobs} trials, options {asdict(opts)}"
    if isinstance(opts, MassFrictionOptions):
        from qpnso.lab.experiments import mass_friction_analysis as mfa

        stats = mfa.mass_friction_stats(rows, work_area_summary(opts), opts.control_reps)
        report = mfa.mass_friction_report(stats, header)
        names = opts.strategies + opts.controls
        panels = [(title, analysis.groups(rows, metric, names)) for metric, title in mfa.METRICS.items()]
    else:
        stats = analysis.elbow_stats(rows)
        report = analysis.elbow_report(stats, header)
        panels = [
            ("A: Δ (deg)", analysis.groups(rows, "elbow_mobility_deg", ELBOW_STRATEGIES, scenario="A", tremor="on")),
            (
                "B: Δc (deg)",
                analysis.groups(rows, "constraint_proximity_deg", ELBOW_STRATEGIES, scenario="B", tremor="on"),
            ),
            ("A: S per segment", analysis.elbow_segments([r for r in rows if r["tremor"] == "on"], "A")),
            ("B: S per segment", analysis.elbow_segments([r for r in rows if r["tremor"] == "on"], "B")),
        ]
    stats = {
        "experiment": name,
        "seed": int(seed),
        "options": asdict(opts),
        **stats,
        "seconds": time.perf_counter() - t0,
    }
    _atomic_bytes(out / "trials.csv", _csv_bytes(rows))
    _atomic_bytes(out / "stats.json", json.dumps(stats, indent=1, default=float).encode())
    _atomic_bytes(out / "report.md", report.encode())
    try:
        _atomic_bytes(out / "figures.png", analysis.box_figure(panels, header[:120]))
    except ImportError:
        pass  # (no matplotlib: the figure is skipped, the tables are written)
    return stats
