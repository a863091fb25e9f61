"""Offline solve of a whole tool trajectory, tick by tick (the main job).

Level 1 tracks the trajectory's tool motion (twist feed-forward plus pose
correction); level 2 does what the strategy asks.  The joints are integrated
kinematically, ``q ← q + dt·q̇``, as a position-controlled arm would follow.
"""

from __future__ import annotations

import json
import os
import tempfile
import zipfile
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
from scipy.spatial.transform import Rotation

from qpnso.control.config import ControllerConfig, Status
from qpnso.control.controller import Controller
from qpnso.control.trajectory import Trajectory
from qpnso.errors import InputError, QpnsoError, TrajectoryError, UnreachableError
from qpnso.model.robot import Robot, robot_spec

RESULT_KEYS = (
    "t",
    "q",
    "dq",
    "ns",
    "rom_lo",
    "rom_hi",
    "interval_lo",
    "interval_hi",
    "cost",
    "mass",
    "friction_force",
    "status",
    "stiffness",
    "tool_position",
    "ref_position",
    "tool_position_error",
    "tool_rotation_error",
    "tick_time",
    "solve_time",
)

_COMPUTED_AFTER = ("mass", "friction_force", "tool_position_error", "tool_rotation_error")
"""What :class:`Recorder` computes for a whole run at its end."""


@dataclass(frozen=True)
class ObstacleTick:
    """A tick whose status had ``OBSTACLE`` (a link inside its margin of an obstacle, or unable to keep it), as
    the controller reported it: the tick's index (0-based) and time ``t`` (s), the link (its capsule's
    name), the obstacle (its index in the controller's obstacles), the controller's clearance of that pair (m)
    and the command's message; ``data_row`` the trajectory's data row the tick follows (:func:`data_row`; None:
    no trajectory file, e.g. a simulation)."""

    tick: int
    t: float
    link: str
    obstacle: int
    clearance: float
    message: str
    data_row: int | None = None

    @classmethod
    def of(cls, tick: int, t: float, cmd, ctrl: Controller) -> "ObstacleTick":
        """The tick ``tick`` at ``t`` (s) just stepped by ``ctrl``, its command ``cmd``: the pair from the tick's
        report (the one the command's clearance and message name)."""
        report = ctrl.records.report[0]
        capsule, obstacle = int(report["clear_capsule"]), int(report["clear_obstacle"])
        link = ctrl.capsules.names[capsule] if ctrl.capsules is not None and capsule >= 0 else ""
        return cls(tick, float(t), link, obstacle, float(cmd.clearance), cmd.message)

    def summary(self) -> dict[str, Any]:
        """Summary entries ``first_obstacle_tick``, ``_t_s``, ``_link``, ``_obstacle``, ``_clearance_m`` (and
        ``_data_row`` when known)."""
        out: dict[str, Any] = {
            "first_obstacle_tick": self.tick,
            "first_obstacle_t_s": float(f"{self.t:.12g}"),
            "first_obstacle_link": self.link,
            "first_obstacle_obstacle": self.obstacle,
            "first_obstacle_clearance_m": self.clearance,
        }
        if self.data_row is not None:
            out["first_obstacle_data_row"] = self.data_row
        return out

    def describe(self) -> str:
        """One line: where the first ``OBSTACLE`` tick was and what the controller said."""
        row = f", data row {self.data_row}" if self.data_row is not None else ""
        return (
            f"first OBSTACLE tick {self.tick} (t = {self.t:.6g} s{row}): {self.link or 'a link'} "
            f"{self.clearance:.4f} m from obstacle {self.obstacle}; {self.message}"
        )


@dataclass
class RunResult:
    """Arrays over ticks of one run (rad, m, s, kg, N; world frame) and its summary.

    ``failure`` is empty unless the run finished but failed its check (for
    :func:`solve_trajectory`: the tool left the trajectory by more than the
    tolerance); it is then one line saying where and by how much, and
    ``summary["result"]`` is ``"failed"``.  ``first_obstacle`` is the first tick
    whose status had ``OBSTACLE`` (None: none had).
    """

    arrays: dict[str, np.ndarray]
    summary: dict[str, Any] = field(default_factory=dict)
    messages: list[str] = field(default_factory=list)
    failure: str = ""
    first_obstacle: ObstacleTick | None = None
    setup: dict[str, Any] = field(default_factory=dict)  # what ran it, as plain data (a simulation's plant, surgeon)
    scene: dict[str, Any] = field(default_factory=dict)  # what it moved, as plain data (:func:`scene_record`)

    @property
    def ok(self) -> bool:
        """True unless the run failed its check (see ``failure``)."""
        return not self.failure

    def save(self, path: str | Path) -> Path:
        """Write ``result.npz`` atomically (temporary file, then rename): the arrays, and the scene record as the
        JSON text ``scene`` (read back by :func:`read_result`)."""
        data = dict(self.arrays)
        if self.scene:
            data[SCENE_KEY] = np.array(json.dumps(self.scene))
        # NumPy's stub: mypy cannot tell that no key of ``**data`` is the keyword ``allow_pickle: bool``
        return atomic_write(Path(path), lambda f: np.savez_compressed(f, **data))  # type: ignore[arg-type]


SCENE_KEY = "scene"
"""The result file's entry holding :attr:`RunResult.scene` as JSON text."""


def scene_record(ctrl: Controller, obstacles=None) -> dict[str, Any]:
    """What a run moved, as plain data for a 3-D replay: the robot (:func:`~qpnso.model.robot.robot_spec`), the
    controller's ``strategy``, the keep-out volumes in the room (``obstacles``, default the controller's: their
    TOML tables, m, world frame) and how many of them the controller was given (``known_obstacles``)."""
    room = ctrl.obstacles if obstacles is None else obstacles
    return {
        "robot": robot_spec(ctrl.robot),
        "strategy": ctrl.config.strategy,
        "obstacles": [o.to_dict() for o in room],
        "known_obstacles": len(ctrl.obstacles),
    }


def read_result(path: str | Path, required: tuple[str, ...]) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """The arrays of a result file (``--out`` of ``qpnso solve`` or ``simulate``) and its scene record (empty for
    a file written before it had one); an InputError says what is wrong (no such file, not a ``.npz``, cannot be
    read, lacks one of ``required``)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"result file not found: {path}")
    not_result = f"{path} is not a qpnso result .npz (the --out file of qpnso solve or simulate)"
    if not zipfile.is_zipfile(path):  # a CSV, a .npy, ...: np.load would talk about pickled data
        raise InputError(f"{not_result}: it is not a NumPy .npz archive")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise InputError(f"{not_result}: cannot read it ({exc})") from None
    missing = [k for k in required if k not in arrays]
    if missing:
        raise InputError(f"{not_result}: it lacks {missing}")
    scene = arrays.pop(SCENE_KEY, None)
    try:
        record = json.loads(str(scene)) if scene is not None else {}
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: its scene record is not JSON ({exc})") from None
    if not isinstance(record, dict):
        raise InputError(f"{path}: its scene record is not a table")
    return arrays, record


def atomic_write(path: Path, write) -> Path:
    """Call ``write(file)`` on a temporary file beside ``path``, then rename it into place.

    The file gets the mode a plain ``open(path, "w")`` would give it: an existing
    file's mode, else 0666 minus the umask (``mkstemp`` alone would leave 0600).
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        os.chmod(tmp, _new_file_mode(path))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def _new_file_mode(path: Path) -> int:
    """The permission bits ``open(path, "w")`` would leave: the existing file's, else 0666 & ~umask."""
    try:
        st = path.stat()
    except OSError:
        return 0o666 & ~_umask()
    import stat

    return stat.S_IMODE(st.st_mode) if stat.S_ISREG(st.st_mode) else 0o666 & ~_umask()


def _umask() -> int:
    """The process umask, read without changing it where Linux shows it (thread-safe)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o077)  # elsewhere: set and restore (a restrictive value while it is swapped)
    os.umask(mask)
    return mask


def config_values(path: str | Path | None, overrides: dict | None = None) -> dict:
    """Controller settings as plain data: a TOML file (top level or ``[controller]``),
    then ``overrides`` (CLI flags; None values are not given).

    The file's keys and value types are checked here, the error naming the file and
    the key.  Beside a ``[controller]`` table the top level may hold only the other
    tables of a scenario file (``[scenario]``, ``[start]``, ``[path]``, ``[[obstacles]]``:
    a scenario file is a valid config file, its ``[[obstacles]]`` going to the controller
    with its ``[controller]`` settings); a setting there, or given both at the top level
    and under ``[controller]``, is an error rather than silently dropped.
    """
    from qpnso.lab.scenarios import SCENARIO_TABLES
    from qpnso.settings import SettingError, check_table, read_toml, show

    values: dict = {}
    if path is not None:
        p = Path(path)
        data = read_toml(p, "config file")
        values = data
        if "controller" in data:
            values = data["controller"]
            if not isinstance(values, dict):
                raise SettingError(
                    str(p),
                    "controller",
                    f"expected a table of ControllerConfig settings, got {type(values).__name__}",
                    show(values),
                )
            tables = sorted(SCENARIO_TABLES)
            for key in data:
                if key in values and key != "controller":
                    raise SettingError(str(p), key, "given both at the top level and under [controller]; keep one")
                if key not in tables:
                    raise SettingError(
                        str(p),
                        key,
                        f"not allowed at the top level beside a [controller] table "
                        f"(top-level tables: {', '.join(tables)}); controller settings go under "
                        f"[controller]",
                    )
            if "obstacles" in data:  # (a scenario file's [[obstacles]]: the room's, given to the controller)
                values = {**values, "obstacles": data["obstacles"]}
        values = dict(values)
        check_table(ControllerConfig, values, str(p))
    values.update({k: v for k, v in (overrides or {}).items() if v is not None})
    return values


def load_config(path: str | Path | None, overrides: dict | None = None) -> ControllerConfig:
    """A :class:`ControllerConfig` from a TOML file, then ``overrides`` (CLI flags); an
    error about a setting the file gave names the file and the key."""
    from qpnso.settings import SettingError

    values = config_values(path, overrides)
    flags = {k for k, v in (overrides or {}).items() if v is not None}
    try:
        return ControllerConfig.from_dict(values)
    except SettingError as exc:
        if path is None or exc.key.split(".")[0] in flags:
            raise
        raise exc.within(where=str(path)) from None


def initial_configuration(
    robot: Robot, pose: pin.SE3, arm_angle: float = 0.0, interval_margin_deg: float = 15.0
) -> np.ndarray:
    """A configuration (rad) reaching ``pose`` with the arm angle closest to ``arm_angle``
    (0 = elbow up), joints 2° inside their limits, preferring those at least
    ``interval_margin_deg`` from the ends of their continuity interval (S-R-S arms)."""
    from qpnso.elbow.intervals import continuity_interval
    from qpnso.elbow.srs import Branch, ik

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
    from qpnso.elbow.arm_angle import arm_angle

    try:
        iv = continuity_interval(robot, q)
        ns = arm_angle(robot, q)
    except QpnsoError:
        return -np.inf
    return np.inf if iv.full_circle else min(ns - iv.lo, iv.hi - ns)


class Recorder:
    """Collects the per-tick arrays of a run (:data:`RESULT_KEYS`, plus extras): what each tick returned and
    the tool's and the reference's poses, copied, nothing computed per tick.  :meth:`result` computes the rest
    for the whole run at once: ``mass``, the largest principal mass felt at the tool (kg), and
    ``friction_force``, the potential friction force magnitude (N, √c_f), both at the measured ``q``
    (:meth:`~qpnso.model.costs.CostModel.felt`, every ``feel_every``-th tick, NaN in between), and the tool's
    position and rotation errors.  With ``felt`` (``qs (N, nq) → (mass (N,), friction force (N,))``, e.g. a
    simulated plant's :meth:`~qpnso.lab.plant.Plant.felt`), ``mass`` and ``friction_force`` are what it
    gives and the controller's own estimates are ``mass_model`` and ``friction_model``.
    """

    def __init__(self, ctrl: Controller, feel_every: int = 1, felt=None) -> None:
        self.ctrl = ctrl
        self.feel_every = max(1, int(feel_every))
        self.felt = felt
        ctrl.cost.felt_function()  # (made now: a background compile of it runs during the run)
        self.rec: dict[str, list] = {k: [] for k in _TICK_KEYS}
        self.messages: list[str] = []
        self.first_obstacle: ObstacleTick | None = None

    def add(
        self, t: float, q: np.ndarray, cmd, tool: pin.SE3 | tuple, ref: pin.SE3 | tuple, **extra: np.ndarray
    ) -> None:
        """Tick ``t`` (s) at joints ``q`` (rad) with its command; ``tool`` and ``ref`` the tool's and the
        reference's poses (world frame), each a ``pinocchio.SE3`` or ``(rotation, position)``."""
        rec = self.rec
        tool_R, tool_p = (tool.rotation, tool.translation) if isinstance(tool, pin.SE3) else tool
        ref_R, ref_p = (ref.rotation, ref.translation) if isinstance(ref, pin.SE3) else ref
        rec["t"].append(t)
        rec["q"].append(q.copy())
        rec["dq"].append(cmd.dq)
        rec["ns"].append(cmd.arm_angle)
        rec["rom_lo"].append(cmd.rom[0])
        rec["rom_hi"].append(cmd.rom[1])
        rec["interval_lo"].append(cmd.interval[0])
        rec["interval_hi"].append(cmd.interval[1])
        rec["cost"].append(cmd.cost)
        rec["status"].append(int(cmd.status.value))
        rec["stiffness"].append(cmd.stiffness)
        rec["tool_rotation"].append(tool_R.copy())
        rec["tool_position"].append(tool_p.copy())
        rec["ref_rotation"].append(ref_R.copy())
        rec["ref_position"].append(ref_p.copy())
        rec["tick_time"].append(cmd.tick_time)
        rec["solve_time"].append(cmd.solve_time)
        for key, value in extra.items():
            rec.setdefault(key, []).append(value)
        if cmd.message and (not self.messages or not self.messages[-1].endswith(cmd.message)):
            self.messages.append(f"t={t:.3f}s: {cmd.message}")
        if self.first_obstacle is None and cmd.status & Status.OBSTACLE:
            self.first_obstacle = ObstacleTick.of(len(rec["t"]) - 1, t, cmd, self.ctrl)

    def result(self) -> RunResult:
        """The arrays and their summary (docs/method.md §9 metrics, status counts, felt mass and friction, the
        first ``OBSTACLE`` tick if any: :meth:`ObstacleTick.summary`)."""
        from qpnso.lab.metrics import summarize_run

        arrays = {k: np.asarray(v) for k, v in self.rec.items()}
        q = arrays["q"].reshape(-1, self.ctrl.robot.nq)
        felt = np.arange(q.shape[0]) % self.feel_every == 0
        model_keys = ("mass", "friction_force") if self.felt is None else ("mass_model", "friction_model")
        sources = [(model_keys, self.ctrl.cost.felt)]
        if self.felt is not None:
            sources.append((("mass", "friction_force"), self.felt))
        for (mass_key, friction_key), felt_at in sources:
            arrays[mass_key], arrays[friction_key] = np.full(q.shape[0], np.nan), np.full(q.shape[0], np.nan)
            arrays[mass_key][felt], arrays[friction_key][felt] = felt_at(q[felt])
        tool_R, ref_R = arrays.pop("tool_rotation"), arrays.pop("ref_rotation")
        arrays["tool_position_error"] = np.linalg.norm(arrays["ref_position"] - arrays["tool_position"], axis=-1)
        arrays["tool_rotation_error"] = rotation_angle(ref_R @ np.swapaxes(tool_R, -1, -2))
        flags = {f.name: f.value for f in Status if f.value and f.name is not None}  # (members are named)
        summary = summarize_run(arrays, flags, dt=self.ctrl.config.dt)
        summary.update(feel_summary(arrays))
        if self.first_obstacle is not None:
            summary.update(self.first_obstacle.summary())
        return RunResult(
            arrays, summary, self.messages, first_obstacle=self.first_obstacle, scene=scene_record(self.ctrl)
        )


_TICK_KEYS = tuple(k for k in RESULT_KEYS if k not in _COMPUTED_AFTER) + ("tool_rotation", "ref_rotation")


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """The angle (rad, in [0, π]) of each rotation matrix of ``R`` (..., 3, 3): ``‖log₃ R‖``, from the
    quaternion (SciPy), accurate near 0 and π alike.  An empty stack gives an empty array."""
    R = np.asarray(R, dtype=float)
    if R.size == 0:
        return np.zeros(R.shape[:-2])
    return Rotation.from_matrix(R.reshape(-1, 3, 3)).magnitude().reshape(R.shape[:-2])


TOOL_TOLERANCE_M = 1e-3
"""Default tool position tolerance of :func:`solve_trajectory` (m)."""
TOOL_TOLERANCE_RAD = float(np.radians(1.0))
"""Default tool rotation tolerance of :func:`solve_trajectory` (rad)."""


def solve_trajectory(
    robot: Robot,
    traj: Trajectory,
    q0: np.ndarray | None = None,
    config: ControllerConfig | None = None,
    progress=None,
    tool_tolerance_m: float = TOOL_TOLERANCE_M,
    tool_tolerance_rad: float = TOOL_TOLERANCE_RAD,
) -> RunResult:
    """Run the controller along ``traj`` at ``config.dt``; the per-tick arrays and summary.

    ``q0`` (rad) must put the tool on the first pose (within 1 mm); without it,
    :func:`initial_configuration` finds one with the elbow up.  The robot must be
    a 7-DOF arm (:meth:`Robot.require_redundant_arm`).

    The run always completes; afterwards, if the tool ever left the reference by
    more than ``tool_tolerance_m`` (m) or ``tool_tolerance_rad`` (rad), the
    summary's ``result`` is ``"failed"`` and ``RunResult.failure`` says at which
    tick and which trajectory sample (:func:`tool_error_check`); else ``"ok"``.
    A tick flagged ``OBSTACLE`` does not fail the run (the tool kept its path):
    ``RunResult.first_obstacle`` and the summary's ``first_obstacle_*`` name the
    first (:class:`ObstacleTick`, with its data row).
    """
    cfg = config or ControllerConfig()
    robot.require_redundant_arm()
    for name, value in (("tool_tolerance_m", tool_tolerance_m), ("tool_tolerance_rad", tool_tolerance_rad)):
        try:
            tolerance = float(value)
        except (TypeError, ValueError):
            tolerance = float("nan")
        if not (np.isfinite(tolerance) and tolerance > 0):
            raise InputError(f"{name} must be a positive finite number, got {value!s}")
    ctrl = Controller(robot, cfg)
    first = traj.pose(traj.t[0])
    q = initial_configuration(robot, first) if q0 is None else robot.check_q(q0, "q0")
    gap = float(np.linalg.norm(robot.tool_pose(q).translation - first.translation))
    if gap > 1e-3:
        raise UnreachableError(f"q0 puts the tool {1000 * gap:.1f} mm from the trajectory's first pose")
    ctrl.reset(q)
    recorder = Recorder(ctrl)
    n = int(np.floor(traj.duration / cfg.dt + 1e-9)) + 1
    times = traj.t[0] + np.arange(n) * cfg.dt
    positions, rotations, v, w = traj.samples(times)  # (the whole run's reference at once)
    check_tool_speeds(traj, times, v, w, cfg)
    twists = np.concatenate([v, w], axis=1)
    state = ctrl.records.state
    tool = (state["R"][0], state["p"][0])  # views: the tool's pose at the tick's q, as the tick evaluated it
    for k in range(n):
        ref = pin.SE3(rotations[k], positions[k])
        cmd = ctrl.step(q, tool_twist=twists[k], tool_pose=ref)
        recorder.add(float(times[k]), q, cmd, tool, (rotations[k], positions[k]))
        q = q + cfg.dt * cmd.dq
        if progress is not None:
            progress(k + 1, n)
    result = recorder.result()
    verdict, result.failure = tool_error_check(result.arrays, traj.t, tool_tolerance_m, tool_tolerance_rad)
    result.summary.update(verdict)
    if result.first_obstacle is not None:
        result.first_obstacle = replace(result.first_obstacle, data_row=data_row(traj.t, result.first_obstacle.t))
        result.summary.update(result.first_obstacle.summary())
    return result


def check_tool_speeds(traj: Trajectory, times: np.ndarray, v: np.ndarray, w: np.ndarray, cfg: ControllerConfig) -> None:
    """:class:`TrajectoryError` naming the first tick (its time and data row) whose tool speed (m/s, rad/s; the
    trajectory's own, ``v`` and ``w`` at ``times``) is beyond what the controller accepts
    (``tool_speed_accepted``, ``tool_angular_speed_accepted``): a jump in the file, or mm for m, would
    otherwise stop the run at that tick."""
    linear, angular = np.linalg.norm(v, axis=1), np.linalg.norm(w, axis=1)
    over = (linear > cfg.tool_speed_accepted) | (angular > cfg.tool_angular_speed_accepted)
    if over.any():
        k = int(np.argmax(over))
        raise TrajectoryError(
            f"the trajectory asks {linear[k]:.4g} m/s and {angular[k]:.4g} rad/s of the tool at t = {times[k]:.4g} s "
            f"(data row {data_row(traj.t, float(times[k]))}), beyond the accepted {cfg.tool_speed_accepted:g} m/s "
            f"and {cfg.tool_angular_speed_accepted:g} rad/s (tool_speed_accepted, tool_angular_speed_accepted): "
            "a jump in the file, or positions not in metres?"
        )


def data_row(row_times: np.ndarray, t: float) -> int:
    """The 1-based data row of a trajectory (CSV rows counted from 1 after the header)
    that is the last one at or before time ``t`` (s): the sample the tick at ``t``
    interpolates from.  0 if ``t`` is before the first row."""
    return int(np.searchsorted(np.asarray(row_times, dtype=float), float(t) + 1e-9, side="right"))  # 1e-9 s: round-off


def tool_error_check(
    arrays: dict[str, np.ndarray],
    row_times: np.ndarray,
    tolerance_m: float = TOOL_TOLERANCE_M,
    tolerance_rad: float = TOOL_TOLERANCE_RAD,
) -> tuple[dict[str, Any], str]:
    """Did the tool stay on the trajectory?  ``(summary entries, failure line)``.

    Compares the recorded ``tool_position_error`` (m) and ``tool_rotation_error``
    (rad) of every tick with the tolerances.  The summary entries are ``result``
    (``"ok"`` or ``"failed"``), ``tool_tolerance_m``, ``tool_tolerance_deg`` and,
    on failure, ``first_failed_tick`` (0-based), ``first_failed_t_s`` (the tick's
    time), ``first_failed_data_row`` (1-based data row of ``row_times`` — the CSV
    row after the header — last at or before that time) with its time
    ``first_failed_data_row_t_s``, the errors there and the largest errors with
    their data rows.  The failure line is empty when the run is ok.
    """
    t = np.asarray(arrays["t"], dtype=float)
    pos = np.asarray(arrays["tool_position_error"], dtype=float)
    rot = np.asarray(arrays["tool_rotation_error"], dtype=float)
    out: dict[str, Any] = {
        "result": "ok",
        "tool_tolerance_m": float(tolerance_m),
        "tool_tolerance_deg": float(np.degrees(tolerance_rad)),
    }
    bad = ~(pos <= tolerance_m) | ~(rot <= tolerance_rad)  # NaN counts as exceeded
    if not bad.any():
        return out, ""
    k = int(np.flatnonzero(bad)[0])
    row_times = np.asarray(row_times, dtype=float)
    row = data_row(row_times, t[k])
    worst_p = int(np.nanargmax(pos)) if np.isfinite(pos).any() else k
    worst_r = int(np.nanargmax(rot)) if np.isfinite(rot).any() else k
    out.update(
        result="failed",
        first_failed_tick=k,
        first_failed_t_s=float(f"{t[k]:.12g}"),
        first_failed_data_row=row,
        first_failed_data_row_t_s=float(row_times[max(row, 1) - 1]),
        first_failed_position_error_m=float(pos[k]),
        first_failed_rotation_error_deg=float(np.degrees(rot[k])),
        worst_position_error_m=float(pos[worst_p]),
        worst_position_error_data_row=data_row(row_times, t[worst_p]),
        worst_rotation_error_deg=float(np.degrees(rot[worst_r])),
        worst_rotation_error_data_row=data_row(row_times, t[worst_r]),
    )
    what = []
    if not pos[k] <= tolerance_m:
        what.append(f"position error {1000 * pos[k]:.3g} mm > {1000 * tolerance_m:g} mm")
    if not rot[k] <= tolerance_rad:
        what.append(f"rotation error {np.degrees(rot[k]):.3g} deg > {np.degrees(tolerance_rad):g} deg")
    line = (
        f"the tool left the trajectory at data row {row} (t = {row_times[max(row, 1) - 1]:.6g} s; "
        f"data rows count from 1 after the header), tick t = {t[k]:.6g} s: {' and '.join(what)}; "
        f"largest position error {1000 * out['worst_position_error_m']:.4g} mm "
        f"(data row {out['worst_position_error_data_row']}), rotation error "
        f"{out['worst_rotation_error_deg']:.3g} deg (data row {out['worst_rotation_error_data_row']})"
    )
    return out, line


def feel_summary(arrays: dict[str, np.ndarray]) -> dict[str, float]:
    """Mean and worst felt mass (kg) and friction force (N) over the recorded ticks, and the controller's
    estimates of them when a plant's are recorded beside them (``mass_model``, ``friction_model``)."""
    out = {}
    for key, unit in (("mass", "kg"), ("friction_force", "N"), ("mass_model", "kg"), ("friction_model", "N")):
        v = np.asarray(arrays.get(key, []), dtype=float)
        v = v[np.isfinite(v)]
        if v.size:
            out[f"{key}_mean_{unit}"] = float(v.mean())
            out[f"{key}_max_{unit}"] = float(v.max())
    return out
