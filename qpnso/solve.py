"""Offline solve of a whole tool trajectory, tick by tick (the main job).

Level 1 tracks the trajectory's tool motion (twist feed-forward plus pose
correction); level 2 does what the strategy asks.  The joints are integrated
kinematically, ``q ← q + dt·q̇``, as a position-controlled arm would follow.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pinocchio as pin

from qpnso.controller import Controller, ControllerConfig
from qpnso.errors import ConfigError, QpnsoError, UnreachableError
from qpnso.robot import Robot
from qpnso.trajectory import Trajectory

try:  # Python 3.11+
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]


RESULT_KEYS = ("t", "q", "dq", "ns", "rom_lo", "rom_hi", "interval_lo", "interval_hi", "cost", "mass",
               "friction_force", "status", "stiffness", "tool_position", "ref_position",
               "tool_position_error", "tool_rotation_error", "tick_time", "solve_time")


@dataclass
class RunResult:
    """Arrays over ticks of one run (rad, m, s, kg, N; world frame) and its summary."""

    arrays: dict[str, np.ndarray]
    summary: dict[str, float] = field(default_factory=dict)
    messages: list[str] = field(default_factory=list)

    def save(self, path: str | Path) -> Path:
        """Write ``result.npz`` atomically (temporary file, then rename)."""
        return atomic_write(Path(path), lambda f: np.savez_compressed(f, **self.arrays))


def atomic_write(path: Path, write) -> Path:
    """Call ``write(file)`` on a temporary file beside ``path``, then rename it into place."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def config_values(path: str | Path | None, overrides: dict | None = None) -> dict:
    """Controller settings as plain data: a TOML file (top level or ``[controller]``),
    then ``overrides`` (CLI flags; None values are not given)."""
    values: dict = {}
    if path is not None:
        p = Path(path)
        if not p.is_file():
            raise ConfigError(f"config file not found: {p}")
        try:
            values = tomllib.loads(p.read_text())
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{p}: not valid TOML: {exc}") from None
        values = dict(values.get("controller", values))
    values.update({k: v for k, v in (overrides or {}).items() if v is not None})
    return values


def load_config(path: str | Path | None, overrides: dict | None = None) -> ControllerConfig:
    """A :class:`ControllerConfig` from a TOML file, then ``overrides`` (CLI flags)."""
    return ControllerConfig.from_dict(config_values(path, overrides))


def initial_configuration(robot: Robot, pose: pin.SE3, arm_angle: float = 0.0,
                          interval_margin_deg: float = 15.0) -> np.ndarray:
    """A configuration (rad) reaching ``pose`` with the arm angle closest to ``arm_angle``
    (0 = elbow up), joints 2° inside their limits, preferring those at least
    ``interval_margin_deg`` from the ends of their continuity interval (S-R-S arms)."""
    from qpnso.elbow import Branch, ik
    from qpnso.intervals import continuity_interval

    candidates = []
    offsets = np.radians(np.arange(0, 181, 5))
    for signs in [(1, 1, 1), (1, 1, -1), (-1, 1, 1), (-1, 1, -1), (1, -1, 1), (1, -1, -1), (-1, -1, 1), (-1, -1, -1)]:
        for offset in offsets:
            for ns in (arm_angle + offset, arm_angle - offset):
                try:
                    q = ik(robot, pose, float(np.angle(np.exp(1j * ns))), Branch(*signs))
                except QpnsoError:
                    continue
                if np.min(np.minimum(q - robot.q_min, robot.q_max - q)) > np.radians(2):
                    candidates.append((float(offset), q))
    if not candidates:
        raise UnreachableError("no configuration inside the joint limits reaches the first pose of the trajectory")
    candidates.sort(key=lambda c: c[0])
    for _, q in candidates:
        if _interval_room(robot, q, continuity_interval) >= np.radians(interval_margin_deg):
            return q
    return candidates[0][1]


def _interval_room(robot: Robot, q: np.ndarray, continuity_interval) -> float:
    """Distance (rad) of q's arm angle from its continuity interval's nearer end."""
    from qpnso.elbow import arm_angle

    try:
        iv = continuity_interval(robot, q)
        ns = arm_angle(robot, q)
    except QpnsoError:
        return -np.inf
    return np.inf if iv.full_circle else min(ns - iv.lo, iv.hi - ns)


class Recorder:
    """Collects the per-tick arrays of a run (:data:`RESULT_KEYS`, plus extras).

    ``mass`` is the largest principal mass felt at the tool (kg) and
    ``friction_force`` the potential friction force magnitude (N, √c_f), both
    at the measured ``q``; computing them costs about as much as a tick, so a
    run may record them every ``feel_every`` ticks (NaN in between).
    """

    def __init__(self, ctrl: Controller, feel_every: int = 1) -> None:
        self.ctrl = ctrl
        self.feel_every = max(1, int(feel_every))
        self.rec: dict[str, list] = {k: [] for k in RESULT_KEYS}
        self.messages: list[str] = []

    def add(self, t: float, q: np.ndarray, cmd, tool: pin.SE3, ref: pin.SE3, **extra: np.ndarray) -> None:
        rec, cost = self.rec, self.ctrl.cost
        feel = len(rec["t"]) % self.feel_every == 0
        rec["t"].append(t)
        rec["q"].append(q.copy())
        rec["dq"].append(cmd.dq)
        rec["ns"].append(cmd.arm_angle)
        rec["rom_lo"].append(cmd.rom[0])
        rec["rom_hi"].append(cmd.rom[1])
        rec["interval_lo"].append(cmd.interval[0])
        rec["interval_hi"].append(cmd.interval[1])
        rec["cost"].append(cmd.cost)
        rec["mass"].append(cost.principal_mass(q) if feel else np.nan)
        rec["friction_force"].append(cost.friction_force_magnitude(q) if feel else np.nan)
        rec["status"].append(int(cmd.status.value))
        rec["stiffness"].append(cmd.stiffness)
        rec["tool_position"].append(tool.translation.copy())
        rec["ref_position"].append(ref.translation.copy())
        rec["tool_position_error"].append(float(np.linalg.norm(ref.translation - tool.translation)))
        rec["tool_rotation_error"].append(float(np.linalg.norm(pin.log3(ref.rotation @ tool.rotation.T))))
        rec["tick_time"].append(cmd.tick_time)
        rec["solve_time"].append(cmd.solve_time)
        for key, value in extra.items():
            rec.setdefault(key, []).append(value)
        if cmd.message and (not self.messages or not self.messages[-1].endswith(cmd.message)):
            self.messages.append(f"t={t:.3f}s: {cmd.message}")

    def result(self) -> RunResult:
        """The arrays and their summary (METHOD §9 metrics, status counts, felt mass and friction)."""
        from qpnso.controller import Status
        from qpnso.metrics import summarize_run

        arrays = {k: np.asarray(v) for k, v in self.rec.items()}
        summary = summarize_run(arrays, {f.name: f.value for f in Status if f.value})
        summary.update(feel_summary(arrays))
        return RunResult(arrays, summary, self.messages)


def solve_trajectory(robot: Robot, traj: Trajectory, q0: np.ndarray | None = None,
                     config: ControllerConfig | None = None, progress=None) -> RunResult:
    """Run the controller along ``traj`` at ``config.dt``; the per-tick arrays and summary.

    ``q0`` (rad) must put the tool on the first pose (within 1 mm); without it,
    :func:`initial_configuration` finds one with the elbow up.
    """
    cfg = config or ControllerConfig()
    ctrl = Controller(robot, cfg)
    first = traj.pose(traj.t[0])
    q = initial_configuration(robot, first) if q0 is None else robot.check_q(q0, "q0")
    gap = float(np.linalg.norm(robot.tool_pose(q).translation - first.translation))
    if gap > 1e-3:
        raise UnreachableError(f"q0 puts the tool {1000 * gap:.1f} mm from the trajectory's first pose")
    ctrl.reset(q)
    recorder = Recorder(ctrl)
    n = int(np.floor(traj.duration / cfg.dt + 1e-9)) + 1
    for k in range(n):
        t = traj.t[0] + k * cfg.dt
        p_ref, r_ref, v, w = traj.sample(t)
        ref = pin.SE3(r_ref, p_ref)
        cmd = ctrl.step(q, tool_twist=np.concatenate([v, w]), tool_pose=ref)
        recorder.add(t, q, cmd, robot.tool_pose(q), ref)
        q = q + cfg.dt * cmd.dq
        if progress is not None:
            progress(k + 1, n)
    return recorder.result()


def feel_summary(arrays: dict[str, np.ndarray]) -> dict[str, float]:
    """Mean and worst felt mass (kg) and friction force (N) over the recorded ticks."""
    out = {}
    for key, unit in (("mass", "kg"), ("friction_force", "N")):
        v = np.asarray(arrays.get(key, []), dtype=float)
        v = v[np.isfinite(v)]
        if v.size:
            out[f"{key}_mean_{unit}"] = float(v.mean())
            out[f"{key}_max_{unit}"] = float(v.max())
    return out
