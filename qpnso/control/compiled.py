"""The ``qp`` strategy's compiled tick, seen from Python (docs/method.md §7): one Numba call from the CasADi
state to the level-2 line QP (:func:`qpnso.control.tick.qp_tick`), ProxSuite's solve on its persistent object,
one Numba call for the checks, the command and the torque (:func:`qpnso.control.tick.qp_tick_answer`).
:meth:`qpnso.control.controller.Controller.step` takes it whenever the line fast path applies; its answers
equal the general path's to round-off (tests/test_tick.py)."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np

from qpnso.control.config import Command, ElbowState, Status, _stamped, _status
from qpnso.control.flags import ELBOW_BITS
from qpnso.control.tick import (
    TICK_ELBOW_DROPPED,
    TICK_NEED_INTERVAL,
    TICK_NOT_FINITE,
    TICK_Q_REFUSED,
    TICK_STATE_NOT_FINITE,
    LineTickBuffers,
    qp_command,
    qp_tick,
    qp_tick_answer,
)
from qpnso.qp.backends import solved_vector
from qpnso.qp.line import LINE_ANSWER_OK, LINE_OK
from qpnso.qp.results import level_failure

if TYPE_CHECKING:
    from qpnso.control.controller import Controller


def compiled_step(
    ctrl: Controller, qv: np.ndarray, twist: np.ndarray, dq_meas: np.ndarray, t0: float
) -> Command | tuple | None:
    """The ``qp`` strategy's tick as :func:`qpnso.control.tick.qp_tick` (the CasADi state read in place →
    level-2 line QP, one Numba call), the back end's level-2 solve (:meth:`HierarchicalQP.line_level_raw`)
    and :func:`qpnso.control.tick.qp_tick_answer` (checks, command, torque): the general path's answer to
    round-off.  Returns the Command; or, when the line fast path does not apply, ``(state, elbow,
    status)`` for the general path to go on from; or None when nothing was done (singular arm angle)."""
    flat = ctrl.evaluate.raw(qv, ctrl._dq_prev, twist)
    t1 = time.perf_counter()
    buf = ctrl._line
    assert buf is not None  # the compiled tick has its buffers (_can_compile)
    tick, t_interval = _qp_tick(ctrl, buf, qv, flat, twist, True), 0.0
    if tick[0] == TICK_NEED_INTERVAL:  # (its time is not the QP's)
        t_interval = time.perf_counter()
        ctrl._update_interval(qv, flat[:12])  # (qp_tick then flags a stale interval itself)
        t_interval = time.perf_counter() - t_interval
        tick = _qp_tick(ctrl, buf, qv, flat, twist, False)
    code, ns, rom_lo, rom_hi, iv_lo, iv_hi, k, e_pos, e_rot, residual, cost, bits = tick
    if code == TICK_NOT_FINITE or code == TICK_Q_REFUSED:
        ctrl._refuse_q(qv)  # raises, naming the entries or the joint
    if code == TICK_ELBOW_DROPPED or code == TICK_STATE_NOT_FINITE:
        return None  # the general path drops the elbow, or stops the joints
    if code != LINE_OK:
        elbow = ElbowState(ns, (rom_lo, rom_hi), (iv_lo, iv_hi), k, _status(bits & ELBOW_BITS))
        return ctrl.evaluate.state(qv, flat.copy()), elbow, _status(bits)
    raw = ctrl.qp.line_level_raw(buf.H, buf.g, buf.C, buf.l, buf.u, buf.box_l, buf.box_u, buf.x0, buf.d, 1)
    v = solved_vector(raw, buf.box_l.shape)
    answer: tuple | None = None
    if v is not None:
        answer = qp_tick_answer(
            v,
            buf.line,
            buf.box_l,
            buf.box_u,
            buf.C,
            buf.l,
            buf.u,
            ctrl.qp.settings.feasibility_tol,
            flat,
            ctrl.evaluate.offsets,
            qv,
            dq_meas,
            k,
            ctrl.config.dt,
            ctrl.config.joint_damping,
            residual,
            bits,
            ctrl._tau_limit,
            ctrl.robot.dq_max,
            ns,
            rom_lo,
            rom_hi,
        )
    ok = answer is not None and answer[0] == LINE_ANSWER_OK
    ctrl.qp.count_solve(ok)
    if ok:  # finished in qp_tick_answer (finish_command): the command as sent
        assert answer is not None  # (ok)
        _, dq_cmd, q_des, tau, bits = answer
        message = ""
    else:  # the answer refused: level 1's least-norm point, then every tick's finishing step
        second = ctrl.qp.line_level_result(raw, buf.d, buf.x0, buf.box_l, buf.box_u, buf.C, buf.l, buf.u, 1)
        dq_cmd, fallback, message = ctrl._fallback(level_failure(1, 2, second), buf.x1.copy())
        q_des, tau = qp_command(
            flat, ctrl.evaluate.offsets, qv, dq_cmd, dq_meas, k, ctrl.config.dt, ctrl.config.joint_damping
        )
    cmd = Command(
        dq_cmd,
        q_des,
        tau,
        k,
        ns,
        (rom_lo, rom_hi),
        (iv_lo, iv_hi),
        cost,
        Status.OK,
        time.perf_counter() - t1 - t_interval,
        0.0,
        (e_pos, e_rot),
        message,
    )
    if ok:
        return _stamped(cmd, bits, t0)
    o = ctrl.evaluate.offsets
    return ctrl._finish(cmd, qv, flat[o[9] : o[10]], bits | fallback.value, t0, False)


def _qp_tick(
    ctrl: Controller, buf: LineTickBuffers, qv: np.ndarray, flat: np.ndarray, twist: np.ndarray, advance: bool
) -> tuple:
    """:func:`qpnso.control.tick.qp_tick` on this controller's reference, elbow memory, settings and buffers
    (``buf``: ``ctrl._line``)."""
    return qp_tick(
        qv,
        flat,
        ctrl.evaluate.offsets,
        ctrl._limits,
        ctrl.ref_rotation,
        ctrl.ref_position,
        twist,
        ctrl._elbow_memory,
        ctrl.ns0,
        ctrl._elbow_params,
        advance,
        ctrl._gains,
        ctrl._qp_tol,
        buf.identity,
        *buf.outputs(),
    )
