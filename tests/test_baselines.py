"""The papers' baselines do what their papers say, checked by what their torques and motions do, not by
their formulas (docs/method.md §10): DP dissipates, FOP and elbow-up restore their postures, the gradient
baseline descends the cost (by finite differences of the cost model), and the elbow paper's set-point
modulation brings an elbow outside ROM_t back (closed loop, arm angle by Pinocchio's forward kinematics)."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from conftest import limit_params, reference_arm_angle

import qpnso
from qpnso.control.config import ControllerConfig, ElbowState, Status
from qpnso.control.controller import Controller
from qpnso.control.tick import velocity_bounds

Q1 = np.radians([10, 40, -10, -70, 20, 50, 0])


@pytest.fixture(scope="module")
def robot() -> qpnso.Robot:
    return qpnso.load_robot("lwr4p", tool_offset=[0.0, 0.0, 0.1])


def controller(robot: qpnso.Robot, strategy: str, **settings) -> Controller:
    ctrl = Controller(robot, ControllerConfig(strategy=strategy, **settings))
    ctrl.reset(Q1)
    return ctrl


def elbow_at(state) -> ElbowState:
    """The elbow at the state's arm angle, well inside a ROM_t of ±0.5 rad (what DP, FOP, elbow-up and the
    gradient baseline read of it: the arm angle)."""
    ns = state.arm_angle
    return ElbowState(ns, (ns - 0.5, ns + 0.5), (ns - np.pi, ns + np.pi), 10.0, Status.OK)


def test_damped_posture_dissipates(robot) -> None:
    ctrl = controller(robot, "damped")
    state = ctrl.evaluate(Q1)
    elbow = elbow_at(state)
    for seed in range(5):
        dq = np.random.default_rng(seed).normal(size=7)
        tau = ctrl.strategy.nullspace_torque(state, elbow, dq)
        assert dq @ tau == pytest.approx(-ctrl.config.joint_damping * (dq @ dq), rel=1e-12)  # power −D|q̇|²


def test_fixed_posture_pulls_back_to_its_posture(robot) -> None:
    ctrl = controller(robot, "fixed")
    moved = Q1 + np.radians([0, 0, 5, 0, -3, 0, 2])
    state = ctrl.evaluate(moved)
    tau = ctrl.strategy.nullspace_torque(state, elbow_at(state), np.zeros(7))
    np.testing.assert_allclose(tau, ctrl.config.posture_stiffness * (Q1 - moved), rtol=0, atol=1e-12)
    assert (Q1 - moved) @ tau > 0  # towards the posture


def test_elbow_up_turns_the_arm_angle_towards_its_target(robot) -> None:
    """Elbow-up's torque, applied as a small joint displacement, moves the arm angle (by Pinocchio) towards
    ``elbow_up_angle_deg``, from either side."""
    for target_deg in (-60.0, 60.0):
        ctrl = controller(robot, "elbow-up", elbow_up_angle_deg=target_deg)
        state = ctrl.evaluate(Q1)
        tau = ctrl.strategy.nullspace_torque(state, elbow_at(state), np.zeros(7))
        ns, ns_after = reference_arm_angle(robot, Q1), reference_arm_angle(robot, Q1 + 1e-4 * tau / np.linalg.norm(tau))
        assert np.sign(ns_after - ns) == np.sign(np.radians(target_deg) - ns)


def test_gradient_baseline_at_rest_descends_the_cost(robot) -> None:
    """[M 20] at rest: ``F_p = k_d v_d ω_des`` with ``ω_des = −k_p∇c/k_d``: a small step along it lowers the
    weighted cost (evaluated by the cost model, finite differences, not its gradient), and it is saturated
    at ``gradient_omega_max`` rad/s times k_d."""
    ctrl = controller(robot, "gradient")
    state = ctrl.evaluate(Q1)
    tau = ctrl.strategy.nullspace_torque(state, elbow_at(state), np.zeros(7))
    step = 1e-5 * tau / np.linalg.norm(tau)
    assert ctrl.cost.value(Q1 + step) < ctrl.cost.value(Q1) < ctrl.cost.value(Q1 - step)
    assert np.linalg.norm(tau) <= ctrl.config.gradient_kd * ctrl.config.gradient_omega_max * (1 + 1e-12)
    moving = ctrl.strategy.nullspace_torque(state, elbow_at(state), tau / ctrl.config.gradient_kd)
    np.testing.assert_allclose(moving, 0.0, atol=1e-9)  # at the desired velocity: no force left


def test_rom_modulation_is_silent_inside_the_rom_and_restoring_outside(robot) -> None:
    ctrl = controller(robot, "rom")
    state = ctrl.evaluate(Q1)
    inside = ElbowState(
        state.arm_angle, (state.arm_angle - 0.5, state.arm_angle + 0.5), (-np.pi, np.pi), 10.0, Status.OK
    )
    dq = np.random.default_rng(0).normal(size=7)
    np.testing.assert_allclose(
        ctrl.strategy.nullspace_torque(state, inside, dq), -ctrl.config.joint_damping * dq, atol=1e-12
    )  # inside: only damped
    assert ctrl.strategy.level2(state, inside) is None
    for side in (-1.0, 1.0):  # the arm angle 0.2 rad above / below ROM_t
        rom = (
            (state.arm_angle - 0.7, state.arm_angle - 0.2)
            if side > 0
            else (state.arm_angle + 0.2, state.arm_angle + 0.7)
        )
        outside = ElbowState(state.arm_angle, rom, (-np.pi, np.pi), 10.0, Status.OK)
        tau = ctrl.strategy.nullspace_torque(state, outside, np.zeros(7))
        ns_after = reference_arm_angle(robot, Q1 + 1e-4 * tau / np.linalg.norm(tau))
        assert np.sign(ns_after - reference_arm_angle(robot, Q1)) == -side  # back towards ROM_t
        # the set-point is the closed-form IK at the ROM's near end: K·(q_des − q) with ns(q_des) that end
        q_des = Q1 + tau / outside.stiffness
        assert reference_arm_angle(robot, q_des) == pytest.approx(rom[1] if side > 0 else rom[0], abs=1e-9)


def test_rom_modulation_brings_an_elbow_outside_its_rom_back_in_closed_loop(robot) -> None:
    """Reset with the ROM centred 60° from the arm angle (half width 50°): 10° outside.  A position-controlled
    arm (q ← q + dt·q̇) following the ``rom`` strategy returns inside ROM_t, the excursion never grows, and the
    held tool stays put (Pinocchio's forward kinematics)."""
    ctrl = Controller(robot, ControllerConfig(strategy="rom"))
    ns_start = reference_arm_angle(robot, Q1)
    ctrl.reset(Q1, ns0=ns_start + np.radians(60))
    data = robot.model.createData()
    pin.framesForwardKinematics(robot.model, data, Q1)
    tool0 = data.oMf[robot.tool_frame_id].translation.copy()
    q, excursion = Q1.copy(), []
    for _ in range(3000):  # 3 s: the posture rate posture_gain = 2 /s returns it as e^(−2t), after its filter
        cmd = ctrl.step(q)
        q = q + ctrl.config.dt * cmd.dq
        excursion.append(max(cmd.rom[0] - cmd.arm_angle, cmd.arm_angle - cmd.rom[1], 0.0))
    assert excursion[0] == pytest.approx(np.radians(10), abs=1e-6)
    assert all(b <= a + 1e-9 for a, b in zip(excursion, excursion[1:]))
    assert excursion[-1] < 1e-3
    lo = ns_start + np.radians(10)  # ROM_t's lower end, which the arm angle (by Pinocchio) has reached
    assert reference_arm_angle(robot, q) >= lo - 1e-3
    pin.framesForwardKinematics(robot.model, data, q)
    assert np.linalg.norm(data.oMf[robot.tool_frame_id].translation - tool0) < 1e-5


def test_the_joint_limit_damper_has_its_gain_near_a_limit() -> None:
    """By hand: 0.01 rad below q_max with γ = 20 /s the upper bound is γ·0.01 = 0.2 rad/s; 0.001 rad above
    q_min the lower bound is −0.02 rad/s; far from both, the velocity limits; one tick at the bound leaves
    (1 − γ·dt) of the distance (q never crosses)."""
    q_min, q_max, dq_max = -np.ones(3), np.ones(3), np.full(3, 2.0)
    q = np.array([0.99, -0.999, 0.0])
    lb, ub = velocity_bounds(q, limit_params(q_min, q_max, dq_max, 20.0, 0.2))
    np.testing.assert_allclose(ub, [0.2, 2.0, 2.0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(lb, [-2.0, -0.02, -2.0], rtol=0, atol=1e-12)
    after = q[0] + 1e-3 * ub[0]
    assert q_max[0] - after == pytest.approx((1 - 20.0 * 1e-3) * 0.01, abs=1e-15)


def test_elbow_up_damps_a_measured_velocity(robot) -> None:
    """Elbow-up's torque with a measured joint velocity q̇ is its torque at rest plus the damping −D q̇
    (D = ``joint_damping``, 10 N·m·s/rad): that part dissipates power −D|q̇|²."""
    ctrl = controller(robot, "elbow-up", elbow_up_angle_deg=30.0)
    state = ctrl.evaluate(Q1)
    elbow = elbow_at(state)
    at_rest = ctrl.strategy.nullspace_torque(state, elbow, np.zeros(7))
    dq = np.random.default_rng(3).normal(size=7)
    extra = ctrl.strategy.nullspace_torque(state, elbow, dq) - at_rest
    assert dq @ extra == pytest.approx(-10.0 * (dq @ dq), rel=1e-12)
    np.testing.assert_allclose(extra, -10.0 * dq, rtol=1e-12, atol=1e-12)


def test_rom_modulation_target_decays_after_the_elbow_reenters(robot) -> None:
    """Outside ROM_t the ``rom`` strategy's level 2 asks a low-passed step towards the set-point; once ``ns`` is
    back inside, the target is not dropped at once but decays as the first-order low-pass of a zero step:
    by (1 − dt/τ) = 0.99 a tick (dt = 1 ms, τ = ``posture_filter_time`` = 0.1 s), then nothing."""
    ctrl = controller(robot, "rom")
    state = ctrl.evaluate(Q1)
    ns = state.arm_angle
    outside = ElbowState(ns, (ns - 0.7, ns - 0.2), (-np.pi, np.pi), 10.0, Status.OK)
    inside = ElbowState(ns, (ns - 0.5, ns + 0.5), (-np.pi, np.pi), 10.0, Status.OK)
    first = ctrl.strategy.level2(state, outside)
    assert first is not None and np.linalg.norm(first.b) > 0
    decaying = ctrl.strategy.level2(state, inside)
    assert decaying is not None
    np.testing.assert_allclose(decaying.b, 0.99 * first.b, rtol=1e-12, atol=0)
    ticks = 1
    while ctrl.strategy.level2(state, inside) is not None:
        ticks += 1
        assert ticks < 5000
    # the target fell below 1e-9 rad/s after n ticks with 0.99ⁿ·max|b| < 1e-9 ≤ 0.99ⁿ⁻¹·max|b|
    n = int(np.ceil(np.log(1e-9 / np.abs(first.b).max()) / np.log(0.99)))
    assert abs(ticks - n) <= 1
    assert ctrl.strategy.level2(state, inside) is None


@pytest.mark.parametrize("target", [2.5, -2.5, 3.0, 4.0, -4.0])
def test_the_rom_strategys_ik_step_reaches_a_set_point_beyond_two_radians(robot, target: float) -> None:
    """The ``rom`` strategy's step towards an arm-angle set-point (closed-form IK at the same tool pose and branch):
    ``q + step`` has the set-point as its arm angle (Pinocchio's, modulo 2π), also for set-points beyond ±2 rad
    and ±π (an unwrapped ROM_t), where wrapping the angle into (−π, π] must use 2π."""
    import types

    ctrl = Controller(robot, ControllerConfig(strategy="rom"))
    ctrl.reset(Q1)
    state = ctrl.evaluate(Q1)
    step = ctrl.strategy._ik_step(state, types.SimpleNamespace(ns=reference_arm_angle(robot, Q1)), target)
    assert abs(np.angle(np.exp(1j * (reference_arm_angle(robot, Q1 + step) - target)))) < 1e-9


def test_gradient_baselines_desired_velocity_by_hand(robot) -> None:
    """[M 20]: ``ω_des = −k_p ∇c / k_d`` (k_p = 3, k_d = 4: the ratio, not the product), unsaturated under a
    large ω_max; saturated to ω_max along the same direction under a small one."""
    state = None
    small = 0.5 * 4.0 / np.linalg.norm(Controller(robot, ControllerConfig()).evaluate(Q1).cost_gradient)
    for omega_max, kp, kd in ((1e6, 3.0, 4.0), (1e-3, 3.0, 4.0), (1e-3, small, 4.0)):  # the last: ‖ω_des‖ = 0.5
        config = ControllerConfig(strategy="gradient", gradient_kp=kp, gradient_kd=kd, gradient_omega_max=omega_max)
        ctrl = Controller(robot, config)
        state = ctrl.evaluate(Q1)
        omega = -kp / kd * state.cost_gradient
        expected = omega * min(1.0, omega_max / np.linalg.norm(omega))
        np.testing.assert_allclose(ctrl.strategy.desired_velocity(state), expected, rtol=1e-12, atol=0)
