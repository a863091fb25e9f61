"""What a fuzz run reports: the checks (:data:`CHECKS`, their must-hold lines), the worst and first
example of each violation, and :class:`FuzzReport` with its counters, percentiles, Markdown table and JSON.

Everything that counts a violation goes through :meth:`FuzzReport.record` (and :func:`record_exception`
for exceptions that are not a ``QpnsoError``), so the table and the exit status see the same numbers.
"""

from __future__ import annotations

import math
import traceback
from array import array
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from qpnso.lab.fuzz.config import FuzzConfig, Where


@dataclass(frozen=True)
class Check:
    """One check: ``key`` in the counters, ``text`` its line (formatted with the config; the must-hold
    lines are issue 13's), the unit of the worst value."""

    key: str
    text: str
    unit: str
    must_hold: bool = True  # False: counted and shown, not a failure


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
    """Counters of every check (:data:`CHECKS`), the worst example of each, per-strategy counts, the
    recovery distribution, bad-input outcomes and tick-time percentiles of one fuzz run."""

    config: FuzzConfig
    ticks: int = 0
    probes: int = 0
    episodes: int = 0
    counts: dict[str, int] = field(default_factory=lambda: dict.fromkeys(CHECK_KEYS, 0))
    worst: dict[str, Example] = field(default_factory=dict)
    first: dict[str, Example] = field(default_factory=dict)  # the first violation of each check (often the cause)
    by_strategy: dict[str, dict[str, int]] = field(default_factory=dict)
    start_kinds: dict[str, int] = field(default_factory=dict)
    probe_outcomes: dict[str, dict[str, int]] = field(default_factory=dict)
    recovery: list[int] = field(default_factory=list)  # ticks to recover, every measured disturbance
    recovery_censored: int = 0  # the episode ended or another disturbance came first (< the limit)
    recovery_unreachable: int = 0  # over the limit but the reference was not reachable (not counted)
    recovery_elbow_undefined: int = 0  # over the limit, elbow dropped, the arm angle undefined at the held pose
    drift_checked: int = 0  # held ticks checked for drift (settled, not excused)
    deadline_ticks: int = 0  # valid ticks whose cascade ran out of solver_time_budget (Status.QP_DEADLINE)
    episodes_cut: int = 0  # episodes cut short after episode_seconds
    completed: bool | None = None  # after a run: whether it ran every tick asked for
    exceptions: list[dict] = field(default_factory=list)  # the first foreign exceptions with tracebacks
    build_seconds: dict[str, float] = field(default_factory=dict)
    wall_seconds: float = 0.0
    solve_times: array = field(default_factory=lambda: array("d"), repr=False)  # s, every valid tick
    tick_times: array = field(default_factory=lambda: array("d"), repr=False)
    tick_cpu_times: array = field(default_factory=lambda: array("d"), repr=False)  # s, CPU of the whole step
    slow: list[tuple[Where, float]] = field(default_factory=list)  # every tick of the check "solve_time", its
    # solver time (s): replayed after the run

    max_exceptions_kept = 20

    def record(self, key: str, value: float, where: Where, inputs: dict, detail: str = "") -> None:
        """Count one violation of check ``key``; keep it as the worst example if its value is the largest."""
        self.counts[key] += 1
        per = self.by_strategy.setdefault(where.strategy, {})
        per[key] = per.get(key, 0) + 1
        best = self.worst.get(key)
        if best is None or value > best.value:
            self.worst[key] = Example(float(value), replace(where), _jsonable(inputs), detail)  # type: ignore[arg-type]
        if key not in self.first:
            self.first[key] = Example(float(value), replace(where), _jsonable(inputs), detail)  # type: ignore[arg-type]
        if key == "solve_time":
            self.slow.append((replace(where), float(value)))

    def count_tick(self, strategy: str) -> None:
        self.ticks += 1
        per = self.by_strategy.setdefault(strategy, {})
        per["ticks"] = per.get("ticks", 0) + 1

    def count_probe(self, kind: str, outcome: str) -> None:
        self.probes += 1
        per = self.probe_outcomes.setdefault(kind, {})
        per[outcome] = per.get(outcome, 0) + 1

    # ------------------------------------------------------------ summaries
    def percentiles(self) -> dict[str, dict[str, float]]:
        """Solver and whole-tick times (s): p50, p99, p99.9, max and the count over ``solve_time_max``;
        recovery ticks: p50, p99, max."""
        out: dict[str, dict[str, float]] = {}
        for name, values in (
            ("solve_time", self.solve_times),
            ("tick_time", self.tick_times),
            ("tick_cpu_time", self.tick_cpu_times),
        ):
            a = np.asarray(values, dtype=float)
            if a.size:
                p50, p99, p999 = np.percentile(a, [50, 99, 99.9])
                out[name] = {
                    "p50": float(p50),
                    "p99": float(p99),
                    "p99.9": float(p999),
                    "max": float(a.max()),
                    "over_max": int(np.count_nonzero(a > self.config.solve_time_max)),
                    "n": int(a.size),
                }
        if self.recovery:
            r = np.asarray(self.recovery, dtype=float)
            p50, p99 = np.percentile(r, [50, 99])
            out["recovery_ticks"] = {"p50": float(p50), "p99": float(p99), "max": float(r.max()), "n": int(r.size)}
        return out

    def failures(self) -> list[str]:
        """Every must-hold line violated, with its count and worst example; and a run that stopped short."""
        out = []
        if self.completed is False:
            out.append(
                f"the run stopped after {self.ticks} of {self.config.ticks} ticks "
                f"({self.wall_seconds:.0f} s; max_seconds {self.config.max_seconds})"
            )
        for check in CHECKS:
            n = self.counts[check.key]
            if n and check.must_hold:
                ex = self.worst.get(check.key)
                worst = f"; worst {ex.value:.4g} {check.unit} ({ex.where.short()}){_detail(ex)}" if ex else ""
                out.append(f"{self._text(check)}: {n} violations{worst}")
        return out

    def _text(self, check: Check) -> str:
        return check.text.format(**asdict(self.config))

    def table(self) -> str:
        """Markdown: one row per check (count, worst example), then timings, recovery and bad inputs."""
        cfg = self.config
        lines = [
            f"### qpnso fuzz: {self.ticks} ticks, {self.probes} bad inputs, {self.episodes} episodes, "
            f"seed {cfg.seed}, {cfg.robot}, strategies {','.join(cfg.strategies)}"
            + (", garbage collector frozen after the controllers were built (realtime_gc)" if cfg.freeze_gc else ""),
            "",
            "| check | count | worst |",
            "|---|---|---|",
        ]
        for check in CHECKS:
            ex = self.worst.get(check.key)
            worst = f"{ex.value:.4g} {check.unit}: {ex.where.short()}{_detail(ex)}" if ex else "—"
            lines.append(f"| {self._text(check)} | {self.counts[check.key]} | {worst.replace('|', '/')} |")
        lines += [
            "",
            f"| time | p50 µs | p99 µs | p99.9 µs | max µs | over {1e3 * cfg.solve_time_max:g} ms |",
            "|---|---|---|---|---|---|",
        ]
        pct = self.percentiles()
        for name in ("solve_time", "tick_time", "tick_cpu_time"):
            if name in pct:
                p = pct[name]
                lines.append(
                    f"| {name} | {1e6 * p['p50']:.0f} | {1e6 * p['p99']:.0f} | {1e6 * p['p99.9']:.0f} | "
                    f"{1e6 * p['max']:.0f} | {p['over_max']} |"
                )
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
        lines.append(
            f"ticks per strategy: {per}; held ticks checked for drift {self.drift_checked}; "
            f"ticks out of solver_time_budget ({cfg.solver_time_budget}) {self.deadline_ticks}; "
            f"episodes cut short (over {cfg.episode_seconds:g} s) {self.episodes_cut}; "
            f"wall {self.wall_seconds:.1f} s"
        )
        return "\n".join(lines)

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
                "start_kinds": self.start_kinds,
                "probe_outcomes": self.probe_outcomes,
                "percentiles": self.percentiles(),
                "recovery_censored": self.recovery_censored,
                "recovery_unreachable": self.recovery_unreachable,
                "recovery_elbow_undefined": self.recovery_elbow_undefined,
                "drift_checked": self.drift_checked,
                "deadline_ticks": self.deadline_ticks,
                "episodes_cut": self.episodes_cut,
                "completed": self.completed,
                "exceptions": self.exceptions,
                "build_seconds": self.build_seconds,
                "wall_seconds": self.wall_seconds,
            }
        )  # type: ignore[return-value]


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
