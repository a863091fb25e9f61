"""The mass/friction experiment's analysis: its metrics under both readings of [M 24], the controls, and a
three-valued verdict on each claim (issue 32; ../shared/docs/EVIDENCE.md).

* **Readings.**  [M 24] divides a trial's hand work by its path length; the path is either the one the tool
  took (``measured``: rewards a wandering tool) or the one the surgeon intended (``nominal``).  A verdict is
  taken under every reading that passes its controls (pre-registration version 2: :func:`valid_readings`;
  version 1 made a claim untestable when the readings disagreed); with none left, the claim is ``untestable``.
* **Controls**, on the trials of the first ``control_reps`` repetitions: the negative control compares
  ``damped`` with ``damped-again`` (the same strategy, other noise draws: the test must not call it
  significant); the positive control compares ``damped`` with ``damped-light`` (felt mass −30 %: the metric
  must fall and the test must detect it at 0.01).  A reading whose controls fail is set aside (version 2); a
  metric with no reading left cannot support a verdict: its claims are ``untestable``, with the control that
  failed.
* **Premise.**  A claim about the fixed posture needs a fixed posture that differs from elbow up
  (:attr:`.work_areas.Postures.discriminates`, in every work area at the run's rotor inertia); else it is
  ``untestable`` (the design compares a posture with itself).
* **Guard** (qpnso's, not the paper's): ``qp``'s median tool path and hand work at most 1.2× damped's, and
  no stopped trial.

Statistics: Kruskal–Wallis and Dunn–Šidák at the paper's 0.01 (:mod:`.statistics`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from qpnso.lab.experiments import statistics as st
from qpnso.lab.experiments.analysis import (
    compare,
    groups,
    normalise_per_subject,
    spread_cell,
    stopped,
    three_valued,
    verdict_lines,
)
from qpnso.lab.experiments.mass_friction import CONTROLS, PAPER_STRATEGIES, STRATEGIES

ALPHA = 0.01
"""The paper's significance level (its Table I)."""
READINGS = {"measured": "work_per_metre", "nominal": "work_per_nominal_metre"}
"""[M 24]'s two readings: the trial's hand work over the measured or over the intended path length."""
GUARD_RATIO = 1.2
"""qp's median tool path and hand work may be at most this times damped's (issue 32)."""
METRICS = {
    **{f"work_{r}": f"normalised work per metre ({r} path)" for r in READINGS},
    "orthogonal_torque": "normalised orthogonal moment",
}


def present(rows: list[dict], names) -> tuple[str, ...]:
    """The names of ``names`` that have at least one row."""
    have = {r["strategy"] for r in rows}
    return tuple(n for n in names if n in have)


def normalise(rows: list[dict]) -> None:
    """[M 24]'s per-subject normalisation of each reading's work and of the orthogonal moment, with the paper's
    strategies (those present) as the reference: ``work_<reading>`` and ``orthogonal_torque`` columns."""
    reference = present(rows, PAPER_STRATEGIES) or present(rows, STRATEGIES)
    for reading, key in READINGS.items():
        normalise_per_subject(rows, key, f"work_{reading}", reference)
    normalise_per_subject(rows, "orthogonal_torque_mean_Nm", "orthogonal_torque", reference)


def control_stats(rows: list[dict], control_reps: int) -> dict[str, Any]:
    """Per metric: the controls' test (Kruskal–Wallis, Dunn–Šidák over damped, damped-again, damped-light on the
    first ``control_reps`` repetitions) and whether each control passed; empty when the controls did not run."""
    names = ("damped", *present(rows, CONTROLS))
    if len(names) < 3:
        return {}
    matched = [r for r in rows if r["rep"] < control_reps]
    out: dict[str, Any] = {}
    for metric in METRICS:
        g = groups(matched, metric, names)
        block: dict[str, Any] = {"spread": {k: st.spread(v) for k, v in g.items()}}
        p = st.dunn_sidak(g)
        med = {k: v["median"] for k, v in block["spread"].items()}
        block["dunn_sidak_p"] = p
        block["negative_ok"] = bool(p["damped"]["damped-again"] >= ALPHA)
        block["positive_ok"] = bool(p["damped"]["damped-light"] < ALPHA and med["damped-light"] < med["damped"])
        out[metric] = block
    light, base = groups(matched, "mass_mean_kg", ("damped-light", "damped")).values()
    out["felt_mass_ratio"] = float(np.nanmedian(light) / np.nanmedian(base)) if light.size and base.size else math.nan
    return out


def guard(rows: list[dict]) -> dict[str, Any]:
    """qp against damped: the ratios of their median tool path and hand work, the stopped trials of each, and
    whether the guard holds (:data:`GUARD_RATIO`, no stopped trial)."""
    if "qp" not in present(rows, STRATEGIES):
        return {}
    med = {
        (g, key): float(np.nanmedian(v)) if (v := groups(rows, key, (g,))[g]).size else math.nan
        for g in ("qp", "damped")
        for key in ("path_length_m", "hand_work_J")
    }
    path = med[("qp", "path_length_m")] / med[("damped", "path_length_m")]
    work = med[("qp", "hand_work_J")] / med[("damped", "hand_work_J")]
    halted = stopped(rows, ("qp", "damped"))
    ok = path <= GUARD_RATIO and work <= GUARD_RATIO and not any(halted.values())
    return {"path_ratio": path, "work_ratio": work, "stopped": halted, "holds": bool(ok)}


def mass_friction_stats(rows: list[dict], areas: list[dict[str, Any]], control_reps: int) -> dict[str, Any]:
    """Statistics, controls, guard and verdicts of the mass/friction experiment; ``areas``: the work areas'
    premise at the run's rotor inertia (:func:`~.mass_friction.work_area_summary`)."""
    normalise(rows)
    strategies = present(rows, STRATEGIES)
    paper = present(rows, PAPER_STRATEGIES)
    out: dict[str, Any] = {
        "trials": len(rows),
        "stopped": stopped(rows, strategies + CONTROLS),
        "work_areas": areas,
        "premise_holds": bool(areas) and all(a.get("discriminates") for a in areas),
        "controls": control_stats(rows, control_reps),
        "guard": guard(rows),
    }
    for metric in METRICS:
        out[metric] = compare(groups(rows, metric, paper)) if len(paper) >= 2 else {}
        out[metric + "_all"] = compare(groups(rows, metric, strategies)) if len(strategies) >= 2 else {}
    for key in ("mass_mean_kg", "mass_model_mean_kg", "friction_force_mean_N", "path_length_m", "hand_work_J"):
        out[key] = {k: st.spread(v) for k, v in groups(rows, key, strategies + CONTROLS).items()}
    out["verdicts"] = mass_friction_verdicts(out) if set(PAPER_STRATEGIES) <= set(paper) else []
    return out


# ------------------------------------------------------------------ verdicts
def lower_and_significant(s: dict[str, Any], low: tuple[str, ...], high: tuple[str, ...]) -> bool:
    """Kruskal–Wallis below :data:`ALPHA`, and every pair ``low`` × ``high`` lower and Dunn–Šidák significant."""
    med = {k: v["median"] for k, v in s["spread"].items()}
    p = s["dunn_sidak_p"]
    return s["kruskal"]["p"] < ALPHA and all(p[a][b] < ALPHA and med[a] < med[b] for a in low for b in high)


def controls_failed(s: dict[str, Any], metric: str) -> str:
    """Why ``metric``'s controls cannot support a verdict ('' when they pass)."""
    c = s["controls"].get(metric)
    if not c:
        return "the controls did not run"
    if not c["positive_ok"]:
        p = c["dunn_sidak_p"]["damped"]["damped-light"]
        return (
            f"the positive control failed: a {100 * (1 - s['controls']['felt_mass_ratio']):.0f} % lighter robot "
            f"was not detected (Dunn–Šidák p = {p:.3g})"
        )
    if not c["negative_ok"]:
        p = c["dunn_sidak_p"]["damped"]["damped-again"]
        return f"the negative control failed: damped against itself is significant (p = {p:.3g})"
    return ""


def _medians(block: dict[str, Any]) -> str:
    return ", ".join(f"{k} {v['median']:.3f}" for k, v in block["spread"].items())


def valid_readings(s: dict[str, Any], judged: dict[str, bool]) -> tuple[dict[str, bool], list[str], str]:
    """``(kept, blockers, set_aside)``: the readings of ``judged`` whose work metric passed its controls (a reading
    that fails them cannot say anything and is set aside, pre-registration v2); when none passed, all of them with
    each failure as a blocker (the claim is untestable)."""
    failed = {r: why for r in judged if (why := controls_failed(s, f"work_{r}"))}
    kept = {r: v for r, v in judged.items() if r not in failed}
    if not kept:
        return judged, [f"{r} reading: {why}" for r, why in failed.items()], ""
    return kept, [], "; ".join(f"the {r} reading set aside ({why})" for r, why in failed.items())


def _with(measured: str, set_aside: str) -> str:
    return f"{measured}; {set_aside}" if set_aside else measured


def mass_friction_verdicts(s: dict[str, Any]) -> list[dict[str, str]]:
    """The paper's three claims (its Table I, Fig. 10) under the readings whose controls passed
    (:func:`valid_readings`), with the premise, then qpnso's claim and guard."""
    works = {r: s[f"work_{r}"] for r in READINGS}
    premise = "" if s["premise_holds"] else "the fixed posture does not differ enough from elbow up in every area"
    measured = "; ".join(f"{r}: {_medians(w)}, Kruskal–Wallis p = {w['kruskal']['p']:.3g}" for r, w in works.items())
    m1, b1, aside = valid_readings(
        s, {r: lower_and_significant(w, ("fixed", "active"), ("damped", "elbow-up")) for r, w in works.items()}
    )
    m3, b3, _ = valid_readings(s, {r: bool(w["dunn_sidak_p"]["fixed"]["active"] >= ALPHA) for r, w in works.items()})
    torque = s["orthogonal_torque"]
    verdicts = [
        three_valued(
            "M1: fixed and active need significantly less work than damped and elbow-up (Kruskal–Wallis p < 0.01, "
            "Dunn–Šidák at 0.01)",
            m1,
            _with(measured, aside),
            [premise, *b1],
        ),
        three_valued(
            "M2: the moment orthogonal to the motion is significantly higher with damped and elbow-up than with fixed "
            "and active",
            {"moment": lower_and_significant(torque, ("fixed", "active"), ("damped", "elbow-up"))},
            f"{_medians(torque)}; Kruskal–Wallis p = {torque['kruskal']['p']:.3g}",
            [premise, controls_failed(s, "orthogonal_torque")],
        ),
        three_valued(
            "M3: the fixed pre-optimised posture performs nearly as well as active optimisation (no significant "
            "difference in work)",
            m3,
            _with(
                "; ".join(
                    f"{r}: Dunn–Šidák p(fixed, active) = {w['dunn_sidak_p']['fixed']['active']:.3g}"
                    for r, w in works.items()
                ),
                aside,
            ),
            [premise, *b3],
        ),
    ]
    return verdicts + qpnso_verdicts(s)


def qpnso_verdicts(s: dict[str, Any]) -> list[dict[str, str]]:
    """qpnso's own claim (qp needs less work than damped) under the readings whose controls passed, and the
    guard."""
    if "qp" not in s["work_measured_all"].get("spread", {}):
        return []
    works = {r: s[f"work_{r}_all"] for r in READINGS}
    q1, blockers, aside = valid_readings(
        s, {r: lower_and_significant(w, ("qp",), ("damped",)) for r, w in works.items()}
    )
    out = [
        three_valued(
            "Q1 (qpnso): qp needs significantly less work than damped",
            q1,
            _with(
                "; ".join(
                    f"{r}: qp {w['spread']['qp']['median']:.3f}, damped {w['spread']['damped']['median']:.3f}, "
                    f"Dunn–Šidák p = {w['dunn_sidak_p']['qp']['damped']:.3g}"
                    for r, w in works.items()
                ),
                aside,
            ),
            blockers,
        )
    ]
    g = s["guard"]
    if g:
        out.append(
            {
                "claim": f"Q2 (qpnso's guard): qp's median tool path and hand work at most {GUARD_RATIO}× damped's, no "
                "stopped trial",
                "verdict": "holds" if g["holds"] else "fails",
                "measured": f"path {g['path_ratio']:.2f}×, work {g['work_ratio']:.2f}×, stopped {g['stopped']}",
            }
        )
    return out


# ------------------------------------------------------------------ report
def mass_friction_report(s: dict[str, Any], header: str) -> str:
    """The Markdown report: the work areas' premise, the spreads, the controls, the Table I layout under each
    reading, the p-values, the guard and the verdicts."""
    lines = [header, "", *(area_line(a) for a in s["work_areas"]), ""]
    lines += strategy_table(s)
    lines += control_lines(s)
    for metric, title in METRICS.items():
        block = s[metric]
        if not block:
            continue
        lines += [
            "",
            f"Dunn–Šidák on the {title} (1: significant at 0.01; the layout of [M] Table I); Kruskal–Wallis "
            f"H = {block['kruskal']['H']:.3g}, p = {block['kruskal']['p']:.3g}; Kolmogorov–Smirnov normality p: "
            + ", ".join(f"{k} {v:.2g}" for k, v in block["normality_ks_p"].items()),
            "",
            st.significance_table(block["dunn_sidak_p"]),
            "",
            "Šidák-corrected p-values, every strategy:",
            "",
            st.pvalue_table(s[metric + "_all"]["dunn_sidak_p"]),
        ]
    return "\n".join(lines + ["", verdict_lines(s["verdicts"])]) + "\n"


def strategy_table(s: dict[str, Any]) -> list[str]:
    """One row per strategy and control: each metric's spread, felt mass and friction, path, hand work."""
    lines = [
        "| group | work/m (measured) | work/m (nominal) | orthogonal moment | felt mass, plant (kg) | "
        "felt friction, plant (N) | tool path (m) | hand work (J) | stopped |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for k in s["mass_mean_kg"]:
        cells = [
            spread_cell(s[m + "_all"]["spread"][k]) if k in s[m + "_all"].get("spread", {}) else "—" for m in METRICS
        ]
        cells += [
            spread_cell(s[key][k]) for key in ("mass_mean_kg", "friction_force_mean_N", "path_length_m", "hand_work_J")
        ]
        lines.append(f"| {k} | " + " | ".join(cells) + f" | {s['stopped'].get(k, 0)} |")
    return lines


def control_lines(s: dict[str, Any]) -> list[str]:
    """The controls' outcome per metric (Dunn–Šidák p against damped, on matched repetitions)."""
    c = s["controls"]
    if not c:
        return ["", "Controls: not run."]
    out = ["", f"Controls (felt mass of damped-light / damped, plant: {c['felt_mass_ratio']:.2f}):", ""]
    for metric, title in METRICS.items():
        b = c[metric]
        p = b["dunn_sidak_p"]["damped"]
        out.append(
            f"- {title}: negative (damped-again) p = {p['damped-again']:.3g} "
            f"{'passed' if b['negative_ok'] else 'FAILED'}; positive (damped-light) p = {p['damped-light']:.3g}, "
            f"median {b['spread']['damped-light']['median']:.3f} against {b['spread']['damped']['median']:.3f} "
            f"{'passed' if b['positive_ok'] else 'FAILED'}"
        )
    return out


def area_line(a: dict[str, Any]) -> str:
    """What the postures feel in one work area (the experiment's premise), one line."""
    return (
        f"Work area at {a['center_m']} m, tilt {a['pitch_deg']:g}°: the fixed posture is at arm angle "
        f"{a['fixed_arm_angle_deg']:.1f}° (elbow up: 0°); felt mass {a['mass_fixed_kg']:.2f} kg there against "
        f"{a['mass_elbow_up_kg']:.2f} kg elbow up, friction force {a['friction_fixed_N']:.1f} N against "
        f"{a['friction_elbow_up_N']:.1f} N (premise {'holds' if a['discriminates'] else 'FAILS'}; "
        f"{'pre-registered' if a['preregistered'] else 'not in the pre-registration'}); fixed and elbow-up held by "
        f"{a['posture_stiffness_Nm_per_rad']:g} N·m/rad with {a['nullspace_damping_Nms_per_rad']:.3g} N·m·s/rad."
    )
