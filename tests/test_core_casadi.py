"""The compiled core qpnso._core (C++17, nanobind, scikit-build-core; src/core) is built by ``pip install .`` and
``pip install -e .`` and evaluates CasADi functions as casadi does, to round-off, both ways the core uses:

* the shared library compiled from the C that ``Function.generate`` writes (dlopen), and
* CasADi's own runtime (libcasadi of the casadi wheel, through its C API, on a Function saved with
  ``Function.save``), against casadi's own evaluation in Python;
* without the GIL; and from C++ alone: examples/cpp/state_loop built with CMake against the installed package
  (``find_package(qpnso)``) evaluates the control tick's state function as Python does.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import threading

import casadi as ca
import numpy as np
import pytest
from conftest import SOURCE_TREE

from qpnso import _core
from qpnso.model import codegen

EXAMPLE = SOURCE_TREE / "examples" / "cpp"


def casadi_test_function() -> ca.Function:
    """Three inputs (a vector, a 2x2 matrix, a scalar) and three outputs, one of them a sparse Jacobian."""
    x = ca.SX.sym("x", 3)
    P = ca.SX.sym("P", 2, 2)
    s = ca.SX.sym("s")
    y = ca.vertcat(ca.sin(x[0]) * P[0, 0] + x[1] * P[1, 0], ca.cos(x[1]) * P[0, 1] * s, ca.exp(0.1 * x[2]) + P[1, 1])
    J = ca.jacobian(y, x)  # structurally sparse
    M = ca.mtimes(P, P.T) * s + ca.diag(x[:2])
    return ca.Function("spike_f", [x, P, s], [y, J, M], ["x", "P", "s"], ["y", "J", "M"])


def casadi_inputs():
    rng = np.random.default_rng(7)
    return [rng.standard_normal(3), np.asfortranarray(rng.standard_normal((2, 2))), np.array(0.7)]


def expected_outputs(f: ca.Function, args) -> list[np.ndarray]:
    return [np.array(ca.DM(out).full()) for out in f.call([ca.DM(a) for a in args])]


def assert_same(got, want):
    assert len(got) == len(want)
    for g_, w in zip(got, want):
        assert g_.shape == w.shape
        assert np.allclose(g_, w, rtol=1e-14, atol=1e-15), (g_, w)


def libcasadi() -> str:
    """libcasadi of the casadi package imported here (qpnso.model.codegen.libcasadi: the one FastFunction loads)."""
    return str(codegen.libcasadi())


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler: the core uses CasADi's runtime then")
def test_casadi_generated_c_compiled_and_loaded(tmp_path):
    f = casadi_test_function()
    f.generate("spike_f.c", {"with_header": False})  # written to the working directory
    shutil.move("spike_f.c", tmp_path / "spike_f.c")
    lib = tmp_path / "spike_f.so"
    subprocess.run(["cc", "-O1", "-fPIC", "-shared", str(tmp_path / "spike_f.c"), "-o", str(lib), "-lm"], check=True)
    core_f = _core.CasadiFunction.load_compiled(str(lib), "spike_f")
    assert (core_f.runtime, core_f.n_in, core_f.n_out) == ("compiled C", 3, 3)
    args = casadi_inputs()
    assert_same(core_f(args), expected_outputs(f, args))


def test_casadi_runtime_from_the_wheel(tmp_path):
    f = casadi_test_function()
    f.save(str(tmp_path / "spike_f.casadi"))
    core_f = _core.CasadiFunction.load_runtime(libcasadi(), str(tmp_path / "spike_f.casadi"), "spike_f")
    assert core_f.runtime == "casadi runtime"
    args = casadi_inputs()
    want = expected_outputs(f, args)
    assert_same(core_f(args), want)
    # into arrays of the caller's: written in place, nothing allocated or copied
    outs = [np.zeros(w.shape, order="F") for w in want]
    ids = [o.__array_interface__["data"][0] for o in outs]
    core_f.eval_into(args, outs)
    assert [o.__array_interface__["data"][0] for o in outs] == ids
    assert_same(outs, want)
    with pytest.raises(TypeError):  # a C-ordered 2x2 output would need a copy: refused, not silently lost
        core_f.eval_into(args, [outs[0], outs[1], np.zeros((3, 3))])


def test_core_calls_release_the_gil(tmp_path):
    assert _core._gil_held_in_core_call() is False
    # and four threads evaluate at once, each its own bound evaluation, without one waiting on another's GIL
    f = casadi_test_function()
    f.save(str(tmp_path / "spike_f.casadi"))
    core_f = _core.CasadiFunction.load_runtime(libcasadi(), str(tmp_path / "spike_f.casadi"), "spike_f")
    args = [np.asfortranarray(a, dtype=float) for a in casadi_inputs()]
    want = expected_outputs(f, args)
    answers = []

    def evaluate() -> None:
        outs = [np.zeros(w.shape, order="F") for w in want]
        bound = core_f.bind([a.copy(order="F") for a in args], outs)
        for _ in range(200):
            bound()
        answers.append(outs)

    threads = [threading.Thread(target=evaluate) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(answers) == 4
    for outs in answers:
        assert_same(outs, want)


PRINT_CMAKE_PREFIX = (
    "from importlib.metadata import distribution as d; print(d('qpnso').locate_file('qpnso/share/cmake'))"
)
"""The command of examples/cpp/CMakeLists.txt: it does not import qpnso (nor Numba, CasADi...)."""


def cmake_prefix() -> str:
    """Where find_package(qpnso) looks: the installed package's share/cmake (regular and editable install)."""
    return subprocess.run(
        [sys.executable, "-c", PRINT_CMAKE_PREFIX], check=True, capture_output=True, text=True
    ).stdout.strip()


@pytest.mark.skipif(shutil.which("cmake") is None or shutil.which("c++") is None, reason="no cmake or C++ compiler")
def test_cpp_example_evaluates_the_ticks_state_as_python_does(tmp_path):
    """examples/cpp/state_loop, built against the installed package, evaluates the LWR4+'s tick state function
    (exported by ``StateEvaluator.save``) over 50 ticks of its joint sweep; its last state equals the Python
    controller's evaluation at the same input to 1e-12 (the same CasADi runtime: round-off of the printed
    digits only)."""
    from qpnso import Controller, ControllerConfig, load_robot

    build = tmp_path / "build"
    configure = ["cmake", "-S", str(EXAMPLE), "-B", str(build), f"-DCMAKE_PREFIX_PATH={cmake_prefix()}"]
    subprocess.run([*configure, "-DCMAKE_BUILD_TYPE=Release"], check=True, capture_output=True)
    subprocess.run(["cmake", "--build", str(build), "-j2"], check=True, capture_output=True)
    robot = load_robot("lwr4p")
    evaluator = Controller(robot, ControllerConfig(strategy="damped")).evaluate
    function = evaluator.save(tmp_path / "state.casadi")
    name = evaluator._fn.function.name()
    ticks = 50
    run = [str(build / "state_loop"), libcasadi(), str(function), name, str(ticks)]
    out = subprocess.run(run, check=True, capture_output=True, text=True).stdout.splitlines()
    assert out[0].startswith(f"{name}: casadi runtime, {ticks} ticks: median ")
    got = np.array([float(v) for v in out[1:]])
    q = 0.3 * np.sin(1e-3 * (ticks - 1) + np.arange(robot.nq))
    zero7, zero6 = np.zeros(robot.nq), np.zeros(6)
    want = evaluator.record(q, zero7, zero6, zero6).view(np.float64).ravel().copy()
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_released_runtime_functions_leave_libcasadis_list(tmp_path):
    """libcasadi's C API keeps every loaded Function in one list and can pop only its last entry: a released
    CasadiFunction's entry goes once every entry above it is released (each load of a tick's state function
    kept about 1 MB before: 98 MB over 100 loads)."""
    import ctypes

    n_loaded = ctypes.CDLL(libcasadi()).casadi_c_n_loaded  # (the same library the core loaded: one list)
    f = casadi_test_function()
    f.save(str(tmp_path / "spike_f.casadi"))
    n0 = n_loaded()
    a = _core.CasadiFunction.load_runtime(libcasadi(), str(tmp_path / "spike_f.casadi"), "spike_f")
    b = _core.CasadiFunction.load_runtime(libcasadi(), str(tmp_path / "spike_f.casadi"), "spike_f")
    assert n_loaded() == n0 + 2
    del a  # (below b: stays until b goes)
    assert n_loaded() == n0 + 2
    args = casadi_inputs()
    assert_same(b(args), expected_outputs(f, args))
    del b
    assert n_loaded() == n0
