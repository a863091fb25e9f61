"""Figures (matplotlib, optional: ``pip install 'qpnso[plot]'``)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from qpnso.elbow.arm_angle import arm_angle
from qpnso.elbow.intervals import continuity_interval, feasible_intervals
from qpnso.elbow.rom import ElbowConfig, clip_rom
from qpnso.elbow.srs import branch, self_motion
from qpnso.errors import InputError
from qpnso.model.collision import clearances, geometry_model
from qpnso.model.obstacles import Obstacle
from qpnso.model.robot import Robot


def _pyplot():
    try:
        import matplotlib
    except ImportError:
        raise ImportError("plotting needs matplotlib: pip install 'qpnso[plot]'") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _shade(ax, arcs, color: str, alpha: float) -> None:
    """Shade arcs (rad, possibly crossing ±π) on an axis in degrees over [-180, 180]."""
    for lo, hi in arcs:
        for shift in (-2 * math.pi, 0.0, 2 * math.pi):
            a, b = max(lo + shift, -math.pi), min(hi + shift, math.pi)
            if a < b:
                ax.axvspan(math.degrees(a), math.degrees(b), color=color, alpha=alpha, lw=0)


def _clearance_panel(
    ax, robot: Robot, grid: np.ndarray, joints: np.ndarray, obstacles: Sequence[Obstacle], margin: float
) -> None:
    """Each link capsule's clearance (m: its least distance to an obstacle, coal through
    :func:`qpnso.model.collision.clearances`, independent of the interval's own kernels) against the arm angle
    ``grid`` (rad, drawn in degrees) at the self-motion's ``joints`` (rad), and the margin (m)."""
    geom = geometry_model(robot)
    least = np.array([clearances(robot, q, obstacles, geom).min(axis=1) for q in joints])
    for k, obj in enumerate(geom.geometryObjects):
        ax.plot(np.degrees(grid), least[:, k], lw=1.0, label=obj.name)
    ax.axhline(margin, color="tab:red", ls="--", lw=0.8, label=f"margin {margin:g} m")
    ax.set_ylabel("clearance (m)")
    ax.legend(fontsize=6, loc="upper right", ncol=2)


def plot_intervals(
    robot: Robot,
    q: object,
    rom: ElbowConfig | None = None,
    out: str | Path = "intervals.png",
    samples: int = 1441,
    obstacles: Sequence[Obstacle] = (),
    margin: float = 0.03,
) -> Path:
    """Every joint versus the arm angle for the tool pose of ``q`` (S-R-S closed form).

    One panel per joint (deg versus deg): the joint curve, its limits, the arcs
    where that joint is within its limits (light green), Ψ (all joints, green
    band in every panel), the continuity interval (blue outline), the current
    arm angle (black line) and, if ``rom`` is given, ROM_t (orange band;
    ``ns0`` is the current arm angle).  With ``obstacles`` Ψ and the continuity interval also keep every link
    capsule ``margin`` (m) from them (:func:`qpnso.elbow.intervals.feasible_intervals`), and a last panel draws
    each capsule's clearance (m) with the margin and the interval shaded (blue).  Writes a PNG and returns its
    path.
    """
    plt = _pyplot()
    qv = robot.check_q(q)
    pose, b, ns = robot.tool_pose(qv), branch(robot, qv), arm_angle(robot, qv)
    if samples < 10:
        raise InputError(f"samples must be >= 10, got {samples}")
    grid = np.linspace(-math.pi, math.pi, samples)
    joints = self_motion(robot, pose, b).joints(grid)
    psi, per_joint = feasible_intervals(robot, pose, b, per_joint=True, obstacles=obstacles, margin=margin)
    interval = continuity_interval(robot, qv, obstacles=obstacles, margin=margin)
    panels = robot.nq + (1 if obstacles else 0)
    fig, axes = plt.subplots(panels, 1, figsize=(8, 1.6 * panels + 1), sharex=True)
    if obstacles:
        _clearance_panel(axes[-1], robot, grid, joints, obstacles, margin)
        _shade(axes[-1], [(interval.lo, interval.hi)], "tab:blue", 0.15)
        axes[-1].axvline(math.degrees(ns), color="black", lw=1.0)
        axes[-1].grid(alpha=0.3)
    for k, ax in enumerate(axes[: robot.nq]):
        curve = np.degrees(joints[:, k])
        curve[1:][np.abs(np.diff(curve)) > 90] = np.nan  # do not draw the ±180° wrap as a line
        _shade(ax, per_joint[k], "tab:green", 0.12)
        _shade(ax, psi, "tab:green", 0.25)
        if rom is not None:
            rt = clip_rom(ns, rom.half_width_rad, interval, rom.safety_margin_rad)
            if not rt.empty:
                _shade(ax, [(rt.lo, rt.hi)], "tab:orange", 0.35)
        ax.plot(np.degrees(grid), curve, color="tab:blue", lw=1.2)
        for lim in (robot.q_min[k], robot.q_max[k]):
            ax.axhline(math.degrees(lim), color="tab:red", ls="--", lw=0.8)
        ax.axvline(math.degrees(ns), color="black", lw=1.0)
        ax.plot(math.degrees(ns), math.degrees(qv[k]), "ko", ms=4)
        if not interval.full_circle:
            for end in (interval.lo, interval.hi):
                ax.axvline(math.degrees((end + math.pi) % (2 * math.pi) - math.pi), color="tab:blue", ls=":", lw=1.0)
        ax.set_ylabel(f"q{k + 1} (deg)")
        ax.set_ylim(-185, 185)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("arm angle ns (deg)")
    axes[-1].set_xlim(-180, 180)
    width = (
        "full circle"
        if interval.full_circle
        else f"[{math.degrees(interval.lo):.1f}, {math.degrees(interval.hi):.1f}] deg"
    )
    keep_out = f", {len(obstacles)} obstacle(s), margin {margin:g} m" if obstacles else ""
    axes[0].set_title(
        f"{robot.name}: joints vs arm angle, branch {b.as_tuple()}, ns = {math.degrees(ns):.1f} deg, "
        f"interval {width}{keep_out}\n(green: Ψ, light green: joint within limits, orange: ROM_t, red: limits)",
        fontsize=9,
    )
    fig.tight_layout()
    path = Path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _save(fig, out: str | Path) -> Path:
    """Write a figure atomically (temporary file, then rename) and close it."""
    from qpnso.control.offline import atomic_write

    path = Path(out)
    atomic_write(path, lambda f: fig.savefig(f, dpi=110, format="png"))
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path


def _run_panels(axes, arrays, label: str = "", color: str | None = None, bounds: bool = True) -> None:
    """Arm angle with ROM_t and interval, stiffness, felt mass and friction over time."""
    t = np.asarray(arrays["t"])
    deg = np.degrees
    ax = axes[0]
    ax.plot(t, deg(arrays["ns"]), color=color or "black", lw=1.2, label=f"ns {label}".strip())
    if bounds:
        ax.plot(t, deg(arrays["rom_lo"]), color="tab:blue", ls=":", lw=1.0, label="ROM_t")
        ax.plot(t, deg(arrays["rom_hi"]), color="tab:blue", ls=":", lw=1.0)
        ax.plot(t, deg(arrays["interval_lo"]), color="tab:red", lw=1.0, label="continuity interval")
        ax.plot(t, deg(arrays["interval_hi"]), color="tab:red", lw=1.0)
    ax.set_ylabel("arm angle (deg)")
    axes[1].plot(t, arrays["stiffness"], color=color or "tab:purple", lw=1.0, label=label or None)
    axes[1].set_ylabel("K (N·m/rad)")
    for ax, key, unit in ((axes[2], "mass", "kg"), (axes[3], "friction_force", "N")):
        v = np.asarray(arrays[key], dtype=float)
        ok = np.isfinite(v)
        ax.plot(t[ok], v[ok], color=color or "tab:green", lw=1.0, label=label or None)
        ax.set_ylabel(f"{key.replace('_', ' ')} ({unit})")
    for ax in axes:
        ax.grid(alpha=0.3)


def plot_run(arrays, out: str | Path = "run.png", title: str = "") -> Path:
    """A run over time (like the elbow paper's Fig. 3): the arm angle with ROM_t
    and the continuity bounds, the elbow stiffness, the felt mass and friction
    force, and the 3-D tool path (reference dashed).  Writes a PNG."""
    plt = _pyplot()
    fig = plt.figure(figsize=(11, 8))
    grid = fig.add_gridspec(4, 2, width_ratios=[1.6, 1])
    axes = [fig.add_subplot(grid[k, 0]) for k in range(4)]
    _run_panels(axes, arrays)
    axes[0].legend(fontsize=7, loc="best")
    axes[-1].set_xlabel("t (s)")
    ax3 = fig.add_subplot(grid[:, 1], projection="3d")
    p = np.asarray(arrays["tool_position"])
    ax3.plot(p[:, 0], p[:, 1], p[:, 2], color="black", lw=1.0, label="tool")
    if "ref_position" in arrays:
        r = np.asarray(arrays["ref_position"])
        ax3.plot(r[:, 0], r[:, 1], r[:, 2], color="tab:orange", ls="--", lw=0.8, label="reference")
    ax3.set_xlabel("x (m)")
    ax3.set_ylabel("y (m)")
    ax3.set_zlabel("z (m)")
    ax3.legend(fontsize=7)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, out)


def plot_comparison(runs: dict, out: str | Path = "comparison.png", title: str = "") -> Path:
    """Several runs (name → arrays) side by side: one column per run, same panels."""
    plt = _pyplot()
    if not runs:
        raise InputError("plot_comparison needs at least one run")
    fig, axes = plt.subplots(4, len(runs), figsize=(4 * len(runs) + 1, 8), sharex="col", sharey="row", squeeze=False)
    for col, (name, arrays) in enumerate(runs.items()):
        _run_panels(axes[:, col], arrays)
        axes[0, col].set_title(name, fontsize=10)
        axes[-1, col].set_xlabel("t (s)")
    axes[0, 0].legend(fontsize=7, loc="best")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, out)
