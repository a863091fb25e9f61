"""What a 3-D replay shows of a run: the robot, the recorded configurations (rad), arm angle, ROM_t and
continuity interval (rad), the tool's path and its reference (m, world frame) and the room's keep-out volumes.

The robot and the obstacles come from the result file's scene record (:func:`qpnso.control.offline.scene_record`);
a file written before it had one needs them given (``qpnso view --robot``, ``--obstacles``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from qpnso.errors import FrameNotFoundError, InputError, JointLimitError, ModelError, RobotNotFoundError
from qpnso.model.obstacles import Obstacle, as_obstacles
from qpnso.model.robot import Robot, load_robot_spec, robot_spec
from qpnso.settings import SettingError

REPLAY_KEYS = (
    "t",
    "q",
    "ns",
    "rom_lo",
    "rom_hi",
    "interval_lo",
    "interval_hi",
    "tool_position",
    "ref_position",
)
"""The arrays of a result file a replay reads."""


@dataclass(frozen=True)
class Replay:
    """One run to replay: ``t`` (n,) s, ``q`` (n, nq) rad, ``ns`` the arm angle (n,) rad (NaN where undefined),
    ``rom`` and ``interval`` (n, 2) rad (ROM_t and the continuity interval; ±inf or NaN where unbounded or
    unknown), ``tool`` and ``ref`` (n, 3) m, world frame; ``obstacles`` the room's; ``title`` one line."""

    robot: Robot
    t: np.ndarray
    q: np.ndarray
    ns: np.ndarray
    rom: np.ndarray
    interval: np.ndarray
    tool: np.ndarray
    ref: np.ndarray
    obstacles: tuple[Obstacle, ...] = ()
    title: str = ""

    @classmethod
    def of(cls, arrays: dict[str, np.ndarray], robot: Robot, obstacles=(), title: str = "") -> "Replay":
        """The replay of a result's ``arrays`` (:data:`REPLAY_KEYS`) on ``robot``; an InputError names an array
        of the wrong shape and the first tick whose configuration is not finite."""
        missing = [k for k in REPLAY_KEYS if k not in arrays]
        if missing:
            raise InputError(f"the run lacks {missing}")
        t = np.asarray(arrays["t"], dtype=float)
        n = t.shape[0]
        shapes: dict[str, tuple[int, ...]] = {"q": (n, robot.nq), "tool_position": (n, 3), "ref_position": (n, 3)}
        shapes |= {k: (n,) for k in ("ns", "rom_lo", "rom_hi", "interval_lo", "interval_hi")}
        for key, shape in shapes.items():
            if np.shape(arrays[key]) != shape:
                raise InputError(f"{key} has shape {np.shape(arrays[key])}, expected {shape} ({robot.name}, {n} ticks)")
        if n == 0 or t.ndim != 1 or not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
            raise InputError("t must be a non-empty, finite, increasing time axis (s)")
        q = np.asarray(arrays["q"], dtype=float)
        bad = ~np.all(np.isfinite(q), axis=1)
        if bad.any():
            k = int(np.argmax(bad))
            raise InputError(f"q at tick {k} (t = {t[k]:.6g} s) is not finite")
        return cls(
            robot,
            t,
            q,
            np.asarray(arrays["ns"], dtype=float),
            np.column_stack([arrays["rom_lo"], arrays["rom_hi"]]).astype(float),
            np.column_stack([arrays["interval_lo"], arrays["interval_hi"]]).astype(float),
            np.asarray(arrays["tool_position"], dtype=float),
            np.asarray(arrays["ref_position"], dtype=float),
            tuple(obstacles),
            title,
        )

    @property
    def duration(self) -> float:
        """s, from the first tick to the last."""
        return float(self.t[-1] - self.t[0])

    def frames(self, fps: float) -> np.ndarray:
        """Indices of the ticks shown at ``fps`` frames per second: the tick nearest each ``t0 + k/fps``, the last
        tick included."""
        if not (np.isfinite(fps) and fps > 0):
            raise InputError(f"frames per second must be a positive number, got {fps:g}")
        times = np.append(np.arange(self.t[0], self.t[-1], 1.0 / fps), self.t[-1])
        k = np.searchsorted(self.t, times).clip(0, len(self.t) - 1)
        before = (k - 1).clip(0)
        k = np.where(np.abs(self.t[before] - times) < np.abs(self.t[k] - times), before, k)
        return np.unique(k)

    def at(self, t: float) -> int:
        """The index of the tick at or just before ``t`` (s), clipped to the run."""
        return int(np.clip(np.searchsorted(self.t, t, side="right") - 1, 0, len(self.t) - 1))


def load_replay(path: str | Path, robot: Robot | None = None, obstacles=None) -> Replay:
    """The replay of a result file.  ``obstacles`` (world frame, m) replace the file's.  The robot is the one
    its scene record names; a file without one (written before qpnso recorded it) needs ``robot``.  A given
    ``robot`` that contradicts the file is refused (InputError): another robot or tool than the record's
    (:func:`check_recorded_robot`), or, without a record, one that cannot have made the run
    (:func:`check_run_fits`)."""
    from qpnso.control.offline import read_result

    arrays, record = read_result(path, REPLAY_KEYS)
    if robot is None:
        if "robot" not in record:
            raise InputError(f"{path} does not say which robot ran it (an older file): give the robot (--robot)")
        try:
            robot = load_robot_spec(record["robot"])
        except (ModelError, RobotNotFoundError, FrameNotFoundError) as exc:
            raise InputError(f"{path}: its robot record: {exc}") from None
    elif "robot" in record:
        check_recorded_robot(path, robot, record["robot"])
    if obstacles is None:
        try:
            obstacles = as_obstacles(record.get("obstacles", []), f"{path}: obstacles")
        except SettingError as exc:
            raise InputError(str(exc)) from None
    known = record.get("known_obstacles")
    note = f", {known} of {len(obstacles)} obstacles known to the controller" if known is not None and obstacles else ""
    replay = Replay.of(arrays, robot, obstacles, f"{Path(path).name}: {robot.name}{note}")
    if "robot" not in record:
        check_run_fits(path, replay)
    return replay


def check_recorded_robot(path: str | Path, robot: Robot, spec: object) -> None:
    """Refuse ``robot``, given for the result file ``path`` whose robot record is ``spec``
    (:func:`~qpnso.model.robot.robot_spec`), when it is another robot (by name: a shipped robot's, or the stem
    of the URDF file) or carries the tool on another frame or offset: the record says what ran."""
    try:
        if not isinstance(spec, dict):
            raise TypeError(repr(spec))
        name, frame = Path(str(spec["robot"])).stem, str(spec["tool_frame"])
        offset = np.asarray(spec["tool_offset"], dtype=np.float64)
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(
            f"{path}: its robot record: not a robot record (robot, tool_frame, tool_offset): {exc}"
        ) from None
    if name != robot.name:
        raise InputError(
            f"{path} was recorded on {name}, not {robot.name}: leave --robot out (the file says which robot ran it)"
        )
    given = robot_spec(robot)
    if given["tool_frame"] != frame or np.shape(offset) != (4, 4) or not np.allclose(given["tool_offset"], offset):
        raise InputError(
            f"{path} was recorded with {name}'s tool at {offset_text(frame, offset)}, not at "
            f"{offset_text(given['tool_frame'], np.array(given['tool_offset']))}: leave --tool-frame and "
            "--tool-offset out (the file says where the tool was)"
        )


def offset_text(frame: str, offset: np.ndarray) -> str:
    """A tool mounting in words: the frame and the tool point's position in it (m)."""
    if np.shape(offset) != (4, 4):
        return f"{frame} (offset {offset.tolist()})"
    x, y, z = offset[:3, 3]
    return f"{frame} + ({x:g}, {y:g}, {z:g}) m"


CONTRADICTING_TICKS_FRACTION = 0.5
"""A robot given for a file without a robot record is refused when more than this fraction of the run's ticks
contradict it (:func:`check_run_fits`).  A run of that robot has none with the controller's default tolerance,
and only a transient few where a larger ``q_limit_tolerance_deg`` let a joint out and brought it back."""
TOOL_POINT_TOLERANCE_M = 0.005
"""m: how far the recorded tool point may be from the given robot's tool point at the recorded q (a simulated
plant's measured tool point is within 0.07 mm of its model's in the shipped scenarios)."""
TOOL_POINT_TICKS_MAX = 1000
"""At most this many evenly spaced ticks are checked for the tool point (forward kinematics each)."""


def check_run_fits(path: str | Path, replay: Replay) -> None:
    """Refuse a replay of the file ``path`` on a robot that cannot have made the run (InputError naming the
    first contradicting tick): on more than :data:`CONTRADICTING_TICKS_FRACTION` of its ticks a recorded joint
    is outside the robot's limits by more than the controller's default ``q_limit_tolerance_deg`` (beyond it
    the controller refuses the measured q: JointLimitError naming the joint), or the robot's tool point at the
    recorded q is farther than :data:`TOOL_POINT_TOLERANCE_M` from the recorded one (the file's joint count is
    checked before, :meth:`Replay.of`)."""
    from qpnso.control.config import ControllerConfig

    r, q, n = replay.robot, replay.q, len(replay.t)
    tolerance_deg = ControllerConfig.q_limit_tolerance_deg
    tolerance = np.radians(tolerance_deg)
    beyond = (q < r.q_min - tolerance) | (q > r.q_max + tolerance)
    ticks = beyond.any(axis=1)
    if ticks.sum() > CONTRADICTING_TICKS_FRACTION * n:
        k = int(np.argmax(ticks))
        j = int(np.argmax(beyond[k]))
        raise JointLimitError(
            f"{path} cannot be a run of {r.name}: at tick {k} (t = {replay.t[k]:.6g} s) q[{j}] ({r.joint_names[j]}) "
            f"= {np.degrees(q[k, j]):.4g}° is outside its limits [{np.degrees(r.q_min[j]):.4g}°, "
            f"{np.degrees(r.q_max[j]):.4g}°] by more than {tolerance_deg:g}°, and a joint is so on {int(ticks.sum())} "
            f"of {n} ticks: give the robot that ran it (--robot)"
        )
    checked = np.unique(np.linspace(0, n - 1, min(n, TOOL_POINT_TICKS_MAX)).astype(int))
    gap = np.array([np.linalg.norm(r.tool_pose(q[k]).translation - replay.tool[k]) for k in checked])
    far = gap > TOOL_POINT_TOLERANCE_M
    if far.sum() > CONTRADICTING_TICKS_FRACTION * len(checked):
        i = int(np.argmax(far))
        raise InputError(
            f"{path} cannot be a run of {r.name} with this tool: at tick {checked[i]} (t = "
            f"{replay.t[checked[i]]:.6g} s) its tool point at the recorded q is {gap[i]:.4g} m from the recorded "
            f"one, and is so on {int(far.sum())} of {len(checked)} ticks checked: give the robot and tool that ran it "
            "(--robot, --tool-frame, --tool-offset)"
        )


def scenario_replay(
    name: str, strategy: str | None = None, duration_scale: float = 1.0, progress=None, ignore_obstacles: bool = False
) -> Replay:
    """Simulate scenario ``name`` with ``strategy`` (:func:`qpnso.lab.scenarios.simulate_scenario`) and replay
    the run."""
    from qpnso.lab.scenarios import load_scenario, simulate_scenario

    result = simulate_scenario(name, strategy, duration_scale, progress, ignore_obstacles=ignore_obstacles)
    robot = load_robot_spec(result.scene["robot"])
    room = as_obstacles(result.scene["obstacles"])
    unknown = ", obstacles unknown to the controller" if ignore_obstacles and room else ""
    title = f"scenario {load_scenario(name).name}, strategy {result.scene['strategy']}{unknown}"
    return Replay.of(result.arrays, robot, room, title)
