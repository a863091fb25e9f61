"""The metrics, as qpbenchmark defines them: the KKT residuals of an answer (:func:`kkt_residuals`), one
solve's :class:`Outcome`, the shifted geometric mean of the times, and the per-solver summary
(:func:`summarize`) written to ``results.csv``.

Kept to qpbenchmark's definitions so our numbers compare with its published ones.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from qpnso.errors import InputError
from qpnso.lab.solver_bench.backends import TIME_LIMIT_S
from qpnso.lab.solver_bench.problems import StandardForm

SGM_SHIFT_US = 10.0
"""Shift of the shifted geometric mean of solve times, µs (qpbenchmark's 10, in our time unit)."""


CSV_COLUMNS = (
    "solver",
    "settings",
    "success_rate",
    "runtime_sgm",
    "runtime_median_us",
    "primal_residual",
    "dual_residual",
    "duality_gap",
)
"""First columns of ``results.csv`` (more follow)."""


def kkt_residuals(sf: StandardForm, x: np.ndarray | None, y, z, z_box) -> tuple[float, float, float]:
    """qpbenchmark's (qpsolvers') primal residual, dual residual and duality gap:

    ``r_p = max(‖Ax − b‖∞, [Gx − h]⁺, [lb − x]⁺, [x − ub]⁺)``,
    ``r_d = ‖Px + q + Aᵀy + Gᵀz + z_box‖∞``,
    ``r_g = |xᵀPx + qᵀx + bᵀy + hᵀz + lbᵀz_box⁻ + ubᵀz_box⁺|``;
    ``inf`` when ``x`` or a needed dual is missing.
    """
    import qpsolvers

    if x is None or not np.all(np.isfinite(x)):
        return math.inf, math.inf, math.inf
    sol = qpsolvers.Solution(sf.problem, found=True, x=np.asarray(x, dtype=float), y=y, z=z, z_box=z_box)
    with np.errstate(all="ignore"):
        out = (float(sol.primal_residual()), float(sol.dual_residual()), float(sol.duality_gap()))
    return tuple(v if math.isfinite(v) else math.inf for v in out)  # type: ignore[return-value]


@dataclass
class Outcome:
    """One solve: ``time_s`` wall time of the call (``qpsolvers.solve_problem``, or
    ProxSuite ``init``/``update`` + ``solve``); residuals ``inf`` without a solution."""

    solver: str
    settings: str
    problem: str
    found: bool
    status: str  # "solved", "not found (…)", "error: <exception>", "inaccurate: primal/dual/gap", "timeout"
    time_s: float
    primal: float
    dual: float
    gap: float
    cost_error: float
    x_error: float  # ‖decode(v) − decode(ref_v)‖∞, rad/s
    success: bool
    time_limit_s: float = TIME_LIMIT_S
    detail: str = ""  # the solver's own status word and the offending residuals
    level: int = 0  # of the problem (1-based)


def shifted_geometric_mean(values: Sequence[float], shift: float) -> float:
    """``exp(mean(log(v + shift))) − shift`` (qpbenchmark's runtime/residual summary)."""
    v = np.asarray(values, dtype=float)
    if v.size == 0 or np.any(v < 0) or not np.all(np.isfinite(v)):
        raise InputError("shifted_geometric_mean needs finite values >= 0")
    return float(np.exp(np.mean(np.log(v + shift))) - shift)


def summarize(outcomes: Sequence[Outcome], reference_solver: str = "proxqp") -> list[dict]:
    """One row per (solver, settings), columns :data:`CSV_COLUMNS` then extras.

    ``success_rate`` in %; ``runtime_sgm`` shifted geometric mean of the time
    (µs, shift :data:`SGM_SHIFT_US`, a failure charged its setting's time limit)
    divided by the best solver's at the same setting; ``runtime_median_us``
    median time of all solves; residuals, gap and cost error: medians over the
    problems the solver returned a solution for (NaN if none), cost error and
    ``x_error`` over its successes only; ``*_max`` their worst; ``failures``
    counts per status; ``dq_error_max_L2`` the worst joint-velocity difference (rad/s)
    to the reference on the last level (the command; on level 1 the direction level 2
    decides is nearly flat, so its difference says nothing);
    ``time_ratio_to_<ref>`` median time / the reference solver's.
    """
    groups: dict[tuple[str, str], list[Outcome]] = {}
    for o in outcomes:
        groups.setdefault((o.solver, o.settings), []).append(o)
    rows: list[dict[str, Any]] = []
    for (solver, setting), group in groups.items():
        limit_us = group[0].time_limit_s * 1e6
        charged = [o.time_s * 1e6 if o.success else limit_us for o in group]
        found = [o for o in group if o.found]
        good = [o for o in group if o.success]

        def stat(fn, key: str, among: list[Outcome]) -> float:
            return float(fn([getattr(o, key) for o in among])) if among else math.nan

        failures: dict[str, int] = {}
        for o in group:
            if not o.success:
                failures[o.status] = failures.get(o.status, 0) + 1
        rows.append(
            {
                "solver": solver,
                "settings": setting,
                "success_rate": 100.0 * sum(o.success for o in group) / len(group),
                "runtime_sgm": shifted_geometric_mean(charged, SGM_SHIFT_US),
                "runtime_median_us": float(np.median([o.time_s for o in group]) * 1e6),
                "primal_residual": stat(np.median, "primal", found),
                "dual_residual": stat(np.median, "dual", found),
                "duality_gap": stat(np.median, "gap", found),
                "cost_error": stat(np.median, "cost_error", good),
                "cost_error_max": stat(np.max, "cost_error", good),
                "dq_error_max_L2": stat(np.max, "x_error", [o for o in good if o.level == 2]),
                "primal_residual_max": stat(np.max, "primal", found),
                "runtime_p99_us": float(np.percentile([o.time_s for o in group], 99) * 1e6),
                "problems": len(group),
                "found": len(found),
                "failures": "; ".join(f"{n}× {s}" for s, n in sorted(failures.items(), key=lambda kv: -kv[1])),
            }
        )
    for setting in {r["settings"] for r in rows}:
        same = [r for r in rows if r["settings"] == setting]
        best = min(r["runtime_sgm"] for r in same)
        ref = next((r["runtime_median_us"] for r in same if r["solver"] == reference_solver), None)
        for r in same:
            r["runtime_sgm"] = r["runtime_sgm"] / best if best > 0 else math.nan
            r[f"time_ratio_to_{reference_solver}"] = r["runtime_median_us"] / ref if ref else math.nan
    order = {"default": 0, "high_accuracy": 1}
    rows.sort(key=lambda r: (order.get(r["settings"], 9), r["runtime_sgm"]))
    return rows


def write_results_csv(rows: Sequence[dict], path: Path) -> Path:
    """``results.csv``: :data:`CSV_COLUMNS` first, then the extra columns of :func:`summarize`."""
    if not rows:
        raise InputError("no result rows to write")
    extra = [k for k in rows[0] if k not in CSV_COLUMNS]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(CSV_COLUMNS) + extra)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    return path
