"""Robot loading, input checks, and the numeric API against independent computations."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from conftest import ALL_ROBOTS

import qpnso


@pytest.mark.parametrize("name", ALL_ROBOTS)
def test_shipped_robots_load_with_limits(name: str) -> None:
    robot = qpnso.load_robot(name)
    assert robot.nq == 7
    assert np.all(robot.q_min < robot.q_max)
    assert np.all(robot.dq_max > 0)
    assert robot.friction.tau_max.shape == (7,)


def test_unknown_robot_names_the_choices() -> None:
    with pytest.raises(qpnso.RobotNotFoundError, match="unknown robot 'ur5'.*lwr4p"):
        qpnso.load_robot("ur5")


def test_missing_urdf_file() -> None:
    with pytest.raises(qpnso.RobotNotFoundError, match="not found"):
        qpnso.load_robot("/nonexistent/arm.urdf")


def test_malformed_urdf(tmp_path) -> None:
    bad = tmp_path / "bad.urdf"
    bad.write_text("<robot name='x'><link name='a'></robot>")
    with pytest.raises(qpnso.ModelError, match="cannot parse"):
        qpnso.load_robot(bad)


def test_unknown_tool_frame_lists_frames() -> None:
    with pytest.raises(qpnso.FrameNotFoundError, match="'nope'.*link_7"):
        qpnso.load_robot("lwr4p", tool_frame="nope")


def test_user_urdf_path_loads_like_shipped() -> None:
    robot = qpnso.load_robot(qpnso.model.robot.MODELS_DIR / "lwr4p.urdf")
    ref = qpnso.load_robot("lwr4p")
    q = np.linspace(-1, 1, 7)
    assert robot.name == "lwr4p"
    assert np.allclose(robot.tool_pose(q).homogeneous, ref.tool_pose(q).homogeneous)


def test_tool_offset_is_applied_in_the_flange_frame(lwr, rng) -> None:
    offset = np.array([0.01, -0.02, 0.15])
    robot = qpnso.load_robot("lwr4p", tool_offset=offset)
    q = lwr.random_q(rng)
    flange = lwr.tool_pose(q)
    tool = robot.tool_pose(q)
    assert np.allclose(tool.translation, flange.translation + flange.rotation @ offset, atol=1e-12)
    assert np.allclose(tool.rotation, flange.rotation, atol=1e-12)


@pytest.mark.parametrize(
    "bad, match",
    [
        (np.zeros(6), r"shape \(7,\)"),
        (np.full(7, np.nan), "NaN"),
        ([0, 0, 0, np.inf, 0, 0, 0], "NaN or inf at index \\[3\\]"),
        ("abc", "numeric"),
    ],
)
def test_bad_q_is_rejected_with_a_clear_error(lwr, bad, match) -> None:
    with pytest.raises(qpnso.InputError, match=match):
        lwr.tool_pose(bad)


def test_joint_outside_limits_is_named(lwr) -> None:
    q = np.zeros(7)
    q[1] = np.radians(125)
    with pytest.raises(qpnso.JointLimitError, match=r"q\[1\] \(joint_2\) = 125.000 deg"):
        lwr.check_q(q)


def test_jacobian_matches_finite_differences_of_the_tool_pose(lwr, rng) -> None:
    """Independent check of the world-aligned convention: linear rows d(p)/dq,
    angular rows from d(R) Rᵀ."""
    q = lwr.random_q(rng)
    jac = lwr.jacobian(q)
    h = 1e-6
    for k in range(7):
        dq = np.zeros(7)
        dq[k] = h
        plus, minus = lwr.tool_pose(q + dq), lwr.tool_pose(q - dq)
        assert np.allclose(jac[:3, k], (plus.translation - minus.translation) / (2 * h), atol=1e-8)
        omega = pin.log3(plus.rotation @ minus.rotation.T) / (2 * h)
        assert np.allclose(jac[3:, k], omega, atol=1e-7)


def test_mass_matrix_is_symmetric_positive_definite(lwr, rng) -> None:
    for _ in range(10):
        a = lwr.mass_matrix(lwr.random_q(rng))
        assert np.allclose(a, a.T)
        assert np.linalg.eigvalsh(a)[0] > 0


def test_mass_matrix_matches_kinetic_energy(rng) -> None:
    """½ dqᵀ A dq equals the links' kinetic energy computed by Pinocchio from their velocities (a copy of the
    model without rotors) plus the rotors' ½ Σ armature·dq² (one rotor inertia per joint, each different)."""
    robot = qpnso.load_robot("lwr4p", armature=np.linspace(0.02, 0.14, 7))
    q, dq = robot.random_q(rng), rng.normal(size=7)
    links = robot.model.copy()
    links.armature = np.zeros(7)
    energy = pin.computeKineticEnergy(links, links.createData(), q, dq)
    energy += 0.5 * np.sum(robot.model.armature * dq**2)
    assert np.isclose(0.5 * dq @ robot.mass_matrix(q) @ dq, energy, rtol=1e-12)


def test_load_robot_with_armature() -> None:
    """None keeps the model's rotor inertia (``models/armature.json``), a number sets it on every joint, anything
    else is refused by name; the LWR4+'s own is 0 ([M]'s rigid-body plant)."""
    from qpnso.errors import ConfigError
    from qpnso.model.robot import load_robot_with_armature

    assert np.array_equal(load_robot_with_armature("lwr4p", None).model.armature, np.zeros(7))
    assert np.array_equal(
        load_robot_with_armature("iiwa14", None).model.armature, qpnso.load_robot("iiwa14").model.armature
    )
    assert np.array_equal(load_robot_with_armature("lwr4p", 0.03).model.armature, np.full(7, 0.03))
    for bad in (-0.01, float("nan"), float("inf"), "0.1", True):
        with pytest.raises(ConfigError, match="armature_kgm2"):
            load_robot_with_armature("lwr4p", bad)  # type: ignore[arg-type]


def test_friction_is_the_smooth_coulomb_model(lwr) -> None:
    dq = np.array([0.0, 1e-3, -0.05, 0.5, -5.0, 100.0, -100.0])
    tau = lwr.friction_torque(dq)
    expected = 1.5 * 2 / np.pi * np.arctan(lwr.friction.beta * dq)
    assert np.allclose(tau, expected)
    assert tau[0] == 0 and abs(tau[5] - 1.5) < 0.01 and abs(tau[6] + 1.5) < 0.01


def test_friction_override_is_checked() -> None:
    with pytest.raises(qpnso.InputError, match="beta"):
        qpnso.model.robot.friction_from_lists([1.5] * 7, [0.0] * 7, 7)
    custom = qpnso.model.robot.friction_from_lists([2.0] * 7, [10.0] * 7, 7)
    robot = qpnso.load_robot("lwr4p", friction=custom)
    assert np.allclose(robot.friction_torque(np.full(7, 1e6)), 2.0, atol=1e-4)


@pytest.mark.skipif("panda" in ALL_ROBOTS, reason="example-robot-data is installed")
def test_panda_without_example_robot_data_says_how_to_install() -> None:
    with pytest.raises(qpnso.RobotNotFoundError, match="example-robot-data"):
        qpnso.load_robot("panda")
