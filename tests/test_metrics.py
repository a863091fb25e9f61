"""Tests of qpnso.lab.metrics against closed forms and independent computations."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from qpnso.errors import InputError
from qpnso.lab.metrics import (
    constraint_proximity,
    elbow_mobility,
    path_length,
    relative_work,
    rotation_angles,
    smoothness,
    summarize_run,
    timing_summary,
    tracking_error,
    uniform_period,
    user_work_per_metre,
)


def test_elbow_mobility_unwraps():
    ns = np.array([3.0, 3.1, -3.1, -3.0, 3.05])  # crosses ±π: true span 3.0 → 2π−3.0
    assert elbow_mobility(ns) == pytest.approx((2 * np.pi - 3.0) - 3.0)
    assert elbow_mobility(np.radians([-10, 20, 5])) == pytest.approx(np.radians(30))
    with pytest.raises(InputError, match="NaN"):
        elbow_mobility([0.0, np.nan])


def test_constraint_proximity_brute_force():
    rng = np.random.default_rng(0)
    ns = rng.uniform(-1, 1, 50)
    lo, hi = ns - rng.uniform(0.1, 1, 50), ns + rng.uniform(0.1, 1, 50)
    expected = min(min(n - a, b - n) for n, a, b in zip(ns, lo, hi))
    assert constraint_proximity(ns, lo, hi) == pytest.approx(expected)
    assert constraint_proximity([0.0, 0.5], -1.0, np.inf) == pytest.approx(1.0)  # scalars, open bound
    assert constraint_proximity([0.0, 1.5], -1.0, 1.0) == pytest.approx(-0.5)  # outside: negative
    with pytest.raises(InputError, match="different lengths"):
        constraint_proximity([0.0, 1.0], [0.0], [1.0])


def test_path_length():
    theta = np.linspace(0, 2 * np.pi, 10001)
    circle = np.column_stack([np.cos(theta), np.sin(theta), np.zeros_like(theta)]) * 0.2
    assert path_length(circle) == pytest.approx(2 * np.pi * 0.2, rel=1e-7)
    assert path_length([[0, 0, 0], [3, 4, 0], [3, 4, 12]]) == pytest.approx(17.0)


def test_smoothness_polynomial_closed_form():
    # p(t) = (t⁴, 0, 0) on [0, 1]: jerk 24t, ∫ jerk² = 192, T = L = 1 → S = √192
    t = np.linspace(0, 1, 2001)
    p = np.column_stack([t**4, 0 * t, 0 * t])
    assert smoothness(t, p) == pytest.approx(np.sqrt(192), rel=5e-3)


def test_smoothness_minimum_jerk_closed_form():
    # x = L(10τ³ − 15τ⁴ + 6τ⁵): ∫ jerk² dt = 720 L²/T⁵ → S = √720 for any L, T
    for length, duration in ((0.1, 2.0), (3.0, 0.5)):
        t = np.linspace(0, duration, 4001)
        tau = t / duration
        x = length * (10 * tau**3 - 15 * tau**4 + 6 * tau**5)
        p = np.column_stack([x, 2 * x, -x]) / np.sqrt(6)
        assert smoothness(t, p) == pytest.approx(np.sqrt(720), rel=2e-3)


def test_smoothness_circle_closed_form():
    # constant speed on a circle: |jerk| = r ω³, L = r ω T → S = (ω T)² (total angle squared)
    r, w, duration = 0.05, 1.3, 4.0
    t = np.linspace(0, duration, 4001)
    p = r * np.column_stack([np.cos(w * t), np.sin(w * t), np.zeros_like(t)])
    assert smoothness(t, p) == pytest.approx((w * duration) ** 2, rel=2e-3)


def test_smoothness_requires_uniform_time_and_motion():
    t = np.array([0.0, 0.1, 0.2, 0.35, 0.4])
    with pytest.raises(InputError, match="uniform"):
        smoothness(t, np.random.default_rng(0).normal(size=(5, 3)))
    with pytest.raises(InputError, match="zero length"):
        smoothness(np.arange(5.0), np.zeros((5, 3)))


def test_rotation_angles_match_pinocchio():
    rng = np.random.default_rng(2)
    a = np.array([pin.exp3(rng.normal(size=3)) for _ in range(30)])
    b = np.array([pin.exp3(rng.normal(size=3) * s) for s in np.linspace(1e-9, 3.1, 30)])
    expected = [np.linalg.norm(pin.log3(x @ y.T)) for x, y in zip(a, b)]
    np.testing.assert_allclose(rotation_angles(a, b), expected, atol=1e-9)
    small = pin.exp3(np.array([1e-9, 0, 0]))
    assert rotation_angles(small[None], np.eye(3)[None])[0] == pytest.approx(1e-9, rel=1e-6)


def test_tracking_error():
    p_ref = np.zeros((3, 3))
    p = np.array([[0.003, 0.004, 0], [0, 0, 0.001], [0, 0, 0]])
    r_ref = np.array([np.eye(3)] * 3)
    r = np.array([pin.utils.rotate("z", a) for a in (0.1, -0.2, 0.0)])
    err = tracking_error(p_ref, p, r_ref, r)
    assert err["position_error_max_m"] == pytest.approx(0.005)
    assert err["position_error_mean_m"] == pytest.approx(0.002)
    assert err["rotation_error_max_rad"] == pytest.approx(0.2)
    assert err["rotation_error_mean_rad"] == pytest.approx(0.1)
    assert set(tracking_error(p_ref, p)) == {"position_error_mean_m", "position_error_max_m"}
    with pytest.raises(InputError, match="both"):
        tracking_error(p_ref, p, r_ref)


def test_user_work_closed_form():
    # 2 N along x, 1 m out at 0.5 m/s and 1 m back: |work| = 4 J over 2 m → 2 N
    t = np.linspace(0, 4, 4001)
    v = np.where(t < 2, 0.5, -0.5)[:, None] * [1, 0, 0]
    x = np.where(t < 2, 0.5 * t, 2 - 0.5 * t)
    p = np.column_stack([x, 0 * x, 0 * x])
    f = np.tile([2.0, 7.0, 0.0], (len(t), 1))  # y force does no work
    assert user_work_per_metre(f, v, t, p) == pytest.approx(2.0, rel=1e-3)
    # wrench/twist: torque 2 N·m about z with ω = 1 rad/s; |power| = |±1 + 2| W:
    # 3 W for 2 s out, 1 W for 2 s back → 8 J over 2 m
    w6 = np.column_stack([f, np.tile([0, 0, 2.0], (len(t), 1))])
    v6 = np.column_stack([v, np.tile([0, 0, 1.0], (len(t), 1))])
    assert user_work_per_metre(w6, v6, t, p) == pytest.approx(4.0, rel=1e-3)
    with pytest.raises(InputError, match="both be"):
        user_work_per_metre(f, v6, t, p)
    with pytest.raises(InputError, match="t needs at least 2 samples, got 1"):  # named, not "different lengths"
        user_work_per_metre(f[:2], v[:2], t[:1], p[:2])


def test_user_work_sinusoid():
    # F = sin(t) x̂, v = cos(t) x̂ on [0, 2π]: ∫|sin cos| = 2; p = sin(t) x̂ has L = 4
    t = np.linspace(0, 2 * np.pi, 20001)
    f = np.column_stack([np.sin(t), 0 * t, 0 * t])
    v = np.column_stack([np.cos(t), 0 * t, 0 * t])
    p = np.column_stack([np.sin(t), 0 * t, 0 * t])
    assert user_work_per_metre(f, v, t, p) == pytest.approx(0.5, rel=1e-6)


def test_relative_work():
    out = relative_work({"dp": [2.0, 4.0], "nso": [1.0, 2.0]})
    np.testing.assert_allclose(out["dp"], [2 / 3, 4 / 3])
    np.testing.assert_allclose(out["nso"], [1 / 3, 2 / 3])


def test_timing_summary_by_hand():
    s = timing_summary(np.arange(1, 101) * 1e-6)
    assert s["median_us"] == pytest.approx(50.5)
    assert s["p95_us"] == pytest.approx(95.05)  # linear: 95 + 0.05·(96 − 95)
    assert s["p99_us"] == pytest.approx(99.01)
    assert s["max_us"] == pytest.approx(100.0)


def test_summarize_run():
    n = 400
    t = np.arange(n) * 0.01
    ns = np.radians(20) * np.sin(t)
    theta = 0.5 * t
    pos = 0.1 * np.column_stack([np.cos(theta), np.sin(theta), np.zeros(n)])
    arrays = {
        "t": t,
        "ns": ns,
        "interval_lo": np.full(n, -np.radians(60)),
        "interval_hi": np.full(n, np.radians(30)),
        "rom_lo": np.full(n, -np.radians(50)),
        "rom_hi": np.full(n, np.radians(50)),
        "tool_position": pos,
        "ref_position": pos + [0.001, 0, 0],
        "tool_rotation_error": np.full(n, np.radians(0.5)),
        "status": np.where(np.arange(n) % 4 == 0, 5, 0),
        "tick_time": np.full(n, 2e-4),
    }
    s = summarize_run(arrays, status_flags={"OK": 0, "QP_FAILED": 1, "ELBOW_DROPPED": 2, "ELBOW_SLACK": 4})
    assert s["ticks"] == n and s["duration_s"] == pytest.approx(3.99)
    assert s["elbow_mobility_deg"] == pytest.approx(np.degrees(ns.max() - ns.min()))
    assert s["constraint_proximity_deg"] == pytest.approx(30 - np.degrees(ns.max()))
    assert s["rom_proximity_deg"] == pytest.approx(50 - 20, abs=1e-3)
    assert s["smoothness"] == pytest.approx((0.5 * 3.99) ** 2, rel=1e-2)  # circle: (ωT)²
    assert s["tool_position_error_max_m"] == pytest.approx(0.001)
    assert s["tool_rotation_error_max_deg"] == pytest.approx(0.5)
    assert s["status_not_ok_ticks"] == 100 and s["status_QP_FAILED_ticks"] == 100
    assert s["status_ELBOW_SLACK_ticks"] == 100 and s["status_ELBOW_DROPPED_ticks"] == 0
    assert "status_OK_ticks" not in s
    assert s["tick_time_p99_us"] == pytest.approx(200.0)
    assert all(isinstance(v, float) for v in s.values())
    assert set(summarize_run({"t": t})) == {"duration_s", "ticks"}


def test_smoothness_of_a_sampled_cubic_is_exact() -> None:
    """p(t) = t³ along x, N samples dt apart: the third difference is exactly 6·dt³, L = T³, T = (N−1)·dt, so
    S = √(T⁵/L² · 36·(N−3)·dt) = 6·√((N−3)/(N−1)) to round-off; few samples make an off-by-one in the
    duration or the jerk count visible (a 1/N change)."""
    for n, dt in ((11, 0.1), (7, 0.25)):
        t = dt * np.arange(n)
        p = np.zeros((n, 3))
        p[:, 0] = t**3
        assert smoothness(t, p) == pytest.approx(6.0 * np.sqrt((n - 3) / (n - 1)), rel=1e-12)


def test_work_per_metre_integrates_a_linear_power_exactly() -> None:
    """F = (2, 0, 0) N, v = (1 + 3t, 0, 0) m/s on uneven times: the power 2 + 6t is linear, so the trapezoidal
    rule is exact: ∫₀^T = 2T + 3T²; the path (a 4 m segment, sampled unevenly) gives L = 4 m."""
    t = np.array([0.0, 0.1, 0.35, 0.4, 0.9, 1.0])
    force = np.tile([2.0, 0.0, 0.0], (t.size, 1))
    velocity = np.zeros((t.size, 3))
    velocity[:, 0] = 1.0 + 3.0 * t
    p = np.zeros((t.size, 3))
    p[:, 1] = 4.0 * t**2
    assert user_work_per_metre(force, velocity, t, p) == pytest.approx((2.0 + 3.0) / 4.0, rel=1e-13)


def test_input_errors_name_the_expected_shape_and_the_first_bad_index() -> None:
    """The shape error states the shape the argument must have ((N,) for a per-tick series, (N, 3) for
    positions), and the NaN error names the first bad sample, written out by hand here."""
    with pytest.raises(InputError, match=r"ns must have shape \(N,\), got \(2, 2\)"):
        elbow_mobility(np.zeros((2, 2)))
    with pytest.raises(InputError, match=r"p must have shape \(N, 3\), got \(4,\)"):
        path_length(np.zeros(4))
    with pytest.raises(InputError, match=r"ns contains NaN or inf \(first at index 1\)"):
        elbow_mobility([0.0, np.nan, 1.0, np.inf, np.nan])


def test_uniform_period_error_reports_the_largest_deviation() -> None:
    """t = (0, 1, 3, 4) s: the mean period is 4/3 s and the steps (1, 2, 1) s deviate from it by at most
    2 − 4/3 = 0.667 s, which the error message reports."""
    assert uniform_period([0.0, 0.5, 1.0, 1.5]) == pytest.approx(0.5)
    with pytest.raises(InputError, match=r"period 1\.33333 s; deviation 0\.667 s"):
        uniform_period([0.0, 1.0, 3.0, 4.0])


def test_smoothness_needs_four_samples_and_works_with_exactly_four() -> None:
    """The third difference needs 4 samples: with 4 samples of p = t³ (one jerk value 6, T = 3·dt, L = T³) S is
    6·√(1/3) exactly; with 3 samples there is no jerk and smoothness refuses, naming the minimum."""
    dt = 0.5
    t = dt * np.arange(4)
    p = np.zeros((4, 3))
    p[:, 0] = t**3
    assert smoothness(t, p) == pytest.approx(6.0 * np.sqrt(1.0 / 3.0), rel=1e-12)
    with pytest.raises(InputError, match="p needs at least 4 samples, got 3"):
        smoothness(t[:3], p[:3])


def test_work_per_metre_refuses_a_repeated_time_stamp() -> None:
    """A repeated time stamp (Δt = 0) is not strictly increasing: refused, as a decreasing one is."""
    f = np.tile([1.0, 0.0, 0.0], (4, 1))
    p = np.zeros((4, 3))
    p[:, 0] = np.arange(4.0)
    with pytest.raises(InputError, match="strictly increasing"):
        user_work_per_metre(f, f, [0.0, 1.0, 1.0, 2.0], p)


def test_summarize_run_of_four_ticks_by_hand() -> None:
    """Four ticks 0.5 s apart: the tool path p = t³ along x gives the smoothness 6·√(1/3) (as
    :func:`smoothness` with exactly 4 samples); 1 non-OK status tick out of 4 is a fraction 0.25; the slowest
    tick of 1.5 ms is 1500 µs = 1.5 ms."""
    t = 0.5 * np.arange(4)
    p = np.zeros((4, 3))
    p[:, 0] = t**3
    s = summarize_run(
        {
            "t": t,
            "tool_position": p,
            "status": np.array([0, 5, 0, 0]),
            "tick_time": np.array([1e-4, 1.5e-3, 2e-4, 3e-4]),
        }
    )
    assert s["path_length_m"] == pytest.approx(27.0 / 8.0)
    assert s["smoothness"] == pytest.approx(6.0 * np.sqrt(1.0 / 3.0), rel=1e-12)
    assert s["status_not_ok_ticks"] == 1.0 and s["status_not_ok_fraction"] == 0.25
    assert s["tick_time_max_us"] == pytest.approx(1500.0) and s["tick_time_max_ms"] == pytest.approx(1.5)
    assert s["slow_ticks"] == 0.0  # all below the 0.5 s period
