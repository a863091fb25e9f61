"""The closed-loop fuzzer: random control loops over every robot, tick length and strategy, checked
independently (issues 13 and 31).

``run_fuzz(FuzzConfig(ticks=N, seed=S))`` runs episodes of a *kinematic closed
loop* (``q ← q + dt·cmd.dq``: the plant follows the velocity command exactly,
as a position-controlled arm; the offline solve's model), episode E on the robot, dt and strategy of
``FuzzConfig.setting(E)`` (by default LWR4+, iiwa14 and the Panda — skipped, said so, without
example-robot-data —, dt 1 and 4 ms, every strategy), each on its cached
:class:`~qpnso.control.controller.Controller`:

* a random start: uniform within the limits, near one or two limits (0–3°
  inside), or near a singular arm angle (straight elbow, wrist over the
  shoulder);
* phases: the tool held (``tool_twist=None``), random smooth twists (up to
  0.3 m/s and 1 rad/s, kept near the start pose), violent pulls (2 m/s and 1 rad/s
  for 20 ticks, then held), the joint nearest a limit pushed past it by up to 2°
  when within 5° of it (then held);
* bad inputs interleaved in bursts (:data:`PROBE_KINDS`: NaN, inf, complex,
  wrong shape or type in ``q``, ``dq``, ``tool_twist``, ``tool_pose``; ``q`` in
  degrees; ``q`` outside its limits by a little and by a lot): each must raise a
  :class:`~qpnso.errors.QpnsoError` (a ``q`` less than ``far_outside_deg``
  outside may instead be accepted, as documented, and its command is checked),
  and the loop goes on from the same ``q``.

Every command is checked by :class:`TickChecker` with Pinocchio and the
robot's limits only (never qpnso's own state evaluator): finite ``dq``,
``q_des``, ``tau``; ``|dq| ≤ dq_max``; ``q + dt·dq`` and ``q_des`` within the
limits (or, from outside, not further out); ``|tau| ≤ tau_limit``; solver time
≤ ``solve_time_max`` (1 ms) unless the solver's own CPU time was below it (:class:`SolverClock`:
then the tick was preempted, counted apart); and, reported but not must-hold lines, the
preempted ticks and the arm angle leaving ROM_t further without ``ELBOW_SLACK`` or ``ROM_EMPTY``.
Issue 31's lines: the whole ``step`` call's thread CPU time (``time.thread_time_ns``) over ``tick_cpu_max``
(1 ms) on fewer than ``tick_cpu_fraction_max`` (0.1 %) of the ticks, per robot and strategy in the table; no
Numba kernel signature added after the constructor (:class:`KernelWatch`, checked after every ``step``); no
command changed by more than ``Controller.ddq_max·dt`` from the controller's previous one since its reset
(when the controller has a ``ddq_max``); no joint command reversed from beyond 0.5 rad/s one way to beyond it
the other way within two ticks (:class:`CommandHistory`).
The fuzzer integrates the tool reference itself (the
controller's rule: ``p += dt·v``, ``R ← exp₃(dt·ω) R``) and measures the tool's
pose error by Pinocchio forward kinematics: held-tool drift (held phases of
episodes from non-singular starts, once the tool has settled within the
tolerance; ticks flagged ``TOOL_LIMITED`` or ``Q_OUT_OF_LIMITS`` excused) and
recovery (ticks after a pull, an overshoot or a bad-input burst that began
from an OK state, until ``cmd.ok`` and the error is below 1e-4 m or closing at half the capped
correction speed; not counted when the reference is out of reach or the arm angle is undefined at
the held pose; the 20 ticks after accepted bad inputs are no drift).  With ``freeze_gc`` the
controllers are built first and the garbage collector is frozen for the run (:func:`realtime_gc`).

With ``workers=N`` the ticks run in shards of about ``shard_ticks``, each in a fresh spawned process, N at a
time, and each slow tick's episode (and the slowest whole tick's) is replayed ``replays`` times, each replay in
a fresh process: a kernel compiled or loaded inside a tick happens once per process, so a replay in the same
process cannot show it.  (A script that calls ``run_fuzz`` with workers needs the
``if __name__ == "__main__":`` guard of :mod:`multiprocessing`'s spawn.)

:class:`FuzzReport` counts each must-hold line (:data:`CHECKS`), keeps the worst
example of each (seed, episode, tick, robot, dt, strategy, start, phase, the input) and
the tick-time percentiles; ``table()`` is Markdown, ``failures()`` lists the
lines violated.  An episode is reproduced alone, in this process, by
``run_fuzz(replace(config, first_episode=E, ticks=config.episode_ticks, workers=0), observe=...)``,
``observe(where, inputs, cmd, error)`` seeing every valid tick.
``qpnso bench fuzz -n N`` is the command line.

The package, one concept per module; each imports only those listed above it (type-only imports aside):

* :mod:`~qpnso.lab.fuzz.config`: :class:`FuzzConfig` (and each episode's setting), the start and probe kinds,
  :class:`Where`;
* :mod:`~qpnso.lab.fuzz.report`: the checks (:data:`CHECKS`), :class:`Example`, :class:`FuzzReport`
  (its table, JSON and the merge of shards), ``record_exception``;
* :mod:`~qpnso.lab.fuzz.kernels`: :class:`KernelWatch`, the Numba kernels' signatures since a baseline;
* :mod:`~qpnso.lab.fuzz.starts`: random starts and the arm's singular zones (:func:`arm_angle_undefined`);
* :mod:`~qpnso.lab.fuzz.checker`: :class:`TickChecker` (the independent checks), :class:`CommandHistory`
  (command to command), :class:`HoldMonitor` (drift) and :class:`Recovery` (:func:`update_recovery`) bookkeeping;
* :mod:`~qpnso.lab.fuzz.phases`: the episode's phases, twists and tool reference;
* :mod:`~qpnso.lab.fuzz.probes`: the bad inputs (:class:`Probe`), made (:func:`make_probe`) and sent
  (:func:`send_probe`);
* :mod:`~qpnso.lab.fuzz.episode`: :class:`SolverClock` and ``Episode``, one closed loop;
* :mod:`~qpnso.lab.fuzz.runner`: ``Fuzzer``, the shards and replays in fresh processes, :func:`realtime_gc` and
  :func:`run_fuzz`.
"""

from __future__ import annotations

from qpnso.lab.fuzz.checker import CommandHistory, HoldMonitor, Recovery, TickChecker, update_recovery
from qpnso.lab.fuzz.config import PROBE_KINDS, START_KINDS, FuzzConfig, Where
from qpnso.lab.fuzz.episode import SolverClock
from qpnso.lab.fuzz.kernels import KernelWatch
from qpnso.lab.fuzz.probes import Probe, make_probe, send_probe
from qpnso.lab.fuzz.report import CHECK_KEYS, CHECKS, Example, FuzzReport
from qpnso.lab.fuzz.runner import realtime_gc, run_fuzz
from qpnso.lab.fuzz.starts import arm_angle_undefined

__all__ = [
    "CHECKS",
    "CHECK_KEYS",
    "CommandHistory",
    "PROBE_KINDS",
    "START_KINDS",
    "Example",
    "FuzzConfig",
    "FuzzReport",
    "HoldMonitor",
    "KernelWatch",
    "Probe",
    "Recovery",
    "SolverClock",
    "TickChecker",
    "Where",
    "arm_angle_undefined",
    "make_probe",
    "realtime_gc",
    "run_fuzz",
    "send_probe",
    "update_recovery",
]
