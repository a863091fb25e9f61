"""The sub-commands ``info``, ``intervals``, ``trajectory``, ``solve``, ``simulate``, ``plot``, ``compare``
and ``study``: each a function ``cmd_<name>(args) -> int``."""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING, Any

import numpy as np

from qpnso.cli.common import (
    NO_MATPLOTLIB,
    controller_overrides,
    have_matplotlib,
    load_cli_robot,
    output_path,
    parse_vector,
    positive,
    print_notes,
    print_slow_ticks,
    print_summary,
    progress_bar,
    robot_q,
    write_json,
)

if TYPE_CHECKING:
    from qpnso.model.obstacles import Obstacle


# ---------------------------------------------------------------------- info
def cmd_info(args: argparse.Namespace) -> int:
    """Print the model: joints, limits, masses, tool frame, costs at a sample q."""
    from qpnso.model.costs import TERMS, CostModel

    robot = load_cli_robot(args)
    q = robot_q(args, robot)
    print(f"robot {robot.name}  ({robot.source})  nq = {robot.nq}")
    print(
        f"{'joint':<10}{'q_min°':>9}{'q_max°':>9}{'dq_max°/s':>11}{'tau_max N·m':>13}"
        f"{'friction N·m':>14}{'beta s/rad':>12}{'link kg':>9}"
    )
    for k, name in enumerate(robot.joint_names):
        mass = robot.model.inertias[k + 1].mass
        print(
            f"{name:<10}{np.degrees(robot.q_min[k]):>9.1f}{np.degrees(robot.q_max[k]):>9.1f}"
            f"{np.degrees(robot.dq_max[k]):>11.1f}{robot.tau_limit[k]:>13.1f}"
            f"{robot.friction.tau_max[k]:>14.2f}{robot.friction.beta[k]:>12.1f}{mass:>9.3f}"
        )
    moving = sum(robot.model.inertias[j].mass for j in range(1, robot.model.njoints))
    base = robot.model.inertias[0].mass
    print(f"moving mass {moving:.3f} kg (+ {base:.3f} kg fixed base)")
    tool = robot.model.frames[robot.tool_frame_id]
    parent = robot.model.frames[tool.parentFrame].name
    pose = robot.tool_pose(q)
    print(
        f"tool frame on {parent!r}, offset {np.round(tool.placement.translation, 4).tolist()} m from joint "
        f"{robot.model.names[tool.parentJoint]!r}"
    )
    print(f"at q = {np.round(np.degrees(q), 2).tolist()} deg:")
    print(f"  tool position (world) {np.round(pose.translation, 4).tolist()} m")
    cost = CostModel(robot, compile="off")
    terms = cost.terms(q)
    units = {"mass": "1/kg³", "inertia": "1/(kg·m²)³", "friction_force": "N²", "friction_torque": "N²·m²"}
    for t in TERMS:
        print(f"  {t:<16} {terms[t]: .6g} {units[t]:<12} (scale {cost.scales[t]:.4g})")
    print(
        f"  largest principal mass {cost.principal_mass(q):.3f} kg, "
        f"friction force magnitude {cost.friction_force_magnitude(q):.3f} N "
        f"(potential speed {cost.potential_speed} m/s)"
    )
    print(f"  weighted cost {cost.value(q):.6g} with weights {cost.describe()['weights']}")
    return 0


# ----------------------------------------------------------------- intervals
def cmd_intervals(args: argparse.Namespace) -> int:
    """Plot every joint versus the arm angle for the tool pose of q (PNG); with ``--obstacles`` (a TOML file,
    :func:`read_obstacles`) the intervals also keep every link ``--obstacle-margin`` metres from them and a panel
    draws the links' clearance."""
    from qpnso.elbow.intervals import continuity_interval
    from qpnso.elbow.rom import ElbowConfig
    from qpnso.lab.plots import plot_intervals

    output_path(args.out, "--out")
    if not have_matplotlib():
        from qpnso.errors import InputError

        raise InputError(f"qpnso intervals draws a figure and needs {NO_MATPLOTLIB}")
    robot = load_cli_robot(args, redundant=True)
    q = robot_q(args, robot)
    rom = ElbowConfig(half_width_deg=args.rom_half_width_deg, safety_margin_deg=args.safety_margin_deg)
    obstacles = read_obstacles(args.obstacles) if args.obstacles else ()
    margin = args.obstacle_margin
    iv = continuity_interval(robot, q, obstacles=obstacles, margin=margin)
    path = plot_intervals(robot, q, rom=rom, out=args.out, obstacles=obstacles, margin=margin)
    span = "full circle" if iv.full_circle else f"[{np.degrees(iv.lo):.2f}, {np.degrees(iv.hi):.2f}] deg"
    keep_out = f", {len(obstacles)} obstacle(s) kept {margin:g} m away" if obstacles else ""
    print(f"continuity interval {span} ({iv.method}{keep_out}); figure written to {path}")
    return 0


def read_obstacles(path: str) -> tuple[Obstacle, ...]:
    """The ``[[obstacles]]`` tables of a TOML file (``type = "sphere" | "capsule" | "box"`` and the fields of
    :mod:`qpnso.model.obstacles`, m, world frame) as obstacles; a ConfigError names the file and the entry."""
    from qpnso.errors import ConfigError
    from qpnso.model.obstacles import as_obstacles
    from qpnso.settings import SettingError, read_toml

    data = read_toml(path, "obstacle file")
    if "obstacles" not in data:
        raise ConfigError(f"{path}: no [[obstacles]] tables")
    try:
        return as_obstacles(data["obstacles"])
    except SettingError as exc:
        raise exc.within("", str(path)) from None


# ---------------------------------------------------------------- trajectory
def parse_targets(text: str) -> np.ndarray:
    """``x,y,z;x,y,z;...`` in metres."""
    rows = [parse_vector(part, 3, "--targets point") for part in text.split(";") if part.strip()]
    if len(rows) < 2:
        raise argparse.ArgumentTypeError("--targets needs at least two points x,y,z;x,y,z (m)")
    return np.array(rows)


def cmd_trajectory(args: argparse.Namespace) -> int:
    """Generate a tool trajectory CSV (t,x,y,z,qx,qy,qz,qw)."""
    from pathlib import Path

    import pinocchio as pin

    from qpnso.control import trajectory as tr

    output_path(args.out, "--out")
    center = parse_vector(args.center, 3, "--center")
    rot = pin.rpy.rpyToMatrix(*np.radians(parse_vector(args.rpy_deg, 3, "--rpy-deg")))
    pose = pin.SE3(rot, center)
    if args.kind == "guidance":
        traj = tr.guidance_path(pose, size=args.size, speed=args.speed, dt=args.dt)
    elif args.kind == "point-to-point":
        targets = (
            parse_targets(args.targets)
            if args.targets
            else center
            + np.array([[0, 0, 0], [0.08, 0, 0], [0.08, 0.08, 0], [0, 0.08, 0], [-0.08, 0, 0], [0, -0.08, 0]])
        )
        traj = tr.point_to_point(targets, peak_speed=args.speed, orientation=rot, dt=args.dt)
    else:
        traj = tr.hold(pose, args.duration, dt=args.dt)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)  # as every command's output
    tr.write_csv(traj, args.out)
    print(f"{args.kind}: {len(traj)} samples, {traj.duration:.2f} s, written to {args.out}")
    return 0


# --------------------------------------------------------------------- solve
def cmd_solve(args: argparse.Namespace) -> int:
    """Offline solve of a tool trajectory, tick by tick: the main job.

    Exit status 0 when the tool stayed within the tolerance of the trajectory,
    1 when it did not (the result and summary are written all the same), 2 for
    bad input."""
    from qpnso.control.offline import load_config, solve_trajectory
    from qpnso.control.trajectory import read_csv

    output_path(args.out, "--out")
    if args.summary:
        output_path(args.summary, "--summary")
    tol_m = positive(args.tool_tolerance_mm, "--tool-tolerance-mm") / 1000.0
    tol_rad = np.radians(positive(args.tool_tolerance_deg, "--tool-tolerance-deg"))
    robot = load_cli_robot(args, redundant=True)
    traj = read_csv(args.trajectory)
    cfg = load_config(args.config, controller_overrides(args))
    q0 = None
    if args.q0 is not None:
        q0 = robot.check_q(parse_vector(args.q0, robot.nq, "--q0"), "--q0")
    result = solve_trajectory(
        robot,
        traj,
        q0=q0,
        config=cfg,
        progress=progress_bar(not args.quiet, "solve"),
        tool_tolerance_m=tol_m,
        tool_tolerance_rad=float(tol_rad),
    )
    result.save(args.out)
    if args.summary:
        write_json(
            args.summary,
            {"robot": robot.name, "strategy": cfg.strategy, "trajectory": str(args.trajectory), **result.summary},
        )
    print_summary(result.summary, f"{robot.name}, strategy {cfg.strategy}, {args.trajectory} -> {args.out}")
    print_notes(result.messages)
    print_slow_ticks(result.summary, cfg.dt)
    if result.first_obstacle is not None:
        print(f"  obstacle: {result.first_obstacle.describe()}")
    if not result.ok:
        sys.stdout.flush()
        written = args.out + (f" and {args.summary}" if args.summary else "")
        print(f"qpnso: failed: {args.trajectory}: {result.failure}; results written to {written}", file=sys.stderr)
        return 1
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    """Hands-on guidance simulation of a scenario with one strategy."""
    from pathlib import Path

    from qpnso.control.offline import config_values
    from qpnso.lab.plots import plot_run
    from qpnso.lab.scenarios import load_scenario, simulate_scenario

    output_path(args.out, "--out", folder=True)
    sc = load_scenario(args.scenario)
    settings = config_values(args.config, controller_overrides(args))
    plot = not args.no_plot and have_matplotlib()  # checked first: say so before a long run, not after
    if not args.no_plot and not plot:
        print(
            f"qpnso: note: {NO_MATPLOTLIB}: run.png will be skipped (result.npz and summary.json are written)",
            file=sys.stderr,
        )
    result = simulate_scenario(
        args.scenario,
        None,
        args.duration_scale,
        progress_bar(not args.quiet, "simulate"),
        settings,
        ignore_obstacles=args.ignore_obstacles,
    )
    strategy = result.scene["strategy"]
    out = Path(args.out)
    result.save(out / "result.npz")
    write_json(str(out / "summary.json"), {"scenario": sc.name, "strategy": strategy, **result.summary, **result.setup})
    if plot:
        plot_run(result.arrays, out / "run.png", title=f"scenario {sc.name}, strategy {strategy}")
    title = f"scenario {sc.name} ({sc.description}), strategy {strategy}{_unknown_note(args)} -> {out}"
    print_summary(result.summary, title)
    print_slow_ticks(result.summary, float(settings.get("dt", sc.controller.get("dt", 1e-3))))
    if not args.no_plot and not plot:
        print(f"qpnso: note: figure {out / 'run.png'} skipped: {NO_MATPLOTLIB}", file=sys.stderr)
    return 0


PLOTTED = (
    "t",
    "ns",
    "rom_lo",
    "rom_hi",
    "interval_lo",
    "interval_hi",
    "stiffness",
    "mass",
    "friction_force",
    "tool_position",
)
"""The arrays ``qpnso plot`` draws."""


def cmd_plot(args: argparse.Namespace) -> int:
    """Plot a result.npz (arm angle, ROM_t, bounds, stiffness, felt mass/friction, tool path)."""
    from qpnso.control.offline import read_result
    from qpnso.errors import InputError
    from qpnso.lab.plots import plot_run

    output_path(args.out, "--out")
    arrays, _ = read_result(args.result, PLOTTED)
    if not have_matplotlib():
        raise InputError(f"qpnso plot needs {NO_MATPLOTLIB}")
    print(f"figure written to {plot_run(arrays, args.out, title=str(args.result))}")
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    """3-D replay of a result file or of a scenario's simulation: a live viser server, or with ``--html`` one
    self-contained page."""
    from qpnso.errors import InputError
    from qpnso.view import load_replay, scenario_replay
    from qpnso.view.scene import serve, viser_module, write_html

    viser_module()  # say it is missing before a long simulation, not after
    positive(args.fps, "--fps")
    if (args.result is None) == (args.scenario is None):
        raise InputError("give a result file or --scenario NAME, not both")
    scenario_only = {"--strategy": args.strategy, "--duration-scale": args.duration_scale}
    scenario_only["--ignore-obstacles"] = args.ignore_obstacles or None
    file_only = {"--robot": args.robot, "--tool-frame": args.tool_frame, "--tool-offset": args.tool_offset}
    file_only["--obstacles"] = args.obstacles
    wrong = [flag for flag, value in (file_only if args.scenario else scenario_only).items() if value is not None]
    if wrong:
        where = "a scenario (--scenario)" if args.scenario else "a result file"
        raise InputError(f"{', '.join(wrong)} do not apply to {where}")
    if args.scenario is not None:
        replay = scenario_replay(
            args.scenario,
            args.strategy,
            positive(1.0 if args.duration_scale is None else args.duration_scale, "--duration-scale"),
            progress_bar(not args.quiet, "simulate"),
            args.ignore_obstacles,
        )
    else:
        if not args.robot and (args.tool_frame or args.tool_offset):
            raise InputError("--tool-frame and --tool-offset apply with --robot")
        robot = load_cli_robot(args, redundant=True) if args.robot else None
        obstacles = read_obstacles(args.obstacles) if args.obstacles else None
        replay = load_replay(args.result, robot, obstacles)
    if args.html:
        path = write_html(replay, args.html, args.fps)
        print(f"{replay.title}: {len(replay.frames(args.fps))} frames, {path.stat().st_size / 1e6:.2f} MB -> {path}")
        return 0
    serve(replay, args.host, args.port, args.fps)
    return 0


def cmd_compare(args: argparse.Namespace) -> int:
    """Several strategies on one scenario: one table (Markdown) and one figure.

    A strategy whose run stops with an error (e.g. it drives a joint past its limits, which the controller
    refuses) gets a row saying so; the others are run, and the exit status is then 1."""
    from pathlib import Path

    from qpnso.control.config import STRATEGIES
    from qpnso.errors import ConfigError, QpnsoError
    from qpnso.lab.plots import plot_comparison
    from qpnso.lab.scenarios import load_scenario, simulate_scenario

    output_path(args.out, "--out", folder=True)
    strategies = [x.strip() for x in args.strategies.split(",") if x.strip()]
    unknown = [x for x in strategies if x not in STRATEGIES]
    if unknown:
        raise ConfigError(f"unknown strategy {unknown}; choose from {STRATEGIES}")
    sc = load_scenario(args.scenario)
    plot = have_matplotlib()
    if not plot:
        print(f"qpnso: note: {NO_MATPLOTLIB}: comparison.png will be skipped", file=sys.stderr)
    runs, rows, failed = {}, [], []
    for name in strategies:
        try:
            result = simulate_scenario(
                args.scenario,
                name,
                args.duration_scale,
                progress_bar(not args.quiet, name),
                ignore_obstacles=args.ignore_obstacles,
            )
        except QpnsoError as exc:
            rows.append((name, {"error": str(exc)}))
            failed.append(f"strategy {name}: {exc}")
            continue
        runs[name] = result.arrays
        rows.append((name, result.summary))
    out = Path(args.out)
    table = comparison_table(rows, sc, _unknown_note(args))
    out.mkdir(parents=True, exist_ok=True)
    (out / "comparison.md").write_text(table + "\n")
    if plot and runs:
        plot_comparison(runs, out / "comparison.png", title=f"scenario {sc.name}: {sc.description}")
    print(table)
    if not plot:
        print(f"qpnso: note: figure {out / 'comparison.png'} skipped: {NO_MATPLOTLIB}", file=sys.stderr)
    for line in failed:
        print(f"qpnso: failed: {line}", file=sys.stderr)
    return 1 if failed else 0


def _unknown_note(args: argparse.Namespace) -> str:
    """`` (obstacles unknown to the controller)`` when ``--ignore-obstacles`` was given, else empty."""
    return " (obstacles unknown to the controller)" if args.ignore_obstacles else ""


def comparison_table(rows: list, sc, note: str = "") -> str:
    """The Markdown table of ``rows`` (strategy, run summary; a summary ``{"error": ...}``: a row saying the run
    stopped); with the room's obstacles (``sc.obstacles``), the coal clearance columns (:func:`clearance_cells`)."""
    margin = sc.controller.get("safety_margin_deg", 10.0)
    room = bool(sc.obstacles)
    lines = [
        f"scenario {sc.name} ({sc.description}), safety margin {margin:g} deg{note}",
        "",
        "| strategy | Δ elbow mobility (deg) | Δc proximity (deg) | Δc ≥ margin | S per segment (median) | "
        "tool from intended, max (mm) | work per metre (N) | hand work (J) | felt mass, mean (kg) | "
        "tick median (µs) |" + (CLEARANCE_HEAD if room else ""),
        "|---|---|---|---|---|---|---|---|---|---|" + ("---|" * CLEARANCE_HEAD.count("|") if room else ""),
    ]
    for name, m in rows:
        if "error" in m:
            lines.append(f"| {name} | run stopped: {m['error']} |")
            continue
        lines.append(
            f"| {name} | {m.get('elbow_mobility_deg', float('nan')):.1f} | "
            f"{m.get('constraint_proximity_deg', float('nan')):.1f} | "
            f"{'yes' if m.get('constraint_proximity_deg', -1) >= margin else 'no'} | "
            f"{m.get('smoothness', float('nan')):.0f} | "
            f"{1000 * m.get('tool_position_error_max_m', float('nan')):.2f} | "
            f"{m.get('user_work_per_metre_N', float('nan')):.2f} | {m.get('hand_work_J', float('nan')):.3f} | "
            f"{m.get('mass_mean_kg', float('nan')):.2f} | {m.get('tick_time_median_us', float('nan')):.0f} |"
            + (clearance_cells(m) if room else "")
        )
    return "\n".join(lines)


CLEARANCE_HEAD = " clearance min (mm, coal) | at link, obstacle | penetration ticks | OBSTACLE ticks |"
"""The comparison table's columns for a room with obstacles."""


def clearance_cells(m: dict) -> str:
    """A row's clearance cells from its summary (:func:`qpnso.lab.metrics.clearance_summary`)."""
    return (
        f" {1000 * m.get('clearance_min_m', float('nan')):.1f} | "
        f"{m.get('clearance_min_link', '')}, {m.get('clearance_min_obstacle', '')} | "
        f"{m.get('penetration_ticks', '')} | {m.get('obstacle_ticks', '')} |"
    )


# ---------------------------------------------------------------- experiment
EXPERIMENT_FLAGS = {
    "mass-friction": ("subjects", "orders", "reps", "moves", "armature_kgm2", "strategies", "control_reps"),
    "elbow": ("subjects", "trials", "quiet_trials", "duration_scale", "armature_kgm2"),
    "preregister": (),
}
"""The flags each experiment takes (the others are refused by name)."""


def cmd_experiment(args: argparse.Namespace) -> int:
    """One of the papers' user experiments, on every core or a Dask cluster; prints the report."""
    from pathlib import Path

    from qpnso.lab.experiments import run_experiment

    options: dict[str, Any] = {}
    for flag in sorted({f for flags in EXPERIMENT_FLAGS.values() for f in flags}):
        value = getattr(args, flag)
        if value is None:
            continue
        if flag not in EXPERIMENT_FLAGS[args.name]:
            raise argparse.ArgumentTypeError(f"--{flag.replace('_', '-')} does not apply to experiment {args.name}")
        options[flag] = value
    if args.name == "preregister":
        return preregister(Path(args.out))
    output_path(args.out, "--out", folder=True)
    if "strategies" in options:
        from qpnso.lab.experiments.mass_friction import CONTROLS

        names = tuple(n.strip() for n in options.pop("strategies").split(",") if n.strip())
        options["strategies"] = tuple(n for n in names if n not in CONTROLS)
        options["controls"] = tuple(n for n in names if n in CONTROLS)
    if args.no_model_error:
        options["model_error"] = {"mass": 0.0, "friction": 0.0, "armature": 0.0, "torque_offset": 0.0}
    run_experiment(
        args.name,
        Path(args.out),
        options,
        seed=args.seed,
        workers=args.workers,
        scheduler=args.scheduler,
        progress=not args.quiet,
    )
    print((Path(args.out) / "report.md").read_text(), end="")
    return 0


def preregister(path: Any) -> int:
    """Write the mass/friction experiment's pre-registration (its work areas, from the model alone) to ``path``
    (a :class:`pathlib.Path`)."""
    from qpnso.lab.experiments.work_areas import preregistration

    output_path(str(path), "--out")
    text = preregistration()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    print(text, end="")
    return 0


# --------------------------------------------------------------------- study
def cmd_study(args: argparse.Namespace) -> int:
    """One of the papers' studies, on every core or a Dask cluster."""
    from pathlib import Path

    from qpnso.lab.studies import run_study

    output_path(args.out, "--out", folder=True)
    options = {}
    for item in args.option or []:
        key, sep, value = item.partition("=")
        if not sep:
            raise argparse.ArgumentTypeError(f"--option takes key=value, got {item!r}")
        options[key.strip()] = value.strip()
    summary = run_study(
        args.name,
        Path(args.out),
        n=args.n,
        seed=args.seed,
        workers=args.workers,
        scheduler=args.scheduler,
        progress=not args.quiet,
        options=options or None,
    )
    print_summary(
        {k: v for k, v in summary.items() if not isinstance(v, (dict, list))}, f"study {args.name} -> {args.out}"
    )
    for key, value in summary.items():
        if isinstance(value, dict):
            print(
                f"  {key}: "
                + ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in value.items())
            )
    return 0
