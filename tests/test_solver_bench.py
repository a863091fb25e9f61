"""Solver benchmark (the package qpnso.lab.solver_bench): KKT metrics against closed-form answers, the
runner's bookkeeping (skips, failures, CSV), and recorded QPs that reproduce the controller."""

from __future__ import annotations

import csv
import math
from dataclasses import replace

import numpy as np
import pytest

from qpnso.errors import InputError
from qpnso.lab import solver_bench as sb
from qpnso.lab.solver_bench import metrics as sb_metrics
from qpnso.lab.solver_bench import problems as sb_problems
from qpnso.lab.solver_bench import record as sb_record
from qpnso.lab.solver_bench import runs as sb_runs

INF = math.inf


def hand_qp(**changes) -> sb.BenchProblem:
    """min ½‖x‖² − 2x₁ − 2x₂  s.t.  x₁ + x₂ ≤ 2,  −1 ≤ x ≤ (0.5, 5).

    By hand: x* = (0.5, 1.5), cost −2.75; row dual z = 0.5 (upper side), box dual
    z_box = (1, 0) (x₁ at its upper bound): Px + q + Cᵀz + z_box = 0.
    """
    fields = dict(
        name="hand",
        sequence="hand",
        level=2,
        tick=0,
        P=np.eye(2),
        q=np.array([-2.0, -2.0]),
        C=np.array([[1.0, 1.0]]),
        l=np.array([-INF]),
        u=np.array([2.0]),
        box_l=np.array([-1.0, -1.0]),
        box_u=np.array([0.5, 5.0]),
        x_prev=np.zeros(2),
        Z=np.eye(2),
        ref_v=np.array([0.5, 1.5]),
        ref_obj=-2.75,
    )
    fields.update(changes)
    return sb.BenchProblem(**fields)


# ------------------------------------------------------------- KKT metrics
def test_residuals_vanish_at_the_hand_solution_and_grow_as_computed_by_hand():
    p = hand_qp()
    sf = sb.standard_form(p)
    y, z, z_box = sf.duals(np.array([0.5]), np.array([1.0, 0.0]))
    assert y is None and z.tolist() == [0.5] and z_box.tolist() == [1.0, 0.0]
    assert sb.kkt_residuals(sf, np.array([0.5, 1.5]), y, z, z_box) == pytest.approx((0, 0, 0), abs=1e-15)
    d = 1e-3  # x₂ pushed up by d: row violated by d, stationarity off by d in x₂, gap d + d²
    rp, rd, rg = sb.kkt_residuals(sf, np.array([0.5, 1.5 + d]), y, z, z_box)
    assert (rp, rd, rg) == pytest.approx((d, d, d + d * d), rel=1e-9)
    assert p.objective(np.array([0.5, 1.5])) == pytest.approx(-2.75)


def test_missing_solution_or_dual_gives_infinite_residuals():
    sf = sb.standard_form(hand_qp())
    assert sb.kkt_residuals(sf, None, None, None, None) == (INF, INF, INF)
    rp, rd, rg = sb.kkt_residuals(sf, np.array([0.5, 1.5]), None, None, None)
    assert rp == 0.0 and rd == INF and rg == INF


def test_standard_form_splits_two_sided_rows_equalities_and_an_infinite_box():
    p = hand_qp(
        C=np.array([[1.0, 1.0], [1.0, -1.0], [0.0, 1.0]]),
        l=np.array([-INF, -1.0, -3.0]),
        u=np.array([2.0, -1.0, 3.0]),
        box_l=np.array([-1.0, -INF]),
        box_u=np.array([0.5, INF]),
    )
    sf = sb.standard_form(p)
    prob = sf.problem
    # rows: x1+x2 ≤ 2, x2 ≤ 3, −x2 ≤ 3, box x1 ≤ 0.5, −x1 ≤ 1 (folded: the box has an infinite side)
    assert prob.G.tolist() == [[1, 1], [0, 1], [0, -1], [1, 0], [-1, 0]]
    assert prob.h.tolist() == [2, 3, 3, 0.5, 1]
    assert prob.A.tolist() == [[1, -1]] and prob.b.tolist() == [-1]
    assert prob.lb is None and prob.ub is None and not sf.box
    y, z, z_box = sf.duals(np.array([0.5, -0.25, -2.0]), np.array([1.0, 0.0]))  # ProxSuite signs
    assert y.tolist() == [-0.25] and z.tolist() == [0.5, 0.0, 2.0, 1.0, 0.0] and z_box is None


def test_shifted_geometric_mean_by_hand():
    assert sb.shifted_geometric_mean([0.0, 10.0, 30.0], 10.0) == pytest.approx(10.0)  # ∛(10·20·40) − 10
    with pytest.raises(InputError):
        sb.shifted_geometric_mean([], 10.0)


# ------------------------------------------------------------------ runner
SOLVERS = ["proxsuite", "daqp", "quadprog", "no_such_solver"]


def test_runner_solves_the_hand_qp_and_skips_unknown_solvers():
    # the time limit is the benchmark's verdict, not this test's: a cold first call on a loaded CI machine
    # once took 12.9 ms (no timing assertions in tests)
    untimed = [replace(s, time_limit_s=math.inf) for s in (sb.DEFAULT, sb.HIGH_ACCURACY)]
    outcomes, skipped = sb.run_problems([hand_qp()], SOLVERS, untimed)
    assert "no_such_solver" in skipped
    ran = {o.solver for o in outcomes}
    assert "no_such_solver" not in ran and len(ran) >= 2
    assert {o.settings for o in outcomes} == {"default", "high_accuracy"}
    for o in outcomes:
        assert o.success, (o.solver, o.settings, o.status, o.detail)
        tight = o.settings == "high_accuracy"
        assert o.cost_error < (1e-8 if tight else 1e-4) and o.x_error < (1e-6 if tight else 1e-3)
        assert max(o.primal, o.dual, o.gap) <= (1e-3 if o.settings == "default" else 1e-9)


def test_infeasible_problem_and_crashing_solver_are_failures_with_status(monkeypatch):
    infeasible = hand_qp(box_l=np.array([1.5, 1.5]), box_u=np.array([5.0, 5.0]), ref_v=None, ref_obj=None)
    outcomes, _ = sb.run_problems([infeasible], ["proxsuite", "daqp"], settings=[sb.HIGH_ACCURACY])
    assert outcomes and all(not o.success and o.status.startswith("not found") for o in outcomes)
    native = next(o for o in outcomes if o.solver == "proxsuite")
    assert native.status.startswith("not found (proxsuite PROXQP_")  # its own word (max_iter here)

    import qpsolvers

    def broken(*args, **kwargs):
        raise RuntimeError("boom")

    monkeypatch.setattr(qpsolvers, "solve_problem", broken)
    outcomes, _ = sb.run_problems([hand_qp()], ["daqp"], settings=[sb.DEFAULT])
    (o,) = outcomes
    assert not o.success and o.status == "error: RuntimeError" and "boom" in o.detail
    (row,) = sb.summarize(outcomes)
    assert row["success_rate"] == 0.0 and "1× error: RuntimeError" in row["failures"]
    assert row["runtime_sgm"] == pytest.approx(1.0)  # the only solver is the best


def test_inaccurate_answer_is_a_failure():
    p = hand_qp()
    strict = sb.BenchSettings("strict", 1e-9, 1e-9)
    o = sb_runs._outcome(
        p,
        sb.standard_form(p),
        strict,
        "x",
        True,
        "found",
        1e-5,
        np.array([0.5, 1.5 + 1e-4]),
        None,
        np.array([0.5]),
        np.array([1.0, 0.0]),
    )
    assert not o.success and o.status == "inaccurate: primal/dual/gap"
    slow = sb_runs._outcome(
        p,
        sb.standard_form(p),
        strict,
        "x",
        True,
        "found",
        1.0,
        np.array([0.5, 1.5]),
        None,
        np.array([0.5]),
        np.array([1.0, 0.0]),
    )
    assert not slow.success and slow.status == "timeout"


def test_summary_csv_columns(tmp_path):
    outcomes, _ = sb.run_problems([hand_qp(), hand_qp(name="hand2")], ["proxsuite", "daqp"])
    rows = sb.summarize(outcomes)
    path = sb_metrics.write_results_csv(rows, tmp_path / "results.csv")
    with open(path) as f:
        header = next(csv.reader(f))
    assert tuple(header[: len(sb.CSV_COLUMNS)]) == sb.CSV_COLUMNS
    assert len(rows) == 2 * len({o.solver for o in outcomes})
    assert min(r["runtime_sgm"] for r in rows if r["settings"] == "default") == pytest.approx(1.0)


# --------------------------------------------------------------- recording
@pytest.fixture(scope="module")
def recorded():
    """A short run of the shipped controller (native ProxSuite, μ = 0) with the tool moving."""
    from qpnso.control.config import ControllerConfig
    from qpnso.control.controller import Controller
    from qpnso.lab.scenarios import load_scenario
    from qpnso.model.robot import load_robot

    sc = load_scenario("A")
    robot = load_robot(sc.robot)
    ctrl = Controller(robot, ControllerConfig.from_dict(dict(sc.controller)))
    traj = sc.path()
    traj = traj.window(traj.t[0], traj.t[0] + 0.5)
    with sb.QPRecorder(ctrl, "A", keep=lambda k: k >= 200) as rec:
        sb_record._track(ctrl, traj, sc.start(robot), 215)
    assert "solve_problem" not in vars(ctrl.qp)  # the wrapper is gone afterwards
    return rec.problems


def test_recorded_qps_reproduce_the_controller_with_proxsuite(recorded):
    import proxsuite

    assert {p.level for p in recorded} == {1, 2} and len(recorded) == 30
    for p in recorded:
        qp = proxsuite.proxqp.dense.QP(p.nv, 0, p.C.shape[0], p.box_l is not None)
        qp.settings.eps_abs, qp.settings.eps_rel = 1e-12, 0.0
        kw = dict(H=p.P, g=p.q)
        if p.C.shape[0]:
            kw.update(C=p.C, l=p.l, u=p.u)
        if p.box_l is not None:
            kw.update(l_box=p.box_l, u_box=p.box_u)
        qp.init(**kw)
        qp.solve()
        assert qp.results.info.status == proxsuite.proxqp.QPSolverOutput.PROXQP_SOLVED
        v = np.array(qp.results.x)
        if p.level == 2:  # strictly convex: the controller's command itself
            assert np.abs(p.decode(v) - p.x_controller).max() < 1e-7, p.name
        else:  # μ = 0 leaves the self-motion direction flat: same optimal cost, level 2 picks the rest
            v_ctrl = p.Z.T @ (p.x_controller - p.x_prev)
            assert p.objective(v_ctrl) == pytest.approx(p.objective(v), abs=1e-9)


def test_problem_set_round_trip_and_reference(recorded, tmp_path):
    problems = recorded[:6]
    sb.compute_reference(problems)
    for p in problems:
        assert p.ref_v is not None and p.ref_spread < 1e-9
    path = sb.save_problems(tmp_path / "set.npz", problems, {"note": "test"})
    loaded, meta = sb.load_problems(path)
    assert meta == {"note": "test"} and len(loaded) == len(problems)
    for a, b in zip(problems, loaded):
        for name in ("P", "q", "C", "l", "u", "box_l", "box_u", "x_prev", "Z", "x_controller", "ref_v"):
            x, y = getattr(a, name), getattr(b, name)
            assert (x is None and y is None) or np.array_equal(x, y), name
        assert (a.name, a.level, a.ref_obj) == (b.name, b.level, b.ref_obj)


def test_committed_quick_set_matches_the_controller():
    path = sb_problems.PROBLEM_DIR / "quick.npz"
    if not path.is_file():
        pytest.skip("solvers/problems/quick.npz not in this tree")
    problems, meta = sb.load_problems(path)
    assert meta["regularization"] == sb_record.BENCH_REGULARIZATION and len(problems) >= 200
    level2 = [p for p in problems if p.level == 2]
    assert level2 and all(p.ref_v is not None for p in problems)
    worst = max(np.abs(p.decode(p.ref_v) - p.x_controller).max() for p in level2)
    assert worst < 1e-6  # rebuilt with μ = 1e-7 instead of the native 0: a tiny bias only


# ------------------------------------------------------- closed loop, report
def test_closed_loop_and_report(recorded, tmp_path):
    sb.compute_reference(recorded[:4])
    path = sb.save_problems(tmp_path / "tiny.npz", recorded[:4], {"regularization": 0.0})
    report = sb.run_solver_benchmark(tmp_path / "out", quick=True, solvers=["proxsuite", "daqp", "nope"], problems=path)
    text = report.read_text()
    assert "`nope`" in text and "| proxsuite | default |" in text and "## Closed loop" in text
    with open(tmp_path / "out" / "closed_loop.csv") as f:
        rows = list(csv.DictReader(f))
    by = {r["backend"]: r for r in rows}
    assert set(by) == {"proxsuite", "daqp"}
    assert float(by["daqp"]["status_QP_FAILED_ticks"]) == 0.0
    assert float(by["daqp"]["dq_diff_max"]) < 1e-5  # same commands as native ProxSuite
    assert (tmp_path / "out" / "results.csv").is_file()
