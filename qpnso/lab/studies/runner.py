"""The studies' registry (:data:`STUDIES`) and their runner, :func:`run_study`."""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, Callable

from qpnso.errors import ConfigError
from qpnso.lab.parallel import RunSpec, run_jobs
from qpnso.lab.studies.jobs import SCENARIO_JOBS, scenarios_job, tradeoff_job, uncertainty_job, workspace_job
from qpnso.lab.studies.measures import workbench
from qpnso.lab.studies.options import StudyOptions
from qpnso.lab.studies.reports import (
    _atomic_bytes,
    _csv_bytes,
    csv_rows,
    plot_study,
    scenarios_summary,
    scenarios_table,
    tradeoff_summary,
    uncertainty_summary,
    workspace_summary,
)


# ---------------------------------------------------------------- registry
@dataclass(frozen=True)
class Study:
    """A study: its job, default size, the options it depends on, and its summary."""

    job: Callable[[int, int, StudyOptions], dict]
    default_n: int
    uses: tuple[str, ...]
    summarize: Callable[[list[dict], StudyOptions], dict]
    needs_workbench: bool = True
    fixed_n: int | None = None


_POSE_OPTIONS = ("robot", "grid_step_deg", "singular_threshold", "armature_kgm2")
STUDIES: dict[str, Study] = {
    "workspace": Study(workspace_job, 1000, _POSE_OPTIONS, workspace_summary),
    "tradeoff": Study(tradeoff_job, 1000, (*_POSE_OPTIONS, "mass_shares"), tradeoff_summary),
    "uncertainty": Study(uncertainty_job, 100, (*_POSE_OPTIONS, "trials", "friction_sd"), uncertainty_summary),
    "scenarios": Study(
        scenarios_job,
        len(SCENARIO_JOBS),
        ("duration_scale",),
        scenarios_summary,
        needs_workbench=False,
        fixed_n=len(SCENARIO_JOBS),
    ),
}
"""The studies :func:`run_study` knows."""


def _run_job(name: str, options: dict[str, Any], index: int, seed: int) -> dict:
    """Module-level (picklable) job: study ``name``, job ``index``."""
    return STUDIES[name].job(index, seed, StudyOptions.from_dict(options))


def _init_worker(options: dict[str, Any]) -> None:
    """Process-pool initialiser: build the worker's :class:`Workbench` once."""
    opts = StudyOptions.from_dict(options)
    workbench(opts.robot, opts.compile, opts.armature_kgm2)


def run_study(
    name: str,
    out: Path | str,
    n: int | None = None,
    seed: int = 0,
    workers: int | None = None,
    scheduler: Any = None,
    progress: bool = False,
    options: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Run (or resume) study ``name`` into folder ``out``; returns the summary written to ``summary.json``.

    ``n``: number of poses (default 1000 for workspace/tradeoff, 100 for
    uncertainty; scenarios: always the 10 pairs of :data:`SCENARIO_JOBS`, ``n``
    must be None or 10).  ``seed``: the study's seed (results are identical for
    any ``workers``/``scheduler``).  ``workers``: processes (default: all
    cores).  ``scheduler``: a Dask scheduler address (or cluster object) to run
    the jobs on instead.  ``options``: fields of :class:`StudyOptions`.
    """
    if name not in STUDIES:
        raise ConfigError(f"unknown study {name!r}; choose one of {sorted(STUDIES)}")
    study = STUDIES[name]
    opts = StudyOptions.from_dict(options)
    if study.fixed_n is not None and n not in (None, study.fixed_n):
        raise ConfigError(f"study {name} has {study.fixed_n} jobs (scenarios × strategies); do not give n={n}")
    n_jobs = study.default_n if n is None else int(n)
    if n_jobs < 1:
        raise ConfigError(f"n must be >= 1, got {n}")
    if name == "scenarios":
        try:
            import qpnso.lab.scenarios  # noqa: F401
        except ImportError as exc:
            raise ConfigError(
                f"the scenarios study needs qpnso.lab.scenarios, which cannot be imported: {exc}"
            ) from None
    stored = opts.subset(study.uses)
    worker_options = {**stored, "compile": opts.compile}
    spec = RunSpec(name, n_jobs, int(seed), stored)
    out = Path(out)
    t0 = time.perf_counter()
    results = run_jobs(
        spec,
        partial(_run_job, name, worker_options),
        out,
        init=partial(_init_worker, worker_options) if study.needs_workbench else None,
        workers=workers,
        scheduler=scheduler,
        progress=progress,
    )
    summary = {
        "study": name,
        "seed": int(seed),
        "options": stored,
        **study.summarize(results, opts),
        "seconds": time.perf_counter() - t0,
    }
    summary = _json_safe(summary)
    _atomic_bytes(out / "results.csv", _csv_bytes(csv_rows(name, results)))
    _atomic_bytes(out / f"{name}.png", plot_study(name, results, summary, opts))
    if name == "scenarios":
        _atomic_bytes(out / "table.md", scenarios_table(summary).encode())
    _atomic_bytes(out / "summary.json", (json.dumps(summary, indent=2) + "\n").encode())
    return summary


def _json_safe(data: Any) -> Any:
    """NaN/inf → None so that summary.json is strict JSON."""
    if isinstance(data, dict):
        return {k: _json_safe(v) for k, v in data.items()}
    if isinstance(data, (list, tuple)):
        return [_json_safe(v) for v in data]
    if isinstance(data, float) and not math.isfinite(data):
        return None
    return data
