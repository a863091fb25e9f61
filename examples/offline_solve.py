"""Offline solve of a shipped trajectory, then its summary and a figure.

Run: python examples/offline_solve.py   (same as: qpnso solve examples/trajectories/hold_lwr4p.csv)
"""

from pathlib import Path

import qpnso
from qpnso.control.offline import solve_trajectory
from qpnso.control.trajectory import read_csv
from qpnso.lab.plots import plot_run

here = Path(__file__).parent
robot = qpnso.load_robot("lwr4p")
traj = read_csv(here / "trajectories" / "hold_lwr4p.csv")
result = solve_trajectory(robot, traj, config=qpnso.ControllerConfig(strategy="qp"))
for key in ("tool_position_error_max_m", "elbow_mobility_deg", "mass_mean_kg", "friction_force_mean_N"):
    print(f"{key:28s} {result.summary[key]:.4g}")
out = Path("out")
out.mkdir(exist_ok=True)
result.save(out / "hold_qp.npz")
print("figure:", plot_run(result.arrays, out / "hold_qp.png", title="hold, strategy qp"))
