"""The ``qpnso`` command line.

Every sub-command is a small function ``cmd_<name>(args) -> int`` registered in
``build_parser``.  Errors that qpnso raises on purpose (bad robot, bad file,
bad angle, bad flag value, an output path that cannot be written...) are printed
as one line, ``qpnso: error: ...``, exit status 2; so is a file that cannot be
read or written after all.  A run that completes but fails its check (``qpnso
solve``: the tool left the trajectory by more than the tolerance) writes its
results, prints one line ``qpnso: failed: ...`` and exits with status 1.

The parser and :func:`main` are here; the sub-commands are in :mod:`.commands`
(info, intervals, trajectory, solve, simulate, plot, compare, study, view) and :mod:`.bench`
(``qpnso bench ...``), the argument and output helpers they share in :mod:`.common`.
"""

from __future__ import annotations

import argparse
import sys
from typing import Callable, Sequence

from qpnso.cli.bench import cmd_bench
from qpnso.cli.commands import (
    cmd_compare,
    cmd_experiment,
    cmd_info,
    cmd_intervals,
    cmd_plot,
    cmd_simulate,
    cmd_solve,
    cmd_study,
    cmd_trajectory,
    cmd_view,
)
from qpnso.cli.common import add_q_arguments, add_robot_arguments
from qpnso.errors import QpnsoError

__all__ = ["Handler", "build_parser", "main"]

Handler = Callable[[argparse.Namespace], int]

IGNORE_OBSTACLES_HELP = (
    "the controller is not given the scenario's obstacles; the room still has them and the run measures every "
    "link's clearance to them (coal)"
)


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
    p.add_argument(
        "--obstacles",
        default=None,
        help='TOML file of [[obstacles]] tables (type = "sphere" | "capsule" | "box" and their fields, m, world)',
    )
    p.add_argument(
        "--obstacle-margin",
        type=float,
        default=0.03,
        help="clearance every link keeps from the obstacles, METRES (default 0.03)",
    )
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
    p.add_argument(
        "--q0",
        default=None,
        help="start configuration in RADIANS, comma-separated (default: found for the first pose, elbow up)",
    )
    p.add_argument(
        "--strategy", default=None, help="qp (default), damped, fixed, elbow-up, gradient, gradient-impedance, rom"
    )
    p.add_argument("--config", default=None, help="TOML file of controller settings (flags override it)")
    p.add_argument("--dt", type=float, default=None, help="tick length, s (default 0.001)")
    p.add_argument("--out", default="result.npz", help="per-tick arrays (NumPy .npz)")
    p.add_argument("--summary", default=None, help="also write the summary as JSON")
    p.add_argument(
        "--tool-tolerance-mm",
        type=float,
        default=1.0,
        help="the run fails (exit status 1) if the tool ever leaves the path by more (default 1 mm)",
    )
    p.add_argument(
        "--tool-tolerance-deg",
        type=float,
        default=1.0,
        help="same for the tool's orientation error, DEGREES (default 1)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=cmd_solve)

    p = sub.add_parser("simulate", help="hands-on guidance simulation of a scenario (A, B, microscope, hold)")
    p.add_argument("--scenario", default="A", help="A, B, microscope, hold or a scenario .toml file")
    p.add_argument("--strategy", default=None, help="strategy (default qp)")
    p.add_argument("--config", default=None, help="TOML file of controller settings")
    p.add_argument("--duration-scale", type=float, default=1.0, help="run only this fraction of the path")
    p.add_argument("--out", required=True, help="folder for result.npz, summary.json, run.png")
    p.add_argument("--no-plot", action="store_true")
    p.add_argument("--ignore-obstacles", action="store_true", help=IGNORE_OBSTACLES_HELP)
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(handler=cmd_simulate, dt=None)

    p = sub.add_parser("plot", help="plot a result.npz (PNG)")
    p.add_argument("result")
    p.add_argument("--out", default="run.png")
    p.set_defaults(handler=cmd_plot)

    p = sub.add_parser("view", help="3-D replay of a run in the browser: a live server, or one HTML page (--html)")
    p.add_argument("result", nargs="?", default=None, help="a result.npz (of qpnso solve or simulate)")
    p.add_argument(
        "--scenario", default=None, help="instead of a file: simulate a scenario (A, B, microscope, hold, .toml)"
    )
    p.add_argument("--strategy", default=None, help="with --scenario: the strategy (default: the scenario's, qp)")
    p.add_argument("--duration-scale", type=float, default=None, help="with --scenario: run only this fraction")
    p.add_argument("--ignore-obstacles", action="store_true", help=f"with --scenario: {IGNORE_OBSTACLES_HELP}")
    p.add_argument("--html", default=None, help="write one self-contained page that plays the run, then exit")
    p.add_argument("--fps", type=float, default=20.0, help="frames per second of the page or timeline (default 20)")
    p.add_argument("--host", default="127.0.0.1", help="the live server's address (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8080, help="the live server's port (default 8080)")
    p.add_argument(
        "--robot",
        default=None,
        help="a file without a robot record: lwr4p, iiwa14, panda or a URDF (refused when it contradicts the file)",
    )
    p.add_argument("--tool-frame", default=None, help="with --robot: frame the tool is mounted on")
    p.add_argument("--tool-offset", default=None, help="with --robot: tool point in that frame, x,y,z in metres")
    p.add_argument("--obstacles", default=None, help="TOML file of [[obstacles]] drawn instead of the file's")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(handler=cmd_view)

    p = sub.add_parser("compare", help="several strategies on one scenario: table and figure")
    p.add_argument("--scenario", default="B")
    p.add_argument("--strategies", default="qp,damped,fixed,rom,gradient")
    p.add_argument("--duration-scale", type=float, default=1.0)
    p.add_argument("--out", required=True, help="folder for comparison.md and comparison.png")
    p.add_argument("--ignore-obstacles", action="store_true", help=IGNORE_OBSTACLES_HELP)
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

    p = sub.add_parser("experiment", help="a paper's user experiment with virtual surgeons (CSV, stats, report)")
    p.add_argument("name", choices=["mass-friction", "elbow", "preregister"])
    p.add_argument("--subjects", type=int, default=None, help="virtual surgeons (default: the paper's, 8 or 3)")
    p.add_argument("--orders", type=int, default=None, help="mass-friction: random target orders (default 5)")
    p.add_argument("--reps", type=int, default=None, help="mass-friction: repetitions of each order (default 3)")
    p.add_argument("--moves", type=int, default=None, help="mass-friction: targets per trial (default 6)")
    p.add_argument("--trials", type=int, default=None, help="elbow: trials per subject (default 3)")
    p.add_argument(
        "--quiet-trials", type=int, default=None, help="elbow: trials per subject with the tremor off (default 1)"
    )
    p.add_argument(
        "--strategies",
        default=None,
        help="mass-friction: comma-separated strategies and controls to run (default all; 'damped' required)",
    )
    p.add_argument(
        "--control-reps",
        type=int,
        default=None,
        help="mass-friction: repetitions the controls and the ablation run (default 3: every one, the groups' size)",
    )
    p.add_argument("--duration-scale", type=float, default=None, help="elbow: run only this fraction of each path")
    p.add_argument("--no-model-error", action="store_true", help="the plant is the controller's model exactly")
    p.add_argument(
        "--armature-kgm2",
        type=float,
        default=None,
        help="the rotor inertia (kg·m², >= 0) on every joint, controller and plant alike (default: the model's)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=None, help="processes (default: every core)")
    p.add_argument("--scheduler", default=None, help="Dask scheduler address (tcp://host:8786)")
    p.add_argument("--out", required=True, help="folder for trials.csv, stats.json, report.md, figures.png")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(handler=cmd_experiment)

    p = sub.add_parser("bench", help="time the cost evaluation or the control tick (median, p99)")
    p.add_argument("what", choices=["cost", "interval", "tick", "solvers", "fuzz"])
    add_robot_arguments(p)
    p.add_argument("-n", type=int, default=3000, help="timed calls per row; fuzz: ticks (default 3000)")
    p.add_argument("--strategies", default=None, help="comma-separated strategies for 'tick', 'fuzz' (default all)")
    p.add_argument("--seed", type=int, default=0, help="fuzz: random seed (default 0)")
    p.set_defaults(robot=None)  # fuzz: --robot may list several (default lwr4p,iiwa14,panda); else lwr4p
    p.add_argument("--dt-ms", default=None, help="fuzz: comma-separated tick lengths in ms (default 1,4)")
    p.add_argument(
        "--workers",
        type=int,
        default=1,
        help="fuzz: fresh processes at a time (each runs a shard of ticks, then each replay; 0: all in this "
        "process, no fresh process; default 1)",
    )
    p.add_argument(
        "--solver-time-budget-ms",
        type=float,
        default=None,
        help="fuzz: every controller's solver_time_budget, in ms of CPU time (default: none)",
    )
    p.add_argument("--quick", action="store_true", help="solvers: the small committed problem set (< 1 min)")
    p.add_argument(
        "--out",
        default=None,
        help="solvers: folder for report.md, results.csv, figure (default solver-bench); fuzz: the report as JSON",
    )
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
    except OSError as exc:  # a named file that cannot be read or written after all (disk full, removed meanwhile...)
        if exc.filename is None:
            raise
        print(f"qpnso: error: {file_error(exc)}", file=sys.stderr)
        return 2


def file_error(exc: OSError) -> str:
    """``exc`` as one line naming the file: the destination of a rename (the file asked for, not its temporary
    twin), else the file."""
    name = exc.filename2 if exc.filename2 is not None else exc.filename
    return f"{name}: {exc.strerror or exc}"
