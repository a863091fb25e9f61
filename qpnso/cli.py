"""The ``qpnso`` command line.

Every sub-command is a small function ``cmd_<name>(args) -> int`` registered in
``build_parser``.  Errors that qpnso raises on purpose (bad robot, bad file,
bad angle...) are printed as one line, ``qpnso: error: ...``, exit status 2.
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


def sample_configuration(robot) -> np.ndarray:
    """A non-singular configuration inside the limits: elbow bent, wrist bent (rad)."""
    q = np.zeros(robot.nq)
    q[1], q[3], q[5] = 0.5, -1.2, 0.8
    if robot.name == "panda":  # Franka's "ready" posture
        q = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
    return np.clip(q, robot.q_min, robot.q_max)


def robot_q(args: argparse.Namespace, robot) -> np.ndarray:
    """``--q`` (rad) or ``--q-deg`` (degrees), else the sample configuration; checked."""
    if getattr(args, "q_deg", None) is not None:
        return robot.check_q(np.radians(parse_vector(args.q_deg, robot.nq, "--q-deg")), "--q-deg")
    if getattr(args, "q", None) is not None:
        return robot.check_q(parse_vector(args.q, robot.nq, "--q"), "--q")
    return sample_configuration(robot)


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


def load_cli_robot(args: argparse.Namespace):
    from qpnso.robot import load_robot

    offset = parse_vector(args.tool_offset, 3, "--tool-offset") if args.tool_offset else None
    return load_robot(args.robot, tool_frame=args.tool_frame, tool_offset=offset)


# ---------------------------------------------------------------------- info
def cmd_info(args: argparse.Namespace) -> int:
    """Print the model: joints, limits, masses, tool frame, costs at a sample q."""
    from qpnso.costs import TERMS, CostModel

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


# --------------------------------------------------------------------- bench
def cmd_bench(args: argparse.Namespace) -> int:
    """Time the cost or the control tick; print a Markdown table of medians and p99."""
    from qpnso import benchmark

    robot = load_cli_robot(args)
    if args.what == "cost":
        rows = benchmark.bench_cost(robot, n=args.n)
        title = f"cost.value + cost.gradient, {robot.name}, mass + friction force"
    else:
        strategies = tuple(args.strategies.split(",")) if args.strategies else None
        rows = benchmark.bench_tick(robot, n=args.n, strategies=strategies)
        title = f"Controller.step, {robot.name}, dt = 1 ms"
    print(benchmark.table(rows, title))
    return 0


# ------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="qpnso", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("info", help="print a robot model and its costs at a sample configuration")
    add_robot_arguments(p, positional=True)
    add_q_arguments(p)
    p.set_defaults(handler=cmd_info)

    p = sub.add_parser("bench", help="time the cost evaluation or the control tick (median, p99)")
    p.add_argument("what", choices=["cost", "tick"])
    add_robot_arguments(p)
    p.add_argument("-n", type=int, default=3000, help="timed calls per row (default 3000)")
    p.add_argument("--strategies", default=None, help="comma-separated strategies for 'tick' (default all)")
    p.set_defaults(handler=cmd_bench)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    handler: Handler = args.handler
    try:
        return handler(args)
    except argparse.ArgumentTypeError as exc:
        parser.error(str(exc))
    except QpnsoError as exc:
        print(f"qpnso: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
