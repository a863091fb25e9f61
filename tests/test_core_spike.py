"""Issue 33's build spike: the compiled core qpnso._core (C++17, nanobind, scikit-build-core) is built by
``pip install .`` and ``pip install -e .`` and answers as the Python libraries do, to round-off:

* a dense QP by ProxSuite's C++ API against the Python proxsuite's dense solver;
* a CasADi Function evaluated without Python, both ways the core will use: the shared library compiled from
  the C that ``Function.generate`` writes, and CasADi's own runtime (libcasadi of the casadi wheel, through its
  C API, on a Function saved with ``Function.save``), against casadi's own evaluation in Python;
* the C++ API: examples/cpp/ built with CMake against the installed package (find_package(qpnso)) and run.
"""

from __future__ import annotations

import glob
import os
import shutil
import subprocess
import sys
import threading
from importlib import metadata

import casadi as ca
import numpy as np
import proxsuite
import pytest
from conftest import SOURCE_TREE

from qpnso import _core

EXAMPLE = SOURCE_TREE / "examples" / "cpp"


def random_qp(rng: np.random.Generator, n: int = 7, n_eq: int = 2, n_in: int = 5):
    M = rng.standard_normal((n, n))
    H = M @ M.T + 0.1 * np.eye(n)
    g = rng.standard_normal(n)
    A = rng.standard_normal((n_eq, n))
    b = rng.standard_normal(n_eq)
    C = rng.standard_normal((n_in, n))
    l = -0.2 * np.ones(n_in)  # tight enough that some rows are active
    u = 0.3 * np.ones(n_in)
    return H, g, A, b, C, l, u


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_dense_qp_matches_python_proxsuite(seed):
    H, g, A, b, C, l, u = random_qp(np.random.default_rng(seed))
    got = _core.solve_dense_qp(H, g, A, b, C, l, u, eps_abs=1e-10)
    qp = proxsuite.proxqp.dense.QP(H.shape[0], A.shape[0], C.shape[0])
    qp.settings.eps_abs = 1e-10
    qp.settings.eps_rel = 0.0
    qp.init(H, g, A, b, C, l, u)
    qp.solve()
    assert got["status"] == 0  # PROXQP_SOLVED
    assert np.allclose(got["x"], qp.results.x, rtol=0, atol=1e-8)
    assert np.allclose(got["z"], qp.results.z, rtol=0, atol=1e-7)
    # and it is the optimum: stationarity and feasibility, judged in NumPy
    x, y, z = got["x"], got["y"], got["z"]
    assert np.linalg.norm(H @ x + g + A.T @ y + C.T @ z, np.inf) < 1e-8
    assert np.linalg.norm(A @ x - b, np.inf) < 1e-9
    assert np.all(C @ x >= l - 1e-9) and np.all(C @ x <= u + 1e-9)


def test_dense_qp_without_constraints_and_from_other_layouts():
    H, g, *_ = random_qp(np.random.default_rng(3))
    x = _core.solve_dense_qp(H, g, eps_abs=1e-12)["x"]  # ProxQP's stop is on residuals: |dx| <= eps / min eig H
    assert np.allclose(x, np.linalg.solve(H, -g), rtol=0, atol=1e-9)
    # Fortran-ordered and float32 inputs are converted once by the binding, not refused
    assert np.allclose(
        _core.solve_dense_qp(np.asfortranarray(H), g.astype(np.float32))["x"],
        np.linalg.solve(H, -g.astype(np.float32).astype(float)),
        atol=1e-6,
    )
    with pytest.raises(ValueError):
        _core.solve_dense_qp(H, g[:-1])


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
    """libcasadi of the casadi package imported here (its name carries CasADi's soname version)."""
    found = sorted(glob.glob(os.path.join(os.path.dirname(ca.__file__), "libcasadi.so.*")))
    assert found, "no libcasadi in the casadi wheel"
    return found[0]


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


def test_core_calls_release_the_gil():
    assert _core._gil_held_in_core_call() is False
    # and two threads solve at once without one waiting on the other's GIL
    H, g, A, b, C, l, u = random_qp(np.random.default_rng(0))
    answers = []
    threads = [
        threading.Thread(target=lambda: answers.append(_core.solve_dense_qp(H, g, A, b, C, l, u)["x"]))
        for _ in range(4)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(answers) == 4 and all(np.array_equal(a, answers[0]) for a in answers)


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
def test_cpp_example_builds_against_the_installed_package_and_answers_as_python(tmp_path):
    build = tmp_path / "build"
    subprocess.run(
        [
            "cmake",
            "-S",
            str(EXAMPLE),
            "-B",
            str(build),
            f"-DCMAKE_PREFIX_PATH={cmake_prefix()}",
            "-DCMAKE_BUILD_TYPE=Release",
        ],
        check=True,
        capture_output=True,
    )
    subprocess.run(["cmake", "--build", str(build), "-j2"], check=True, capture_output=True)
    out = subprocess.run([str(build / "core_spike")], check=True, capture_output=True, text=True).stdout
    x = np.array([float(v) for v in out.split("x =")[1].split()[:3]])
    H = np.array([[4.0, 1.0, 0.0], [1.0, 3.0, 0.5], [0.0, 0.5, 2.0]])
    g = np.array([1.0, -2.0, 0.5])
    A = np.array([[1.0, 1.0, 1.0]])
    want = _core.solve_dense_qp(H, g, A, np.array([1.0]), np.eye(3), -np.ones(3) * 0.4, np.ones(3))["x"]
    assert np.allclose(x, want, rtol=0, atol=1e-12)
    assert metadata.version("qpnso") in out


def test_the_committed_stub_is_the_one_nanobind_writes(tmp_path):
    """qpnso/_core.pyi (what mypy reads) is nanobind.stubgen's output for the built module, unchanged: regenerate it
    with ``python -m nanobind.stubgen -m qpnso._core -o qpnso/_core.pyi`` when the binding changes."""
    stub = tmp_path / "_core.pyi"
    subprocess.run([sys.executable, "-m", "nanobind.stubgen", "-q", "-m", "qpnso._core", "-o", str(stub)], check=True)
    committed = SOURCE_TREE / "qpnso" / "_core.pyi"
    assert stub.read_text() == committed.read_text(), "qpnso/_core.pyi is stale: regenerate it (docstring above)"
