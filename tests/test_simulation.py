"""The hands-on simulation's integrator against Pinocchio's ABA (explicit, tiny steps)."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

import qpnso
from qpnso.lab.simulation import HandModel, SimulationConfig, _integrate, _tool_state


def explicit_step(model, data, q, dq, tau, robot, tool_id, h, hand, ref):
    """Forward Euler with every force at the current velocity (the reference)."""
    tool = _tool_state(model, data, q, dq, tool_id)
    pin.computeJointJacobians(model, data, q)
    jac = pin.getFrameJacobian(model, data, tool_id, pin.LOCAL_WORLD_ALIGNED)
    total = tau + jac.T @ hand.wrench(ref, tool) - robot.friction.torque(dq)
    ddq = pin.aba(model, data, q, dq, total)
    return q + h * (dq + h * ddq), dq + h * ddq


def test_linearly_implicit_step_matches_aba_for_small_steps(lwr) -> None:
    model = lwr.model.copy()
    model.armature = np.full(7, 0.1)
    data = model.createData()
    rng = np.random.default_rng(3)
    q, dq = lwr.random_q(rng, margin=0.3), rng.normal(scale=0.3, size=7)
    tau = rng.normal(scale=5.0, size=7)
    hand = HandModel()
    tool = _tool_state(model, data, q, dq, lwr.tool_frame_id)
    ref = (tool[0] + 0.01, tool[1], np.zeros(3), np.zeros(3))
    h = 1e-6
    q1, dq1 = _integrate(model, data, q, dq, tau, lwr, lwr.tool_frame_id, h, hand, ref)
    q2, dq2 = explicit_step(model, data, q, dq, tau, lwr, lwr.tool_frame_id, h, hand, ref)
    accel = np.abs(dq2 - dq).max() / h
    # the two differ by O(h²·stiffness): relative to one step's change, ~1e-4 at h = 1 µs
    assert np.abs(dq1 - dq2).max() < 1e-3 * np.abs(dq2 - dq).max() + 1e-12
    assert np.abs(q1 - q2).max() < 1e-12 + 1e-3 * h * h * accel
    assert accel > 1.0  # the step really accelerates the joints


def test_stiff_friction_is_stable_at_the_control_rate(lwr) -> None:
    """With the default reflected inertia, friction (slope 19 N·m·s/rad) at 2 kHz only slows the joints."""
    model = lwr.model.copy()
    model.armature = np.full(7, SimulationConfig().armature)
    data = model.createData()
    q, dq = np.array([0.1, 0.6, -0.2, -1.3, 0.3, 0.9, 0.2]), np.full(7, 0.5)
    hand = HandModel(stiffness=0.0, damping=0.0, rotational_stiffness=0.0, rotational_damping=0.0)
    tool = _tool_state(model, data, q, dq, lwr.tool_frame_id)
    ref = (tool[0], tool[1], np.zeros(3), np.zeros(3))

    def kinetic(q, dq):
        return pin.computeKineticEnergy(model, model.createData(), q, dq)

    energy = [kinetic(q, dq)]
    for _ in range(200):  # gravity compensated, no hand: friction can only dissipate
        q, dq = _integrate(model, data, q, dq, lwr.gravity(q), lwr, lwr.tool_frame_id, 5e-4, hand, ref)
        energy.append(kinetic(q, dq))
    assert np.all(np.isfinite(dq))
    assert energy[-1] < 0.8 * energy[0]
    assert np.all(np.diff(energy) < 1e-6 * energy[0])


def test_bad_simulation_settings() -> None:
    with pytest.raises(qpnso.InputError, match="substeps"):
        SimulationConfig(substeps=0)
    with pytest.raises(qpnso.InputError, match="armature"):
        SimulationConfig(armature=-1.0)
