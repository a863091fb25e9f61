"""Virtual surgeons: an intended tool motion driving a human-arm impedance at the tool (docs/method.md §9).

The hand is not a path follower.  The surgeon intends a motion (:class:`IntendedMotion`: minimum-jerk
point-to-point moves, the elbow paper's lemniscates timed by the two-thirds power law, or a hold); the
arm's endpoint impedance (:class:`Subject`: a hand mass at the tool, stiffness and damping, with
rotational counterparts) pulls the tool towards it, plus the force of the hand's physiological tremor
(:class:`Tremor`).  The tool's path emerges from the interaction with the robot.

Parameters, fixed before any result was seen (sources, or "assumed" where none exists):

* translational impedance: hand mass 1–2 kg, stiffness 100–300 N/m, damping 10–30 N·s/m
  (:data:`SUBJECT_RANGES`; stated assumptions from the endpoint-impedance literature: Mussa-Ivaldi, Hogan
  and Flash 1985; Burdet et al. 2001);
* rotational (assumed; the wrist's stiffness of a relaxed grip is a few N·m/rad): stiffness
  2–6 N·m/rad, damping 0.05–0.2 N·m·s/rad, hand inertia 1e-3 kg·m² about each axis;
* voluntary motion: minimum-jerk moves (Flash and Hogan 1985), lemniscates timed by the two-thirds power
  law (Lacquaniti, Terzuolo and Viviani 1983); its power lies below 2 Hz as measured in eye surgeons (Riviere,
  Rader and Khosla, "Characteristics of hand motion of eye surgeons", Proc. 19th IEEE EMBS, 1997,
  pp. 1690–1693: on average 98.9 % of the power of the voluntary movements below 2 Hz);
* physiological tremor: a displacement of the hand band-limited to :data:`TREMOR_BAND_HZ` = 8–12 Hz (the
  8–12 Hz component of physiological tremor: Elble, "Physiologic and essential tremor", Neurology 36(2),
  1986, pp. 225–231; Elble and Koller, *Tremor*, Johns Hopkins University Press, 1990), of RMS 50–200 µm
  (Wells, Yang, MacLachlan, Handa, Gehlbach and Riviere, "Comparison of baseline tremor under various
  microsurgical conditions", Proc. IEEE SMC 2013, pp. 1482–1487: "an RMS amplitude on the order of
  50–200 µm ... commonly in the 8–12 Hz band", and 144 µm 3-D RMS in their unconstrained pointing task;
  Riviere, Rader and Khosla 1997: eye surgeons holding an instrument still, 49 µm RMS error, 202 µm
  range).  ``tremor_rms_m`` is the RMS of the 3-D displacement, shared equally by the three axes
  (isotropic: assumed); its spectrum is flat in the band (assumed); no rotational tremor (assumed).  It
  acts as the force that produces exactly that displacement on the hand alone, F = m d̈ + B ḋ + K d
  (the subject's hand mass, damping and stiffness), so a hand holding a free instrument trembles as
  measured; on the robot the tool's tremor is what the coupled dynamics make of that force.  It starts
  from rest over :data:`TREMOR_FADE_IN_S` (ours, assumed) so that hand and tool start together at rest;
* voluntary correction: the surgeon means to reach the intended pose, so the impedance's equilibrium point
  moves by the integral of the remaining position error, ċ = ``correction_rate``·(p_d − p), with the
  force ``stiffness``·‖c‖ capped at ``correction_force_max`` (:data:`VOLUNTARY_CORRECTION_RATE`,
  :data:`VOLUNTARY_FORCE_MAX`; assumed).  Without it a 100–300 N/m spring towards the intended path cannot
  break the joints' Coulomb friction (1.5 N·m each): on the rigid-body plant the tool moved 18 mm of an
  intended 211 mm and the trials measured a stuck tool;
* a subject is a uniform draw in these ranges (seeded); speed scales 0.8–1.2 of the protocol's speed
  (assumed).

In point-to-point moves the rotation about the tool axis is left free (``free_tool_axis``): the hand
neither holds nor turns the tool about it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields

import numpy as np
import pinocchio as pin

from qpnso.control.trajectory import Trajectory
from qpnso.settings import SettingError, check, out_of_range, show
from qpnso.settings import from_dict as settings_from_dict

SUBJECT_RANGES: dict[str, tuple[float, float]] = {
    "mass": (1.0, 2.0),  # kg
    "stiffness": (100.0, 300.0),  # N/m
    "damping": (10.0, 30.0),  # N·s/m
    "rotational_stiffness": (2.0, 6.0),  # N·m/rad
    "rotational_damping": (0.05, 0.2),  # N·m·s/rad
    "tremor_rms_m": (50e-6, 200e-6),  # m, RMS of the tremor's 3-D displacement
    "speed_scale": (0.8, 1.2),
}
"""The ranges a subject is drawn from (uniform), see the module's docstring for their sources."""

TREMOR_BAND_HZ: tuple[float, float] = (8.0, 12.0)
"""Hz: the band of the physiological tremor's displacement (Elble 1986; Elble and Koller 1990)."""
TREMOR_FADE_IN_S = 0.5
"""s: the tremor grows from rest over this time (a quintic ramp; ours, assumed), so that the hand starts at rest
with the tool and the hand alone follows the tremor's displacement from the first sample."""
TREMOR_SYNTHESIS_S = 10.0
"""s: the shortest record the tremor is synthesised over (0.1 Hz between its spectral lines, 41 in the band),
so that a short run's tremor has the same spectrum as a long one's."""
VOLUNTARY_CORRECTION_RATE = 2.0
"""1/s: the voluntary correction's integral gain (time constant 0.5 s, a crossover well below the 2 Hz of
voluntary motion and slower than the 0.15–0.25 s of visuomotor feedback; ours, assumed)."""
VOLUNTARY_DEADBAND_M = 2e-3
"""m: errors below this are not corrected (the hand's positioning resolution without magnification; ours,
assumed): the correction stops hunting once the tool is near its target."""
VOLUNTARY_FORCE_MAX = 30.0
"""N: the largest force the voluntary correction adds to the impedance's (ours, assumed: a hand guiding an
instrument; twenty times the tremor's force, below a hand's maximal push)."""
RENAMED_SUBJECT_KEYS = {
    "noise_rms": "the surgeon's force noise (N) is now the physiological tremor: give 'tremor_rms_m' (m, RMS of "
    "its 3-D displacement, 50e-6 to 200e-6; 0 turns it off)",
    "noise_cutoff_hz": "the tremor's band is fixed at 8-12 Hz (TREMOR_BAND_HZ): give 'tremor_rms_m' (m, RMS of "
    "its 3-D displacement) instead",
}
"""Keys of earlier versions of :class:`Subject` and what replaced them (the error a table with one gets)."""


@dataclass(frozen=True)
class Subject:
    """A virtual surgeon: hand mass (kg) at the tool, arm endpoint impedance towards the intended pose
    (N/m, N·s/m; N·m/rad, N·m·s/rad), the physiological tremor's RMS displacement ``tremor_rms_m`` (m, 3-D,
    band :data:`TREMOR_BAND_HZ`; 0: none, see :class:`Tremor`) and the scale of the protocol's speed.
    Defaults: the middle of :data:`SUBJECT_RANGES`."""

    mass: float = 1.5
    stiffness: float = 200.0
    damping: float = 20.0
    rotational_stiffness: float = 4.0
    rotational_damping: float = 0.125
    rotational_inertia: float = 1e-3  # kg·m²
    tremor_rms_m: float = 125e-6
    speed_scale: float = 1.0
    correction_rate: float = VOLUNTARY_CORRECTION_RATE  # 1/s: the voluntary correction's integral gain
    correction_force_max: float = VOLUNTARY_FORCE_MAX  # N: the largest force the correction adds

    def __post_init__(self) -> None:
        check(self)
        for f in fields(self):
            if getattr(self, f.name) < 0:
                raise out_of_range(self, f.name, "must be >= 0")
        if self.speed_scale <= 0:
            raise out_of_range(self, "speed_scale", "must be > 0")

    @classmethod
    def from_dict(cls, values: dict, where: str = "") -> "Subject":
        """Build from plain data (a ``[surgeon]`` table); a key of an earlier version
        (:data:`RENAMED_SUBJECT_KEYS`) is a :class:`~qpnso.settings.SettingError` naming what replaced it."""
        if isinstance(values, Mapping):
            for key, value in values.items():
                if key in RENAMED_SUBJECT_KEYS:
                    raise SettingError(where or cls.__name__, str(key), RENAMED_SUBJECT_KEYS[key], show(value))
        return settings_from_dict(cls, values, where)

    @classmethod
    def draw(cls, rng: np.random.Generator) -> "Subject":
        """A subject drawn uniformly from :data:`SUBJECT_RANGES`."""
        return cls(**{k: float(rng.uniform(lo, hi)) for k, (lo, hi) in SUBJECT_RANGES.items()})

    def correct(self, correction: np.ndarray, error: np.ndarray, dt: float) -> np.ndarray:
        """The voluntary correction (m, world frame) after ``dt`` s with the position ``error`` p_d − p (m):
        ``correction + dt·correction_rate·error``, scaled so that ``stiffness``·‖c‖ ≤ ``correction_force_max``."""
        norm_e = float(np.sqrt(error @ error))
        beyond = error * (1.0 - VOLUNTARY_DEADBAND_M / norm_e) if norm_e > VOLUNTARY_DEADBAND_M else 0.0 * error
        c = correction + dt * self.correction_rate * beyond
        limit = self.correction_force_max / self.stiffness if self.stiffness > 0 else 0.0
        norm = float(np.sqrt(c @ c))
        return c * (limit / norm) if norm > limit else c

    def wrench(self, intended: tuple, tool: tuple, free_axis: bool = False) -> np.ndarray:
        """The arm's impedance wrench on the hand (N, N·m; world frame, at the tool point).

        ``intended`` = (p, R, v, ω) of the intended motion, ``tool`` = (p, R, v, ω) of the tool.  With
        ``free_axis`` the moment has no component along the tool's z axis (the tool turns freely about it).
        """
        p_d, r_d, v_d, w_d = intended
        p, r, v, w = tool
        force = self.stiffness * (p_d - p) + self.damping * (v_d - v)
        moment = self.rotational_stiffness * pin.log3(r_d @ r.T) + self.rotational_damping * (w_d - w)
        if free_axis:
            z = r[:, 2]
            moment = moment - (moment @ z) * z
        return np.concatenate([force, moment])


class Tremor:
    """The physiological tremor of ``surgeon``'s hand over ``n`` samples at ``dt`` s (world frame, 3 axes),
    seeded by ``rng``: the displacement ``displacement`` (m) with its derivatives ``velocity`` (m/s) and
    ``acceleration`` (m/s²), from :func:`band_limited_motion` (:data:`TREMOR_BAND_HZ`, 3-D RMS
    ``surgeon.tremor_rms_m``), and ``force`` (N), the force that produces exactly that displacement on the hand
    alone (mass m held by the arm's stiffness K and damping B to a still intended pose):
    F = m d̈ + B ḋ + K d."""

    def __init__(self, surgeon: Subject, dt: float, n: int, rng: np.random.Generator) -> None:
        self.displacement, self.velocity, self.acceleration = band_limited_motion(
            surgeon.tremor_rms_m, TREMOR_BAND_HZ, dt, n, rng
        )
        self.force = (
            surgeon.mass * self.acceleration + surgeon.damping * self.velocity + surgeon.stiffness * self.displacement
        )

    def __call__(self, k: int) -> np.ndarray:
        """The tremor's force (N) at sample ``k`` (held at the last sample beyond the end)."""
        return self.force[min(k, len(self.force) - 1)]


def band_limited_motion(
    rms: float, band_hz: tuple[float, float], dt: float, n: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A random 3-D displacement (m) with its velocity (m/s) and acceleration (m/s²), (n, 3) each at ``dt`` s: a
    sum of sinusoids at every spectral line of a record of max(``n``·``dt``, :data:`TREMOR_SYNTHESIS_S`) s that
    lies in ``band_hz``, with Gaussian coefficients (a flat spectrum in the band), differentiated exactly (iω,
    −ω² per line); scaled so that the RMS of the 3-D displacement over the samples after the fade-in (all of
    them in a shorter record) is ``rms``; then grown from rest by the quintic ramp w(t) over
    :data:`TREMOR_FADE_IN_S` (d = w·s, ḋ = ẇ·s + w·ṡ, d̈ = ẅ·s + 2ẇ·ṡ + w·s̈), so d, ḋ (and the force) start at 0.
    Zero arrays for ``rms`` 0."""
    if rms == 0:
        zero = np.zeros((n, 3))
        return zero, zero.copy(), zero.copy()
    length = max(n, int(np.ceil(TREMOR_SYNTHESIS_S / dt)))
    f = np.fft.rfftfreq(length, dt)
    lines = (f >= band_hz[0]) & (f <= band_hz[1])
    spectrum = np.zeros((len(f), 3), dtype=complex)
    spectrum[lines] = rng.standard_normal((lines.sum(), 3)) + 1j * rng.standard_normal((lines.sum(), 3))
    omega = 2.0 * np.pi * f[:, None]
    s, ds, dds = (
        np.fft.irfft(x, length, axis=0)[:n] for x in (spectrum, 1j * omega * spectrum, -(omega**2) * spectrum)
    )
    t = dt * np.arange(n)
    steady = t >= TREMOR_FADE_IN_S if t[-1] > 2 * TREMOR_FADE_IN_S else np.ones(n, dtype=bool)
    scale = rms / np.sqrt(np.mean(np.sum(s[steady] ** 2, axis=1)))
    s, ds, dds = s * scale, ds * scale, dds * scale
    w, dw, ddw = (x[:, None] for x in quintic_ramp(t / TREMOR_FADE_IN_S))
    dw, ddw = dw / TREMOR_FADE_IN_S, ddw / TREMOR_FADE_IN_S**2
    return w * s, dw * s + w * ds, ddw * s + 2 * dw * ds + w * dds


def quintic_ramp(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ramp r(x) = 10x³ − 15x⁴ + 6x⁵ on [0, 1] (0 before, 1 after) and its first two derivatives in x:
    0 to 1 with zero slope and curvature at both ends."""
    x = np.clip(x, 0.0, 1.0)
    return x**3 * (10 - 15 * x + 6 * x**2), 30 * x**2 * (1 - x) ** 2, 60 * x * (1 - x) * (1 - 2 * x)


@dataclass(frozen=True, eq=False)
class IntendedMotion:
    """What the surgeon means to do: the tool ``trajectory`` (world frame), its ``segments`` ((t0, t1) s:
    each a rest-to-rest move whose smoothness is taken on its own) and whether the rotation about the tool
    axis is free."""

    trajectory: Trajectory
    segments: tuple[tuple[float, float], ...]
    free_tool_axis: bool = False

    @property
    def duration(self) -> float:
        """Length of the motion (s)."""
        return float(self.trajectory.t[-1] - self.trajectory.t[0])

    def start(self, fraction: float) -> "IntendedMotion":
        """The first ``fraction`` (0, 1] of the motion (quick checks), with the segments that begin in it."""
        if fraction >= 1.0:
            return self
        t0 = float(self.trajectory.t[0])
        end = t0 + fraction * self.duration
        segments = tuple((a, min(b, end)) for a, b in self.segments if a < end)
        return IntendedMotion(self.trajectory.window(t0, end), segments, self.free_tool_axis)


def moving_segments(traj: Trajectory, rest_speed: float = 1e-6) -> tuple[tuple[float, float], ...]:
    """The maximal time spans (s) in which ``traj``'s sampled speed exceeds ``rest_speed`` (m/s): its
    rest-to-rest moves."""
    t = np.asarray(traj.t)
    speed = np.linalg.norm(np.diff(traj.position, axis=0), axis=1) / np.diff(t)
    moving = np.concatenate([[False], speed > rest_speed, [False]])
    edges = np.flatnonzero(np.diff(moving.astype(int)))
    return tuple((float(t[a]), float(t[min(b, len(t) - 1)])) for a, b in zip(edges[::2], edges[1::2]))


def power_law_curve(curve, half_width: float, samples: int = 4001):
    """``curve(σ)`` (σ ∈ [0, 1]) re-timed by the two-thirds power law: under a uniform parameter τ its
    speed is proportional to R^{1/3}, R the radius of curvature clipped at ``half_width`` m (a straight
    stretch would ask an unbounded speed), so the hand is slower in the curves.  Returns ``g(τ)``."""
    s = np.linspace(0.0, 1.0, samples)
    p = curve(s)
    d1 = np.gradient(p, s, axis=0)
    d2 = np.gradient(d1, s, axis=0)
    speed = np.linalg.norm(d1, axis=1)
    kappa = np.linalg.norm(np.cross(d1, d2), axis=1) / np.maximum(speed, 1e-12) ** 3
    radius = np.minimum(1.0 / np.maximum(kappa, 1e-12), half_width)
    dtau = speed / radius ** (1.0 / 3.0)  # time per unit σ at a speed ∝ R^{1/3}
    tau = np.concatenate([[0.0], np.cumsum(0.5 * (dtau[1:] + dtau[:-1]) * np.diff(s))])
    tau /= tau[-1]
    return lambda t: curve(np.interp(np.atleast_1d(t), tau, s))


def guidance_motion(center: pin.SE3, size: float, speed: float, pause: float = 0.5, dt: float = 0.01) -> IntendedMotion:
    """The elbow paper's guidance task as intended by a surgeon: its four segments
    (:func:`qpnso.control.trajectory.guidance_path`: lemniscates in xy, xz, yz, then the tilted parabola),
    each re-timed by the two-thirds power law (:func:`power_law_curve`) inside a minimum-jerk envelope of
    peak speed ``speed`` m/s, with ``pause`` s at rest after each, so that every segment's record ends at
    rest."""
    from qpnso.control.trajectory import _concatenate, _constant_orientation, _segment, guidance_curves

    c, rot = center.translation.copy(), center.rotation.copy()
    a = size / 2
    curves = guidance_curves(c, a)
    parts = []
    rest = np.tile(c, (max(1, round(pause / dt)) + 1, 1))
    for g in curves:
        parts += [_segment(power_law_curve(g, a), dt, speed=speed), rest]
    traj = _constant_orientation(_concatenate(parts), rot, dt)
    return IntendedMotion(traj, moving_segments(traj))


def point_to_point_motion(
    start: pin.SE3, targets: np.ndarray, peak_speed: float, dwell: float = 0.5, dt: float = 0.01
) -> IntendedMotion:
    """Minimum-jerk straight moves from ``start`` through ``targets`` ((K, 3) m, world) at ``peak_speed``
    m/s, ``dwell`` s at rest at each target (and at the end), the start's orientation intended throughout
    and the rotation about the tool axis free ([M] §V-B; Flash and Hogan)."""
    from qpnso.control.trajectory import point_to_point

    traj = point_to_point(
        [start, *np.asarray(targets, dtype=float)], peak_speed=peak_speed, dwell=dwell, lift=0.0, dt=dt
    )
    traj = with_rest(traj, dwell)
    return IntendedMotion(traj, moving_segments(traj), free_tool_axis=True)


def with_rest(traj: Trajectory, duration: float) -> Trajectory:
    """``traj`` followed by ``duration`` s at rest at its last pose."""
    dt = float(traj.t[1] - traj.t[0])
    extra = max(1, round(duration / dt))
    t = np.concatenate([traj.t, traj.t[-1] + dt * np.arange(1, extra + 1)])
    return Trajectory(
        t,
        np.vstack([traj.position, np.repeat(traj.position[-1:], extra, axis=0)]),
        np.vstack([traj.quaternion, np.repeat(traj.quaternion[-1:], extra, axis=0)]),
    )


def hold_motion(pose: pin.SE3, duration: float, dt: float = 0.01) -> IntendedMotion:
    """The tool held still at ``pose`` for ``duration`` s: no segment."""
    from qpnso.control.trajectory import hold

    return IntendedMotion(hold(pose, duration, dt=dt), ())


def dome_targets(center: np.ndarray, radius: float = 0.05, count: int = 6) -> np.ndarray:
    """``count`` points (m, world) on a spherical cap of ``radius`` m above ``center``: one at the top and
    the rest on a ring at 60° from it, the size of a surgical target (the mass/friction paper's six points;
    their exact layout is not published: ours, assumed)."""
    pts = [np.asarray(center, dtype=float) + [0.0, 0.0, radius]]
    ring = math.radians(60.0)
    for k in range(count - 1):
        phi = 2 * math.pi * k / (count - 1)
        pts.append(
            np.asarray(center)
            + radius * np.array([math.sin(ring) * math.cos(phi), math.sin(ring) * math.sin(phi), math.cos(ring)])
        )
    return np.array(pts)
