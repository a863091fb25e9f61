"""Regenerate the solver benchmark's problem sets from real controller runs.

    python solvers/record.py            # solvers/problems/quick.npz (committed, ~560 QPs)
    python solvers/record.py --full     # solvers/problems/full.npz (not committed, ~4000 QPs)

Each source (scenarios A and B, the guidance path on the iiwa14, held tools at
random postures of both robots) is tracked offline by the shipped controller;
the QPs of both levels are recorded tick by tick by wrapping that controller's
``qp.solve`` (see ``qpnso.lab.solver_bench.record.record_problem_set``), and each gets a
high-accuracy reference solution (DAQP / quadprog / ProxQP at 1e-12, cross-checked).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))  # the checkout's qpnso when run from a source tree

from qpnso.lab.solver_bench import load_problems, record_problem_set  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--full", action="store_true", help="the large set (longer runs, more ticks kept)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random held-tool postures")
    parser.add_argument(
        "--out", type=Path, default=None, help="output .npz (default solvers/problems/{quick,full}.npz)"
    )
    args = parser.parse_args(argv)
    out = args.out or HERE / "problems" / ("full.npz" if args.full else "quick.npz")
    t0 = time.perf_counter()
    record_problem_set(out, full=args.full, seed=args.seed, progress=print)
    problems, meta = load_problems(out)
    spread = max((p.ref_spread for p in problems if p.ref_spread == p.ref_spread), default=float("nan"))
    print(
        f"{out}: {len(problems)} problems, {out.stat().st_size / 1e3:.0f} kB, "
        f"reference cross-check spread {spread:.1e}, {time.perf_counter() - t0:.0f} s"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
