"""The compiled tick (qpnso/control/tick.py): its kernels against independent computations, and the
controller's compiled path against its general path (HierarchicalQP.solve) tick by tick."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import qpnso
from qpnso.control import elbow_memory, tick
from qpnso.control.config import ControllerConfig, Status
from qpnso.control.controller import Controller
from qpnso.qp import LevelStatus
from qpnso.qp.backends import _Raw

DT = 1e-3
Q0 = np.array([0.1, 0.6, -0.2, -1.3, 0.3, 0.9, 0.2])


@pytest.fixture(scope="module")
def robot() -> qpnso.Robot:
    return qpnso.load_robot("lwr4p")


def pair(robot, **cfg) -> tuple[Controller, Controller]:
    """The same controller twice: compiled tick allowed, and general path only."""
    fast = Controller(robot, ControllerConfig(strategy="qp", **cfg))
    slow = Controller(robot, ControllerConfig(strategy="qp", compiled_tick=False, **cfg))
    assert fast.compiled_tick and not slow.compiled_tick
    return fast, slow


def count_compiled(ctrl: Controller, monkeypatch) -> list[int]:
    """Counts the ticks the compiled path answered (it returned the Command, not a hand-over)."""
    hits = [0]
    original = ctrl._compiled

    def spy(*args):
        out = original(*args)
        hits[0] += type(out) is qpnso.Command
        return out

    monkeypatch.setattr(ctrl, "_compiled", spy)
    return hits


def assert_same(a, b, tol: float = 1e-12) -> None:
    np.testing.assert_allclose(a.dq, b.dq, rtol=0, atol=tol)
    np.testing.assert_allclose(a.tau, b.tau, rtol=0, atol=1e3 * tol)
    np.testing.assert_allclose(a.q_des, b.q_des, rtol=0, atol=tol)
    assert a.status == b.status and a.message == b.message
    assert a.rom == b.rom and a.interval == b.interval and a.arm_angle == b.arm_angle
    np.testing.assert_allclose(a.tool_error, b.tool_error, rtol=0, atol=tol)


def held_both(fast: Controller, slow: Controller, q0: np.ndarray, ticks: int) -> None:
    """Both controllers from ``q0`` with the tool held, the same ``q`` each tick: same commands."""
    fast.reset(q0), slow.reset(q0)
    q = q0.copy()
    for _ in range(ticks):
        a, b = fast.step(q), slow.step(q)
        assert_same(a, b)
        q = q + DT * a.dq


# ------------------------------------------------------------------ kernels
def random_rotation(rng: np.random.Generator, max_angle: float) -> np.ndarray:
    axis = rng.normal(size=3)
    return pin.exp3(axis / np.linalg.norm(axis) * rng.uniform(0, max_angle))


def test_pose_error_is_pinocchio_log3() -> None:
    rng = np.random.default_rng(0)
    for scale in (1e-9, 1e-5, 1e-3, 0.1, 1.0, 3.0, tick.LOG3_MAX_ANGLE):
        for _ in range(200):
            R, R_ref = random_rotation(rng, np.pi), None
            R_ref = random_rotation(rng, scale) @ R
            p, p_ref = rng.normal(size=3), rng.normal(size=3)
            e, ok = tick.pose_error(R, p, R_ref, p_ref)
            assert ok
            np.testing.assert_allclose(e[:3], p_ref - p, rtol=0, atol=1e-15)
            np.testing.assert_allclose(e[3:], pin.log3(R_ref @ R.T), rtol=0, atol=1e-12)


def test_pose_error_near_pi_is_refused_and_the_controller_uses_log3(robot) -> None:
    R = np.eye(3)
    R_ref = pin.exp3(np.array([0.0, 0.0, np.pi - 1e-4]))
    _, ok = tick.pose_error(R, np.zeros(3), R_ref, np.zeros(3))
    assert not ok
    ctrl = Controller(robot, ControllerConfig(strategy="qp"))
    ctrl.reset(Q0)
    state = ctrl.evaluate(Q0)
    ctrl.ref_rotation = pin.exp3(np.array([0.0, 0.0, np.pi - 1e-4])) @ state.tool_rotation
    np.testing.assert_allclose(ctrl._pose_error(state)[3:], [0, 0, np.pi - 1e-4], atol=1e-9)
    cmd = ctrl.step(Q0)  # the compiled kernel refuses the pose, the general path answers
    assert np.all(np.isfinite(cmd.dq)) and cmd.tool_error[1] == pytest.approx(np.pi - 1e-4, abs=1e-9)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-3, 3), min_size=7, max_size=7))
def test_velocity_bounds_keep_q_inside_its_limits(robot, q_list) -> None:
    q = np.array(q_list)
    gain = 20.0
    recovery = 0.2
    lb, ub = tick.velocity_bounds(q, robot.q_min, robot.q_max, robot.dq_max, gain, recovery)
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


def test_qp_torque_is_gravity_plus_projected_impedance(robot) -> None:
    rng = np.random.default_rng(2)
    q = robot.random_q(rng, margin=0.2)
    J = robot.jacobian(q)
    A = pin.crba(robot.model, robot.data, q)
    A = np.triu(A) + np.triu(A, 1).T
    g = pin.computeGeneralizedGravity(robot.model, robot.data, q)
    dq, dq_meas = rng.normal(size=7), rng.normal(size=7)
    tau = tick.qp_torque(A, g, J, dq, dq_meas, 20.0, DT, 10.0)
    Ai = np.linalg.inv(A)
    Jbar = Ai @ J.T @ np.linalg.inv(J @ Ai @ J.T)
    expected = g + (np.eye(7) - Jbar @ J).T @ (20.0 * DT * dq + 10.0 * (dq - dq_meas))
    # JA⁻¹Jᵀ is regularised by 1e-12 of its trace (linalg.py): agreement to its conditioning
    np.testing.assert_allclose(tau, expected, rtol=0, atol=1e-6 * np.linalg.norm(expected))


def test_elbow_advance_unwraps_the_arm_angle_and_ages_the_interval() -> None:
    rng = np.random.default_rng(4)
    path = np.cumsum(rng.uniform(-0.5, 0.5, 400)) + 3.0  # crosses ±π many times
    memory = elbow_memory.elbow_memory(path[0])
    pose = rng.normal(size=12)
    unwrapped = []
    for ns in path:
        value, recompute = elbow_memory.elbow_advance(float(np.angle(np.exp(1j * ns))), pose, memory, 10, 1e-6)
        assert recompute  # no interval known yet
        unwrapped.append(value)
    np.testing.assert_allclose(unwrapped, path, atol=1e-12)
    elbow_memory.store_interval(memory, -1.0, 2.0, False, pose)
    moved = pose + 2e-6
    poses = [pose] * 12 + [moved] * 12
    answers = [elbow_memory.elbow_advance(memory[elbow_memory.NS], p, memory, 10, 1e-6)[1] for p in poses]
    # the same pose keeps the interval at any age; a moved tool renews it once it is 10 ticks old
    assert answers == [False] * 12 + [True] * 12
    assert memory[elbow_memory.IV_AGE] == 24


def test_elbow_bounds_are_the_shifted_interval_clipped_and_the_sigmoid() -> None:
    rng = np.random.default_rng(5)
    cfg = qpnso.ElbowConfig(half_width_deg=50, safety_margin_deg=10)
    params = elbow_memory.elbow_parameters(
        cfg.half_width_rad,
        cfg.safety_margin_rad,
        cfg.stiffness_min,
        cfg.stiffness_max,
        cfg.alpha_per_rad,
        cfg.d_rad,
        0.1,
        0.01,
        10,
    )
    for _ in range(300):
        lo = rng.uniform(-4, 4)
        hi = lo + rng.uniform(0.1, 6.0)
        full = bool(rng.random() < 0.2)
        memory = elbow_memory.elbow_memory(0.0)
        elbow_memory.store_interval(memory, lo, hi, full, np.zeros(12))
        turns = int(rng.integers(-3, 4))
        ns = rng.uniform(lo, hi) + 2 * np.pi * turns
        ns0 = ns + rng.uniform(-1.5, 1.5)
        interval = (
            qpnso.Interval(ns - np.pi, ns + np.pi, True)
            if full
            else qpnso.Interval(lo + 2 * np.pi * turns, hi + 2 * np.pi * turns, False)
        )
        expected = qpnso.clip_rom(ns0, cfg.half_width_rad, interval, cfg.safety_margin_rad)
        rom_lo, rom_hi, empty, iv_lo, iv_hi, k = elbow_memory.elbow_bounds(ns, memory, ns0, params)
        assert (iv_lo, iv_hi) == pytest.approx((interval.lo, interval.hi), abs=1e-12)
        assert (rom_lo, rom_hi, empty) == pytest.approx((expected.lo, expected.hi, expected.empty), abs=1e-12)
        span = cfg.stiffness_max - cfg.stiffness_min
        assert k == pytest.approx(span / (1 + np.exp(cfg.alpha_per_rad * (cfg.d_rad - abs(ns - ns0)))) + 10, rel=1e-12)
    unknown = elbow_memory.elbow_bounds(1.0, elbow_memory.elbow_memory(1.0), 1.0, params)
    assert unknown[3:5] == pytest.approx((1.0 - np.pi, 1.0 + np.pi))  # no interval yet: the circle around ns


def test_answer_bits_are_the_status_flags() -> None:
    assert Status(tick.answer_bits(1e-3, 0.0)) == Status.TOOL_LIMITED
    assert Status(tick.answer_bits(0.0, 1e-2)) == Status.ELBOW_SLACK
    assert tick.answer_bits(-1.0, -1.0) == 0
    from qpnso.control import flags

    bits = {name[5:]: value for name, value in vars(flags).items() if name.startswith("FLAG_")}
    assert {m.name: m.value for m in Status if m.value} == bits  # each bit named once, the same on both sides
    assert all(v > 0 and v & (v - 1) == 0 for v in bits.values()) and len(set(bits.values())) == len(bits)


# ------------------------------------------------------ compiled = general
def test_held_tool_ticks_equal_the_general_path(robot, monkeypatch) -> None:
    fast, slow = pair(robot)
    hits = count_compiled(fast, monkeypatch)
    rng = np.random.default_rng(3)
    for _ in range(3):
        held_both(fast, slow, robot.random_q(rng, margin=0.3), 400)
    assert hits[0] > 1000  # the compiled path did answer


def test_moving_tool_and_measured_velocity_equal_the_general_path(robot, monkeypatch) -> None:
    fast, slow = pair(robot)
    hits = count_compiled(fast, monkeypatch)
    fast.reset(Q0), slow.reset(Q0)
    q, dq = Q0.copy(), np.zeros(7)
    for k in range(1500):
        twist = np.array([0.05 * np.sin(k * DT * 3), 0.03, -0.02, 0.1, 0.0, -0.2 * np.cos(k * DT)])
        a, b = fast.step(q, dq=dq, tool_twist=twist), slow.step(q, dq=dq, tool_twist=twist)
        assert_same(a, b, tol=1e-11)
        dq = 0.9 * a.dq
        q = q + DT * a.dq
    assert hits[0] > 1000


def test_offline_tool_pose_equals_the_general_path(robot) -> None:
    fast, slow = pair(robot)
    fast.reset(Q0), slow.reset(Q0)
    pose = robot.tool_pose(Q0)
    q = Q0.copy()
    for k in range(300):
        target = pin.SE3(pose.rotation, pose.translation + np.array([0.0, 1e-4 * k, 0.0]))
        a, b = fast.step(q, tool_pose=target), slow.step(q, tool_pose=target)
        assert_same(a, b, tol=1e-11)
        q = q + DT * a.dq


def test_joint_limit_cutting_the_line_takes_the_general_cascade(robot, monkeypatch) -> None:
    """A tool motion the bounds cannot follow: the line misses the box, the compiled path steps aside."""
    fast, slow = pair(robot)
    hits = count_compiled(fast, monkeypatch)
    fast.reset(Q0), slow.reset(Q0)
    a = fast.step(Q0, tool_twist=np.array([5.0, 0, 0, 0, 0, 0]))
    b = slow.step(Q0, tool_twist=np.array([5.0, 0, 0, 0, 0, 0]))
    assert hits[0] == 0 and a.status & Status.TOOL_LIMITED
    assert_same(a, b)


def test_failed_level_two_holds_the_tool_as_the_general_path_does(robot, monkeypatch) -> None:
    fast, slow = pair(robot)
    for ctrl in (fast, slow):
        ctrl.reset(Q0)
        backend = ctrl.qp._backend
        monkeypatch.setattr(
            backend, "solve_arrays", lambda *args: _Raw(None, LevelStatus.INFEASIBLE, 3, "proxsuite TEST_FAILURE")
        )
    failures = fast.qp.stats.failures
    a, b = fast.step(Q0), slow.step(Q0)
    assert a.status & Status.QP_FAILED and not a.ok
    assert "level 2 of 2 infeasible: proxsuite TEST_FAILURE" in a.message and "tool held" in a.message
    assert_same(a, b)
    assert fast.qp.stats.failures == failures + 1
    J = robot.jacobian(Q0)
    np.testing.assert_allclose(J @ a.dq, 0, atol=1e-12)  # tool held: level 1's least-norm answer
    np.testing.assert_allclose(a.dq, np.linalg.pinv(J) @ (J @ a.dq), atol=1e-12)


def test_singular_tool_task_takes_the_damped_general_path(robot, monkeypatch) -> None:
    """Joints 2 and 6 at zero align axes 1, 3 and 5, 7: rank 5, no line; the damped cascade answers."""
    fast, slow = pair(robot)
    hits = count_compiled(fast, monkeypatch)
    q0 = Q0.copy()
    q0[1] = q0[5] = 0.0
    assert np.linalg.svd(robot.jacobian(q0), compute_uv=False)[-1] < 1e-6
    held_both(fast, slow, q0, 20)
    assert hits[0] == 0


def test_non_finite_level_two_answer_holds_the_tool(robot, monkeypatch) -> None:
    fast, slow = pair(robot)
    for ctrl in (fast, slow):
        ctrl.reset(Q0)
        monkeypatch.setattr(
            ctrl.qp._backend,
            "solve_arrays",
            lambda *args: _Raw(np.array([np.nan, 0.0]), LevelStatus.SOLVED, 1, "proxsuite PROXQP_SOLVED"),
        )
    a, b = fast.step(Q0), slow.step(Q0)
    assert a.status & Status.QP_FAILED and "non-finite" in a.message and "tool held" in a.message
    assert np.all(np.isfinite(a.dq)) and np.all(np.isfinite(a.tau))
    assert_same(a, b)


def test_interval_that_cannot_be_renewed_is_flagged_stale_on_both_paths(robot, monkeypatch) -> None:
    fast, slow = pair(robot)
    for ctrl in (fast, slow):
        ctrl.reset(Q0)
    twist = np.array([0.02, 0.0, 0.0, 0.0, 0.0, 0.0])
    q = Q0.copy()
    for k in range(40):
        if k == 5:  # from here on the interval cannot be computed: the last one stands, flagged

            def singular(*args):
                raise qpnso.SingularityError("test: no interval")

            monkeypatch.setattr(qpnso.control.controller, "continuity_interval", singular)
        a, b = fast.step(q, tool_twist=twist), slow.step(q, tool_twist=twist)
        assert_same(a, b, tol=1e-11)
        assert bool(a.status & Status.INTERVAL_STALE) == (k >= 10)  # renewed every 10 ticks while moving
        q = q + DT * a.dq


def test_nan_q_is_refused_before_anything_advances(robot) -> None:
    fast, _ = pair(robot)
    fast.reset(Q0)
    fast.step(Q0)
    memory, steps, ref = fast._elbow_memory.copy(), fast.step_count, fast.ref_position.copy()
    bad = Q0.copy()
    bad[3] = np.nan
    with pytest.raises(ValueError, match=r"q"):
        fast.step(bad, tool_twist=np.ones(6))
    assert np.array_equal(fast._elbow_memory, memory) and fast.step_count == steps
    assert np.array_equal(fast.ref_position, ref)


def test_mis_shaped_level_two_answer_holds_the_tool(robot, monkeypatch) -> None:
    fast, slow = pair(robot)
    for ctrl in (fast, slow):
        ctrl.reset(Q0)
        monkeypatch.setattr(
            ctrl.qp._backend,
            "solve_arrays",
            lambda *args: _Raw(np.zeros(3), LevelStatus.SOLVED, 1, "proxsuite PROXQP_SOLVED"),
        )
    a, b = fast.step(Q0), slow.step(Q0)
    assert a.status & Status.QP_FAILED and "mis-shaped" in a.message and "tool held" in a.message
    assert_same(a, b)


def test_compiled_tick_with_a_qpsolvers_back_end_equals_the_general_path(robot, monkeypatch) -> None:
    """The compiled tick hands its line QP to any back end (here DAQP, exact active set)."""
    fast, slow = pair(robot, qp_backend="daqp")
    hits = count_compiled(fast, monkeypatch)
    held_both(fast, slow, Q0, 200)
    assert hits[0] == 200


def test_strategies_other_than_qp_never_compile(robot) -> None:
    for name in ("damped", "fixed", "gradient", "rom", "elbow-up"):
        assert not Controller(robot, ControllerConfig(strategy=name)).compiled_tick
    assert not Controller(robot, ControllerConfig(qp_settings=qpnso.QPSettings(line_fast_path=False))).compiled_tick


def test_no_kernel_is_compiled_or_loaded_after_the_constructor(robot) -> None:
    """Whatever array kind the user passes (list, strided view, read-only, tuple), the tick's kernels
    run the versions the constructor's dry tick compiled: none is compiled or loaded mid-loop."""
    from qpnso import linalg
    from qpnso.qp import line

    ctrl = Controller(robot, ControllerConfig(strategy="qp"))
    from qpnso.control import state
    from qpnso.elbow import rom

    kernels = [
        tick.qp_tick,
        tick.qp_tick_answer,
        tick.qp_command,
        elbow_memory.arm_angle_singular,
        tick.limits_status,
        elbow_memory.max_abs_difference,
        elbow_memory.elbow_advance,
        elbow_memory.elbow_bounds,
        state.state_views,
        rom.clipped_bounds,
        linalg.least_norm_line,
        line.task_line,
        line.least_norm_point,
        line.checked_line_answer,
    ]
    before = [len(k.signatures) for k in kernels]
    ctrl.reset(Q0)
    wide = np.tile(Q0[:, None], (1, 3))  # a column of it is a strided view
    frozen = Q0.copy()
    frozen.flags.writeable = False
    twist = np.zeros((6, 2))[:, 0]
    for q in (list(Q0), wide[:, 1], frozen, tuple(Q0), Q0):
        cmd = ctrl.step(q, dq=np.zeros((7, 2))[:, 1], tool_twist=twist)
        assert np.all(np.isfinite(cmd.dq))
    pose = robot.tool_pose(Q0)
    ctrl.step(Q0, tool_pose=pose)
    assert [len(k.signatures) for k in kernels] == before


def _kernel_signatures() -> dict[str, int]:
    """Signature counts of every Numba kernel of every qpnso module (walked, not listed by hand)."""
    import importlib
    import pkgutil

    import numba

    out = {}
    for info in pkgutil.walk_packages(qpnso.__path__, "qpnso."):
        try:
            module = importlib.import_module(info.name)
        except ImportError:  # an optional dependency (extras) missing
            continue
        for name, value in vars(module).items():
            if isinstance(value, numba.core.dispatcher.Dispatcher) and value.py_func.__module__ == module.__name__:
                out[f"{module.__name__}.{name}"] = len(value.signatures)
    return out


@pytest.mark.parametrize("strategy", ["qp", "damped"])
def test_no_kernel_of_any_module_loads_in_a_tick_after_the_constructor(robot, strategy: str) -> None:
    """After the constructor, no tick loads or compiles a kernel of any qpnso module: the compiled tick, the
    general path, a dropped elbow (q = 0, the wrist over the shoulder; its K(ns) was once loaded in the first
    such tick, 85 ms when the cache had to be rebuilt), a joint just outside its limit, a tool pose."""
    _kernel_signatures()  # every module imported first
    ctrl = Controller(robot, ControllerConfig(strategy=strategy))
    before = _kernel_signatures()
    ctrl.reset(Q0)
    ctrl.step(Q0, tool_twist=[0.05, 0.0, 0.0, 0.0, 0.0, 0.1])
    outside = Q0.copy()
    outside[0] = robot.q_max[0] + 0.01
    ctrl.step(outside)
    ctrl.step(Q0, tool_pose=robot.tool_pose(Q0))
    ctrl.reset(np.zeros(7))
    cmd = ctrl.step(np.zeros(7))
    assert cmd.status & Status.ELBOW_DROPPED
    after = _kernel_signatures()
    assert {k: (before.get(k), n) for k, n in after.items() if n != before.get(k)} == {}
