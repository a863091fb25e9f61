"""Tool trajectories: a timed sequence of tool poses in the world frame.

A :class:`Trajectory` holds samples ``t`` (s), ``position`` (m, world frame)
and ``quaternion`` (unit, world frame, order ``qx, qy, qz, qw`` — scalar LAST,
which is the order of ``pinocchio.Quaternion.coeffs()``, of
``pinocchio.SE3ToXYZQUAT`` and of ``scipy.spatial.transform.Rotation.as_quat``).

Between samples (:meth:`Trajectory.sample`):

* position: the C² cubic spline through the samples (SciPy ``CubicSpline``,
  not-a-knot ends); the linear velocity returned is the spline's exact time
  derivative, so velocity feed-forward and position are consistent;
* orientation: slerp between consecutive samples,
  ``R(t) = R_k · exp(s · log(R_kᵀ R_{k+1}))``, ``s = (t - t_k)/(t_{k+1} - t_k)``;
  the angular velocity is constant on each interval and given in the WORLD
  frame, ``ω = R_k · log(R_kᵀ R_{k+1}) / (t_{k+1} - t_k)`` (rad/s), so that
  ``R(t + h) ≈ exp(h ω) R(t)``;
* outside ``[t_0, t_end]`` the pose is clamped to the end sample and both
  velocities are zero.

CSV files (:func:`read_csv`, :func:`write_csv`) have the header
``t,x,y,z,qx,qy,qz,qw`` (any column order) and one sample per line.  Row numbers
in error messages are 1-based DATA rows (data row 1 is the line after the
header).

Generators (world z is up, lengths in m, speeds in m/s, sample period ``dt``):
:func:`guidance_path` (the elbow paper's path, [E] Fig. 4),
:func:`point_to_point` (the mass/friction paper's moves, [M] §V-B) and
:func:`hold`.  Every moving segment follows one geometric curve ``g(σ)``,
``σ ∈ [0, 1]``, with the minimum-jerk (quintic) time scaling
``σ = 10τ³ - 15τ⁴ + 6τ⁵`` (zero velocity and acceleration at both ends,
bounded jerk).
"""

from __future__ import annotations

import csv
import io
import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import pinocchio as pin
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation

from qpnso.errors import TrajectoryError
from qpnso.settings import read_utf8

COLUMNS = ("t", "x", "y", "z", "qx", "qy", "qz", "qw")
"""CSV columns: time (s), position (m, world), unit quaternion (scalar last)."""

QUATERNION_NORM_TOLERANCE = 1e-3
"""Quaternions whose norm is within this of 1 are normalised; others are refused."""


# --------------------------------------------------------------------------- class


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Tool poses over time, world frame.

    ``t`` (N,) s strictly increasing, ``position`` (N, 3) m, ``quaternion``
    (N, 4) ``qx, qy, qz, qw``.  Construction validates the arrays (raising
    :class:`TrajectoryError` naming the first bad row, 1-based), normalises
    quaternions within 1e-3 of unit norm and flips signs so consecutive
    quaternions have a non-negative dot product.  The stored arrays are
    read-only copies.
    """

    t: np.ndarray
    position: np.ndarray
    quaternion: np.ndarray
    _rotation: np.ndarray = field(init=False, repr=False)
    _omega: np.ndarray = field(init=False, repr=False)
    _rotvec: np.ndarray = field(init=False, repr=False)
    _coef: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        t, p, q = _validated(self.t, self.position, self.quaternion, "row")
        rot = Rotation.from_quat(q)  # SciPy's order is scalar last, like ours
        rotvec = (rot[:-1].inv() * rot[1:]).as_rotvec()  # body frame, per interval
        mats = rot.as_matrix()
        omega = np.einsum("kij,kj->ki", mats[:-1], rotvec) / np.diff(t)[:, None]
        coef = CubicSpline(t, p, axis=0).c  # (4, N-1, 3), highest power first
        for name, value in (
            ("t", t),
            ("position", p),
            ("quaternion", q),
            ("_rotation", mats),
            ("_omega", omega),
            ("_rotvec", rotvec),
            ("_coef", coef),
        ):
            value.flags.writeable = False
            object.__setattr__(self, name, value)

    def __len__(self) -> int:
        return len(self.t)

    @property
    def duration(self) -> float:
        """``t_end - t_0`` in s."""
        return float(self.t[-1] - self.t[0])

    @property
    def rotation(self) -> np.ndarray:
        """(N, 3, 3) tool rotation matrices at the samples (world frame)."""
        return self._rotation

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(position (3,) m, rotation (3, 3), linear velocity (3,) m/s,
        angular velocity (3,) rad/s)`` at time ``t`` (s), all in the world frame: :meth:`samples` at one time."""
        p, r, v, w = self.samples(np.array([float(t)]))
        return p[0], r[0], v[0], w[0]

    def samples(self, t: object) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The poses and velocities at the times ``t`` (N,) s, all at once: positions (N, 3) m, rotations
        (N, 3, 3), linear velocities (N, 3) m/s and angular velocities (N, 3) rad/s, world frame.

        Cubic-spline position with its exact derivative; slerp orientation (``R_k exp(s·rotvec_k)``) with
        the world-frame angular velocity of the current interval; clamped with zero velocities outside the
        time range (see the module docstring; at ``t_0`` itself the first interval's velocities).
        """
        ts = np.asarray(t, dtype=float).reshape(-1)
        if not np.all(np.isfinite(ts)):
            raise TrajectoryError(f"sample times must be finite, got {ts[~np.isfinite(ts)][0]}")
        T = self.t
        k = np.clip(np.searchsorted(T, ts, side="right") - 1, 0, len(T) - 2)
        dx = (ts - T[k])[:, None]
        c = self._coef[:, k]  # (4, N, 3)
        p = ((c[0] * dx + c[1]) * dx + c[2]) * dx + c[3]
        v = (3.0 * c[0] * dx + 2.0 * c[1]) * dx + c[2]
        s = (ts - T[k]) / (T[k + 1] - T[k])
        r = self._rotation[k] @ Rotation.from_rotvec(s[:, None] * self._rotvec[k]).as_matrix()
        w = self._omega[k].copy()
        before, after = ts <= T[0], ts > T[-1]
        for outside, end in ((before, 0), (after, len(T) - 1)):
            if outside.any():
                p[outside], r[outside], v[outside], w[outside] = self.position[end], self._rotation[end], 0.0, 0.0
        start = ts == T[0]
        v[start], w[start] = self._coef[2, 0], self._omega[0]
        return p, r, v, w

    def window(self, t_start: float, t_end: float) -> "Trajectory":
        """The samples with ``t_start <= t <= t_end`` (s), as a new trajectory."""
        keep = (self.t >= t_start) & (self.t <= t_end)
        if np.count_nonzero(keep) < 2:
            raise TrajectoryError(f"window [{t_start}, {t_end}] s holds fewer than 2 samples")
        return Trajectory(self.t[keep], self.position[keep], self.quaternion[keep])

    def pose(self, t: float) -> pin.SE3:
        """The tool pose at ``t`` (s) as a ``pinocchio.SE3`` (world frame)."""
        p, r, _, _ = self.sample(t)
        return pin.SE3(r, p)


def _validated(t, position, quaternion, row: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Checked float copies of the arrays; ``row`` is the word used in messages."""
    arrays = []
    for name, value, width in (("t", t, None), ("position", position, 3), ("quaternion", quaternion, 4)):
        try:
            a = np.array(value, dtype=float)
        except (TypeError, ValueError) as exc:
            raise TrajectoryError(f"{name} is not numeric: {exc}") from None
        shape_ok = a.ndim == 1 if width is None else (a.ndim == 2 and a.shape[1] == width)
        if not shape_ok:
            want = "(N,)" if width is None else f"(N, {width})"
            raise TrajectoryError(f"{name} must have shape {want}, got {a.shape}")
        bad: np.ndarray | list[int] = np.flatnonzero(~np.isfinite(a).reshape(len(a), -1).all(axis=1)) if a.size else []
        if len(bad):
            raise TrajectoryError(f"{name}: {row} {bad[0] + 1} is not finite (NaN or inf)")
        arrays.append(a)
    t, p, q = arrays
    if not len(t) == len(p) == len(q):
        raise TrajectoryError(f"t, position and quaternion have different lengths: {len(t)}, {len(p)}, {len(q)}")
    if len(t) < 2:
        raise TrajectoryError(f"a trajectory needs at least 2 samples, got {len(t)}")
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        k = bad[0] + 1
        kind = "repeats" if t[k] == t[k - 1] else "is earlier than"
        raise TrajectoryError(
            f"time must be strictly increasing: {row} {k + 1} (t={float(t[k])!r}) {kind} "
            f"{row} {k} (t={float(t[k - 1])!r})"
        )  # float: no np.float64(...) in the text
    norms = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > QUATERNION_NORM_TOLERANCE)
    if bad.size:
        raise TrajectoryError(
            f"quaternion of {row} {bad[0] + 1} has norm {norms[bad[0]]:.6g}, "
            f"not within {QUATERNION_NORM_TOLERANCE} of 1"
        )
    q = q / norms[:, None]
    flips = np.concatenate([[False], np.einsum("ij,ij->i", q[1:], q[:-1]) < 0])
    signs = np.where(np.logical_xor.accumulate(flips), -1.0, 1.0)
    return t, p, q * signs[:, None]


# --------------------------------------------------------------------------- CSV


def read_csv(path: str | os.PathLike) -> Trajectory:
    """Read a trajectory CSV (header ``t,x,y,z,qx,qy,qz,qw`` in any order).

    Raises :class:`TrajectoryError` naming the file, the 1-based data row and
    the column for: missing or unreadable file, text not UTF-8 (naming the line;
    a leading byte-order mark is dropped), empty file, missing/unknown/duplicate
    column, wrong field count, unparsable number, NaN/inf, time not strictly
    increasing, quaternion far from unit norm, fewer than 2 rows.
    """
    path = Path(path)
    if not path.is_file():
        raise TrajectoryError(f"trajectory file not found: {path}")
    rows = list(csv.reader(io.StringIO(read_utf8(path, TrajectoryError), newline="")))
    while rows and not any(cell.strip() for cell in rows[-1]):
        rows.pop()  # trailing blank lines
    if not rows:
        raise TrajectoryError(f"{path}: empty file (expected header {','.join(COLUMNS)})")
    index = _header_index(rows[0], path)
    values = np.empty((len(rows) - 1, len(COLUMNS)))
    for i, row in enumerate(rows[1:], start=1):
        if len(row) != len(rows[0]):
            raise TrajectoryError(f"{path}: data row {i} has {len(row)} fields, expected {len(rows[0])}")
        for j, name in enumerate(COLUMNS):
            values[i - 1, j] = _parse(row[index[name]], path, i, name)
    try:
        _validated(values[:, 0], values[:, 1:4], values[:, 4:8], "data row")
    except TrajectoryError as exc:
        raise TrajectoryError(f"{path}: {exc}") from None
    return Trajectory(values[:, 0], values[:, 1:4], values[:, 4:8])


def _header_index(header: list[str], path: Path) -> dict[str, int]:
    names = [h.strip().lower() for h in header]
    for name in names:
        if name not in COLUMNS:
            raise TrajectoryError(f"{path}: unknown column {name!r} (expected {','.join(COLUMNS)})")
        if names.count(name) > 1:
            raise TrajectoryError(f"{path}: column {name!r} appears more than once")
    missing = [c for c in COLUMNS if c not in names]
    if missing:
        raise TrajectoryError(f"{path}: missing column(s) {', '.join(repr(m) for m in missing)}")
    return {name: names.index(name) for name in COLUMNS}


def _parse(text: str, path: Path, row: int, column: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise TrajectoryError(f"{path}: data row {row}, column {column!r}: cannot parse {text!r} as a number") from None
    if not math.isfinite(value):
        raise TrajectoryError(f"{path}: data row {row}, column {column!r}: {text.strip()!r} is not finite")
    return value


def write_csv(traj: Trajectory, path: str | os.PathLike, digits: int = 17) -> Path:
    """Write ``traj`` as CSV with ``digits`` significant digits (17: exact round trip).

    The file is written to a temporary file in the same directory, then renamed
    into place with ``os.replace``: on any failure no partial file is left.
    """
    path = Path(path)
    if not isinstance(traj, Trajectory):
        raise TrajectoryError(f"write_csv needs a Trajectory, got {type(traj).__name__}")
    t, p, q = _validated(traj.t, traj.position, traj.quaternion, "row")
    if not path.parent.is_dir():
        raise TrajectoryError(f"cannot write {path}: directory {path.parent} does not exist")
    if path.is_dir():
        raise TrajectoryError(f"cannot write {path}: it is a directory")
    fmt = f"{{:.{int(digits)}g}}"
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", newline="") as f:
            writer = csv.writer(f, lineterminator="\n")
            writer.writerow(COLUMNS)
            for row in np.column_stack([t, p, q]):
                writer.writerow([fmt.format(v) for v in row])
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600; give the usual mode
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


# --------------------------------------------------------------------------- generators


def min_jerk(tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Minimum-jerk time scaling ``σ(τ) = 10τ³ - 15τ⁴ + 6τ⁵`` and ``dσ/dτ``, τ ∈ [0, 1]."""
    tau = np.clip(tau, 0.0, 1.0)
    return tau**3 * (10 - 15 * tau + 6 * tau**2), 30 * tau**2 * (1 - tau) ** 2


def _segment(
    curve: Callable[[np.ndarray], np.ndarray], dt: float, *, speed: float | None = None, duration: float | None = None
) -> np.ndarray:
    """Positions (M+1, 3) at period ``dt`` of ``curve(σ)`` under the min-jerk scaling.

    The duration is ``duration`` or, with ``speed``, the shortest one whose peak
    tool speed ``max |g'(σ)|·σ'(τ)/T`` does not exceed ``speed`` (m/s); it is
    rounded UP to a whole number of periods.
    """
    if speed is not None:
        tau = np.linspace(0.0, 1.0, 4001)
        sig, dsig = min_jerk(tau)
        h = 1e-6
        dg = np.linalg.norm(curve(np.clip(sig + h, 0, 1)) - curve(np.clip(sig - h, 0, 1)), axis=1) / (
            np.clip(sig + h, 0, 1) - np.clip(sig - h, 0, 1)
        )
        duration = float(np.max(dg * dsig)) / speed * (1 + 1e-3)  # margin for the grid
    assert duration is not None, "give speed or duration"
    if not duration > 0:
        raise TrajectoryError("a segment has zero length or duration")
    steps = max(1, math.ceil(duration / dt - 1e-9))
    sig, _ = min_jerk(np.arange(steps + 1) / steps)
    return curve(sig)


def _concatenate(segments: Sequence[np.ndarray]) -> np.ndarray:
    """Join position segments that share their end points (the duplicate is dropped)."""
    out = [segments[0]]
    for seg in segments[1:]:
        if np.linalg.norm(seg[0] - out[-1][-1]) > 1e-12:
            raise TrajectoryError("internal: segments are not continuous")
        out.append(seg[1:])
    return np.concatenate(out)


def _constant_orientation(positions: np.ndarray, rotation: np.ndarray, dt: float) -> Trajectory:
    quat = np.tile(Rotation.from_matrix(rotation).as_quat(), (len(positions), 1))
    return Trajectory(np.arange(len(positions)) * dt, positions, quat)


def _pose_of(pose_or_center, orientation) -> tuple[np.ndarray, np.ndarray]:
    """``(p (3,), R (3, 3))`` from an SE3, or from a point and an orientation
    (3×3 rotation matrix or quaternion ``qx, qy, qz, qw``)."""
    if isinstance(pose_or_center, pin.SE3):
        if orientation is not None:
            raise TrajectoryError("give the orientation either in the SE3 pose or as orientation=, not both")
        return pose_or_center.translation.copy(), pose_or_center.rotation.copy()
    p = np.asarray(pose_or_center, dtype=float)
    if p.shape != (3,) or not np.isfinite(p).all():
        raise TrajectoryError(f"centre must be a finite 3-vector (m) or a pinocchio.SE3, got {p}")
    if orientation is None:
        raise TrajectoryError(
            "orientation is required when the centre is a point "
            "(3x3 rotation matrix, quaternion qx,qy,qz,qw, or pass a pinocchio.SE3)"
        )
    o = np.asarray(orientation, dtype=float)
    if o.shape == (4,) and abs(np.linalg.norm(o) - 1) <= QUATERNION_NORM_TOLERANCE:
        return p, Rotation.from_quat(o).as_matrix()
    if o.shape == (3, 3) and np.allclose(o @ o.T, np.eye(3), atol=1e-6) and np.linalg.det(o) > 0:
        return p, o.copy()
    raise TrajectoryError(f"orientation must be a rotation matrix or a unit quaternion, got {o.tolist()}")


def _check_positive(**values: float | None) -> None:
    for name, v in values.items():
        if v is not None and not (math.isfinite(v) and v > 0):
            raise TrajectoryError(f"{name} must be positive and finite, got {v}")


LEMNISCATE_PLANES = {"xy": (0, 1), "xz": (0, 2), "yz": (1, 2)}


def lemniscate(sigma: np.ndarray, half_width: float) -> np.ndarray:
    """Lemniscate of Bernoulli in its plane, (M, 2), starting and ending at the centre.

    ``θ = π/2 + 2πσ``; ``u = a cos θ / (1 + sin²θ)``, ``v = a sin θ cos θ / (1 + sin²θ)``
    with ``a`` = ``half_width`` (tips at ``u = ±a``, height ``±a/(2√2)``).
    """
    th = np.pi / 2 + 2 * np.pi * np.asarray(sigma)
    den = 1 + np.sin(th) ** 2
    return half_width * np.column_stack([np.cos(th) / den, np.sin(th) * np.cos(th) / den])


PARABOLA_AXES = (np.array([1.0, 1.0, 0.0]) / np.sqrt(2), np.array([-1.0, 1.0, 2.0]) / np.sqrt(6))
"""Orthonormal axes (e1, e2) of the tilted plane holding the guidance parabola."""


def parabola(sigma: np.ndarray, half_width: float) -> np.ndarray:
    """Out-and-back parabola in the tilted plane of :data:`PARABOLA_AXES`, (M, 3).

    ``p = a·u·e1 + a·u²·e2`` with ``u = sin(2πσ)``: vertex (centre) → one end →
    back through the centre → the other end → centre; ``a`` = ``half_width``.
    """
    u = np.sin(2 * np.pi * np.asarray(sigma))[:, None]
    e1, e2 = PARABOLA_AXES
    return half_width * (u * e1 + u**2 * e2)


def guidance_curves(c: np.ndarray, half_width: float) -> list[Callable[[np.ndarray], np.ndarray]]:
    """The four curves ``g(σ)`` (σ ∈ [0, 1] → (M, 3) m, world) of the guidance path around the point ``c``:
    lemniscates in the x-y, x-z and y-z planes, then the tilted parabola; each starts and ends at ``c``."""

    def in_plane(axes):
        def curve(s):
            out = np.tile(c, (len(np.atleast_1d(s)), 1))
            out[:, list(axes)] += lemniscate(np.atleast_1d(s), half_width)
            return out

        return curve

    curves = [in_plane(LEMNISCATE_PLANES[k]) for k in ("xy", "xz", "yz")]
    curves.append(lambda s: c + parabola(np.atleast_1d(s), half_width))
    return curves


def guidance_path(center, size: float = 0.10, speed: float = 0.05, orientation=None, dt: float = 0.01) -> Trajectory:
    """The elbow paper's guidance path ([E] Fig. 4), constant tool orientation.

    Four segments, each starting and ending at ``center`` (m, world) at rest: a
    lemniscate of Bernoulli in the x-y plane, then in x-z, then in y-z
    (:func:`lemniscate`, tip-to-tip width ``size``), then an out-and-back
    parabola in a plane tilted across x, y and z (:func:`parabola`, width
    ``size``).  Each segment uses the minimum-jerk time scaling, so velocity
    and acceleration are continuous (zero at the centre between segments) and
    jerk is bounded; its duration makes the peak tool speed ``speed`` (m/s).
    ``center`` may be a ``pinocchio.SE3`` (its rotation is the orientation);
    otherwise ``orientation`` (rotation matrix or quaternion) is required.
    """
    _check_positive(size=size, speed=speed, dt=dt)
    c, rot = _pose_of(center, orientation)
    curves = guidance_curves(c, size / 2)
    return _constant_orientation(_concatenate([_segment(g, dt, speed=speed) for g in curves]), rot, dt)


def point_to_point(
    targets,
    *,
    peak_speed: float | None = None,
    duration_per_move: float | None = None,
    dwell: float = 0.5,
    lift: float = 0.03,
    orientation=None,
    dt: float = 0.01,
) -> Trajectory:
    """Point-to-point tool moves between ``targets`` ((K, 3) m, world), as in [M] §V-B.

    The paper's subjects touched six targets in turn; it notes that such
    contact-to-contact moves have a parabolic shape in the vertical plane
    through consecutive points.  Each move here follows
    ``g(σ) = A + σ(B − A) + 4·lift·σ(1 − σ)·ẑ`` (a parabola rising ``lift`` m
    above the chord at mid-way, world z up; ``lift=0``: straight line) with the
    minimum-jerk time scaling (the bell-shaped speed profile of human reaching
    moves).  Give exactly one of ``peak_speed`` (m/s, per move) or
    ``duration_per_move`` (s).  The tool stays still ``dwell`` s at every
    intermediate target.  ``targets[0]`` may be a ``pinocchio.SE3`` giving the
    constant orientation; otherwise ``orientation`` is required.
    """
    if (peak_speed is None) == (duration_per_move is None):
        raise TrajectoryError("give exactly one of peak_speed and duration_per_move")
    _check_positive(peak_speed=peak_speed, duration_per_move=duration_per_move, dt=dt)
    if not (math.isfinite(dwell) and dwell >= 0 and math.isfinite(lift)):
        raise TrajectoryError(f"dwell must be >= 0 and lift finite, got dwell={dwell}, lift={lift}")
    first = targets[0] if len(targets) else None
    _, rot = _pose_of(first, orientation) if first is not None else (None, None)
    pts = np.array([t.translation if isinstance(t, pin.SE3) else t for t in targets], dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 2 or not np.isfinite(pts).all():
        raise TrajectoryError(f"targets must be at least 2 finite points of shape (K, 3), got shape {pts.shape}")
    up = np.array([0.0, 0.0, 1.0])
    segments = []
    for k, (a, b) in enumerate(zip(pts[:-1], pts[1:])):
        if lift == 0 and np.linalg.norm(b - a) < 1e-9:
            raise TrajectoryError(f"targets {k + 1} and {k + 2} coincide (1-based)")
        curve = (lambda a, b: lambda s: a + np.outer(s, b - a) + np.outer(4 * lift * s * (1 - s), up))(a, b)
        segments.append(_segment(curve, dt, speed=peak_speed, duration=duration_per_move))
        if dwell > 0 and k < len(pts) - 2:
            segments.append(np.tile(b, (max(1, round(dwell / dt)) + 1, 1)))
    assert rot is not None  # targets has two points or more here, so a first one
    return _constant_orientation(_concatenate(segments), rot, dt)


def hold(pose_or_center, duration: float, orientation=None, dt: float = 0.01) -> Trajectory:
    """The tool held still at a pose for ``duration`` s (samples every ``dt`` s)."""
    _check_positive(duration=duration, dt=dt)
    p, rot = _pose_of(pose_or_center, orientation)
    n = max(1, round(duration / dt)) + 1
    return _constant_orientation(np.tile(p, (n, 1)), rot, dt)
