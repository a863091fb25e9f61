"""Bad inputs (:data:`~qpnso.lab.fuzz.config.PROBE_KINDS`): NaN, inf, complex, wrong shapes and types in
``q``, ``dq``, ``tool_twist`` and ``tool_pose``, ``q`` in degrees, ``q`` a little or far outside its limits;
made by :func:`make_probe` and sent by :func:`send_probe`, which counts the outcome.

Each must raise a ``QpnsoError`` (a ``q`` only a little outside may be accepted, as documented, and its
command is then checked like any other): anything else reaching a 1 kHz loop is a failure.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
import pinocchio as pin

from qpnso.control.controller import Controller
from qpnso.errors import QpnsoError
from qpnso.lab.fuzz.checker import CommandHistory, TickChecker
from qpnso.lab.fuzz.config import FuzzConfig, Where
from qpnso.lab.fuzz.report import record_exception
from qpnso.model.robot import Robot

if TYPE_CHECKING:  # the episode imports the probes
    from qpnso.lab.fuzz.episode import SolverClock


@dataclass
class Probe:
    """A bad input: the ``step`` keyword arguments, whether it must be refused, the real ``q`` (rad) its
    command is checked at if it is accepted (None: not checkable), and a description."""

    kind: str
    kwargs: dict
    must_refuse: bool
    q: np.ndarray | None
    description: str


def _bad_vector(kind: str, rng: np.random.Generator, v: np.ndarray) -> tuple[object, str]:
    """``v`` spoilt: ``nan``, ``inf``, ``complex``, ``shape`` or ``type``."""
    v = v.copy()
    i = int(rng.integers(v.size))
    if kind == "nan":
        v[i] = np.nan
        return v, f"NaN at {i}"
    if kind == "inf":
        v[i] = np.inf if rng.random() < 0.5 else -np.inf
        return v, f"inf at {i}"
    if kind == "complex":
        return v + 1j * rng.uniform(0.01, 0.1, v.size), "complex with imaginary parts 0.01–0.1"
    if kind == "shape":
        options = [v[:-1], np.append(v, 0.0), np.tile(v, (2, 1)), v[0], np.empty(0)]
        k = int(rng.integers(len(options)))
        return options[k], f"shape {np.shape(options[k])}"
    options = [None, ["x"] * v.size, ",".join(str(x) for x in v), {"q": v}]
    k = int(rng.integers(len(options)))
    return options[k], f"type {type(options[k]).__name__}"


def _outside(
    rng: np.random.Generator, robot: Robot, q: np.ndarray, lo_deg: float, hi_deg: float, nearest: bool = False
) -> np.ndarray:
    """``q`` with one joint outside a limit by ``lo_deg``–``hi_deg`` degrees: a random joint and side, or
    (``nearest``) the joint and side nearest to a limit, as an encoder overshoot."""
    q = q.copy()
    if nearest:
        low, high = q - robot.q_min, robot.q_max - q
        j = int(np.argmin(np.minimum(low, high)))
        below = low[j] <= high[j]
    else:
        j, below = int(rng.integers(robot.nq)), rng.random() < 0.5
    out = math.radians(rng.uniform(lo_deg, hi_deg))
    q[j] = robot.q_min[j] - out if below else robot.q_max[j] + out
    return q


def limit_distance(robot: Robot, q: np.ndarray) -> float:
    """Distance (rad) of the joint nearest to one of its limits (negative outside)."""
    return float(np.min(np.minimum(q - robot.q_min, robot.q_max - q)))


def make_probe(
    kind: str, rng: np.random.Generator, q: np.ndarray, dq: np.ndarray, robot: Robot, config: FuzzConfig
) -> Probe:
    """The bad input ``kind`` (:data:`PROBE_KINDS`) at the plant's ``q`` (rad) and velocity ``dq`` (rad/s)."""
    what, _, how = kind.partition("_")
    far = math.radians(config.far_outside_deg)
    if kind == "q_degrees":
        qd = np.degrees(q)
        out = float(np.max(np.maximum(robot.q_min - qd, qd - robot.q_max)))
        return Probe(kind, {"q": qd}, out > far, qd, f"q in degrees (outside by up to {out:.3g} rad)")
    if kind == "q_out_little":
        qo = _outside(rng, robot, q, 0.01, config.overshoot_max_deg, nearest=True)
        return Probe(
            kind, {"q": qo}, False, qo, f"q: the joint nearest a limit past it by < {config.overshoot_max_deg}°"
        )
    if kind == "q_out_far":
        qo = (
            _outside(rng, robot, q, config.far_outside_deg + 1.0, 180.0)
            if rng.random() < 0.9
            else np.full(robot.nq, 1e6)
        )
        return Probe(kind, {"q": qo}, True, qo, f"q outside its limits by > {config.far_outside_deg}°")
    if what == "pose":
        return _pose_probe(kind, how, rng, q, robot)
    base = {"q": q, "dq": dq, "twist": np.zeros(6)}[what]
    bad, desc = _bad_vector(how, rng, base)
    name = {"q": "q", "dq": "dq", "twist": "tool_twist"}[what]
    kwargs: dict = {"q": q, name: bad}
    return Probe(kind, kwargs, True, None if what == "q" else q, f"{name}: {desc}")


def _pose_probe(kind: str, how: str, rng: np.random.Generator, q: np.ndarray, robot: Robot) -> Probe:
    pose = robot.tool_pose(q)
    if how in ("nan", "inf"):
        p = pose.translation.copy()
        p[int(rng.integers(3))] = np.nan if how == "nan" else np.inf
        bad: object = pin.SE3(pose.rotation, p)
        desc = f"SE3 with translation {p.tolist()}"
    elif how == "not_rotation":
        m = pose.rotation * rng.uniform(1.5, 3.0) if rng.random() < 0.5 else rng.normal(size=(3, 3))
        bad, desc = pin.SE3(m, pose.translation), "SE3 whose rotation is not a rotation"
    else:
        options = [pose.homogeneous, (pose.rotation, pose.translation), pose.translation, "pose"]
        k = int(rng.integers(len(options)))
        bad, desc = options[k], f"tool_pose of type {type(options[k]).__name__}"
    return Probe(kind, {"q": q, "tool_pose": bad}, True, q, desc)


def send_probe(
    ctrl: Controller,
    probe: Probe,
    checker: TickChecker,
    where: Where,
    clock: SolverClock | None = None,
    history: CommandHistory | None = None,
) -> str:
    """Call ``ctrl.step`` with a bad input: ``refused`` (a QpnsoError), ``foreign`` (another exception,
    counted with its traceback) or ``accepted`` (counted if it had to be refused; its command checked, with
    its CPU times when ``clock`` is the controller's :class:`SolverClock`, and against the controller's previous
    commands when ``history`` holds them: an accepted command is the one the next tick's is bounded from)."""
    rep = checker.report
    where = replace(where, phase=f"probe {probe.kind}")
    inputs = {"probe": probe.kind, "description": probe.description, **probe.kwargs}
    if clock is not None:
        clock.take()
    cpu = time.thread_time()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cmd = ctrl.step(**probe.kwargs)
    except QpnsoError:
        outcome = "refused"
    except Exception as exc:  # noqa: BLE001 - the point: anything that is not a QpnsoError is a failure
        outcome = "foreign"
        record_exception(rep, exc, where, inputs)
    else:
        outcome = "accepted"
        if probe.must_refuse:
            rep.record("bad_accepted", 1.0, where, inputs, f"{probe.description}: accepted, status {cmd.status}")
        cpu = time.thread_time() - cpu
        if probe.q is not None and np.all(np.isfinite(probe.q)):
            checker.command(
                cmd,
                np.asarray(probe.q, dtype=float),
                where,
                inputs,
                timed=False,
                cpu_time=cpu,
                solver_cpu_time=math.inf if clock is None else clock.take(),
                history=history,
            )
        dq = np.asarray(cmd.dq, dtype=float)
        if history is not None and dq.shape == (checker.robot.nq,) and np.all(np.isfinite(dq)):
            checker.motion(history, dq, cmd, where, inputs, q=probe.q)
    rep.count_probe(probe.kind, outcome)
    return outcome
