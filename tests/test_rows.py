"""The constraint-row contract (qpnso/control/rows): the velocity damper by hand, and a row kind defined here
only, in one class as a user would add one — a floor under the elbow — checked against Pinocchio (its value
and exact gradient in the tick's state), in closed loop (the elbow stops on the floor; without the row it
goes through), on the line fast path (a hard row folds into the segment: no cascade), and its errors."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin
import pytest
from conftest import kernel_signatures

import qpnso
from qpnso.control.config import ControllerConfig, Status
from qpnso.control.controller import Controller
from qpnso.control.rows import RowKind
from qpnso.control.rows.damper import damper

Q1 = np.radians([10, 40, -10, -70, 20, 50, 0])
DT = 1e-3


@pytest.fixture(scope="module")
def robot() -> qpnso.Robot:
    return qpnso.load_robot("lwr4p", tool_offset=[0.0, 0.0, 0.1])


@dataclass(frozen=True)
class ElbowFloor(RowKind):
    """Test-only row kind: the elbow (joint 4's origin) at least ``z_min`` m above the base, ``h = z_elbow``."""

    z_min: float = 0.0

    def values(self, model, robot):
        return model.frame_placement(robot.model.getFrameId("joint_4")).p[2]

    def bounds(self, robot):
        return np.array([self.z_min]), np.array([np.inf])


def elbow_z(robot: qpnso.Robot, q: np.ndarray) -> float:
    data = robot.model.createData()
    pin.forwardKinematics(robot.model, data, q)
    return float(data.oMi[robot.model.getJointId("joint_4")].translation[2])


def test_the_damper_by_hand() -> None:
    """Inside: ``γ(lo − h) ≤ ḣ ≤ γ(hi − h)``; outside: back at rate γ, at most ``recovery``."""
    assert damper(0.5, 0.0, 1.0, 20.0, 0.2) == (pytest.approx(-10.0), pytest.approx(10.0))
    assert damper(-0.001, 0.0, 1.0, 20.0, 0.2) == (pytest.approx(0.02), pytest.approx(20.02))  # below: back
    assert damper(-0.1, 0.0, 1.0, 20.0, 0.2) == (0.2, pytest.approx(22.0))  # far below: at most 0.2
    assert damper(1.1, 0.0, 1.0, 20.0, 0.2) == (pytest.approx(-22.0), -0.2)
    assert damper(0.0, 0.0, np.inf, 20.0, 0.2) == (0.0, np.inf)
    from qpnso.control.config import ControllerConfig
    from qpnso.control.rows import RowKind

    assert RowKind().gain == ControllerConfig().joint_limit_gain == 20.0  # one γ by default (docs/method.md §7.1)


def test_a_row_kind_s_value_and_gradient_are_in_the_state(robot) -> None:
    """The one CasADi call evaluates ``h(q)`` and its exact gradient: Pinocchio's elbow height, and its
    central differences."""
    ctrl = Controller(robot, ControllerConfig(), rows=[ElbowFloor(z_min=0.1)])
    rng = np.random.default_rng(0)
    for _ in range(5):
        q = robot.random_q(rng, margin=0.2)
        s = ctrl.evaluate.record(q, np.zeros(7), np.zeros(6), np.zeros(6))[0]
        assert s["rows"][0] == pytest.approx(elbow_z(robot, q), abs=1e-12)
        h = 1e-6
        fd = [(elbow_z(robot, q + h * e) - elbow_z(robot, q - h * e)) / (2 * h) for e in np.eye(7)]
        np.testing.assert_allclose(s["rows_gradient"][0], fd, rtol=0, atol=1e-8)


def run(robot, rows, ticks: int = 1500) -> tuple[list[float], Controller, list[Status]]:
    """Elbow-up with its target at 180° (elbow down) from Q1, tool held: the elbow sinks."""
    ctrl = Controller(robot, ControllerConfig(strategy="elbow-up", elbow_up_angle_deg=180.0), rows=rows)
    ctrl.reset(Q1)
    q, heights, statuses = Q1.copy(), [], []
    for _ in range(ticks):
        cmd = ctrl.step(q)
        q = cmd.q_des
        heights.append(elbow_z(robot, q))
        statuses.append(cmd.status)
    return heights, ctrl, statuses


def test_a_hard_row_stops_the_elbow_on_its_floor(robot, monkeypatch) -> None:
    z0 = elbow_z(robot, Q1)
    free, _, _ = run(robot, [])
    assert min(free) < z0 - 0.05  # without the row the elbow sinks by more than 5 cm
    floor = z0 - 0.02
    kind = ElbowFloor(z_min=floor)
    ctrl = Controller(robot, ControllerConfig(strategy="elbow-up", elbow_up_angle_deg=180.0), rows=[kind])
    calls = {"cascade": 0}
    original = ctrl.qp._solve_problem_levels

    def cascade(*args):
        calls["cascade"] += 1
        return original(*args)

    monkeypatch.setattr(ctrl.qp, "_solve_problem_levels", cascade)
    ctrl.reset(Q1)
    q, heights, limited = Q1.copy(), [], 0
    for _ in range(1500):
        cmd = ctrl.step(q)
        assert cmd.ok and cmd.tool_error[0] < 1e-6
        limited += bool(cmd.status & Status.TOOL_LIMITED)  # (the self-motion braking at ddq_max: a few ticks)
        q = cmd.q_des
        heights.append(elbow_z(robot, q))
    assert limited <= 15  # (at the whole acceleration bound, 188 ticks and 1.3 mm: rows.braking.BRAKING_SHARE)
    assert min(heights) >= floor - 1e-6  # the damper: never through the floor (first order, γ·dt ≤ 1)
    assert heights[-1] == pytest.approx(floor, abs=1e-4)  # and resting on it
    assert calls["cascade"] <= limited  # the hard row folded into the line fast path's segment (but where it binds)
    tool = robot.tool_pose(Q1)
    now = robot.tool_pose(q)
    assert np.linalg.norm(now.translation - tool.translation) < 1e-5  # the tool held


def test_a_soft_row_is_level_two_s(robot) -> None:
    """The same floor, soft: a level-2 row of the problem (its slack would let the tool win), which still
    holds the elbow within its slack."""
    z0 = elbow_z(robot, Q1)
    heights, ctrl, _ = run(robot, [ElbowFloor(z_min=z0 - 0.02, soft=True)])
    assert min(heights) >= z0 - 0.02 - 1e-3
    p = ctrl.records.problem[0]
    assert p["n_hard"] == 0 and p["n_soft"] == 1


@pytest.mark.parametrize(
    "kind, words",
    [
        (ElbowFloor(gain=2000.0), "gain"),
        (ElbowFloor(gain=0.0), "gain"),
        (ElbowFloor(z_min=np.nan), "bounds"),
        ("floor", "not a RowKind"),
    ],
)
def test_a_bad_row_kind_is_refused_naming_it(robot, kind, words: str) -> None:
    with pytest.raises(qpnso.ConfigError, match=words):
        Controller(robot, ControllerConfig(), rows=[kind])


def test_no_kernel_loads_in_a_tick_with_a_row_kind(robot) -> None:
    """A controller with a row kind (another record layout: its kernels are other signatures) compiles or
    loads them all in its constructor: none in a tick, held, moving, with the row binding."""
    kernel_signatures()  # every module imported first
    ctrl = Controller(robot, ControllerConfig(), rows=[ElbowFloor(z_min=elbow_z(robot, Q1) - 1e-3)])
    before = kernel_signatures()
    ctrl.reset(Q1)
    q = Q1.copy()
    for k in range(50):
        q = ctrl.step(q, tool_twist=[0.0, 0.0, -0.05, 0.0, 0.0, 0.0] if k > 10 else None).q_des
    after = kernel_signatures()
    assert {k: (before.get(k), n) for k, n in after.items() if n != before.get(k)} == {}


def test_two_equal_row_kinds_are_two_rows(robot) -> None:
    """Two equal kinds (frozen dataclasses compare equal) are two rows each with room in the records."""
    z = elbow_z(robot, Q1) - 0.05
    ctrl = Controller(robot, ControllerConfig(), rows=[ElbowFloor(z_min=z), ElbowFloor(z_min=z)])
    ctrl.reset(Q1)
    assert ctrl.step(Q1).ok
    p = ctrl.records.problem[0]
    assert p["n_hard"] == 2 and p["hard_C"].shape[0] == 2
    np.testing.assert_array_equal(p["hard_C"][0], p["hard_C"][1])


def test_the_qp_strategy_keeps_its_elbow_row_beside_a_soft_row_kind(robot) -> None:
    """The ``qp`` strategy with a soft row kind: level 2 has two soft rows, the kind's (the elbow height's
    gradient, Pinocchio's central differences) and then the elbow's (∂ns/∂q)."""
    z0 = elbow_z(robot, Q1)
    ctrl = Controller(robot, ControllerConfig(strategy="qp"), rows=[ElbowFloor(z_min=z0 - 0.1, soft=True)])
    ctrl.reset(Q1)
    assert ctrl.step(Q1).ok
    p = ctrl.records.problem[0]
    assert p["n_soft"] == 2 and p["n_hard"] == 0
    h = 1e-6
    fd = [(elbow_z(robot, Q1 + h * e) - elbow_z(robot, Q1 - h * e)) / (2 * h) for e in np.eye(7)]
    np.testing.assert_allclose(p["soft_C"][0], fd, rtol=0, atol=1e-8)
    np.testing.assert_allclose(p["soft_C"][1], ctrl.evaluate(Q1).arm_angle_gradient, rtol=0, atol=1e-12)
