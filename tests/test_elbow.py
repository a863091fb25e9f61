"""Arm angle, S-R-S geometry and closed-form IK, against Pinocchio and finite differences."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pinocchio as pin
import pytest
from conftest import reference_arm_angle

from qpnso.elbow import arm_angle as E
from qpnso.elbow import srs as S
from qpnso.errors import InputError, ModelError, SingularityError, UnreachableError
from qpnso.model.robot import Robot, friction_from_lists, load_robot
from qpnso.model.symbolic import SymbolicModel

SRS = ["lwr4p", "iiwa14"]


@pytest.fixture(scope="module", params=SRS)
def robot(request) -> Robot:
    return load_robot(request.param)


def _regular_qs(robot: Robot, rng: np.random.Generator, n: int) -> list[np.ndarray]:
    qs = (robot.random_q(rng, 0.05) for _ in range(4 * n))
    return [q for q in qs if E.arm_angle_status(robot, q).ok][:n]


def test_geometry_read_from_model(robot: Robot) -> None:
    g = S.srs_geometry(robot)
    expected = {"lwr4p": (0.40, 0.39), "iiwa14": (0.42, 0.40)}[robot.name]  # MODELS-AND-ELBOW.md
    assert (g.upper_arm_m, g.forearm_m) == pytest.approx(expected, abs=1e-12)
    data = robot.model.createData()
    pin.forwardKinematics(robot.model, data, np.zeros(7))
    pts = g.points
    for j, off in ((pts.shoulder_joint, pts.shoulder_offset), (pts.wrist_joint, pts.wrist_offset)):
        assert np.allclose(data.oMi[j].act(np.array(off))[:2], 0.0)  # on the vertical line at q = 0


def test_non_srs_models_are_refused(robot: Robot) -> None:
    model = robot.model.copy()
    model.jointPlacements[4] = pin.SE3(np.eye(3), model.jointPlacements[4].translation + [0.01, 0, 0])
    bent = Robot("bent", model, robot.tool_frame_id, friction_from_lists([1.5] * 7, [20.0] * 7, 7))
    assert not S.is_srs(bent)
    with pytest.raises(ModelError, match="not S-R-S"):
        S.srs_geometry(bent)
    q = np.full(7, 0.4)
    assert E.arm_angle_status(bent, q).ok  # the arm angle itself stays defined


def test_arm_angle_matches_literal_formula(robot: Robot, rng) -> None:
    for q in _regular_qs(robot, rng, 50):
        assert E.arm_angle(robot, q) == pytest.approx(reference_arm_angle(robot, q), abs=1e-12)


def test_an_arm_mounted_off_the_world_origin_has_the_literal_arm_angle(robot: Robot, rng) -> None:
    """A cart puts the base anywhere: with the shoulder off the world z axis (x ≠ y ≠ 0) every component of
    p_sw = p_w - p_s and p_se = p_e - p_s matters, and the arm angle still equals the literal [E 2]-[E 4]."""
    model = robot.model.copy()
    model.jointPlacements[1] = pin.SE3(np.eye(3), model.jointPlacements[1].translation + [0.3, -0.2, 0.05])
    moved = Robot("moved", model, robot.tool_frame_id, robot.friction)
    assert S.is_srs(moved)
    for q in _regular_qs(moved, rng, 30):
        assert E.arm_angle(moved, q) == pytest.approx(reference_arm_angle(moved, q), abs=1e-12)
        assert E.arm_angle(moved, q) == pytest.approx(E.arm_angle(robot, q), abs=1e-12)  # the base only translated


def test_zero_is_elbow_up(robot: Robot, rng) -> None:
    """cos ns > 0 exactly when the elbow is above the shoulder–wrist line."""
    data = robot.model.createData()
    pts = E.elbow_points(robot)
    for q in _regular_qs(robot, rng, 50):
        pin.forwardKinematics(robot.model, data, q)
        ps, pe, pw = (data.oMi[j].translation for j in (pts.shoulder_joint, pts.elbow_joint, pts.wrist_joint))
        t = (pe - ps) @ (pw - ps) / ((pw - ps) @ (pw - ps))
        height = (pe - (ps + t * (pw - ps)))[2]
        ns = E.arm_angle(robot, q)
        if abs(height) > 1e-3 and abs(np.cos(ns)) > 1e-3:
            assert np.sign(np.cos(ns)) == np.sign(height)


def test_gradient_matches_central_differences(robot: Robot, rng) -> None:
    h = 1e-6
    for q in _regular_qs(robot, rng, 10):
        grad = E.arm_angle_gradient(robot, q)
        fd = np.array(
            [
                np.angle(np.exp(1j * (E.arm_angle(robot, q + h * e) - E.arm_angle(robot, q - h * e)))) / (2 * h)
                for e in np.eye(7)
            ]
        )
        assert np.allclose(grad, fd, atol=1e-6, rtol=1e-6)


def test_expression_and_measures(robot: Robot, rng) -> None:
    sym = SymbolicModel(robot.model)
    ns, measures = E.arm_angle_expression(sym, E.elbow_points(robot))
    fun = sym.function("ns", {"ns": ns, "m": measures})
    for q in _regular_qs(robot, rng, 10):
        out = fun(q=q)
        state = E.arm_angle_status(robot, q)
        assert float(out["ns"]) == pytest.approx(state.value, abs=1e-12)
        assert np.allclose(np.asarray(out["m"]).ravel(), [state.wrist_sin, state.elbow_offset_m], atol=1e-12)


def test_singular_configurations_are_reported(robot: Robot) -> None:
    straight_up = np.zeros(7)
    assert E.arm_angle_status(robot, straight_up).status == "wrist_vertical"
    bent_shoulder_straight_elbow = np.array([0.0, 0.6, 0.0, 0.0, 0.0, 0.3, 0.0])
    state = E.arm_angle_status(robot, bent_shoulder_straight_elbow)
    assert state.status == "elbow_straight" and state.elbow_offset_m < 1e-12
    for q in (straight_up, bent_shoulder_straight_elbow):
        with pytest.raises(SingularityError, match="arm angle undefined"):
            E.arm_angle(robot, q)
        with pytest.raises(SingularityError):
            E.arm_angle_gradient(robot, q)
    with pytest.raises(SingularityError, match="joint 4"):
        S.branch(robot, bent_shoulder_straight_elbow)


def test_a_wrist_inside_the_cone_but_off_the_vertical_keeps_its_arm_angle(robot: Robot) -> None:
    """Inside the wrist cone (``wrist_sin`` < sin 2°) the status is ``wrist_vertical``, but while the wrist is off
    the vertical (``wrist_sin`` > 0) the arm angle is still defined and reported: the literal formula's value
    (:func:`reference_arm_angle`), and the same as with no cone; exactly on the vertical it is NaN."""
    from scipy.optimize import minimize_scalar

    def pose(q2: float, q3: float) -> np.ndarray:
        return np.array([0.3, q2, q3, 0.4, 0.0, 0.0, 0.0])

    over = minimize_scalar(
        lambda q2: E.arm_angle_status(robot, pose(q2, 0.0)).wrist_sin, bounds=(0.0, 0.4), method="bounded"
    )
    q = pose(over.x, 0.1)  # the wrist just over the shoulder, then joint 3 tilts it off the vertical
    inside = E.arm_angle_status(robot, q)
    assert inside.status == "wrist_vertical" and 0.0 < inside.wrist_sin < np.sin(np.radians(E.WRIST_CONE_DEG))
    assert inside.value == pytest.approx(reference_arm_angle(robot, q), abs=1e-9)
    assert inside.value == E.arm_angle_status(robot, q, wrist_cone_deg=0.0).value
    assert math.isnan(E.arm_angle_status(robot, np.zeros(7)).value)  # straight up: exactly vertical


def test_ik_round_trips(robot: Robot, rng) -> None:
    data = robot.model.createData()
    for q in _regular_qs(robot, rng, 100):
        pose, ns, b = robot.tool_pose(q), E.arm_angle(robot, q), S.branch(robot, q)
        q_ik = S.ik(robot, pose, ns, b)
        assert np.abs(q_ik - q).max() < 1e-9
        for q_other in S.ik(robot, pose, rng.uniform(-np.pi, np.pi, 5), b):
            pin.framesForwardKinematics(robot.model, data, q_other)
            assert np.abs(data.oMf[robot.tool_frame_id].homogeneous - pose.homogeneous).max() < 1e-9
            assert S.branch(robot, q_other) == b
        ns_new = rng.uniform(-np.pi, np.pi)
        q_new = S.ik(robot, pose, ns_new, b)
        if E.arm_angle_status(robot, q_new).ok:
            assert abs(np.angle(np.exp(1j * (E.arm_angle(robot, q_new) - ns_new)))) < 1e-9


def test_all_eight_branches(robot: Robot, rng) -> None:
    q = _regular_qs(robot, rng, 1)[0]
    pose = robot.tool_pose(q)
    for signs in itertools.product((1, -1), repeat=3):
        q_b = S.ik(robot, pose, 0.7, signs)
        assert np.abs(robot.tool_pose(q_b).homogeneous - pose.homogeneous).max() < 1e-9
        assert S.branch(robot, q_b).as_tuple() == signs


def test_bad_input(robot: Robot) -> None:
    q = np.full(7, 0.5)
    pose = robot.tool_pose(q)
    far = pin.SE3(pose.rotation, pose.translation + np.array([2.0, 0, 0]))
    with pytest.raises(UnreachableError, match="out of reach.*by"):
        S.ik(robot, far, 0.0, (1, 1, 1))
    with pytest.raises(InputError, match="NaN"):
        S.ik(robot, pose, float("nan"), (1, 1, 1))
    bad = pose.homogeneous.copy()
    bad[0, 3] = np.nan
    with pytest.raises(InputError, match="NaN"):
        S.ik(robot, bad, 0.0, (1, 1, 1))
    for wrong in [(1, 0, 1), (1, 1), "abc", 3, (1, 2, 1)]:
        with pytest.raises(InputError, match="branch"):
            S.ik(robot, pose, 0.0, wrong)
    with pytest.raises(InputError, match="NaN"):
        E.arm_angle(robot, np.full(7, np.nan))
