"""Virtual surgeons: an intended tool motion driving a human-arm impedance at the tool (docs/method.md §9).

The hand is not a path follower.  The surgeon intends a motion (:class:`IntendedMotion`: minimum-jerk
point-to-point moves, the elbow paper's lemniscates timed by the two-thirds power law, or a hold); the
arm's endpoint impedance (:class:`Subject`: a hand mass at the tool, stiffness and damping, with
rotational counterparts) pulls the tool towards it, plus band-limited force noise (:class:`ForceNoise`).
The tool's path emerges from the interaction with the robot.

Parameters, fixed before any result was seen (stated assumptions, from the endpoint-impedance literature
the issue names: Mussa-Ivaldi, Hogan and Flash 1985; Burdet et al. 2001; Flash and Hogan 1985 for the
minimum-jerk moves; Lacquaniti, Terzuolo and Viviani 1983 for the two-thirds power law):

* translational: hand mass 1–2 kg, stiffness 100–300 N/m, damping 10–30 N·s/m (:data:`SUBJECT_RANGES`);
* rotational (ours, assumed; the wrist's stiffness of a relaxed grip is a few N·m/rad): stiffness
  2–6 N·m/rad, damping 0.05–0.2 N·m·s/rad, hand inertia 1e-3 kg·m² about each axis;
* force noise: 0.2–0.5 N RMS per axis, white noise low-passed at 10 Hz (physiological force
  fluctuation and tremor band; assumed);
* a subject is a uniform draw in these ranges (seeded); speed scales 0.8–1.2 of the protocol's speed.

In point-to-point moves the rotation about the tool axis is left free (``free_tool_axis``): the hand
neither holds nor turns the tool about it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np
import pinocchio as pin
from scipy import signal

from qpnso.control.trajectory import Trajectory
from qpnso.settings import check, out_of_range
from qpnso.settings import from_dict as settings_from_dict

SUBJECT_RANGES: dict[str, tuple[float, float]] = {
    "mass": (1.0, 2.0),  # kg
    "stiffness": (100.0, 300.0),  # N/m
    "damping": (10.0, 30.0),  # N·s/m
    "rotational_stiffness": (2.0, 6.0),  # N·m/rad
    "rotational_damping": (0.05, 0.2),  # N·m·s/rad
    "noise_rms": (0.2, 0.5),  # N per axis
    "speed_scale": (0.8, 1.2),
}
"""The ranges a subject is drawn from (uniform), see the module's docstring for their sources."""


@dataclass(frozen=True)
class Subject:
    """A virtual surgeon: hand mass (kg) at the tool, arm endpoint impedance towards the intended pose
    (N/m, N·s/m; N·m/rad, N·m·s/rad), force noise (N RMS per axis, low-passed at ``noise_cutoff_hz``),
    and the scale of the protocol's speed.  Defaults: the middle of :data:`SUBJECT_RANGES`."""

    mass: float = 1.5
    stiffness: float = 200.0
    damping: float = 20.0
    rotational_stiffness: float = 4.0
    rotational_damping: float = 0.125
    rotational_inertia: float = 1e-3  # kg·m²
    noise_rms: float = 0.35
    noise_cutoff_hz: float = 10.0
    speed_scale: float = 1.0

    def __post_init__(self) -> None:
        check(self)
        for f in fields(self):
            if getattr(self, f.name) < 0:
                raise out_of_range(self, f.name, "must be >= 0")
        if self.noise_cutoff_hz <= 0 or self.speed_scale <= 0:
            raise out_of_range(self, "noise_cutoff_hz" if self.noise_cutoff_hz <= 0 else "speed_scale", "must be > 0")

    @classmethod
    def from_dict(cls, values: dict, where: str = "") -> "Subject":
        """Build from plain data (a ``[surgeon]`` table)."""
        return settings_from_dict(cls, values, where)

    @classmethod
    def draw(cls, rng: np.random.Generator) -> "Subject":
        """A subject drawn uniformly from :data:`SUBJECT_RANGES`."""
        return cls(**{k: float(rng.uniform(lo, hi)) for k, (lo, hi) in SUBJECT_RANGES.items()})

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


class ForceNoise:
    """Band-limited force noise (N, world frame, 3 axes): white noise low-passed by a 2nd-order Butterworth
    filter at ``cutoff_hz``, scaled to ``rms`` N per axis; ``n`` samples at ``dt`` s, seeded."""

    def __init__(self, rms: float, cutoff_hz: float, dt: float, n: int, rng: np.random.Generator) -> None:
        white = rng.standard_normal((n + 2000, 3))
        if rms > 0:
            sos = signal.butter(2, min(cutoff_hz, 0.45 / dt), fs=1.0 / dt, output="sos")
            band = signal.sosfilt(sos, white, axis=0)[2000:]  # the filter's start-up dropped
            self.samples = band * (rms / np.sqrt(np.mean(band**2, axis=0)))
        else:
            self.samples = np.zeros((n, 3))

    def __call__(self, k: int) -> np.ndarray:
        """The noise force at sample ``k`` (held at the last sample beyond the end)."""
        return self.samples[min(k, len(self.samples) - 1)]


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
    return IntendedMotion(traj, moving_segments(traj, rest_speed=1e-4), free_tool_axis=True)


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
