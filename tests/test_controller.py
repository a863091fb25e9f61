"""The controller (docs/method.md §7) and the baselines (§8), end to end.

The held-tool study of the issue: 20 random non-singular LWR4+ configurations,
5 s at 1 kHz each, checked against independent computations: Pinocchio FK
for the drift, the closed-form self-motion (IK sampled along the arm-angle
circle) for the local minimum of the cost, an exact active-set solver (DAQP)
for the QP answers.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

import qpnso
from qpnso.control.config import ControllerConfig, Status
from qpnso.control.controller import Controller
from qpnso.qp.problem import STOPPED

DT = 1e-3


def random_nonsingular(robot: qpnso.Robot, rng: np.random.Generator) -> np.ndarray:
    """Uniform within the limits (0.2 rad inside), J Jᵀ well conditioned, arm angle defined,
    and a continuity interval wide enough for a ROM with the 10° margin."""
    while True:
        q = robot.random_q(rng, margin=0.2)
        s = np.linalg.svd(robot.jacobian(q), compute_uv=False)
        if s[-1] < 0.05 or not qpnso.arm_angle_status(robot, q).ok:
            continue
        if min(abs(q[1]), abs(q[3]), abs(q[5])) < 0.2:
            continue
        iv = qpnso.continuity_interval(robot, q)
        ns = qpnso.arm_angle(robot, q)
        if iv.full_circle or (ns - iv.lo > np.radians(15) and iv.hi - ns > np.radians(15)):
            return q


def run_held(ctrl: Controller, q0: np.ndarray, ticks: int) -> tuple[np.ndarray, list]:
    ctrl.reset(q0)
    q = q0.copy()
    cmds = []
    for _ in range(ticks):
        cmd = ctrl.step(q)
        assert np.all(np.isfinite(cmd.dq)) and np.all(np.isfinite(cmd.tau))
        q = q + DT * cmd.dq
        cmds.append(cmd)
    return q, cmds


def cost_along_self_motion(ctrl: Controller, q: np.ndarray, half_width: float, n: int = 401):
    """Cost sampled on the arm-angle circle with the tool pose and branch of ``q`` held."""
    robot = ctrl.robot
    ns0 = qpnso.arm_angle(robot, q)
    grid = ns0 + np.linspace(-half_width, half_width, n)
    qs = qpnso.ik(robot, robot.tool_pose(q), np.angle(np.exp(1j * grid)), qpnso.branch(robot, q))
    return grid, qs, np.array([ctrl.cost.value(x) for x in qs])


@pytest.fixture(scope="module")
def lwr_qp() -> Controller:
    return Controller(qpnso.load_robot("lwr4p"), ControllerConfig(strategy="qp"))


@pytest.fixture(scope="module")
def lwr_gradient() -> Controller:
    return Controller(qpnso.load_robot("lwr4p"), ControllerConfig(strategy="gradient"))


HELD_SEEDS = list(range(20))


@pytest.mark.parametrize("seed", HELD_SEEDS)
def test_tool_held_five_seconds(lwr_qp: Controller, lwr_gradient: Controller, seed: int) -> None:
    robot = lwr_qp.robot
    q0 = random_nonsingular(robot, np.random.default_rng(1000 + seed))
    start = robot.tool_pose(q0)
    q, cmds = run_held(lwr_qp, q0, 5000)
    end = robot.tool_pose(q)
    # the tool does not move (Pinocchio FK, independent of the controller's CasADi model)
    assert np.linalg.norm(end.translation - start.translation) < 1e-6
    assert np.linalg.norm(pin.log3(end.rotation @ start.rotation.T)) < 1e-5
    # joint limits are never crossed
    qs = np.array([q0] + [c.q_des for c in cmds])
    assert np.all(qs >= robot.q_min - 1e-12) and np.all(qs <= robot.q_max + 1e-12)
    assert all(c.ok for c in cmds)
    # the arm angle stays in ROM_t, or moves back into it
    ns = np.array([c.arm_angle for c in cmds])
    lo = np.array([c.rom[0] for c in cmds])
    hi = np.array([c.rom[1] for c in cmds])
    outside = np.maximum(lo - ns, ns - hi)
    assert np.all(np.diff(np.maximum(outside, 0)) <= 1e-9) or outside.max() <= 1e-6
    # the cost does not increase (level 2 descends)
    cost = np.array([c.cost for c in cmds])
    assert cost[-1] <= cost[0] + 1e-12
    # a local minimum along the self-motion (closed-form IK samples), unless an elbow bound holds it
    final_ns = ns[-1]
    at_bound = min(final_ns - lo[-1], hi[-1] - final_ns) < np.radians(0.5)
    grid, _, values = cost_along_self_motion(lwr_qp, q, np.radians(3))
    centre = len(grid) // 2
    if not at_bound:
        assert values[centre] <= values.min() + 1e-6 * max(1.0, abs(values[centre]))
    if not at_bound and seed % 8 == 0:  # (15 000 ticks, 9 s each: three seeds keep the suite under 5 min)
        # the gradient baseline converges to the same minimum
        qg, _ = run_held(lwr_gradient, q0, 15000)  # capped at nullspace_speed_max like qp: slower early on
        assert abs(qpnso.arm_angle(robot, qg) - qpnso.arm_angle(robot, q)) < np.radians(0.5)


def test_tool_follows_a_twist_while_level_two_optimises(lwr_qp: Controller) -> None:
    robot = lwr_qp.robot
    q0 = np.array([0.1, 0.6, -0.2, -1.3, 0.3, 0.9, 0.2])
    twist = np.array([0.05, -0.02, 0.03, 0.0, 0.0, 0.2])  # m/s, rad/s, world frame
    lwr_qp.reset(q0)
    damped = Controller(robot, ControllerConfig(strategy="damped"))
    damped.reset(q0)
    start = robot.tool_pose(q0)
    q, qd = q0.copy(), q0.copy()
    n = 1000
    for _ in range(n):
        q = q + DT * lwr_qp.step(q, tool_twist=twist).dq
        qd = qd + DT * damped.step(qd, tool_twist=twist).dq
    expected_p = start.translation + n * DT * twist[:3]
    expected_r = pin.exp3(n * DT * twist[3:]) @ start.rotation
    end = robot.tool_pose(q)
    assert np.linalg.norm(end.translation - expected_p) < 1e-6
    assert np.linalg.norm(pin.log3(end.rotation @ expected_r.T)) < 1e-5
    # same tool motion, but the QP moved the arm in the null space to a lower cost
    assert np.linalg.norm(robot.tool_pose(qd).translation - expected_p) < 1e-6
    assert lwr_qp.cost.value(q) < lwr_qp.cost.value(qd) - 1e-3
    assert np.linalg.norm(q - qd) > 1e-2


def test_qp_answers_match_an_exact_active_set_solver() -> None:
    """ProxSuite (native, warm) against DAQP through qpsolvers on the same ticks."""
    robot = qpnso.load_robot("lwr4p")
    q0 = np.array([0.3, 1.0, 0.4, -1.6, -0.5, 1.1, 0.1])
    prox = Controller(robot, ControllerConfig(strategy="qp"))
    exact = Controller(robot, ControllerConfig(strategy="qp", qp_backend="daqp"))
    prox.reset(q0)
    exact.reset(q0)
    q = q0.copy()
    worst = 0.0
    for _ in range(300):
        a, b = prox.step(q), exact.step(q)
        worst = max(worst, np.abs(a.dq - b.dq).max())
        q = q + DT * a.dq
    assert worst < 1e-6


def test_elbow_is_kept_in_a_narrow_rom() -> None:
    """A 5° ROM with the cost pulling the elbow away: the arm angle stays in ROM_t."""
    robot = qpnso.load_robot("lwr4p")
    q0 = random_nonsingular(robot, np.random.default_rng(7))
    ctrl = Controller(robot, ControllerConfig(strategy="qp", rom_half_width_deg=5, cost_gain=20))
    _, cmds = run_held(ctrl, q0, 2000)
    ns = np.array([c.arm_angle for c in cmds])
    assert np.all(ns >= cmds[0].rom[0] - 1e-4) and np.all(ns <= cmds[0].rom[1] + 1e-4)
    free = Controller(robot, ControllerConfig(strategy="qp", rom_half_width_deg=180, cost_gain=20))
    _, free_cmds = run_held(free, q0, 2000)
    assert abs(free_cmds[-1].arm_angle - free_cmds[0].arm_angle) > abs(ns[-1] - ns[0]) - 1e-9


def test_torque_does_not_accelerate_the_tool(lwr_qp: Controller) -> None:
    """τ − g(q) is in the dynamically consistent null space: J A⁻¹ (τ − g) = 0 (Pinocchio ABA)."""
    robot = lwr_qp.robot
    q0 = np.array([0.2, 0.7, -0.1, -1.4, 0.2, 0.8, -0.3])
    lwr_qp.reset(q0)
    cmd = lwr_qp.step(q0, dq=np.zeros(7))
    data = robot.model.createData()
    ddq = pin.aba(robot.model, data, q0, np.zeros(7), cmd.tau)  # gravity included
    assert np.abs(cmd.tau - robot.gravity(q0)).max() > 1e-6
    # (relative to the joint accelerations; the 1e-12 regularisation of JA⁻¹Jᵀ is what remains)
    assert np.abs(robot.jacobian(q0) @ ddq).max() < 1e-7 * np.abs(ddq).max()


@pytest.mark.parametrize("strategy", qpnso.STRATEGIES)
def test_every_strategy_gives_finite_commands(strategy: str) -> None:
    robot = qpnso.load_robot("lwr4p")
    q0 = np.array([0.1, 0.6, -0.2, -1.3, 0.3, 0.9, 0.2])
    ctrl = Controller(robot, ControllerConfig(strategy=strategy, rom_half_width_deg=3))
    start = robot.tool_pose(q0)
    q, cmds = run_held(ctrl, q0, 300)
    assert np.linalg.norm(robot.tool_pose(q).translation - start.translation) < 1e-6
    for c in cmds:
        assert c.q_des.shape == (7,) and np.all(np.isfinite(c.q_des))
        assert np.all(np.isfinite(c.tau)) and np.isfinite(c.stiffness)


def test_fixed_posture_returns_to_its_posture() -> None:
    robot = qpnso.load_robot("lwr4p")
    q0 = np.array([0.1, 0.6, -0.2, -1.3, 0.3, 0.9, 0.2])
    ctrl = Controller(robot, ControllerConfig(strategy="fixed"))
    ctrl.reset(q0)
    # push the arm along its self-motion, then let the FOP bring it back
    ns = qpnso.arm_angle(robot, q0)
    q = qpnso.ik(robot, robot.tool_pose(q0), ns + 0.2, qpnso.branch(robot, q0))
    for _ in range(3000):
        q = q + DT * ctrl.step(q).dq
    assert np.abs(q - q0).max() < 1e-2


def test_elbow_up_raises_the_elbow() -> None:
    robot = qpnso.load_robot("lwr4p")
    q0 = np.array([0.1, 0.6, -0.2, -1.3, 0.3, 0.9, 0.2])
    ctrl = Controller(robot, ControllerConfig(strategy="elbow-up"))
    q, cmds = run_held(ctrl, q0, 3000)
    assert abs(cmds[-1].arm_angle) < abs(cmds[0].arm_angle) * 0.2


# ------------------------------------------------------------------ bad input
@pytest.mark.parametrize("bad", [np.full(7, np.nan), np.zeros(6), [0, 0, 0, np.inf, 0, 0, 0]])
def test_bad_q_raises_value_error(lwr_qp: Controller, bad) -> None:
    lwr_qp.reset(np.array([0.1, 0.6, -0.2, -1.3, 0.3, 0.9, 0.2]))
    with pytest.raises(ValueError):
        lwr_qp.step(bad)


def test_bad_twist_raises_value_error(lwr_qp: Controller) -> None:
    lwr_qp.reset(np.array([0.1, 0.6, -0.2, -1.3, 0.3, 0.9, 0.2]))
    with pytest.raises(ValueError, match="tool_twist"):
        lwr_qp.step(np.array([0.1, 0.6, -0.2, -1.3, 0.3, 0.9, 0.2]), tool_twist=np.zeros(5))


def test_step_before_reset_is_an_error() -> None:
    ctrl = Controller(qpnso.load_robot("lwr4p"))
    with pytest.raises(qpnso.QpnsoError, match="reset"):
        ctrl.step(np.zeros(7))


def test_q_outside_limits_is_flagged_and_pushed_back(lwr_qp: Controller) -> None:
    robot = lwr_qp.robot
    q0 = np.array([0.1, 0.6, -0.2, -1.3, 0.3, 0.9, 0.2])
    lwr_qp.reset(q0)
    q = q0.copy()
    q[1] = robot.q_max[1] + 0.01
    cmd = lwr_qp.step(q)
    assert cmd.status & Status.Q_OUT_OF_LIMITS
    assert cmd.dq[1] < 0 and np.all(np.isfinite(cmd.dq))


def test_failed_qp_falls_back_to_holding_the_tool(lwr_qp: Controller, monkeypatch) -> None:
    q0 = np.array([0.1, 0.6, -0.2, -1.3, 0.3, 0.9, 0.2])
    lwr_qp.reset(q0)

    def failing(problem, solution, time_budget=None):  # level 1 failed: the solver leaves zero
        solution[0]["x"], solution[0]["outcome"] = 0.0, STOPPED
        return "level 1 of 2 infeasible: test"

    monkeypatch.setattr(lwr_qp.qp, "solve_problem", failing)
    cmd = lwr_qp.step(q0)
    assert cmd.status & Status.QP_FAILED and not cmd.ok
    assert np.all(cmd.dq == 0) and np.all(np.isfinite(cmd.tau))
    assert cmd.message == "QP failed (level 1 of 2 infeasible: test): joints brought to rest at ddq_max"


def test_singular_arm_angle_drops_the_elbow_constraints(lwr_qp: Controller) -> None:
    q0 = np.array([0.1, 0.6, -0.2, -1.3, 0.3, 0.9, 0.2])
    lwr_qp.reset(q0)
    straight = np.array([0.1, 0.6, -0.2, 0.0, 0.3, 0.9, 0.2])  # joint 4 = 0: elbow straight
    cmd = lwr_qp.step(straight)
    assert cmd.status & Status.ELBOW_DROPPED
    assert np.all(np.isfinite(cmd.dq)) and np.all(np.isfinite(cmd.tau))


def test_no_allocation_per_tick(lwr_qp: Controller, monkeypatch) -> None:
    q0 = np.array([0.1, 0.6, -0.2, -1.3, 0.3, 0.9, 0.2])
    lwr_qp.reset(q0)
    q = q0.copy()
    for _ in range(5):
        q = q + DT * lwr_qp.step(q).dq
    created = lwr_qp.qp.stats.qp_created

    def forbidden(*args, **kwargs):
        raise AssertionError("a CasADi function was built during a tick")

    monkeypatch.setattr(qpnso.model.symbolic.SymbolicModel, "function", forbidden)
    monkeypatch.setattr(qpnso.model.codegen.FastFunction, "__init__", forbidden)
    for _ in range(100):
        q = q + DT * lwr_qp.step(q).dq
    assert lwr_qp.qp.stats.qp_created == created


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"strategy": "magic"}, "unknown strategy"),
        ({"dt": 0.0}, "dt"),
        ({"joint_limit_gain": 2000.0}, "joint_limit_gain"),
    ],
)
def test_bad_config(kwargs, match) -> None:
    with pytest.raises(qpnso.ConfigError, match=match):
        ControllerConfig(**kwargs)


def test_config_from_dict_names_unknown_keys() -> None:
    with pytest.raises(qpnso.ConfigError, match="colour"):
        ControllerConfig.from_dict({"colour": "red"})
    cfg = ControllerConfig.from_dict({"strategy": "rom", "weights": {"mass": 0.3, "friction_force": 0.7}})
    assert cfg.weights.mass == 0.3 and cfg.strategy == "rom"


def test_tool_motion_beyond_the_joint_speeds_is_flagged(lwr_qp: Controller) -> None:
    """A 5 m/s tool twist needs more than the joint velocity limits: the bounds hold,
    level 1 does what it can, and the status says the tool was limited."""
    robot = lwr_qp.robot
    q0 = np.array([0.1, 0.6, -0.2, -1.3, 0.3, 0.9, 0.2])
    lwr_qp.reset(q0)
    q = q0.copy()
    for _ in range(200):  # (the joints gain speed at ddq_max from rest)
        cmd = lwr_qp.step(q, tool_twist=np.array([5.0, 0, 0, 0, 0, 0]))
        assert cmd.status & Status.TOOL_LIMITED and cmd.ok
        assert np.all(np.abs(cmd.dq) <= robot.dq_max + 1e-9)
        q = q + lwr_qp.config.dt * cmd.dq
    assert (robot.jacobian(q) @ cmd.dq)[0] > 0.1  # still moving the tool the right way


def test_the_moving_benchmark_moves_the_tool_on_its_target() -> None:
    """``moving_tool_ticks`` (the moving rows of ``qpnso bench tick``): the controller's reference follows
    :class:`MovingTarget`'s pose (the integral of its twist): after half a period the tool point is one
    diameter away and turned by the target's rotation, after a whole period back where it started; the
    commanded joints put the tool there (Pinocchio's forward kinematics)."""
    from qpnso.lab.benchmark import MovingTarget, moving_tool_ticks

    robot = qpnso.load_robot("lwr4p", tool_offset=[0.0, 0.0, 0.1])
    ctrl = Controller(robot, ControllerConfig(strategy="qp"))
    q0 = robot.sample_configuration()
    ctrl.reset(q0)
    target = MovingTarget(radius=0.05, frequency=2.5, rotation=0.2)  # a 0.4 s period
    run = moving_tool_ticks(ctrl, q0, target)
    start = robot.tool_pose(q0)
    times = run(200)
    assert times.shape == (200,) and np.all(times > 0)
    p, R = target.pose(0.2, start.translation, start.rotation)
    assert np.linalg.norm(p - start.translation) == pytest.approx(0.1, abs=1e-12)
    slip = 1e-3 * 0.05 * 2 * np.pi * 2.5  # the reference sums the twist over ticks: within dt·|v| of the integral
    np.testing.assert_allclose(ctrl.ref_position, p, atol=1.01 * slip)
    run(200)
    np.testing.assert_allclose(ctrl.ref_position, start.translation, atol=1.01 * slip)
    ctrl.reset(q0)
    q, target = q0.copy(), MovingTarget()  # the benchmark's own target, which the arm can follow
    for k in range(600):  # the tool itself, ticking from q0 along the target (from rest: it catches up at
        # ddq_max and pose_correction_speed within the first 0.3 s)
        q = q + 1e-3 * ctrl.step(q, tool_twist=target.twist(k * 1e-3)).dq
    p, R = target.pose(0.6, start.translation, start.rotation)
    tool = robot.tool_pose(q)
    np.testing.assert_allclose(tool.translation, p, atol=5e-4)
    assert np.degrees(np.linalg.norm(pin.log3(R.T @ tool.rotation))) < 0.1


def test_peer_rows_follow_the_same_target() -> None:
    """The peers' rows of ``qpnso bench tick`` solve IK on the target qpnso's moving rows follow: Pink's tool
    frame and mink's site (MuJoCo's model of the same URDF) start on qpnso's tool pose (two forward
    kinematics), and after 200 calls on :class:`MovingTarget` each peer's tool is near the target's pose."""
    from qpnso.lab.benchmark import MovingTarget, mink_ticks, pink_ticks

    robot = qpnso.load_robot("lwr4p", tool_offset=[0.0, 0.0, 0.1])
    q0 = robot.sample_configuration()
    start = robot.tool_pose(q0)
    target = MovingTarget()
    p, _ = target.pose(0.2, start.translation, start.rotation)
    made = 0
    for make in (pink_ticks, mink_ticks):
        peer = make(robot, q0, target)
        if peer is None:
            continue
        made += 1
        run, note = peer
        np.testing.assert_allclose(run.tool_pose().homogeneous, start.homogeneous, atol=1e-9)
        assert run(200).shape == (200,) and note
        np.testing.assert_allclose(run.tool_pose().translation, p, atol=3e-3)
    if made == 0:
        pytest.skip("neither pin-pink nor mink is installed")
