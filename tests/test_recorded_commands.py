"""Today's recorded commands (issue 33): the main job's and fuzz episodes', replayed into a fresh controller.

``tests/data/record_commands.py`` recorded, before the tick moves to the C++ core, every input of the main job
(``qpnso solve examples/trajectories/guidance_lwr4p.csv``) and of seeded closed-loop fuzz episodes, and the
commands they gave (``tests/data/commands_*.npz``, made as ``commands.json`` says).  Here the *inputs* are
replayed, every call in order from the recorded reset (the controller has memory: the previous command, the
reference, the elbow's interval and ROM, the QP's warm starts), and each recorded command's ``dq``, ``q_des`` and
``tau`` must agree with the recording to :data:`TOLERANCE`, its status bits exactly; a call the recording
refused must be refused again.  The plant does not enter it (no ``q ← q + dt·dq`` here).

By default the main job is replayed for its first :data:`MAIN_REPLAYED` ticks (every command of them is recorded);
``QPNSO_RECORDED_ALL=1`` replays all its ticks (36 141, about 12 s) and checks every kept command.
"""

from __future__ import annotations

import functools
import importlib.util
import json
import math
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
import pytest
from conftest import SOURCE_TREE

from qpnso.control.config import ControllerConfig
from qpnso.control.controller import Controller
from qpnso.control.trajectory import read_csv
from qpnso.errors import QpnsoError
from qpnso.model.robot import load_robot_spec

DATA = Path(__file__).resolve().parent / "data"

TOLERANCE = {"dq": (1e-9, 1e-9), "q_des": (2e-11, 0.0), "tau": (1e-9, 1e-9)}
"""(atol, rtol) of each command entry: |replayed − recorded| ≤ atol + rtol·|recorded| (rad/s, rad, N·m).

Measured (this machine, each recording replayed whole, the main job's 36 141 ticks too, in six fresh processes: four
with ``QPNSO_COMPILE=off``, two with ``sync``):

* the same code replayed: the main job and five of the seven fuzz episodes bit for bit, in every process.  Two episodes
  differ in some processes and not in others (one of two answers per process): episode 24 (iiwa14, 4 ms, elbow-up) from
  the first tick after a joint overshot its limit (``Q_OUT_OF_LIMITS|QP_FALLBACK``), by 7.6e-17 rad/s growing to 1.2e-14
  rad/s on ``dq`` (relative 2.5e-12), 4.4e-16 rad on ``q_des``; episode 48 (iiwa14, 1 ms, gradient-impedance) from its
  tick 267 by up to 6.7e-16 rad/s, 3.5e-18 rad.  ``tau`` never differed.  Round-off that depends on the process, not on
  the code (most likely where its allocator put an array: a vectorised reduction's summation order follows the data's
  alignment).  Two *recordings* (closed loops, the noise fed back into ``q``) of episode 24 differed by 4.8e-12 rad/s on
  ``dq`` and 3.1e-11 N·m on ``tau``: why the check replays inputs;
* the state function by CasADi's runtime (``QPNSO_COMPILE=off``, the recording's) against compiled C
  (``QPNSO_COMPILE=sync``): bit for bit (the same operations in the same order, no FMA on the generic x86-64 target),
  apart from the same two episodes' noise.

Chosen: ``dq`` 1e-9 rad/s absolute and 1e-9 relative, ~1e5 times the largest difference measured: room for the C++
core's round-off (operations reordered by Eigen and the compiler: ~1e-15 per tick) growing through the controller's
memory (7.6e-17 to 1.2e-14 in 290 ticks in episode 24) and through the QPs solved to ProxSuite's 1e-11 tolerance,
while a wrong gain, row or sign (1e-6 and more) fails.  ``q_des`` = q + dt·dq: 2e-11 rad absolute, dq's tolerance
(≤ 3e-9 rad/s at |dq| ≤ 2 rad/s) times dt ≤ 4 ms plus the round-off of q.  ``tau``: 1e-9 N·m absolute and 1e-9
relative (0 measured; torques up to ~100 N·m, their round-off ~1e-14).  Status bits must be equal."""

MAIN_REPLAYED = 2000
"""The main job's ticks replayed by default (from its reset, in order)."""


def _recorder() -> Any:
    """``tests/data/record_commands.py`` as a module (its :func:`decode_q` unpacks the main job's ``q``)."""
    spec = importlib.util.spec_from_file_location("record_commands", DATA / "record_commands.py")
    assert spec is not None and spec.loader is not None
    module = sys.modules.setdefault(spec.name, importlib.util.module_from_spec(spec))
    spec.loader.exec_module(module)  # (in sys.modules first: its dataclasses look their module up)
    return module


@functools.cache
def _meta() -> dict[str, Any]:
    """``commands.json``: what made the recordings (read once; not to be changed)."""
    return json.loads((DATA / "commands.json").read_text())


@functools.cache
def _load(name: str) -> dict[str, np.ndarray]:
    """A recording's arrays (read once; not to be changed: the tests copy what they modify)."""
    with np.load(DATA / name, allow_pickle=False) as f:
        return {k: f[k] for k in f.files}


def controller(robot_spec: dict, config: dict) -> Controller:
    """A fresh controller for a recording: its robot record and its controller settings."""
    return Controller(load_robot_spec(robot_spec), ControllerConfig.from_dict(config))


def close(replayed: np.ndarray, recorded: np.ndarray, atol: float, rtol: float) -> np.ndarray:
    """Per row: every entry within ``atol + rtol·|recorded|`` (NaN never is)."""
    return np.all(np.abs(replayed - recorded) <= atol + rtol * np.abs(recorded), axis=-1)


def check_commands(where: str, replayed: dict[str, np.ndarray], recorded: dict[str, np.ndarray]) -> None:
    """Status bits equal, ``dq``, ``q_des``, ``tau`` within tolerance; the message names the first bad row."""
    bad = np.flatnonzero(replayed["status"] != recorded["status"])
    assert bad.size == 0, (
        f"{where}: status differs at {bad.size} rows, first row {bad[0]}: "
        f"{replayed['status'][bad[0]]} != {recorded['status'][bad[0]]}"
    )
    for key, (atol, rtol) in TOLERANCE.items():
        ok = close(replayed[key], recorded[key], atol, rtol)
        if not ok.all():
            k = int(np.flatnonzero(~ok)[0])
            diff = np.max(np.abs(replayed[key] - recorded[key]), axis=-1)
            raise AssertionError(
                f"{where}: {key} differs at {int(np.sum(~ok))} rows, first row {k} by {diff[k]:.3g} "
                f"(largest {np.max(diff):.3g}); replayed {replayed[key][k]}, recorded {recorded[key][k]}"
            )


# ----------------------------------------------------------------------- main job
def main_inputs(meta: dict, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The main job's twists (n, 6) and reference poses (n, 3, 3), (n, 3), as ``solve_trajectory`` samples them."""
    traj = read_csv(SOURCE_TREE / meta["trajectory"])
    dt = meta["config"]["dt"]
    times = traj.t[0] + np.arange(n) * dt
    positions, rotations, v, w = traj.samples(times)
    return np.concatenate([v, w], axis=1), rotations, positions


def replay_main(ticks: int) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The main job's first ``ticks`` ticks replayed: (replayed, recorded) at its kept ticks among them."""
    meta, rec = _meta()["main"], _load("commands_main.npz")
    q = _recorder().decode_q(rec["q_planes"])
    np.testing.assert_array_equal(q[0], rec["q0"], err_msg="the main job's first tick is not at its reset")
    twists, rotations, positions = main_inputs(meta, meta["ticks"])
    kept = rec["tick"] < ticks
    for name, full in (("twist", twists), ("pose_R", rotations), ("pose_p", positions)):
        np.testing.assert_array_equal(full[rec["tick"]], rec[name], err_msg=f"the trajectory's {name} changed")
    ctrl = controller(meta["robot"], meta["config"])
    ctrl.reset(rec["q0"])
    want = set(rec["tick"][kept].tolist())
    out: dict[str, list] = {"dq": [], "q_des": [], "tau": [], "status": []}
    for k in range(ticks):
        cmd = ctrl.step(q[k], tool_twist=twists[k], tool_pose=pin.SE3(rotations[k], positions[k]))
        if k in want:
            out["dq"].append(cmd.dq)
            out["q_des"].append(cmd.q_des)
            out["tau"].append(cmd.tau)
            out["status"].append(int(cmd.status.value))
    recorded = {key: rec[key][kept] for key in ("dq", "q_des", "tau", "status")}
    return {key: np.array(v) for key, v in out.items()}, recorded


def test_main_job_replays_to_its_recorded_commands() -> None:
    ticks = _meta()["main"]["ticks"] if os.environ.get("QPNSO_RECORDED_ALL") == "1" else MAIN_REPLAYED
    replayed, recorded = replay_main(ticks)
    assert len(recorded["dq"]) >= min(ticks, MAIN_REPLAYED)
    check_commands(f"main job, first {ticks} ticks", replayed, recorded)


# ----------------------------------------------------------------------- fuzz
def replay_calls(ctrl: Controller, calls: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Every call of one recorded run, in order: its command, or NaN and status -1 where it was refused."""
    n, nq = len(calls["q"]), ctrl.robot.nq
    out = {"dq": np.full((n, nq), math.nan), "q_des": np.full((n, nq), math.nan), "tau": np.full((n, nq), math.nan)}
    status = np.full(n, -1, dtype=np.int64)
    for k in range(n):
        pose = pin.SE3(calls["pose_R"][k], calls["pose_p"][k]) if calls["has_pose"][k] else None
        try:
            cmd = ctrl.step(
                calls["q"][k].copy(),
                dq=calls["dq_in"][k].copy() if calls["has_dq"][k] else None,
                tool_twist=calls["twist"][k].copy() if calls["has_twist"][k] else None,
                tool_pose=pose,
            )
        except QpnsoError:
            continue
        out["dq"][k], out["q_des"][k], out["tau"][k], status[k] = cmd.dq, cmd.q_des, cmd.tau, int(cmd.status.value)
    return {**out, "status": status}


FUZZ = _meta()["fuzz"]["episodes"]


@functools.cache
def replay_episode(index: int) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Fuzz episode ``index`` of the recording replayed: (replayed, recorded) at its calls that gave a command;
    the calls refused must be the same."""
    episode = FUZZ[index]
    rec = _load("commands_fuzz.npz")
    rows = rec["episode"] == index
    calls = {k: v[rows] for k, v in rec.items()}
    ctrl = controller(episode["robot"], episode["controller"])
    ctrl.reset(np.array(episode["q0"]))
    replayed = replay_calls(ctrl, calls)
    refused = calls["outcome"] == 1
    np.testing.assert_array_equal(replayed["status"] == -1, refused, err_msg="the refused calls differ")
    keys = ("dq", "q_des", "tau", "status")
    return {k: replayed[k][~refused] for k in keys}, {k: calls[k][~refused] for k in keys}


@pytest.mark.parametrize("index", range(len(FUZZ)), ids=[f"episode{e['episode']}" for e in FUZZ])
def test_fuzz_episode_replays_to_its_recorded_commands(index: int) -> None:
    replayed, recorded = replay_episode(index)
    check_commands(f"fuzz episode {FUZZ[index]['episode']}", replayed, recorded)


def test_the_check_fails_beyond_its_tolerance() -> None:
    """A recorded command moved by twice its tolerance on one entry, or its status changed by one bit, fails the
    check; moved by half its tolerance it passes."""
    replayed, recorded = replay_episode(0)
    check_commands("unchanged", replayed, recorded)
    k = len(recorded["dq"]) // 2
    for key, (atol, rtol) in TOLERANCE.items():
        for factor, fails in ((2.0, True), (0.5, False)):
            moved = {name: value.copy() for name, value in recorded.items()}
            moved[key][k, 3] += factor * (atol + rtol * abs(recorded[key][k, 3]))
            if fails:
                with pytest.raises(AssertionError, match=f"{key} differs at 1 rows, first row {k}"):
                    check_commands("moved", replayed, moved)
            else:
                check_commands("moved a little", replayed, moved)
    flipped = {name: value.copy() for name, value in recorded.items()}
    flipped["status"][k] ^= 1
    with pytest.raises(AssertionError, match=f"status differs at 1 rows, first row {k}"):
        check_commands("status", replayed, flipped)
