"""Offline solve and hands-on simulation end to end, and their error paths."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

import qpnso
from qpnso.control import trajectory as tr
from qpnso.control.offline import RESULT_KEYS, initial_configuration, load_config, solve_trajectory
from qpnso.lab.scenarios import load_scenario, simulate_scenario

POSE = pin.SE3(pin.rpy.rpyToMatrix(np.pi, np.radians(30), np.pi), np.array([0.65, 0.0, 0.5]))


@pytest.fixture(scope="module")
def short_guidance() -> tr.Trajectory:
    path = tr.guidance_path(POSE, size=0.06, speed=0.05)
    return path.window(path.t[0], path.t[0] + 1.5)


def test_initial_configuration_reaches_the_pose_with_the_elbow_up(lwr) -> None:
    q = initial_configuration(lwr, POSE)
    reached = lwr.tool_pose(q)
    assert np.linalg.norm(reached.translation - POSE.translation) < 1e-9
    assert np.linalg.norm(pin.log3(reached.rotation @ POSE.rotation.T)) < 1e-9
    assert abs(qpnso.arm_angle(lwr, q)) < 1e-9
    assert np.all(q > lwr.q_min) and np.all(q < lwr.q_max)


def test_solve_tracks_the_path_and_records_every_key(lwr, short_guidance) -> None:
    result = solve_trajectory(lwr, short_guidance)
    a = result.arrays
    assert set(RESULT_KEYS) <= set(a)
    n = len(a["t"])
    assert n == int(round(short_guidance.duration / 1e-3)) + 1
    # level 1 tracks the reference: errors measured with Pinocchio FK at every tick
    fk = np.array([lwr.tool_pose(q).translation for q in a["q"]])
    ref = np.array([short_guidance.sample(t)[0] for t in a["t"]])
    assert np.abs(fk - ref).max() < 1e-5
    assert result.summary["tool_position_error_max_m"] < 1e-5
    assert np.all(a["q"] >= lwr.q_min) and np.all(a["q"] <= lwr.q_max)
    assert result.summary["mass_mean_kg"] > 0 and result.summary["friction_force_mean_N"] > 0
    # what the recorder computes for the whole run at its end, against Pinocchio and the cost, tick by tick
    poses = [lwr.tool_pose(q) for q in a["q"]]
    np.testing.assert_allclose(a["tool_position"], [x.translation for x in poses], atol=1e-12)
    rot = [np.linalg.norm(pin.log3(short_guidance.sample(t)[1] @ x.rotation.T)) for t, x in zip(a["t"], poses)]
    np.testing.assert_allclose(a["tool_rotation_error"], rot, atol=1e-12)
    np.testing.assert_allclose(a["tool_position_error"], np.linalg.norm(fk - ref, axis=1), atol=1e-12)
    cost = qpnso.CostModel(lwr)
    some = a["q"][::97]
    mass = [1.0 / np.linalg.eigvalsh(cost.lambda_inv(q)[0])[0] for q in some]
    np.testing.assert_allclose(a["mass"][::97], mass, rtol=1e-12)
    np.testing.assert_allclose(a["friction_force"][::97], [np.sqrt(cost.terms(q)["friction_force"]) for q in some])


def test_solve_result_file_is_written_atomically(lwr, short_guidance, tmp_path) -> None:
    result = solve_trajectory(lwr, short_guidance.window(0, 0.1))
    path = result.save(tmp_path / "r.npz")
    with np.load(path) as data:
        assert set(RESULT_KEYS) <= set(data.files)
    assert [p.name for p in tmp_path.iterdir()] == ["r.npz"]


def test_q0_far_from_the_first_pose_is_refused(lwr, short_guidance) -> None:
    with pytest.raises(qpnso.UnreachableError, match="mm from the trajectory"):
        solve_trajectory(lwr, short_guidance, q0=np.zeros(7) + 0.3)


def test_unreachable_first_pose(lwr) -> None:
    far = tr.hold(pin.SE3(np.eye(3), np.array([2.0, 0, 0.5])), 0.1)
    with pytest.raises(qpnso.UnreachableError):
        solve_trajectory(lwr, far)


def test_config_file_and_overrides(tmp_path) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text('[controller]\nstrategy = "rom"\nrom_half_width_deg = 20\n[controller.weights]\nmass = 0.2\n')
    c = load_config(cfg, {"strategy": "fixed", "dt": None})
    assert c.strategy == "fixed" and c.rom_half_width_deg == 20 and c.weights.mass == 0.2
    bad = tmp_path / "bad.toml"
    bad.write_text("[controller]\nrom_width = 3\n")
    with pytest.raises(qpnso.ConfigError, match="rom_width"):
        load_config(bad)
    broken = tmp_path / "broken.toml"
    broken.write_text("[controller\n")
    with pytest.raises(qpnso.ConfigError, match="not valid TOML"):
        load_config(broken)


@pytest.mark.parametrize("name", ["A", "B"])
def test_scenarios_start_as_described(name) -> None:
    sc = load_scenario(name)
    robot = qpnso.load_robot(sc.robot)
    q0 = sc.start(robot)
    assert np.isclose(np.degrees(qpnso.arm_angle(robot, q0)), sc.ns0_deg, atol=1e-6)
    iv = qpnso.continuity_interval(robot, q0)
    ns = qpnso.arm_angle(robot, q0)
    room = np.degrees(min(ns - iv.lo, iv.hi - ns))
    if name == "A":
        assert room > 90  # far from the limits
    else:
        assert 10 < room < 30  # close to a limit, but outside the safety margin


def test_unknown_scenario() -> None:
    with pytest.raises(qpnso.ConfigError, match="unknown scenario 'C'"):
        load_scenario("C")


def test_simulation_keeps_the_elbow_in_rom_and_tracks_the_hand() -> None:
    """Scenario B, 2 s of hands-on guidance with the QP strategy."""
    arrays = simulate_scenario("B", "qp", duration_scale=2.0 / 36.0).arrays
    ns, lo, hi = arrays["ns"], arrays["rom_lo"], arrays["rom_hi"]
    assert np.all(ns >= lo - np.radians(0.5)) and np.all(ns <= hi + np.radians(0.5))
    margin = np.radians(10)
    assert np.all(ns - arrays["interval_lo"] >= margin - np.radians(0.5))
    assert np.all(arrays["interval_hi"] - ns >= margin - np.radians(0.5))
    err = np.linalg.norm(arrays["tool_position"] - arrays["ref_position"], axis=1)
    assert err.max() < 0.03  # the hand is a spring: it lags by millimetres to centimetres
    assert np.all(np.isfinite(arrays["q"]))


def test_scenario_file_missing_key_is_named(tmp_path) -> None:
    bad = tmp_path / "s.toml"
    bad.write_text('[scenario]\nname = "X"\n[start]\ncenter = [0.5, 0, 0.4]\n')
    with pytest.raises(qpnso.ConfigError, match="missing key 'rpy_deg'"):
        load_scenario(bad)


def test_simulation_settings_override_the_scenario_and_strategy_wins() -> None:
    run = simulate_scenario(
        "B", "damped", duration_scale=0.05 / 36.0, settings={"rom_half_width_deg": 30.0, "strategy": "qp"}
    )
    # ROM_t's upper end is ns0 + 30° (the interval's end, minus the margin, is farther)
    assert np.isclose(np.degrees(run.arrays["rom_hi"][0]), -90.0 + 30.0, atol=1e-6)
    assert np.all(run.arrays["stiffness"] == 0.0)  # damped applies no stiffness: strategy argument won


def test_diverging_simulation_is_an_error_not_nan(monkeypatch) -> None:
    import qpnso.lab.simulation as sim
    from qpnso.lab.plant import Plant

    def blow_up(plant, tau, wrench=None):
        plant.data.qvel[:] = np.nan

    monkeypatch.setattr(Plant, "step", blow_up)
    with pytest.raises(sim.SimulationError, match="diverged at t = 0.000 s"):
        simulate_scenario("A", "qp", duration_scale=0.01)


# ------------------------------------------------------------------- issue 13, items 7 and 12
def test_solve_summary_has_a_verdict_and_counts_slow_ticks(lwr, short_guidance) -> None:
    result = solve_trajectory(lwr, short_guidance.window(0, 0.1))
    s = result.summary
    assert result.ok and result.failure == "" and s["result"] == "ok"
    assert s["tool_tolerance_m"] == 1e-3 and s["tool_tolerance_deg"] == pytest.approx(1.0)
    ticks = result.arrays["tick_time"]
    assert s["slow_ticks"] == np.count_nonzero(ticks > 1e-3)
    assert s["tick_time_max_ms"] == pytest.approx(1000 * ticks.max())
    with pytest.raises(qpnso.InputError, match="tool_tolerance_m"):
        solve_trajectory(lwr, short_guidance.window(0, 0.1), tool_tolerance_m=0.0)


def test_summarize_run_counts_ticks_longer_than_the_period() -> None:
    from qpnso.lab.metrics import summarize_run

    t = np.arange(5) * 1e-3
    s = summarize_run({"t": t, "tick_time": np.array([1e-4, 2e-3, 1e-3, 5e-3, 9e-4])}, dt=1e-3)
    assert s["slow_ticks"] == 2.0 and s["tick_time_max_ms"] == pytest.approx(5.0)
    assert summarize_run({"t": 2 * t, "tick_time": np.full(5, 1.5e-3)})["slow_ticks"] == 0.0  # dt from t


def test_tool_error_check_maps_ticks_to_csv_rows() -> None:
    """Ticks every 1 ms from t0 = 0.5 s, rows every 10 ms: the row is the last one at or before the tick."""
    from qpnso.control.offline import data_row, tool_error_check

    rows = 0.5 + 0.01 * np.arange(11)
    t = 0.5 + 1e-3 * np.arange(101)
    pos, rot = np.full(101, 1e-4), np.zeros(101)
    ok, line = tool_error_check({"t": t, "tool_position_error": pos, "tool_rotation_error": rot}, rows)
    assert ok["result"] == "ok" and line == ""
    pos[23], rot[60] = 2e-3, np.radians(3)  # 0.523 s: data row 3 (t = 0.52 s); 0.56 s: data row 7 exactly
    out, line = tool_error_check({"t": t, "tool_position_error": pos, "tool_rotation_error": rot}, rows)
    assert out["result"] == "failed" and out["first_failed_tick"] == 23
    assert out["first_failed_data_row"] == 3 and out["first_failed_data_row_t_s"] == pytest.approx(0.52)
    assert out["worst_position_error_m"] == 2e-3 and out["worst_position_error_data_row"] == 3
    assert out["worst_rotation_error_deg"] == pytest.approx(3) and out["worst_rotation_error_data_row"] == 7
    assert "data row 3 (t = 0.52 s" in line and "position error 2 mm > 1 mm" in line and "np." not in line
    assert data_row(rows, 0.5 + 20 * 1e-3) == 3  # 0.52000000000000002 vs 0.52: round-off does not pick row 2
    assert data_row(rows, rows[-1] + 1) == 11


def test_six_dof_arm_is_refused_by_the_api(tmp_path) -> None:
    import re

    from qpnso.model.robot import MODELS_DIR

    text = (MODELS_DIR / "lwr4p.urdf").read_text()
    text = re.sub(r'\s*<joint name="joint_7".*?</joint>', "", text, flags=re.S)
    text = re.sub(r'\s*<link name="link_7">.*?</link>', "", text, flags=re.S)
    (tmp_path / "arm6.urdf").write_text(text.replace('<parent link="link_7"/>', '<parent link="link_6"/>'))
    robot = qpnso.load_robot(tmp_path / "arm6.urdf")
    assert robot.nq == 6
    message = r"qpnso needs a 7-DOF arm \(one redundant degree of freedom for a 6-D tool task\); arm6 has 6 joints"
    with pytest.raises(qpnso.ModelError, match=message):
        robot.require_redundant_arm()
    with pytest.raises(qpnso.ModelError, match=message):
        solve_trajectory(robot, tr.hold(POSE, 0.05))
    qpnso.load_robot("lwr4p").require_redundant_arm()  # a 7-DOF arm passes


def test_results_honour_the_umask(tmp_path) -> None:
    """Item 12: npz/json/png were written 0600 (mkstemp) while CSVs got 0644."""
    import os
    import stat

    from qpnso.cli.common import write_json
    from qpnso.control.offline import RunResult

    old = os.umask(0o022)
    try:
        npz = RunResult({"t": np.zeros(2)}).save(tmp_path / "r.npz")
        write_json(str(tmp_path / "s.json"), {"a": 1})
        os.umask(0o027)
        RunResult({"t": np.zeros(2)}).save(tmp_path / "g.npz")
    finally:
        os.umask(old)
    mode = lambda p: stat.S_IMODE(p.stat().st_mode)  # noqa: E731
    assert mode(npz) == 0o644 and mode(tmp_path / "s.json") == 0o644 and mode(tmp_path / "g.npz") == 0o640
    os.chmod(npz, 0o600)  # an existing file keeps its mode, as with open(path, "w")
    RunResult({"t": np.ones(2)}).save(npz)
    assert mode(npz) == 0o600
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.npz", "r.npz", "s.json"]


def test_rotation_angle_is_the_norm_of_log3() -> None:
    """``rotation_angle`` (the recorder's rotation error) against Pinocchio's ``log3`` on random rotations, tiny
    ones (1e-9 rad) and ones near π; an empty stack."""
    from qpnso.control.offline import rotation_angle

    rng = np.random.default_rng(2)
    axes = rng.normal(size=(60, 3))
    axes /= np.linalg.norm(axes, axis=1)[:, None]
    angles = np.concatenate([rng.uniform(0, np.pi, 20), np.full(20, 1e-9), np.pi - np.logspace(-8, -2, 20)])
    R = np.array([pin.exp3(a * u) for a, u in zip(angles, axes)])
    np.testing.assert_allclose(rotation_angle(R), [np.linalg.norm(pin.log3(r)) for r in R], atol=1e-9)
    np.testing.assert_allclose(rotation_angle(R), angles, atol=1e-9)
    assert rotation_angle(np.zeros((0, 3, 3))).shape == (0,)
