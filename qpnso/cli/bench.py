"""``qpnso bench ...``: timings of the cost, the continuity interval and the tick, the QP solver
comparison and the fuzz test."""

from __future__ import annotations

import argparse

from qpnso.cli.common import load_cli_robot, output_path, parse_vector, progress_bar, write_json


# --------------------------------------------------------------------- bench
def cmd_bench(args: argparse.Namespace) -> int:
    """Time the cost or the control tick; print a Markdown table of medians and p99."""
    from qpnso.lab import benchmark

    if args.what == "solvers":
        from pathlib import Path

        from qpnso.lab.solver_bench import run_solver_benchmark

        out = output_path(args.out or "solver-bench", "--out", folder=True)
        report = run_solver_benchmark(Path(out), quick=args.quick, progress=None if args.quiet else print)
        print(report.read_text())
        return 0
    if args.what == "fuzz":
        return bench_fuzz(args)
    args.robot = args.robot or "lwr4p"  # (the bench parser leaves it None: fuzz's default is every robot)
    robot = load_cli_robot(args, redundant=args.what != "cost")
    if args.what == "cost":
        rows = benchmark.bench_cost(robot, n=args.n)
        title = f"cost.value + cost.gradient, {robot.name}, mass + friction force"
    elif args.what == "interval":
        rows = benchmark.bench_interval(robot, n=args.n)
        title = f"continuity interval, {robot.name}"
    else:
        strategies = tuple(args.strategies.split(",")) if args.strategies else None
        rows = benchmark.bench_tick(robot, n=args.n, strategies=strategies)
        title = f"Controller.step, {robot.name}, dt = 1 ms"
    print(benchmark.table(rows, title))
    return 0


def bench_fuzz(args: argparse.Namespace) -> int:
    """``qpnso bench fuzz -n N``: N fuzzed closed-loop ticks (qpnso/lab/fuzz/) over the robots of ``--robot``
    (default the three), the tick lengths of ``--dt-ms`` (default 1 and 4 ms) and the strategies, in
    ``--workers`` fresh processes at a time; the Markdown table, the report as JSON with ``--out``; exit status 1
    if a must-hold check fails."""
    from qpnso.control.config import STRATEGIES
    from qpnso.lab.fuzz import FuzzConfig, run_fuzz
    from qpnso.lab.fuzz.config import DTS, ROBOTS

    if args.out:
        output_path(args.out, "--out")
    offset = parse_vector(args.tool_offset, 3, "--tool-offset") if args.tool_offset else (0.0, 0.0, 0.1)
    strategies = _names(args.strategies) or STRATEGIES
    dts = tuple(1e-3 * x for x in parse_vector(args.dt_ms, None, "--dt-ms")) if args.dt_ms else DTS
    budget = None if args.solver_time_budget_ms is None else args.solver_time_budget_ms * 1e-3
    config = FuzzConfig(
        seed=args.seed,
        ticks=args.n,
        strategies=strategies,
        robots=_names(args.robot) or ROBOTS,
        dts=dts,
        workers=args.workers,
        tool_frame=args.tool_frame,
        tool_offset=tuple(offset),
        solver_time_budget=budget,
    )
    report = run_fuzz(config, progress=progress_bar(not args.quiet, "fuzz"))
    if args.out:
        write_json(args.out, report.to_dict())
    print(report.table())
    failures = report.failures()
    for line in failures:
        print(f"FAIL: {line}")
    return 1 if failures else 0


def _names(text: str | None) -> tuple[str, ...]:
    """A comma-separated list of names (empty when not given)."""
    return tuple(x.strip() for x in text.split(",") if x.strip()) if text else ()
