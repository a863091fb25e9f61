"""The closed-loop fuzzer (qpnso/lab/fuzz/): its checker sees what it must, and a seeded run holds every line."""

from __future__ import annotations

import functools
import json
import time
from dataclasses import fields, replace

import fuzz_faults
import numba
import numpy as np
import pytest
from conftest import HAS_PANDA, without_second_pass

import qpnso
from qpnso.control.config import STRATEGIES, Command, ControllerConfig, Status
from qpnso.control.controller import Controller
from qpnso.errors import InputError
from qpnso.lab.fuzz import (
    CHECK_KEYS,
    PROBE_KINDS,
    CommandHistory,
    FuzzConfig,
    FuzzReport,
    HoldMonitor,
    KernelWatch,
    Probe,
    TickChecker,
    Where,
    make_probe,
    run_fuzz,
    send_probe,
)


@pytest.fixture(scope="module")
def tool_robot() -> qpnso.Robot:
    return qpnso.load_robot("lwr4p", tool_offset=[0, 0, 0.1])


@pytest.fixture
def checker(tool_robot) -> TickChecker:
    return TickChecker(tool_robot, FuzzConfig(), FuzzReport(FuzzConfig()))


TICKS = 18_000
WHERE = Where(seed=0, episode=0, strategy="qp", start="uniform", phase="hold", robot="lwr4p", dt=1e-3)
LWR_1MS = dict(robots=("lwr4p",), dts=(1e-3,))  # the one setting of the runs before issue 31 (episode numbers kept)
HAS_ACCEL_BOUND = "ddq_max" in {f.name for f in fields(ControllerConfig)}


def fake_command(
    robot: qpnso.Robot, q: np.ndarray, dq: np.ndarray | None = None, tau: np.ndarray | None = None, **fields
) -> Command:
    """A Command as the controller makes one: q_des = q + dt·dq, gravity-like torque."""
    dq = np.zeros(robot.nq) if dq is None else dq
    values = dict(
        dq=dq,
        q_des=q + 1e-3 * dq,
        tau=np.zeros(robot.nq) if tau is None else tau,
        stiffness=0.0,
        arm_angle=0.0,
        rom=(-1.0, 1.0),
        interval=(-3.0, 3.0),
        cost=0.0,
        status=Status.OK,
        solve_time=1e-5,
        tick_time=2e-5,
        tool_error=(0.0, 0.0),
    )
    values.update(fields)
    return Command(**values)


def nonzero(report: FuzzReport) -> dict[str, int]:
    return {k: v for k, v in report.counts.items() if v}


def test_a_good_command_passes(checker, tool_robot) -> None:
    q = tool_robot.sample_configuration()
    assert checker.command(
        fake_command(tool_robot, q, dq=0.5 * tool_robot.dq_max, tau=0.9 * tool_robot.tau_limit), q, WHERE, {"q": q}
    )
    assert nonzero(checker.report) == {} and checker.report.failures() == []


def test_checker_sees_non_finite_velocity_limit_torque_and_time(checker, tool_robot) -> None:
    q = tool_robot.sample_configuration()
    rep = checker.report
    nan_dq = np.zeros(7)
    nan_dq[3] = np.nan
    assert not checker.command(fake_command(tool_robot, q, dq=nan_dq), q, WHERE, {"q": q})
    assert rep.counts["non_finite"] == 1
    tau = tool_robot.tau_limit.copy()
    tau[5] *= -2.0
    checker.command(fake_command(tool_robot, q, tau=tau), q, WHERE, {"q": q})
    assert rep.counts["torque"] == 1 and rep.worst["torque"].value == pytest.approx(2.0)
    assert "joint 6" in rep.worst["torque"].detail
    fast = np.zeros(7)
    fast[0] = 1.01 * tool_robot.dq_max[0]
    checker.command(fake_command(tool_robot, q, dq=fast), q, WHERE, {"q": q})
    assert rep.counts["velocity"] == 1 and rep.worst["velocity"].value == pytest.approx(1.01)
    at_limit = q.copy()
    at_limit[1] = tool_robot.q_max[1] - 1e-4
    up = np.zeros(7)
    up[1] = 1.0  # 1e-3 rad in a tick: crosses q_max by 9e-4
    checker.command(fake_command(tool_robot, at_limit, dq=up), at_limit, WHERE, {"q": at_limit})
    assert rep.counts["limit_crossing"] == 1 and rep.worst["limit_crossing"].value == pytest.approx(9e-4)
    checker.command(fake_command(tool_robot, q, solve_time=2e-3), q, WHERE, {"q": q})
    assert rep.counts["solve_time"] == 1
    assert {f.split(":")[0] for f in rep.failures()} >= {
        "0 non-finite commands (dq, q_des, tau)",
        "0 torques above the effort limits (abs(tau) ≤ tau_limit)",
    }
    assert "| 0 torques above the effort limits (abs(tau) ≤ tau_limit) | 1 | 2 × tau_limit" in rep.table()


def test_outside_a_limit_may_move_back_not_further_out(checker, tool_robot) -> None:
    q = tool_robot.sample_configuration()
    q[2] = tool_robot.q_min[2] - 0.01
    back, out = np.zeros(7), np.zeros(7)
    back[2], out[2] = 0.2, -0.2
    checker.command(fake_command(tool_robot, q, dq=back), q, WHERE, {"q": q})
    assert checker.report.counts["limit_crossing"] == 0
    checker.command(fake_command(tool_robot, q, dq=out), q, WHERE, {"q": q})
    assert checker.report.counts["limit_crossing"] == 1


def test_checker_sees_a_growing_rom_excursion_unflagged(checker, tool_robot) -> None:
    q = tool_robot.sample_configuration()
    previous = checker.rom(fake_command(tool_robot, q, arm_angle=1.1), None, WHERE, {})
    assert previous == pytest.approx(0.1) and checker.report.counts["rom_excursion"] == 0
    flagged = fake_command(tool_robot, q, arm_angle=1.2, status=Status.ELBOW_SLACK)
    previous = checker.rom(flagged, previous, WHERE, {})
    assert checker.report.counts["rom_excursion"] == 0
    checker.rom(fake_command(tool_robot, q, arm_angle=1.3), previous, WHERE, {})
    assert checker.report.counts["rom_excursion"] == 1
    checker.rom(fake_command(tool_robot, q, arm_angle=1.25), 0.3, WHERE, {})  # moving back in: fine
    assert checker.report.counts["rom_excursion"] == 1


def test_checker_sees_a_drifting_held_tool(checker, tool_robot) -> None:
    q = tool_robot.sample_configuration()
    reference = checker.tool_pose(q)
    hold = HoldMonitor()
    hold.start()
    checker.drift(hold, checker.tool_error(q, *reference), None, WHERE, {})
    assert hold.settled
    moved = q.copy()
    moved[0] += 1e-4  # the tool moves ~0.1 mm about the base axis
    error = checker.tool_error(moved, *reference)
    assert error[0] > 1e-5
    checker.drift(hold, error, Status.TOOL_LIMITED, WHERE, {})  # excused: bounds stopped the tool
    assert checker.report.counts["drift"] == 0 and not hold.settled
    checker.drift(hold, checker.tool_error(q, *reference), Status.OK, WHERE, {})
    checker.drift(hold, error, Status.OK, WHERE, {})
    assert checker.report.counts["drift"] == 1 and checker.report.worst["drift"].value == pytest.approx(max(error))


class FakeController:
    """Stands for a Controller: ``step`` raises ``error`` or returns ``cmd``."""

    def __init__(self, error: Exception | None = None, cmd: Command | None = None) -> None:
        self.error, self.cmd = error, cmd

    def step(self, q, dq=None, tool_twist=None, tool_pose=None) -> Command:
        if self.error is not None:
            raise self.error
        return self.cmd  # type: ignore[return-value]


def test_probe_outcomes_refused_foreign_accepted(checker, tool_robot) -> None:
    q = tool_robot.sample_configuration()
    rng = np.random.default_rng(1)
    rep = checker.report
    probe = make_probe("q_nan", rng, q, np.zeros(7), tool_robot, checker.config)
    assert probe.must_refuse and np.isnan(probe.kwargs["q"]).any()
    assert send_probe(FakeController(InputError("q contains NaN")), probe, checker, WHERE) == "refused"
    assert send_probe(FakeController(KeyError("oops")), probe, checker, WHERE) == "foreign"
    assert rep.counts["foreign_exception"] == 1 and "KeyError" in rep.exceptions[0]["traceback"]
    twist = make_probe("twist_inf", rng, q, np.zeros(7), tool_robot, checker.config)
    bad_torque = fake_command(tool_robot, q, tau=3 * tool_robot.tau_limit)
    assert send_probe(FakeController(cmd=bad_torque), twist, checker, WHERE) == "accepted"
    assert rep.counts["bad_accepted"] == 1 and rep.counts["torque"] == 1
    little = make_probe("q_out_little", rng, q, np.zeros(7), tool_robot, checker.config)
    assert not little.must_refuse
    assert send_probe(FakeController(cmd=fake_command(tool_robot, little.q)), little, checker, WHERE) == "accepted"
    assert rep.counts["bad_accepted"] == 1
    assert rep.probe_outcomes["q_nan"] == {"refused": 1, "foreign": 1}


def test_every_probe_kind_is_made(tool_robot) -> None:
    q = tool_robot.sample_configuration()
    rng = np.random.default_rng(2)
    for kind in PROBE_KINDS:
        probe = make_probe(kind, rng, q, np.zeros(7), tool_robot, FuzzConfig())
        assert isinstance(probe, Probe) and probe.kind == kind and "q" in probe.kwargs


def test_cli_bench_fuzz_writes_the_report_and_sets_the_exit_status(tmp_path, capsys) -> None:
    from qpnso.cli import main

    out = tmp_path / "fuzz.json"
    quick = ["--robot", "lwr4p", "--dt-ms", "4", "--workers", "0"]
    code = main(
        ["bench", "fuzz", "-n", "300", "--seed", "3", "--strategies", "damped,qp", "--out", str(out), "--quiet", *quick]
    )
    data = json.loads(out.read_text())
    assert data["ticks"] == 300 and data["config"]["seed"] == 3 and data["config"]["strategies"] == ["damped", "qp"]
    assert data["config"]["robots"] == ["lwr4p"] and data["config"]["dts"] == [4e-3] and data["processes"] == 0
    assert code == (1 if data["failures"] else 0)
    assert "| check | count | worst |" in capsys.readouterr().out
    assert main(["bench", "fuzz", "-n", "10", "--strategies", "nope"]) == 2
    capsys.readouterr()
    for flag, value in (("--robot", "nope"), ("--dt-ms", "0"), ("--workers", "-1"), ("--dt-ms", "1,x")):
        assert main(["bench", "fuzz", "-n", "10", "--strategies", "qp", flag, value]) == 2
        assert capsys.readouterr().err.count("\n") == 1


def test_cli_bench_fuzz_passes_the_solver_time_budget_and_counts_its_ticks(tmp_path) -> None:
    """``--solver-time-budget-ms``: every controller gets it; a budget nothing fits in cuts every general
    cascade after level 1 (the damped strategy from singular starts runs many), and the report counts them."""
    from qpnso.cli import main

    out = tmp_path / "fuzz.json"
    quick = ["--robot", "lwr4p", "--dt-ms", "1", "--workers", "0"]
    main(
        [
            "bench",
            "fuzz",
            "-n",
            "600",
            "--seed",
            "5",
            "--strategies",
            "fixed",
            "--solver-time-budget-ms",
            "1e-9",
            "--out",
            str(out),
            "--quiet",
            *quick,
        ]
    )
    data = json.loads(out.read_text())
    assert data["config"]["solver_time_budget"] == pytest.approx(1e-12)
    assert data["deadline_ticks"] > 0
    main(["bench", "fuzz", "-n", "600", "--seed", "5", "--strategies", "fixed", "--out", str(out), "--quiet", *quick])
    assert json.loads(out.read_text())["deadline_ticks"] == 0


@pytest.mark.xfail(
    not HAS_ACCEL_BOUND,
    reason="issue 31: joint commands reverse by > 0.5 rad/s within two ticks until ControllerConfig.ddq_max "
    "bounds them",
    strict=True,
)
def test_seeded_closed_loop_fuzz_holds_every_line() -> None:
    """About 20 s here: 18 000 ticks of the LWR4+ at 1 ms, 3000 per strategy, from every kind of start, with twists,
    pulls, overshoots and bad inputs (a run that stops at ``max_seconds`` fails); every line, the acceleration
    bound and reversals included.  Reproduce a failing episode alone with
    ``run_fuzz(FuzzConfig(seed=13, first_episode=E, ticks=600, robots=("lwr4p",), dts=(1e-3,)))``; long runs:
    ``qpnso bench fuzz -n 1000000 --workers 2``."""
    # No timing assertion in the suite (a loaded CI machine is not this machine's class): the solver-time and
    # whole-tick CPU lines are counted, not held here; `qpnso bench fuzz` holds them (README).
    report = run_fuzz(
        FuzzConfig(
            seed=13,
            ticks=TICKS,
            episode_seconds=20.0,
            max_seconds=600.0,
            solve_time_max=float("inf"),
            tick_cpu_max=float("inf"),
            **LWR_1MS,
        )
    )
    json.dumps(report.to_dict())
    assert set(report.by_strategy) == set(STRATEGIES) and set(report.counts) == set(CHECK_KEYS)
    assert report.probes > 50 and len(report.recovery) > 20 and report.drift_checked > 1000  # not vacuous
    assert {k.split(" ")[0] for k in report.start_kinds} == {
        "uniform",
        "near_limit",
        "elbow_straight",
        "wrist_over_shoulder",
    }
    assert report.failures() == [], report.table()


def test_a_tick_slow_only_in_wall_time_counts_as_preempted(tool_robot) -> None:
    """A tick over the solver-time limit in wall time in which the solver used less CPU time than the limit is
    the machine's (preempted); one over it in CPU time too is a slow tick, kept to be replayed (next test)."""
    rep = FuzzReport(FuzzConfig())
    checker = TickChecker(tool_robot, rep.config, rep)
    q = tool_robot.sample_configuration()
    checker.command(
        fake_command(tool_robot, q, solve_time=2e-3), q, WHERE, {"q": q}, cpu_time=3e-3, solver_cpu_time=1e-4
    )
    assert rep.counts["preempted"] == 1 and rep.counts["solve_time"] == 0
    checker.command(
        fake_command(tool_robot, q, solve_time=2e-3), q, WHERE, {"q": q}, cpu_time=3e-3, solver_cpu_time=1.5e-3
    )
    assert rep.counts["preempted"] == 1 and rep.counts["solve_time"] == 1
    assert rep.failures() == []  # neither line is a must-hold: a slow tick fails when its replays reproduce it
    assert [where.tick for where, _ in rep.slow] == [WHERE.tick]  # (the slow one kept for its replays)


def test_a_dropped_elbow_at_a_pose_that_fixes_it_is_not_a_failure_to_recover(checker, tool_robot) -> None:
    """Overdue, ``ELBOW_DROPPED``, the elbow straight (its distance from the shoulder–wrist line is 0 for every
    self-motion): counted apart, not as a failed recovery; the same at a bent elbow is a failure."""
    from qpnso.lab.fuzz import Recovery, arm_angle_undefined, update_recovery

    straight = np.radians([10.0, 40.0, -10.0, 0.0, 20.0, 50.0, 0.0])  # q4 = 0: elbow straight
    bent = np.radians([10.0, 40.0, -10.0, -70.0, 20.0, 50.0, 0.0])
    assert arm_angle_undefined(checker, straight) and not arm_angle_undefined(checker, bent)
    rep, limit = checker.report, checker.config.recovery_ticks
    for q, undefined, failed in ((straight, 1, 0), (bent, 1, 1)):
        reference = checker.tool_pose(q)
        pending = Recovery("pull", 0, WHERE)
        cmd = fake_command(tool_robot, q, status=Status.ELBOW_DROPPED)
        assert (update_recovery(pending, limit, cmd, 0.0, checker, q, reference, {"q": q}) is None) == (q is straight)
        assert (rep.recovery_elbow_undefined, rep.counts["recovery"]) == (undefined, failed)


def test_solver_clock_measures_the_solver_calls_of_a_tick() -> None:
    """:class:`SolverClock` counts the CPU time of ``solve_problem`` calls (a busy loop of 2 ms CPU here, called
    twice: a tick solved twice), not of other calls (``solve``), and 0 when nothing was solved; and on a real
    controller it wraps the method every tick calls (a tick's solver time is > 0)."""
    import time

    import qpnso
    from qpnso.lab.fuzz import SolverClock

    class Busy:
        def solve_problem(self) -> int:
            end = time.thread_time() + 2e-3
            while time.thread_time() < end:
                pass
            return 7

        def solve(self) -> int:
            end = time.thread_time() + 2e-3
            while time.thread_time() < end:
                pass
            return 8

    busy = Busy()
    clock = SolverClock(busy)
    assert busy.solve_problem() == 7 and busy.solve_problem() == 7 and busy.solve() == 8
    assert 4e-3 <= clock.take() < 6e-3
    assert clock.take() == 0.0  # nothing ran since
    robot = qpnso.load_robot("lwr4p", tool_offset=[0, 0, 0.1])
    ctrl = qpnso.Controller(robot, qpnso.ControllerConfig())
    clock = SolverClock(ctrl.qp)
    q = robot.sample_configuration()
    ctrl.reset(q)
    ctrl.step(q)
    assert clock.take() > 0.0


def test_realtime_gc_freezes_for_the_block_and_unfreezes() -> None:
    import gc

    from qpnso.lab.fuzz import realtime_gc

    assert gc.get_freeze_count() == 0
    with realtime_gc():
        assert gc.get_freeze_count() > 1000  # the objects alive now are out of the collector's generations
    assert gc.get_freeze_count() == 0


def test_a_config_that_could_not_send_bad_inputs_is_refused() -> None:
    """No probe kinds or bursts of at most zero would crash the first burst (``rng.integers``): a ConfigError."""
    with pytest.raises(qpnso.ConfigError, match="probe kinds"):
        FuzzConfig(probe_kinds=())
    with pytest.raises(qpnso.ConfigError, match="probe_burst_max"):
        FuzzConfig(probe_burst_max=0)


def test_the_pull_that_stopped_next_to_the_joint_bounds_leaves_the_tool_held(monkeypatch) -> None:
    """Seed 1, episode 129 of the 10⁶-tick run: elbow-up, a 2 m/s pull that ends with level 1 leaving the joint
    bounds, so the self-motion they held back starts at once (1.42 rad/s off the predicted command); the held
    tool then moved 1.14 µrad.  It holds now (the tick is solved again along its own q̇), and it does not when
    the first solve is kept."""
    episode = FuzzConfig(
        seed=1, first_episode=129, ticks=600, strategies=("elbow-up",), compile="sync", ddq_max=1e9, **LWR_1MS
    )  # (no acceleration bound: alone it keeps the held tool here since issue 31)
    report = run_fuzz(episode)
    assert report.counts["drift"] == 0 and report.drift_checked > 500
    without_second_pass(monkeypatch)
    assert run_fuzz(episode).counts["drift"] == 1


def test_only_a_tick_on_its_reference_and_not_limited_starts_a_recovery(tool_robot) -> None:
    """A disturbance is measured for recovery only from a tick that was OK, within the tolerance of its reference
    and not ``TOOL_LIMITED``; and episode 844 of seed 1 (a twist the joint velocity limits could not follow near
    a straight elbow, bad inputs refused in the middle) no longer counts as a failed recovery."""
    from qpnso.lab.fuzz.episode import on_reference

    q = np.zeros(7)
    assert on_reference(fake_command(tool_robot, q), 5e-5, 1e-4)
    assert not on_reference(fake_command(tool_robot, q), 2e-4, 1e-4)
    assert not on_reference(fake_command(tool_robot, q, status=Status.TOOL_LIMITED), 5e-5, 1e-4)
    assert not on_reference(fake_command(tool_robot, q, status=Status.QP_FAILED), 5e-5, 1e-4)
    assert not on_reference(None, 0.0, 1e-4)
    report = run_fuzz(
        FuzzConfig(seed=1, first_episode=844, ticks=600, strategies=("gradient",), compile="sync", **LWR_1MS)
    )
    assert report.counts["recovery"] == 0


@pytest.mark.parametrize("every_time", [True, False])
def test_a_slow_tick_is_replayed_and_counted_only_when_it_is_slow_again(monkeypatch, every_time: bool) -> None:
    """A tick whose solve burns 6 ms of CPU on every run of its episode (the code) is reproduced by both replays
    and fails the must-hold line; one that burns it only the first time (the machine) is counted, not held."""
    from qpnso.qp.solver import HierarchicalQP

    calls = {"since_reset": 0, "burnt": 0}
    solve_problem, reset = HierarchicalQP.solve_problem, Controller.reset

    def counting_reset(self, *args, **kwargs):
        calls["since_reset"] = 0
        return reset(self, *args, **kwargs)

    def burning_solve(self, *args, **kwargs):
        calls["since_reset"] += 1
        if calls["since_reset"] == 40 and (every_time or not calls["burnt"]):
            calls["burnt"] += 1
            start = time.thread_time()
            while time.thread_time() - start < 6e-3:
                pass
        return solve_problem(self, *args, **kwargs)

    monkeypatch.setattr(Controller, "reset", counting_reset)
    monkeypatch.setattr(HierarchicalQP, "solve_problem", burning_solve)
    config = FuzzConfig(
        seed=3,
        ticks=120,
        episode_ticks=120,
        strategies=("qp",),
        solve_time_max=4e-3,
        tick_cpu_max=float("inf"),  # (this test is about the solver-time line)
        p_probe_burst=0,
        **LWR_1MS,
    )
    report = run_fuzz(config)
    assert report.counts["solve_time"] == 1
    assert calls["burnt"] == (3 if every_time else 1)  # the run and its two replays, or the run alone
    assert report.counts["solve_time_reproduced"] == (1 if every_time else 0)
    assert bool(report.failures()) == every_time


# ---------------------------------------------------------------- issue 31: the mix, CPU, kernels, commands
def test_an_episode_setting_cycles_the_strategies_then_the_robot_and_dt() -> None:
    """Episode E runs strategy E mod S on the (robot, dt) pair (E div S) mod P: any S·P consecutive episodes run
    every combination once (counted here), and a shard's stride (every K-th episode) runs what it lists."""
    cfg = FuzzConfig(robots=("lwr4p", "iiwa14"), dts=(1e-3, 4e-3), strategies=("qp", "rom", "fixed"))
    assert cfg.setting(0) == ("lwr4p", 1e-3, "qp") and cfg.setting(4) == ("lwr4p", 4e-3, "rom")
    assert cfg.setting(11) == ("iiwa14", 4e-3, "fixed") and cfg.setting(12) == ("lwr4p", 1e-3, "qp")
    every = {(r, dt, s) for r in cfg.robots for dt in cfg.dts for s in cfg.strategies}
    for first in (0, 5, 17):
        run = [cfg.setting(e) for e in range(first, first + 12)]
        assert len(run) == 12 and set(run) == every
    for first, stride in ((1, 2), (0, 5), (3, 4)):
        assert set(cfg.settings_of(first, stride)) == {cfg.setting(e) for e in range(first, 500, stride)}


def send(checker: TickChecker, history: CommandHistory, dq: np.ndarray) -> None:
    """One command (rad/s) of the controller, as the episode hands it to :meth:`TickChecker.motion`."""
    q = np.zeros(7)
    checker.motion(history, np.asarray(dq, dtype=float), fake_command(checker.robot, q, dq=dq), WHERE, {})


def test_checker_counts_a_command_change_beyond_the_acceleration_bound(checker) -> None:
    """ddq_max 10 rad/s² at dt 1 ms: a joint's command may change by 0.01 rad/s a tick (and 1e-9 of it, + 1e-12);
    1.02 times that is counted, valued 1.02 (× ddq_max·dt); the first command after a reset is compared with
    nothing; a controller without ddq_max is not checked, and says so."""
    rep, e = checker.report, np.eye(7)[2]
    history = CommandHistory(np.full(7, 10.0), 1e-3)
    send(checker, history, 0.3 * e)
    assert rep.accel_checked == 0
    send(checker, history, (0.3 + 0.0099) * e)
    send(checker, history, (0.3 + 0.0099 + 0.01 * (1 + 5e-10)) * e)  # on the bound, within its tolerance
    assert (rep.accel_checked, rep.counts["accel_bound"]) == (2, 0)
    send(checker, history, (0.3 + 0.0099 + 0.01 * (1 + 5e-10) - 0.0102) * e)
    assert rep.counts["accel_bound"] == 1 and rep.worst["accel_bound"].value == pytest.approx(1.02, rel=1e-9)
    assert "joint 3" in rep.worst["accel_bound"].detail
    history.reset()
    send(checker, history, np.zeros(7))
    assert (rep.accel_checked, rep.counts["accel_bound"]) == (3, 1)
    unbounded = CommandHistory(None, 1e-3)
    send(checker, unbounded, np.zeros(7))
    send(checker, unbounded, 5.0 * e)
    assert (rep.accel_checked, rep.accel_unbounded, rep.counts["accel_bound"]) == (3, 1, 1)
    assert "| 1 | 1.02 × ddq_max·dt: " in rep.table()
    unchecked = FuzzReport(FuzzConfig(), accel_unbounded=4).table()
    assert "| not checked: the controller has no ddq_max (4 commands) | — |" in unchecked


@pytest.mark.parametrize(
    "sequence, reversals",
    [
        ([0.6, -0.6], 1),
        ([-0.6, 0.6], 1),
        ([0.6, 0.0, -0.6], 1),  # within two ticks
        ([0.6, -0.6, -0.7, -0.6], 1),  # one reversal, counted once
        ([0.6, -0.6, 0.6], 2),
        ([0.6, 0.0, 0.0, -0.6], 0),  # over three ticks
        ([0.6, -0.4], 0),
        ([0.4, -0.6], 0),
    ],
)
def test_checker_counts_a_joint_command_reversed_beyond_half_a_radian_per_second(checker, sequence, reversals) -> None:
    """A joint's command from beyond 0.5 rad/s one way to beyond it the other way within two ticks: one count on
    the tick it arrives (the issue's "reversal"), valued by the swing (rad/s)."""
    history = CommandHistory(None, 1e-3)
    for v in sequence:
        send(checker, history, v * np.eye(7)[4])
    assert checker.report.counts["reversal"] == reversals
    if reversals:
        assert checker.report.first["reversal"].value == pytest.approx(1.2)
        assert "joint 5" in checker.report.first["reversal"].detail


def test_the_whole_tick_cpu_line_fails_from_its_fraction_of_the_ticks(tool_robot) -> None:
    """The line holds while fewer than tick_cpu_fraction_max (0.1 %) of the valid ticks take over tick_cpu_max
    (1 ms) of CPU: 1 of 2000 holds, 2 of 2000 fail; the table's row per robot and strategy counts them."""
    rep = FuzzReport(FuzzConfig())
    checker = TickChecker(tool_robot, rep.config, rep)
    for k in range(2000):
        rep.count_tick(WHERE)
        checker.tick_cpu(2e-3 if k == 7 else 1e-4, WHERE, {}, lambda: "slow")
    assert rep.counts["tick_cpu"] == 1 and rep.failures() == []
    checker.tick_cpu(5e-3, replace(WHERE, tick=9), {}, lambda: "slower")
    assert len(rep.failures()) == 1 and "2 violations (0.100% of 2000 ticks)" in rep.failures()[0]
    assert rep.worst["tick_cpu"].detail == "slower" and rep.first["tick_cpu"].detail == "slow"
    group = rep.tick_cpu_groups()["lwr4p qp"]
    assert (group["n"], group["over_max"], group["max"], group["p50"]) == (2001, 2, 5e-3, 1e-4)
    assert "| lwr4p qp | 100 |" in rep.table()


@pytest.mark.jit
def test_kernel_watch_names_each_signature_added_after_its_baseline(monkeypatch) -> None:
    """A kernel of a qpnso module called with a new type after the baseline is one signature added, named with
    its types; a type it has is none; a kernel of a module attribute set after the baseline is found by the full
    walk only; the walk finds qpnso's own kernels (store_interval, issue 31's item 4)."""
    import qpnso.control.memory
    from qpnso.lab.fuzz.kernels import qpnso_dispatchers

    kernel = numba.njit(lambda x: x + 1)
    monkeypatch.setattr(qpnso.control.memory, "_test_kernel", kernel, raising=False)
    watch = KernelWatch()
    assert "qpnso.control.memory.store_interval" in qpnso_dispatchers() and watch.added() == []
    kernel(1)
    assert watch.added() == ["qpnso.control.memory._test_kernel(int64)"]
    kernel(2)
    assert watch.added() == []
    kernel(1.5)
    assert watch.added() == ["qpnso.control.memory._test_kernel(float64)"]
    late = numba.njit(lambda x: x - 1)
    monkeypatch.setattr(qpnso.control.memory, "_late_kernel", late, raising=False)
    late(1)
    assert watch.added() == [] and watch.added(full=True) == ["qpnso.control.memory._late_kernel(int64)"]


@pytest.mark.jit
def test_a_kernel_compiled_in_a_tick_is_reproduced_only_by_fresh_processes(monkeypatch) -> None:
    """A kernel compiled inside a tick's solve, once per process (tests/fuzz_faults.py, as issue 31's item 4):
    the compile line counts it and the slowest whole tick names it, in this process and in a fresh one.  Replayed
    on the same controllers it does not happen again (the old criterion: not reproduced); replayed in a fresh
    process it does, so the solver-time line fails."""
    config = FuzzConfig(seed=2, ticks=80, episode_ticks=80, strategies=("qp",), p_probe_burst=0, replays=1, **LWR_1MS)
    with monkeypatch.context() as patch:
        fuzz_faults.compile_in_a_solve(functools.partial(patch.setattr, raising=False))
        here = run_fuzz(config)
    fresh = run_fuzz(replace(config, workers=1, setup="fuzz_faults:compile_in_a_solve_once"))
    added = [f"{fuzz_faults.KERNEL}(float64)"]
    for report in (here, fresh):
        compiled = report.first["compile"]
        assert report.counts["compile"] == 1 and compiled.detail == f"added {added[0]}"
        assert report.kernels_added == {added[0]: 1} and f"(1×, at most once a process): {added[0]}" in report.table()
        assert (
            report.worst["tick_cpu"].where.tick == compiled.where.tick and added[0] in report.worst["tick_cpu"].detail
        )
        assert report.counts["solve_time"] >= 1 and report.replayed_episodes == 1
    assert here.counts["solve_time_reproduced"] == 0 and [r["kernels"] for r in here.worst_tick_replays] == [[]]
    assert fresh.counts["solve_time_reproduced"] == 1 and fresh.replays_fresh and fresh.processes == 1
    assert [r["kernels"] for r in fresh.worst_tick_replays] == [added]
    assert fresh.worst_tick_replays[0]["tick_cpu"] > 1e-3
    assert any("solver time that every one of 1 replays" in line for line in fresh.failures())


@pytest.mark.parametrize("fault", ["step", "reversal"])
def test_an_injected_command_step_or_reversal_is_counted_in_the_closed_loop(monkeypatch, fault: str) -> None:
    """The controller's command replaced on chosen ticks of a held start (tests/fuzz_faults.py): a step of 1.5 ×
    ddq_max·dt on joint 3 at tick 20 is two violations of the bound (the step, then the return to the controller's
    own command) and no reversal; 0.8 then -0.8 rad/s on joint 3 at ticks 20 and 21 is one reversal, at tick 21.
    A controller without ddq_max (before issue 31's bound) is given one through its class, 10 rad/s² (0.01 rad/s a
    tick): its own commands in this held start change by about 3e-5 rad/s a tick (self-motion at up to 0.2 rad/s),
    so only the injected steps can break it."""
    patch = functools.partial(monkeypatch.setattr, raising=False)
    if not HAS_ACCEL_BOUND:
        patch(Controller, "ddq_max", np.full(7, 10.0))

    def stepped(dq: np.ndarray, previous: np.ndarray, ctrl: Controller) -> np.ndarray:
        out = previous.copy()
        out[2] += 1.5 * ctrl.ddq_max[2] * ctrl.config.dt  # type: ignore[attr-defined]
        return out

    def joint_3_at(v: float):
        def set_joint(dq: np.ndarray, previous: np.ndarray, ctrl: Controller) -> np.ndarray:
            dq[2] = v
            return dq

        return set_joint

    fuzz_faults.command_changed(
        patch, {20: stepped} if fault == "step" else {20: joint_3_at(0.8), 21: joint_3_at(-0.8)}
    )
    report = run_fuzz(FuzzConfig(seed=4, ticks=40, episode_ticks=40, strategies=("qp",), p_probe_burst=0, **LWR_1MS))
    if fault == "step":
        assert report.counts["accel_bound"] == 2 and report.first["accel_bound"].where.tick == 20
        assert report.first["accel_bound"].value == pytest.approx(1.5, rel=1e-6)
        assert report.counts["reversal"] == 0
    else:
        assert report.counts["reversal"] == 1 and report.first["reversal"].where.tick == 21
        assert report.first["reversal"].value == pytest.approx(1.6)


def test_the_default_mix_runs_every_robot_dt_and_strategy_in_fresh_processes() -> None:
    """The default robots (the Panda when example-robot-data is installed, else skipped and said so), dt 1 and
    4 ms and every strategy, 20-tick episodes in two shards, each in a fresh process: every combination ran,
    each tick's CPU time is in its robot and strategy's row, the examples name their robot and dt."""
    config = FuzzConfig(seed=6, ticks=36 * 20, episode_ticks=20, workers=2, shard_ticks=360, replays=0)
    report = run_fuzz(config)
    robots = ("lwr4p", "iiwa14", "panda") if HAS_PANDA else ("lwr4p", "iiwa14")
    assert report.config.robots == robots and ("panda" in report.skipped_robots) == (not HAS_PANDA)
    assert report.ticks == config.ticks and report.processes == 2 and report.completed
    assert set(report.by_setting) == {f"{r}, dt {ms} ms" for r in robots for ms in (1, 4)}
    groups = report.tick_cpu_groups()
    assert set(groups) == {f"{r} {s}" for r in robots for s in STRATEGIES}
    assert sum(g["n"] for g in groups.values()) == report.ticks == sum(v["ticks"] for v in report.by_strategy.values())
    assert all(ex.where.robot in robots and ex.where.dt in (1e-3, 4e-3) for ex in report.worst.values())
    assert ("SKIPPED robot panda: " in report.table()) == (not HAS_PANDA)
    json.dumps(report.to_dict())


def test_a_panda_without_example_robot_data_is_skipped_and_said_so(monkeypatch, capsys) -> None:
    """Without example-robot-data (made so here) the Panda is left out of the run with a line saying why; asked
    for alone it is refused by name (the command line: one line, exit 2)."""
    from qpnso.cli import main

    monkeypatch.setattr(qpnso.model.robot, "_panda_urdf", lambda: None)
    report = run_fuzz(
        FuzzConfig(ticks=20, episode_ticks=20, strategies=("qp",), robots=("lwr4p", "panda"), dts=(1e-3,))
    )
    assert report.config.robots == ("lwr4p",) and set(report.by_setting) == {"lwr4p, dt 1 ms"}
    assert "example-robot-data" in report.skipped_robots["panda"]
    assert "SKIPPED robot panda: robot 'panda' needs the optional package example-robot-data" in report.table()
    with pytest.raises(qpnso.RobotNotFoundError, match="no robot to fuzz"):
        run_fuzz(FuzzConfig(ticks=20, robots=("panda",)))
    assert main(["bench", "fuzz", "-n", "20", "--robot", "panda", "--workers", "0"]) == 2
    assert capsys.readouterr().err.count("\n") == 1
