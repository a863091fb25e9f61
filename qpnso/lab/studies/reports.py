"""What a study writes: its summary (beside the papers' figures), ``results.csv``, its figure and Table I."""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from qpnso.lab.studies.jobs import SCENARIO_JOBS, _share_label
from qpnso.lab.studies.options import StudyOptions

PAPER: dict[str, dict[str, Any]] = {
    "workspace": {
        "mass_reduction_pct": {"mean": 44.23, "sd": 20.97},
        "friction_reduction_pct": {"mean": 41.44, "sd": 21.93},
        "samples": 1000,
    },
    "uncertainty": {"increase_pct": {"mean": 0.0631, "sd": 0.361, "worst": 5.298}, "poses": 100, "trials": 100},
    "scenarios": {
        "smoothness": {"A": {"damped": 482, "fixed": 446, "rom": 410}, "B": {"damped": 1140, "fixed": 426, "rom": 408}},
        "note": "elbow paper Table I: S for DP (damped), FOP (fixed), NSO (rom)",
    },
}
"""Figures of the papers, written beside ours in each summary."""


# --------------------------------------------------------------- summaries
def stats(values: Sequence[float | None]) -> dict[str, float | int]:
    """mean, sd (n − 1), median, min, max, n of the finite values."""
    a = np.array([v for v in values if v is not None], dtype=float)
    a = a[np.isfinite(a)]
    if a.size == 0:
        return {"n": 0}
    return {
        "mean": float(a.mean()),
        "sd": float(a.std(ddof=1)) if a.size > 1 else 0.0,
        "median": float(np.median(a)),
        "min": float(a.min()),
        "max": float(a.max()),
        "n": int(a.size),
    }


def _fraction(results: list[dict], key: str) -> float:
    return float(np.mean([bool(r[key]) for r in results]))


def workspace_summary(results: list[dict], opts: StudyOptions) -> dict[str, Any]:
    return {
        "samples": len(results),
        "mass_reduction_pct": stats([r["mass_reduction_pct"] for r in results]),
        "friction_reduction_pct": stats([r["friction_reduction_pct"] for r in results]),
        "definition": "reduction = (value at the local-max posture - value at the local-min posture) / "
        "value at the local-max posture * 100; mass: largest principal mass (kg) at the c_m "
        "extrema; friction: sqrt(c_f) (N) at the c_f extrema",
        "stopped_at_interval_end": {
            f"{n}_{s}": _fraction(results, f"{n}_{s}_at_end") for n in ("mass", "friction") for s in ("min", "max")
        },
        "interior_only": {  # both extrema of the measure strictly inside the continuity interval
            f"{n}_reduction_pct": stats(
                [r[f"{n}_reduction_pct"] for r in results if not (r[f"{n}_min_at_end"] or r[f"{n}_max_at_end"])]
            )
            for n in ("mass", "friction")
        },
        "full_circle_fraction": _fraction(results, "full_circle"),
        "rejected_singular_draws": int(sum(r["rejected_draws"] for r in results)),
        "paper": PAPER["workspace"],
    }


def tradeoff_summary(results: list[dict], opts: StudyOptions) -> dict[str, Any]:
    out: dict[str, Any] = {
        "samples": len(results),
        "optima_distance_rad": stats([r["optima_distance_rad"] for r in results]),
    }
    for w in opts.mass_shares:
        key = _share_label(w)
        out[key] = {
            "mass_share": w,
            **{
                m: stats([r[f"{key}_{m}"] for r in results])
                for m in (
                    "mass_change_pct",
                    "friction_change_pct",
                    "mass_share_of_reduction_pct",
                    "friction_share_of_reduction_pct",
                )
            },
        }
    out["definition"] = (
        "change = (value at the weighted optimum - value at the single-objective optimum) / "
        "value at the single-objective optimum * 100 (paper Fig. 4); share_of_reduction = "
        "(start - weighted) / (start - single optimum) * 100"
    )
    return out


def uncertainty_summary(results: list[dict], opts: StudyOptions) -> dict[str, Any]:
    inc = np.concatenate([r["increase_pct"] for r in results])
    s = stats(inc.tolist())
    s["worst"] = s.pop("max")
    return {
        "poses": len(results),
        "trials_per_pose": opts.trials,
        "friction_sd": opts.friction_sd,
        "increase_pct": s,
        "fraction_increased": float(np.mean(inc > 1e-9)),
        "fraction_decreased": float(np.mean(inc < -1e-9)),
        "paper": PAPER["uncertainty"],
        "perturbation": "tau_max_k * (1 + friction_sd * N(0, 1)) per joint and trial; "
        "increase = (true sqrt(c_f) at the perturbed optimum - true optimum) / true optimum * 100",
    }


def scenarios_summary(results: list[dict], opts: StudyOptions) -> dict[str, Any]:
    keys = ("elbow_mobility_deg", "constraint_proximity_deg", "smoothness")
    table: dict[str, dict] = {}
    for r in results:
        row = {k: r.get(k) for k in keys}
        row["margin_respected"] = r.get("constraint_proximity_deg", -math.inf) >= r["safety_margin_deg"]
        table.setdefault(r["scenario"], {})[r["strategy"]] = row
    return {"table": table, "duration_scale": opts.duration_scale, "paper": PAPER["scenarios"]}


# --------------------------------------------------------------- outputs
def _atomic_bytes(path: Path, data: bytes) -> None:
    from qpnso.control.offline import atomic_write

    atomic_write(path, lambda f: f.write(data))


def _csv_bytes(rows: list[dict]) -> bytes:
    buf = io.StringIO()
    columns = list(rows[0]) if rows else []
    writer = csv.DictWriter(buf, columns, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue().encode()


def _flat(result: dict) -> dict:
    out = {}
    for k, v in result.items():
        if isinstance(v, list):
            out.update({f"{k}_{i + 1}": x for i, x in enumerate(v)})
        else:
            out[k] = v
    return out


def csv_rows(name: str, results: list[dict]) -> list[dict]:
    """Rows of ``results.csv``: one per job (uncertainty: one per trial)."""
    if name == "uncertainty":
        return [
            {
                "pose": i,
                "trial": t,
                "increase_pct": x,
                "perturbed_opt_ns_deg": ns,
                "friction_opt_N": r["friction_opt_N"],
            }
            for i, r in enumerate(results)
            for t, (x, ns) in enumerate(zip(r["increase_pct"], r["perturbed_opt_ns_deg"]))
        ]
    return [{"job": i, **_flat(r)} for i, r in enumerate(results)]


def _figure_bytes(fig) -> bytes:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120)
    plt.close(fig)
    return buf.getvalue()


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def plot_study(name: str, results: list[dict], summary: dict, opts: StudyOptions) -> bytes:
    """The study's figure as PNG bytes (paper Figs. 2, 4+5a, 6; bars for the scenarios)."""
    plt = _plt()
    if name == "workspace":
        fig, ax = plt.subplots(figsize=(7, 4))
        for key, label, colour in (
            ("mass_reduction_pct", "largest principal mass", "tab:blue"),
            ("friction_reduction_pct", "friction force magnitude", "tab:red"),
        ):
            ax.plot(
                np.sort([r[key] for r in results]), color=colour, label=f"{label} (mean {summary[key]['mean']:.1f} %)"
            )
        ax.set(
            xlabel="trial (sorted)",
            ylabel="reduction local max → local min (%)",
            title=f"{opts.robot}: {len(results)} random poses (paper Fig. 2)",
        )
    elif name == "tradeoff":
        fig, axes = plt.subplots(1, 3, figsize=(13, 4))
        for ax, metric, what in (
            (axes[0], "mass_change_pct", "principal mass"),
            (axes[1], "friction_change_pct", "friction force"),
        ):
            for w in opts.mass_shares:
                key = _share_label(w)
                ax.plot(
                    np.sort([r[f"{key}_{metric}"] for r in results]), label=f"{round(100 * w)}/{round(100 * (1 - w))}"
                )
            ax.set(xlabel="trial (sorted)", ylabel=f"{what}: weighted vs single optimum (%)")
        axes[0].set_title("Fig. 4a"), axes[1].set_title("Fig. 4b")
        axes[2].plot(np.sort([r["optima_distance_rad"] for r in results]), color="k")
        axes[2].set(xlabel="trial (sorted)", ylabel="‖q_mass − q_friction‖ (rad)", title="Fig. 5a")
        ax = axes[1]
    elif name == "uncertainty":
        fig, ax = plt.subplots(figsize=(7, 4))
        inc = np.sort(np.concatenate([r["increase_pct"] for r in results]))
        ax.plot(
            inc,
            color="tab:red",
            label=f"mean {summary['increase_pct']['mean']:.3g} %, worst {summary['increase_pct']['worst']:.3g} %",
        )
        ax.set(xlabel="trial (sorted)", ylabel="true friction increase (%)", title="paper Fig. 6")
    else:
        fig, axes = plt.subplots(1, 3, figsize=(13, 4))
        strategies = [st for _, st in SCENARIO_JOBS[:5]]
        x = np.arange(len(strategies))
        for ax, metric in zip(axes, ("elbow_mobility_deg", "constraint_proximity_deg", "smoothness")):
            for k, sc in enumerate(("A", "B")):
                row = summary["table"].get(sc, {})
                ax.bar(
                    x + 0.4 * k, [row.get(st, {}).get(metric) or 0.0 for st in strategies], 0.4, label=f"scenario {sc}"
                )
            ax.set_xticks(x + 0.2, strategies)
            ax.set_title(metric)
        ax = axes[0]
    ax.legend()
    fig.tight_layout()
    return _figure_bytes(fig)


def scenarios_table(summary: dict) -> str:
    """Markdown in the layout of the elbow paper's Table I (plus Δ, Δc and the margin check)."""
    lines = [
        "| scenario | strategy | Δ (deg) | Δc (deg) | Δc ≥ margin | S | S paper |",
        "|---|---|---|---|---|---|---|",
    ]
    paper = PAPER["scenarios"]["smoothness"]
    for sc, rows in summary["table"].items():
        for st, row in rows.items():
            fmt = lambda v, f: "n/a" if v is None else format(v, f)  # noqa: E731
            lines.append(
                f"| {sc} | {st} | {fmt(row['elbow_mobility_deg'], '.1f')} | "
                f"{fmt(row['constraint_proximity_deg'], '.1f')} | {'yes' if row['margin_respected'] else 'no'} | "
                f"{fmt(row['smoothness'], '.0f')} | {paper.get(sc, {}).get(st, '')} |"
            )
    return "\n".join(lines) + "\n"
