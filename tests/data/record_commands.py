"""Record today's control commands (issue 33), so the C++ port of the tick can be checked against them.

Run from the source tree: ``QPNSO_COMPILE=off python tests/data/record_commands.py`` (30 s once the Numba
kernels are cached, 4 min the first time).  It writes, beside this file:

* ``commands_main.npz``: the main job, ``qpnso solve examples/trajectories/guidance_lwr4p.csv`` with the CLI's
  defaults (the LWR4+ with its flange as the tool, ``ControllerConfig()``, the start configuration
  :func:`~qpnso.control.offline.initial_configuration` finds), run by :func:`~qpnso.control.offline.solve_trajectory`
  itself;
* ``commands_fuzz.npz``: closed-loop fuzz episodes (:mod:`qpnso.lab.fuzz`, seed :data:`FUZZ_SEED`), each run alone
  by :func:`~qpnso.lab.fuzz.run_fuzz` on a fresh controller, as the fuzzer reproduces one episode;
* ``commands.json``: what made them (the qpnso commit, the package versions, the robots, configs and seeds).

Both runs are recorded by a :class:`~qpnso.control.controller.Controller` subclass (:class:`RecordingController`)
put in place of the class the runner builds: every ``step`` call after a ``reset`` is kept, its inputs (``q``,
``dq``, ``tool_twist``, ``tool_pose``; rad, rad/s, m/s then rad/s, world frame) and its outcome (the command's
``dq`` rad/s, ``q_des`` rad, ``tau`` N·m and status bits, or "refused" for a ``QpnsoError``).  The check
(``tests/test_recorded_commands.py``) replays the *inputs* into a fresh controller, tick by tick in order, and
compares the outputs: the plant (the offline solve's ``q ← q + dt·dq``, the fuzzer's loop with its overshoots and
bad inputs) does not enter it.

What is kept:

* main job: the inputs of every tick (``q``; the twist and reference pose the trajectory gives that tick are
  recomputed from the CSV by the check, and kept here at the recorded ticks to check that), the command of the
  first :data:`MAIN_FIRST` ticks, of every :data:`MAIN_EVERY`-th tick after, and of the last tick;
* fuzz: every call of each episode, valid ticks and the fuzzer's bad inputs alike (an accepted bad input is a
  tick like any other; a refused one is replayed and must be refused again).  A bad input that is not an array of
  floats of the right shape (complex, a list of strings, a wrong shape, a ``tool_pose`` that is not an SE3) cannot
  be stored as float64; it is refused by ``step``'s input checks before the tick runs, so it is left out, counted
  in the metadata, after checking here that the controller's records, previous command and twist are unchanged by
  it.

Deterministic: ``QPNSO_COMPILE=off`` (CasADi's runtime for the state function, as the suite runs; the script sets
it unless it is given), no solver time budget (``ControllerConfig.solver_time_budget`` None), seeded starts and
phases.  Running it twice gives the same arrays (the metadata's ``created`` aside).  The fuzz episodes are bit
for bit the same in most processes only: two of them (24, 48) take one of two answers that differ by round-off
from process to process (``tests/test_recorded_commands.py``'s ``TOLERANCE`` says how much).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field, replace
from importlib import metadata
from pathlib import Path
from typing import Any
from unittest import mock

os.environ.setdefault("QPNSO_COMPILE", "off")

import numpy as np  # noqa: E402
import pinocchio as pin  # noqa: E402

HERE = Path(__file__).resolve().parent
SOURCE_TREE = HERE.parent.parent
TRAJECTORY = "examples/trajectories/guidance_lwr4p.csv"
"""The main job's trajectory, relative to the source tree (the README's ``qpnso solve`` example)."""

MAIN_FIRST = 2000
"""The main job's commands kept: every tick of the first ``MAIN_FIRST``..."""
MAIN_EVERY = 50
"""...then every ``MAIN_EVERY``-th tick (tick index a multiple of it), and the last tick."""

FUZZ_SEED = 33
FUZZ_TICKS = 300
"""Valid ticks per fuzz episode (bad inputs come on top)."""
FUZZ_ROBOTS = ("lwr4p", "iiwa14")
FUZZ_EPISODES = (0, 8, 16, 24, 32, 40, 48)
"""With the fuzzer's default strategies (7) and tick lengths (1 and 4 ms) on the two S-R-S arms, episode E runs
strategy ``E % 7`` on the (robot, dt) pair ``(E // 7) % 4``: these seven run every strategy once and every robot
and tick length at least once (:meth:`FuzzConfig.setting`)."""

NOT_STORED = "not stored"
"""A call whose inputs are not float64 arrays: refused at the input checks, left out (see the module doc)."""

OUTCOME_COMMAND = 0
OUTCOME_REFUSED = 1


@dataclass
class Call:
    """One ``step`` call: its inputs as float64 (NaN where not given, with the ``has_*`` flags) and its outcome."""

    q: np.ndarray
    dq: np.ndarray | None
    twist: np.ndarray | None
    pose: tuple[np.ndarray, np.ndarray] | None
    outcome: int = OUTCOME_COMMAND
    dq_cmd: np.ndarray | None = None
    q_des: np.ndarray | None = None
    tau: np.ndarray | None = None
    status: int = -1


@dataclass
class Run:
    """One run of a recorded controller: its reset (``q0`` rad) and its calls in order."""

    q0: np.ndarray
    calls: list[Call] = field(default_factory=list)
    not_stored: int = 0


def as_float_vector(x: object, n: int) -> np.ndarray | None:
    """``x`` as a float64 (n,) array if it is one already (a real float array of that shape), else None."""
    if isinstance(x, np.ndarray) and x.dtype == np.float64 and x.shape == (n,):
        return x.copy()
    return None


class RecordingController:
    """Mixed into :class:`Controller` by :func:`recording_class`: keeps every ``step`` of every run after the
    constructor (whose warm-up ticks are not a run)."""

    runs: list[Run]
    instances: list[Any] = []

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.runs = []
        self._recording = False
        super().__init__(*args, **kwargs)
        self._recording = True
        RecordingController.instances.append(self)

    def reset(self, q0: object, ns0: float | None = None) -> None:
        super().reset(q0, ns0)  # type: ignore[misc]
        if self._recording:
            if ns0 is not None:
                raise RuntimeError("a recorded run was reset with ns0: the replay does not pass it")
            self.runs.append(Run(np.array(q0, dtype=np.float64)))

    def step(self, q: object, dq: object = None, tool_twist: object = None, tool_pose: object = None):  # noqa: ANN201
        from qpnso.errors import QpnsoError

        step = super().step  # type: ignore[misc]
        if not self._recording:
            return step(q, dq, tool_twist, tool_pose)
        run = self.runs[-1]
        nq = self.robot.nq  # type: ignore[attr-defined]
        qv, dqv, tw = as_float_vector(q, nq), as_float_vector(dq, nq), as_float_vector(tool_twist, 6)
        stored = (
            qv is not None
            and (dq is None or dqv is not None)
            and (tool_twist is None or tw is not None)
            and (tool_pose is None or isinstance(tool_pose, pin.SE3))
        )
        pose = (tool_pose.rotation.copy(), tool_pose.translation.copy()) if isinstance(tool_pose, pin.SE3) else None
        before = self._memory() if not stored else None
        try:
            cmd = step(q, dq, tool_twist, tool_pose)
        except QpnsoError:
            if stored:
                assert qv is not None
                run.calls.append(Call(qv, dqv, tw, pose, OUTCOME_REFUSED))
            else:
                if self._memory() != before:
                    raise RuntimeError("a refused call that is not stored changed the controller") from None
                run.not_stored += 1
            raise
        if not stored or qv is None:
            raise RuntimeError(f"a call with inputs that are not float64 arrays was accepted: {q!r}, {dq!r}")
        run.calls.append(Call(qv, dqv, tw, pose, OUTCOME_COMMAND, cmd.dq.copy(), cmd.q_des.copy(), cmd.tau.copy()))
        run.calls[-1].status = int(cmd.status.value)
        return cmd

    def _memory(self) -> tuple[bytes, bytes, bytes]:
        """What a tick reads of earlier ticks: the tick's records, the previous command and twist."""
        return (self.tick.tobytes(), self._dq_prev.tobytes(), self._twist_prev.tobytes())  # type: ignore[attr-defined]


def recording_class() -> type:
    from qpnso.control.controller import Controller

    return type("RecordingController", (RecordingController, Controller), {})


# ----------------------------------------------------------------------- arrays
def config_record(config: Any) -> dict[str, Any]:
    """The controller's settings as plain data without its unset (None) entries, checked to build the same
    config again (``ControllerConfig.from_dict``, as the check builds it)."""
    from qpnso.control.config import ControllerConfig

    values = {k: v for k, v in config.to_dict().items() if v is not None}
    if ControllerConfig.from_dict(json.loads(json.dumps(values))) != config:
        raise RuntimeError("the controller's settings do not survive JSON")
    return values


def call_arrays(calls: list[Call], nq: int) -> dict[str, np.ndarray]:
    """The calls as arrays over calls (float64; NaN where a command or an input is not there)."""
    n = len(calls)
    nan = np.full

    def stack(values: list[np.ndarray | None], shape: tuple[int, ...]) -> np.ndarray:
        out = nan((n, *shape), np.nan)
        for k, v in enumerate(values):
            if v is not None:
                out[k] = v
        return out

    return {
        "q": stack([c.q for c in calls], (nq,)),
        "dq_in": stack([c.dq for c in calls], (nq,)),
        "has_dq": np.array([c.dq is not None for c in calls]),
        "twist": stack([c.twist for c in calls], (6,)),
        "has_twist": np.array([c.twist is not None for c in calls]),
        "pose_R": stack([None if c.pose is None else c.pose[0] for c in calls], (3, 3)),
        "pose_p": stack([None if c.pose is None else c.pose[1] for c in calls], (3,)),
        "has_pose": np.array([c.pose is not None for c in calls]),
        "outcome": np.array([c.outcome for c in calls], dtype=np.int64),
        "dq": stack([c.dq_cmd for c in calls], (nq,)),
        "q_des": stack([c.q_des for c in calls], (nq,)),
        "tau": stack([c.tau for c in calls], (nq,)),
        "status": np.array([c.status for c in calls], dtype=np.int64),
    }


def encode_q(q: np.ndarray) -> np.ndarray:
    """Joint positions (N, nq) float64 packed exactly and small: their IEEE bit patterns as int64, differenced twice
    along the ticks (``np.diff(..., prepend=0)``, wrapping mod 2**64), as 8 byte planes (8, N, nq) uint8 (plane b the
    b-th byte of each little-endian int64).  A smooth joint path leaves the high bytes of the second differences
    nearly constant, so they compress: 0.8 MB for the main job's 36 141 ticks instead of 1.8 MB.  :func:`decode_q`
    inverts it bit for bit."""
    bits = np.ascontiguousarray(q, dtype="<f8").view("<i8")
    with np.errstate(over="ignore"):
        second = np.diff(np.diff(bits, axis=0, prepend=0), axis=0, prepend=0)
    planes = np.ascontiguousarray(second.view(np.uint8).reshape(*q.shape, 8).transpose(2, 0, 1))
    if not np.array_equal(decode_q(planes).view("<i8"), bits):
        raise RuntimeError("encode_q does not invert")
    return planes


def decode_q(planes: np.ndarray) -> np.ndarray:
    """The joint positions (N, nq) float64 of :func:`encode_q`'s byte planes (8, N, nq)."""
    second = np.ascontiguousarray(planes.transpose(1, 2, 0)).view("<i8")[..., 0]
    with np.errstate(over="ignore"):
        return np.cumsum(np.cumsum(second, axis=0), axis=0).view("<f8")


def main_kept_ticks(n: int) -> np.ndarray:
    """The main job's ticks whose command is kept (:data:`MAIN_FIRST`, :data:`MAIN_EVERY`, the last)."""
    k = np.arange(n)
    return np.flatnonzero((k < MAIN_FIRST) | (k % MAIN_EVERY == 0) | (k == n - 1))


# ----------------------------------------------------------------------- runs
def record_main() -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """The main job as ``qpnso solve TRAJECTORY`` runs it (the CLI's robot and defaults)."""
    from qpnso.control import offline
    from qpnso.control.offline import load_config, solve_trajectory
    from qpnso.control.trajectory import read_csv
    from qpnso.model.robot import load_robot, robot_spec

    robot = load_robot("lwr4p")  # (qpnso.cli.common.load_cli_robot without --robot, --tool-frame, --tool-offset)
    traj = read_csv(SOURCE_TREE / TRAJECTORY)
    cfg = load_config(None, {"strategy": None, "dt": None})  # (no --config, --strategy, --dt)
    RecordingController.instances.clear()
    with mock.patch.object(offline, "Controller", recording_class()):
        result = solve_trajectory(robot, traj, config=cfg)
    (ctrl,) = RecordingController.instances
    (run,) = ctrl.runs
    calls = run.calls
    n = len(calls)
    if n != len(result.arrays["t"]) or any(c.outcome != OUTCOME_COMMAND or c.dq is not None for c in calls):
        raise RuntimeError("the main job's calls are not one command per tick with dq=None")
    arrays = call_arrays(calls, robot.nq)
    kept = main_kept_ticks(n)
    out = {
        "q0": run.q0,
        "q_planes": encode_q(arrays["q"]),  # every tick's input (the replay needs them all), packed
        "tick": kept,
        "t": np.asarray(result.arrays["t"], dtype=np.float64)[kept],
        "twist": arrays["twist"][kept],
        "pose_R": arrays["pose_R"][kept],
        "pose_p": arrays["pose_p"][kept],
        "dq": arrays["dq"][kept],
        "q_des": arrays["q_des"][kept],
        "tau": arrays["tau"][kept],
        "status": arrays["status"][kept],
    }
    meta = {
        "trajectory": TRAJECTORY,
        "robot": robot_spec(robot),
        "config": config_record(ctrl.config),
        "ticks": n,
        "kept": f"the commands of ticks 0..{MAIN_FIRST - 1}, every {MAIN_EVERY}th tick after, and tick {n - 1}",
        "inputs": "q of every tick (q_planes: decode_q of record_commands.py); tool_twist and tool_pose "
        "recomputed from the trajectory (Trajectory.samples at t0 + k*dt, as solve_trajectory does), kept at the "
        "kept ticks; dq None",
        "summary": {  # (the run's own summary, its timings left out: they are the machine's)
            k: v
            for k, v in result.summary.items()
            if isinstance(v, (int, float, str)) and "time" not in k and k != "slow_ticks"
        },
    }
    return out, meta


def record_fuzz() -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Each of :data:`FUZZ_EPISODES` run alone (``first_episode=E``) on a fresh controller."""
    from qpnso.lab.fuzz import FuzzConfig, run_fuzz, runner
    from qpnso.model.robot import robot_spec

    base = FuzzConfig(
        seed=FUZZ_SEED, robots=FUZZ_ROBOTS, episode_ticks=FUZZ_TICKS, replays=0, workers=0, freeze_gc=False
    )  # (freeze_gc would build the controllers of every setting first: not the commands' business)
    parts: list[dict[str, np.ndarray]] = []
    episodes: list[dict[str, Any]] = []
    for e in FUZZ_EPISODES:
        config = replace(base, first_episode=e, ticks=FUZZ_TICKS)
        RecordingController.instances.clear()
        with mock.patch.object(runner, "Controller", recording_class()):
            report = run_fuzz(config)
        (ctrl,) = RecordingController.instances
        (run,) = ctrl.runs
        if report.counts["foreign_exception"] or report.counts["valid_refused"] or report.counts["bad_accepted"]:
            raise RuntimeError(f"episode {e} did not run as the fuzzer runs it: {report.exceptions}")
        robot, dt, strategy = config.setting(e)
        arrays = call_arrays(run.calls, ctrl.robot.nq)
        arrays["episode"] = np.full(len(run.calls), len(episodes), dtype=np.int64)
        parts.append(arrays)
        valid = int(np.sum(arrays["outcome"] == OUTCOME_COMMAND))
        episodes.append(
            {
                "episode": e,
                "robot": robot_spec(ctrl.robot),
                "controller": config_record(ctrl.config),
                "q0": run.q0.tolist(),
                "calls": len(run.calls),
                "commands": valid,
                "refused": len(run.calls) - valid,
                "refused_not_stored": run.not_stored,
                "fuzz_ticks": report.ticks,
                "fuzz_failures": [f for f in report.failures() if "CPU time" not in f],  # (the machine's)
            }
        )
        print(f"fuzz episode {e}: {robot} dt {1e3 * dt:g} ms {strategy}: {len(run.calls)} calls", file=sys.stderr)
    out = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    meta = {"fuzz_config": {**base.to_dict(), "ticks": FUZZ_TICKS}, "episodes": episodes}
    return out, meta


# ----------------------------------------------------------------------- metadata
def provenance() -> dict[str, Any]:
    """The commit and the versions the recording was made with."""

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=SOURCE_TREE, capture_output=True, text=True).stdout.strip()

    versions: dict[str, str | None] = {}
    for name in ("qpnso", "numpy", "scipy", "casadi", "pin", "proxsuite", "daqp", "numba"):
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return {
        "qpnso_commit": git("rev-parse", "HEAD"),
        "qpnso_code_commit": git("log", "-1", "--format=%H", "--", "qpnso", "src", "CMakeLists.txt", "pyproject.toml"),
        "qpnso_tree_dirty": bool(git("status", "--porcelain", "--untracked-files=no", "qpnso", "src")),
        "versions": versions,
        "python": sys.version.split()[0],
        "QPNSO_COMPILE": os.environ.get("QPNSO_COMPILE"),
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


def main() -> int:
    t0 = time.perf_counter()
    main_arrays, main_meta = record_main()
    print(f"main job: {main_meta['ticks']} ticks ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    fuzz_arrays, fuzz_meta = record_fuzz()
    # (NumPy's stub: mypy cannot tell that no key of ``**arrays`` is the keyword ``allow_pickle: bool``)
    np.savez_compressed(HERE / "commands_main.npz", **main_arrays)  # type: ignore[arg-type]
    np.savez_compressed(HERE / "commands_fuzz.npz", **fuzz_arrays)  # type: ignore[arg-type]
    meta = {
        **provenance(),
        "script": "tests/data/record_commands.py",
        "units": "q, q_des rad; dq rad/s; tau N·m; twist m/s then rad/s (world); pose world <- tool, m",
        "main": main_meta,
        "fuzz": fuzz_meta,
    }
    (HERE / "commands.json").write_text(json.dumps(meta, indent=1, sort_keys=True, default=str) + "\n")
    for name in ("commands_main.npz", "commands_fuzz.npz", "commands.json"):
        print(f"{name}: {(HERE / name).stat().st_size / 1e3:.0f} kB", file=sys.stderr)
    print(f"done in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
