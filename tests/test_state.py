"""The tick's state (qpnso/control/state.py) against independent computations: Pinocchio for the kinematics
and dynamics, the arm-angle module (numeric, Pinocchio-based) for the elbow, the cost model's own
functions and central differences for the cost and its gradient."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

import qpnso
from qpnso.control.state import PREDICTION_DAMPING, StateEvaluator, TickState, sanitize_state
from qpnso.elbow import arm_angle as E
from qpnso.model.costs import CostModel, CostWeights


@pytest.fixture(scope="module")
def evaluator() -> StateEvaluator:
    robot = qpnso.load_robot("lwr4p")
    return StateEvaluator(CostModel(robot, CostWeights(mass=1.0, friction_force=0.5)), compile="off")


def test_every_field_matches_its_independent_computation(evaluator, rng) -> None:
    robot, cost = evaluator.robot, CostModel(evaluator.robot, CostWeights(mass=1.0, friction_force=0.5), compile="off")
    data = robot.model.createData()
    checked = 0
    while checked < 10:
        q = robot.random_q(rng, margin=0.2)
        elbow = E.arm_angle_status(robot, q)
        if elbow.status != "ok":  # arm angle undefined there: not a case for its gradient
            continue
        checked += 1
        s = evaluator(q)
        pose = robot.tool_pose(q)
        np.testing.assert_allclose(s.tool_rotation, pose.rotation, atol=1e-12)
        np.testing.assert_allclose(s.tool_position, pose.translation, atol=1e-12)
        np.testing.assert_allclose(s.jacobian, robot.jacobian(q), atol=1e-12)
        A = pin.crba(robot.model, data, q)
        np.testing.assert_allclose(s.mass_matrix, np.triu(A) + np.triu(A, 1).T, atol=1e-12)
        np.testing.assert_allclose(s.gravity, pin.computeGeneralizedGravity(robot.model, data, q), atol=1e-10)
        assert s.cost == pytest.approx(cost.value(q), rel=1e-12)
        h = 1e-6
        fd = [(cost.value(q + h * e) - cost.value(q - h * e)) / (2 * h) for e in np.eye(7)]
        np.testing.assert_allclose(s.cost_gradient, cost.gradient(q), rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(s.cost_gradient, fd, rtol=0, atol=1e-5 * np.abs(fd).max())  # atan friction: stiff
        assert s.arm_angle == pytest.approx(elbow.value, abs=1e-12)
        np.testing.assert_allclose(s.arm_angle_gradient, E.arm_angle_gradient(robot, q), atol=1e-9)
        assert (s.wrist_sin, s.elbow_offset) == pytest.approx((elbow.wrist_sin, elbow.elbow_offset_m), abs=1e-12)
        np.testing.assert_array_equal(s.tool_drift, np.zeros(6))  # no velocity given
        dq = rng.normal(size=7)
        moving = evaluator(q, dq)
        pin.forwardKinematics(robot.model, data, q, dq, np.zeros(7))  # J̇q̇: the classical acceleration at q̈ = 0
        a = pin.getFrameClassicalAcceleration(robot.model, data, robot.tool_frame_id, pin.LOCAL_WORLD_ALIGNED)
        np.testing.assert_allclose(moving.tool_drift, a.vector, atol=1e-12)
        jac = [robot.jacobian(q + t * dq) for t in (1e-6, -1e-6)]
        np.testing.assert_allclose(moving.tool_drift, (jac[0] - jac[1]) @ dq / 2e-6, atol=1e-7)  # central difference
        twist = rng.normal(size=6)  # this tick's twist: the drift is along dq with its tool part replaced
        J = robot.jacobian(q)
        predicted = dq + J.T @ np.linalg.solve(J @ J.T + PREDICTION_DAMPING**2 * np.eye(6), twist - J @ dq)
        pin.forwardKinematics(robot.model, data, q, predicted, np.zeros(7))
        a = pin.getFrameClassicalAcceleration(robot.model, data, robot.tool_frame_id, pin.LOCAL_WORLD_ALIGNED)
        np.testing.assert_allclose(evaluator(q, dq, twist).tool_drift, a.vector, atol=1e-12)
        previous = rng.normal(size=6)  # the previous tick's twist: the tool part changes by the twist's change
        predicted = dq + J.T @ np.linalg.solve(J @ J.T + PREDICTION_DAMPING**2 * np.eye(6), twist - previous)
        pin.forwardKinematics(robot.model, data, q, predicted, np.zeros(7))
        a = pin.getFrameClassicalAcceleration(robot.model, data, robot.tool_frame_id, pin.LOCAL_WORLD_ALIGNED)
        changed = evaluator(q, dq, twist, previous)
        np.testing.assert_allclose(changed.tool_drift, a.vector, atol=1e-12)
        np.testing.assert_allclose(changed.predicted_velocity, predicted, atol=1e-12)


def test_the_record_is_the_function_buffer_field_for_field(evaluator) -> None:
    """The record is a view of the CasADi function's output (no copy a tick), overwritten by the next call;
    each field holds what the TickState of the same q holds."""
    q = evaluator.robot.sample_configuration()
    s = evaluator(q)
    record = evaluator.record(q, np.zeros(7), np.zeros(6), np.zeros(6))
    assert record.shape == (1,) and record.dtype == evaluator.dtype
    view = TickState.of(q, record)
    for name in ("tool_rotation", "tool_position", "jacobian", "mass_matrix", "gravity", "cost_gradient"):
        np.testing.assert_array_equal(getattr(view, name), getattr(s, name))
    assert (view.cost, view.arm_angle, view.wrist_sin) == (s.cost, s.arm_angle, s.wrist_sin)
    assert evaluator.record(q + 0.01, np.zeros(7), np.zeros(6), np.zeros(6)) is record  # the same buffer, overwritten
    assert not np.array_equal(view.jacobian, s.jacobian)


def test_sanitize_state_zeroes_what_it_can_and_refuses_the_rest(evaluator) -> None:
    from qpnso.control.flags import FLAG_COST_UNDEFINED, FLAG_INTERNAL_ERROR

    q = evaluator.robot.sample_configuration()
    clean = evaluator.record(q, np.zeros(7), np.zeros(6), np.zeros(6)).copy()
    assert sanitize_state(clean[0]) == 0
    bad = clean.copy()
    bad[0]["cost_gradient"][2] = np.nan
    assert sanitize_state(bad[0]) == FLAG_COST_UNDEFINED
    assert bad[0]["cost"] == 0.0 and not bad[0]["cost_gradient"].any()
    bad = clean.copy()
    bad[0]["elbow_offset"] = np.inf  # an undefined arm angle: made singular (wrist sine 0), no flag of its own
    assert sanitize_state(bad[0]) == 0 and bad[0]["wrist_sin"] == 0.0 and not bad[0]["arm_angle_gradient"].any()
    for field, index in (("R", (1, 2)), ("p", 0), ("J", (5, 6)), ("A", (3, 3)), ("g", 6), ("drift", 1)):
        bad = clean.copy()
        bad[0][field][index] = np.nan
        assert sanitize_state(bad[0]) == FLAG_INTERNAL_ERROR, field


def test_binding_a_record_of_another_layout_is_refused(evaluator) -> None:
    """The evaluator writes only into a record of its own layout, and its function only into a float64 vector
    of its output's size: anything else is refused before a tick could write past it."""
    with pytest.raises(ValueError, match="bind needs"):
        evaluator.bind(np.zeros(2, evaluator.dtype))
    with pytest.raises(ValueError, match="output 0 needs"):
        evaluator._fn.use_output(0, np.zeros(3))
    q = evaluator.robot.sample_configuration()
    assert evaluator.record(q, np.zeros(7), np.zeros(6), np.zeros(6)).dtype == evaluator.dtype  # still bound as before
