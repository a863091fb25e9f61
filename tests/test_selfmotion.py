"""The self-motion's own torque terms (issue 32): the null-space impedance's gains bounded by the self-motion's
inertia (qpnso.control.selfmotion, qpnso.linalg), stable closed loops of every strategy on the bare LWR4+ in
MuJoCo, the friction compensation of the measured self-motion, and [M]'s active law as [M] V-A ran it (the
``gradient-impedance`` strategy, qpnso.control.virtual_arm)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pinocchio as pin
import pytest
from scipy.linalg import expm

import qpnso
from qpnso.control.config import STRATEGIES, ControllerConfig, Status
from qpnso.control.controller import Controller
from qpnso.control.selfmotion import impedance_gains, smooth_friction
from qpnso.control.virtual_arm import VirtualArm, saturated_gradient_velocity
from qpnso.errors import QpnsoError
from qpnso.lab.plant import Plant, PlantParameters
from qpnso.linalg import nullspace_factors, project_velocity, selfmotion_inertia
from qpnso.settings import SettingError

DT = 1e-3


@pytest.fixture(scope="module")
def bare() -> qpnso.Robot:
    """The LWR4+ without rotor inertia (the rigid-body arm [M] V-A states)."""
    return qpnso.load_robot("lwr4p", armature=np.zeros(7))


def null_basis(J: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """An orthonormal basis of ``ker J`` by NumPy's SVD (singular values below ``tol`` count as zero)."""
    _, s, vt = np.linalg.svd(J)
    rank = int(np.sum(s > tol))
    return vt[rank:].T


def reference_inertia(robot: qpnso.Robot, q: np.ndarray) -> float:
    """``zᵀAz`` of the unit null vector of Pinocchio's tool Jacobian, Pinocchio's mass matrix."""
    z = null_basis(robot.jacobian(q))
    assert z.shape[1] == 1
    return float(z[:, 0] @ robot.mass_matrix(q) @ z[:, 0])


def upper_only(M: np.ndarray) -> np.ndarray:
    """``M`` with garbage below the diagonal: the kernels read the upper triangle only."""
    out = M.copy()
    out[np.tril_indices_from(out, -1)] = 1e6
    return out


def kernel_inertia(A: np.ndarray, J: np.ndarray) -> float:
    LA, W, LL, ok = nullspace_factors(upper_only(A), J)
    assert ok
    return float(selfmotion_inertia(LA, W, LL))


# ------------------------------------------------------------------ the self-motion's inertia
def test_selfmotion_inertia_is_the_inertia_of_the_null_direction(bare) -> None:
    """1/trace(N A⁻¹) equals zᵀAz (z the unit null vector of Pinocchio's J by SVD) on 200 configurations: to
    1e-6 where J is well conditioned (σ_min > 0.05), and never above it (the regularisation of JA⁻¹Jᵀ by 1e-12 of
    its trace, about 1e5 on the bare arm, errs low: 4e-5 at σ_min = 2e-3)."""
    rng = np.random.default_rng(3)
    errors, values = [], []
    for _ in range(200):
        q = bare.random_q(rng, 0.2)
        J = bare.jacobian(q)
        sigma = np.linalg.svd(J, compute_uv=False)[-1]
        if sigma < 1e-3:
            continue
        ref = reference_inertia(bare, q)
        errors.append((kernel_inertia(bare.mass_matrix(q), J) / ref - 1.0, sigma))
        values.append(ref)
    rel, sigma = np.array(errors).T
    assert len(values) > 150 and rel.max() < 1e-10 and rel.min() > -1e-4
    assert np.abs(rel[sigma > 0.05]).max() < 1e-6
    assert min(values) < 0.01 < 0.03 < np.median(values)  # (the bare arm's self-motion is light: 0.003–0.2 kg·m²)


def test_selfmotion_inertia_of_a_two_dimensional_null_space_is_conservative(bare) -> None:
    """With joints 2 and 4 at 0 (the axes of joints 1, 3 and 5 on one line) ``ker J`` is a plane: the kernel's value is
    at most the least inertia over the plane's directions (brute force over 7200 unit vectors, which agrees with
    the least eigenvalue of ZᵀAZ) and at least half of it (a trace of two terms)."""
    q = np.array([0.3, 0.0, 0.5, 0.0, 0.4, 0.8, 0.2])
    J, A = bare.jacobian(q), bare.mass_matrix(q)
    Z = null_basis(J)
    assert Z.shape[1] == 2
    angles = np.linspace(0.0, np.pi, 7200, endpoint=False)
    U = Z @ np.vstack([np.cos(angles), np.sin(angles)])
    brute = float(np.min(np.einsum("ik,ij,jk->k", U, A, U)))
    assert brute == pytest.approx(np.linalg.eigvalsh(Z.T @ A @ Z)[0], rel=1e-6)
    m = kernel_inertia(A, J)
    assert 0.5 * brute * (1 - 1e-6) <= m <= brute * (1 + 1e-6)


def test_the_tick_reports_the_selfmotion_inertia_and_the_damping_it_applied(bare) -> None:
    """Command.nullspace_inertia is zᵀAz at the tick's q (CasADi's A and J against Pinocchio's), and the damping
    applied is joint_damping where the bound allows it, the bound ``margin·m/dt`` where it does not."""
    rng = np.random.default_rng(5)
    ctrl = Controller(bare, ControllerConfig(strategy="damped"))
    seen = set()
    for _ in range(40):
        q = bare.random_q(rng, 0.4)
        if np.linalg.svd(bare.jacobian(q), compute_uv=False)[-1] < 1e-2:
            continue
        ctrl.reset(q)
        cmd = ctrl.step(q, np.zeros(7))
        m = reference_inertia(bare, q)
        assert cmd.nullspace_inertia == pytest.approx(m, rel=1e-6)
        bound = 0.5 * m / DT
        assert cmd.nullspace_damping == pytest.approx(min(10.0, bound), rel=1e-6)
        seen.add(bound < 10.0)
    assert seen == {True, False}  # (both cases met)


# ------------------------------------------------------------------ the gains' bounds
def zoh_loop(m: float, K: float, D: float, dt: float = DT) -> np.ndarray:
    """The self-motion's loop over one tick, state (x, ν): ``m ν̇ = u`` with ``u = −K x − D ν`` taken at the
    tick's start and held (zero-order hold by the matrix exponential of the augmented system, not the
    closed form the module derives)."""
    aug = np.zeros((3, 3))
    aug[0, 1], aug[1, 2] = 1.0, 1.0 / m
    E = expm(aug * dt)
    phi, gamma = E[:2, :2], E[:2, 2:]
    return phi - gamma @ np.array([[K, D]])


def test_impedance_gains_keep_the_held_torque_loop_stable() -> None:
    """Over inertias 1e-4–1 kg·m², stiffnesses 0–1e4 N·m/rad, dampings 0–100 N·m·s/rad and damping ratios 0,
    0.1, 1: the bounded gains follow their formula and the loop's poles (zero-order hold) are inside the unit
    circle — the damper's at 1 − D·dt/m ≥ 1 − margin: no pole on the negative axis; the unbounded gains of the
    same grid are not always (the bound is what makes the difference)."""
    margin = 0.5
    unstable_before = 0
    for m in (1e-4, 1e-3, 3.4e-3, 0.03, 1.0):
        for K in (0.0, 10.0, 100.0, 1e3, 1e4):
            for D in (0.0, 0.1, 10.0, 100.0):
                for zeta in (0.0, 0.1, 1.0):
                    k, d = impedance_gains(K, D, zeta, m, DT, margin)
                    wanted = D + 2 * zeta * np.sqrt(K * m)
                    assert d == pytest.approx(min(max(wanted, K * DT), margin * m / DT), rel=1e-12)
                    assert k == pytest.approx(min(K, d / DT), rel=1e-12) and d * DT / m <= margin * (1 + 1e-12)
                    if k == 0.0 and d == 0.0:
                        continue
                    poles = np.linalg.eigvals(zoh_loop(m, k, d))
                    if k == 0.0:  # (x is not fed back: a pole at 1, the damper's at 1 − b ∈ [1 − margin, 1))
                        assert sorted(poles.real)[0] == pytest.approx(1 - d * DT / m, abs=1e-9)
                        assert sorted(poles.real)[0] >= 1 - margin - 1e-9
                    else:
                        assert np.abs(poles).max() < 1.0, (m, K, D, zeta, k, d, poles)
                    if np.abs(np.linalg.eigvals(zoh_loop(m, K, wanted))).max() > 1.0 + 1e-9:
                        unstable_before += 1
    assert unstable_before > 20
    assert impedance_gains(30.0, 10.0, 0.0, 0.0, DT, margin) == (0.0, 0.0)  # (no inertia: no impedance)


def test_the_margin_is_a_checked_setting() -> None:
    for bad in (0.0, 2.0, -1.0):
        with pytest.raises(SettingError, match="nullspace_damping_margin"):
            ControllerConfig(nullspace_damping_margin=bad)
    for bad in (-0.1, 1.5):
        with pytest.raises(SettingError, match="friction_compensation"):
            ControllerConfig(friction_compensation=bad)
    for bad in (0.0, -1e-4, float("nan")):
        with pytest.raises(SettingError, match="friction_compensation_speed"):
            ControllerConfig(friction_compensation_speed=bad)


# ------------------------------------------------------------------ closed loops on the MuJoCo plant
NU0 = 0.1  # rad/s: the self-motion velocity a run starts with (twin: 0)
RUN_S = 1.0


def frictionless_plant(robot: qpnso.Robot) -> Plant:
    """The MuJoCo plant of ``robot`` without joint friction (nothing but the controller damps the self-motion),
    no hand, at its default 0.5 ms step (two per tick: close to the continuous plant)."""
    params = PlantParameters.draw(robot)
    return Plant(robot, replace(params, tau_coulomb=0.0 * params.tau_coulomb, damping=0.0 * params.damping))


def selfmotion_speed(robot: qpnso.Robot, strategy: str, q0: np.ndarray, nu0: float, margin: float | None = None):
    """The self-motion velocity ``zᵀq̇`` (rad/s; z the unit null vector, its sign kept continuous) of each tick of
    a run from ``q0`` started with ``nu0·z``, the tool free, friction compensation off (the plant has none), or
    None when the run stopped (a joint too fast for the controller, not finite); ``margin`` replaces the damping
    bound's (1e9: none, the law of before)."""
    ctrl = Controller(robot, ControllerConfig(strategy=strategy, friction_compensation=0.0))
    if margin is not None:
        ctrl.records.params[0]["nullspace_damping_margin"] = margin
    plant = frictionless_plant(robot)
    z = null_basis(robot.jacobian(q0))[:, 0]
    plant.reset(q0, nu0 * z)
    ctrl.reset(q0)
    out = []
    try:
        for _ in range(round(RUN_S / DT)):
            q, dq = plant.q, plant.dq
            zk = null_basis(robot.jacobian(q))[:, 0]
            z = zk if zk @ z > 0 else -zk
            out.append(float(z @ dq))
            tau = ctrl.step(q, dq).tau
            for _ in range(2):
                plant.step(tau)
    except QpnsoError:
        return None
    return np.array(out) if np.all(np.isfinite(out)) else None


def settles(delta: np.ndarray | None, nu0: float) -> str:
    """The criterion, fixed before any run: the difference ``δν`` between the run started with ``nu0`` and its
    twin from rest (what the strategy's own drive does is in both) ran to the end; never exceeded 1.1·nu0 (no
    growth); is below 0.1·nu0 over the last 0.1 s (decayed); and never changed sign on two ticks running while
    above 0.01·nu0 (no pole on the negative axis: a damper gain above m/dt).  Returns "" or what failed."""
    if delta is None:
        return "stopped"
    big = np.abs(delta) > 0.01 * nu0
    flips = (delta[:-2] * delta[1:-1] < 0) & (delta[1:-1] * delta[2:] < 0) & big[:-2]
    fails = [
        "grew" if np.abs(delta).max() > 1.1 * nu0 else "",
        "did not decay" if np.abs(delta[-100:]).max() > 0.1 * nu0 else "",
        "rang at the tick rate" if flips.any() else "",
    ]
    return ", ".join(f for f in fails if f)


def response(robot, strategy, q0, margin=None) -> np.ndarray | None:
    moved = selfmotion_speed(robot, strategy, q0, NU0, margin)
    rest = selfmotion_speed(robot, strategy, q0, 0.0, margin)
    return None if moved is None or rest is None else moved - rest


_LIGHT: dict[str, np.ndarray] = {}


def light_configuration(robot: qpnso.Robot) -> np.ndarray:
    """The configuration of least self-motion inertia among 2000 seeded ones 0.5 rad inside the limits, J
    well conditioned (σ_min > 0.05) and the elbow inside its ROM at a reset there: the bare wrist's
    self-motion (m ≈ 0.004 kg·m², against 0.05 at the hold scenario's start)."""
    if "q" not in _LIGHT:
        rng = np.random.default_rng(0)
        candidates = []
        for _ in range(2000):
            q = robot.random_q(rng, 0.5)
            if np.linalg.svd(robot.jacobian(q), compute_uv=False)[-1] > 0.05:
                candidates.append((reference_inertia(robot, q), q))
        ctrl = Controller(robot, ControllerConfig(strategy="damped"))
        for _, q in sorted(candidates, key=lambda c: c[0]):
            ctrl.reset(q)
            if not ctrl.step(q, np.zeros(7)).status & (Status.ELBOW_OUTSIDE_ROM | Status.ELBOW_DROPPED):
                _LIGHT["q"] = q
                break
    return _LIGHT["q"]


def hold_start(robot: qpnso.Robot) -> np.ndarray:
    from qpnso.lab.scenarios import load_scenario

    return load_scenario("hold").start(robot)


@pytest.mark.parametrize("where", ["light", "hold"])
@pytest.mark.parametrize("strategy", STRATEGIES)
def test_every_strategy_settles_a_selfmotion_on_the_bare_arm(bare, strategy: str, where: str) -> None:
    """Must hold: every strategy's closed loop on the bare LWR4+ in MuJoCo (dt = 1 ms, no friction, no hand),
    started with a self-motion of 0.1 rad/s, settles it by :func:`settles`' criterion — at the lightest
    self-motion found (:func:`light_configuration`) and at the hold scenario's start."""
    q0 = light_configuration(bare) if where == "light" else hold_start(bare)
    if where == "light":
        assert reference_inertia(bare, q0) < 0.005  # (10 N·m·s/rad is beyond 2m/dt here)
    why = settles(response(bare, strategy, q0), NU0)
    assert why == "", f"{strategy} at the {where} configuration: {why}"


@pytest.mark.parametrize("strategy", ["damped", "qp"])
def test_the_unbounded_damping_of_before_does_not_settle(bare, strategy: str) -> None:
    """Positive control: the same runs with the damping bound taken out (the law before issue 32, D = 10
    N·m·s/rad = 2.9 m/dt at the light configuration) fail the criterion."""
    assert settles(response(bare, strategy, light_configuration(bare), margin=1e9), NU0) != ""


# ------------------------------------------------------------------ friction compensation
def dynamically_consistent_null(robot: qpnso.Robot, q: np.ndarray) -> np.ndarray:
    """``N = I − A⁻¹Jᵀ(JA⁻¹Jᵀ)⁻¹J`` with NumPy inverses."""
    A_inv = np.linalg.inv(robot.mass_matrix(q))
    J = robot.jacobian(q)
    return np.eye(robot.nq) - A_inv @ J.T @ np.linalg.inv(J @ A_inv @ J.T) @ J


def compensation(ctrl: Controller, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
    """``τ − g(q)`` (N·m) of a tick of a controller with no null-space impedance (damped, D = 0)."""
    ctrl.reset(q)
    return ctrl.step(q, dq).tau - ctrl.robot.gravity(q)


def test_friction_compensation_is_the_model_at_the_measured_selfmotion(bare) -> None:
    """τ − g(q) = f̂(N q̇) for a measured q̇ (N by NumPy inverses, f̂ the robot's friction model): in full by
    default, half at ``friction_compensation`` 0.5, none at 0; to the projector's precision (JA⁻¹Jᵀ is
    regularised by 1e-12 of its trace: N q̇ to ~5e-7 rad/s on the bare arm, 1e-5 N·m through f̂'s slope of
    19 N·m·s/rad at rest)."""
    rng = np.random.default_rng(2)
    controllers = {
        frac: Controller(bare, ControllerConfig(strategy="damped", joint_damping=0.0, friction_compensation=frac))
        for frac in (1.0, 0.5, 0.0)
    }
    for _ in range(10):
        q = bare.random_q(rng, 0.4)
        dq = 0.3 * rng.standard_normal(7)
        expected = bare.friction_torque(dynamically_consistent_null(bare, q) @ dq)
        for frac, ctrl in controllers.items():
            np.testing.assert_allclose(compensation(ctrl, q, dq), frac * expected, rtol=0, atol=2e-5)


@pytest.mark.parametrize("speed", [0.05, 1e-3])
def test_the_compensation_speed_sets_the_laws_slope(bare, speed) -> None:
    """With ``friction_compensation_speed`` v, τ − g(q) = τ_max·(2/π)·atan(N q̇ / v) (N by NumPy inverses): half
    of τ_max at v; at 0.05 rad/s the robot's own model (β = 20 s/rad), so the setting's None and 0.05 agree."""
    rng = np.random.default_rng(3)
    cfg = ControllerConfig(strategy="damped", joint_damping=0.0, friction_compensation_speed=speed)
    ctrl = Controller(bare, cfg)
    tau_max = bare.friction.tau_max
    for _ in range(5):
        q = bare.random_q(rng, 0.4)
        z = dynamically_consistent_null(bare, q) @ (0.01 * rng.standard_normal(7))
        expected = tau_max * (2.0 / np.pi) * np.arctan(z / speed)
        np.testing.assert_allclose(compensation(ctrl, q, z), expected, rtol=0, atol=2e-5 * 0.05 / speed)
        if speed == 0.05:
            np.testing.assert_allclose(expected, bare.friction_torque(z), atol=1e-12)


def test_the_surgeons_own_motion_gets_no_compensation(bare) -> None:
    """A velocity a tool force gives the arm from rest, ``A⁻¹Jᵀf`` (the range of J̄ = A⁻¹JᵀΛ), gets none (its
    friction is the surgeon's to feel; 1e-5 N·m: the projector's precision on the bare arm, against f̂'s 1.5 N·m)
    and a self-motion ``z`` gets f̂(z) whole."""
    rng = np.random.default_rng(4)
    ctrl = Controller(bare, ControllerConfig(strategy="damped", joint_damping=0.0))
    for _ in range(10):
        q = bare.random_q(rng, 0.4)
        J, A = bare.jacobian(q), bare.mass_matrix(q)
        tool = np.linalg.solve(A, J.T @ rng.standard_normal(6))
        np.testing.assert_allclose(compensation(ctrl, q, 0.5 * tool / np.abs(tool).max()), 0.0, atol=1e-5)
        z = 0.2 * null_basis(J)[:, 0]
        np.testing.assert_allclose(compensation(ctrl, q, z), bare.friction_torque(z), atol=2e-5)


def test_project_velocity_against_numpy(bare) -> None:
    """N q̇ against NumPy's inverses where J is well conditioned (σ_min > 0.05; nearer a singularity the
    regularisation of JA⁻¹Jᵀ dominates), in ker J, A-orthogonal to the rest of q̇."""
    rng = np.random.default_rng(6)
    for _ in range(10):
        q = bare.random_q(rng, 0.3)
        J, A = bare.jacobian(q), bare.mass_matrix(q)
        if np.linalg.svd(J, compute_uv=False)[-1] < 0.05:
            continue
        dq = rng.standard_normal(7)
        _, W, LL, ok = nullspace_factors(upper_only(A), J)
        assert ok
        part = project_velocity(J, W, LL, dq)
        np.testing.assert_allclose(part, dynamically_consistent_null(bare, q) @ dq, atol=1e-5)  # (|dq| ~ 1 rad/s)
        assert np.abs(J @ part).max() < 1e-6
        rest = dq - part  # the kinetic energy splits: the two parts are A-orthogonal
        assert abs(rest @ A @ part) < 1e-5 * (dq @ A @ dq)


def test_smooth_friction_is_the_robots_model(bare) -> None:
    dq = np.linspace(-2.0, 2.0, 7)
    f = bare.friction
    np.testing.assert_allclose(smooth_friction(dq, f.tau_max, f.beta), bare.friction_torque(dq), rtol=1e-14)


# ------------------------------------------------------------------ [M]'s law as [M] ran it
def test_the_virtual_arm_is_anchored_at_the_measured_pose_and_relaxes_as_the_law(bare) -> None:
    """Anchored, the virtual arm's tool is at the measured pose (Pinocchio; 1e-10 the next tick); one tick of
    [M 20]–[M 22] relaxes its self-motion velocity as the exact solution of ``m ν̇ = −k_d(ν − ν_t)`` (m = zᵀAz,
    ν_t the saturated gradient velocity's null part, computed here independently) and moves it along z."""
    ctrl = Controller(bare, ControllerConfig(strategy="gradient-impedance"))
    cfg = ctrl.config
    arm = VirtualArm(bare, ctrl.cost, cfg.gradient_kp, cfg.gradient_kd, cfg.gradient_omega_max)
    q = hold_start(bare)
    arm.reset(q + np.radians([2, -1, 3, 0.5, -2, 1, 1]))  # (a virtual arm off the measured pose)
    pose = bare.tool_pose(q)
    for tol in (1e-6, 1e-10):  # (a step from below 1e-4 leaves its residual to the next tick)
        assert arm.anchor(pose.rotation, pose.translation)
        there = bare.tool_pose(arm.q)
        assert np.abs(there.translation - pose.translation).max() < tol
        assert np.abs(pin.log3(there.rotation @ pose.rotation.T)).max() < tol
    z = null_basis(bare.jacobian(arm.q))[:, 0]
    arm.dq = 0.4 * z
    m = float(z @ bare.mass_matrix(arm.q) @ z)
    grad = ctrl.cost.gradient(arm.q)
    nu_t = float(z @ saturated_gradient_velocity(grad, cfg.gradient_kp, cfg.gradient_kd, cfg.gradient_omega_max))
    q_before = arm.q.copy()
    arm.advance(DT)
    rate = cfg.gradient_kd / m
    nu = nu_t + (0.4 - nu_t) * np.exp(-rate * DT)
    np.testing.assert_allclose(arm.dq, nu * z, atol=1e-12)
    moved = nu_t * DT + (0.4 - nu_t) * (1 - np.exp(-rate * DT)) / rate
    np.testing.assert_allclose(arm.q - q_before, moved * z, atol=1e-12)


def test_gradient_impedance_lowers_the_cost_of_a_held_tool_and_does_not_move_it() -> None:
    """The hold protocol (scenario ``hold``, 6 s, the surgeon holding still, no tremor) with the plant's joint
    friction off (the strategy's own torque, not the friction's reaction, is what may move the tool): the cost
    falls, the elbow turns over 20°, the tool moves < 1 mm and the hand does < 0.05 J.  At ``gradient_omega_max``
    = 1 rad/s (qpnso's nullspace_speed_max): at [M 20]'s 10 rad/s the bare arm's self-motion reaches 3.8 rad/s
    and its centrifugal terms, which qpnso's torque does not compensate ([M 22]'s u_t), move the held tool 20 mm
    (0.16 mm with u_t added, measured; docs/method.md §7.7)."""
    from qpnso.lab.scenarios import simulate_scenario
    from qpnso.lab.simulation import SimulationConfig

    quiet = SimulationConfig(surgeon={"tremor_rms_m": 0.0}, plant_friction=False)
    settings = {"gradient_omega_max": 1.0, "friction_compensation": 0.0}
    run = simulate_scenario("hold", "gradient-impedance", settings=settings, simulation=quiet)
    s, cost = run.summary, run.arrays["cost"]
    assert cost[-1] < cost[0] - 0.3 and s["elbow_mobility_deg"] > 20.0
    assert s["tool_displacement_max_m"] < 1e-3 and s["hand_work_J"] < 0.05


@pytest.mark.parametrize("strategy", STRATEGIES)
def test_a_tool_moved_off_a_singular_configuration_is_no_internal_error(bare, strategy) -> None:
    """At the straight arm (q = 0: J singular) the tool moved by 2e-4 rad of joints 2 and 4: every strategy
    gives a finite command and no INTERNAL_ERROR (gradient-impedance's virtual arm solved JJᵀ there and stopped
    every tick with "LinAlgError: Singular matrix"; now J⁺'s least-norm least-squares step)."""
    ctrl = Controller(bare, ControllerConfig(strategy=strategy))
    q = np.zeros(7)
    ctrl.reset(q)
    ctrl.step(q, np.zeros(7))
    moved = q.copy()
    moved[[1, 3]] = 2e-4, -2e-4
    for _ in range(3):
        cmd = ctrl.step(moved, np.zeros(7))
        assert not cmd.status & Status.INTERNAL_ERROR, cmd.status
        assert np.all(np.isfinite(cmd.tau)) and np.all(np.isfinite(cmd.dq))


def test_no_damping_ratio_takes_no_square_root() -> None:
    """A negative stiffness with no damping ratio (ζ = 0) gives finite gains, as the law has no √(K·m) term then
    (``2·0·√(−30·m)`` was NaN: the tick stopped with INTERNAL_ERROR on every tick of such a controller)."""
    K, D = impedance_gains(-30.0, 10.0, 0.0, 0.04, DT, 0.5)
    assert math.isfinite(K) and math.isfinite(D) and D == pytest.approx(min(10.0, 0.5 * 0.04 / DT))
