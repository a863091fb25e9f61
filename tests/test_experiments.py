"""Virtual surgeons, the papers' statistics and both experiments end to end at tiny sizes (issue 14)."""

from __future__ import annotations

import csv
import itertools
import json

import numpy as np
import pinocchio as pin
import pytest
from scipy import stats

from qpnso.cli import main
from qpnso.control.trajectory import lemniscate
from qpnso.lab.experiments import run_experiment
from qpnso.lab.experiments import statistics as st
from qpnso.lab.experiments.analysis import normalise_per_subject
from qpnso.lab.experiments.mass_friction import PAPER_STRATEGIES as PAPER
from qpnso.lab.surgeon import (
    SUBJECT_RANGES,
    Subject,
    dome_targets,
    guidance_motion,
    moving_segments,
    point_to_point_motion,
    power_law_curve,
)


# ------------------------------------------------------------------ surgeons
def test_subject_wrench_is_the_arm_impedance() -> None:
    s = Subject(stiffness=150.0, damping=12.0, rotational_stiffness=3.0, rotational_damping=0.1)
    rot = pin.rpy.rpyToMatrix(0.1, -0.2, 0.3)
    turn = pin.exp3(np.array([0.05, -0.02, 0.01]))
    intended = (np.array([0.5, 0.0, 0.4]), turn @ rot, np.array([0.1, 0.0, 0.0]), np.array([0.0, 0.2, 0.0]))
    tool = (np.array([0.49, 0.01, 0.4]), rot, np.array([0.05, 0.0, 0.01]), np.zeros(3))
    w = s.wrench(intended, tool)
    assert np.allclose(w[:3], 150.0 * (intended[0] - tool[0]) + 12.0 * (intended[2] - tool[2]))
    assert np.allclose(w[3:], 3.0 * np.array([0.05, -0.02, 0.01]) + 0.1 * intended[3])
    free = s.wrench(intended, tool, free_axis=True)
    assert abs(free[3:] @ rot[:, 2]) < 1e-12 and np.allclose(free[:3], w[:3])  # no moment about the tool axis


def test_subjects_are_drawn_in_the_stated_ranges() -> None:
    rng = np.random.default_rng(0)
    for _ in range(50):
        s = Subject.draw(rng)
        for key, (lo, hi) in SUBJECT_RANGES.items():
            assert lo <= getattr(s, key) <= hi


def test_power_law_timing_is_slower_in_the_curves() -> None:
    """Under the re-timed parameter the speed is proportional to R^{1/3} where R < the half width."""
    a = 0.04
    curve = power_law_curve(lambda s: np.column_stack([lemniscate(s, a), np.zeros(len(np.atleast_1d(s)))]), a)
    tau = np.linspace(0.01, 0.99, 20001)
    p = curve(tau)
    d1, d2 = np.gradient(p, tau, axis=0), np.gradient(np.gradient(p, tau, axis=0), tau, axis=0)
    speed = np.linalg.norm(d1, axis=1)
    radius = speed**3 / np.linalg.norm(np.cross(d1, d2), axis=1)
    curved = radius < 0.8 * a
    ratio = speed[curved] / radius[curved] ** (1 / 3)
    assert np.std(ratio) < 0.03 * np.mean(ratio)
    assert speed[np.argmin(radius)] < 0.8 * speed.max()


def test_guidance_and_point_to_point_motions() -> None:
    pose = pin.SE3(pin.rpy.rpyToMatrix(np.pi, 0.5, np.pi), np.array([0.65, 0.0, 0.5]))
    g = guidance_motion(pose, 0.08, 0.05)
    assert len(g.segments) == 4 and not g.free_tool_axis
    _, _, v, _ = g.trajectory.samples(np.array([b for _, b in g.segments]))
    assert np.abs(v).max() < 1e-3  # every segment ends at rest
    targets = dome_targets(pose.translation, 0.05, 6)
    assert np.allclose(np.linalg.norm(targets - pose.translation, axis=1), 0.05)
    m = point_to_point_motion(pose, targets, 0.1)
    assert len(m.segments) == 6 and m.free_tool_axis
    ends = m.trajectory.samples(np.array([b for _, b in m.segments]))[0]
    assert np.allclose(ends, targets, atol=1e-6)
    assert moving_segments(m.trajectory) == m.segments


# ------------------------------------------------------------------ statistics
def dunn_by_hand(groups: list[np.ndarray]) -> np.ndarray:
    """Dunn (1964) with the tie correction and Šidák's adjustment, from ranks: the independent reference."""
    pooled = np.concatenate(groups)
    ranks = stats.rankdata(pooled)
    n = len(pooled)
    _, counts = np.unique(pooled, return_counts=True)
    ties = np.sum(counts**3 - counts) / (12.0 * (n - 1))
    mean_rank, start = [], 0
    for g in groups:
        mean_rank.append(ranks[start : start + len(g)].mean())
        start += len(g)
    k = len(groups)
    m = k * (k - 1) / 2
    p = np.ones((k, k))
    for i, j in itertools.combinations(range(k), 2):
        sigma = np.sqrt((n * (n + 1) / 12.0 - ties) * (1 / len(groups[i]) + 1 / len(groups[j])))
        z = abs(mean_rank[i] - mean_rank[j]) / sigma
        p[i, j] = p[j, i] = 1 - (1 - 2 * stats.norm.sf(z)) ** m
    return p


def test_dunn_sidak_matches_the_rank_formula() -> None:
    rng = np.random.default_rng(4)
    groups = [np.round(rng.normal(mu, 1.0, n), 1) for mu, n in ((0, 12), (0.6, 15), (1.5, 10), (0.2, 12))]
    got = st.dunn_sidak({f"g{i}": g for i, g in enumerate(groups)})
    table = np.array([[got[f"g{i}"][f"g{j}"] for j in range(4)] for i in range(4)])
    assert np.allclose(table, dunn_by_hand(groups), rtol=1e-9, atol=1e-12)
    text = st.significance_table(got)
    assert text.splitlines()[2].startswith("| g0 | X |") and "1" in text  # g0 vs g2 differ at 0.01


def test_kruskal_bartlett_normality_and_spread() -> None:
    rng = np.random.default_rng(5)
    g = {"a": rng.normal(0, 1, 30), "b": rng.normal(3, 1, 30), "c": rng.normal(0, 3, 30)}
    assert st.kruskal(g)["p"] == pytest.approx(stats.kruskal(*g.values()).pvalue)
    assert st.kruskal(g)["p"] < 1e-6 and st.bartlett(g)["p"] < 1e-6
    assert all(p > 0.01 for p in st.normality(g).values())
    assert st.spread([1, 2, 3, 4, np.nan]) == {"median": 2.5, "q1": 1.75, "q3": 3.25, "n": 4}


def test_work_is_normalised_per_subject_by_the_highest_strategy_mean() -> None:
    """[M 24]: per subject, divide by the largest per-strategy mean."""
    rows = [
        {"subject": 0, "strategy": "a", "w": 2.0},
        {"subject": 0, "strategy": "a", "w": 4.0},
        {"subject": 0, "strategy": "b", "w": 1.0},
        {"subject": 1, "strategy": "a", "w": 10.0},
        {"subject": 1, "strategy": "b", "w": 20.0},
        {"subject": 1, "strategy": "b", "w": float("nan")},
    ]
    normalise_per_subject(rows, "w", "n")
    assert [r["n"] for r in rows[:5]] == [2 / 3, 4 / 3, 1 / 3, 0.5, 1.0] and np.isnan(rows[5]["n"])


# ------------------------------------------------------------------ the experiments, tiny
def test_mass_friction_experiment_end_to_end(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("QPNSO_COMPILE", "off")  # (qp-zero's weights are new C code: no background compile in the suite)
    out = tmp_path / "mf"
    size = {"subjects": 1, "orders": 1, "reps": 1, "moves": 2, "dwell": 0.2, "peak_speed": 0.15}
    stats_ = run_experiment("mass-friction", out, size, workers=1)
    with open(out / "trials.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 8
    for key in ("subject", "area", "strategy", "order", "rep", "work_per_metre", "work_per_nominal_metre"):
        assert key in rows[0]
    assert {r["strategy"] for r in rows} == {
        "damped", "elbow-up", "fixed", "active", "qp", "qp-zero", "damped-again", "damped-light"
    }  # fmt: skip
    assert max(float(r["work_measured"]) for r in rows if r["strategy"] in PAPER) == pytest.approx(1.0)
    assert all(r["error"] == "" for r in rows)
    saved = json.loads((out / "stats.json").read_text())
    assert saved["work_measured"]["kruskal"]["p"] == pytest.approx(stats_["work_measured"]["kruskal"]["p"])
    assert [v["claim"][:2] for v in saved["verdicts"]] == ["M1", "M2", "M3", "Q1", "Q2"]
    assert all(
        v["verdict"] in ("reproduced", "not reproduced", "untestable", "holds", "fails") for v in saved["verdicts"]
    )
    assert saved["controls"]["felt_mass_ratio"] == pytest.approx(0.7, abs=0.05)
    report = (out / "report.md").read_text()
    assert "| damped | X |" in report and "Verdicts:" in report and "Controls (felt mass" in report
    # resumable: a rerun reads the checkpoint
    again = run_experiment("mass-friction", out, size, workers=1)
    assert again["work_measured"]["spread"] == stats_["work_measured"]["spread"]


def test_elbow_experiment_from_the_command_line(tmp_path, capsys) -> None:
    out = tmp_path / "el"
    argv = ["experiment", "elbow", "--subjects", "1", "--trials", "1", "--duration-scale", "0.025", "--workers", "1"]
    assert main([*argv, "--out", str(out), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "Scenario A:" in text and "Scenario B:" in text and "E1 (scenario A)" in text
    with open(out / "trials.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 16 and {r["scenario"] for r in rows} == {"A", "B"}  # (a trial and a quiet trial each)
    assert {r["tremor"] for r in rows} == {"on", "off"}
    assert {r["strategy"] for r in rows} == {"DP", "FOP", "NSO", "qp"}
    assert main(["experiment", "elbow", "--orders", "2", "--out", str(tmp_path / "x")]) == 2
    assert "--orders does not apply to experiment elbow" in capsys.readouterr().err


@pytest.mark.parametrize(
    "name, options, message",
    [
        ("mass-friction", {"subjects": 0}, "subjects must be >= 1"),
        ("mass-friction", {"moves": 1}, r"moves must be in \[2, 12\]"),
        ("mass-friction", {"armature_kgm2": -1.0}, "armature_kgm2 must be a finite rotor inertia >= 0"),
        ("elbow", {"trials": 0}, "subjects and trials must be >= 1"),
        ("elbow", {"duration_scale": 0.0}, r"duration_scale must be in \(0, 1\]"),
        ("walking", {}, "unknown experiment 'walking'"),
    ],
)
def test_bad_experiment_options_are_named(tmp_path, name, options, message) -> None:
    from qpnso.errors import ConfigError

    with pytest.raises(ConfigError, match=message):
        run_experiment(name, tmp_path / "x", options, workers=1)
    assert not (tmp_path / "x").exists()  # (refused before any job ran)
