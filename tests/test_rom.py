"""ROM [E 5], clipping [E 10]/[E 11], stiffness [E 6], set-point, and the intervals figure."""

from __future__ import annotations

import importlib.util
import math

import numpy as np
import pytest

from qpnso.elbow.intervals import Interval
from qpnso.elbow.rom import ClippedRom, ElbowConfig, clip_rom, rom_bounds, setpoint, sigmoid_stiffness, stiffness
from qpnso.errors import ConfigError, InputError, QpnsoError

D = math.radians


def test_rom_bounds() -> None:
    assert rom_bounds(0.3, 0.5) == pytest.approx((-0.2, 0.8))
    with pytest.raises(InputError):
        rom_bounds(float("nan"), 0.5)
    with pytest.raises(InputError):
        rom_bounds(0.0, -0.1)


@pytest.mark.parametrize(
    ("lo", "hi", "expected"),
    [
        (-3.0, 3.0, (0.5 - D(50), 0.5 + D(50))),  # interval wide: ROM unchanged
        (0.0, 3.0, (D(10), 0.5 + D(50))),  # [E 10]: low end clipped to lo_i + d_sg
        (-3.0, 1.0, (0.5 - D(50), 1.0 - D(10))),  # [E 11]: high end clipped to hi_i − d_sg
    ],
)
def test_clip_rom(lo: float, hi: float, expected: tuple[float, float]) -> None:
    rt = clip_rom(0.5, D(50), Interval(lo, hi, False), D(10))
    assert (rt.lo, rt.hi) == pytest.approx(expected) and not rt.empty


def test_clip_rom_unwraps_ns0_and_full_circle() -> None:
    interval = Interval(5.0, 7.0, False)  # unwrapped around an arm angle near 2π
    rt = clip_rom(6.0 - 2 * math.pi, 0.2, interval, 0.1)
    assert (rt.lo, rt.hi) == pytest.approx((5.8, 6.2))
    assert clip_rom(1.0, 0.3, Interval(-2.0, 4.2, True), 0.1) == ClippedRom(pytest.approx(0.7), pytest.approx(1.3))


def test_clip_rom_empty_cases() -> None:
    rt = clip_rom(0.0, 0.2, Interval(1.0, 2.5, False), 0.1)  # ROM entirely below the interval
    assert rt.empty and rt.lo == rt.hi == pytest.approx(1.1)
    rt = clip_rom(3.0, 0.2, Interval(1.0, 2.5, False), 0.1)
    assert rt.empty and rt.lo == rt.hi == pytest.approx(2.4)
    rt = clip_rom(1.0, 0.2, Interval(0.9, 1.05, False), 0.1)  # narrower than twice the margin
    assert rt.empty and rt.lo == rt.hi == pytest.approx(0.975)


def test_stiffness_double_sigmoid() -> None:
    cfg = ElbowConfig(half_width_deg=50, stiffness_min=10, stiffness_max=30)
    ns0 = 0.4
    x = np.linspace(-2, 2, 101) + ns0
    k = stiffness(x, ns0, cfg)
    reference = (30 - 10) / (1 + np.exp(cfg.alpha_per_rad * (cfg.d_rad - np.abs(x - ns0)))) + 10  # [E 6]
    assert np.allclose(k, reference, rtol=1e-12)
    assert stiffness(ns0 + cfg.d_rad, ns0, cfg) == pytest.approx(20.0)  # inflection at d
    assert stiffness(ns0, ns0, cfg) < 10.1 and stiffness(ns0 + D(50), ns0, cfg) > 27.0  # soft inside, stiff at ends
    assert np.allclose(k, stiffness(2 * ns0 - x, ns0, cfg))  # symmetric
    assert stiffness(1e6, 0.0, cfg) == pytest.approx(30.0)  # no overflow
    floats = [stiffness(float(v), ns0, cfg) for v in x]  # the per-tick kernel, one angle at a time
    assert all(type(v) is float for v in floats)
    np.testing.assert_allclose(floats, reference, rtol=1e-12)


def test_setpoint_saturates() -> None:
    rt = ClippedRom(-0.5, 0.7)
    assert [setpoint(x, rt) for x in (-1.0, 0.1, 2.0)] == [-0.5, 0.1, 0.7]
    assert setpoint(0.9, (-0.5, 0.7)) == 0.7


def test_config_validation_and_units() -> None:
    cfg = ElbowConfig(half_width_deg=10, safety_margin_deg=10)
    assert cfg.half_width_rad == pytest.approx(D(10)) and cfg.safety_margin_rad == pytest.approx(D(10))
    for bad in (
        {"half_width_deg": -1},
        {"stiffness_min": 40.0},
        {"alpha": 0.0},
        {"safety_margin_deg": float("nan")},
        {"safety_margin_deg": -0.5},  # (a negative value close to 0 too)
        {"stiffness_min": -0.5},
    ):
        with pytest.raises(ConfigError):
            ElbowConfig(**bad)


@pytest.mark.skipif(importlib.util.find_spec("matplotlib") is None, reason="matplotlib not installed")
def test_plot_intervals_writes_png(tmp_path) -> None:
    from qpnso.lab.plots import plot_intervals
    from qpnso.model.robot import load_robot

    robot = load_robot("lwr4p")
    path = plot_intervals(robot, np.radians([20, 60, -30, -80, 40, 70, 10]), rom=ElbowConfig(), out=tmp_path / "iv.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 20_000


def test_elbow_config_defaults_are_the_papers_scenario_a() -> None:
    """``ElbowConfig()`` is the documented scenario A: ROM ±50°, safety margin 10°, stiffness 10–30 N·m/rad, with
    α = 12/Δns and d = 0.75·Δns derived from the half width."""
    cfg = ElbowConfig()
    assert (cfg.half_width_deg, cfg.safety_margin_deg, cfg.stiffness_min, cfg.stiffness_max) == (50.0, 10.0, 10.0, 30.0)
    assert cfg.alpha is None and cfg.d is None
    assert cfg.safety_margin_rad == pytest.approx(D(10))
    assert cfg.alpha_per_rad == pytest.approx(12.0 / D(50)) and cfg.d_rad == pytest.approx(0.75 * D(50))


def test_half_width_may_be_a_half_turn_but_no_more() -> None:
    """The half width is in (0, 180] deg: 180° (the whole circle) is accepted, anything above is refused."""
    assert ElbowConfig(half_width_deg=180).half_width_rad == pytest.approx(math.pi)
    assert ElbowConfig(half_width_deg=179.5).half_width_rad == pytest.approx(D(179.5))
    with pytest.raises(ConfigError, match=r"half_width_deg must be in \(0, 180\]"):
        ElbowConfig(half_width_deg=180.5)


def test_clip_rom_margin_zero_clips_at_the_interval_and_negative_is_refused() -> None:
    """With d_sg = 0 ROM_t is ROM ∩ interval itself ([E 10]/[E 11] without margin): ROM [-0.5, 1.5] in
    [0, 1] → [0, 1]; a negative margin is refused naming ``margin``."""
    rt = clip_rom(0.5, 1.0, Interval(0.0, 1.0, False), 0.0)
    assert (rt.lo, rt.hi, rt.empty) == (0.0, 1.0, False)
    with pytest.raises(InputError, match="margin must be >= 0"):
        clip_rom(0.5, 1.0, Interval(0.0, 1.0, False), -0.1)


def test_stiffness_of_a_zero_dimensional_array_is_a_float() -> None:
    """A 0-d array is a single arm angle: the stiffness is a Python ``float``, at the inflection point d the
    middle of the span (K_min + K_max)/2 = 20 N·m/rad, computed by the per-tick kernel's float specialisation
    (with the JIT on, no second specialisation is compiled for the 0-d array)."""
    cfg = ElbowConfig()
    assert stiffness(0.4 + cfg.d_rad, 0.4, cfg) == pytest.approx(20.0)  # the float path, compiled once
    before = len(getattr(sigmoid_stiffness, "signatures", ()))
    k = stiffness(np.array(0.4 + cfg.d_rad), 0.4, cfg)
    assert type(k) is float and k == pytest.approx(20.0)
    assert len(getattr(sigmoid_stiffness, "signatures", ())) == before


@pytest.mark.parametrize("half_width", [-0.5, -1e-9, -2.0])
def test_clip_rom_refuses_a_negative_half_width(half_width: float) -> None:
    """A ROM of negative half width (rad) is refused by name, however small the excess."""
    with pytest.raises(InputError, match="half_width must be >= 0"):
        clip_rom(0.5, half_width, Interval(-1.0, 1.0, False), 0.1)


# ------------------------------------------------- the rom strategy's set-point (issue 31, item 5)
def _numpy_joints(motion, ns: np.ndarray) -> np.ndarray:
    """``SelfMotion.joints`` as NumPy computed it before the kernel (``basis @ num.T``, ``arctan2``/``arccos``):
    the reference the kernel must reproduce to round-off."""
    from qpnso.elbow.closed_form import TAN

    basis = np.column_stack([np.sin(ns), np.cos(ns), np.ones_like(ns)])
    n, d = basis @ motion.num.T, basis @ motion.den.T
    q = np.where(motion.kind == TAN, np.arctan2(n, d), np.arccos(np.clip(d, -1.0, 1.0))) * motion.sign
    q[:, 3] = motion.q4
    return q


@pytest.mark.parametrize("name", ["lwr4p", "iiwa14"])
def test_the_closed_form_ik_kernel_reproduces_the_numpy_formula_and_the_pose(name: str, rng) -> None:
    """``ik`` (now the kernel :func:`~qpnso.elbow.closed_form.joints_along`) equals the NumPy formula it replaced to
    1e-12 rad over 40 random configurations × 25 arm angles, and every answer puts the tool back on the pose
    (Pinocchio FK) with the asked arm angle (the independent arm angle of [E 2]–[E 4])."""
    from conftest import reference_arm_angle

    from qpnso.elbow.srs import branch, ik, self_motion
    from qpnso.model.robot import load_robot

    robot = load_robot(name)
    ns = np.linspace(-math.pi, math.pi, 25, endpoint=False)
    checked = 0
    for _ in range(40):
        q = robot.random_q(rng, margin=0.1)
        pose, b = robot.tool_pose(q), branch(robot, q)
        try:
            joints = ik(robot, pose, ns, b)
        except QpnsoError:
            continue  # (an undefined arm angle at this pose)
        np.testing.assert_allclose(joints, _numpy_joints(self_motion(robot, pose, b), ns), rtol=0, atol=1e-12)
        for k in range(0, ns.size, 6):
            err = (robot.tool_pose(joints[k]).inverse() * pose).homogeneous - np.eye(4)
            assert np.abs(err).max() < 1e-9
            assert abs(math.remainder(reference_arm_angle(robot, joints[k]) - ns[k], 2 * math.pi)) < 1e-9
        checked += 1
    assert checked >= 30


@pytest.mark.parametrize("name", ["lwr4p", "iiwa14"])
def test_the_rom_set_point_is_the_librarys_ik_at_the_saturated_arm_angle(name: str) -> None:
    """Outside ROM_t the ``rom`` strategy's step ``q_des − q`` is ``qpnso.elbow.srs.ik`` at the saturated arm angle
    (the tool's pose, the branch of q) minus q, to round-off, and its set-point is computed once per tick: the
    level-2 target and the torque of one tick ask for it once (they asked twice, 0.2 ms each in Python)."""
    import pinocchio as pin

    from qpnso.control.config import ControllerConfig
    from qpnso.control.controller import Controller
    from qpnso.control.strategies import RomModulation
    from qpnso.elbow.srs import branch, ik
    from qpnso.model.robot import load_robot

    robot = load_robot(name)
    ctrl = Controller(robot, ControllerConfig(strategy="rom"))
    q = robot.sample_configuration()
    ctrl.reset(q, ns0=ctrl.evaluate(q).arm_angle + 1.5)  # the elbow 1.5 rad from the ROM's centre: outside ROM_t
    calls = []
    ik_step = RomModulation._ik_step

    def counted(self, state, elbow, target):
        calls.append(target)
        return ik_step(self, state, elbow, target)

    RomModulation._ik_step = counted  # type: ignore[method-assign]
    try:
        for _ in range(5):
            cmd = ctrl.step(q)
            q = q + ctrl.config.dt * cmd.dq
    finally:
        RomModulation._ik_step = ik_step  # type: ignore[method-assign]
    assert len(calls) == 5
    state, elbow = ctrl.evaluate(q), ctrl.records.elbow()  # (the last tick's arm angle and ROM_t)
    target = min(max(elbow.ns, elbow.rom[0]), elbow.rom[1])
    assert target != elbow.ns
    step = ctrl.strategy._setpoint_step(state, elbow)
    wrapped = (target + math.pi) % (2 * math.pi) - math.pi
    expected = ik(robot, pin.SE3(state.tool_rotation.copy(), state.tool_position.copy()), wrapped, branch(robot, q)) - q
    np.testing.assert_allclose(step, expected, rtol=0, atol=1e-12)
