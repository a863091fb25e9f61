"""The run: :class:`Fuzzer` builds the robot and one cached controller per strategy, then runs episodes
until the ticks asked for are done (or the wall-time limit); :func:`run_fuzz` is the entry point and
:func:`realtime_gc` freezes the garbage collector for the run, as a real-time loop does.
"""

from __future__ import annotations

import contextlib
import gc
import math
import time
from dataclasses import replace
from typing import Iterator

from qpnso.control.config import ControllerConfig
from qpnso.control.controller import Controller
from qpnso.lab.fuzz.checker import TickChecker
from qpnso.lab.fuzz.config import FuzzConfig, Observer, Progress, Where
from qpnso.lab.fuzz.episode import Episode, SolverClock
from qpnso.lab.fuzz.report import FuzzReport
from qpnso.model.robot import load_robot


class Fuzzer:
    """The run: the robot, a cached controller per strategy, the checker and the report."""

    def __init__(self, config: FuzzConfig, observe: Observer | None = None) -> None:
        self.config, self.observe = config, observe
        self.robot = load_robot(config.robot, tool_frame=config.tool_frame, tool_offset=list(config.tool_offset))
        self.report = FuzzReport(config)
        self.checker = TickChecker(self.robot, config, self.report)
        self._controllers: dict[str, Controller] = {}
        self.clocks: dict[str, SolverClock] = {}  # each controller's solver CPU time

    def controller(self, strategy: str) -> Controller:
        """The strategy's controller, built once (its constructor compiles or loads the Numba kernels)."""
        ctrl = self._controllers.get(strategy)
        if ctrl is None:
            t0 = time.perf_counter()
            ctrl = Controller(
                self.robot,
                ControllerConfig(
                    strategy=strategy, compile=self.config.compile, solver_time_budget=self.config.solver_time_budget
                ),
            )
            ctrl.cost.wait_compiled()
            ctrl.evaluate.wait_compiled()
            self.report.build_seconds[strategy] = time.perf_counter() - t0
            self.checker.dt = ctrl.config.dt
            self.checker.correction_speed = ctrl.config.pose_correction_speed
            self._controllers[strategy] = ctrl
            self.clocks[strategy] = SolverClock(ctrl.qp)
        return ctrl

    def run(self, progress: Progress | None = None) -> FuzzReport:
        """Every episode; with ``freeze_gc`` the controllers are built first and the garbage collector's
        generations frozen for the run (:func:`realtime_gc`, as a real-time loop does), then unfrozen."""
        cfg = self.config
        if not cfg.freeze_gc:
            return self._run(progress)
        for strategy in cfg.strategies:
            self.controller(strategy)
        with realtime_gc():
            return self._run(progress)

    def replay_slow(self) -> None:
        """Each tick over ``solve_time_max`` of solver CPU time (the check "solve_time") whose episode is
        replayed ``config.replays`` times on the same controllers (reset at each episode's start, so each replay
        runs the same ticks): counted in "solve_time_reproduced" when every replay has the same tick over
        ``solve_time_max`` of solver CPU time again.  A slow tick that the code causes is slow every time; one
        that the machine causes (another process, the hypervisor) is not."""
        cfg, rep = self.config, self.report
        replays: dict[tuple[int, str], list[dict[int, float]]] = {}  # (episode, strategy) → each replay's slow ticks
        for where, _ in rep.slow:
            key = (where.episode, where.strategy)
            if key not in replays:  # (an episode with several slow ticks is replayed once for all of them)
                replays[key] = [self._replayed_slow_ticks(where) for _ in range(cfg.replays)]
            again = replays[key]
            if cfg.replays and all(where.tick in ticks for ticks in again):
                rep.record("solve_time_reproduced", again[-1][where.tick], where, {}, f"reproduced in {cfg.replays}")

    def _replayed_slow_ticks(self, where: Where) -> dict[int, float]:
        """One replay of ``where``'s episode alone: its ticks over ``solve_time_max`` of solver CPU time
        (tick → solver wall time, s)."""
        cfg = self.config
        replay = Fuzzer(
            replace(cfg, first_episode=where.episode, ticks=cfg.episode_ticks, strategies=(where.strategy,), replays=0)
        )
        replay.robot, replay._controllers, replay.clocks = self.robot, self._controllers, self.clocks
        replay.checker = TickChecker(self.robot, replay.config, replay.report)
        replay.checker.dt, replay.checker.correction_speed = self.checker.dt, self.checker.correction_speed
        Episode(replay, where.episode, cfg.episode_ticks).run(lambda: None, math.inf)
        return {w.tick: seconds for w, seconds in replay.report.slow}

    def _run(self, progress: Progress | None) -> FuzzReport:
        cfg, rep = self.config, self.report
        t0 = time.perf_counter()
        deadline = math.inf if cfg.max_seconds is None else t0 + cfg.max_seconds
        index = cfg.first_episode

        def tick_done() -> None:
            if progress is not None:
                progress(rep.ticks, cfg.ticks)

        while rep.ticks < cfg.ticks:
            if time.perf_counter() > deadline:
                break
            before = rep.ticks
            Episode(self, index, min(cfg.episode_ticks, cfg.ticks - rep.ticks)).run(tick_done, deadline)
            rep.episodes += 1
            index += 1
            if rep.ticks == before and rep.episodes > 10 * (1 + cfg.ticks // cfg.episode_ticks):
                break  # every start refused: nothing more to learn
        rep.completed = rep.ticks >= cfg.ticks
        self.replay_slow()
        rep.wall_seconds = time.perf_counter() - t0
        return rep


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
    """Run ``config.ticks`` fuzzed closed-loop ticks (the package doc, :mod:`qpnso.lab.fuzz`);
    ``progress(done, total)`` after each tick; ``observe(where, inputs, cmd, error)`` after each valid tick
    (``cmd`` None when it raised; ``error`` the tool's pose error (m, rad) at its start), to trace an episode."""
    return Fuzzer(config, observe).run(progress)
