"""Strategies side by side on the elbow paper's scenario B (first 3 s of the path).

Run: python examples/compare_strategies.py
(the whole path: qpnso compare --scenario B --out out/compare_B)
"""

from pathlib import Path

from qpnso.lab.plots import plot_comparison
from qpnso.lab.scenarios import simulate_scenario

runs = {s: simulate_scenario("B", s, duration_scale=3 / 36) for s in ("qp", "damped", "fixed")}
for name, run in runs.items():
    m = run.summary
    print(
        f"{name:8s} elbow mobility {m['elbow_mobility_deg']:6.2f} deg, "
        f"proximity {m['constraint_proximity_deg']:6.2f} deg, tool error {1e3 * m['tool_position_error_max_m']:.2f} mm"
    )
Path("out").mkdir(exist_ok=True)
print(
    "figure:",
    plot_comparison({k: r.arrays for k, r in runs.items()}, "out/compare_B.png", title="scenario B, first 3 s"),
)
