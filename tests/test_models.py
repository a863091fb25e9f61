"""The shipped robot descriptions (models/*.urdf, models/friction.json).

Checked with Pinocchio directly against the numbers documented in
models/README.md, and against an independent kinematic description (standard
DH parameters, evaluated by hand here) at random configurations.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import pinocchio as pin
import pytest

from qpnso.model.robot import MODELS_DIR

MODELS = MODELS_DIR  # the package's own data: what a wheel ships
JOINTS = [f"joint_{i}" for i in range(1, 8)]
N_RANDOM = 20


@dataclass(frozen=True)
class Spec:
    """Documented data of one robot (models/README.md); angles in deg, lengths in m."""

    joint_z_m: tuple[float, ...]  # joint origins along z, parent frame
    tool_z_m: float  # tool frame beyond joint_7
    axes: tuple[tuple[float, float, float], ...]  # world axes at q = 0
    limit_deg: tuple[float, ...]
    velocity_deg_s: tuple[float, ...]
    effort_Nm: tuple[float, ...]
    shoulder_z_m: float
    upper_arm_m: float  # shoulder -> elbow
    forearm_m: float  # elbow -> wrist
    hand_m: float  # wrist -> flange (tool frame)
    dh_alpha_deg: tuple[float, ...]  # standard DH, all a = 0
    cylinders_m: tuple[tuple[float, float], ...]  # (length, radius) of base_link, link_1..7
    total_mass_kg: tuple[float, float]  # plausible range, base included


Z, Y, NY = (0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (0.0, -1.0, 0.0)
LWR_ALPHA = (90.0, -90.0, -90.0, 90.0, 90.0, -90.0, 0.0)
SPECS = {
    "lwr4p": Spec(
        joint_z_m=(0.11, 0.2005, 0.20, 0.20, 0.20, 0.19, 0.078),
        tool_z_m=0.0,
        axes=(Z, NY, Z, Y, Z, NY, Z),
        limit_deg=(170, 120, 170, 120, 170, 120, 170),
        velocity_deg_s=(110, 110, 128, 128, 204, 184, 184),
        effort_Nm=(176, 176, 100, 100, 100, 38, 38),
        shoulder_z_m=0.3105,
        upper_arm_m=0.40,
        forearm_m=0.39,
        hand_m=0.078,
        dh_alpha_deg=LWR_ALPHA,
        cylinders_m=(
            (0.11, 0.07),
            (0.2005, 0.065),
            (0.20, 0.065),
            (0.20, 0.065),
            (0.20, 0.065),
            (0.19, 0.065),
            (0.078, 0.06),
            (0.02, 0.035),
        ),
        total_mass_kg=(12.0, 17.0),
    ),
    "iiwa14": Spec(
        joint_z_m=(0.1575, 0.2025, 0.2045, 0.2155, 0.1845, 0.2155, 0.081),
        tool_z_m=0.045,
        axes=(Z, Y, Z, NY, Z, Y, Z),
        limit_deg=(170, 120, 170, 120, 170, 120, 175),
        velocity_deg_s=(85, 85, 100, 75, 130, 135, 135),
        effort_Nm=(320, 320, 176, 176, 110, 40, 40),
        shoulder_z_m=0.36,
        upper_arm_m=0.42,
        forearm_m=0.40,
        hand_m=0.126,
        dh_alpha_deg=tuple(-a for a in LWR_ALPHA),
        cylinders_m=(
            (0.1575, 0.10),
            (0.2025, 0.09),
            (0.2045, 0.09),
            (0.2155, 0.08),
            (0.1845, 0.08),
            (0.2155, 0.07),
            (0.081, 0.06),
            (0.045, 0.04),
        ),
        total_mass_kg=(20.0, 32.0),
    ),
}
ROBOTS = list(SPECS)


@pytest.fixture(scope="module", params=ROBOTS)
def robot(request: pytest.FixtureRequest) -> tuple[str, pin.Model, Spec]:
    model = pin.buildModelFromUrdf(str(MODELS / f"{request.param}.urdf"))
    return request.param, model, SPECS[request.param]


def _random_q(model: pin.Model, rng: np.random.Generator) -> np.ndarray:
    return rng.uniform(model.lowerPositionLimit, model.upperPositionLimit)


def _placements(model: pin.Model, q: np.ndarray) -> tuple[pin.Data, pin.SE3]:
    """Joint placements and the tool frame placement in the world."""
    data = model.createData()
    pin.framesForwardKinematics(model, data, q)
    return data, data.oMf[model.getFrameId("tool")]


def _centres(model: pin.Model, q: np.ndarray) -> tuple[np.ndarray, ...]:
    """Shoulder, elbow, wrist centres (joint_2, joint_4, joint_6 origins) and flange (m, world)."""
    data, tool = _placements(model, q)
    jid = [model.getJointId(n) for n in ("joint_2", "joint_4", "joint_6")]
    return (*(data.oMi[j].translation.copy() for j in jid), tool.translation.copy())


def _dh_pose(alpha_deg: tuple[float, ...], d_m: list[float], q: np.ndarray) -> np.ndarray:
    """Standard DH forward kinematics (a = 0): prod Rz(q_i) Tz(d_i) Rx(alpha_i)."""
    T = np.eye(4)
    for qi, di, ai in zip(q, d_m, np.radians(alpha_deg)):
        cq, sq, ca, sa = np.cos(qi), np.sin(qi), np.cos(ai), np.sin(ai)
        A = np.array([[cq, -sq * ca, sq * sa, 0.0], [sq, cq * ca, -cq * sa, 0.0], [0.0, sa, ca, di], [0, 0, 0, 1]])
        T = T @ A
    return T


def test_joint_names_and_dof(robot):
    _, model, _ = robot
    assert model.nq == 7 and model.nv == 7
    assert list(model.names)[1:] == JOINTS
    assert model.existFrame("tool") and model.existFrame("base_link")


def test_limits_match_documented_values(robot):
    _, model, spec = robot
    rad = np.radians(spec.limit_deg)
    np.testing.assert_allclose(model.upperPositionLimit, rad, atol=1e-9)
    np.testing.assert_allclose(model.lowerPositionLimit, -rad, atol=1e-9)
    np.testing.assert_allclose(model.velocityLimit, np.radians(spec.velocity_deg_s), atol=1e-9)
    np.testing.assert_allclose(model.effortLimit, spec.effort_Nm)


def test_joint_axes_in_world_at_zero(robot):
    _, model, spec = robot
    data = model.createData()
    J = pin.computeJointJacobians(model, data, np.zeros(7))  # WORLD frame: angular rows = joint axes
    np.testing.assert_allclose(J[3:, :].T, np.array(spec.axes), atol=1e-12)


def test_centres_at_zero_are_on_the_vertical(robot):
    _, model, spec = robot
    s, e, w, f = _centres(model, np.zeros(7))
    expected = np.cumsum([spec.shoulder_z_m, spec.upper_arm_m, spec.forearm_m, spec.hand_m])
    for p, z in zip((s, e, w, f), expected):
        np.testing.assert_allclose(p, [0.0, 0.0, z], atol=1e-12)
    _, tool = _placements(model, np.zeros(7))
    np.testing.assert_allclose(tool.rotation, np.eye(3), atol=1e-12)


def test_segment_lengths_are_invariant(robot):
    _, model, spec = robot
    rng = np.random.default_rng(7)
    for _ in range(N_RANDOM):
        q = _random_q(model, rng)
        s, e, w, f = _centres(model, q)
        assert np.linalg.norm(e - s) == pytest.approx(spec.upper_arm_m, abs=1e-12)
        assert np.linalg.norm(w - e) == pytest.approx(spec.forearm_m, abs=1e-12)
        assert np.linalg.norm(f - w) == pytest.approx(spec.hand_m, abs=1e-12)
        np.testing.assert_allclose(s, [0.0, 0.0, spec.shoulder_z_m], atol=1e-12)


def test_tool_pose_matches_standard_dh(robot):
    """Independent chain: standard DH with d = (base-shoulder, 0, upper arm, 0, forearm, 0, hand)."""
    _, model, spec = robot
    d = [spec.shoulder_z_m, 0.0, spec.upper_arm_m, 0.0, spec.forearm_m, 0.0, spec.hand_m]
    rng = np.random.default_rng(11)
    for _ in range(N_RANDOM):
        q = _random_q(model, rng)
        _, tool = _placements(model, q)
        np.testing.assert_allclose(tool.homogeneous, _dh_pose(spec.dh_alpha_deg, d, q), atol=1e-12)


def _bodies(model: pin.Model) -> list[pin.Inertia]:
    """Inertia of base_link (merged into the universe body by Pinocchio) and link_1..7."""
    return [model.inertias[i] for i in range(8)]


def test_inertias_are_physically_consistent(robot):
    _, model, _ = robot
    for body in _bodies(model):
        assert body.mass > 0.0
        principal = np.linalg.eigvalsh(body.inertia)  # about the COM
        assert principal.min() > 0.0
        a, b, c = principal
        assert a + b >= c and a + c >= b and b + c >= a


def test_inertias_are_the_documented_solid_cylinders(robot):
    """[README: inertial parameters] I = diag(m(3r²+L²)/12, same, m r²/2) about the COM."""
    _, model, spec = robot
    for body, (length, radius) in zip(_bodies(model), spec.cylinders_m):
        m = body.mass
        side = m * (3 * radius**2 + length**2) / 12.0
        np.testing.assert_allclose(body.inertia, np.diag([side, side, m * radius**2 / 2.0]), rtol=1e-5)


def test_total_mass_is_plausible(robot):
    _, model, spec = robot
    total_with_base = sum(b.mass for b in _bodies(model))
    lo, hi = spec.total_mass_kg
    assert lo <= total_with_base <= hi
    assert pin.computeTotalMass(model) == pytest.approx(total_with_base - model.inertias[0].mass)


def test_urdf_friction_reaches_the_model(robot):
    _, model, _ = robot
    np.testing.assert_allclose(model.friction, np.full(7, 1.5))
    np.testing.assert_allclose(model.damping, np.zeros(7))


def test_friction_json():
    table = json.loads((MODELS / "friction.json").read_text())
    assert {"lwr4p", "iiwa14", "panda"} <= set(table)
    for name in ("lwr4p", "iiwa14", "panda"):
        tau, beta = np.array(table[name]["tau_max_Nm"]), np.array(table[name]["beta_s_per_rad"])
        assert tau.shape == (7,) and beta.shape == (7,)
        assert np.all(tau > 0) and np.all(beta > 0)
        assert table[name]["source"]
    np.testing.assert_allclose(table["lwr4p"]["tau_max_Nm"], 1.5)
    # README claim: with beta = 20 s/rad the smooth Coulomb torque [M 23] is half of tau_max at 0.05 rad/s.
    beta = np.array(table["lwr4p"]["beta_s_per_rad"])
    np.testing.assert_allclose((2 / np.pi) * np.arctan(beta * 0.05), 0.5, rtol=1e-12)
