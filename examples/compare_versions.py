"""Two qpnso versions' ticks in one process, timed in turns, with Pink's solve_ik beside them.

Run: python examples/compare_versions.py OTHER_CHECKOUT [-n 3000] [--strategies qp,damped,...] [--moving]
(without OTHER_CHECKOUT: this version against itself, 300 ticks of qp: a check that the script works).

OTHER_CHECKOUT is a folder holding another version's `qpnso/` and `models/` (for instance
`git worktree add /tmp/qpnso_old 0516678`). Its package is copied to a temporary folder as
`qpnso_other` (imports rewritten) so that both versions run in this process, the rows taken
in turns of 250 ticks (`qpnso.lab.benchmark.interleaved`): on a shared VM whose speed drifts by
2x over seconds, only rows timed side by side can be compared (separate runs of the same
code differed by 30 %, measured). Prints each strategy's median and p99 for both versions
and their ratio; the tool is held from the robot's sample configuration (``--moving``: it moves on a
5 cm circle at 0.5 Hz while turning, :class:`qpnso.lab.benchmark.MovingTarget`, Pink's row too).
"""

from __future__ import annotations

import argparse
import importlib
import re
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

import qpnso
from qpnso.lab.benchmark import MovingTarget, held_tool_ticks, interleaved, moving_tool_ticks, pink_ticks

_IMPORTS = (
    (re.compile(r"\bfrom qpnso\b"), "from qpnso_other"),
    (re.compile(r"\bimport qpnso\b"), "import qpnso_other"),
    (re.compile(r"\bqpnso\.([a-z_]+)"), r"qpnso_other.\1"),
)


def rewrite_imports(text: str) -> str:
    """A module of the other version, importing ``qpnso_other`` instead of ``qpnso``."""
    for pattern, replacement in _IMPORTS:
        text = pattern.sub(replacement, text)
    return text


def load_other(checkout: Path) -> object:
    """The other checkout's package, imported as ``qpnso_other`` from a rewritten copy."""
    root = Path(tempfile.mkdtemp(prefix="qpnso_other_"))
    shutil.copytree(checkout / "qpnso", root / "qpnso_other", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(checkout / "models", root / "models")
    for path in (root / "qpnso_other").rglob("*.py"):
        path.write_text(rewrite_imports(path.read_text(encoding="utf-8")), encoding="utf-8")
    sys.path.insert(0, str(root))
    return importlib.import_module("qpnso_other")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("other", type=Path, nargs="?", help="another checkout (holding qpnso/ and models/)")
    parser.add_argument("-n", type=int, default=None, help="timed ticks per row (default 3000)")
    parser.add_argument("--strategies", default=None, help="comma-separated (default all)")
    parser.add_argument("--moving", action="store_true", help="the tool on a moving target (MovingTarget), not held")
    args = parser.parse_args()
    smoke = args.other is None
    strategies = (args.strategies or ("qp" if smoke else ",".join(qpnso.STRATEGIES))).split(",")
    n = args.n or (300 if smoke else 3000)
    runs = {}
    assert (
        rewrite_imports("from qpnso.qp.line import x; import qpnso; qpnso.control.tick")
        == "from qpnso_other.qp.line import x; import qpnso_other; qpnso_other.control.tick"
    )
    for lib, tag in ((qpnso, "this"), (qpnso if smoke else load_other(args.other), "other")):
        robot = lib.load_robot("lwr4p", tool_offset=[0.0, 0.0, 0.1])
        q0 = robot.sample_configuration()
        for name in strategies:
            ctrl = lib.Controller(robot, lib.ControllerConfig(strategy=name))
            ctrl.cost.wait_compiled()
            ctrl.evaluate.wait_compiled()
            ctrl.reset(q0)
            runs[f"{name} {tag}"] = (moving_tool_ticks if args.moving else held_tool_ticks)(ctrl, q0)
    robot = qpnso.load_robot("lwr4p", tool_offset=[0.0, 0.0, 0.1])
    pink = pink_ticks(robot, robot.sample_configuration(), MovingTarget() if args.moving else None)
    if pink is not None:
        runs["Pink solve_ik"] = pink[0]
    times = {name: 1e6 * t for name, t in interleaved(runs, n, chunk=250).items()}
    print("| strategy | this median µs | other median µs | this/other | this p99 µs | other p99 µs |")
    print("|---|---|---|---|---|---|")
    for name in strategies:
        a, b = times[f"{name} this"], times[f"{name} other"]
        print(
            f"| {name} | {np.median(a):.1f} | {np.median(b):.1f} | {np.median(a) / np.median(b):.3f} | "
            f"{np.percentile(a, 99):.0f} | {np.percentile(b, 99):.0f} |"
        )
    if "Pink solve_ik" in times:
        print(f"\nPink solve_ik in the same run: median {np.median(times['Pink solve_ik']):.1f} µs")


if __name__ == "__main__":
    main()
