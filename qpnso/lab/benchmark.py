"""Timing benchmarks: measured, never assumed.  Medians and tails in microseconds.

``qpnso bench cost`` times ``cost.value`` + ``cost.gradient``;
``qpnso bench tick`` times ``Controller.step`` for every strategy with the tool held and with the tool
moving on :class:`MovingTarget` (a 5 cm circle at 0.5 Hz and a rotation, the twist changing every tick),
the held ``qp`` tick also with four obstacles around the arm (:func:`obstacles_around`), beside Pink's
``solve_ik`` (``pin-pink``, ProxQP) and mink's (``mink``, DAQP) on the same targets when they are installed,
all rows taken in turns (:func:`interleaved`).  Compiled CasADi code is awaited
before timing, so the figures are the steady state of a control loop.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import pinocchio as pin

from qpnso.model.collision import has_capsules, link_capsules
from qpnso.model.costs import CostModel, CostWeights
from qpnso.model.obstacles import Box, Capsule, Obstacle, Sphere
from qpnso.model.robot import Robot


@dataclass
class Timing:
    """Per-call times of one benchmark row, in seconds."""

    name: str
    seconds: np.ndarray
    note: str = ""

    @property
    def median_us(self) -> float:
        return float(np.median(self.seconds) * 1e6)

    @property
    def p99_us(self) -> float:
        return float(np.percentile(self.seconds, 99) * 1e6)

    def row(self) -> str:
        p95, p99, p999 = np.percentile(self.seconds, [95, 99, 99.9]) * 1e6
        return (
            f"| {self.name} | {self.median_us:.1f} | {p95:.1f} | {p99:.1f} | {p999:.1f} | {len(self.seconds)} | "
            f"{self.note} |"
        )


def time_calls(fn: Callable[[int], object], n: int, warmup: int = 50) -> np.ndarray:
    """Seconds of each of ``n`` calls ``fn(i)`` after ``warmup`` untimed ones."""
    for i in range(warmup):
        fn(i)
    out = np.empty(n)
    for i in range(n):
        t0 = time.perf_counter()
        fn(i)
        out[i] = time.perf_counter() - t0
    return out


def table(timings: list[Timing], title: str) -> str:
    head = "| what | median µs | p95 µs | p99 µs | p99.9 µs | calls | note |"
    lines = [f"### {title}", "", head, "|---|---|---|---|---|---|---|"]
    return "\n".join(lines + [t.row() for t in timings])


def bench_cost(robot: Robot, n: int = 5000, seed: int = 0) -> list[Timing]:
    """``value`` + ``gradient`` (mass + friction force weights) at random configurations."""
    rng = np.random.default_rng(seed)
    qs = [robot.random_q(rng, margin=0.1) for _ in range(64)]
    from qpnso.model.codegen import compile_mode

    out = []
    for mode in ("background", "off") if compile_mode() != "off" else ("off",):
        cost = CostModel(robot, CostWeights(mass=1, friction_force=1), compile=mode)
        compiled = cost.wait_compiled()
        note = "compiled C" if compiled else "CasADi VM"

        def call(i: int, cost=cost) -> None:
            q = qs[i % len(qs)]
            cost.value(q)
            cost.gradient(q)

        out.append(Timing(f"value + gradient ({note})", time_calls(call, n), note="two calls"))

        def both(i: int, cost=cost) -> None:
            cost.value_and_gradient(qs[i % len(qs)])

        out.append(Timing(f"value_and_gradient ({note})", time_calls(both, n), note="one call"))
    return out


def bench_interval(robot: Robot, n: int = 1000, seed: int = 0) -> list[Timing]:
    """``continuity_interval`` at ``n`` random configurations within the limits."""
    from qpnso.elbow.intervals import continuity_interval
    from qpnso.errors import QpnsoError

    rng = np.random.default_rng(seed)
    qs: list[np.ndarray] = []
    while len(qs) < n:
        q = robot.random_q(rng, margin=0.05)
        try:
            continuity_interval(robot, q)
        except QpnsoError:  # singular arm angle: not a timing case
            continue
        qs.append(q)
    return [
        Timing(
            "continuity_interval",
            time_calls(lambda i: continuity_interval(robot, qs[i % n]), n, warmup=20),
            note="random q",
        )
    ]


def held_tool_ticks(ctrl, q0: np.ndarray) -> Callable[[int], np.ndarray]:
    """A run with the tool held from ``q0`` (already reset), advanced by ``k`` ticks per call:
    returns the seconds of each ``step``, integrating ``q ← q + dt·dq`` across calls."""
    q = q0.copy()
    dt = ctrl.config.dt

    def ticks(k: int) -> np.ndarray:
        nonlocal q
        times = np.empty(k)
        for i in range(k):
            t0 = time.perf_counter()
            cmd = ctrl.step(q)
            times[i] = time.perf_counter() - t0
            q = q + dt * cmd.dq
        return times

    return ticks


@dataclass(frozen=True)
class MovingTarget:
    """The tool's moving target, relative to its start pose (world frame): its point on a horizontal circle of
    ``radius`` m at ``frequency`` Hz (starting at the start point, 0.157 m/s at the defaults) and its orientation
    turning about the world's vertical by ``rotation·sin(2π f t)`` rad.  Its twist changes every tick."""

    radius: float = 0.05
    frequency: float = 0.5
    rotation: float = 0.2

    def twist(self, t: float) -> np.ndarray:
        """The tool twist at ``t`` s: linear (m/s) then angular (rad/s) velocity, world frame."""
        w = 2.0 * math.pi * self.frequency
        v = self.radius * w
        return np.array([-v * math.sin(w * t), v * math.cos(w * t), 0.0, 0.0, 0.0, self.rotation * w * math.cos(w * t)])

    def pose(self, t: float, p0: np.ndarray, R0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The target pose at ``t`` s from the start pose ``(p0, R0)`` (m, rotation matrix; world frame): the
        integral of :meth:`twist` (the controller's reference follows it to the integration error of dt)."""
        w = 2.0 * math.pi * self.frequency
        p = p0 + self.radius * np.array([math.cos(w * t) - 1.0, math.sin(w * t), 0.0])
        a = self.rotation * math.sin(w * t)
        Rz = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
        return p, Rz @ R0


def moving_tool_ticks(ctrl, q0: np.ndarray, target: MovingTarget = MovingTarget()) -> Callable[[int], np.ndarray]:
    """As :func:`held_tool_ticks`, with the tool following ``target``'s twist, so the continuity interval is
    renewed every ``interval_period`` ticks (docs/method.md §5) as in hands-on use."""
    q = q0.copy()
    dt = ctrl.config.dt
    k_total = 0

    def ticks(k: int) -> np.ndarray:
        nonlocal q, k_total
        times = np.empty(k)
        for i in range(k):
            twist = target.twist(k_total * dt)
            t0 = time.perf_counter()
            cmd = ctrl.step(q, tool_twist=twist)
            times[i] = time.perf_counter() - t0
            q = q + dt * cmd.dq
            k_total += 1
        return times

    return ticks


def interleaved(runs: dict[str, Callable[[int], np.ndarray]], n: int, chunk: int = 500) -> dict[str, np.ndarray]:
    """``n`` timed calls of each run, taken in turns of ``chunk``: every row sees the same
    machine (on a shared VM its speed drifts by 2× over seconds, measured)."""
    out: dict[str, list] = {name: [] for name in runs}
    for start in range(0, n, chunk):
        for name, run in runs.items():
            out[name].append(run(min(chunk, n - start)))
    return {name: np.concatenate(parts) for name, parts in out.items()}


def bench_tick(robot: Robot, n: int = 3000, strategies: tuple[str, ...] | None = None) -> list[Timing]:
    """``Controller.step`` per strategy from the sample configuration, the tool held and the tool moving
    (:class:`MovingTarget`), with Pink's and mink's ``solve_ik`` on the same held and moving targets when
    installed; the rows are timed in turns (:func:`interleaved`)."""
    from qpnso.control.config import STRATEGIES, ControllerConfig
    from qpnso.control.controller import Controller

    strategies = strategies or STRATEGIES
    q0 = robot.sample_configuration()
    runs, notes = {}, {}
    rows_of = {}  # (the obstacle row's controller: its keep-out rows are counted after the timing)
    for motion, make in (("held", held_tool_ticks), ("moving", moving_tool_ticks)):
        for name in strategies:
            ctrl = _ready(Controller(robot, ControllerConfig(strategy=name)), q0)
            row = f"step, strategy {name}, tool {motion}"
            runs[row], notes[row] = make(ctrl, q0), f"tool {motion}"
            if name == "qp" and motion == "held" and has_capsules(robot):
                around = obstacles_around(robot, q0)
                ctrl = _ready(Controller(robot, ControllerConfig(strategy=name, obstacles=around)), q0)
                row = f"step, strategy {name}, tool {motion}, {len(around)} obstacles"
                runs[row], rows_of[row] = make(ctrl, q0), ctrl
        for peer, make_peer in (("Pink", pink_ticks), ("mink", mink_ticks)):
            made = make_peer(robot, q0, MovingTarget() if motion == "moving" else None)
            if made is not None:
                row = f"{peer} solve_ik (FrameTask + PostureTask), tool {motion}"
                runs[row], notes[row] = made
    for run in runs.values():
        run(200)  # warm-up
    timed = interleaved(runs, n)
    for row, ctrl in rows_of.items():
        notes[row] = f"tool held, {int(ctrl.records.report[0]['obstacle_rows'])} keep-out rows (last tick)"
    return [Timing(name, seconds, note=notes[name]) for name, seconds in timed.items()]


def _ready(ctrl, q0: np.ndarray):
    """``ctrl`` with its compiled code awaited, reset at ``q0`` (rad)."""
    ctrl.cost.wait_compiled()
    ctrl.evaluate.wait_compiled()
    ctrl.reset(q0)
    return ctrl


OBSTACLE_GAP = 0.08
"""m: how far :func:`obstacles_around` puts each obstacle's surface from its link's capsule: inside the default
influence distance (0.15 m), clear of the default margin (0.03 m)."""


def obstacles_around(robot: Robot, q: np.ndarray, gap: float = OBSTACLE_GAP) -> tuple[Obstacle, ...]:
    """Four obstacles around the arm at ``q`` (rad), world frame, each ``gap`` m from one link capsule's surface
    along the normal ``n`` of the plane of the last three links (upper arm, forearm, hand for the LWR4+): a
    0.1 m cube beside the middle of link capsule 1 (the upper arm) on the ``+n`` side, one beside capsule 2 (the
    forearm) on ``-n``, each turned to lie along its link; a sphere of 0.04 m radius beside the middle of the last
    capsule (the hand) on ``+n``; a rod (capsule of 0.03 m radius) parallel to capsule 0 (the base) on ``-n``."""
    caps = link_capsules(robot)
    a, b = caps.segments(robot, q)
    u = (b - a) / np.linalg.norm(b - a, axis=1)[:, None]
    n = np.cross(u[-3], u[-2])
    n /= np.linalg.norm(n)
    mid = 0.5 * (a + b)

    def off(k: int, side: float, size: float) -> np.ndarray:
        return side * (caps.radius[k] + gap + size) * n

    def cube(k: int, side: float) -> Box:
        rot = np.column_stack([u[k], n, np.cross(u[k], n)])
        return Box(center=tuple(mid[k] + off(k, side, 0.05)), half_extents=(0.05, 0.05, 0.05), rotation=rot.tolist())

    last = caps.count - 1
    return (
        cube(1, 1.0),
        cube(2, -1.0),
        Sphere(center=tuple(mid[last] + off(last, 1.0, 0.04)), radius=0.04),
        Capsule(a=tuple(a[0] + off(0, -1.0, 0.03)), b=tuple(b[0] + off(0, -1.0, 0.03)), radius=0.03),
    )


def pink_ticks(robot: Robot, q0: np.ndarray, target: MovingTarget | None = None) -> tuple[PeerRun, str] | None:
    """Pink's ``solve_ik`` with a FrameTask on the tool frame and a PostureTask (same robot, ProxQP), if
    installed, the frame's target held or, with ``target``, set each call to the pose the tool should reach
    by the end of the tick: a run advanced by ``k`` calls per call (seconds of each), and its note."""
    try:
        import pink
        from pink.tasks import FrameTask, PostureTask
    except ImportError:
        return None
    config = pink.Configuration(robot.model, robot.model.createData(), q0)
    tool = robot.model.frames[robot.tool_frame_id].name
    frame_task = FrameTask(tool, position_cost=1.0, orientation_cost=1.0)
    posture = PostureTask(cost=1e-3)
    start = config.get_transform_frame_to_world(tool)
    p0, R0 = start.translation.copy(), start.rotation.copy()
    frame_task.set_target(start)
    posture.set_target(q0)
    tasks = [frame_task, posture]

    def step(dt: float) -> None:
        config.integrate_inplace(pink.solve_ik(config, tasks, dt, solver="proxqp"), dt)

    run = PeerRun(
        step,
        lambda R, p: frame_task.set_target(pin.SE3(R, p)),
        (R0, p0, target),
        lambda: config.get_transform_frame_to_world(tool),
    )
    return run, f"pink {_version('pin-pink')}, proxqp, pin {pin.__version__}"


def mink_ticks(robot: Robot, q0: np.ndarray, target: MovingTarget | None = None) -> tuple[PeerRun, str] | None:
    """mink's ``solve_ik`` (DAQP) with a FrameTask on a site at the tool point and a PostureTask, on MuJoCo's
    model of the same URDF (fixed links fused; the site placed on the last joint's body as Pinocchio's tool
    frame is), targets as :func:`pink_ticks`'; None when mink is not installed or MuJoCo cannot read the URDF."""
    try:
        import mink
        import mujoco
    except ImportError:
        return None
    from qpnso.errors import ModelError
    from qpnso.lab.plant import TOOL_SITE, tool_site_spec

    try:
        spec = tool_site_spec(robot)
    except ModelError:  # (a URDF whose meshes MuJoCo cannot find, or without the tool's joint: no mink row)
        return None
    configuration = mink.Configuration(spec.compile())
    configuration.update(q0)
    frame_task = mink.FrameTask(TOOL_SITE, "site", position_cost=1.0, orientation_cost=1.0)
    posture = mink.PostureTask(configuration.model, cost=1e-3)
    start = configuration.get_transform_frame_to_world(TOOL_SITE, "site")
    p0, R0 = start.translation().copy(), start.rotation().as_matrix().copy()
    frame_task.set_target(start)
    posture.set_target(q0)
    tasks = [frame_task, posture]

    def step(dt: float) -> None:
        configuration.integrate_inplace(mink.solve_ik(configuration, tasks, dt, solver="daqp"), dt)

    def tool_pose() -> pin.SE3:
        pose = configuration.get_transform_frame_to_world(TOOL_SITE, "site")
        return pin.SE3(pose.rotation().as_matrix(), pose.translation())

    def set_target(R: np.ndarray, p: np.ndarray) -> None:
        frame_task.set_target(mink.SE3.from_rotation_and_translation(mink.SO3.from_matrix(R), p))

    run = PeerRun(step, set_target, (R0, p0, target), tool_pose)
    return run, f"mink {_version('mink')}, daqp, mujoco {mujoco.__version__}"


class PeerRun:
    """A peer's IK loop as a benchmark run: ``run(k)`` makes ``k`` more ticks of 1 ms and returns the seconds of
    each; a tick sets the peer's frame target (``set_target(R, p)``) to ``target``'s pose at the tick's end from
    the start pose ``(R0, p0)`` (``target`` None: the start pose is held), then ``step(dt)`` solves and integrates;
    ``tool_pose()`` is where the peer's tool is (world frame)."""

    def __init__(
        self,
        step: Callable[[float], None],
        set_target: Callable[[np.ndarray, np.ndarray], None],
        start: tuple[np.ndarray, np.ndarray, MovingTarget | None],
        tool_pose: Callable[[], pin.SE3],
    ) -> None:
        self._step, self._set_target, self.tool_pose = step, set_target, tool_pose
        self._R0, self._p0, self._target = start
        self._done = 0

    def _tick(self, i: int) -> None:
        dt = 1e-3
        if self._target is not None:
            p, R = self._target.pose((i + 1) * dt, self._p0, self._R0)
            self._set_target(R, p)
        self._step(dt)

    def __call__(self, k: int) -> np.ndarray:
        seconds = time_calls(lambda i: self._tick(self._done + i), k, warmup=0)
        self._done += k
        return seconds


def _version(package: str) -> str:
    """An installed package's version."""
    from importlib.metadata import version

    return version(package)
