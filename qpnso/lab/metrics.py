"""Run metrics of the papers (docs/method.md §9), pure NumPy, robot-independent.

Angles in rad unless a name ends in ``_deg``; positions in m (world frame);
times in s; forces in N.  Every function checks its input and raises
:class:`~qpnso.errors.InputError` naming the bad argument.
"""

from __future__ import annotations

import math
from typing import Collection, Mapping, Sequence

import numpy as np

from qpnso.errors import InputError


def _array(x, name: str, ndim: int, width: int | None = None, min_len: int = 1, allow_inf: bool = False) -> np.ndarray:
    try:
        a = np.asarray(x, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{name} is not numeric") from None
    if a.ndim != ndim or (width is not None and a.shape[1] != width):
        want = "(N,)" if ndim == 1 else f"(N, {width if width is not None else 'k'})"
        raise InputError(f"{name} must have shape {want}, got {a.shape}")
    if len(a) < min_len:
        raise InputError(f"{name} needs at least {min_len} samples, got {len(a)}")
    ok = ~np.isnan(a) if allow_inf else np.isfinite(a)
    if not ok.all():
        raise InputError(
            f"{name} contains NaN{'' if allow_inf else ' or inf'} (first at index {np.argwhere(~ok)[0][0]})"
        )
    return a


def _same_length(**arrays: np.ndarray) -> None:
    lengths = {k: len(v) for k, v in arrays.items() if np.ndim(v) > 0}
    if len(set(lengths.values())) > 1:
        raise InputError(f"arrays have different lengths: {lengths}")


def elbow_mobility(ns) -> float:
    """Elbow mobility Δ = max_t ns − min_t ns [E 12] (rad).

    ``ns`` (N,) is the arm angle per tick (rad); it is unwrapped first
    (``np.unwrap``) since the arm angle is continuous along a run.
    """
    a = np.unwrap(_array(ns, "ns", 1))
    return float(a.max() - a.min())


def constraint_proximity(ns, lo, hi) -> float:
    """Constraint proximity Δc = min_t min(ns − lo, hi − ns) [E 13] (rad).

    ``ns`` (N,) arm angle per tick, ``lo``/``hi`` (N,) or scalars: the
    continuity interval bounds per tick (may be ±inf when no joint limit
    restricts the elbow), in the same branch of angles as ``ns``.  Negative
    when ``ns`` left the interval.
    """
    a = _array(ns, "ns", 1)
    lo, hi = (
        _array(np.broadcast_to(np.asarray(b, dtype=float), a.shape) if np.ndim(b) == 0 else b, name, 1, allow_inf=True)
        for b, name in ((lo, "lo"), (hi, "hi"))
    )
    _same_length(ns=a, lo=lo, hi=hi)
    return float(np.min(np.minimum(a - lo, hi - a)))


def path_length(p) -> float:
    """Length (m) of the polyline through the positions ``p`` (N, 3)."""
    a = _array(p, "p", 2, 3)
    return float(np.sum(np.linalg.norm(np.diff(a, axis=0), axis=1)))


def uniform_period(t, rtol: float = 1e-6) -> float:
    """The sample period (s) of ``t`` (N,), which must be uniform within ``rtol``."""
    a = _array(t, "t", 1, min_len=2)
    d = np.diff(a)
    dt = (a[-1] - a[0]) / (len(a) - 1)
    if not dt > 0 or np.max(np.abs(d - dt)) > rtol * dt:
        raise InputError(
            f"t must be uniformly sampled and increasing (period {dt:.6g} s; "
            f"deviation {np.max(np.abs(d - dt)):.3g} s); resample first"
        )
    return float(dt)


def smoothness(t, p) -> float:
    """Root-mean-square integral jerk S = sqrt(T⁵/L² · Σ_i ‖d³p/dt³‖²_i dt) [E 14] (dimensionless).

    ``t`` (N,) s must be UNIFORM (raises InputError otherwise; resample first);
    ``p`` (N, 3) m.  Jerk is the third forward difference divided by dt³ (N−3
    values); ``T = t_end − t_0``; ``L`` = :func:`path_length`.
    """
    dt = uniform_period(t)
    a = _array(p, "p", 2, 3, min_len=4)
    _same_length(t=np.asarray(t), p=a)
    length = path_length(a)
    if not length > 0:
        raise InputError("smoothness is undefined for a path of zero length")
    jerk = np.diff(a, n=3, axis=0) / dt**3
    duration = float(t[-1] - t[0])
    return float(np.sqrt(duration**5 / length**2 * np.sum(jerk**2) * dt))


def low_pass(t, p, cutoff_hz: float) -> np.ndarray:
    """Positions ``p`` (N, k) sampled at the uniform times ``t`` (N,) s, low-passed at ``cutoff_hz`` by a
    2nd-order Butterworth filter run forwards and backwards (zero phase, SciPy's ``sosfiltfilt``)."""
    from scipy import signal

    dt = uniform_period(t)
    a = _array(p, "p", 2)
    if not (math.isfinite(cutoff_hz) and 0 < cutoff_hz < 0.5 / dt):
        raise InputError(f"cutoff_hz must be in (0, {0.5 / dt:g}) Hz for samples every {dt:g} s, got {cutoff_hz}")
    sos = signal.butter(2, cutoff_hz, fs=1.0 / dt, output="sos")
    return signal.sosfiltfilt(sos, a, axis=0)


REST_SPEED = 0.005
"""m/s: the tool speed under which a segment's record ends (its low-passed speed; the surgeon's tremor, 8–12 Hz,
mostly above the smoothness filter's cut-off, keeps a held tool moving by less)."""


def segment_smoothness(t, p, segments: Sequence[tuple[float, float]], cutoff_hz: float) -> dict[str, float]:
    """The smoothness S [E 14] of each segment of a record, on positions low-passed at ``cutoff_hz``
    (:func:`low_pass`).  Segment k's record starts where the intended move starts and ends at rest: the
    first tick after the intended move's end at which the low-passed tool speed is below
    :data:`REST_SPEED` (at the latest where the next segment starts, or the record's end).

    ``t`` (N,) s uniform; ``p`` (N, 3) m; ``segments`` the (t0, t1) s of each intended move.  Keys:
    ``smoothness_segment_<k>`` (k from 1) and ``smoothness`` (their median); none without segments.
    S does not depend on a segment's duration or size; over K equal segments taken at once it grows like K².
    """
    ts = _array(t, "t", 1)
    if not len(segments):
        return {}
    smooth = low_pass(ts, p, cutoff_hz)
    speed = np.concatenate([[0.0], np.linalg.norm(np.diff(smooth, axis=0), axis=1) / np.diff(ts)])
    starts = [float(a) for a, _ in segments] + [float(ts[-1]) + 1.0]
    out: dict[str, float] = {}
    for k, ((a, b), limit) in enumerate(zip(segments, starts[1:])):
        resting = np.flatnonzero((ts >= b) & (ts < limit) & (speed < REST_SPEED))
        end = ts[resting[0]] if resting.size else limit
        window = (ts >= a - 1e-9) & (ts <= end + 1e-9)
        if np.count_nonzero(window) >= 4 and path_length(smooth[window]) > 0:
            out[f"smoothness_segment_{k + 1}"] = smoothness(ts[window], smooth[window])
    values = list(out.values())
    if values:
        out["smoothness"] = float(np.median(values))
    return out


def hand_summary(t, wrench, twist, p, intended_p=None) -> dict[str, float]:
    """What the hand did in a run: ``hand_work_J`` = W = ∫|F·v + M·ω| dt (J), the absolute work of the hand's
    wrench (N, N·m) on the tool's twist (m/s, rad/s), (N, 6) each, world frame, trapezoidal rule; the work per
    metre [M 24] under two readings of the path length: ``user_work_per_metre_N`` = W / L with L the measured
    tool path (``p`` (N, 3) m, :func:`path_length`; a wandering tool lengthens it and lowers the figure), and,
    with ``intended_p`` (N, 3) m, the intended motion's positions at the same times,
    ``intended_path_length_m`` (L₀) and ``user_work_per_nominal_metre_N`` = W / L₀; each NaN when its length
    is 0.  Also ``tool_displacement_max_m``, the tool point's largest distance (m) from where it started, and
    ``orthogonal_torque_mean_Nm``, the mean magnitude of the hand's moment orthogonal to the tool's direction of
    motion over the ticks in which the tool moves faster than 1 mm/s (the mass/friction paper's Fig. 10b; NaN
    when it never does)."""
    ts = _array(t, "t", 1, min_len=2)
    f = _array(wrench, "wrench", 2, 6)
    v = _array(twist, "twist", 2, 6)
    pos = _array(p, "p", 2, 3)
    _same_length(t=ts, wrench=f, twist=v, p=pos)
    speed = np.linalg.norm(v[:, :3], axis=1)
    moving = speed > 1e-3
    u = v[moving, :3] / speed[moving, None]
    m = f[moving, 3:]
    orthogonal = m - np.einsum("ij,ij->i", m, u)[:, None] * u
    work = absolute_work(f, v, ts)
    out = {
        "hand_work_J": work,
        "user_work_per_metre_N": _per_metre(work, path_length(pos)),
        "tool_displacement_max_m": float(np.max(np.linalg.norm(pos - pos[0], axis=1))),
        "orthogonal_torque_mean_Nm": float(np.mean(np.linalg.norm(orthogonal, axis=1))) if moving.any() else math.nan,
    }
    if intended_p is not None:
        nominal = _array(intended_p, "intended_p", 2, 3)
        _same_length(t=ts, intended_p=nominal)
        length = path_length(nominal)
        out.update(intended_path_length_m=length, user_work_per_nominal_metre_N=_per_metre(work, length))
    return out


def _per_metre(work: float, length: float) -> float:
    """``work`` (J) per metre of ``length`` (m); NaN for a length of 0."""
    return work / length if length > 0 else math.nan


def rotation_angles(r_ref, r) -> np.ndarray:
    """Angles (rad, in [0, π]) of ``R_ref R^T`` for stacks of rotations (N, 3, 3)."""
    a = _array(r_ref, "R_ref", 3)
    b = _array(r, "R", 3)
    _same_length(R_ref=a, R=b)
    e = np.einsum("nij,nkj->nik", a, b)
    sin_axis = 0.5 * np.stack([e[:, 2, 1] - e[:, 1, 2], e[:, 0, 2] - e[:, 2, 0], e[:, 1, 0] - e[:, 0, 1]], axis=1)
    cos = 0.5 * (np.trace(e, axis1=1, axis2=2) - 1.0)
    return np.arctan2(np.linalg.norm(sin_axis, axis=1), cos)


def tracking_error(p_ref, p, r_ref=None, r=None) -> dict[str, float]:
    """Tool tracking error: position error norms (m) and, with rotations (N, 3, 3),
    orientation error angles (rad) of ``R_ref Rᵀ``; mean and max of each.

    Keys: ``position_error_mean_m``, ``position_error_max_m`` and, when given,
    ``rotation_error_mean_rad``, ``rotation_error_max_rad``.
    """
    a = _array(p_ref, "p_ref", 2, 3)
    b = _array(p, "p", 2, 3)
    _same_length(p_ref=a, p=b)
    e = np.linalg.norm(a - b, axis=1)
    out = {"position_error_mean_m": float(e.mean()), "position_error_max_m": float(e.max())}
    if (r_ref is None) != (r is None):
        raise InputError("give both r_ref and r, or neither")
    if r_ref is not None:
        ang = rotation_angles(r_ref, r)
        _same_length(p=b, R=ang)
        out.update(rotation_error_mean_rad=float(ang.mean()), rotation_error_max_rad=float(ang.max()))
    return out


def user_work_per_metre(force, velocity, t, p) -> float:
    """Absolute work the hand puts into the tool per metre of path, ∫|F·v| dt / L ([M 24], N = J/m).

    ``force`` (N, 3) N with ``velocity`` (N, 3) m/s, or a wrench (N, 6) [f; τ]
    with a twist (N, 6) [v; ω] (world frame; then the power includes τ·ω);
    ``t`` (N,) s (trapezoidal rule, any spacing); ``p`` (N, 3) m gives L.
    This is the per-trial quantity W/L of [M 24]; :func:`relative_work` applies
    the paper's normalisation across controllers.
    """
    f = _array(force, "force", 2, min_len=2)
    v = _array(velocity, "velocity", 2, min_len=2)
    if f.shape[1] not in (3, 6) or f.shape != v.shape:
        raise InputError(f"force and velocity must both be (N, 3) or (N, 6), got {f.shape} and {v.shape}")
    ts = _array(t, "t", 1, min_len=2)
    if np.any(np.diff(ts) <= 0):
        raise InputError("t must be strictly increasing")
    _same_length(force=f, velocity=v, t=ts, p=np.asarray(p))
    length = path_length(p)
    if not length > 0:
        raise InputError("work per metre is undefined for a path of zero length")
    return absolute_work(f, v, ts) / length


def absolute_work(force: np.ndarray, velocity: np.ndarray, t: np.ndarray) -> float:
    """∫|F·v| dt (J) of checked arrays: a force or wrench (N, k) on a velocity or twist (N, k) over times
    ``t`` (N,) s, trapezoidal rule (the numerator of :func:`user_work_per_metre`)."""
    power = np.abs(np.einsum("ij,ij->i", force, velocity))
    return float(np.sum(0.5 * (power[1:] + power[:-1]) * np.diff(t)))


def relative_work(
    work_per_metre: Mapping[str, np.ndarray], reference: Collection[str] | None = None
) -> dict[str, np.ndarray]:
    """[M 24] normalisation for one subject: each controller's trials (W/L per
    trial) divided by the largest per-controller mean W/L among the controllers ``reference`` (default: all)."""
    arrays = {k: _array(np.atleast_1d(v), f"work_per_metre[{k!r}]", 1) for k, v in work_per_metre.items()}
    means = [float(v.mean()) for k, v in arrays.items() if reference is None or k in reference]
    if not means:
        raise InputError("relative_work needs at least one controller (of the reference)")
    top = max(means)
    if not top > 0:
        raise InputError("the largest mean work per metre is not positive")
    return {k: v / top for k, v in arrays.items()}


def timing_summary(seconds) -> dict[str, float]:
    """Median, 95th, 99th percentile and max of durations given in s, in µs.

    Keys ``median_us``, ``p95_us``, ``p99_us``, ``max_us`` (NumPy's linear
    percentile interpolation).
    """
    a = _array(np.ravel(seconds), "seconds", 1) * 1e6
    p50, p95, p99 = np.percentile(a, [50, 95, 99])
    return {"median_us": float(p50), "p95_us": float(p95), "p99_us": float(p99), "max_us": float(a.max())}


def clearance_summary(
    t, distance, links: Sequence[str], status=None, obstacle_bit: int = 0
) -> dict[str, float | int | str]:
    """The least link–obstacle clearance of a run and how often a link was inside an obstacle.

    ``t`` (N,) s; ``distance`` (N, links, obstacles) m, each link's distance to each obstacle per tick (negative:
    penetration), e.g. coal's (:func:`qpnso.model.collision.clearances`); ``links`` names the links;
    ``status`` (N,) int flags per tick with ``obstacle_bit`` the bit of the controller's obstacle status.

    Keys: ``clearance_min_m`` (least over the run), ``clearance_min_link`` (its link's name),
    ``clearance_min_obstacle`` (its obstacle's index), ``clearance_min_tick`` and ``clearance_min_t_s`` (the
    first tick with it), ``penetration_ticks`` (ticks with a distance < 0) and, with ``status``,
    ``obstacle_ticks`` (ticks whose status has ``obstacle_bit``).
    """
    ts = _array(t, "t", 1)
    d = _array(distance, "distance", 3)
    _same_length(t=ts, distance=d)
    if d.shape[1] != len(links) or d.shape[2] == 0:
        raise InputError(f"distance must be (N, {len(links)} links, obstacles >= 1), got {d.shape}")
    k, link, obstacle = (int(i) for i in np.unravel_index(int(np.argmin(d)), d.shape))
    out: dict[str, float | int | str] = {
        "clearance_min_m": float(d[k, link, obstacle]),
        "clearance_min_link": str(links[link]),
        "clearance_min_obstacle": int(obstacle),
        "clearance_min_tick": int(k),
        "clearance_min_t_s": float(ts[k]),
        "penetration_ticks": int(np.count_nonzero((d < 0).any(axis=(1, 2)))),
    }
    if status is not None:
        s = np.asarray(status).astype(np.int64)
        _same_length(t=ts, status=s)
        out["obstacle_ticks"] = int(np.count_nonzero(s & int(obstacle_bit)))
    return out


def summarize_run(
    arrays: Mapping[str, np.ndarray], status_flags: Mapping[str, int] | None = None, dt: float | None = None
) -> dict[str, float]:
    """Flat dict of the run metrics from per-tick arrays (e.g. ``RunResult.arrays``).

    Uses whichever of these keys are present (names of ``qpnso.control.offline.RESULT_KEYS``
    and of the simulation log): ``t`` (required, s); ``ns``; ``interval_lo``,
    ``interval_hi``; ``rom_lo``, ``rom_hi`` (rad); ``tool_position``,
    ``ref_position`` (N, 3) m; ``tool_position_error`` (m) and
    ``tool_rotation_error`` (rad) per tick; ``status`` (int flags per tick);
    ``tick_time``, ``solve_time`` (s); ``hand_wrench`` and ``tool_twist`` (N, 6).

    Keys returned (when their inputs exist): ``duration_s``, ``ticks``,
    ``elbow_mobility_deg`` [E 12], ``constraint_proximity_deg`` [E 13] (to the
    continuity interval), ``rom_proximity_deg`` (same formula with the ROM;
    negative = outside), ``smoothness`` [E 14] (tool path), ``path_length_m``,
    ``tool_position_error_mean_m``/``_max_m``,
    ``tool_rotation_error_mean_deg``/``_max_deg``, ``status_not_ok_ticks``,
    ``status_not_ok_fraction``, ``status_<NAME>_ticks`` for each entry of
    ``status_flags`` (name → bit value, e.g. ``{f.name: f.value for f in Status}``),
    ``tick_time_{median,p95,p99,max}_us``, ``solve_time_{...}_us``,
    ``slow_ticks`` (ticks whose ``tick_time`` exceeds the control period ``dt``,
    s; without ``dt``, the median spacing of ``t``) and ``tick_time_max_ms``,
    ``user_work_per_metre_N`` [M 24].
    """
    if "t" not in arrays:
        raise InputError("summarize_run needs the per-tick times 't'")
    t = _array(arrays["t"], "t", 1)
    has = lambda *keys: all(k in arrays and arrays[k] is not None and len(arrays[k]) for k in keys)  # noqa: E731
    out: dict[str, float] = {"duration_s": float(t[-1] - t[0]), "ticks": float(len(t))}
    if has("ns"):
        out["elbow_mobility_deg"] = float(np.degrees(elbow_mobility(arrays["ns"])))
        for key, lo, hi in (
            ("constraint_proximity_deg", "interval_lo", "interval_hi"),
            ("rom_proximity_deg", "rom_lo", "rom_hi"),
        ):
            if has(lo, hi):
                out[key] = float(np.degrees(constraint_proximity(arrays["ns"], arrays[lo], arrays[hi])))
    if has("tool_position"):
        out["path_length_m"] = path_length(arrays["tool_position"])
        if len(t) >= 4 and out["path_length_m"] > 0:
            out["smoothness"] = smoothness(t, arrays["tool_position"])
    if has("tool_position_error"):
        e = _array(arrays["tool_position_error"], "tool_position_error", 1)
        out.update(tool_position_error_mean_m=float(e.mean()), tool_position_error_max_m=float(e.max()))
    elif has("tool_position", "ref_position"):
        err = tracking_error(arrays["ref_position"], arrays["tool_position"])
        out.update(
            tool_position_error_mean_m=err["position_error_mean_m"],
            tool_position_error_max_m=err["position_error_max_m"],
        )
    if has("tool_rotation_error"):
        e = np.degrees(_array(arrays["tool_rotation_error"], "tool_rotation_error", 1))
        out.update(tool_rotation_error_mean_deg=float(e.mean()), tool_rotation_error_max_deg=float(e.max()))
    if has("status"):
        s = np.asarray(arrays["status"]).astype(np.int64)
        out["status_not_ok_ticks"] = float(np.count_nonzero(s))
        out["status_not_ok_fraction"] = float(np.count_nonzero(s) / len(s))
        for name, bit in (status_flags or {}).items():
            if int(bit):
                out[f"status_{name}_ticks"] = float(np.count_nonzero(s & int(bit)))
    for key in ("tick_time", "solve_time"):
        if has(key):
            out.update({f"{key}_{k}": v for k, v in timing_summary(arrays[key]).items()})
    if has("tick_time"):
        period = float(dt) if dt is not None else (float(np.median(np.diff(t))) if len(t) >= 2 else None)
        if period is not None:
            if not (np.isfinite(period) and period > 0):
                raise InputError(f"dt must be a positive number of seconds, got {period}")
            ticks = np.ravel(np.asarray(arrays["tick_time"], dtype=float))
            out["slow_ticks"] = float(np.count_nonzero(ticks > period))
        out["tick_time_max_ms"] = out["tick_time_max_us"] / 1000.0
    if has("hand_wrench", "tool_twist", "tool_position") and out.get("path_length_m", 0) > 0:
        out["user_work_per_metre_N"] = user_work_per_metre(
            arrays["hand_wrench"], arrays["tool_twist"], t, arrays["tool_position"]
        )
    return out
