"""The elbow paper's hands-on scenarios A and B ([E] II-D, docs/method.md §9), and B with a microscope.

A scenario file (TOML, ``examples/scenarios/*.toml``) gives the robot, the tool
pose at the centre of the guidance path, the start arm angle and branch (the
start configuration is the closed-form IK there), the path, controller
settings (``[controller]``) and the room's keep-out volumes: ``[[obstacles]]``
tables at the TOP LEVEL of the file (``type = "box"`` etc., world frame, m;
:mod:`qpnso.model.obstacles`), not inside ``[controller]`` (refused there).
The obstacles reach the controller (``ControllerConfig.obstacles``) unless a
run ignores them (``ignore_obstacles``, ``--ignore-obstacles``); either way the
simulation measures every link's clearance to them with coal
(:func:`qpnso.lab.simulation.simulate`).  A scenario file is also a valid
``--config`` file: its ``[[obstacles]]`` go to the controller with its
``[controller]`` settings (:func:`qpnso.control.offline.config_values`).
:func:`run_scenario` simulates one strategy on it and returns the run's metrics.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pinocchio as pin

from qpnso.control.trajectory import Trajectory, guidance_path
from qpnso.errors import ConfigError
from qpnso.model.obstacles import Obstacle
from qpnso.model.robot import Robot, load_robot
from qpnso.settings import SettingError, check, from_dict, out_of_range, read_toml
from qpnso.shipped import shipped_dir

if TYPE_CHECKING:
    from qpnso.control.offline import RunResult
    from qpnso.lab.simulation import SimulationConfig
    from qpnso.lab.surgeon import IntendedMotion

SCENARIO_DIR = shipped_dir("scenarios")
"""Where the shipped scenario files are (``examples/scenarios/`` of the source tree)."""


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
    path_kind: str = "guidance"
    hold_duration: float = 5.0
    controller: dict = field(default_factory=dict)
    obstacles: tuple[Obstacle, ...] = ()  # the room's keep-out volumes (world frame, m)
    surgeon: dict = field(default_factory=dict)  # the scenario's surgeon (:class:`qpnso.lab.surgeon.Subject`)

    def tool_pose(self) -> pin.SE3:
        """Tool pose at the path centre (world frame)."""
        rot = pin.rpy.rpyToMatrix(*np.radians(self.rpy_deg))
        return pin.SE3(rot, np.asarray(self.center, dtype=float))

    def start(self, robot: Robot) -> np.ndarray:
        """Start configuration (rad): closed-form IK at ``ns0_deg`` on ``branch``."""
        from qpnso.elbow.srs import Branch, ik

        return robot.check_q(ik(robot, self.tool_pose(), np.radians(self.ns0_deg), Branch(*self.branch)), "start")

    def path(self, dt: float = 0.01) -> Trajectory:
        """The guidance path around the centre pose (the elbow paper's, minimum-jerk timed)."""
        return guidance_path(self.tool_pose(), size=self.path_size, speed=self.path_speed, dt=dt)

    def motion(self, speed_scale: float = 1.0) -> "IntendedMotion":
        """What the surgeon intends: the guidance task timed by the two-thirds power law, each segment ending
        at rest (:func:`qpnso.lab.surgeon.guidance_motion`), or, for a ``hold`` path, the tool held still at
        the centre pose for ``hold_duration`` s.  ``speed_scale`` scales the path's speed (a subject's)."""
        from qpnso.lab.surgeon import guidance_motion, hold_motion

        if self.path_kind == "hold":
            return hold_motion(self.tool_pose(), self.hold_duration)
        return guidance_motion(self.tool_pose(), self.path_size, self.path_speed * speed_scale)


@dataclass(frozen=True)
class ScenarioTable:
    """``[scenario]`` of a scenario file."""

    name: str
    description: str = ""
    robot: str = "lwr4p"

    def __post_init__(self) -> None:
        check(self)


@dataclass(frozen=True)
class StartTable:
    """``[start]``: the tool pose at the path centre (m, degrees, world frame), the start arm angle and branch."""

    center: tuple[float, float, float]
    rpy_deg: tuple[float, float, float]
    ns0_deg: float
    branch: tuple[int, int, int]  # signs of joints 2, 4, 6

    def __post_init__(self) -> None:
        check(self)
        if any(s not in (1, -1) for s in self.branch):
            raise out_of_range(self, "branch", "must be three signs, each 1 or -1")


@dataclass(frozen=True)
class PathTable:
    """``[path]``: the guidance path (lemniscates) around the centre pose, or ``kind = "hold"``: the tool
    held still there for ``duration`` s."""

    kind: str = "guidance"
    size: float = 0.08  # m, tip to tip
    speed: float = 0.05  # m/s, peak tool speed
    duration: float = 5.0  # s, of a hold

    def __post_init__(self) -> None:
        check(self)
        if self.kind not in ("guidance", "hold"):
            raise out_of_range(self, "kind", "must be 'guidance' or 'hold'")
        for name in ("size", "speed", "duration"):
            if getattr(self, name) <= 0:
                raise out_of_range(self, name, "must be > 0")


@dataclass(frozen=True)
class ScenarioFile:
    """A scenario file's tables, type-checked by :func:`qpnso.settings.from_dict`
    (``controller`` holds :class:`qpnso.control.config.ControllerConfig` settings but not ``obstacles``, which
    are top-level ``[[obstacles]]`` tables)."""

    scenario: ScenarioTable
    start: StartTable
    path: PathTable = field(default_factory=PathTable)
    controller: dict = field(default_factory=dict)
    obstacles: tuple[Obstacle, ...] = ()
    surgeon: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        check(self)


SCENARIO_TABLES = tuple(f.name for f in fields(ScenarioFile))
"""The top-level tables of a scenario file."""


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
    """Read a scenario file (tables :class:`ScenarioFile`); a missing, unknown or wrongly
    typed key, or a value out of range, is a :class:`ConfigError` naming the file and the key."""
    from qpnso.control.config import ControllerConfig

    p = scenario_path(name_or_path)
    data = read_toml(p, "scenario file")
    f = from_dict(ScenarioFile, data, str(p))
    if "obstacles" in f.controller:
        raise SettingError(str(p), "controller.obstacles", "a scenario's obstacles go at the top level: [[obstacles]]")
    try:
        ControllerConfig.from_dict({**f.controller, "obstacles": f.obstacles})
    except SettingError as exc:
        raise exc.within("controller", str(p)) from None
    from qpnso.lab.surgeon import Subject

    Subject.from_dict(f.surgeon, str(p))
    return Scenario(
        name=f.scenario.name,
        description=f.scenario.description,
        robot=f.scenario.robot,
        center=f.start.center,
        rpy_deg=f.start.rpy_deg,
        ns0_deg=f.start.ns0_deg,
        branch=f.start.branch,
        path_size=f.path.size,
        path_speed=f.path.speed,
        path_kind=f.path.kind,
        hold_duration=f.path.duration,
        controller=dict(f.controller),
        obstacles=f.obstacles,
        surgeon=dict(f.surgeon),
    )


def run_scenario(
    name: str, strategy: str, seed: int = 0, duration_scale: float = 1.0, progress=None
) -> dict[str, float]:
    """Simulate hands-on guidance of scenario ``name`` with ``strategy``; the run's metrics.

    ``duration_scale`` < 1 runs only the start of the path (for quick checks).  ``seed`` seeds the
    surgeon's tremor (the default surgeon, no model error).
    """
    from qpnso.lab.simulation import SimulationConfig

    return simulate_scenario(
        name, strategy, duration_scale, progress, simulation=SimulationConfig(noise_seed=seed)
    ).summary


def simulate_scenario(
    name: str,
    strategy: str | None = None,
    duration_scale: float = 1.0,
    progress=None,
    settings: dict | None = None,
    ignore_obstacles: bool = False,
    simulation: "SimulationConfig | None" = None,
    robot: Robot | None = None,
) -> "RunResult":
    """Simulate scenario ``name``: the per-tick arrays and summary (:class:`qpnso.control.offline.RunResult`).

    Controller settings: the scenario file's ``[controller]`` and ``[[obstacles]]``, then ``settings``
    (e.g. a user's config file and CLI flags), then ``strategy`` if given.  The obstacles so resolved are the
    room's: the simulation measures every link's clearance to them (coal); with ``ignore_obstacles`` the
    controller does not get them (it runs as if the room were empty).  ``simulation``: the plant, surgeon and
    model error (default :class:`qpnso.lab.simulation.SimulationConfig` with the scenario's ``[surgeon]``
    table, if any); the surgeon intends
    :meth:`Scenario.motion` at its speed scale.  ``robot``: the scenario's robot with other parameters (e.g.
    another rotor inertia: it must be the scenario's robot, by name).
    """
    from qpnso.control.config import ControllerConfig
    from qpnso.control.controller import Controller
    from qpnso.lab.simulation import simulate

    sc = load_scenario(name)
    if robot is not None and robot.name != sc.robot:
        raise ConfigError(f"scenario {sc.name} is for robot {sc.robot!r}, got {robot.name!r}")
    robot = robot or load_robot(sc.robot)
    values = {**sc.controller, **({"obstacles": sc.obstacles} if sc.obstacles else {}), **(settings or {})}
    if strategy is not None:
        values["strategy"] = strategy
    from qpnso.lab.simulation import SimulationConfig
    from qpnso.lab.surgeon import Subject

    sim = simulation or SimulationConfig(surgeon=Subject.from_dict(sc.surgeon))
    motion = sc.motion(sim.surgeon.speed_scale).start(duration_scale)
    config = ControllerConfig.from_dict(values)
    room = config.obstacles
    if ignore_obstacles:
        config = replace(config, obstacles=())
    return simulate(Controller(robot, config), motion, sc.start(robot), sim, progress=progress, room=room)
