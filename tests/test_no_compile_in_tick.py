"""Nothing compiles or loads inside a control tick (issue 31, item 4): the constructor's warm-up calls every
Numba kernel the ticks call, with the same argument types (layout, dtype, writability), so a tick never waits
for Numba's type dispatch to compile a new signature or load it from the disk cache (959 ms on a cold cache,
15–22 ms in every new process, measured when a Panda walk handed Pinocchio's Fortran-ordered rotation to
``store_interval``).

Each case runs in a fresh Python process (a kernel compiled by an earlier test of this process would hide a
missing warm-up): it builds one controller, takes the signatures of every qpnso Numba dispatcher, runs ticks of
every kind a user's loop can send (a moving tool, a held tool, a violent pull, a given tool pose, measured ``dq``,
a ``q`` a little outside its limits, bad inputs, a reset with the elbow outside its ROM, moved obstacles), and
prints any signature that appeared; the Panda's ticks also finish several numerical walks of its continuity
interval.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from conftest import ALL_ROBOTS

from qpnso.control.config import STRATEGIES

_CHILD = textwrap.dedent(
    r"""
    import json, math, re, sys
    import numba
    import numpy as np
    import qpnso
    from qpnso.control.memory import KNOWN
    from qpnso.errors import QpnsoError
    from qpnso.lab.benchmark import MovingTarget, obstacles_around
    from qpnso.model.obstacles import Sphere

    robot_name, strategy, with_obstacles, moving_ticks = sys.argv[1], sys.argv[2], sys.argv[3] == "1", int(sys.argv[4])


    def signatures():
        found = {}
        for name, module in list(sys.modules.items()):
            if not name.startswith("qpnso") or module is None:
                continue
            for value in list(vars(module).values()):
                if isinstance(value, numba.core.registry.CPUDispatcher):
                    found[value.py_func.__module__ + "." + value.py_func.__qualname__] = value
        return {key: [_short(s) for s in d.signatures] for key, d in found.items()}


    def _short(signature):  # a signature's types, a record's fields left out (its size stays)
        return re.sub(r"Record\(\[.*?\], (\d+), (True|False)\)", r"Record(\1)", str(signature))


    robot = qpnso.load_robot(robot_name)
    q0 = robot.sample_configuration()
    far = tuple(Sphere(center=(5.0 + i, 5.0, 5.0), radius=0.05) for i in range(5))  # (9 volumes: a room of 9)
    obstacles = obstacles_around(robot, q0) + far if with_obstacles else ()
    ctrl = qpnso.Controller(robot, qpnso.ControllerConfig(strategy=strategy, obstacles=obstacles))
    before = signatures()
    dt, target = ctrl.config.dt, MovingTarget()
    stored = 0


    def tick(q, **kwargs):
        global stored
        cmd = ctrl.step(q, **kwargs)
        m = ctrl.records.memory[0]
        stored += bool(m["iv_age"] == 0.0 and m["iv_known"] == KNOWN)
        return q + dt * cmd.dq, cmd


    def refused(*args, **kwargs):
        try:
            ctrl.step(*args, **kwargs)
        except QpnsoError:
            return
        raise AssertionError(f"not refused: {args} {kwargs}")


    ctrl.reset(q0)
    q = q0.copy()
    for k in range(moving_ticks):  # the tool moving: intervals renewed (the Panda's walks)
        q, cmd = tick(q, tool_twist=target.twist(k * dt), dq=cmd.dq if k else None)
    for k in range(40 if with_obstacles else 0):  # the volumes moved every tick (a walk under way restarts), fewer
        moved = Sphere(center=(0.6, 0.1 + 1e-4 * k, 0.4), radius=0.03)  # than the room
        if k % 2:
            ctrl.set_obstacles(obstacles[:3] + (moved,))  # its velocity estimated
        else:
            ctrl.set_obstacles(obstacles[:4], velocities=[None, [0.01, 0.0, 0.0], None, [0.0] * 6])
        q, cmd = tick(q, tool_twist=target.twist(k * dt))
    if with_obstacles:
        ctrl.set_obstacles(obstacles[:4])  # (fewer volumes than the room: a Panda walk to its end with them)
        for k in range(800 if robot_name == "panda" else 20):
            q, cmd = tick(q, tool_twist=target.twist(k * dt))
    for _ in range(30):  # held
        q, cmd = tick(q)
    frozen = q.copy()
    frozen.setflags(write=False)
    for given in (list(q), np.repeat(q, 2)[::2], frozen, q.astype(np.float32)):  # a list, a strided view, a
        q, cmd = tick(given, dq=list(cmd.dq), tool_twist=(0.01, 0.0, 0.0, 0.0, 0.0, 0.0))  # read-only, float32
    for _ in range(20):  # a violent pull, then held: fallbacks, second passes, the tool limited
        q, cmd = tick(q, tool_twist=[2.0, 0.0, 0.0, 0.0, 1.0, 0.0])
    for _ in range(30):
        q, cmd = tick(q)
    pose = robot.tool_pose(q)  # a given tool pose (offline tracking)
    for _ in range(5):
        q, cmd = tick(q, tool_pose=pose)
    refused(np.full(robot.nq, np.nan))
    refused(q, tool_twist=[np.inf, 0, 0, 0, 0, 0])
    refused(q0 + 100.0)
    refused(q, dq=np.full(robot.nq, 1e3))
    outside = q0.copy()  # a joint a little outside its limit (within the tolerance): brought back
    outside[1] = robot.q_max[1] + math.radians(0.5)
    ctrl.reset(np.clip(outside, robot.q_min, robot.q_max))
    q = outside
    for _ in range(20):
        q, cmd = tick(q)
    ctrl.reset(q0, ns0=ctrl.evaluate(q0).arm_angle + 1.5)  # the elbow outside its ROM: rom's set-point, the slack
    q = q0.copy()
    for k in range(100):
        q, cmd = tick(q, tool_twist=target.twist(k * dt))
    after = signatures()
    new = {key: sigs[len(before.get(key, [])):] for key, sigs in after.items() if sigs[len(before.get(key, [])):]}
    print(json.dumps({"new": new, "stored": stored}))
    """
)


def _run(robot: str, strategy: str, obstacles: bool, moving_ticks: int, cwd: Path) -> dict:
    """The child's report: ``new`` signatures by kernel, ``stored`` continuity intervals stored by the ticks.  It
    runs in ``cwd`` (``python -c`` imports from its working folder first: not the source tree's qpnso)."""
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_DISABLE_JIT"}
    env["QPNSO_COMPILE"] = "off"  # (CasADi's own compile is not Numba's; off keeps the child's CPU low)
    args = [robot, strategy, "1" if obstacles else "0", str(moving_ticks)]
    done = subprocess.run(
        [sys.executable, "-c", _CHILD, *args], env=env, cwd=cwd, capture_output=True, text=True, timeout=900
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.jit
@pytest.mark.parametrize("strategy", STRATEGIES)
@pytest.mark.parametrize("robot", ALL_ROBOTS)  # (the Panda with example-robot-data)
def test_nothing_compiles_after_the_constructor(robot: str, strategy: str, tmp_path: Path) -> None:
    """Every strategy on every robot, with and without obstacles: no kernel gains a signature after the
    constructor; the Panda's ticks finish several numerical walks (the walk-finished path)."""
    moving = 2500 if robot == "panda" else 300
    for obstacles in (True, False):
        report = _run(robot, strategy, obstacles, moving, tmp_path)
        assert report["new"] == {}, f"{robot} {strategy} obstacles={obstacles}: compiled in a tick: {report['new']}"
        if robot == "panda":
            assert report["stored"] >= 3, report
