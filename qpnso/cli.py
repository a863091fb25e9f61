"""The ``qpnso`` command line.

Every sub-command is a small function ``cmd_<name>(args) -> int`` registered in
``build_parser``.  Errors that qpnso raises on purpose (bad robot, bad file,
bad angle, bad flag value...) are printed as one line, ``qpnso: error: ...``,
exit status 2.  A run that completes but fails its check (``qpnso solve``: the
tool left the trajectory by more than the tolerance) writes its results, prints
one line ``qpnso: failed: ...`` and exits with status 1.
"""

from __future__ import annotations

import argparse
import sys
from typing import Callable, Sequence

import numpy as np

from qpnso.errors import QpnsoError

Handler = Callable[[argparse.Namespace], int]


def parse_vector(text: str, n: int | None = None, what: str = "vector") -> np.ndarray:
    """Comma-separated numbers, e.g. ``0,0.5,0,-1.2,0,0.8,0``."""
    try:
        values = np.array([float(x) for x in text.replace(" ", "").split(",") if x != ""])
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what} must be comma-separated numbers, got {text!r}") from None
    if n is not None and values.shape != (n,):
        raise argparse.ArgumentTypeError(f"{what} needs {n} comma-separated numbers, got {values.size}")
    if not np.all(np.isfinite(values)):
        raise argparse.ArgumentTypeError(f"{what} contains NaN or inf: {text!r}")
    return values


def robot_q(args: argparse.Namespace, robot) -> np.ndarray:
    """``--q`` (rad) or ``--q-deg`` (degrees), else the sample configuration; checked."""
    if getattr(args, "q_deg", None) is not None:
        return robot.check_q(np.radians(parse_vector(args.q_deg, robot.nq, "--q-deg")), "--q-deg")
    if getattr(args, "q", None) is not None:
        return robot.check_q(parse_vector(args.q, robot.nq, "--q"), "--q")
    return robot.sample_configuration()


def add_robot_arguments(p: argparse.ArgumentParser, positional: bool = False) -> None:
    if positional:
        p.add_argument("robot", nargs="?", default="lwr4p", help="lwr4p (default), iiwa14, panda or a URDF path")
    else:
        p.add_argument("--robot", default="lwr4p", help="lwr4p (default), iiwa14, panda or a URDF path")
    p.add_argument("--tool-frame", default=None, help="frame the tool is mounted on (default: the flange)")
    p.add_argument("--tool-offset", default=None, help="tool point in that frame, x,y,z in metres")


def add_q_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--q", default=None, help="joint configuration in RADIANS, comma-separated")
    g.add_argument("--q-deg", default=None, help="joint configuration in DEGREES, comma-separated")


def load_cli_robot(args: argparse.Namespace, redundant: bool = False):
    """The robot of ``--robot``/``--tool-frame``/``--tool-offset``; with ``redundant``,
    refused unless it is a 7-DOF arm (the commands that move the elbow)."""
    from qpnso.model.robot import load_robot

    offset = parse_vector(args.tool_offset, 3, "--tool-offset") if args.tool_offset else None
    robot = load_robot(args.robot, tool_frame=args.tool_frame, tool_offset=offset)
    if redundant:
        robot.require_redundant_arm()
    return robot


def have_matplotlib() -> bool:
    """Whether the optional ``plot`` extra (matplotlib) can be imported."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


NO_MATPLOTLIB = "matplotlib is not installed (pip install 'qpnso[plot]')"


# ---------------------------------------------------------------------- info
def cmd_info(args: argparse.Namespace) -> int:
    """Print the model: joints, limits, masses, tool frame, costs at a sample q."""
    from qpnso.model.costs import TERMS, CostModel

    robot = load_cli_robot(args)
    q = robot_q(args, robot)
    print(f"robot {robot.name}  ({robot.source})  nq = {robot.nq}")
    print(f"{'joint':<10}{'q_min°':>9}{'q_max°':>9}{'dq_max°/s':>11}{'tau_max N·m':>13}"
          f"{'friction N·m':>14}{'beta s/rad':>12}{'link kg':>9}")
    for k, name in enumerate(robot.joint_names):
        mass = robot.model.inertias[k + 1].mass
        print(f"{name:<10}{np.degrees(robot.q_min[k]):>9.1f}{np.degrees(robot.q_max[k]):>9.1f}"
              f"{np.degrees(robot.dq_max[k]):>11.1f}{robot.tau_limit[k]:>13.1f}"
              f"{robot.friction.tau_max[k]:>14.2f}{robot.friction.beta[k]:>12.1f}{mass:>9.3f}")
    moving = sum(robot.model.inertias[j].mass for j in range(1, robot.model.njoints))
    base = robot.model.inertias[0].mass
    print(f"moving mass {moving:.3f} kg (+ {base:.3f} kg fixed base)")
    tool = robot.model.frames[robot.tool_frame_id]
    parent = robot.model.frames[tool.parentFrame].name
    pose = robot.tool_pose(q)
    print(f"tool frame on {parent!r}, offset {np.round(tool.placement.translation, 4).tolist()} m from joint "
          f"{robot.model.names[tool.parentJoint]!r}")
    print(f"at q = {np.round(np.degrees(q), 2).tolist()} deg:")
    print(f"  tool position (world) {np.round(pose.translation, 4).tolist()} m")
    cost = CostModel(robot, compile="off")
    terms = cost.terms(q)
    units = {"mass": "1/kg³", "inertia": "1/(kg·m²)³", "friction_force": "N²", "friction_torque": "N²·m²"}
    for t in TERMS:
        print(f"  {t:<16} {terms[t]: .6g} {units[t]:<12} (scale {cost.scales[t]:.4g})")
    print(f"  largest principal mass {cost.principal_mass(q):.3f} kg, "
          f"friction force magnitude {cost.friction_force_magnitude(q):.3f} N "
          f"(potential speed {cost.potential_speed} m/s)")
    print(f"  weighted cost {cost.value(q):.6g} with weights {cost.describe()['weights']}")
    return 0


# ----------------------------------------------------------------- intervals
def cmd_intervals(args: argparse.Namespace) -> int:
    """Plot every joint versus the arm angle for the tool pose of q (PNG)."""
    from qpnso.elbow.intervals import continuity_interval
    from qpnso.lab.plots import plot_intervals
    from qpnso.elbow.rom import ElbowConfig

    if not have_matplotlib():
        from qpnso.errors import InputError

        raise InputError(f"qpnso intervals draws a figure and needs {NO_MATPLOTLIB}")
    robot = load_cli_robot(args, redundant=True)
    q = robot_q(args, robot)
    rom = ElbowConfig(half_width_deg=args.rom_half_width_deg, safety_margin_deg=args.safety_margin_deg)
    iv = continuity_interval(robot, q)
    path = plot_intervals(robot, q, rom=rom, out=args.out)
    span = "full circle" if iv.full_circle else f"[{np.degrees(iv.lo):.2f}, {np.degrees(iv.hi):.2f}] deg"
    print(f"continuity interval {span} ({iv.method}); figure written to {path}")
    return 0


# ---------------------------------------------------------------- trajectory
def parse_targets(text: str) -> np.ndarray:
    """``x,y,z;x,y,z;...`` in metres."""
    rows = [parse_vector(part, 3, "--targets point") for part in text.split(";") if part.strip()]
    if len(rows) < 2:
        raise argparse.ArgumentTypeError("--targets needs at least two points x,y,z;x,y,z (m)")
    return np.array(rows)


def cmd_trajectory(args: argparse.Namespace) -> int:
    """Generate a tool trajectory CSV (t,x,y,z,qx,qy,qz,qw)."""
    import pinocchio as pin

    from qpnso.control import trajectory as tr
    center = parse_vector(args.center, 3, "--center")
    rot = pin.rpy.rpyToMatrix(*np.radians(parse_vector(args.rpy_deg, 3, "--rpy-deg")))
    pose = pin.SE3(rot, center)
    if args.kind == "guidance":
        traj = tr.guidance_path(pose, size=args.size, speed=args.speed, dt=args.dt)
    elif args.kind == "point-to-point":
        targets = parse_targets(args.targets) if args.targets else center + np.array(
            [[0, 0, 0], [0.08, 0, 0], [0.08, 0.08, 0], [0, 0.08, 0], [-0.08, 0, 0], [0, -0.08, 0]])
        traj = tr.point_to_point(targets, peak_speed=args.speed, orientation=rot, dt=args.dt)
    else:
        traj = tr.hold(pose, args.duration, dt=args.dt)
    tr.write_csv(traj, args.out)
    print(f"{args.kind}: {len(traj)} samples, {traj.duration:.2f} s, written to {args.out}")
    return 0


# --------------------------------------------------------------------- solve
def progress_bar(enabled: bool, desc: str):  # type: ignore[no-untyped-def]
    """A ``progress(done, total)`` callback drawing a tqdm bar on stderr, or None."""
    if not enabled:
        return None
    from tqdm import tqdm

    state: dict = {}

    def update(done: int, total: int) -> None:
        bar = state.get("bar")
        if bar is None:
            bar = state["bar"] = tqdm(total=total, desc=desc, unit="tick", leave=False, mininterval=0.5)
        if done % 100 == 0 or done == total:
            bar.update(done - bar.n)
        if done == total:
            bar.close()

    return update


def print_summary(summary: dict, title: str) -> None:
    print(f"{title}")
    width = max(len(k) for k in summary) if summary else 10
    for key, value in summary.items():
        print(f"  {key:<{width}}  {value:.6g}" if isinstance(value, float) else f"  {key:<{width}}  {value}")


def write_json(path: str, data: dict) -> None:
    import json
    from pathlib import Path

    from qpnso.control.offline import atomic_write

    text = json.dumps(data, indent=2, sort_keys=True).encode()
    atomic_write(Path(path), lambda f: f.write(text))


def controller_overrides(args: argparse.Namespace) -> dict:
    """CLI flags that override the config file (None: not given)."""
    return {"strategy": getattr(args, "strategy", None), "dt": getattr(args, "dt", None)}


def positive(value: float, flag: str) -> float:
    """``value`` if it is a positive finite number, else an error naming ``flag``."""
    from qpnso.errors import InputError

    if not (np.isfinite(value) and value > 0):
        raise InputError(f"{flag} must be a positive number, got {value:g}")
    return float(value)


def print_notes(messages: list[str], limit: int = 10) -> None:
    for message in messages[:limit]:
        print(f"  note: {message}")
    if len(messages) > limit:
        print(f"  ... and {len(messages) - limit} more notes")


def print_slow_ticks(summary: dict, dt: float) -> None:
    """One line when some ticks took longer than the control period."""
    slow = int(summary.get("slow_ticks", 0))
    if slow:
        print(f"  note: {slow} of {int(summary['ticks'])} ticks ({100 * slow / summary['ticks']:.1f} %) took longer "
              f"than the {1000 * dt:g} ms control period; the longest took {summary['tick_time_max_ms']:.4g} ms")


def cmd_solve(args: argparse.Namespace) -> int:
    """Offline solve of a tool trajectory, tick by tick: the main job.

    Exit status 0 when the tool stayed within the tolerance of the trajectory,
    1 when it did not (the result and summary are written all the same), 2 for
    bad input."""
    from qpnso.control.offline import load_config, solve_trajectory
    from qpnso.control.trajectory import read_csv

    tol_m = positive(args.tool_tolerance_mm, "--tool-tolerance-mm") / 1000.0
    tol_rad = np.radians(positive(args.tool_tolerance_deg, "--tool-tolerance-deg"))
    robot = load_cli_robot(args, redundant=True)
    traj = read_csv(args.trajectory)
    cfg = load_config(args.config, controller_overrides(args))
    q0 = None
    if args.q0 is not None:
        q0 = robot.check_q(parse_vector(args.q0, robot.nq, "--q0"), "--q0")
    result = solve_trajectory(robot, traj, q0=q0, config=cfg, progress=progress_bar(not args.quiet, "solve"),
                              tool_tolerance_m=tol_m, tool_tolerance_rad=float(tol_rad))
    result.save(args.out)
    if args.summary:
        write_json(args.summary, {"robot": robot.name, "strategy": cfg.strategy, "trajectory": str(args.trajectory),
                                  **result.summary})
    print_summary(result.summary, f"{robot.name}, strategy {cfg.strategy}, {args.trajectory} -> {args.out}")
    print_notes(result.messages)
    print_slow_ticks(result.summary, cfg.dt)
    if not result.ok:
        sys.stdout.flush()
        written = args.out + (f" and {args.summary}" if args.summary else "")
        print(f"qpnso: failed: {args.trajectory}: {result.failure}; results written to {written}", file=sys.stderr)
        return 1
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    """Hands-on guidance simulation of a scenario with one strategy."""
    from pathlib import Path

    from qpnso.lab.plots import plot_run
    from qpnso.lab.scenarios import load_scenario, simulate_scenario
    from qpnso.control.offline import config_values

    sc = load_scenario(args.scenario)
    settings = config_values(args.config, controller_overrides(args))
    plot = not args.no_plot and have_matplotlib()  # checked first: say so before a long run, not after
    if not args.no_plot and not plot:
        print(f"qpnso: note: {NO_MATPLOTLIB}: run.png will be skipped (result.npz and summary.json are written)",
              file=sys.stderr)
    result = simulate_scenario(args.scenario, None, args.duration_scale,
                               progress_bar(not args.quiet, "simulate"), settings)
    strategy = settings.get("strategy", sc.controller.get("strategy", "qp"))
    out = Path(args.out)
    result.save(out / "result.npz")
    write_json(str(out / "summary.json"), {"scenario": sc.name, "strategy": strategy, **result.summary})
    if plot:
        plot_run(result.arrays, out / "run.png", title=f"scenario {sc.name}, strategy {strategy}")
    print_summary(result.summary, f"scenario {sc.name} ({sc.description}), strategy {strategy} -> {out}")
    print_slow_ticks(result.summary, float(settings.get("dt", sc.controller.get("dt", 1e-3))))
    if not args.no_plot and not plot:
        print(f"qpnso: note: figure {out / 'run.png'} skipped: {NO_MATPLOTLIB}", file=sys.stderr)
    return 0


def cmd_plot(args: argparse.Namespace) -> int:
    """Plot a result.npz (arm angle, ROM_t, bounds, stiffness, felt mass/friction, tool path)."""
    import zipfile
    from pathlib import Path

    from qpnso.errors import InputError
    from qpnso.lab.plots import plot_run

    path = Path(args.result)
    if not path.is_file():
        raise InputError(f"result file not found: {path}")
    not_result = f"{path} is not a qpnso result .npz (the --out file of qpnso solve or simulate)"
    if not zipfile.is_zipfile(path):  # a CSV, a .npy, ...: np.load would talk about pickled data
        raise InputError(f"{not_result}: it is not a NumPy .npz archive")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise InputError(f"{not_result}: cannot read it ({exc})") from None
    missing = [k for k in ("t", "ns", "rom_lo", "rom_hi", "interval_lo", "interval_hi", "stiffness", "mass",
                           "friction_force", "tool_position") if k not in arrays]
    if missing:
        raise InputError(f"{not_result}: it lacks {missing}")
    if not have_matplotlib():
        raise InputError(f"qpnso plot needs {NO_MATPLOTLIB}")
    print(f"figure written to {plot_run(arrays, args.out, title=str(args.result))}")
    return 0


def cmd_compare(args: argparse.Namespace) -> int:
    """Several strategies on one scenario: one table (Markdown) and one figure."""
    from pathlib import Path

    from qpnso.control.controller import STRATEGIES
    from qpnso.errors import ConfigError
    from qpnso.lab.plots import plot_comparison
    from qpnso.lab.scenarios import load_scenario, simulate_scenario

    strategies = [x.strip() for x in args.strategies.split(",") if x.strip()]
    unknown = [x for x in strategies if x not in STRATEGIES]
    if unknown:
        raise ConfigError(f"unknown strategy {unknown}; choose from {STRATEGIES}")
    sc = load_scenario(args.scenario)
    plot = have_matplotlib()
    if not plot:
        print(f"qpnso: note: {NO_MATPLOTLIB}: comparison.png will be skipped", file=sys.stderr)
    runs, rows = {}, []
    for name in strategies:
        result = simulate_scenario(args.scenario, name, args.duration_scale, progress_bar(not args.quiet, name))
        runs[name] = result.arrays
        rows.append((name, result.summary))
    out = Path(args.out)
    table = comparison_table(rows, sc)
    out.mkdir(parents=True, exist_ok=True)
    (out / "comparison.md").write_text(table + "\n")
    if plot:
        plot_comparison(runs, out / "comparison.png", title=f"scenario {sc.name}: {sc.description}")
    print(table)
    if not plot:
        print(f"qpnso: note: figure {out / 'comparison.png'} skipped: {NO_MATPLOTLIB}", file=sys.stderr)
    return 0


def comparison_table(rows: list, sc) -> str:  # type: ignore[no-untyped-def]
    margin = sc.controller.get("safety_margin_deg", 10.0)
    lines = [f"scenario {sc.name} ({sc.description}), safety margin {margin:g} deg", "",
             "| strategy | Δ elbow mobility (deg) | Δc proximity (deg) | Δc ≥ margin | S smoothness | "
             "tool error max (mm) | work per metre (N) | tick median (µs) |",
             "|---|---|---|---|---|---|---|---|"]
    for name, m in rows:
        lines.append(
            f"| {name} | {m.get('elbow_mobility_deg', float('nan')):.1f} | "
            f"{m.get('constraint_proximity_deg', float('nan')):.1f} | "
            f"{'yes' if m.get('constraint_proximity_deg', -1) >= margin else 'no'} | "
            f"{m.get('smoothness', float('nan')):.0f} | {1000 * m.get('tool_position_error_max_m', float('nan')):.2f} | "
            f"{m.get('user_work_per_metre_N', float('nan')):.2f} | {m.get('tick_time_median_us', float('nan')):.0f} |")
    return "\n".join(lines)


# --------------------------------------------------------------------- study
def cmd_study(args: argparse.Namespace) -> int:
    """One of the papers' studies, on every core or a Dask cluster."""
    from pathlib import Path

    from qpnso.lab.studies import run_study

    options = {}
    for item in args.option or []:
        key, sep, value = item.partition("=")
        if not sep:
            raise argparse.ArgumentTypeError(f"--option takes key=value, got {item!r}")
        options[key.strip()] = value.strip()
    summary = run_study(args.name, Path(args.out), n=args.n, seed=args.seed, workers=args.workers,
                        scheduler=args.scheduler, progress=not args.quiet, options=options or None)
    print_summary({k: v for k, v in summary.items() if not isinstance(v, (dict, list))},
                  f"study {args.name} -> {args.out}")
    for key, value in summary.items():
        if isinstance(value, dict):
            print(f"  {key}: " + ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                                            for k, v in value.items()))
    return 0


# --------------------------------------------------------------------- bench
def cmd_bench(args: argparse.Namespace) -> int:
    """Time the cost or the control tick; print a Markdown table of medians and p99."""
    from qpnso.lab import benchmark
    if args.what == "solvers":
        from pathlib import Path

        from qpnso.lab.solver_bench import run_solver_benchmark

        report = run_solver_benchmark(Path(args.out or "solver-bench"), quick=args.quick,
                                      progress=None if args.quiet else print)
        print(report.read_text())
        return 0
    if args.what == "fuzz":
        return bench_fuzz(args)
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
    """``qpnso bench fuzz -n N``: N fuzzed closed-loop ticks (qpnso/lab/fuzz.py); the Markdown table, the report
    as JSON with ``--out``; exit status 1 if a must-hold check fails."""
    from qpnso.control.controller import STRATEGIES
    from qpnso.lab.fuzz import FuzzConfig, run_fuzz

    offset = parse_vector(args.tool_offset, 3, "--tool-offset") if args.tool_offset else (0.0, 0.0, 0.1)
    strategies = tuple(x.strip() for x in args.strategies.split(",") if x.strip()) if args.strategies else STRATEGIES
    budget = None if args.solver_time_budget_ms is None else args.solver_time_budget_ms * 1e-3
    config = FuzzConfig(seed=args.seed, ticks=args.n, strategies=strategies, robot=args.robot,
                        tool_frame=args.tool_frame, tool_offset=tuple(offset), solver_time_budget=budget)
    report = run_fuzz(config, progress=progress_bar(not args.quiet, "fuzz"))
    if args.out:
        write_json(args.out, report.to_dict())
    print(report.table())
    failures = report.failures()
    for line in failures:
        print(f"FAIL: {line}")
    return 1 if failures else 0


# ------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="qpnso", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("info", help="print a robot model and its costs at a sample configuration")
    add_robot_arguments(p, positional=True)
    add_q_arguments(p)
    p.set_defaults(handler=cmd_info)

    p = sub.add_parser("intervals", help="plot joints vs arm angle with limits, feasible arcs, ROM (PNG)")
    add_robot_arguments(p, positional=True)
    add_q_arguments(p)
    p.add_argument("--rom-half-width-deg", type=float, default=50.0, help="ROM half width, degrees (default 50)")
    p.add_argument("--safety-margin-deg", type=float, default=10.0, help="safety margin, degrees (default 10)")
    p.add_argument("--out", default="intervals.png", help="PNG file to write")
    p.set_defaults(handler=cmd_intervals)

    p = sub.add_parser("trajectory", help="generate a tool trajectory CSV (t,x,y,z,qx,qy,qz,qw)")
    p.add_argument("kind", choices=["guidance", "point-to-point", "hold"])
    p.add_argument("--center", default="0.5,0,0.45", help="path centre / start, x,y,z in metres (world)")
    p.add_argument("--rpy-deg", default="180,0,0", help="tool orientation roll,pitch,yaw in DEGREES")
    p.add_argument("--size", type=float, default=0.08, help="guidance: lemniscate width, m")
    p.add_argument("--speed", type=float, default=0.05, help="peak tool speed, m/s")
    p.add_argument("--targets", default=None, help="point-to-point: x,y,z;x,y,z;... in metres")
    p.add_argument("--duration", type=float, default=2.0, help="hold: seconds")
    p.add_argument("--dt", type=float, default=0.01, help="sample period, s")
    p.add_argument("--out", required=True, help="CSV file to write")
    p.set_defaults(handler=cmd_trajectory)

    p = sub.add_parser("solve", help="solve a tool trajectory tick by tick (the main job)")
    p.add_argument("trajectory", help="CSV with header t,x,y,z,qx,qy,qz,qw (s, m, unit quaternion)")
    add_robot_arguments(p)
    p.add_argument("--q0", default=None, help="start configuration in RADIANS, comma-separated "
                   "(default: found for the first pose, elbow up)")
    p.add_argument("--strategy", default=None, help="qp (default), damped, fixed, elbow-up, gradient, rom")
    p.add_argument("--config", default=None, help="TOML file of controller settings (flags override it)")
    p.add_argument("--dt", type=float, default=None, help="tick length, s (default 0.001)")
    p.add_argument("--out", default="result.npz", help="per-tick arrays (NumPy .npz)")
    p.add_argument("--summary", default=None, help="also write the summary as JSON")
    p.add_argument("--tool-tolerance-mm", type=float, default=1.0,
                   help="the run fails (exit status 1) if the tool ever leaves the path by more (default 1 mm)")
    p.add_argument("--tool-tolerance-deg", type=float, default=1.0,
                   help="same for the tool's orientation error, DEGREES (default 1)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=cmd_solve)

    p = sub.add_parser("simulate", help="hands-on guidance simulation of scenario A or B")
    p.add_argument("--scenario", default="A", help="A, B or a scenario .toml file")
    p.add_argument("--strategy", default=None, help="strategy (default qp)")
    p.add_argument("--config", default=None, help="TOML file of controller settings")
    p.add_argument("--duration-scale", type=float, default=1.0, help="run only this fraction of the path")
    p.add_argument("--out", required=True, help="folder for result.npz, summary.json, run.png")
    p.add_argument("--no-plot", action="store_true")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(handler=cmd_simulate, dt=None)

    p = sub.add_parser("plot", help="plot a result.npz (PNG)")
    p.add_argument("result")
    p.add_argument("--out", default="run.png")
    p.set_defaults(handler=cmd_plot)

    p = sub.add_parser("compare", help="several strategies on one scenario: table and figure")
    p.add_argument("--scenario", default="B")
    p.add_argument("--strategies", default="qp,damped,fixed,rom,gradient")
    p.add_argument("--duration-scale", type=float, default=1.0)
    p.add_argument("--out", required=True, help="folder for comparison.md and comparison.png")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(handler=cmd_compare)

    p = sub.add_parser("study", help="reproduce a study of the papers (JSON + CSV + PNG in --out)")
    p.add_argument("name", choices=["workspace", "tradeoff", "uncertainty", "scenarios"])
    p.add_argument("--n", type=int, default=None, help="poses (default: the paper's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=None, help="processes (default: every core)")
    p.add_argument("--scheduler", default=None, help="Dask scheduler address (tcp://host:8786)")
    p.add_argument("--option", action="append", help="study option key=value (repeatable)")
    p.add_argument("--out", required=True)
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(handler=cmd_study)

    p = sub.add_parser("bench", help="time the cost evaluation or the control tick (median, p99)")
    p.add_argument("what", choices=["cost", "interval", "tick", "solvers", "fuzz"])
    add_robot_arguments(p)
    p.add_argument("-n", type=int, default=3000, help="timed calls per row; fuzz: ticks (default 3000)")
    p.add_argument("--strategies", default=None, help="comma-separated strategies for 'tick', 'fuzz' (default all)")
    p.add_argument("--seed", type=int, default=0, help="fuzz: random seed (default 0)")
    p.add_argument("--solver-time-budget-ms", type=float, default=None,
                   help="fuzz: every controller's solver_time_budget, in ms of CPU time (default: none)")
    p.add_argument("--quick", action="store_true", help="solvers: the small committed problem set (< 1 min)")
    p.add_argument("--out", default=None, help="solvers: folder for report.md, results.csv, figure "
                   "(default solver-bench); fuzz: the report as JSON")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(handler=cmd_bench)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    handler: Handler = args.handler
    try:
        return handler(args)
    except (argparse.ArgumentTypeError, QpnsoError) as exc:  # a bad flag value (named) or refused input
        print(f"qpnso: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
