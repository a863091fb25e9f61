"""What a 3-D replay shows of a run: the robot, the recorded configurations (rad), arm angle, ROM_t and
continuity interval (rad), the tool's path and its reference (m, world frame) and the room's keep-out volumes.

The robot and the obstacles come from the result file's scene record (:func:`qpnso.control.offline.scene_record`);
a file written before it had one needs them given (``qpnso view --robot``, ``--obstacles``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from qpnso.errors import FrameNotFoundError, InputError, ModelError, RobotNotFoundError
from qpnso.model.obstacles import Obstacle, as_obstacles
from qpnso.model.robot import Robot, load_robot_spec
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
    """The replay of a result file.  ``robot`` and ``obstacles`` (world frame, m) replace the file's scene
    record; a file without one (written before qpnso recorded it) needs ``robot``."""
    from qpnso.control.offline import read_result

    arrays, record = read_result(path, REPLAY_KEYS)
    if robot is None:
        if "robot" not in record:
            raise InputError(f"{path} does not say which robot ran it (an older file): give the robot (--robot)")
        try:
            robot = load_robot_spec(record["robot"])
        except (ModelError, RobotNotFoundError, FrameNotFoundError) as exc:
            raise InputError(f"{path}: its robot record: {exc}") from None
    if obstacles is None:
        try:
            obstacles = as_obstacles(record.get("obstacles", []), f"{path}: obstacles")
        except SettingError as exc:
            raise InputError(str(exc)) from None
    known = record.get("known_obstacles")
    note = f", {known} of {len(obstacles)} obstacles known to the controller" if known is not None and obstacles else ""
    return Replay.of(arrays, robot, obstacles, f"{Path(path).name}: {robot.name}{note}")


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
