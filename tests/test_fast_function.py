"""CasADi functions evaluated by the C++ core (qpnso/model/codegen.py): the compiled C library and CasADi's own
runtime give casadi's answers to round-off, into the caller's arrays, and the controller says which one runs."""

from __future__ import annotations

import shutil

import casadi as ca
import numpy as np
import pytest

from qpnso import Controller, ControllerConfig, load_robot
from qpnso.model.codegen import FastFunction

RUNTIMES = {"off": "casadi runtime", "sync": "compiled C"}


def casadi_function() -> ca.Function:
    """Two dense inputs (a vector, a 2x3 matrix) and outputs of every shape FastFunction returns."""
    x, P = ca.SX.sym("x", 3), ca.SX.sym("P", 2, 3)
    y = ca.vertcat(ca.sin(x[0]) * P[0, 1], ca.exp(0.1 * x[2]) + P[1, 2], x[1] * x[2])
    return ca.Function("qpnso_test_ff", [x, P], [y, ca.mtimes(P, x), ca.sumsqr(x), ca.mtimes(P.T, P) * x[0]])


@pytest.fixture(scope="module", params=sorted(RUNTIMES))
def function(request, tmp_path_factory):
    if request.param == "sync" and shutil.which("cc") is None:
        pytest.skip("no C compiler: only CasADi's runtime can run")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("QPNSO_CACHE_DIR", str(tmp_path_factory.mktemp("cache")))
        return FastFunction(casadi_function(), request.param)


def test_each_runtime_gives_casadis_answers(function) -> None:
    """``ff(x, P)`` against casadi's own call on 20 random inputs, every output's value and shape (rtol 1e-14:
    the same operations in another order at most)."""
    assert function.runtime == RUNTIMES["sync" if function.compiled else "off"]
    f, rng = casadi_function(), np.random.default_rng(0)
    for _ in range(20):
        x, P = rng.standard_normal(3), rng.standard_normal((2, 3))
        got, want = function(x, P), [np.array(v.full()).squeeze() for v in f(x, P)]
        assert isinstance(got[2], float)
        for g, w in zip(got, want):
            np.testing.assert_allclose(np.squeeze(g), w, rtol=1e-14, atol=1e-15)


def test_an_output_written_into_the_callers_array() -> None:
    """``use_output``: the evaluation writes output 0 where the caller's array lies (no copy), from the inputs
    ``evaluate_in_place`` places one after another."""
    x = ca.SX.sym("x", 4)
    f = FastFunction(ca.Function("qpnso_test_in_place", [x], [ca.cumsum(x) * x[3], x[0]]), "off")
    out = np.zeros(4)
    f.use_output(0, out)
    result = f.evaluate_in_place(np.array([1.0, 2.0]), np.array([3.0, 4.0]))
    assert result is out
    np.testing.assert_array_equal(out, np.cumsum([1.0, 2.0, 3.0, 4.0]) * 4.0)
    with pytest.raises(ValueError, match="output 0"):
        f.use_output(0, np.zeros(3))


def test_the_controller_says_what_evaluates_its_state(monkeypatch, tmp_path) -> None:
    """``Controller.info()``: CasADi's runtime with ``QPNSO_COMPILE=off``, the core's build, and the state's
    answers equal whichever runs (the tick's own evaluation against casadi's call of the same function)."""
    monkeypatch.setenv("QPNSO_COMPILE", "off")
    robot = load_robot("lwr4p")
    ctrl = Controller(robot, ControllerConfig(strategy="damped"))
    info = ctrl.info()
    assert info["state_function"] == "casadi runtime" and info["robot"] == "lwr4p"
    assert info["core"].startswith("qpnso ") and "Eigen" in info["core"]
    q = robot.random_q(np.random.default_rng(1), 0.3)
    zero7, zero6 = np.zeros(7), np.zeros(6)
    got = ctrl.evaluate._fn.evaluate_in_place(q, zero7, zero6, zero6).copy()
    want = np.array(ctrl.evaluate._fn.function(np.concatenate([q, zero7, zero6, zero6])).full()).ravel()
    np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-13)


def test_a_cached_library_is_used_from_the_constructor_on(tmp_path, monkeypatch) -> None:
    """Once compiled (``sync``), a new FastFunction of the same function loads the cached library at once, in the
    background mode too: no runtime loaded meanwhile, no thread waiting for a compile."""
    monkeypatch.setenv("QPNSO_CACHE_DIR", str(tmp_path))
    if shutil.which("cc") is None:
        pytest.skip("no C compiler")
    assert FastFunction(casadi_function(), "sync").compiled
    again = FastFunction(casadi_function(), "background")
    assert again.runtime == "compiled C" and again._thread is None
