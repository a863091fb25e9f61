"""The CasADi model agrees with Pinocchio to round-off on every shipped robot."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from conftest import ALL_ROBOTS

import qpnso


@pytest.mark.parametrize("name", ALL_ROBOTS)
def test_symbolic_model_matches_pinocchio(name: str, rng) -> None:
    # A tool offset with a rotation exercises frame placements beyond the flange.
    offset = pin.SE3(pin.rpy.rpyToMatrix(0.3, -0.2, 0.1), np.array([0.02, 0.01, 0.12]))
    robot = qpnso.load_robot(name, tool_offset=offset)
    sym = qpnso.SymbolicModel(robot.model)
    tool = sym.frame_placement(robot.tool_frame_id)
    fn = sym.function(
        "check",
        {
            "R": tool.R,
            "p": tool.p,
            "J": sym.frame_jacobian(robot.tool_frame_id),
            "A": sym.mass_matrix(),
            "g": sym.gravity_torque(),
        },
    )
    worst = 0.0
    for _ in range(50):
        q = robot.random_q(rng)
        out = fn(q=q)
        pose = robot.tool_pose(q)
        errors = [
            np.abs(np.array(out["R"]) - pose.rotation).max(),
            np.abs(np.array(out["p"]).ravel() - pose.translation).max(),
            np.abs(np.array(out["J"]) - robot.jacobian(q)).max(),
            np.abs(np.array(out["A"]) - robot.mass_matrix(q)).max(),
            np.abs(np.array(out["g"]).ravel() - robot.gravity(q)).max(),
        ]
        worst = max(worst, *errors)
    assert worst < 1e-10, f"largest disagreement with Pinocchio: {worst:.3e}"


def test_gravity_is_the_gradient_of_the_potential_energy(lwr, rng) -> None:
    """g(q) against Pinocchio's potential energy by central differences (an independent route)."""
    sym = qpnso.SymbolicModel(lwr.model)
    fn = sym.function("g", {"g": sym.gravity_torque()})
    data = lwr.model.createData()
    q = lwr.random_q(rng)
    h = 1e-6
    fd = [
        (
            pin.computePotentialEnergy(lwr.model, data, q + h * e)
            - pin.computePotentialEnergy(lwr.model, data, q - h * e)
        )
        / (2 * h)
        for e in np.eye(7)
    ]
    g = np.array(fn(q=q)["g"]).ravel()
    assert np.abs(g).max() > 1.0  # the arm does weigh something
    np.testing.assert_allclose(g, fd, rtol=0, atol=1e-6)


def test_every_joint_placement_matches(lwr, rng) -> None:
    sym = qpnso.SymbolicModel(lwr.model)
    fn = sym.function("joints", {f"p{j}": sym.oMi[j].p for j in range(1, 8)})
    q = lwr.random_q(rng)
    data = lwr.model.createData()
    pin.forwardKinematics(lwr.model, data, q)
    out = fn(q=q)
    for j in range(1, 8):
        assert np.allclose(np.array(out[f"p{j}"]).ravel(), data.oMi[j].translation, atol=1e-12)


def test_unsupported_joint_is_a_model_error() -> None:
    model = pin.Model()
    model.addJoint(0, pin.JointModelSpherical(), pin.SE3.Identity(), "ball")
    with pytest.raises(qpnso.ModelError, match="JointModelSpherical"):
        qpnso.SymbolicModel(model)
