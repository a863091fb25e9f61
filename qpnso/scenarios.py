"""The elbow paper's hands-on scenarios A and B ([E] II-D, METHOD §9).

A scenario file (TOML, ``examples/scenarios/*.toml``) gives the robot, the tool
pose at the centre of the guidance path, the start arm angle and branch (the
start configuration is the closed-form IK there), the path, and controller
settings.  :func:`run_scenario` simulates one strategy on it and returns the
run's metrics.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pinocchio as pin

from typing import TYPE_CHECKING

from qpnso.errors import ConfigError
from qpnso.robot import Robot, load_robot
from qpnso.trajectory import Trajectory, guidance_path

if TYPE_CHECKING:
    from qpnso.solve import RunResult

try:  # Python 3.11+
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

SCENARIO_DIR = Path(__file__).resolve().parent.parent / "examples" / "scenarios"
"""Where the shipped scenario files are."""


@dataclass(frozen=True)
class Scenario:
    """A hands-on scenario.  Angles in degrees as in the file; metres; world frame."""

    name: str
    description: str
    robot: str
    center: tuple[float, float, float]
    rpy_deg: tuple[float, float, float]
    ns0_deg: float
    branch: tuple[int, int, int]
    path_size: float = 0.08
    path_speed: float = 0.05
    controller: dict = field(default_factory=dict)

    def tool_pose(self) -> pin.SE3:
        """Tool pose at the path centre (world frame)."""
        rot = pin.rpy.rpyToMatrix(*np.radians(self.rpy_deg))
        return pin.SE3(rot, np.asarray(self.center, dtype=float))

    def start(self, robot: Robot) -> np.ndarray:
        """Start configuration (rad): closed-form IK at ``ns0_deg`` on ``branch``."""
        from qpnso.elbow import Branch, ik

        return robot.check_q(ik(robot, self.tool_pose(), np.radians(self.ns0_deg), Branch(*self.branch)), "start")

    def path(self, dt: float = 0.01) -> Trajectory:
        """The guidance path around the centre pose."""
        return guidance_path(self.tool_pose(), size=self.path_size, speed=self.path_speed, dt=dt)


def scenario_path(name_or_path: str | Path) -> Path:
    """``"A"``/``"B"`` (shipped) or a TOML file path."""
    p = Path(name_or_path)
    if p.suffix != ".toml":
        p = SCENARIO_DIR / f"{name_or_path}.toml"
    if not p.is_file():
        shipped = sorted(x.stem for x in SCENARIO_DIR.glob("*.toml"))
        raise ConfigError(f"unknown scenario {str(name_or_path)!r}: give one of {shipped} or a .toml file")
    return p


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Read a scenario file; a missing or unknown key is named in the error."""
    p = scenario_path(name_or_path)
    try:
        data = tomllib.loads(p.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    try:
        sc, start, path = data["scenario"], data["start"], data.get("path", {})
        if path.get("kind", "guidance") != "guidance":
            raise ConfigError(f"{p}: [path] kind must be 'guidance'")
        return Scenario(
            name=str(sc["name"]), description=str(sc.get("description", "")), robot=str(sc.get("robot", "lwr4p")),
            center=tuple(float(x) for x in start["center"]), rpy_deg=tuple(float(x) for x in start["rpy_deg"]),
            ns0_deg=float(start["ns0_deg"]), branch=tuple(int(x) for x in start["branch"]),
            path_size=float(path.get("size", 0.08)), path_speed=float(path.get("speed", 0.05)),
            controller=dict(data.get("controller", {})),
        )
    except KeyError as exc:
        raise ConfigError(f"{p}: missing key {exc.args[0]!r}") from None


def run_scenario(name: str, strategy: str, seed: int = 0, duration_scale: float = 1.0,
                 progress=None) -> dict[str, float]:
    """Simulate hands-on guidance of scenario ``name`` with ``strategy``; the run's metrics.

    ``duration_scale`` < 1 runs only the start of the path (for quick checks).
    ``seed`` is accepted for the study runner; the simulation is deterministic.
    """
    return simulate_scenario(name, strategy, duration_scale, progress).summary


def simulate_scenario(name: str, strategy: str | None = None, duration_scale: float = 1.0, progress=None,
                      settings: dict | None = None) -> "RunResult":
    """Simulate scenario ``name``: the per-tick arrays and summary (:class:`qpnso.solve.RunResult`).

    Controller settings: the scenario file's ``[controller]``, then ``settings``
    (e.g. a user's config file and CLI flags), then ``strategy`` if given.
    """
    from qpnso.controller import Controller, ControllerConfig
    from qpnso.simulation import simulate

    sc = load_scenario(name)
    robot = load_robot(sc.robot)
    values = {**sc.controller, **(settings or {})}
    if strategy is not None:
        values["strategy"] = strategy
    path = sc.path()
    if duration_scale < 1.0:
        path = path.window(path.t[0], path.t[0] + duration_scale * path.duration)
    ctrl = Controller(robot, ControllerConfig.from_dict(values))
    return simulate(ctrl, path, sc.start(robot), progress=progress)
