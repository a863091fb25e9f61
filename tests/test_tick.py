"""The control tick (qpnso/control/tick.py) on its records: each kernel against an independent computation
(Pinocchio, hand values, brute force), the problem a tick states against one built by hand from Pinocchio,
the line fast path against the general cascade on the same problems, and every way a tick can fail."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from conftest import HAS_PANDA, SRS_ROBOTS, kernel_signatures, limit_params, reference_arm_angle
from hypothesis import given, settings
from hypothesis import strategies as st

import qpnso
from qpnso.control import memory as M
from qpnso.control import tick
from qpnso.control.config import ControllerConfig, Status
from qpnso.control.controller import Controller
from qpnso.control.params import tick_params
from qpnso.qp import Level, LevelStatus
from qpnso.qp.backends import _Raw
from qpnso.records import new_record

DT = 1e-3
Q0 = np.array([0.1, 0.6, -0.2, -1.3, 0.3, 0.9, 0.2])


@pytest.fixture(scope="module")
def robot() -> qpnso.Robot:
    return qpnso.load_robot("lwr4p")


def random_rotation(rng: np.random.Generator, max_angle: float) -> np.ndarray:
    axis = rng.normal(size=3)
    return pin.exp3(axis / np.linalg.norm(axis) * rng.uniform(0, max_angle))


def assert_close(a, b, tol: float) -> None:
    """Two commands equal to ``tol`` (rad/s; N·m at 1e3·tol), with the same status and elbow."""
    np.testing.assert_allclose(a.dq, b.dq, rtol=0, atol=tol)
    np.testing.assert_allclose(a.tau, b.tau, rtol=0, atol=1e3 * tol)
    assert (a.status & ~Status.QP_FALLBACK) == (b.status & ~Status.QP_FALLBACK)
    assert a.rom == b.rom and a.interval == b.interval and a.arm_angle == b.arm_angle


def count_paths(ctrl: Controller, monkeypatch) -> dict[str, int]:
    """Counts the ticks solved on the line and by the general cascade."""
    counts = {"line": 0, "cascade": 0}
    original = ctrl.qp._solve_problem_levels

    def cascade(*args):
        counts["cascade"] += 1
        return original(*args)

    def problem(*args):
        counts["line"] += 1
        return solve(*args)

    solve = ctrl.qp.solve_problem
    monkeypatch.setattr(ctrl.qp, "_solve_problem_levels", cascade)
    monkeypatch.setattr(ctrl.qp, "solve_problem", problem)
    return counts


# ------------------------------------------------------------------ kernels
def test_pose_error_is_pinocchio_log3_up_to_pi() -> None:
    rng = np.random.default_rng(0)
    for scale in (1e-9, 1e-5, 1e-3, 0.1, 1.0, tick.LOG3_NEAR_PI, 3.0, np.pi - 1e-3, np.pi - 1e-6, np.pi):
        for _ in range(200):
            R = random_rotation(rng, np.pi)
            axis = rng.normal(size=3)
            angle = scale if scale > 2.0 else rng.uniform(0, scale)
            R_ref = pin.exp3(axis / np.linalg.norm(axis) * angle) @ R
            p, p_ref = rng.normal(size=3), rng.normal(size=3)
            e = tick.pose_error(R, p, R_ref, p_ref)
            np.testing.assert_allclose(e[:3], p_ref - p, rtol=0, atol=1e-15)
            if angle > 3.0:  # the rotation and its angle (at π the axis's sign is either; log₃ loses 1e-16/sin θ)
                np.testing.assert_allclose(pin.exp3(e[3:]), R_ref @ R.T, rtol=0, atol=1e-13)
                assert np.linalg.norm(e[3:]) == pytest.approx(angle, abs=1e-9)
            else:
                np.testing.assert_allclose(e[3:], pin.log3(R_ref @ R.T), rtol=0, atol=1e-12)


def test_a_reference_near_pi_away_gives_a_finite_bounded_correction(robot) -> None:
    ctrl = Controller(robot, ControllerConfig(strategy="qp"))
    ctrl.reset(Q0)
    state = ctrl.evaluate(Q0)
    ctrl.ref_rotation = pin.exp3(np.array([0.0, 0.0, np.pi - 1e-4])) @ state.tool_rotation
    cmd = ctrl.step(Q0)
    assert np.all(np.isfinite(cmd.dq)) and cmd.tool_error[1] == pytest.approx(np.pi - 1e-4, abs=1e-9)
    b1 = ctrl.records.problem[0]["b1"]
    second_order = 0.5 * ctrl.config.dt * ctrl.records.state[0]["drift"]  # (along the solved q̇: from rest, a miss)
    np.testing.assert_allclose(b1[3:] + second_order[3:], [0, 0, ctrl.config.pose_correction_angular_speed], atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-3, 3), min_size=7, max_size=7))
def test_velocity_bounds_keep_q_inside_its_limits(robot, q_list) -> None:
    q = np.array(q_list)
    gain = 20.0
    recovery = 0.2
    lb, ub = tick.velocity_bounds(q, limit_params(robot.q_min, robot.q_max, robot.dq_max, gain, recovery))
    assert np.all(lb <= ub) and np.all(np.abs(lb) <= robot.dq_max) and np.all(np.abs(ub) <= robot.dq_max)
    inside = (q >= robot.q_min) & (q <= robot.q_max)
    for v in (lb, ub):  # one tick at either bound stays inside (γ·dt ≤ 1)
        q1 = q + DT * v
        assert np.all((q1[inside] >= robot.q_min[inside] - 1e-12) & (q1[inside] <= robot.q_max[inside] + 1e-12))
    below, above = q < robot.q_min, q > robot.q_max  # outside: pushed back (never further out) ...
    assert np.all(lb[below] >= 0) and np.all(ub[above] <= 0)
    # ... at the rate γ·distance, but never faster than the recovery speed
    assert np.allclose(lb[below], np.minimum(gain * (robot.q_min - q), recovery)[below])
    assert np.allclose(ub[above], np.maximum(gain * (robot.q_max - q), -recovery)[above])
    out = below | above
    assert np.all(np.maximum(np.abs(lb), np.abs(ub))[out] <= recovery + 1e-15)


def test_cost_step_saturates_its_null_space_part(robot) -> None:
    rng = np.random.default_rng(1)
    for _ in range(50):
        q = robot.random_q(rng, margin=0.2)
        J = robot.jacobian(q)
        grad = rng.normal(size=7) * rng.uniform(0.01, 100)
        step = tick.cost_step(J, grad, 10.0, 1.0)
        null = (np.eye(7) - np.linalg.pinv(J) @ J) @ step
        assert np.linalg.norm(null) <= 1.0 + 1e-9
        np.testing.assert_allclose(np.cross(step[:3], grad[:3]), 0, atol=1e-9 * np.linalg.norm(grad) ** 2 * 100)
        if np.linalg.norm((np.eye(7) - np.linalg.pinv(J) @ J) @ (10 * grad)) <= 1.0:
            np.testing.assert_allclose(step, 10 * grad, rtol=1e-15)


def test_low_pass() -> None:
    prev, step = np.array([1.0, -1.0]), np.array([3.0, 1.0])
    np.testing.assert_allclose(tick.low_pass(prev, step, 0.25), [1.5, -0.5])
    out = tick.low_pass(prev, step, 0.0)
    assert np.array_equal(out, step) and out is not step


def test_finish_tick_is_gravity_plus_the_projected_impedance(robot) -> None:
    """τ = g + (I − J̄J)ᵀ(K·dt·q̇ + D(q̇ − q̇_meas)) + f̂((I − J̄J)q̇_meas) with J̄ = A⁻¹Jᵀ(JA⁻¹Jᵀ)⁻¹ from Pinocchio,
    inverted by hand, D = joint_damping within its bound 0.5·m/dt (m = zᵀAz, z the unit null vector by SVD) and
    f̂ the robot's friction model (the self-motion's friction compensated, un-projected)."""
    rng = np.random.default_rng(2)
    ctrl = Controller(robot, ControllerConfig(strategy="qp", ddq_max=1e9))  # (dq far from the last command)
    q = robot.random_q(rng, margin=0.2)
    ctrl.reset(q)
    ctrl.step(q)
    rec = ctrl.records
    dq, dq_meas = rng.normal(size=7) * 0.1, rng.normal(size=7) * 0.1
    rec.solution[0]["x"], rec.solution[0]["outcome"] = dq, 0
    K = float(rec.report[0]["stiffness"])
    tick.finish_tick(q, dq_meas, rec.tick)
    J = robot.jacobian(q)
    A = pin.crba(robot.model, robot.data, q)
    A = np.triu(A) + np.triu(A, 1).T
    g = pin.computeGeneralizedGravity(robot.model, robot.data, q)
    Ai = np.linalg.inv(A)
    Jbar = Ai @ J.T @ np.linalg.inv(J @ Ai @ J.T)
    z = np.linalg.svd(J)[2][-1]
    D = min(ctrl.config.joint_damping, 0.5 * float(z @ A @ z) / DT)
    N = np.eye(7) - Jbar @ J
    expected = g + N.T @ (K * DT * dq + D * (dq - dq_meas)) + robot.friction_torque(N @ dq_meas)
    c = rec.command[0]
    # JA⁻¹Jᵀ is regularised by 1e-12 of its trace (linalg.py): agreement to its conditioning
    np.testing.assert_allclose(c["tau"], expected, rtol=0, atol=1e-6 * np.linalg.norm(expected))
    np.testing.assert_array_equal(c["dq"], dq)
    np.testing.assert_allclose(c["q_des"], q + DT * dq, rtol=0, atol=1e-15)


def memory_at(ns: float) -> np.ndarray:
    return M.new_memory(7, ns, 0.0, np.eye(3), np.zeros(3))


def test_elbow_advance_unwraps_the_arm_angle_and_ages_the_interval(robot) -> None:
    rng = np.random.default_rng(4)
    P = tick_params(robot, ControllerConfig(interval_period=10))[0]
    path = np.cumsum(rng.uniform(-0.5, 0.5, 400)) + 3.0  # crosses ±π many times
    memory = memory_at(path[0])
    m = memory[0]
    state = new_record(qpnso.control.state.state_dtype(7))
    s = state[0]
    s["R"], s["p"] = random_rotation(rng, 3.0), rng.normal(size=3)
    unwrapped = []
    for ns in path:
        s["arm_angle"] = float(np.angle(np.exp(1j * ns)))
        assert M.elbow_advance(s, m, P)  # no interval known yet
        unwrapped.append(float(m["ns"]))
    np.testing.assert_allclose(unwrapped, path, atol=1e-12)
    M.store_interval(m, -1.0, 2.0, False, s["R"].copy(), s["p"].copy())
    answers = []
    for k in range(24):
        if k == 12:
            s["p"] = s["p"] + 2e-6  # the tool moves by more than 1e-6
        answers.append(M.elbow_advance(s, m, P))
    # the same pose keeps the interval at any age; a moved tool renews it once it is 10 ticks old
    assert answers == [False] * 12 + [True] * 12
    assert m["iv_age"] == 24
    fresh = memory_at(0.0)  # none known and the first attempt failed: the next one only 10 ticks later
    M.interval_failed(fresh[0])
    assert [M.elbow_advance(s, fresh[0], P) for _ in range(12)] == [False] * 9 + [True] * 3


def test_elbow_bounds_are_the_shifted_interval_clipped_and_the_sigmoid(robot) -> None:
    rng = np.random.default_rng(5)
    config = ControllerConfig(rom_half_width_deg=50, safety_margin_deg=10)
    cfg = config.elbow()
    P = tick_params(robot, config)[0]
    for _ in range(300):
        lo = rng.uniform(-4, 4)
        hi = lo + rng.uniform(0.1, 6.0)
        full = bool(rng.random() < 0.2)
        turns = int(rng.integers(-3, 4))
        ns = rng.uniform(lo, hi) + 2 * np.pi * turns
        ns0 = ns + rng.uniform(-1.5, 1.5)
        memory = M.new_memory(7, ns, ns0, np.eye(3), np.zeros(3))
        M.store_interval(memory[0], lo, hi, full, np.eye(3), np.zeros(3))
        interval = (
            qpnso.Interval(ns - np.pi, ns + np.pi, True)
            if full
            else qpnso.Interval(lo + 2 * np.pi * turns, hi + 2 * np.pi * turns, False)
        )
        expected = qpnso.clip_rom(ns0, cfg.half_width_rad, interval, cfg.safety_margin_rad)
        rom_lo, rom_hi, empty, iv_lo, iv_hi, k = M.elbow_bounds(memory[0], P)
        assert (iv_lo, iv_hi) == pytest.approx((interval.lo, interval.hi), abs=1e-12)
        assert (rom_lo, rom_hi, empty) == pytest.approx((expected.lo, expected.hi, expected.empty), abs=1e-12)
        span = cfg.stiffness_max - cfg.stiffness_min
        assert k == pytest.approx(span / (1 + np.exp(cfg.alpha_per_rad * (cfg.d_rad - abs(ns - ns0)))) + 10, rel=1e-12)
    unknown = M.elbow_bounds(M.new_memory(7, 1.0, 1.0, np.eye(3), np.zeros(3))[0], P)
    assert unknown[3:5] == pytest.approx((1.0 - np.pi, 1.0 + np.pi))  # no interval yet: the circle around ns


def test_answer_bits_are_the_status_flags() -> None:
    assert Status(tick.answer_bits(1e-3, 0.0)) == Status.TOOL_LIMITED
    assert Status(tick.answer_bits(0.0, 1e-2)) == Status.ELBOW_SLACK
    assert tick.answer_bits(-1.0, -1.0) == 0
    from qpnso.control import flags

    bits = {name[5:]: value for name, value in vars(flags).items() if name.startswith("FLAG_")}
    assert {m.name: m.value for m in Status if m.value} == bits  # each bit named once, the same on both sides
    assert all(v > 0 and v & (v - 1) == 0 for v in bits.values()) and len(set(bits.values())) == len(bits)


# ------------------------------------------------------- the tick's problem
def hand_problem(robot: qpnso.Robot, ctrl: Controller, q: np.ndarray, twist: np.ndarray, step0: np.ndarray):
    """The ``qp`` strategy's tick problem at ``q`` built by hand from Pinocchio and the paper's formulas (the
    previous command zero): level 1 ``J q̇ = v + K_p e − ½dt·J̇q̇`` (J̇q̇ Pinocchio's classical acceleration
    along the damped least-squares velocity of ``v``), the bounds, and level 2 ``½‖q̇‖² + sᵀq̇`` with the soft
    elbow row ``ξ(ROM_t − ns)``; ``step0`` the filter's previous cost step."""
    from qpnso.control.state import PREDICTION_DAMPING

    cfg, state = ctrl.config, ctrl.evaluate(q)
    J = robot.jacobian(q)
    pose = robot.tool_pose(q)
    e = np.r_[ctrl.ref_position - pose.translation, pin.log3(ctrl.ref_rotation @ pose.rotation.T)]
    v = J.T @ np.linalg.solve(J @ J.T + PREDICTION_DAMPING**2 * np.eye(6), twist)
    data = robot.model.createData()
    pin.forwardKinematics(robot.model, data, q, v, np.zeros(7))
    drift = pin.getFrameClassicalAcceleration(robot.model, data, robot.tool_frame_id, pin.LOCAL_WORLD_ALIGNED).vector
    b1 = twist + cfg.pose_gain * e - 0.5 * DT * drift
    a = robot.ddq_max
    braking_lo = np.sqrt((a * DT / 2) ** 2 + 2 * a * (q - robot.q_min)) - a * DT / 2  # v(v + a·dt)/(2a) = distance
    braking_hi = np.sqrt((a * DT / 2) ** 2 + 2 * a * (robot.q_max - q)) - a * DT / 2
    lb = np.clip(np.maximum(cfg.joint_limit_gain * (robot.q_min - q), -braking_lo), -robot.dq_max, robot.dq_max)
    ub = np.clip(np.minimum(cfg.joint_limit_gain * (robot.q_max - q), braking_hi), -robot.dq_max, robot.dq_max)
    lb, ub = np.clip(lb, -a * DT, a * DT), np.clip(ub, -a * DT, a * DT)  # (from rest: the previous command is 0)
    N = np.eye(7) - np.linalg.pinv(J) @ J
    step = cfg.cost_gain * ctrl.cost.gradient(q)
    step *= min(1.0, cfg.nullspace_speed_max / np.linalg.norm(N @ step))
    alpha = DT / cfg.cost_filter_time
    s = step0 + alpha * (step - step0)
    ns = reference_arm_angle(robot, q)
    return Level(A=J, b=b1), Level(H=np.eye(7), g=s), state, ns, (lb, ub)


def test_the_tick_states_the_problem_built_by_hand(robot) -> None:
    """What a ``qp`` tick writes into its problem record, against Pinocchio: level 1, the bounds, the filtered
    cost step, the elbow row (its gradient by central differences of the arm angle)."""
    rng = np.random.default_rng(7)
    ctrl = Controller(robot, ControllerConfig(strategy="qp"))
    for _ in range(5):
        q = robot.random_q(rng, margin=0.4)
        if qpnso.arm_angle_status(robot, q).status != "ok":
            continue
        ctrl.reset(q)
        twist = rng.normal(size=6) * 0.02
        step0 = ctrl.records.memory[0]["cost_step"].copy()
        first, second, _, ns, (lb, ub) = hand_problem(robot, ctrl, q, twist, step0)  # (the reference before it moves)
        ctrl.step(q, tool_twist=twist)
        p = ctrl.records.problem[0]
        np.testing.assert_allclose(p["A1"], first.A, rtol=0, atol=1e-12)
        np.testing.assert_allclose(p["b1"], first.b, rtol=0, atol=1e-9)
        np.testing.assert_allclose(p["lb"], lb, rtol=0, atol=1e-12)
        np.testing.assert_allclose(p["ub"], ub, rtol=0, atol=1e-12)
        assert p["has_level2"] and p["use_H2"] and p["use_g2"] and p["m2"] == 0
        np.testing.assert_array_equal(p["H2"], np.eye(7))
        np.testing.assert_allclose(p["g2"], second.g, rtol=1e-9, atol=1e-12)
        assert p["n_soft"] == 1 and p["slack_weight"] == ctrl.config.slack_weight
        h = 1e-6
        grad = [
            (reference_arm_angle(robot, q + h * d) - reference_arm_angle(robot, q - h * d)) / (2 * h) for d in np.eye(7)
        ]
        np.testing.assert_allclose(p["soft_C"][0], grad, rtol=0, atol=1e-6)
        r = ctrl.records.report[0]
        assert r["ns"] == pytest.approx(ns, abs=1e-9)
        xi = ctrl.config.elbow_gain
        assert p["soft_l"][0] == pytest.approx(min(xi * (r["rom_lo"] - ns), ctrl.config.recovery_speed), abs=1e-8)
        assert p["soft_u"][0] == pytest.approx(max(xi * (r["rom_hi"] - ns), -ctrl.config.recovery_speed), abs=1e-8)


def test_every_strategy_takes_the_one_path(robot, monkeypatch) -> None:
    """Every strategy's tick states its problem in the same record and the same solver call answers it."""
    for name in ("qp", "damped", "fixed", "elbow-up", "gradient", "rom"):
        ctrl = Controller(robot, ControllerConfig(strategy=name))
        counts = count_paths(ctrl, monkeypatch)
        ctrl.reset(Q0)
        for _ in range(5):
            assert ctrl.step(Q0, tool_twist=[0.002, 0, 0, 0, 0, 0]).ok  # (within ddq_max·dt of rest)
        assert counts == {"line": 5, "cascade": 0}, name


def run_both(robot, ticks: int, q0: np.ndarray, twist_of, **cfg) -> None:
    """The same closed loop with the line fast path and with the general cascade only: the same commands
    (two algorithms: a closed-form segment and an SVD null-space cascade, to the QPs' tolerances)."""
    line = Controller(robot, ControllerConfig(**cfg))
    cascade = Controller(robot, ControllerConfig(qp_settings=qpnso.QPSettings(line_fast_path=False), **cfg))
    line.reset(q0), cascade.reset(q0)
    q, dq = q0.copy(), np.zeros(7)
    for k in range(ticks):
        a = line.step(q, dq=dq, tool_twist=twist_of(k))
        b = cascade.step(q, dq=dq, tool_twist=twist_of(k))
        assert_close(a, b, 1e-8)
        dq = 0.9 * a.dq
        q = q + DT * a.dq


@pytest.mark.parametrize("strategy", ["qp", "fixed", "elbow-up"])
def test_the_line_fast_path_answers_as_the_general_cascade(robot, strategy: str) -> None:
    def twist(k: int) -> np.ndarray:
        return np.array([0.05 * np.sin(k * DT * 3), 0.03, -0.02, 0.1, 0.0, -0.2 * np.cos(k * DT)])

    run_both(robot, 300, Q0, twist, strategy=strategy)


def test_joint_limit_cutting_the_line_takes_the_general_cascade(robot, monkeypatch) -> None:
    """A tool motion the bounds cannot follow: the line misses the box, the cascade answers."""
    ctrl = Controller(robot, ControllerConfig(strategy="qp"))
    counts = count_paths(ctrl, monkeypatch)
    ctrl.reset(Q0)
    a = ctrl.step(Q0, tool_twist=np.array([5.0, 0, 0, 0, 0, 0]))
    assert counts == {"line": 1, "cascade": 1} and a.status & Status.TOOL_LIMITED
    lb, ub = ctrl.records.problem[0]["lb"], ctrl.records.problem[0]["ub"]
    assert np.all(a.dq >= lb - 1e-9) and np.all(a.dq <= ub + 1e-9)


def test_a_hard_row_folds_into_the_segment(robot) -> None:
    """A hard row on the line narrows its segment exactly (the line fast path keeps it), and the answer
    equals the general cascade's on the same problem."""
    from qpnso.control.memory import KEEP_OUT_ROWS
    from qpnso.qp.problem import new_problem, new_solution, problem_levels

    ctrl = Controller(robot, ControllerConfig(strategy="qp"))
    ctrl.reset(Q0)
    ctrl.step(Q0, tool_twist=[0.02, 0, 0, 0, 0, 0])
    problem = ctrl.records.problem.copy()
    p = problem[0]
    x_free = ctrl.records.solution[0]["x"].copy()
    d = np.linalg.svd(p["A1"])[2][-1]
    p["hard_C"][0] = d
    p["hard_l"][0], p["hard_u"][0] = -np.inf, d @ x_free - 1e-3  # the free answer is cut off by 1e-3
    p["n_hard"] = 1
    solution = new_solution(7)
    assert ctrl.qp.solve_problem(problem, solution) == ""
    x = solution[0]["x"]
    assert d @ x <= p["hard_u"][0] + 1e-9 and d @ x == pytest.approx(p["hard_u"][0], abs=1e-7)
    reference = ctrl.qp.solve(problem_levels(problem), p["lb"], p["ub"])
    np.testing.assert_allclose(x, reference.x, rtol=0, atol=1e-7)
    room = 3 + KEEP_OUT_ROWS  # the controller's room: 2 hard rows; the elbow's, 2 soft and the keep-out rows
    assert new_problem(7, 2, room).dtype == problem.dtype


def test_failed_level_two_holds_the_tool(robot, monkeypatch) -> None:
    ctrl = Controller(robot, ControllerConfig(strategy="qp"))
    ctrl.reset(Q0)
    failed = _Raw(None, LevelStatus.INFEASIBLE, 3, "proxsuite TEST_FAILURE")
    monkeypatch.setattr(ctrl.qp._backend, "solve_arrays", lambda *args, **kwargs: failed)
    failures = ctrl.qp.stats.failures
    a = ctrl.step(Q0)
    assert a.status & Status.QP_FAILED and not a.ok
    assert a.message == "QP failed (level 2 of 2 infeasible: proxsuite TEST_FAILURE): tool held, no null-space motion"
    assert ctrl.qp.stats.failures == failures + 1
    J = robot.jacobian(Q0)
    b1 = ctrl.records.problem[0]["b1"]
    np.testing.assert_allclose(a.dq, np.linalg.pinv(J) @ b1, atol=1e-12)  # level 1's least-norm answer


def test_singular_tool_task_takes_the_damped_general_cascade(robot, monkeypatch) -> None:
    """Joints 2 and 6 at zero align axes 1, 3 and 5, 7: rank 5, no line; the damped cascade answers."""
    q0 = Q0.copy()
    q0[1] = q0[5] = 0.0
    assert np.linalg.svd(robot.jacobian(q0), compute_uv=False)[-1] < 1e-6
    ctrl = Controller(robot, ControllerConfig(strategy="qp"))
    counts = count_paths(ctrl, monkeypatch)
    ctrl.reset(q0)
    q = q0.copy()
    for _ in range(20):
        cmd = ctrl.step(q)
        assert np.all(np.isfinite(cmd.dq))
        q = q + DT * cmd.dq
    assert counts == {"line": 20, "cascade": 20}


@pytest.mark.parametrize(
    "answer, words",
    [(np.array([np.nan, 0.0]), "non-finite"), (np.zeros(3), "mis-shaped"), (np.array([1e3, 0.0]), "violated")],
)
def test_a_bad_level_two_answer_holds_the_tool(robot, monkeypatch, answer, words: str) -> None:
    ctrl = Controller(robot, ControllerConfig(strategy="qp"))
    ctrl.reset(Q0)
    solved = _Raw(answer, LevelStatus.SOLVED, 1, "proxsuite PROXQP_SOLVED")
    monkeypatch.setattr(ctrl.qp._backend, "solve_arrays", lambda *args, **kwargs: solved)
    a = ctrl.step(Q0)
    assert a.status & Status.QP_FAILED and words in a.message and "tool held" in a.message
    assert np.all(np.isfinite(a.dq)) and np.all(np.isfinite(a.tau))
    np.testing.assert_allclose(robot.jacobian(Q0) @ a.dq, ctrl.records.problem[0]["b1"], atol=1e-12)


def test_an_interval_that_cannot_be_renewed_is_flagged_stale(robot) -> None:
    ctrl = Controller(robot, ControllerConfig(strategy="qp"))
    ctrl.reset(Q0)
    twist = np.array([0.02, 0.0, 0.0, 0.0, 0.0, 0.0])
    q = Q0.copy()
    for k in range(40):
        if k == 5:  # from here on the interval cannot be computed (every pose out of the arm's reach in the
            # tick's geometry): the last one stands, flagged
            ctrl.records.params[0]["srs"]["upper_arm_m"] = 1e-3
        a = ctrl.step(q, tool_twist=twist)
        assert bool(a.status & Status.INTERVAL_STALE) == (k >= 10)  # renewed every 10 ticks while moving
        q = q + DT * a.dq


@pytest.mark.parametrize("name", SRS_ROBOTS)
def test_the_tick_renews_the_continuity_interval_of_the_library(robots, name: str) -> None:
    """S-R-S: renewed every tick while the tool moves (the closed form in the tick's kernel, at the tick's own
    pose): each tick's interval is ``continuity_interval`` at its ``q``, moved by whole turns to the run's
    unwrapping."""
    robot = robots[name]
    ctrl = Controller(robot, ControllerConfig(strategy="qp", interval_period=1))
    rng = np.random.default_rng(2)
    q = robot.sample_configuration()
    ctrl.reset(q)
    twist = np.array([0.03, -0.02, 0.01, 0.1, 0.0, -0.1])
    renewed = 0
    for k in range(200):
        cmd = ctrl.step(q, tool_twist=twist * np.sin(0.05 * k))
        if not cmd.status & (Status.INTERVAL_STALE | Status.ELBOW_DROPPED):
            iv = qpnso.continuity_interval(robot, q)
            turns = round((cmd.arm_angle - qpnso.arm_angle(robot, q)) / (2 * np.pi))
            expected = (iv.lo + 2 * np.pi * turns, iv.hi + 2 * np.pi * turns)
            np.testing.assert_allclose(cmd.interval, expected, atol=1e-9)
            renewed += 1
        q = q + DT * cmd.dq + rng.normal(scale=1e-5, size=7)  # (a measured q: noisy)
    assert renewed >= 150


@pytest.mark.skipif(not HAS_PANDA, reason="the Panda's model is not installed")
def test_a_numerical_interval_is_walked_a_few_steps_a_tick(robots, monkeypatch) -> None:
    """An arm without the closed form (the Panda): its first interval is whole at reset; while the tool moves, each
    tick takes at most ``interval_steps_per_tick`` self-motion steps of the next one, and every interval the ticks
    report is ``continuity_interval`` at the ``q`` its walk started from (moved by whole turns)."""
    from qpnso.elbow.intervals import NumericalWalk

    robot = robots["panda"]
    starts: list[np.ndarray] = []
    init, advance = NumericalWalk.__init__, NumericalWalk.advance
    taken = []

    def recording_init(self, robot_, q_, *args, **kwargs):
        starts.append(np.array(q_, dtype=float))
        init(self, robot_, q_, *args, **kwargs)

    def counting_advance(self, steps):
        before = self.steps
        out = advance(self, steps)
        taken.append(self.steps - before)
        return out

    monkeypatch.setattr(NumericalWalk, "__init__", recording_init)
    monkeypatch.setattr(NumericalWalk, "advance", counting_advance)
    ctrl = Controller(robot, ControllerConfig(strategy="qp", interval_period=1, interval_steps_per_tick=6))
    q = robot.sample_configuration()
    ctrl.reset(q)
    first = qpnso.continuity_interval(robot, q)
    starts.clear()
    taken.clear()
    twist = np.array([0.03, -0.02, 0.01, 0.1, 0.0, -0.1])
    seen = []
    for k in range(400):
        cmd = ctrl.step(q, tool_twist=twist * np.sin(0.02 * k))
        if k == 0:
            np.testing.assert_allclose(cmd.interval, (first.lo, first.hi), atol=1e-12)  # (the reset's, whole)
        seen.append(cmd.interval)
        q = q + DT * cmd.dq
    assert taken and max(taken) <= 6  # a few pieces a tick, never a whole walk
    expected = []
    for q0 in starts[:-1]:  # (the last walk may still be under way)
        iv = qpnso.continuity_interval(robot, q0)
        expected.append((iv.lo, iv.hi))
    assert len(expected) >= 2  # walks finished while the tool moved: not vacuous
    for lo, hi in expected:  # each finished walk's interval was reported by some tick, by whole turns
        assert any(
            abs((a - lo) - 2 * np.pi * round((a - lo) / (2 * np.pi))) < 1e-9 and abs(b - a - (hi - lo)) < 1e-9
            for a, b in seen
        )


@pytest.mark.skipif(not HAS_PANDA, reason="the Panda's model is not installed")
def test_a_numerical_walk_that_fails_marks_the_interval_stale_and_starts_again(robots, monkeypatch) -> None:
    """A walk that raises (the self-motion singular on the way) is dropped: the last interval stands, flagged
    ``INTERVAL_STALE``, until a new walk, started later, ends."""
    from qpnso.elbow.intervals import NumericalWalk

    robot = robots["panda"]
    ctrl = Controller(robot, ControllerConfig(strategy="qp", interval_period=1, interval_steps_per_tick=50))
    q = robot.sample_configuration()
    ctrl.reset(q)
    twist = np.array([0.02, 0.0, 0.0, 0.0, 0.0, 0.1])
    advance = NumericalWalk.advance

    def singular(self, steps):
        raise qpnso.SingularityError("test: the self-motion is singular here")

    monkeypatch.setattr(NumericalWalk, "advance", singular)
    first = ctrl.step(q, tool_twist=twist)
    assert not first.status & Status.INTERVAL_STALE  # (the reset's interval, still fresh)
    q = q + DT * first.dq
    failed = ctrl.step(q, tool_twist=twist)
    assert failed.status & Status.INTERVAL_STALE and ctrl._walk is None
    assert failed.interval == pytest.approx(first.interval, abs=1e-12)  # the last one stands
    monkeypatch.setattr(NumericalWalk, "advance", advance)
    stale = []
    for _ in range(400):
        cmd = ctrl.step(q, tool_twist=twist)
        stale.append(bool(cmd.status & Status.INTERVAL_STALE))
        q = q + DT * cmd.dq
    assert stale[0] and not stale[-1]  # renewed again once a new walk ended


def test_nan_q_is_refused_before_anything_advances(robot) -> None:
    ctrl = Controller(robot, ControllerConfig(strategy="qp"))
    ctrl.reset(Q0)
    ctrl.step(Q0)
    memory, steps = ctrl.records.memory.copy(), ctrl.step_count
    bad = Q0.copy()
    bad[3] = np.nan
    with pytest.raises(ValueError, match=r"q"):
        ctrl.step(bad, tool_twist=np.ones(6))
    assert ctrl.records.memory.tobytes() == memory.tobytes() and ctrl.step_count == steps


def test_a_qpsolvers_back_end_answers_as_proxsuite(robot) -> None:
    """The line's level-2 QP handed to another back end (DAQP, exact active set): the same commands, to the
    tie-break μ = 1e-7 that the qpsolvers back ends get (relative 1e-7 of q̇)."""
    a, b = Controller(robot, ControllerConfig(qp_backend="daqp")), Controller(robot, ControllerConfig())
    a.reset(Q0), b.reset(Q0)
    q = Q0.copy()
    for _ in range(200):
        x, y = a.step(q), b.step(q)
        assert_close(x, y, 2e-7 * np.abs(y.dq).max())
        q = q + DT * x.dq


@pytest.mark.jit
@pytest.mark.parametrize("strategy", ["qp", "damped"])
def test_no_kernel_of_any_module_loads_in_a_tick_after_the_constructor(robot, strategy: str) -> None:
    """After the constructor, no tick loads or compiles a kernel of any qpnso module: the compiled tick, the
    general path, a dropped elbow (q = 0, the wrist over the shoulder; its K(ns) was once loaded in the first
    such tick, 85 ms when the cache had to be rebuilt), a joint just outside its limit, a tool pose."""
    kernel_signatures()  # every module imported first
    ctrl = Controller(robot, ControllerConfig(strategy=strategy))
    before = kernel_signatures()
    ctrl.reset(Q0)
    ctrl.step(Q0, tool_twist=[0.05, 0.0, 0.0, 0.0, 0.0, 0.1])
    outside = Q0.copy()
    outside[0] = robot.q_max[0] + 0.01
    ctrl.step(outside)
    ctrl.step(Q0, tool_pose=robot.tool_pose(Q0))
    ctrl.reset(np.zeros(7))
    cmd = ctrl.step(np.zeros(7))
    assert cmd.status & Status.ELBOW_DROPPED
    after = kernel_signatures()
    assert {k: (before.get(k), n) for k, n in after.items() if n != before.get(k)} == {}


def test_a_level_without_a_task_is_written_as_its_quadratic_and_linear_terms(robot) -> None:
    """``set_level2`` of a level with only ``H`` and ``g``: no task rows, and the problem solves as the same
    levels given to ``HierarchicalQP.solve``."""
    from qpnso.qp.problem import new_problem, new_solution, problem_levels, set_level2

    ctrl = Controller(robot, ControllerConfig(strategy="damped"))
    ctrl.reset(Q0)
    ctrl.step(Q0)
    problem = new_problem(7)
    problem[0]["A1"], problem[0]["b1"] = ctrl.records.problem[0]["A1"], ctrl.records.problem[0]["b1"]
    problem[0]["lb"], problem[0]["ub"] = ctrl.records.problem[0]["lb"], ctrl.records.problem[0]["ub"]
    g = np.linspace(-0.3, 0.3, 7)
    set_level2(problem, Level(H=2.0 * np.eye(7), g=g))
    p = problem[0]
    assert p["has_level2"] and p["m2"] == 0 and p["use_H2"] and p["use_g2"]
    solution = new_solution(7)
    assert ctrl.qp.solve_problem(problem, solution) == ""
    reference = ctrl.qp.solve(problem_levels(problem), p["lb"], p["ub"])
    np.testing.assert_allclose(solution[0]["x"], reference.x, rtol=0, atol=1e-9)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_the_tool_errors_are_the_pose_errors_magnitudes(robot, axis: int) -> None:
    """The reference turned by 0.3 rad about the world's x, y or z axis and moved by 2 mm along the same axis: the
    command's ``tool_error`` is (2e-3 m, 0.3 rad) whatever the axis (by hand: the norms of the position and
    rotation errors, every component counted)."""
    ctrl = Controller(robot, ControllerConfig(strategy="qp"))
    ctrl.reset(Q0)
    state = ctrl.evaluate(Q0)
    e = np.eye(3)[axis]
    ctrl.ref_rotation = pin.exp3(0.3 * e) @ state.tool_rotation
    ctrl.ref_position = state.tool_position + 2e-3 * e
    cmd = ctrl.step(Q0)
    assert cmd.tool_error[0] == pytest.approx(2e-3, abs=1e-12) and cmd.tool_error[1] == pytest.approx(0.3, abs=1e-12)


def test_the_arm_angle_is_singular_inside_the_wrist_cone_or_with_a_straight_elbow() -> None:
    """``arm_angle_singular`` by hand, on records: a bent elbow with the wrist inside the cone (wrist_sin half the
    threshold) is singular, as is a straight elbow with the wrist far out; both clear of the thresholds is not."""
    from qpnso.control.memory import arm_angle_singular
    from qpnso.control.params import params_dtype
    from qpnso.control.state import state_dtype

    s, P = new_record(state_dtype(7))[0], new_record(params_dtype(7))[0]
    P["wrist_sin_min"], P["elbow_offset_min"] = 0.03, 0.01
    for wrist_sin, offset, singular in ((0.015, 0.2, True), (0.5, 0.005, True), (0.5, 0.2, False), (0.03, 0.2, False)):
        s["wrist_sin"], s["elbow_offset"] = wrist_sin, offset
        assert bool(arm_angle_singular(s, P)) == singular, (wrist_sin, offset)  # (np.bool_ without the JIT)


@pytest.mark.parametrize("seed", range(6))
def test_the_reference_advances_along_the_twist_as_pinocchios_exp3(seed: int) -> None:
    """``advance_reference``: one tick of a twist moves the reference by ``dt·v`` and turns it by Pinocchio's
    ``exp3(dt·ω)`` (world frame, to round-off), for angular speeds from 1e-6 to 100 rad/s; a zero twist
    leaves it bit for bit."""
    import pinocchio as pin

    from qpnso.control.memory import advance_reference, new_memory

    rng = np.random.default_rng(seed)
    R0, p0 = pin.exp3(rng.standard_normal(3)), rng.standard_normal(3)
    memory = new_memory(7, 0.0, 0.0, R0.copy(), p0.copy())
    advance_reference(memory[0], np.zeros(6), 1e-3)
    np.testing.assert_array_equal(memory[0]["ref_R"], R0)
    np.testing.assert_array_equal(memory[0]["ref_p"], p0)
    twist = rng.standard_normal(6) * 10.0 ** (seed - 4)
    advance_reference(memory[0], twist, 1e-3)
    np.testing.assert_allclose(memory[0]["ref_R"], pin.exp3(1e-3 * twist[3:]) @ R0, rtol=0, atol=1e-15)
    np.testing.assert_allclose(memory[0]["ref_p"], p0 + 1e-3 * twist[:3], rtol=0, atol=1e-15)


@pytest.mark.jit
def test_every_controller_shares_the_record_types_of_the_first() -> None:
    """Two controllers' records (tick, problem, solution, memory) have the very same dtype objects, not only
    equal ones: Numba's dispatcher types an argument fast only for a dtype object it has seen (a second
    controller's ticks cost about 45 µs more before ``records.interned``, measured)."""
    import qpnso
    from qpnso.records import interned, new_record

    robot = qpnso.load_robot("lwr4p")
    first, second = (qpnso.Controller(robot, qpnso.ControllerConfig(strategy=s)) for s in ("qp", "damped"))
    for name in ("problem", "solution", "memory", "state", "params", "report"):
        a, b = getattr(first.records, name), getattr(second.records, name)
        assert a.dtype is b.dtype, name
    assert first.tick.dtype is second.tick.dtype
    made = np.dtype([("x", np.float64, 3)])
    assert new_record(np.dtype([("x", np.float64, 3)])).dtype is interned(made)
