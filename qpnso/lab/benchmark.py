"""Timing benchmarks: measured, never assumed.  Medians and p99 in microseconds.

``qpnso bench cost`` times ``cost.value`` + ``cost.gradient``;
``qpnso bench tick`` times ``Controller.step`` for every strategy (and Pink's
``solve_ik`` for reference when ``pin-pink`` is installed).  Compiled CasADi
code is awaited before timing, so the figures are the steady state of a
control loop.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from qpnso.model.costs import CostModel, CostWeights
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
        return f"| {self.name} | {self.median_us:.1f} | {self.p99_us:.1f} | {len(self.seconds)} | {self.note} |"


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
    lines = [f"### {title}", "", "| what | median µs | p99 µs | calls | note |", "|---|---|---|---|---|"]
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


def moving_tool_ticks(ctrl, q0: np.ndarray, speed: float = 0.05, period: float = 2.0) -> Callable[[int], np.ndarray]:
    """As :func:`held_tool_ticks`, with the tool moving: its point on a horizontal circle at ``speed`` m/s,
    one turn per ``period`` s (radius ``speed·period/2π``: 1.6 cm at the defaults), so the continuity
    interval is renewed every ``interval_period`` ticks (docs/method.md §5) as in hands-on use."""
    q = q0.copy()
    dt = ctrl.config.dt
    k_total = 0

    def ticks(k: int) -> np.ndarray:
        nonlocal q, k_total
        times = np.empty(k)
        for i in range(k):
            phase = 2.0 * np.pi * k_total * dt / period
            twist = np.array([-speed * np.sin(phase), speed * np.cos(phase), 0.0, 0.0, 0.0, 0.0])
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
    """``Controller.step`` per strategy, tool held, from the sample configuration, with Pink's
    ``solve_ik`` for reference when installed; the rows are timed in turns (:func:`interleaved`)."""
    from qpnso.control.config import STRATEGIES, ControllerConfig
    from qpnso.control.controller import Controller

    strategies = strategies or STRATEGIES
    q0 = robot.sample_configuration()
    runs, notes = {}, {}
    for name in strategies:
        ctrl = Controller(robot, ControllerConfig(strategy=name))
        ctrl.cost.wait_compiled()
        ctrl.evaluate.wait_compiled()
        ctrl.reset(q0)
        row = f"step, strategy {name}"
        runs[row] = held_tool_ticks(ctrl, q0)
        notes[row] = "tool held"
    pink = pink_ticks(robot, q0)
    if pink is not None:
        runs["Pink solve_ik (FrameTask + PostureTask)"], notes["Pink solve_ik (FrameTask + PostureTask)"] = pink
    for run in runs.values():
        run(200)  # warm-up
    return [Timing(name, seconds, note=notes[name]) for name, seconds in interleaved(runs, n).items()]


def pink_ticks(robot: Robot, q0: np.ndarray) -> tuple[Callable[[int], np.ndarray], str] | None:
    """Pink's ``solve_ik`` with a FrameTask and a PostureTask (same robot, ProxQP), if installed:
    a run advanced by ``k`` calls per call (seconds of each), and its note."""
    try:
        import pink
        from pink.tasks import FrameTask, PostureTask
    except ImportError:
        return None
    import pinocchio as pin

    config = pink.Configuration(robot.model, robot.model.createData(), q0)
    tool = robot.model.frames[robot.tool_frame_id].name
    frame_task = FrameTask(tool, position_cost=1.0, orientation_cost=1.0)
    posture = PostureTask(cost=1e-3)
    frame_task.set_target(config.get_transform_frame_to_world(tool))
    posture.set_target(q0)
    tasks = [frame_task, posture]

    def call(i: int) -> None:
        v = pink.solve_ik(config, tasks, 1e-3, solver="proxqp")
        config.integrate_inplace(v, 1e-3)

    return (lambda k: time_calls(call, k, warmup=0)), f"pink, proxqp, pin {pin.__version__}"
