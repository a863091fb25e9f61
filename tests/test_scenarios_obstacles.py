"""Obstacles in scenario files and in the runs: the room's keep-out volumes reach the controller (unless ignored),
every simulated tick's clearance is measured with coal, the offline solve names its first OBSTACLE tick, and the
bench has a held qp row with four obstacles."""

from __future__ import annotations

import importlib.util
import json

import numpy as np
import pinocchio as pin
import pytest
from conftest import SOURCE_TREE

import qpnso
from qpnso.cli import main
from qpnso.cli.commands import comparison_table
from qpnso.control import trajectory as tr
from qpnso.control.config import ControllerConfig, Status
from qpnso.control.offline import config_values, data_row, solve_trajectory
from qpnso.errors import ConfigError
from qpnso.lab.benchmark import obstacles_around
from qpnso.lab.metrics import clearance_summary
from qpnso.lab.scenarios import SCENARIO_DIR, load_scenario, simulate_scenario
from qpnso.model.collision import clearances, link_capsules
from qpnso.model.obstacles import Box, Sphere

MICROSCOPE_S = 2.0
"""s of the microscope path simulated."""
POSE = pin.SE3(pin.rpy.rpyToMatrix(np.pi, np.radians(30), np.pi), np.array([0.65, 0.0, 0.5]))
SPHERE = Sphere(center=(0.65, 0.15, 0.5), radius=0.02)
"""On the tool's path (:func:`sideways`), 0.15 m from its start: the hand must run into it."""
SPHERE_TABLE = '[[obstacles]]\ntype = "sphere"\ncenter = [0.65, 0.15, 0.5]\nradius = 0.02\n'
"""The same as a TOML table."""


def scale(seconds: float) -> float:
    """The ``duration_scale`` that runs the first ``seconds`` of the microscope scenario's path."""
    return seconds / load_scenario("microscope").path().duration


def sideways() -> tr.Trajectory:
    """The tool moved 0.2 m along world y in 1 s from :data:`POSE`, orientation held."""
    p0 = POSE.translation
    targets = np.array([p0, p0 + [0.0, 0.2, 0.0]])
    return tr.point_to_point(targets, duration_per_move=1.0, dwell=0.0, lift=0.0, orientation=POSE.rotation)


# ------------------------------------------------------------------ scenario files
def test_scenario_file_obstacles_load_and_reach_the_controller(tmp_path) -> None:
    sc = load_scenario("microscope")
    assert sc.obstacles == (Box(center=(0.1629, -0.3638, 0.5534), half_extents=(0.125, 0.125, 0.15)),)
    assert "obstacles" not in sc.controller
    assert load_scenario("B").obstacles == ()
    # a scenario file is a config file: its top-level [[obstacles]] go to the controller with [controller]
    assert ControllerConfig.from_dict(config_values(SCENARIO_DIR / "microscope.toml")).obstacles == sc.obstacles
    text = (SCENARIO_DIR / "B.toml").read_text() + "\n" + SPHERE_TABLE.replace("0.65, 0.15, 0.5", "0, 0, 1")
    mine = tmp_path / "mine.toml"
    mine.write_text(text)
    assert load_scenario(mine).obstacles == (Sphere(center=(0.0, 0.0, 1.0), radius=0.02),)
    inside = tmp_path / "inside.toml"
    inside.write_text(text.replace("[[obstacles]]", "[[controller.obstacles]]"))
    with pytest.raises(ConfigError, match="top level"):
        load_scenario(inside)
    both = tmp_path / "both.toml"
    both.write_text(inside.read_text() + "\n" + SPHERE_TABLE)
    with pytest.raises(ConfigError, match="both at the top level and under"):
        config_values(both)


def test_microscope_box_is_the_stated_construction() -> None:
    """examples/place_microscope.py regenerates the file's box; the start is clear by more than the margin and
    the upper arm reaches into the box at the ROM's upper edge (coal)."""
    path = SOURCE_TREE / "examples" / "place_microscope.py"
    spec = importlib.util.spec_from_file_location("place_microscope", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    sc = load_scenario("microscope")
    assert module.place_microscope("B") == sc.obstacles[0]
    robot = qpnso.load_robot(sc.robot)
    upper = link_capsules(robot).names.index(module.UPPER_ARM)
    b = load_scenario("B")
    start = clearances(robot, b.start(robot), sc.obstacles)
    edge = clearances(robot, module.edge_configuration(robot, b), sc.obstacles)
    assert start.min() > ControllerConfig().obstacle_margin
    assert edge[upper, 0] == pytest.approx(-module.OVERLAP, abs=1e-4)  # (the centre is rounded to 0.1 mm)


# ------------------------------------------------------------------ simulations
@pytest.fixture(scope="module")
def microscope_run():
    return simulate_scenario("microscope", "qp", scale(MICROSCOPE_S))


def test_simulation_records_coal_clearance_at_the_recorded_configurations(microscope_run) -> None:
    a, m = microscope_run.arrays, microscope_run.summary
    sc = load_scenario("microscope")
    robot = qpnso.load_robot(sc.robot)
    names = link_capsules(robot).names
    coal = np.array([clearances(robot, q, sc.obstacles) for q in a["q"]])
    np.testing.assert_allclose(a["link_clearance"], coal, atol=1e-12)
    k, link, ob = np.unravel_index(np.argmin(coal), coal.shape)
    assert m["clearance_min_m"] == pytest.approx(coal.min(), abs=1e-12)
    assert (m["clearance_min_link"], m["clearance_min_obstacle"], m["clearance_min_tick"]) == (names[link], ob, k)
    assert m["penetration_ticks"] == np.count_nonzero((coal < 0).any(axis=(1, 2)))
    assert m["obstacle_ticks"] == np.count_nonzero(a["status"].astype(np.int64) & Status.OBSTACLE.value)
    assert (m["room_obstacles"], m["controller_obstacles"]) == (1, 1)
    # the controller's own least clearance (its distance kernels) agrees with coal's at every tick
    np.testing.assert_allclose(a["controller_clearance"], coal.min(axis=(1, 2)), atol=1e-6)
    assert m["clearance_min_m"] > ControllerConfig().obstacle_margin - 1e-3  # it kept its margin


def test_without_obstacles_nothing_is_measured() -> None:
    result = simulate_scenario("B", "qp", 0.003)
    assert "link_clearance" not in result.arrays
    assert not {"clearance_min_m", "penetration_ticks", "obstacle_ticks", "room_obstacles"} & set(result.summary)


def test_ignore_obstacles_keeps_the_measurement_not_the_controller_rows(tmp_path, capsys) -> None:
    out = tmp_path / "run"
    argv = ["simulate", "--scenario", "microscope", "--duration-scale", str(scale(0.3)), "--out", str(out)]
    assert main(argv + ["--ignore-obstacles", "--no-plot", "--quiet"]) == 0
    assert "obstacles unknown to the controller" in capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    assert (summary["room_obstacles"], summary["controller_obstacles"]) == (1, 0)
    assert summary["obstacle_ticks"] == 0
    with np.load(out / "result.npz") as data:
        assert np.all(np.isinf(data["controller_clearance"]))  # no keep-out rows: the controller sees no obstacle
        assert summary["clearance_min_m"] == pytest.approx(data["link_clearance"].min(), abs=1e-12)


def test_comparison_table_has_clearance_columns_only_with_obstacles(microscope_run) -> None:
    rows = [("qp", microscope_run.summary)]
    with_room = comparison_table(rows, load_scenario("microscope"), " (note)")
    assert "clearance min (mm, coal)" in with_room and "(note)" in with_room
    assert f"{1000 * microscope_run.summary['clearance_min_m']:.1f} |" in with_room.splitlines()[-1]
    header = comparison_table(rows, load_scenario("B")).splitlines()[2]
    assert "clearance" not in header and header.count("|") == 11


def test_clearance_summary_by_hand() -> None:
    d = np.array([[[0.2], [0.1]], [[0.05], [-0.01]], [[-0.02], [0.3]]])  # 3 ticks, 2 links, 1 obstacle
    status = np.array([0, Status.OBSTACLE.value, Status.OBSTACLE.value | Status.TOOL_LIMITED.value])
    m = clearance_summary([0.0, 0.1, 0.2], d, ("a", "b"), status, Status.OBSTACLE.value)
    assert m == {
        "clearance_min_m": -0.02,
        "clearance_min_link": "a",
        "clearance_min_obstacle": 0,
        "clearance_min_tick": 2,
        "clearance_min_t_s": 0.2,
        "penetration_ticks": 2,
        "obstacle_ticks": 2,
    }
    with pytest.raises(qpnso.InputError):
        clearance_summary([0.0], np.zeros((1, 3, 1)), ("a", "b"))


# ------------------------------------------------------------------ offline solve
@pytest.fixture(scope="module")
def blocked_solve(lwr):
    return solve_trajectory(lwr, sideways(), config=ControllerConfig(obstacles=[SPHERE]))


def test_offline_solve_names_the_first_obstacle_tick(lwr, blocked_solve) -> None:
    a, first = blocked_solve.arrays, blocked_solve.first_obstacle
    flagged = np.flatnonzero(a["status"].astype(np.int64) & Status.OBSTACLE.value)
    assert first is not None and first.tick == flagged[0]
    assert first.t == pytest.approx(a["t"][first.tick])
    coal = clearances(lwr, a["q"][first.tick], [SPHERE])[:, 0]
    assert first.link == link_capsules(lwr).names[int(np.argmin(coal))] and first.obstacle == 0
    assert first.clearance == pytest.approx(coal.min(), abs=1e-6)
    assert first.link in first.message and first.data_row == data_row(sideways().t, first.t)
    s = blocked_solve.summary
    assert (s["first_obstacle_tick"], s["first_obstacle_link"], s["first_obstacle_obstacle"]) == (
        first.tick,
        first.link,
        0,
    )
    assert s["first_obstacle_clearance_m"] == first.clearance and s["first_obstacle_data_row"] == first.data_row
    assert s["result"] == "ok"  # the tool kept its path: an OBSTACLE tick does not fail the run


def test_cli_solve_prints_the_first_obstacle_tick(blocked_solve, tmp_path, capsys) -> None:
    csv = tmp_path / "sideways.csv"
    tr.write_csv(sideways(), csv)
    cfg = tmp_path / "room.toml"
    cfg.write_text(SPHERE_TABLE)  # (top-level settings)
    out, summary = tmp_path / "r.npz", tmp_path / "s.json"
    argv = ["solve", str(csv), "--config", str(cfg), "--out", str(out), "--summary", str(summary), "--quiet"]
    assert main(argv) == 0
    first = blocked_solve.first_obstacle
    assert f"obstacle: first OBSTACLE tick {first.tick} (t = {first.t:.6g} s" in capsys.readouterr().out
    assert json.loads(summary.read_text())["first_obstacle_link"] == first.link


def test_solve_without_obstacle_ticks_names_none(lwr) -> None:
    result = solve_trajectory(lwr, tr.hold(POSE, 0.05))
    assert result.first_obstacle is None and "first_obstacle_tick" not in result.summary


# ------------------------------------------------------------------ bench
def test_obstacles_around_are_inside_the_influence_and_clear_of_the_margin(lwr) -> None:
    q = lwr.sample_configuration()
    d = clearances(lwr, q, obstacles_around(lwr, q))
    cfg = ControllerConfig()
    assert d.min() > cfg.obstacle_margin
    assert np.all(d.min(axis=0) < cfg.obstacle_influence)  # each obstacle near some link: rows


def test_bench_tick_has_the_held_qp_row_with_four_obstacles(capsys) -> None:
    assert main(["bench", "tick", "-n", "20", "--strategies", "qp"]) == 0
    lines = capsys.readouterr().out.splitlines()
    held = next(i for i, x in enumerate(lines) if x.startswith("| step, strategy qp, tool held |"))
    row = lines[held + 1]
    assert row.startswith("| step, strategy qp, tool held, 4 obstacles |")
    rows = int(row.split("tool held, ")[-1].split(" keep-out rows")[0])
    assert rows > 0
