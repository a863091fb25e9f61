"""Faults injected into the controller for the fuzz's positive controls (tests/test_fuzz.py): applied with a
test's ``monkeypatch.setattr`` in the test's process, or by ``FuzzConfig.setup = "fuzz_faults:<name>"`` first in
every fresh process of a run with workers (this folder is on the spawned processes' ``sys.path``, as on pytest's).

Each fault counts from the end of the last ``Controller`` constructor in the process (which itself resets and
steps the controller to load its kernels), so "the N-th call" is the same tick of the first episode in a shard
and in a fresh replay of that episode.
"""

from __future__ import annotations

import time
from typing import Callable

import numba
import numpy as np

import qpnso.qp.solver
from qpnso.control.controller import Controller
from qpnso.qp.solver import HierarchicalQP

Patch = Callable[[object, str, object], None]  # setattr, or monkeypatch.setattr
KERNEL = "qpnso.qp.solver._fuzz_fault_kernel"
"""Where the injected kernel is put: a qpnso module, so the fuzz's kernel walk sees it."""
COMPILE_AT = 30  # the solve_problem call (after the last constructor) that compiles the injected kernel


def _counting_constructor(patch: Patch, calls: dict) -> None:
    """``calls["n"]`` restarts at 0 when a constructor returns (and counts nothing that the constructor calls)."""
    build = Controller.__init__

    def constructor(self, *args, **kwargs) -> None:
        calls["n"] = -(10**9)
        build(self, *args, **kwargs)
        calls["n"] = 0

    patch(Controller, "__init__", constructor)


def compile_in_a_solve(patch: Patch = setattr) -> None:
    """The :data:`COMPILE_AT`-th ``HierarchicalQP.solve_problem`` call after the last constructor calls a new Numba
    kernel (module attribute :data:`KERNEL`), which compiles it there, once per process: what a kernel meeting a
    type the constructor never warmed up does (issue 31, item 4)."""
    calls = {"n": -(10**9)}
    module, _, name = KERNEL.rpartition(".")
    assert module == qpnso.qp.solver.__name__
    patch(qpnso.qp.solver, name, numba.njit(lambda x: x + 1.0))
    _counting_constructor(patch, calls)
    solve_problem = HierarchicalQP.solve_problem

    def compiling(self, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == COMPILE_AT:
            getattr(qpnso.qp.solver, name)(1.0)
        return solve_problem(self, *args, **kwargs)

    patch(HierarchicalQP, "solve_problem", compiling)


_INSTALLED: set[str] = set()


def compile_in_a_solve_once() -> None:
    """:func:`compile_in_a_solve` installed in this process unless it already is: the ``FuzzConfig.setup`` of a run
    with workers (a process reused for a second task would compile nothing the second time, as a real once-per-process
    compile; a new kernel made there again would compile again and hide it)."""
    if "compile_in_a_solve" not in _INSTALLED:
        _INSTALLED.add("compile_in_a_solve")
        compile_in_a_solve()


def command_changed(patch: Patch, ticks: dict[int, Callable[[np.ndarray, np.ndarray, Controller], np.ndarray]]) -> None:
    """The command of the ``step`` calls numbered in ``ticks`` (0: the first after the last constructor) replaced
    by ``ticks[k](dq, previous dq returned, controller)``, whatever the controller would have sent."""
    calls = {"n": -(10**9)}
    _counting_constructor(patch, calls)
    step = Controller.step
    last: dict[str, np.ndarray] = {}

    def changed(self, *args, **kwargs):
        cmd = step(self, *args, **kwargs)
        k = calls["n"]
        calls["n"] += 1
        if k in ticks:
            cmd.dq = ticks[k](np.array(cmd.dq), last.get("dq", np.zeros_like(cmd.dq)), self)
        last["dq"] = np.array(cmd.dq)
        return cmd

    patch(Controller, "step", changed)


def cpu_burnt(patch: Patch, tick: int, seconds: float) -> None:
    """The ``step`` call numbered ``tick`` (after the last constructor) burns ``seconds`` of thread CPU time first."""
    calls = {"n": -(10**9)}
    _counting_constructor(patch, calls)
    step = Controller.step

    def burning(self, *args, **kwargs):
        k = calls["n"]
        calls["n"] += 1
        if k == tick:
            end = time.thread_time() + seconds
            while time.thread_time() < end:
                pass
        return step(self, *args, **kwargs)

    patch(Controller, "step", burning)
