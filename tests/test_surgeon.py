"""A surgeon from the literature (issue 32): physiological tremor on the hand alone, voluntary motion below 2 Hz,
the renamed subject key, the work per metre under both readings of the path, the intended motion's own S."""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest
from scipy import signal

import qpnso
from qpnso.lab.metrics import hand_summary, segment_smoothness
from qpnso.lab.simulation import SMOOTHNESS_CUTOFF_HZ, SimulationConfig, intended_smoothness
from qpnso.lab.surgeon import (
    SUBJECT_RANGES,
    Subject,
    Tremor,
    dome_targets,
    point_to_point_motion,
)

DT = 1e-3  # s, the plant's step
SETTLED_S = 1.0  # s: the records are judged after this (the tremor's start from rest is behind)


# ------------------------------------------------------------------ the hand alone, integrated independently
def hand_alone(subject: Subject, force: np.ndarray, dt: float) -> np.ndarray:
    """The hand alone (mass m held by the arm's K, B to a still intended pose at 0, starting there at rest)
    driven by ``force`` (n, 3) N sampled every ``dt`` s: m ẍ + B ẋ + K x = F(t), integrated per axis by SciPy's
    ``lsim`` (exact for the linearly interpolated force), independently of the code under test; x (n, 3) m."""
    t = dt * np.arange(len(force))
    system = signal.lti([1.0], [subject.mass, subject.damping, subject.stiffness])
    return np.column_stack([signal.lsim(system, force[:, i], t)[1] for i in range(3)])


def rms_and_peak(x: np.ndarray, dt: float) -> tuple[float, float]:
    """The RMS (m) of the 3-D displacement ``x`` (n, 3) after :data:`SETTLED_S`, and the frequency (Hz) of the
    peak of its Welch power spectrum (summed over the axes, 4096-sample segments)."""
    x = x[int(SETTLED_S / dt) :]
    f, pxx = signal.welch(x, fs=1.0 / dt, nperseg=4096, axis=0)
    return float(np.sqrt(np.mean(np.sum(x**2, axis=1)))), float(f[np.argmax(pxx.sum(axis=1))])


def physiological(rms: float, peak_hz: float) -> bool:
    """The literature's physiological tremor: 50–200 µm RMS, spectral peak in 8–12 Hz (surgeon.py's sources)."""
    return 50e-6 <= rms <= 200e-6 and 8.0 <= peak_hz <= 12.0


def previous_force_noise(subject_rms_n: float, n: int, dt: float, rng: np.random.Generator) -> np.ndarray:
    """The surgeon's noise before issue 32 (``ForceNoise``): white noise low-passed by a 2nd-order Butterworth
    filter at 10 Hz, ``subject_rms_n`` N RMS per axis (its start-up dropped)."""
    white = rng.standard_normal((n + 2000, 3))
    band = signal.sosfilt(signal.butter(2, 10.0, fs=1.0 / dt, output="sos"), white, axis=0)[2000:]
    return band * (subject_rms_n / np.sqrt(np.mean(band**2, axis=0)))


def test_the_tremor_makes_the_hand_alone_tremble_as_measured() -> None:
    """Must hold: for subjects drawn across the ranges, the hand alone driven by the tremor's force (integrated by
    SciPy's ``lsim``, not by the code under test) shows 50–200 µm RMS displacement with its Welch peak in 8–12 Hz, the
    subject's own RMS, and the tremor's displacement itself (F = m d̈ + B ḋ + K d produces exactly d)."""
    rng = np.random.default_rng(32)
    n = int(20.0 / DT)
    subjects = [Subject.draw(rng) for _ in range(8)]
    assert np.ptp([s.tremor_rms_m for s in subjects]) > 0.5 * np.ptp(SUBJECT_RANGES["tremor_rms_m"])  # spread
    for s in subjects:
        tremor = Tremor(s, DT, n, rng)
        x = hand_alone(s, tremor.force, DT)
        rms, peak = rms_and_peak(x, DT)
        assert physiological(rms, peak), (s, rms, peak)
        assert rms == pytest.approx(s.tremor_rms_m, rel=0.03)
        assert np.max(np.abs(x - tremor.displacement)) < 0.01 * s.tremor_rms_m


def test_the_previous_force_noise_fails_the_same_check() -> None:
    """Negative control: the noise it replaces (0.2–0.5 N RMS low-passed at 10 Hz) on the same hands puts
    ~1 mm RMS at the hand's resonance, below 8 Hz: the check above tells the two apart."""
    rng = np.random.default_rng(5)
    n = int(20.0 / DT)
    for _ in range(4):
        s = Subject.draw(rng)
        rms, peak = rms_and_peak(hand_alone(s, previous_force_noise(rng.uniform(0.2, 0.5), n, DT, rng), DT), DT)
        assert not physiological(rms, peak), (s, rms, peak)
        assert rms > 200e-6 and peak < 8.0


def test_no_tremor_is_no_force() -> None:
    """``tremor_rms_m`` 0 (the hold scenario's): no force at all; otherwise the force starts from 0 (the fade-in)."""
    assert not np.any(Tremor(Subject(tremor_rms_m=0.0), DT, 1000, np.random.default_rng(0)).force)
    tremor = Tremor(Subject(), DT, 1000, np.random.default_rng(0))
    assert np.all(tremor.force[0] == 0) and np.any(tremor.force[-1] != 0) and np.all(tremor(10**6) == tremor.force[-1])


# ------------------------------------------------------------------ the subject's keys
def test_an_old_subject_key_names_the_new_one(tmp_path) -> None:
    """``noise_rms`` / ``noise_cutoff_hz`` of earlier versions: a ConfigError naming ``tremor_rms_m``, from a
    table, from a simulation's settings and from a scenario file (the file named)."""
    with pytest.raises(qpnso.ConfigError, match=r"Subject: noise_rms = 0\.3: .*give 'tremor_rms_m'"):
        Subject.from_dict({"noise_rms": 0.3})
    with pytest.raises(
        qpnso.ConfigError, match=r"SimulationConfig: surgeon\.noise_cutoff_hz = 10\.0: .*'tremor_rms_m'"
    ):
        SimulationConfig(surgeon={"noise_cutoff_hz": 10.0})
    from qpnso.lab.scenarios import SCENARIO_DIR, load_scenario

    old = (SCENARIO_DIR / "hold.toml").read_text().replace("tremor_rms_m = 0.0", "noise_rms = 0.0")
    assert "noise_rms = 0.0" in old
    (tmp_path / "old.toml").write_text(old)
    with pytest.raises(qpnso.ConfigError, match=r"old\.toml: noise_rms = 0\.0: .*'tremor_rms_m'"):
        load_scenario(tmp_path / "old.toml")
    assert Subject.from_dict({"tremor_rms_m": 0.0}).tremor_rms_m == 0.0
    with pytest.raises(qpnso.ConfigError, match="unknown key 'tremor'"):
        Subject.from_dict({"tremor": 1.0})


# ------------------------------------------------------------------ voluntary motion below 2 Hz
def velocity_power_below(motion, cutoff_hz: float = 2.0, dt: float = DT) -> float:
    """The share of the intended motion's velocity power (summed over the axes; Parseval on the whole record,
    rest to rest) at frequencies below ``cutoff_hz``."""
    traj = motion.trajectory
    t = np.arange(traj.t[0], traj.t[-1], dt)
    v = traj.samples(t)[2]
    power = np.abs(np.fft.rfft(v, axis=0)) ** 2
    f = np.fft.rfftfreq(len(t), dt)
    return float(power[f < cutoff_hz].sum() / power.sum())


def test_voluntary_motion_is_below_2_hz() -> None:
    """Must hold (Riviere, Rader and Khosla 1997: 98.9 % of the voluntary power below 2 Hz): the experiments'
    intended motions at every subject's speed scale keep ≥ 95 % of their velocity power below 2 Hz: the
    mass/friction experiment's moves (its own parameters, three target orders) and scenarios A's and B's
    guidance tasks.  Control: the same moves four times faster do not (the measure can fail)."""
    from qpnso.lab.experiments.mass_friction import MassFrictionOptions
    from qpnso.lab.scenarios import load_scenario

    opts = MassFrictionOptions()
    pose = load_scenario("A").tool_pose()  # (the moves' spectrum does not depend on where the dome is)
    targets = dome_targets(pose.translation, opts.dome_radius, opts.moves)
    rng = np.random.default_rng(3)
    lo, hi = SUBJECT_RANGES["speed_scale"]
    for scale in (lo, 1.0, hi):
        for _ in range(3):
            order = targets[rng.permutation(opts.moves)]
            share = velocity_power_below(point_to_point_motion(pose, order, opts.peak_speed * scale, opts.dwell))
            assert share >= 0.95, (scale, share)
        for name in ("A", "B"):
            share = velocity_power_below(load_scenario(name).motion(scale))
            assert share >= 0.95, (name, scale, share)
    fast = point_to_point_motion(pose, targets, 4 * opts.peak_speed * hi, opts.dwell)
    assert velocity_power_below(fast) < 0.95


# ------------------------------------------------------------------ the work per metre, both readings
def test_hand_summary_work_readings_against_closed_forms() -> None:
    """On a synthetic record over one period T = 1 s: the tool moves along x with v = A cos 2πt (the measured
    path 2A/π), turns about z at ω = 1 rad/s; the hand pushes F along x and holds M about z, so the power is
    a cos θ + c with a = F·A, c = M·ω, and ∫|a cos θ + c| dt over a period is (2/π)(√(a² − c²) + c·arcsin(c/a))·T
    for |c| < a.  The intended path is a 3 cm line."""
    amplitude, force, moment = 0.1, 10.0, 0.5  # m/s, N, N·m
    a_w, c_w = force * amplitude, moment * 1.0
    assert c_w < a_w
    t = np.linspace(0.0, 1.0, 200_001)
    twist = np.zeros((len(t), 6))
    twist[:, 0], twist[:, 5] = amplitude * np.cos(2 * np.pi * t), 1.0
    wrench = np.zeros((len(t), 6))
    wrench[:, 0], wrench[:, 5] = force, moment
    p = np.zeros((len(t), 3))
    p[:, 0] = amplitude / (2 * np.pi) * np.sin(2 * np.pi * t)
    intended = np.zeros((len(t), 3))
    intended[:, 1] = np.linspace(0.0, 0.03, len(t))
    work = 2 / math.pi * (math.sqrt(a_w**2 - c_w**2) + c_w * math.asin(c_w / a_w))
    measured = 2 * amplitude / math.pi
    s = hand_summary(t, wrench, twist, p, intended)
    assert s["hand_work_J"] == pytest.approx(work, rel=1e-6)
    assert s["user_work_per_metre_N"] == pytest.approx(work / measured, rel=1e-6)
    assert s["intended_path_length_m"] == pytest.approx(0.03, rel=1e-12)
    assert s["user_work_per_nominal_metre_N"] == pytest.approx(work / 0.03, rel=1e-6)
    still = hand_summary(t, wrench, twist, p, np.zeros_like(p))  # a hold: no nominal path
    assert still["intended_path_length_m"] == 0.0 and math.isnan(still["user_work_per_nominal_metre_N"])
    assert "user_work_per_nominal_metre_N" not in hand_summary(t, wrench, twist, p)
    with pytest.raises(qpnso.InputError, match="intended_p must have shape"):
        hand_summary(t, wrench, twist, p, intended[:, :2])


# ------------------------------------------------------------------ the intended motion's own S
def test_the_intended_smoothness_of_a_minimum_jerk_move_is_sqrt_720() -> None:
    """Must hold: S of the noise-free intended motion, scored as a record is (sampled at the plant's ticks,
    low-passed, ending at rest), is √720 ≈ 26.8 for a minimum-jerk move (closed form: the jerk integral of
    10τ³ − 15τ⁴ + 6τ⁵ is 720) where the filter is transparent (100 Hz), whatever its length and speed; at the
    simulation's cut-off it is what the same filter makes of the closed-form move (a 6 Hz low-pass takes a few
    per cent off a one-second move).  The segment spans the whole move (it was cut by a sample at each end)."""
    start = pin.SE3(pin.rpy.rpyToMatrix(np.pi, 0.5, np.pi), np.array([0.65, 0.0, 0.5]))
    for length, speed in ((0.1, 0.1), (0.05, 0.12), (0.1, 0.05)):  # m, m/s: 0.8 to 3.8 s moves
        motion = point_to_point_motion(start, np.array([[0.65 + length, 0.0, 0.5]]), speed)
        t = np.arange(motion.trajectory.t[0], motion.trajectory.t[-1], DT)
        sharp = intended_smoothness(t, motion, 100.0)
        assert set(sharp) == {"intended_smoothness_segment_1", "intended_smoothness"}
        assert sharp["intended_smoothness"] == pytest.approx(np.sqrt(720.0), rel=0.01)
        ((a, b),) = motion.segments
        tau = np.clip((t - a) / (b - a), 0.0, 1.0)
        x = 0.65 + length * (10 * tau**3 - 15 * tau**4 + 6 * tau**5)
        closed_form = np.column_stack([x, np.zeros_like(x), np.full_like(x, 0.5)])
        scored = segment_smoothness(t, closed_form, [(0.0, b - a)], SMOOTHNESS_CUTOFF_HZ)["smoothness"]
        assert intended_smoothness(t, motion, SMOOTHNESS_CUTOFF_HZ)["intended_smoothness"] == pytest.approx(
            scored, rel=0.005
        )


def test_the_voluntary_correction_integrates_the_error_beyond_its_deadband_up_to_its_force() -> None:
    """Closed form: a constant 10 mm error for 1 s at 2 1/s moves the equilibrium by 2·(10 − 2) mm = 16 mm along
    it; a large error saturates at correction_force_max/stiffness; an error inside the deadband changes nothing."""
    from qpnso.lab.surgeon import VOLUNTARY_DEADBAND_M

    s = Subject(stiffness=200.0, correction_rate=2.0, correction_force_max=30.0)
    e = np.array([0.0, 0.01, 0.0])
    c = np.zeros(3)
    for _ in range(1000):
        c = s.correct(c, e, 1e-3)
    assert c == pytest.approx([0.0, 2.0 * (0.01 - VOLUNTARY_DEADBAND_M), 0.0], abs=1e-12)
    for _ in range(100_000):
        c = s.correct(c, np.array([0.3, 0.0, 0.0]), 1e-3)
    assert 200.0 * np.linalg.norm(c) == pytest.approx(30.0)
    assert np.all(s.correct(np.zeros(3), np.array([0.0, 0.0, 0.5 * VOLUNTARY_DEADBAND_M]), 1e-3) == 0.0)
    assert np.all(Subject(correction_rate=0.0).correct(np.zeros(3), e, 1e-3) == 0.0)
