"""Your own 1 kHz control loop with qpnso.Controller (kinematic robot stand-in).

Run: python examples/control_loop.py
Replace `read_joints` / `send` with your robot's interface (FRI, ROS, ...).
"""

import gc

import numpy as np

import qpnso

robot = qpnso.load_robot("lwr4p", tool_offset=[0.0, 0.0, 0.10])  # tool point 10 cm beyond the flange
config = qpnso.ControllerConfig(
    dt=1e-3,
    strategy="qp",
    rom_half_width_deg=30,
    safety_margin_deg=10,
    weights=qpnso.CostWeights(mass=1.0, friction_force=1.0),
)
ctrl = qpnso.Controller(robot, config)

q = np.radians([10.0, 40.0, -10.0, -70.0, 20.0, 50.0, 0.0])  # measured joints, rad
ctrl.reset(q)  # holds this tool pose, centres the ROM on this arm angle
start = robot.tool_pose(q)
gc.collect()  # real time: a full garbage collection inside a tick scans ~130 000 objects (80 ms);
gc.freeze()  # frozen now, the collector only looks at what the loop itself makes (README, "Real-time use")

for tick in range(1000):  # one second
    twist = np.zeros(6)  # the surgeon's tool motion (m/s, rad/s, world); zero: tool held
    cmd = ctrl.step(q, tool_twist=twist)
    if not cmd.ok:
        print(f"tick {tick}: {cmd.status} {cmd.message}")
    # send(cmd.q_des) to a position-controlled arm, or send(cmd.tau) to a torque-controlled one
    q = cmd.q_des  # stand-in for the robot following the set-point

gc.unfreeze()  # the loop is over: objects frozen at exit would never be finalised
drift = np.linalg.norm(robot.tool_pose(q).translation - start.translation)
print(
    f"arm angle {np.degrees(cmd.arm_angle):.2f} deg in ROM_t {np.degrees(cmd.rom).round(2)} deg, "
    f"cost {cmd.cost:.4f}, tool drift {drift:.1e} m, last tick {1e6 * cmd.tick_time:.0f} µs"
)
