"""Studies and their parallel runner: measures, extremum search, determinism, resume, failure, Dask."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from qpnso.errors import ConfigError
from qpnso.lab import studies
from qpnso.lab.parallel import CHECKPOINT, JobError, RunSpec, job_rng, run_jobs
from qpnso.lab.studies import (
    SelfMotionCurve,
    StudyOptions,
    arm_angle_grid,
    descend,
    friction_objective,
    mass_objective,
    run_study,
    sample_start,
    weighted_objective,
    workbench,
)
from qpnso.model.costs import CostModel, CostWeights


@pytest.fixture(scope="module")
def bench():
    return workbench("lwr4p", "off")


def _starts(bench, n, seed=3):
    rng = np.random.default_rng(seed)
    return [sample_start(bench.robot, rng, 1e-4)[0] for _ in range(n)]


# ------------------------------------------------------------- measures
def test_measures_match_cost_model(bench):
    qs = np.array(_starts(bench, 4))
    m = bench.measures(qs)
    tau = bench.tau_max()
    weighted = CostModel(bench.robot, CostWeights(mass=0.9, friction_force=0.1), compile="off")
    assert weighted.scales == bench.cost.scales
    for k, q in enumerate(qs):
        terms = bench.cost.terms(q)
        assert m.mass_cost[k] == pytest.approx(terms["mass"], rel=1e-10)
        assert m.friction_cost(tau)[k] == pytest.approx(terms["friction_force"], rel=1e-10)
        assert m.principal_mass()[k] == pytest.approx(bench.cost.principal_mass(q), rel=1e-10)
        assert m.friction_force(tau)[k] == pytest.approx(bench.cost.friction_force_magnitude(q), rel=1e-10)
        assert weighted_objective(0.9, bench.cost.scales, tau)(m)[k] == pytest.approx(weighted.value(q), rel=1e-10)
        one = bench.measures(q[None, :])  # single-point path agrees with the batched one
        np.testing.assert_allclose(one.gram[0], m.gram[k], rtol=1e-12, atol=1e-12)


def test_friction_gram_is_quadratic_in_tau_max(bench):
    """c_f for scaled sliding torques equals a cost model built with those torques."""
    from qpnso.model.robot import Robot, friction_from_lists

    q = _starts(bench, 1, seed=5)[0]
    tau = np.array([1.2, 1.5, 1.7, 1.1, 1.5, 1.9, 1.4])
    r = bench.robot
    other = Robot(r.name, r.model, r.tool_frame_id, friction_from_lists(tau, r.friction.beta, r.nq))
    expected = CostModel(other, normalize=False, compile="off").terms(q)["friction_force"]
    assert bench.measures(q[None, :]).friction_cost(tau)[0] == pytest.approx(expected, rel=1e-10)


# ------------------------------------------------------- extremum search
def test_descend_follows_the_slope_and_stops_at_ends():
    v = np.array([5.0, 4.0, 3.0, 3.5, 2.0, 1.0, 0.5])
    assert descend(v, 1, cyclic=False) == 2  # first local minimum downhill, not the global one
    assert descend(v, 4, cyclic=False) == 6  # runs into the end
    assert descend(v, 3, cyclic=False) == 6  # steeper side first
    assert descend(np.array([1.0, 3.0, 2.0, 4.0]), 3, cyclic=True) == 0  # wraps around
    assert descend(np.array([2.0, 1.0, 2.0]), 1, cyclic=False) == 1
    assert descend(v, 3, cyclic=False, direction=-1) == 2  # the given direction wins over the grid
    assert descend(v, 2, cyclic=False, direction=1) == 2  # uphill at once: stays


def test_grid_holds_start_and_ends(bench):
    from qpnso.elbow.intervals import Interval

    grid, i0, cyclic = arm_angle_grid(0.3, Interval(-1.0, 2.0, False), math.radians(1.0))
    assert not cyclic and grid[0] == -1.0 and grid[-1] == 2.0 and grid[i0] == 0.3
    assert np.all(np.diff(grid) > 0) and np.diff(grid).max() <= math.radians(1.0) + 1e-12
    grid, i0, cyclic = arm_angle_grid(0.3, Interval(0.3 - math.pi, 0.3 + math.pi, True), math.radians(1.0))
    assert cyclic and grid[i0] == 0.3 and grid[-1] < 0.3 + 2 * math.pi


def _dense_extremum(curve, objective, sense, step_deg=0.01):
    """Brute force: walk the same rule on a 0.01° grid."""
    grid, i0, cyclic = arm_angle_grid(curve.ns0, curve.interval, math.radians(step_deg))
    sign = 1.0 if sense == "min" else -1.0
    values = sign * objective(curve.measure(grid))
    # first step along the local slope at the start (a 1e-7 rad central difference), as a gradient flow
    lo_hi = sign * objective(curve.measure(np.array([curve.ns0 - 1e-7, curve.ns0 + 1e-7])))
    i = descend(values, i0, cyclic, 1 if lo_hi[1] < lo_hi[0] else -1)
    # then 2001 samples across the neighbouring cells: a sharp peak (the rotors' inertia makes the friction
    # measure's kinks narrower) is resolved to 1e-5 of a degree
    step = math.radians(step_deg)
    local = np.clip(np.linspace(grid[i] - step, grid[i] + step, 2001), curve.interval.lo, curve.interval.hi)
    local_values = sign * objective(curve.measure(local))
    k = int(np.argmin(local_values))
    if local_values[k] < values[i]:
        return local[k], sign * local_values[k]
    return grid[i], sign * values[i]


@pytest.mark.parametrize("seed", [11, 12])
def test_extremum_matches_dense_sampling(bench, seed):
    q0 = _starts(bench, 1, seed=seed)[0]
    curve = SelfMotionCurve(bench, q0, math.radians(1.0))
    for objective in (mass_objective, friction_objective(bench.tau_max())):
        for sense in ("min", "max"):
            ext = curve.extremum(objective, sense)
            ns_dense, v_dense = _dense_extremum(curve, objective, sense)
            assert abs(ext.ns - ns_dense) < math.radians(0.02), (sense, ext.ns, ns_dense)
            better = ext.value <= v_dense if sense == "min" else ext.value >= v_dense
            assert better or math.isclose(ext.value, v_dense, rel_tol=1e-9)
            # the friction measure has sharp minima (atan kinks): one dense step costs up to ~1e-5
            assert math.isclose(ext.value, v_dense, rel_tol=1e-4, abs_tol=1e-12)
            if not ext.at_end:  # refined to a true local extremum: no better value 1e-6 rad away
                sign = 1.0 if sense == "min" else -1.0
                near = sign * objective(curve.measure(ext.ns + np.array([-1e-6, 1e-6])))
                assert np.all(near >= sign * ext.value - 1e-12 * abs(ext.value))
            assert curve.interval.lo - 1e-12 <= ext.ns <= curve.interval.hi + 1e-12
            bench.robot.check_q(ext.q, tol=1e-9)  # the optimum respects the joint limits
            np.testing.assert_allclose(
                bench.robot.tool_pose(ext.q).homogeneous, bench.robot.tool_pose(q0).homogeneous, atol=1e-9
            )  # tool held


# ---------------------------------------------------------------- runner
def _square(index: int, seed: int) -> dict:
    return {"index": index, "x": float(job_rng(seed, index).standard_normal())}


def _fail_on_two(index: int, seed: int) -> dict:
    if index == 2:
        raise ValueError("boom at two")
    return _square(index, seed)


CALLS: list[int] = []


def _counting(index: int, seed: int) -> dict:
    CALLS.append(index)
    return _square(index, seed)


def test_runner_resumes_without_redoing_finished_jobs(tmp_path):
    spec = RunSpec("toy", 6, 7, {"a": 1})
    full = run_jobs(spec, _square, tmp_path / "full", workers=2)
    out = tmp_path / "part"
    run_jobs(RunSpec("toy", 6, 7, {"a": 1}), _square, out, workers=1)
    lines = (out / CHECKPOINT).read_text().splitlines(keepends=True)
    # keep the header and jobs 0, 1; then a torn line as if killed mid-write
    (out / CHECKPOINT).write_text("".join(lines[:3]) + lines[3][:10])
    CALLS.clear()
    resumed = run_jobs(spec, _counting, out, workers=1)
    assert sorted(CALLS) == [i for i in range(6) if i not in (lines_index(lines[1]), lines_index(lines[2]))]
    assert resumed == full
    CALLS.clear()
    assert run_jobs(spec, _counting, out, workers=1) == full and CALLS == []  # nothing left to do


def lines_index(line: str) -> int:
    return json.loads(line)["index"]


def test_runner_refuses_other_run_in_same_folder(tmp_path):
    run_jobs(RunSpec("toy", 3, 1), _square, tmp_path, workers=1)
    for other in (RunSpec("toy", 3, 2), RunSpec("toy", 4, 1), RunSpec("other", 3, 1), RunSpec("toy", 3, 1, {"b": 2})):
        with pytest.raises(ConfigError, match="different run"):
            run_jobs(other, _square, tmp_path, workers=1)


@pytest.mark.parametrize("workers", [1, 2])
def test_runner_fails_cleanly_with_job_index(tmp_path, workers):
    with pytest.raises(JobError, match=r"job 2 failed: ValueError: boom at two"):
        run_jobs(RunSpec("toy", 5, 0), _fail_on_two, tmp_path, workers=workers)
    done = [json.loads(x)["index"] for x in (tmp_path / CHECKPOINT).read_text().splitlines()[1:]]
    assert 2 not in done


# ---------------------------------------------------------------- studies
def _results(out: Path) -> list[dict]:
    rows = [json.loads(x) for x in (out / CHECKPOINT).read_text().splitlines()[1:]]
    return [r["result"] for r in sorted(rows, key=lambda r: r["index"])]


def test_workspace_study_deterministic_and_complete(tmp_path):
    one = run_study("workspace", tmp_path / "w1", n=6, seed=4, workers=1)
    two = run_study("workspace", tmp_path / "w2", n=6, seed=4, workers=2)
    assert _results(tmp_path / "w1") == _results(tmp_path / "w2")
    for key in ("mass_reduction_pct", "friction_reduction_pct"):
        assert one[key] == two[key]
        assert set(one[key]) >= {"mean", "sd"} and one[key]["n"] == 6
    assert one["samples"] == 6 and one["seconds"] >= 0 and one["paper"]["mass_reduction_pct"]["mean"] == 44.23
    on_disk = json.loads((tmp_path / "w1" / "summary.json").read_text())
    assert on_disk["mass_reduction_pct"] == one["mass_reduction_pct"]
    assert (tmp_path / "w1" / "workspace.png").stat().st_size > 1000
    csv = (tmp_path / "w1" / "results.csv").read_text().splitlines()
    assert len(csv) == 7 and "mass_reduction_pct" in csv[0]
    for r in _results(tmp_path / "w1"):  # the paper's definition, from the stored extrema
        assert r["mass_reduction_pct"] == pytest.approx(
            (r["mass_at_max_kg"] - r["mass_at_min_kg"]) / r["mass_at_max_kg"] * 100
        )
        assert r["friction_at_min_N"] <= r["friction_force_start_N"] <= r["friction_at_max_N"]
    other = run_study("workspace", tmp_path / "w3", n=6, seed=5, workers=1)
    assert other["mass_reduction_pct"] != one["mass_reduction_pct"]
    with pytest.raises(ConfigError, match="different run"):
        run_study("workspace", tmp_path / "w1", n=6, seed=5, workers=1)


def test_study_failure_writes_no_summary(tmp_path, monkeypatch):
    def broken(index, seed, opts):
        if index == 1:
            raise RuntimeError("worker exploded")
        return studies.workspace_job(index, seed, opts)

    monkeypatch.setitem(studies.STUDIES, "workspace", studies.Study(broken, 3, ("robot",), studies.workspace_summary))
    with pytest.raises(JobError, match="job 1 failed: RuntimeError: worker exploded"):
        run_study("workspace", tmp_path, n=3, workers=1)
    assert not (tmp_path / "summary.json").exists()


def test_tradeoff_extreme_weights_reproduce_single_optima(tmp_path):
    s = run_study("tradeoff", tmp_path, n=3, seed=2, workers=1, options={"mass_shares": [1.0, 0.5, 0.0]})
    for r in _results(tmp_path):
        assert r["w100_mass_change_pct"] == pytest.approx(0.0, abs=1e-6)
        assert r["w00_friction_change_pct"] == pytest.approx(0.0, abs=1e-6)
        assert r["optima_distance_rad"] >= 0
    assert set(s) >= {"w100", "w50", "w00", "optima_distance_rad"}


def test_uncertainty_without_perturbation_is_exact(tmp_path):
    s = run_study("uncertainty", tmp_path / "u0", n=2, seed=1, workers=1, options={"trials": 3, "friction_sd": 0.0})
    assert s["increase_pct"]["mean"] == 0.0 and s["increase_pct"]["worst"] == 0.0
    s = run_study("uncertainty", tmp_path / "u1", n=2, seed=1, workers=1, options={"trials": 3})
    assert s["increase_pct"]["n"] == 6 and len((tmp_path / "u1" / "results.csv").read_text().splitlines()) == 7


def test_bad_arguments_are_named(tmp_path):
    with pytest.raises(ConfigError, match="unknown study"):
        run_study("nope", tmp_path)
    with pytest.raises(ConfigError, match="unknown study option"):
        run_study("workspace", tmp_path, n=1, options={"gridstep": 1})
    with pytest.raises(ConfigError, match="10 jobs"):
        run_study("scenarios", tmp_path, n=3)
    assert StudyOptions.from_dict({"trials": "5", "mass_shares": "0.2,0.8"}).mass_shares == (0.2, 0.8)


def test_armature_option_is_a_rotor_inertia() -> None:
    """``armature_kgm2``: a number (kg·m², >= 0; the command line's string too) sets that rotor inertia on every
    joint of the workers' robot, None or "none" keeps the model's; a negative one is refused by name."""
    assert StudyOptions().armature_kgm2 is None
    assert StudyOptions.from_dict({"armature_kgm2": "none"}).armature_kgm2 is None
    opts = StudyOptions.from_dict({"armature_kgm2": "0.03"})
    assert opts.armature_kgm2 == 0.03
    assert np.array_equal(
        workbench(opts.robot, opts.compile, opts.armature_kgm2).robot.model.armature, np.full(7, 0.03)
    )
    for bad in ("-0.1", "x"):
        with pytest.raises(ConfigError, match="armature_kgm2"):
            StudyOptions.from_dict({"armature_kgm2": bad})


def test_dask_local_cluster_matches_local_run(tmp_path):
    distributed = pytest.importorskip("distributed")
    local = run_study("workspace", tmp_path / "local", n=4, seed=9, workers=1)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        remote = run_study("workspace", tmp_path / "dask", n=4, seed=9, scheduler=cluster.scheduler_address)
    assert _results(tmp_path / "local") == _results(tmp_path / "dask")
    assert remote["mass_reduction_pct"] == local["mass_reduction_pct"]


def test_scenarios_study_writes_table_one(tmp_path):
    s = run_study("scenarios", tmp_path, workers=2, options={"duration_scale": 0.005})
    table = (tmp_path / "table.md").read_text().splitlines()
    assert len(table) == 2 + len(studies.SCENARIO_JOBS)
    for sc, st in studies.SCENARIO_JOBS:
        row = s["table"][sc][st]
        assert row["margin_respected"] == (row["constraint_proximity_deg"] >= 10.0)
        assert any(line.startswith(f"| {sc} | {st} |") for line in table)
    assert s["paper"]["smoothness"]["B"]["damped"] == 1140
