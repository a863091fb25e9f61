"""The experiments' analyses: statistics, the papers' tables and figures, and a verdict on each claim.

A verdict is computed from the measured statistics by the rule stated with the claim (the papers' own
thresholds), never edited by hand: ``reproduced`` or ``not reproduced`` with the figures that decide it.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from qpnso.errors import ConfigError, InputError
from qpnso.lab.experiments import statistics as st
from qpnso.lab.experiments.elbow import SCENARIOS
from qpnso.lab.experiments.elbow import STRATEGIES as ELBOW_STRATEGIES
from qpnso.lab.metrics import relative_work


def groups(rows: list[dict], key: str, names, **where: Any) -> dict[str, np.ndarray]:
    """``key``'s values by strategy (in ``names``' order) over the rows matching ``where``."""
    chosen = [r for r in rows if all(r[k] == v for k, v in where.items())]
    return {n: np.array([r[key] for r in chosen if r["strategy"] == n], dtype=float) for n in names}


def normalise_per_subject(rows: list[dict], key: str, out_key: str, reference=None) -> None:
    """[M 24] per subject (:func:`qpnso.lab.metrics.relative_work`): each trial's ``key`` over the largest
    per-strategy mean of that subject's trials among the strategies ``reference`` (default: all), written as
    ``out_key`` (NaN for a trial without a value)."""
    for r in rows:
        r[out_key] = math.nan
    for s in sorted({r["subject"] for r in rows}):
        mine = [r for r in rows if r["subject"] == s and math.isfinite(r[key])]
        by_strategy: dict[str, list[dict]] = {}
        for r in mine:
            by_strategy.setdefault(r["strategy"], []).append(r)
        try:
            scaled = relative_work({k: np.array([r[key] for r in v]) for k, v in by_strategy.items()}, reference)
        except InputError:  # (no reference strategy for this subject, or its largest mean is not positive)
            continue
        for name, trials in by_strategy.items():
            for r, value in zip(trials, scaled[name]):
                r[out_key] = float(value)


def three_valued(claim: str, judged: dict[str, bool], measured: str, blockers: list[str], why_not: str = "") -> dict:
    """A verdict (issue 32): ``untestable`` with the reasons in ``blockers`` (those not empty), or when the
    readings in ``judged`` (name → the claim holds under it) disagree; else ``reproduced`` or ``not reproduced``
    (then with ``why_not``)."""
    out = {"claim": claim, "measured": measured}
    reasons = [b for b in blockers if b]
    if not reasons and len(set(judged.values())) > 1:
        reasons = ["the two readings disagree (" + ", ".join(f"{k}: {v}" for k, v in judged.items()) + ")"]
    if reasons:
        return {**out, "verdict": "untestable", "why": "; ".join(reasons)}
    ok = next(iter(judged.values()))
    return {
        **out,
        "verdict": "reproduced" if ok else "not reproduced",
        **({} if ok or not why_not else {"why": why_not}),
    }


MECHANISM_MIN_DP_RANGE_DEG = 20.0
"""deg: [E] B's contrast needs an elbow that drifts: DP's median Δ in scenario A at least this (issue 32)."""
SMOOTHNESS_THRESHOLD = 500.0
"""[E 14]'s S per segment the elbow paper's claim E3 puts every smooth strategy under."""
DP_B_SMOOTHNESS_MIN = 1100.0
"""[E 14]'s S per segment E3 puts DP above in scenario B."""


def compare(g: dict[str, np.ndarray]) -> dict[str, Any]:
    """Spread per group, Kolmogorov–Smirnov normality, Kruskal–Wallis and Dunn–Šidák."""
    return {
        "spread": {k: st.spread(v) for k, v in g.items()},
        "normality_ks_p": st.normality(g),
        "kruskal": st.kruskal(g),
        "dunn_sidak_p": st.dunn_sidak(g),
    }


def stopped(rows: list[dict], names) -> dict[str, int]:
    """How many trials of each strategy in ``names`` stopped (a row with an error)."""
    return {n: sum(1 for r in rows if r["strategy"] == n and r["error"]) for n in names}


def elbow_segments(rows: list[dict], scenario: str) -> dict[str, np.ndarray]:
    """Every segment's smoothness S by strategy in ``scenario`` (a trial gives one value per segment)."""
    out = {}
    for name in ELBOW_STRATEGIES:
        values = [
            v
            for r in rows
            if r["scenario"] == scenario and r["strategy"] == name
            for k, v in r.items()
            if k.startswith("smoothness_segment_")
        ]
        out[name] = np.array(values, dtype=float)
    return out


def elbow_stats(all_rows: list[dict]) -> dict[str, Any]:
    """Per scenario: spread of Δ, Δc and S (per segment) by strategy; Kruskal–Wallis over the paper's three
    strategies; Bartlett over them and NSO against each of DP and FOP (the trials with the tremor on); S per
    segment with the tremor off and the intended motion's own S; verdicts."""
    paper = ("DP", "FOP", "NSO")
    rows = [r for r in all_rows if r.get("tremor", "on") == "on"]
    quiet = [r for r in all_rows if r.get("tremor", "on") == "off"]
    out: dict[str, Any] = {"trials": len(rows), "quiet_trials": len(quiet), "stopped": {}}
    for sc in SCENARIOS:
        block: dict[str, Any] = {}
        out["stopped"][sc] = stopped([r for r in rows if r["scenario"] == sc], ELBOW_STRATEGIES)
        for key in ("elbow_mobility_deg", "constraint_proximity_deg"):
            g = groups(rows, key, ELBOW_STRATEGIES, scenario=sc)
            block[key] = _elbow_tests(g, paper)
        block["smoothness_per_segment"] = _elbow_tests(elbow_segments(rows, sc), paper)
        block["smoothness_quiet"] = {k: st.spread(v) for k, v in elbow_segments(quiet, sc).items()}
        block["intended_smoothness"] = st.spread([r["intended_smoothness"] for r in all_rows if r["scenario"] == sc])
        out[sc] = block
    out["verdicts"] = elbow_verdicts(out, rows)
    return out


def _elbow_tests(g: dict[str, np.ndarray], paper: tuple[str, ...]) -> dict[str, Any]:
    sub = {k: g[k] for k in paper}
    out: dict[str, Any] = {"spread": {k: st.spread(v) for k, v in g.items()}}
    tests = {
        "kruskal": lambda: st.kruskal(sub),
        "bartlett": lambda: st.bartlett(sub),
        "bartlett_NSO_DP": lambda: st.bartlett({k: sub[k] for k in ("NSO", "DP")}),
        "bartlett_NSO_FOP": lambda: st.bartlett({k: sub[k] for k in ("NSO", "FOP")}),
    }
    for name, test in tests.items():
        try:
            out[name] = test()
        except ConfigError as exc:  # (too few finished trials for a test: said in the stats, not raised)
            out[name] = {"p": math.nan, "error": str(exc)}
    return out


def elbow_verdicts(s: dict[str, Any], rows: list[dict]) -> list[dict[str, str]]:
    """The elbow paper's three claims (§III, Fig. 6, Table I), judged by its own thresholds, three-valued: E2 is
    untestable when DP's elbow does not drift in A (:data:`MECHANISM_MIN_DP_RANGE_DEG`), E3 when the noise-free
    intended motion's own S is not under :data:`SMOOTHNESS_THRESHOLD`."""
    a_delta = s["A"]["elbow_mobility_deg"]
    b_prox = s["B"]["constraint_proximity_deg"]
    med = lambda block, k: block["spread"][k]["median"]  # noqa: E731
    kw = lambda block: block["kruskal"]["p"]  # noqa: E731
    nso_b = [r["constraint_proximity_deg"] for r in rows if r["scenario"] == "B" and r["strategy"] == "NSO"]
    nso_ok = bool(nso_b) and all(math.isfinite(v) and v >= 10.0 for v in nso_b)
    var = {
        k: float(
            np.nanvar([r["constraint_proximity_deg"] for r in rows if r["scenario"] == "B" and r["strategy"] == k])
        )
        for k in ("DP", "FOP", "NSO")
    }
    bart_dp, bart_fop = b_prox["bartlett_NSO_DP"]["p"], b_prox["bartlett_NSO_FOP"]["p"]
    smooth = {sc: {k: v["median"] for k, v in s[sc]["smoothness_per_segment"]["spread"].items()} for sc in SCENARIOS}
    quiet = {sc: {k: v["median"] for k, v in s[sc]["smoothness_quiet"].items()} for sc in SCENARIOS}
    intended = {sc: s[sc]["intended_smoothness"]["median"] for sc in SCENARIOS}
    e3 = (
        all(smooth[sc][k] < SMOOTHNESS_THRESHOLD for sc in SCENARIOS for k in ("FOP", "NSO"))
        and smooth["A"]["DP"] < SMOOTHNESS_THRESHOLD
        and (smooth["B"]["DP"] > DP_B_SMOOTHNESS_MIN)
    )
    dp_range = med(a_delta, "DP")
    no_drift = (
        f"a mechanism the plant does not produce: DP's elbow moves {dp_range:.1f}° in A (< "
        f"{MECHANISM_MIN_DP_RANGE_DEG:g}°), so B's contrast between DP and NSO cannot arise"
        if not dp_range >= MECHANISM_MIN_DP_RANGE_DEG
        else ""
    )
    unreachable = "; ".join(
        f"the noise-free intended motion of {sc} scores S = {v:.0f} per segment (≥ {SMOOTHNESS_THRESHOLD:g}): no "
        "controller can meet the threshold"
        for sc, v in intended.items()
        if not v < SMOOTHNESS_THRESHOLD
    )
    return [
        three_valued(
            "E1 (scenario A): FOP's elbow mobility Δ (median < 5°) is significantly lower than DP's and NSO's "
            "(median > 20°; Kruskal–Wallis p < 0.001)",
            {"Δ": med(a_delta, "FOP") < 5 and dp_range > 20 and med(a_delta, "NSO") > 20 and kw(a_delta) < 0.001},
            f"Δ medians: DP {dp_range:.1f}°, FOP {med(a_delta, 'FOP'):.1f}°, NSO {med(a_delta, 'NSO'):.1f}°"
            f" (qp {med(a_delta, 'qp'):.1f}°); Kruskal–Wallis p = {kw(a_delta):.3g}",
            [],
            "a threshold or the test's level is missed (see the figures)",
        ),
        three_valued(
            "E2 (scenario B): Δc medians comparable (Kruskal–Wallis p > 0.8), NSO's variance significantly smaller "
            "than DP's and FOP's (Bartlett p < 0.05), every NSO trial keeps Δc ≥ d_sg = 10°",
            {
                "Δc": kw(b_prox) > 0.8
                and bart_dp < 0.05
                and bart_fop < 0.05
                and var["NSO"] < min(var["DP"], var["FOP"])
                and nso_ok
            },
            f"Δc medians: DP {med(b_prox, 'DP'):.1f}°, FOP {med(b_prox, 'FOP'):.1f}°, NSO {med(b_prox, 'NSO'):.1f}° "
            f"(qp {med(b_prox, 'qp'):.1f}°); Kruskal–Wallis p = {kw(b_prox):.3g}; Bartlett p NSO–DP = {bart_dp:.3g}, "
            f"NSO–FOP = {bart_fop:.3g}; variances DP {var['DP']:.3g}, FOP {var['FOP']:.3g}, NSO {var['NSO']:.3g} deg²;"
            f" NSO trials with Δc ≥ 10°: {sum(v >= 10 for v in nso_b)}/{len(nso_b)}",
            [no_drift],
            "a threshold or the test's level is missed (see the figures)",
        ),
        three_valued(
            "E3: S < 500 per segment for every strategy in both scenarios, except DP in scenario B (S > 1100)",
            {"S": e3},
            "S medians per segment, tremor on: "
            + "; ".join(f"{sc}: " + ", ".join(f"{k} {v:.0f}" for k, v in smooth[sc].items()) for sc in SCENARIOS)
            + "; tremor off: "
            + "; ".join(f"{sc}: " + ", ".join(f"{k} {v:.0f}" for k, v in quiet[sc].items()) for sc in SCENARIOS)
            + "; the intended motion alone: "
            + ", ".join(f"{sc} {v:.0f}" for sc, v in intended.items()),
            [unreachable],
            "a threshold is missed (see the figures)",
        ),
    ]


# ------------------------------------------------------------------ tables
def spread_cell(s: dict[str, float], digits: int = 3) -> str:
    """``median (q1–q3)``."""
    return f"{s['median']:.{digits}g} ({s['q1']:.{digits}g}–{s['q3']:.{digits}g})" if s["n"] else "—"


def elbow_report(s: dict[str, Any], header: str) -> str:
    """The Markdown report: Δ, Δc, S per segment by scenario and strategy (the layout of [E] Table I), tests,
    verdicts."""
    lines = [header, ""]
    for sc in SCENARIOS:
        b = s[sc]
        lines += [
            f"Scenario {sc}:",
            "",
            "| strategy | Δ (deg) | Δc (deg) | S per segment | S per segment, tremor off | stopped trials |",
            "|---|---|---|---|---|---|",
        ]
        for k in ELBOW_STRATEGIES:
            lines.append(
                f"| {k} | {spread_cell(b['elbow_mobility_deg']['spread'][k])} | "
                f"{spread_cell(b['constraint_proximity_deg']['spread'][k])} | "
                f"{spread_cell(b['smoothness_per_segment']['spread'][k])} | "
                f"{spread_cell(b['smoothness_quiet'][k])} | {s['stopped'][sc][k]} |"
            )
        lines.append(f"\nThe intended motion alone: S per segment {spread_cell(b['intended_smoothness'])}.")
        for key, title in (
            ("elbow_mobility_deg", "Δ"),
            ("constraint_proximity_deg", "Δc"),
            ("smoothness_per_segment", "S"),
        ):
            block = b[key]
            lines.append(
                f"\n{title} over DP, FOP, NSO: Kruskal–Wallis p = {block['kruskal']['p']:.3g}; Bartlett p = "
                f"{block['bartlett']['p']:.3g} (NSO–DP {block['bartlett_NSO_DP']['p']:.3g}, NSO–FOP "
                f"{block['bartlett_NSO_FOP']['p']:.3g})"
            )
        lines.append("")
    return "\n".join(lines + [verdict_lines(s["verdicts"])]) + "\n"


def verdict_lines(verdicts: list[dict[str, str]]) -> str:
    """The verdicts as a Markdown list."""
    out = ["Verdicts:", ""]
    for v in verdicts:
        why = f" Why: {v['why']}." if "why" in v else ""
        out.append(f"- **{v['verdict']}**: {v['claim']}. Measured: {v['measured']}.{why}")
    return "\n".join(out)


# ------------------------------------------------------------------ figures
def box_figure(panels: list[tuple[str, dict[str, np.ndarray]]], title: str) -> bytes:
    """Box plots (median, quartiles, whiskers at 1.5 IQR) of each panel's groups, side by side (PNG bytes)."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.8), squeeze=False)
    for ax, (label, g) in zip(axes[0], panels):
        names = list(g)
        ax.boxplot([v[np.isfinite(v)] for v in g.values()], tick_labels=names)
        ax.set_title(label, fontsize=9)
        ax.tick_params(axis="x", labelrotation=30)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()
