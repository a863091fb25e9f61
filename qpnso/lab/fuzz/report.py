"""What a fuzz run reports: the checks (:data:`CHECKS`, their must-hold lines), the worst and first
example of each violation, and :class:`FuzzReport` with its counters, percentiles, Markdown table and JSON.

Everything that counts a violation goes through :meth:`FuzzReport.record` (and :func:`record_exception`
for exceptions that are not a ``QpnsoError``), so the table and the exit status see the same numbers.
"""

from __future__ import annotations

import math
import traceback
from array import array
from dataclasses import asdict, dataclass, field, fields, replace

import numpy as np

from qpnso.lab.fuzz.config import FuzzConfig, Where


@dataclass(frozen=True)
class Check:
    """One check: ``key`` in the counters, ``text`` its line (formatted with the config; the must-hold
    lines are issue 13's and issue 31's), the unit of the worst value."""

    key: str
    text: str
    unit: str
    must_hold: bool = True  # False: counted and shown, not a failure
    fraction: str | None = None  # the FuzzConfig field of the fraction of valid ticks allowed (None: 0 allowed)


CHECKS = (
    Check("non_finite", "0 non-finite commands (dq, q_des, tau)", "entries"),
    Check("limit_crossing", "0 joint-limit crossings (q + dt·dq or q_des; from outside: not further out)", "rad"),
    Check("velocity", "0 commands above the velocity limits (abs(dq) ≤ dq_max + {joint_tol:g})", "× dq_max"),
    Check("torque", "0 torques above the effort limits (abs(tau) ≤ tau_limit)", "× tau_limit"),
    Check("foreign_exception", "0 exceptions that are not QpnsoError", ""),
    Check("valid_refused", "0 valid closed-loop ticks refused with a QpnsoError", ""),
    Check("bad_accepted", "every bad input refused with a QpnsoError", ""),
    Check("drift", "held-tool drift < {drift_tol_m:g} m / {drift_tol_rad:g} rad from non-singular starts", "m or rad"),
    Check(
        "solve_time",
        "ticks over {solve_time_max:g} s of solver time (cmd.solve_time, unless the solver "
        "used less CPU time than that: then the machine preempted it, counted below; each replayed, next line; "
        "reported, not a must-hold line)",
        "s",
        must_hold=False,
    ),
    Check(
        "solve_time_reproduced",
        "0 ticks over {solve_time_max:g} s of solver time that every one of {replays} replays of their episode "
        "reproduces (the same tick over {solve_time_max:g} s of solver CPU time again: the code, not the machine)",
        "s",
    ),
    Check(
        "preempted",
        "ticks over {solve_time_max:g} s of solver wall time in which the solver used less CPU "
        "time than that (time.thread_time: the machine, not the code; reported, not a must-hold line)",
        "s",
        must_hold=False,
    ),
    Check(
        "rom_excursion",
        "0 ticks with the arm angle outside ROM_t and moving away without "
        "ELBOW_SLACK/ROM_EMPTY (strategies {rom_strategies}; reported, not a must-hold line)",
        "rad",
        must_hold=False,
    ),
    Check(
        "recovery",
        "recovery to OK (cmd.ok, the tool within {recovery_tol_m:g} m or closing at ≥ half the "
        "capped correction speed) within {recovery_ticks} ticks after a disturbance that leaves a reachable "
        "reference",
        "ticks",
    ),
    Check(
        "tick_cpu",
        "whole-tick CPU time over {tick_cpu_max:g} s (time.thread_time_ns around Controller.step, in the process "
        "that ran the episode) on < {tick_cpu_fraction_max:.2%} of valid ticks (per robot and strategy below)",
        "s",
        fraction="tick_cpu_fraction_max",
    ),
    Check(
        "compile",
        "0 Numba kernel signatures added after the constructor (a kernel of a qpnso module compiled or loaded "
        "from the cache in a tick, a reset or a bad input)",
        "signatures",
    ),
    Check(
        "accel_bound",
        "0 ticks changing a joint's command by more than Controller.ddq_max·dt from the controller's previous "
        "command since its reset (tolerance {accel_rtol:g} relative + {accel_atol:g} rad/s)",
        "× ddq_max·dt",
    ),
    Check(
        "reversal",
        "0 ticks reversing a joint's command from beyond {reversal_speed:g} rad/s one way to beyond it the other "
        "way within {reversal_ticks} ticks",
        "rad/s",
    ),
)
CHECK_KEYS = tuple(c.key for c in CHECKS)


@dataclass
class Example:
    """The worst case of one check: its value, where, the input of the tick (rad, rad/s, m/s) and what was seen."""

    value: float
    where: Where
    input: dict
    detail: str = ""


def _jsonable(x: object) -> object:
    """Plain JSON data of an input (arrays as lists; non-finite and complex numbers as strings)."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (bool, np.bool_)) or x is None or isinstance(x, str):
        return bool(x) if isinstance(x, np.bool_) else x
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else str(float(x))
    return repr(x)


@dataclass
class FuzzReport:
    """Counters of every check (:data:`CHECKS`), the worst example of each, per-strategy and per-setting counts,
    the recovery distribution, bad-input outcomes and tick-time percentiles of one fuzz run (or of one shard:
    :meth:`merge` adds the shards up)."""

    config: FuzzConfig
    ticks: int = 0
    probes: int = 0
    episodes: int = 0
    counts: dict[str, int] = field(default_factory=lambda: dict.fromkeys(CHECK_KEYS, 0))
    worst: dict[str, Example] = field(default_factory=dict)
    first: dict[str, Example] = field(default_factory=dict)  # the first violation of each check (often the cause)
    by_strategy: dict[str, dict[str, int]] = field(default_factory=dict)
    by_setting: dict[str, dict[str, int]] = field(default_factory=dict)  # "robot, dt X ms": ticks and counts
    start_kinds: dict[str, int] = field(default_factory=dict)
    probe_outcomes: dict[str, dict[str, int]] = field(default_factory=dict)
    recovery: list[int] = field(default_factory=list)  # ticks to recover, every measured disturbance
    recovery_censored: int = 0  # the episode ended or another disturbance came first (< the limit)
    recovery_unreachable: int = 0  # over the limit but the reference was not reachable (not counted)
    recovery_elbow_undefined: int = 0  # over the limit, elbow dropped, the arm angle undefined at the held pose
    drift_checked: int = 0  # held ticks checked for drift (settled, not excused)
    kernels_added: dict[str, int] = field(
        default_factory=dict
    )  # signature → step calls that added it (check "compile")
    accel_checked: int = 0  # commands compared with the controller's previous one and its ddq_max·dt
    accel_unbounded: int = 0  # commands after another whose controller has no ddq_max (not checked)
    deadline_ticks: int = 0  # valid ticks whose cascade ran out of solver_time_budget (Status.QP_DEADLINE)
    episodes_cut: int = 0  # episodes cut short after episode_seconds
    processes: int = 0  # fresh processes that ran episodes (workers ≥ 1; 0: this process)
    replayed_episodes: int = 0  # episodes replayed (their slow ticks checked again), each config.replays times
    replays_skipped: int = 0  # episodes with a slow tick beyond max_replayed_episodes (not replayed)
    replays_fresh: bool = False  # whether the replays ran in fresh processes (else on this process's controllers)
    worst_tick_replays: list[dict] = field(default_factory=list)  # the worst tick_cpu tick in each replay
    skipped_robots: dict[str, str] = field(default_factory=dict)  # robot → why it did not run
    completed: bool | None = None  # after a run: whether it ran every tick asked for
    exceptions: list[dict] = field(default_factory=list)  # the first foreign exceptions with tracebacks
    build_seconds: dict[str, float] = field(default_factory=dict)  # "robot dt strategy": the slowest build
    wall_seconds: float = 0.0
    solve_times: array = field(default_factory=lambda: array("d"), repr=False)  # s, every valid tick
    tick_times: array = field(default_factory=lambda: array("d"), repr=False)
    tick_cpu: dict[str, array] = field(default_factory=dict, repr=False)  # "robot strategy": whole-step CPU (s)
    slow: list[tuple[Where, float]] = field(default_factory=list)  # every tick of the check "solve_time", its
    # solver time (s): replayed after the run

    max_exceptions_kept = 20

    def record(self, key: str, value: float, where: Where, inputs: dict, detail: str = "") -> None:
        """Count one violation of check ``key``; keep it as the worst example if its value is the largest."""
        self.counts[key] += 1
        for per in (self.by_strategy.setdefault(where.strategy, {}), self.by_setting.setdefault(_setting(where), {})):
            per[key] = per.get(key, 0) + 1
        best = self.worst.get(key)
        if best is None or value > best.value:
            self.worst[key] = Example(float(value), replace(where), _jsonable(inputs), detail)  # type: ignore[arg-type]
        if key not in self.first:
            self.first[key] = Example(float(value), replace(where), _jsonable(inputs), detail)  # type: ignore[arg-type]
        if key == "solve_time":
            self.slow.append((replace(where), float(value)))

    def count_tick(self, where: Where) -> None:
        self.ticks += 1
        for per in (self.by_strategy.setdefault(where.strategy, {}), self.by_setting.setdefault(_setting(where), {})):
            per["ticks"] = per.get("ticks", 0) + 1

    def count_probe(self, kind: str, outcome: str) -> None:
        self.probes += 1
        per = self.probe_outcomes.setdefault(kind, {})
        per[outcome] = per.get(outcome, 0) + 1

    def add_tick_cpu(self, where: Where, seconds: float) -> None:
        """A valid tick's whole-step CPU time (s), in its robot and strategy's group."""
        self.tick_cpu.setdefault(f"{where.robot} {where.strategy}", array("d")).append(seconds)

    # ------------------------------------------------------------ summaries
    def _stats(self, values: array | np.ndarray, limit: float) -> dict[str, float]:
        """p50, p99, p99.9, max (s), the count and fraction over ``limit`` (s) and the number of ``values``."""
        a = np.asarray(values, dtype=float)
        p50, p99, p999 = np.percentile(a, [50, 99, 99.9])
        over = int(np.count_nonzero(a > limit))
        return {
            "p50": float(p50),
            "p99": float(p99),
            "p99.9": float(p999),
            "max": float(a.max()),
            "over_max": over,
            "fraction_over": over / a.size,
            "n": int(a.size),
        }

    def percentiles(self) -> dict[str, dict[str, float]]:
        """Solver and whole-tick wall times (s, over ``solve_time_max``) and whole-tick CPU times (s, over
        ``tick_cpu_max``): p50, p99, p99.9, max and the count over; recovery ticks: p50, p99, max."""
        out: dict[str, dict[str, float]] = {}
        cpu = np.concatenate([np.asarray(v, dtype=float) for v in self.tick_cpu.values()] or [np.empty(0)])
        for name, values, limit in (
            ("solve_time", self.solve_times, self.config.solve_time_max),
            ("tick_time", self.tick_times, self.config.solve_time_max),
            ("tick_cpu_time", cpu, self.config.tick_cpu_max),
        ):
            if len(values):
                out[name] = self._stats(values, limit)
        if self.recovery:
            r = np.asarray(self.recovery, dtype=float)
            p50, p99 = np.percentile(r, [50, 99])
            out["recovery_ticks"] = {"p50": float(p50), "p99": float(p99), "max": float(r.max()), "n": int(r.size)}
        return out

    def tick_cpu_groups(self) -> dict[str, dict[str, float]]:
        """Whole-tick CPU time per robot and strategy (:meth:`_stats`, over ``tick_cpu_max``)."""
        return {k: self._stats(v, self.config.tick_cpu_max) for k, v in sorted(self.tick_cpu.items()) if len(v)}

    def violated(self, check: Check) -> bool:
        """Whether a must-hold line fails: any count, or for a ``fraction`` line a count of at least that fraction
        of the valid ticks."""
        n = self.counts[check.key]
        if not check.must_hold or not n:
            return False
        return check.fraction is None or n >= getattr(self.config, check.fraction) * max(self.ticks, 1)

    def failures(self) -> list[str]:
        """Every must-hold line violated, with its count and worst example; and a run that stopped short."""
        out = []
        if self.completed is False:
            out.append(
                f"the run stopped after {self.ticks} of {self.config.ticks} ticks "
                f"({self.wall_seconds:.0f} s; max_seconds {self.config.max_seconds})"
            )
        for check in CHECKS:
            if self.violated(check):
                n = self.counts[check.key]
                ex = self.worst.get(check.key)
                worst = f"; worst {ex.value:.4g} {check.unit} ({ex.where.short()}){_detail(ex)}" if ex else ""
                share = f" ({n / max(self.ticks, 1):.3%} of {self.ticks} ticks)" if check.fraction else ""
                out.append(f"{self._text(check)}: {n} violations{share}{worst}")
        return out

    def _text(self, check: Check) -> str:
        return check.text.format(**asdict(self.config))

    def _count_cell(self, check: Check) -> str:
        n = self.counts[check.key]
        if check.key == "accel_bound" and not self.accel_checked:
            return f"not checked: the controller has no ddq_max ({self.accel_unbounded} commands)"
        if check.fraction:
            return f"{n} ({n / max(self.ticks, 1):.3%})"
        return str(n)

    def table(self) -> str:
        """Markdown: one row per check (count, worst example), then timings (whole-tick CPU per robot and
        strategy), the worst tick and its replays, recovery and bad inputs."""
        cfg = self.config
        lines = [
            f"### qpnso fuzz: {self.ticks} ticks, {self.probes} bad inputs, {self.episodes} episodes, "
            f"seed {cfg.seed}, robots {','.join(cfg.robots)}, dt {','.join(f'{1e3 * dt:g}' for dt in cfg.dts)} ms, "
            f"strategies {','.join(cfg.strategies)}"
            + (", garbage collector frozen after the controllers were built (realtime_gc)" if cfg.freeze_gc else "")
            + (f"; {self.processes} fresh processes" if self.processes else "; in one process"),
            "",
        ]
        skipped = [f"SKIPPED robot {name}: {why}" for name, why in self.skipped_robots.items()]
        lines += [*skipped, *([""] if skipped else []), "| check | count | worst |", "|---|---|---|"]
        for check in CHECKS:
            ex = self.worst.get(check.key)
            worst = f"{ex.value:.4g} {check.unit}: {ex.where.short()}{_detail(ex)}" if ex else "—"
            lines.append(f"| {self._text(check)} | {self._count_cell(check)} | {worst.replace('|', '/')} |")
        lines += [
            f"added after the constructor ({n}×, at most once a process): {signature}"
            for signature, n in sorted(self.kernels_added.items())
        ]
        lines += self._time_tables() + self._worst_tick_lines()
        pct = self.percentiles()
        r = pct.get("recovery_ticks")
        lines += [
            "",
            f"recovery: {len(self.recovery)} measured"
            + (f", p50 {r['p50']:.0f}, p99 {r['p99']:.0f}, max {r['max']:.0f} ticks" if r else "")
            + f"; {self.recovery_censored} censored; {self.recovery_unreachable} with an unreachable reference"
            + f"; {self.recovery_elbow_undefined} with the arm angle undefined at the held pose (not counted: "
            "the wrist centre fixes it, no self-motion changes it)",
        ]
        refused = sum(v.get("refused", 0) for v in self.probe_outcomes.values())
        accepted = sum(v.get("accepted", 0) for v in self.probe_outcomes.values())
        lines.append(f"bad inputs: {self.probes} sent, {refused} refused, {accepted} accepted")
        per = ", ".join(f"{s} {v.get('ticks', 0)}" for s, v in sorted(self.by_strategy.items()))
        settings = ", ".join(f"{s} {v.get('ticks', 0)}" for s, v in sorted(self.by_setting.items()))
        lines.append(
            f"ticks per strategy: {per}; per robot and dt: {settings}; held ticks checked for drift "
            f"{self.drift_checked}; commands checked against ddq_max·dt {self.accel_checked} (not: "
            f"{self.accel_unbounded}); ticks out of solver_time_budget ({cfg.solver_time_budget}) "
            f"{self.deadline_ticks}; episodes cut short (over {cfg.episode_seconds:g} s) {self.episodes_cut}; "
            f"wall {self.wall_seconds:.1f} s"
        )
        return "\n".join(lines)

    def _time_tables(self) -> list[str]:
        """The times' percentiles (µs): solver and tick wall time, whole-tick CPU; then whole-tick CPU per robot
        and strategy."""
        cfg = self.config
        lines = [
            "",
            f"| time | p50 µs | p99 µs | p99.9 µs | max µs | over {1e3 * cfg.solve_time_max:g} ms "
            f"(tick CPU: {1e3 * cfg.tick_cpu_max:g} ms) |",
            "|---|---|---|---|---|---|",
        ]
        pct = self.percentiles()
        for name in ("solve_time", "tick_time", "tick_cpu_time"):
            if name in pct:
                lines.append(_time_row(name, pct[name]))
        groups = self.tick_cpu_groups()
        if groups:
            lines += [
                "",
                f"| whole-tick CPU | p50 µs | p99 µs | p99.9 µs | max µs | over {1e3 * cfg.tick_cpu_max:g} ms |",
                "|---|---|---|---|---|---|",
            ]
            lines += [_time_row(name, p) for name, p in groups.items()]
        return lines

    def _worst_tick_lines(self) -> list[str]:
        """The tick of the largest whole-step CPU time, what it was, and its time in each replay."""
        ex = self.worst.get("tick_cpu")
        if ex is None:
            return []
        where = "fresh processes" if self.replays_fresh else "this process, on the same controllers"
        replays = "; ".join(
            f"{1e3 * r['tick_cpu']:.3g} ms" + (f" ({', '.join(r['kernels'])})" if r["kernels"] else "")
            if r["tick_cpu"] is not None
            else "not reached"
            for r in self.worst_tick_replays
        )
        return [
            "",
            f"worst tick: {1e3 * ex.value:.4g} ms of CPU, {ex.where.short()}{_detail(ex)}",
            f"the same tick in {len(self.worst_tick_replays)} replays of its episode in {where}: {replays or '—'}; "
            f"{self.replayed_episodes} episodes replayed in all, {self.replays_skipped} not (over "
            f"{self.config.max_replayed_episodes})",
        ]

    def merge(self, other: FuzzReport) -> None:
        """Add another shard's report of the same run: counters summed, lists and per-tick arrays joined, the worst
        example kept, the first one by episode and tick, the slowest build time."""
        for f in fields(self):
            name = f.name
            mine, theirs = getattr(self, name), getattr(other, name)
            if name == "worst":
                for key, ex in theirs.items():
                    if key not in mine or ex.value > mine[key].value:
                        mine[key] = ex
            elif name == "first":
                for key, ex in theirs.items():
                    if key not in mine or (ex.where.episode, ex.where.tick) < (
                        mine[key].where.episode,
                        mine[key].where.tick,
                    ):
                        mine[key] = ex
            elif name == "build_seconds":
                for key, seconds in theirs.items():
                    mine[key] = max(seconds, mine.get(key, 0.0))
            elif name == "exceptions":
                mine.extend(theirs[: max(self.max_exceptions_kept - len(mine), 0)])
            elif name not in ("config", "completed", "wall_seconds", "skipped_robots", "replays_fresh"):
                setattr(self, name, _added(mine, theirs))

    def to_dict(self) -> dict:
        """Plain JSON data (no per-tick arrays)."""
        return _jsonable(
            {
                "config": self.config.to_dict(),
                "ticks": self.ticks,
                "probes": self.probes,
                "episodes": self.episodes,
                "checks": {c.key: self._text(c) for c in CHECKS},
                "counts": self.counts,
                "failures": self.failures(),
                "worst": {k: asdict(v) for k, v in self.worst.items()},
                "first": {k: asdict(v) for k, v in self.first.items()},
                "by_strategy": self.by_strategy,
                "by_setting": self.by_setting,
                "start_kinds": self.start_kinds,
                "probe_outcomes": self.probe_outcomes,
                "percentiles": self.percentiles(),
                "tick_cpu_by_robot_and_strategy": self.tick_cpu_groups(),
                "recovery_censored": self.recovery_censored,
                "recovery_unreachable": self.recovery_unreachable,
                "recovery_elbow_undefined": self.recovery_elbow_undefined,
                "drift_checked": self.drift_checked,
                "kernels_added": self.kernels_added,
                "accel_checked": self.accel_checked,
                "accel_unbounded": self.accel_unbounded,
                "deadline_ticks": self.deadline_ticks,
                "episodes_cut": self.episodes_cut,
                "processes": self.processes,
                "replayed_episodes": self.replayed_episodes,
                "replays_skipped": self.replays_skipped,
                "replays_fresh": self.replays_fresh,
                "worst_tick_replays": self.worst_tick_replays,
                "skipped_robots": self.skipped_robots,
                "completed": self.completed,
                "exceptions": self.exceptions,
                "build_seconds": self.build_seconds,
                "wall_seconds": self.wall_seconds,
            }
        )  # type: ignore[return-value]


def _setting(where: Where) -> str:
    return f"{where.robot}, dt {1e3 * where.dt:g} ms"


def _time_row(name: str, p: dict[str, float]) -> str:
    return (
        f"| {name} | {1e6 * p['p50']:.0f} | {1e6 * p['p99']:.0f} | {1e6 * p['p99.9']:.0f} | {1e6 * p['max']:.0f} | "
        f"{p['over_max']} ({p['fraction_over']:.3%}) |"
    )


def _added(mine: object, theirs: object) -> object:
    """Two shards' values of one field added up: numbers summed, lists and arrays joined, dicts key by key."""
    if isinstance(mine, dict):
        out = dict(mine)
        for key, value in theirs.items():  # type: ignore[attr-defined]
            out[key] = _added(out[key], value) if key in out else value
        return out
    return mine + theirs  # type: ignore[operator]


def _detail(ex: Example) -> str:
    return f" — {ex.detail}" if ex.detail else ""


def record_exception(report: FuzzReport, exc: BaseException, where: Where, inputs: dict) -> None:
    """Count an exception that is not a QpnsoError; keep its traceback (the first ones)."""
    text = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
    report.record("foreign_exception", 1.0, where, inputs, f"{type(exc).__name__}: {exc}")
    if len(report.exceptions) < report.max_exceptions_kept:
        report.exceptions.append(
            {
                "where": asdict(where),
                "type": type(exc).__name__,
                "message": str(exc),
                "input": _jsonable(inputs),
                "traceback": text,
            }
        )
