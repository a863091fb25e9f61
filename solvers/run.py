# `--help` prints this docstring as a raw description: `fmt: skip` keeps the command's indent.
"""Run the QP solver benchmark (same as ``qpnso bench solvers [--quick] --out DIR``).

    python solvers/run.py --quick --out solvers/results
"""  # fmt: skip

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # the checkout's qpnso

from qpnso.lab.solver_bench import run_solver_benchmark  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="committed small set, 0.3 s closed loop (< 1 min)")
    parser.add_argument("--out", type=Path, required=True, help="output directory")
    parser.add_argument("--solvers", nargs="*", default=None, help="names (default: all installed + proxsuite)")
    args = parser.parse_args(argv)
    print(run_solver_benchmark(args.out, quick=args.quick, solvers=args.solvers, progress=print))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
