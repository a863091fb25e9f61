"""The benchmark's output: ``report.md`` (tables, failures, the closed loop), ``closed_loop.csv`` and the
figure ``solver_bench.png``; and :func:`run_solver_benchmark`, the entry point behind
``qpnso bench solvers`` that loads (or records) a problem set, runs it, and writes all of them into ``out``.
"""

from __future__ import annotations

import csv
import math
import platform
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from qpnso.lab.solver_bench.backends import TIME_LIMIT_S, available
from qpnso.lab.solver_bench.metrics import CSV_COLUMNS, SGM_SHIFT_US, summarize, write_results_csv
from qpnso.lab.solver_bench.problems import PROBLEM_DIR, load_problems
from qpnso.lab.solver_bench.record import record_problem_set
from qpnso.lab.solver_bench.runs import CLOSED_LOOP_KEYS, closed_loop, run_problems


def _fmt(v) -> str:
    if isinstance(v, float):
        if math.isnan(v):
            return "–"
        if math.isinf(v):
            return "inf"
        return f"{v:.3g}" if abs(v) >= 1e-3 or v == 0 else f"{v:.1e}"
    return str(v)


def _table(rows: Sequence[dict], columns: Sequence[str]) -> str:
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(_fmt(r.get(c, "")) for c in columns) + " |" for r in rows]
    return "\n".join(lines)


def _versions(solvers: Sequence[str]) -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    dist = {
        "proxsuite": "proxsuite",
        "proxqp": "proxsuite",
        "highs": "highspy",
        "sip": "sip-qp-python",
        "pyqpmad": "pyqpmad",
    }
    out = {}
    for s in list(solvers) + ["qpsolvers"]:
        try:
            out[s] = version(dist.get(s, s))
        except PackageNotFoundError:
            out[s] = "?"
    return out


def write_report(
    path: Path,
    rows: Sequence[dict],
    loop_rows: Sequence[dict],
    skipped: dict[str, str],
    meta: dict,
    n_problems: int,
    command: str,
    elapsed_s: float,
    solvers: Sequence[str],
    problem_set: Path,
    loop_info: str,
) -> Path:
    versions = _versions(solvers)
    cols = list(CSV_COLUMNS) + ["time_ratio_to_proxqp", "cost_error", "cost_error_max", "dq_error_max_L2"]
    parts = [
        "# QP solver benchmark on the controller's QPs",
        "",
        f"Command: `{command}` ({elapsed_s:.0f} s, {platform.processor() or platform.machine()}, "
        f"Python {platform.python_version()}).",
        "",
        f"Problem set: `{problem_set.name}`, {n_problems} QPs (levels 1 and 2, consecutive ticks of "
        f"recorded runs; built with μ = {meta.get('regularization')}).  Solvers (version): "
        + ", ".join(f"{s} {versions[s]}" for s in solvers)
        + f"; qpsolvers {versions['qpsolvers']}.",
        "",
    ]
    if skipped:
        parts += ["Skipped: " + "; ".join(f"`{s}` ({why})" for s, why in skipped.items()) + ".", ""]
    parts += [
        "`proxsuite` = ProxSuite's native dense API warm-started in place (as the controller); "
        "`proxqp` = the same solver through qpsolvers, cold.  success_rate in %; runtime_sgm = shifted "
        f"geometric mean of the time (shift {SGM_SHIFT_US:g} µs, a failure charged "
        f"{TIME_LIMIT_S * 1e3:g} ms) / the best; residuals, gap, cost error (|cost − reference|) "
        "= medians over returned solutions (cost error over successes), dq_error_max_L2 = worst "
        "joint-velocity difference (rad/s) to the reference on level 2, whose answer is the command.  "
        "default: each solver's defaults, checked at 1e-3; high_accuracy: "
        "eps_abs 1e-9, eps_rel 0 (qpbenchmark's mapping), checked at 1e-9.",
        "",
        "## Results",
        "",
        _table(rows, cols),
        "",
        "## Failures",
        "",
    ]
    fails = [r for r in rows if r["failures"]]
    parts += [f"* {r['solver']} / {r['settings']}: {r['failures']}" for r in fails] or ["none"]
    parts += ["", "## Closed loop", "", loop_info, ""]
    loop_cols = ["backend"] + list(CLOSED_LOOP_KEYS) + ["dq_diff_max"]
    if any("error" in r for r in loop_rows):
        loop_cols.append("error")
    parts += [_table(loop_rows, loop_cols), ""]
    notes = [f"* {r['backend']}: {r['first_message']}" for r in loop_rows if r.get("first_message")]
    if notes:
        parts += ["First controller message of each run that had one:", ""] + notes + [""]
    path.write_text("\n".join(parts))
    return path


def plot_results(rows: Sequence[dict], loop_rows: Sequence[dict], path: Path) -> Path | None:
    """Median solve time and success rate per solver and setting, and the closed loop's
    tick time; None when matplotlib is missing."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    solvers = sorted(
        {r["solver"] for r in rows}, key=lambda s: min(r["runtime_median_us"] for r in rows if r["solver"] == s)
    )
    width = 0.4
    for i, setting in enumerate(("default", "high_accuracy")):
        vals = [next((r for r in rows if r["solver"] == s and r["settings"] == setting), None) for s in solvers]
        xs = np.arange(len(solvers)) + (i - 0.5) * width
        axes[0].bar(xs, [v["runtime_median_us"] if v else 0 for v in vals], width, label=setting)
        for x, v in zip(xs, vals):
            if v:
                axes[0].text(
                    x,
                    v["runtime_median_us"],
                    f"{v['success_rate']:.0f}%",
                    ha="center",
                    va="bottom",
                    fontsize=6,
                    rotation=90,
                )
    axes[0].set_xticks(range(len(solvers)), solvers, rotation=45, ha="right")
    axes[0].set_yscale("log")
    axes[0].set_ylabel("median solve time per QP (µs), label: success %")
    axes[0].legend()
    ok = [r for r in loop_rows if "error" not in r]
    axes[1].bar([r["backend"] for r in ok], [r["tick_time_median_us"] for r in ok], label="median")
    axes[1].plot([r["backend"] for r in ok], [r["tick_time_p99_us"] for r in ok], "k_", markersize=12, label="p99")
    axes[1].set_yscale("log")
    axes[1].set_ylabel("closed loop: controller tick time (µs)")
    axes[1].tick_params(axis="x", rotation=45)
    axes[1].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def run_solver_benchmark(
    out: Path,
    quick: bool = False,
    solvers: Sequence[str] | None = None,
    problems: Path | None = None,
    progress: Callable[[str], None] | None = None,
) -> Path:
    """Benchmark the QP solvers on the controller's QPs; returns the path of ``report.md``.

    Writes into ``out``: ``report.md`` (tables), ``results.csv`` (one row per solver ×
    settings, :data:`CSV_COLUMNS` first), ``closed_loop.csv``, ``solver_bench.png``.
    ``quick``: the committed small set (``solvers/problems/quick.npz``) and a 0.3 s closed
    loop (under a minute on 2 cores); otherwise ``solvers/problems/full.npz`` (recorded into
    ``out`` when absent) and a 3 s closed loop.  ``solvers``: names to run (default: native
    ProxSuite and every installed ``qpsolvers`` back end; unknown ones are skipped with a note).
    """
    t0 = time.perf_counter()
    say = progress or (lambda msg: None)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if problems is None:
        problems = PROBLEM_DIR / ("quick.npz" if quick else "full.npz")
        if not problems.is_file():
            problems = out / problems.name
            if not problems.is_file():
                say(f"recording {problems} ...")
                record_problem_set(problems, full=not quick, progress=say)
    items, meta = load_problems(problems)
    say(f"{len(items)} problems from {problems}")
    usable, skipped = available(solvers)
    outcomes, _ = run_problems(items, usable)
    rows = summarize(outcomes)
    write_results_csv(rows, out / "results.csv")
    say("closed loop ...")
    seconds = 0.3 if quick else 3.0
    loop_rows = closed_loop(usable, "A", seconds)
    _write_rows_csv(loop_rows, out / "closed_loop.csv")
    plot_results(rows, loop_rows, out / "solver_bench.png")
    command = f"qpnso bench solvers{' --quick' if quick else ''} --out {out}"
    info = (
        f"Scenario A guidance path, first {seconds:g} s offline (`solve_trajectory`), one run per "
        "back end as `ControllerConfig.qp_backend` with its default options; `proxsuite` is the "
        "shipped controller (native, warm, eps_abs 1e-11).  dq_diff_max: max |dq − dq of the first "
        "row| (rad/s).  Times in µs."
    )
    return write_report(
        out / "report.md",
        rows,
        loop_rows,
        skipped,
        meta,
        len(items),
        command,
        time.perf_counter() - t0,
        usable,
        problems,
        info,
    )


def _write_rows_csv(rows: Sequence[dict], path: Path) -> Path:
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    return path
