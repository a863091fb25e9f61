"""The control tick's constants as one named record (docs/method.md §7): what the tick's Numba kernels
(:mod:`qpnso.control.tick`, :mod:`qpnso.control.memory`) read by field, built once per controller
from its :class:`~qpnso.control.config.ControllerConfig` and robot (:func:`tick_params`), the S-R-S
geometry of the continuity interval's closed form among them (:mod:`qpnso.elbow.closed_form`)."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from qpnso.control.rows import RowKind
from qpnso.control.rows.braking import BRAKING_SHARE
from qpnso.control.state import prediction_tolerance
from qpnso.elbow.arm_angle import ELBOW_OFFSET_MIN_M, WRIST_CONE_DEG
from qpnso.elbow.clearance import KeepOut, keep_out_dtype, keep_out_record
from qpnso.elbow.closed_form import srs_dtype
from qpnso.elbow.intervals import closed_form_applies
from qpnso.elbow.srs import srs_geometry
from qpnso.errors import ConfigError
from qpnso.model.collision import LinkCapsules
from qpnso.model.robot import Robot
from qpnso.records import new_record

TOOL_MOVED_TOL = 1e-6
"""m (position) and unitless (rotation-matrix entries ≈ rad): a tool pose change below this keeps the
cached continuity interval (its ends move by ~1e-6 rad at most, against a safety margin of degrees)."""

Q_CHECK_WIDENING = 1e-9
"""rad: a joint this close outside its limit is taken as within it (round-off of a clipped reading)."""

_SCALARS = (
    # level 1 and the joint bounds
    "pose_gain",  # K_p (1/s)
    "pose_correction_speed",  # m/s: the largest speed of the tool point's return to its reference
    "pose_correction_angular_speed",  # rad/s: the same for its orientation
    "half_dt",  # s: ½dt of level 1's second-order term
    "joint_limit_gain",  # γ (1/s) of the joint-limit velocity damper
    "recovery_speed",  # rad/s: the largest speed of a joint or the elbow back inside its limits
    # the qp strategy's level 2
    "cost_gain",  # k of the cost step k∇c
    "nullspace_speed_max",  # rad/s: the cost step's null-space part at most this
    "cost_filter_alpha",  # per-tick factor of the cost step's low-pass (0: none)
    "elbow_gain",  # ξ (1/s) of the elbow rows' velocity damper
    "slack_weight",  # ρ of the elbow rows' slack
    # the command
    "dt",  # s
    "joint_damping",  # D (N·m·s/rad)
    "nullspace_damping_margin",  # μ: the null-space damping at most μ·m/dt (control.selfmotion)
    "friction_compensation",  # the fraction of the self-motion's modelled friction compensated (0: none)
    # the elbow [E 5], [E 6], [E 10], [E 11]
    "rom_half_width",  # Δns (rad)
    "safety_margin",  # d_sg (rad)
    "stiffness_min",  # K_min (N·m/rad)
    "stiffness_max",  # K_max (N·m/rad)
    "stiffness_slope",  # α (1/rad)
    "stiffness_inflection",  # d (rad)
    "wrist_sin_min",  # the arm angle is singular with the wrist's sine to the vertical below this
    "elbow_offset_min",  # m: or the elbow this close to the shoulder–wrist line
    "interval_period",  # ticks between continuity-interval updates while the tool moves
    "closed_form_interval",  # 1: the tick renews the continuity interval itself (srs, closed form); 0: Python does
    "tool_moved_tol",  # TOOL_MOVED_TOL
    "prediction_tolerance",  # rad/s: a solved q̇ this far from the predicted one is solved again (state.py)
    "tool_speed_accepted",  # m/s: a faster tool twist is refused (tick.twist_status)
    "tool_angular_speed_accepted",  # rad/s
)
_VECTORS = (
    "q_check_lo",  # rad: q_min − Q_CHECK_WIDENING; below, Q_OUT_OF_LIMITS
    "q_check_hi",  # rad
    "q_accept_lo",  # rad: q_min − q_limit_tolerance; below, the tick refuses q
    "q_accept_hi",  # rad
    "q_min",  # rad
    "q_max",  # rad
    "dq_max",  # rad/s
    "ddq_max",  # rad/s²: a command's change per tick at most ddq_max·dt (0: none; rows.joint_limits)
    "tau_limit",  # N·m; 0: none given
    "friction_tau_max",  # N·m: the friction model's sliding torque [M 23] (robot.friction)
    "friction_beta",  # s/rad: the compensation's slope, 1/friction_compensation_speed (or the model's β)
)


TOOL_BRAKING_LEVER = 0.2
"""m: the lever from the joints to the tool point taken for the tool's linear braking (``tool_braking``): the
joints' acceleration bound times this, halved, is the linear deceleration the pose correction counts on (an
assumption: about the wrist-to-tool distance; a longer lever can decelerate faster)."""


def tool_braking(ddq_max: np.ndarray) -> np.ndarray:
    """``(linear m/s², angular rad/s²)``: the deceleration the pose correction counts on
    (:func:`qpnso.control.tick.pose_correction`), :data:`~qpnso.control.rows.braking.BRAKING_SHARE` of the slowest
    joint's acceleration bound (the rest left to the self-motion and the twist), times
    :data:`TOOL_BRAKING_LEVER` for the linear part; 0 (no braking) when a joint has no bound."""
    slowest = BRAKING_SHARE * float(np.min(ddq_max)) if np.all(ddq_max > 0) else 0.0
    return np.array([slowest * TOOL_BRAKING_LEVER, slowest])


def compensation_slope(robot: Robot, config) -> np.ndarray:
    """``β`` (s/rad, per joint) of the self-motion's friction compensation, ``τ_max·(2/π)·atan(β·v)`` [M 23]:
    ``1/config.friction_compensation_speed``, or the robot's friction model's own ``β`` when that is None."""
    speed = config.friction_compensation_speed
    return robot.friction.beta.copy() if speed is None else np.full(robot.nq, 1.0 / speed)


def params_dtype(n: int, rows: int = 0, points: int = 0, capsules: int = 0, obstacles: int = 0) -> np.dtype:
    """The record type of :func:`tick_params` for ``n`` joints, ``rows`` rows of row kinds, the collision
    capsules' ``points`` chain points and ``capsules``, and room for ``obstacles`` keep-out volumes."""
    m = max(rows, 1)
    row_fields = [(name, np.float64, m) for name in ("row_lo", "row_hi", "row_gain", "row_soft")]
    return np.dtype(
        [(name, np.float64) for name in _SCALARS]
        + [(name, np.float64, n) for name in _VECTORS]
        + row_fields
        + [("n_rows", np.int64), ("srs", srs_dtype()), ("tool_braking", np.float64, 2)]
        + [("geo", keep_out_dtype(points, capsules, obstacles))]
    )


def tick_params(
    robot: Robot,
    config,
    rows: Sequence[RowKind] = (),
    room: int = 0,
    capsules: LinkCapsules | None = None,
    obstacle_room: int = 0,
) -> np.ndarray:
    """The tick's constants for ``robot`` under ``config`` (a :class:`~qpnso.control.config.ControllerConfig`)
    with the row kinds ``rows`` (their bounds, gains, hard or soft; :mod:`qpnso.control.rows`; room for
    ``room`` rows), the arm's collision ``capsules`` and room for ``obstacle_room`` keep-out volumes (the
    config's obstacles in it), as a 1-element record array (the form Numba reads cheaply)."""
    from qpnso.control.strategies import filter_alpha

    cfg, ec = config, config.elbow()
    closed_form = closed_form_applies(robot)
    tolerance = math.radians(cfg.q_limit_tolerance_deg)
    limit = np.array(robot.tau_limit, dtype=float)
    values = dict(
        pose_gain=cfg.pose_gain,
        pose_correction_speed=cfg.pose_correction_speed,
        pose_correction_angular_speed=cfg.pose_correction_angular_speed,
        half_dt=0.5 * cfg.dt,
        joint_limit_gain=cfg.joint_limit_gain,
        recovery_speed=cfg.recovery_speed,
        cost_gain=cfg.cost_gain,
        nullspace_speed_max=cfg.nullspace_speed_max,
        cost_filter_alpha=filter_alpha(cfg.cost_filter_time, cfg.dt),
        elbow_gain=cfg.elbow_gain,
        slack_weight=cfg.slack_weight,
        dt=cfg.dt,
        joint_damping=cfg.joint_damping,
        nullspace_damping_margin=cfg.nullspace_damping_margin,
        friction_compensation=cfg.friction_compensation,
        rom_half_width=ec.half_width_rad,
        safety_margin=ec.safety_margin_rad,
        stiffness_min=ec.stiffness_min,
        stiffness_max=ec.stiffness_max,
        stiffness_slope=ec.alpha_per_rad,
        stiffness_inflection=ec.d_rad,
        wrist_sin_min=float(np.sin(np.radians(WRIST_CONE_DEG))),
        elbow_offset_min=ELBOW_OFFSET_MIN_M,
        interval_period=cfg.interval_period,
        tool_moved_tol=TOOL_MOVED_TOL,
        prediction_tolerance=prediction_tolerance(cfg.dt),
        tool_speed_accepted=cfg.tool_speed_accepted,
        tool_angular_speed_accepted=cfg.tool_angular_speed_accepted,
        q_check_lo=robot.q_min - Q_CHECK_WIDENING,
        q_check_hi=robot.q_max + Q_CHECK_WIDENING,
        q_accept_lo=robot.q_min - tolerance,
        q_accept_hi=robot.q_max + tolerance,
        q_min=robot.q_min,
        q_max=robot.q_max,
        dq_max=robot.dq_max,
        ddq_max=acceleration_limits(robot, cfg),
        tau_limit=np.where(np.isfinite(limit) & (limit > 0), limit, 0.0),
        friction_tau_max=robot.friction.tau_max,
        friction_beta=compensation_slope(robot, cfg),
    )
    bounds = [kind.bounds(robot) for kind in rows]
    sizes = [np.size(lo) for lo, _ in bounds]
    if rows:
        values.update(
            row_lo=np.concatenate([np.ravel(lo) for lo, _ in bounds]),
            row_hi=np.concatenate([np.ravel(hi) for _, hi in bounds]),
            row_gain=np.repeat([kind.gain for kind in rows], sizes),
            row_soft=np.repeat([float(kind.soft) for kind in rows], sizes),
            n_rows=sum(sizes),
        )
    points, count = (capsules.points_count, capsules.count) if capsules else (0, 0)
    params = new_record(params_dtype(robot.nq, max(room, sum(sizes)), points, count, obstacle_room))
    for name, value in values.items():
        field = params[name][0]
        if name.startswith("row_"):
            field[: np.size(value)] = value  # (the rows first; the room after them unused)
        else:
            params[name] = value
    params["tool_braking"] = tool_braking(np.asarray(values["ddq_max"]))
    if closed_form:
        params["srs"] = srs_geometry(robot).record  # the arm's geometry for the tick's interval kernel
    if capsules is not None:
        params["geo"] = keep_out_record(robot, capsules, obstacle_room, cfg.obstacles, KeepOut.of(cfg))
    params["closed_form_interval"] = interval_in_tick(robot, params)
    return params


def acceleration_limits(robot: Robot, config) -> np.ndarray:
    """The joint acceleration bounds (rad/s²) of ``config.ddq_max`` (one for all joints or one per joint), or
    the robot's own (:attr:`~qpnso.model.robot.Robot.ddq_max`) when it is None; :class:`ConfigError` when
    the count is not the robot's."""
    if config.ddq_max is None:
        return np.array(robot.ddq_max, dtype=float)
    values = np.atleast_1d(np.asarray(config.ddq_max, dtype=float))
    if values.size == 1:
        return np.full(robot.nq, values[0])
    if values.shape != (robot.nq,):
        raise ConfigError(
            f"ddq_max: {values.size} values for {robot.name}'s {robot.nq} joints; give one, or one per joint (rad/s²)"
        )
    return values


def interval_in_tick(robot: Robot, params: np.ndarray) -> float:
    """1.0 when the tick renews the continuity interval itself: the arm has the closed form
    (:func:`~qpnso.elbow.intervals.closed_form_applies`) and, with obstacles in its keep-out record, its links
    turn rigidly with the arm angle (``geo.arcs``: the closed-form cut); else 0.0 (the controller walks it
    numerically, obstacles and all).  Set again when the obstacles change."""
    g = params["geo"][0]
    rigid = g["arcs"] != 0.0 or g["n_obstacles"] == 0
    return float(closed_form_applies(robot) and rigid)
