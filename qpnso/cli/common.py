"""What the sub-commands share: vectors and configurations from flags, the robot from ``--robot``,
the optional matplotlib, progress bars, printed summaries and notes, JSON output."""

from __future__ import annotations

import argparse

import numpy as np


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


def progress_bar(enabled: bool, desc: str):
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


def output_path(path: str, flag: str, folder: bool = False) -> str:
    """``path`` if the command can write its output there, checked before the work rather than after a long
    run: a file (a folder with ``folder``) that is not a folder (not a file), in a folder qpnso can write (a
    missing one is made when the output is written, in the nearest existing one); else an InputError naming
    ``flag``, ``path`` and the problem."""
    import tempfile
    from pathlib import Path

    from qpnso.errors import InputError

    target = Path(path)
    kinds = ("file", "folder") if folder else ("folder", "file")
    if target.exists() and target.is_dir() != folder:
        raise InputError(f"{flag} {path}: is a {kinds[0]}, not a {kinds[1]}")
    existing = (target if folder else target.parent).absolute()
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise InputError(f"{flag} {path}: {existing} is a file, not a folder")
    try:
        with tempfile.NamedTemporaryFile(dir=existing, prefix=".qpnso-probe-"):
            pass
    except OSError as exc:
        raise InputError(f"{flag} {path}: cannot write in {existing} ({exc.strerror or exc})") from None
    return path


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
        print(
            f"  note: {slow} of {int(summary['ticks'])} ticks ({100 * slow / summary['ticks']:.1f} %) took longer "
            f"than the {1000 * dt:g} ms control period; the longest took {summary['tick_time_max_ms']:.4g} ms"
        )
