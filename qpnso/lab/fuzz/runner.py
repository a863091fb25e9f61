"""The run: :class:`Fuzzer` loads the robots and builds one cached controller per robot, dt and strategy, then
runs episodes until the ticks asked for are done (or the wall-time limit); :func:`run_fuzz` is the entry point.
With ``workers`` the episodes run in shards, each in a fresh (spawned) process (:func:`run_shard`), and the
slow ticks' episodes are replayed in fresh processes too (:func:`replay_in_fresh_process`): a kernel compiled
or loaded inside a tick happens once per process, so only a new process shows it, and shows it again.
:func:`realtime_gc` freezes the garbage collector for the run, as a real-time loop does.
"""

from __future__ import annotations

import contextlib
import gc
import importlib
import math
import multiprocessing
import time
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from dataclasses import dataclass, replace
from typing import Callable, Iterator

from qpnso.control.config import ControllerConfig
from qpnso.control.controller import Controller
from qpnso.errors import ConfigError, RobotNotFoundError
from qpnso.lab.fuzz.checker import TickChecker
from qpnso.lab.fuzz.config import FuzzConfig, Observer, Progress
from qpnso.lab.fuzz.episode import Episode, SolverClock
from qpnso.lab.fuzz.kernels import KernelWatch
from qpnso.lab.fuzz.report import FuzzReport
from qpnso.model.robot import OPTIONAL_ROBOTS, Robot, load_robot

Setting = tuple[str, float, str]  # robot, dt (s), strategy


@dataclass
class Replay:
    """One replay of one episode: its ticks of the check "solve_time" (tick → solve time, s), each valid tick's
    whole-step CPU time (s) and the kernel signatures each tick added."""

    slow: dict[int, float]
    tick_cpu: list[float]
    kernels: dict[int, list[str]]


class Fuzzer:
    """The run in one process: the robots, a cached controller per setting, a checker per robot, the kernels'
    baseline and the report."""

    def __init__(self, config: FuzzConfig, observe: Observer | None = None) -> None:
        self.config, self.observe = config, observe
        self.report = FuzzReport(config)
        self._robots: dict[str, Robot] = {}
        self._checkers: dict[str, TickChecker] = {}
        self._controllers: dict[Setting, Controller] = {}
        self.clocks: dict[Setting, SolverClock] = {}  # each controller's solver CPU time
        self.kernels = KernelWatch()

    def robot(self, name: str) -> Robot:
        if name not in self._robots:
            cfg = self.config
            self._robots[name] = load_robot(name, tool_frame=cfg.tool_frame, tool_offset=list(cfg.tool_offset))
        return self._robots[name]

    def checker(self, robot: str) -> TickChecker:
        """The robot's independent checker (its own Pinocchio data), reporting to this run's report."""
        if robot not in self._checkers:
            self._checkers[robot] = TickChecker(self.robot(robot), self.config, self.report)
        return self._checkers[robot]

    def controller(self, robot: str, dt: float, strategy: str) -> Controller:
        """The setting's controller, built once (its constructor compiles or loads the Numba kernels: the
        kernels' signatures after it are the baseline that nothing may add to)."""
        key = (robot, dt, strategy)
        ctrl = self._controllers.get(key)
        if ctrl is None:
            cfg = self.config
            t0 = time.perf_counter()
            ctrl = Controller(
                self.robot(robot),
                ControllerConfig(
                    dt=dt,
                    strategy=strategy,
                    compile=cfg.compile,
                    solver_time_budget=cfg.solver_time_budget,
                    ddq_max=cfg.ddq_max,
                ),
            )
            ctrl.cost.wait_compiled()
            ctrl.evaluate.wait_compiled()
            self.report.build_seconds[f"{robot} dt {1e3 * dt:g} ms {strategy}"] = time.perf_counter() - t0
            self._controllers[key] = ctrl
            self.clocks[key] = SolverClock(ctrl.qp)
            self.kernels.rebase()
        return ctrl

    @contextlib.contextmanager
    def realtime(self, settings: list[Setting]) -> Iterator[None]:
        """With ``freeze_gc``: the settings' controllers built first, then :func:`realtime_gc` for the block."""
        if not self.config.freeze_gc:
            yield
            return
        for setting in settings:
            self.controller(*setting)
        with realtime_gc():
            yield

    def run(self, progress: Progress | None = None) -> FuzzReport:
        """Every episode in this process from ``first_episode`` on, then each slow tick's episode replayed on the
        same controllers (:func:`replay_slow`)."""
        cfg = self.config
        t0 = time.perf_counter()
        deadline = math.inf if cfg.max_seconds is None else t0 + cfg.max_seconds
        report = self.run_episodes(cfg.first_episode, 1, cfg.ticks, progress, deadline)
        with self.realtime([]):  # (the controllers are built: the collector frozen again for the replays)
            replay_slow(report, lambda eps: {e: [self.replay_here(e) for _ in range(cfg.replays)] for e in eps})
        report.wall_seconds = time.perf_counter() - t0
        return report

    def run_episodes(
        self, first: int, stride: int, ticks: int, progress: Progress | None = None, deadline: float = math.inf
    ) -> FuzzReport:
        """Episodes ``first, first + stride, ...`` until ``ticks`` valid ticks are done (or ``deadline``,
        ``time.perf_counter()``); the report says whether they were (``completed``)."""
        cfg, rep = self.config, self.report

        def tick_done() -> None:
            if progress is not None:
                progress(rep.ticks, ticks)

        index = first
        with self.realtime(cfg.settings_of(first, stride)):
            while rep.ticks < ticks and time.perf_counter() <= deadline:
                before = rep.ticks
                Episode(self, index, min(cfg.episode_ticks, ticks - rep.ticks)).run(tick_done, deadline)
                rep.episodes += 1
                index += stride
                if rep.ticks == before and rep.episodes > 10 * (1 + ticks // cfg.episode_ticks):
                    break  # every start refused: nothing more to learn
        rep.completed = rep.ticks >= ticks
        return rep

    def replay(self, episode: int) -> Replay:
        """Episode ``episode`` alone on this fuzzer (whose config is :func:`replay_config`'s)."""
        run = Episode(self, episode, self.config.episode_ticks)
        run.run(lambda: None, math.inf)
        return Replay({w.tick: seconds for w, seconds in self.report.slow}, run.cpu_by_tick, run.kernels_by_tick)

    def replay_here(self, episode: int) -> Replay:
        """Episode ``episode`` replayed in this process on this fuzzer's controllers (reset at the episode's start,
        so it runs the same ticks)."""
        again = Fuzzer(replay_config(self.config, episode))
        again._robots, again._controllers, again.clocks = self._robots, self._controllers, self.clocks
        return again.replay(episode)


def replay_config(config: FuzzConfig, episode: int) -> FuzzConfig:
    """The config that runs episode ``episode`` alone, in this process, with no replays of its own."""
    return replace(config, first_episode=episode, ticks=config.episode_ticks, replays=0, workers=0)


def replay_slow(report: FuzzReport, replay_many: Callable[[list[int]], dict[int, list[Replay]]]) -> None:
    """Each episode with a tick over ``solve_time_max`` of solver CPU time (the check "solve_time"), and the
    episode of the slowest whole tick (the check "tick_cpu"), replayed ``config.replays`` times by
    ``replay_many(episodes)`` (the slowest first, at most ``max_replayed_episodes``).  A slow tick counts in
    "solve_time_reproduced" when every replay has the same tick over ``solve_time_max`` of solver CPU time again:
    a slow tick that the code causes is slow every time, one that the machine causes (another process, the
    hypervisor) is not.  The slowest whole tick's time in each replay is kept (``worst_tick_replays``)."""
    cfg = report.config
    if not cfg.replays:
        return
    slowest: dict[int, float] = {}
    for where, seconds in report.slow:
        slowest[where.episode] = max(seconds, slowest.get(where.episode, 0.0))
    worst = report.worst.get("tick_cpu")
    if worst is not None:
        slowest[worst.where.episode] = math.inf  # (replayed first)
    episodes = sorted(slowest, key=lambda e: -slowest[e])
    chosen = episodes[: cfg.max_replayed_episodes]
    report.replays_skipped, report.replayed_episodes = len(episodes) - len(chosen), len(chosen)
    replays = replay_many(chosen) if chosen else {}
    place = "fresh processes" if report.replays_fresh else "this process"
    for where, _ in report.slow:
        again = replays.get(where.episode)
        if again and all(where.tick in r.slow for r in again):
            detail = f"reproduced in {len(again)} replays in {place}"
            report.record("solve_time_reproduced", again[-1].slow[where.tick], where, {}, detail)
    if worst is not None and worst.where.episode in replays:
        tick = worst.where.tick
        report.worst_tick_replays = [
            {"tick_cpu": r.tick_cpu[tick] if tick < len(r.tick_cpu) else None, "kernels": r.kernels.get(tick, [])}
            for r in replays[worst.where.episode]
        ]


# ----------------------------------------------------------------- fresh processes
def run_setup(config: FuzzConfig) -> None:
    """Call ``config.setup`` ("module:function", no arguments), if any: first in every fresh process."""
    if config.setup is None:
        return
    module, _, function = config.setup.partition(":")
    try:
        hook = getattr(importlib.import_module(module), function)
    except (ImportError, AttributeError, ValueError) as exc:
        raise ConfigError(f"setup {config.setup!r} is not an importable module:function ({exc})") from None
    hook()


def run_shard(config: FuzzConfig, shard: int, shards: int, ticks: int, deadline_epoch: float | None) -> FuzzReport:
    """Shard ``shard`` of ``shards`` in this (fresh) process: episodes ``first_episode + shard`` and every
    ``shards``-th after it, ``ticks`` valid ticks in all, until ``deadline_epoch`` (``time.time()``) if given."""
    run_setup(config)
    deadline = math.inf if deadline_epoch is None else time.perf_counter() + deadline_epoch - time.time()
    report = Fuzzer(config).run_episodes(config.first_episode + shard, shards, ticks, None, deadline)
    report.processes = 1
    return report


def replay_in_fresh_process(config: FuzzConfig, episode: int) -> Replay:
    """Episode ``episode`` alone in this (fresh) process: its controller built, the collector frozen, as in a
    shard."""
    run_setup(config)
    fuzzer = Fuzzer(replay_config(config, episode))
    with fuzzer.realtime([config.setting(episode)]):
        return fuzzer.replay(episode)


def fresh_processes(workers: int) -> ProcessPoolExecutor:
    """``workers`` processes at a time, each spawned for one task (nothing compiled or loaded before it)."""
    return ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"), max_tasks_per_child=1)


def run_in_workers(config: FuzzConfig, progress: Progress | None = None) -> FuzzReport:
    """The run in shards of about ``shard_ticks`` ticks (at least ``workers``), each in a fresh process,
    ``workers`` at a time; their reports added up in shard order; then the slow ticks' episodes replayed, each
    replay in a fresh process."""
    t0 = time.perf_counter()
    shards = max(config.workers, math.ceil(config.ticks / config.shard_ticks))
    budgets = [config.ticks // shards + (k < config.ticks % shards) for k in range(shards)]
    deadline = None if config.max_seconds is None else time.time() + config.max_seconds
    report = FuzzReport(config)
    with fresh_processes(config.workers) as pool:
        futures = {
            pool.submit(run_shard, config, k, shards, budget, deadline): k for k, budget in enumerate(budgets) if budget
        }
        parts: dict[int, FuzzReport] = {}
        for future in as_completed(futures):
            done = sum(p.ticks for p in parts.values())
            part = parts[futures[future]] = future.result()
            for tick in range(done + 1, done + part.ticks + 1):
                if progress is not None:
                    progress(tick, config.ticks)
        for k in sorted(parts):
            report.merge(parts[k])
        report.completed = report.ticks >= config.ticks
        report.replays_fresh = True
        replay_slow(report, lambda episodes: _replay_in_pool(pool, config, episodes))
    report.wall_seconds = time.perf_counter() - t0
    return report


def _replay_in_pool(pool: ProcessPoolExecutor, config: FuzzConfig, episodes: list[int]) -> dict[int, list[Replay]]:
    futures: dict[int, list[Future]] = {
        e: [pool.submit(replay_in_fresh_process, config, e) for _ in range(config.replays)] for e in episodes
    }
    return {e: [f.result() for f in fs] for e, fs in futures.items()}


# ---------------------------------------------------------------------- entry
def available_robots(config: FuzzConfig) -> tuple[FuzzConfig, dict[str, str]]:
    """The config without the optional robots that cannot be loaded here (the Panda without example-robot-data),
    and why each was left out; each other robot loaded once to refuse a bad name or tool frame before the run
    (a RobotNotFoundError or ModelError), and a RobotNotFoundError when no robot is left."""
    skipped: dict[str, str] = {}
    for name in config.robots:
        try:
            load_robot(name, tool_frame=config.tool_frame, tool_offset=list(config.tool_offset))
        except RobotNotFoundError as exc:
            if name not in OPTIONAL_ROBOTS:
                raise
            skipped[name] = str(exc)
    left = tuple(r for r in config.robots if r not in skipped)
    if not left:
        raise RobotNotFoundError(f"no robot to fuzz: {'; '.join(skipped.values())}")
    return (replace(config, robots=left) if skipped else config), skipped


@contextlib.contextmanager
def realtime_gc() -> Iterator[None]:
    """``gc.collect(); gc.freeze()`` for the block, ``gc.unfreeze()`` after: what a real-time loop does once
    its controllers are built.  A full collection scans every tracked object, and qpnso's dependencies leave
    about 130 000 (80 ms of CPU for one, measured; a young one took 1.4 ms): inside a tick it is a stall
    that no solver setting can prevent.  Frozen, 30 000 fuzzed ticks saw 6 young collections of at most
    0.07 ms (measured).  The README's real-time section says the same to users."""
    gc.collect()
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def run_fuzz(config: FuzzConfig, progress: Progress | None = None, observe: Observer | None = None) -> FuzzReport:
    """Run ``config.ticks`` fuzzed closed-loop ticks (the package doc, :mod:`qpnso.lab.fuzz`): in this process
    (``workers=0``) or in fresh worker processes; ``progress(done, total)`` after each tick (with workers, as each
    shard ends); ``observe(where, inputs, cmd, error)`` after each valid tick (``cmd`` None when it raised;
    ``error`` the tool's pose error (m, rad) at its start), to trace an episode (in this process only)."""
    config, skipped = available_robots(config)
    if config.workers == 0:
        report = Fuzzer(config, observe).run(progress)
    elif observe is not None:
        raise ConfigError("observe sees the ticks of this process: it needs workers=0")
    else:
        report = run_in_workers(config, progress)
    report.skipped_robots = skipped
    return report
