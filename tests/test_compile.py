"""Compiled code is never stale, and compiling is visible and finishes (qpnso/compiled_cache.py,
qpnso/model/codegen.py).

Each test runs Python in a subprocess with its own empty caches (``QPNSO_CACHE_DIR`` in a tmp
folder, no ``NUMBA_CACHE_DIR``), so what it sees is what a user's first runs see.
"""

from __future__ import annotations

import contextlib
import importlib
import inspect
import io
import os
import pkgutil
import shutil
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numba
import numpy as np
import pytest

import qpnso
import qpnso._core
from qpnso import compiled_cache

PACKAGE = Path(qpnso.__file__).resolve().parent


def _env(cache: Path, pythonpath: Path | None = None, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env.update({"QPNSO_CACHE_DIR": str(cache), "QPNSO_COMPILE": "off"}, **extra)
    if pythonpath is not None:
        env["PYTHONPATH"] = str(pythonpath)
    return env


def _python(code: str, env: dict[str, str], cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    done = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], env=env, cwd=cwd, capture_output=True, text=True, timeout=timeout
    )
    assert done.returncode == 0, done.stderr
    return done


NO_EDITABLE_REDIRECT = (
    "import sys; sys.meta_path[:] = [f for f in sys.meta_path if type(f).__name__ != 'ScikitBuildRedirectingFinder']"
)
"""A subprocess's first line that imports qpnso from ``PYTHONPATH``: an editable install's finder (scikit-build-core)
otherwise sends ``import qpnso`` to the checkout whatever the path says."""


def copy_package(dst: Path) -> None:
    """The installed package's files at ``dst``, the compiled core with them (an editable install keeps
    ``qpnso/_core*.so`` and ``qpnso/lib/`` in site-packages, beside no Python source)."""
    shutil.copytree(PACKAGE, dst, ignore=shutil.ignore_patterns("__pycache__"))
    built = Path(qpnso._core.__file__).resolve().parent
    if built != PACKAGE:
        shutil.copy2(qpnso._core.__file__, dst)
        shutil.copytree(built / "lib", dst / "lib", dirs_exist_ok=True)


def test_kernel_recompiles_when_a_kernel_it_calls_in_another_module_changes(tmp_path) -> None:
    """``tick.pose_error`` calls ``linalg.matmul``: Numba alone keeps pose_error's cached code after
    linalg.py changes (it checks tick.py only); the keyed cache folder does not."""
    src = tmp_path / "src"
    copy_package(src / "qpnso")
    linalg = src / "qpnso" / "linalg.py"
    original = linalg.read_bytes()
    env = _env(tmp_path / "cache", pythonpath=src)
    code = f"""
        {NO_EDITABLE_REDIRECT}
        import numpy as np
        import qpnso.control.tick as tick
        assert tick.__file__.startswith({str(src)!r}), tick.__file__
        c, s = np.cos(0.3), np.sin(0.3)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        e = tick.pose_error(R, np.zeros(3), np.eye(3), np.ones(3))
        print(repr([round(float(v), 12) for v in e]))
    """

    def run() -> str:
        return _python(code, env, tmp_path).stdout.strip()

    before = run()
    linalg.write_bytes(
        original
        + textwrap.dedent("""

        _matmul_before = matmul


        @njit(cache=True)
        def matmul(A, B):  # type: ignore[no-untyped-def]
            return 2.0 * _matmul_before(A, B)
    """).encode()
    )
    changed = run()
    assert changed != before, "pose_error ran the cached code of the old linalg.matmul"
    linalg.write_bytes(original)
    assert run() == before


@pytest.mark.jit
def test_every_kernel_is_cached_in_the_keyed_folder() -> None:
    """Every Numba kernel of every qpnso module (also those ``import qpnso`` does not import) is cached
    in the keyed folder, whose key hashes the kernel's module and every qpnso module whose objects it
    holds; Numba's setting is the user's again for other code."""
    folder = compiled_cache.numba_cache_dir()
    assert folder is not None and folder.name == compiled_cache.source_key(qpnso.__version__)
    assert numba.config.CACHE_DIR == os.environ.get("NUMBA_CACHE_DIR", "")
    hashed = set(compiled_cache.kernel_sources())
    kernels = 0
    for info in pkgutil.walk_packages(qpnso.__path__, "qpnso."):
        try:
            module = importlib.import_module(info.name)
        except ImportError:  # an optional dependency (extras) missing
            continue
        here = [
            v
            for v in vars(module).values()
            if isinstance(v, numba.core.dispatcher.Dispatcher) and v.py_func.__module__ == module.__name__
        ]
        for kernel in here:
            path = getattr(kernel._cache, "_cache_path", None)  # None: not cache=True
            assert path is None or Path(path).is_relative_to(folder), (kernel, path)
        kernels += len(here)
        if here:
            for value in vars(module).values():
                origin = value.__name__ if inspect.ismodule(value) else getattr(value, "__module__", None)
                if isinstance(origin, str) and origin.startswith("qpnso"):
                    assert Path(sys.modules[origin].__file__).resolve() in hashed, (module.__name__, value)
    assert kernels >= 20


def test_background_compile_finishes_after_the_process_exits(tmp_path) -> None:
    """A process that exits right after starting a compile still gets its library stored (no ``*.tmp``
    left); a second process started meanwhile waits for that compile instead of starting another
    and loads the finished library; a third loads it from the cache, compiling nothing.  The
    compiler is held until the test releases it, so each step sees the state it checks."""
    if shutil.which(os.environ.get("CC", "cc")) is None:
        pytest.skip("no C compiler")
    cache = tmp_path / "cache"
    cache.mkdir()
    dead = cache / "dead_0123.4.5.tmp"  # a leftover of a compiler that died 11 minutes ago
    dead.write_text("partial")
    os.utime(dead, (time.time() - 660, time.time() - 660))
    calls, release = tmp_path / "cc_calls", tmp_path / "release"
    slow_cc = tmp_path / "slow_cc"  # the system compiler, held until the test releases it
    slow_cc.write_text(f"""#!/bin/sh
echo "$@" >> "{calls}"
i=0; while [ ! -e "{release}" ] && [ $i -lt 600 ]; do sleep 0.1; i=$((i + 1)); done
exec {os.environ.get("CC", "cc")} "$@"
""")
    slow_cc.chmod(0o755)
    env = _env(cache, QPNSO_COMPILE="background", CC=str(slow_cc))
    build = textwrap.dedent("""
        import os, casadi as ca, numpy as np
        from qpnso.model.codegen import FastFunction
        x = ca.SX.sym("x", 3)
        fn = ca.Function("compile_test", [x], [ca.sin(x) * x + ca.sumsqr(x)])
        ff = FastFunction(fn)
    """)
    first = _python(build + "os._exit(0)\n", env, tmp_path)
    assert "qpnso: compiling compile_test in the background (C, once per model, about" in first.stderr
    assert not dead.exists()
    assert not list(cache.glob("*.so")) and len(list(cache.glob("*.tmp"))) == 1  # still compiling
    wait = build + textwrap.dedent("""
        print("constructed", ff.compiled, flush=True)
        assert ff.wait(60), "not compiled"
        x0 = np.array([1.0, 2.0, 3.0])
        assert np.allclose(ff(x0)[0], fn(x0).full().ravel(), rtol=1e-14)
    """)
    second = subprocess.Popen(
        [sys.executable, "-c", wait], env=env, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        assert second.stdout.readline().strip() == "constructed False"
        assert not list(cache.glob("*.so")) and len(list(cache.glob("*.tmp"))) == 1  # the first's compile
        release.touch()
        out, err = second.communicate(timeout=120)
    finally:
        release.touch()
        if second.poll() is None:
            second.kill()
    assert second.returncode == 0, err
    assert "compiling" not in err  # it waited for the first's compile instead of starting one
    for _ in range(300):  # the job folder goes right after the library is renamed into place
        if not list(cache.glob("*.tmp")):
            break
        time.sleep(0.2)
    assert len(list(cache.glob("compile_test_*.so"))) == 1 and not list(cache.glob("*.tmp"))
    third = _python(wait, env, tmp_path)
    assert "compiling" not in third.stderr
    assert len(calls.read_text().splitlines()) == 1  # one compiler for three processes


@pytest.mark.jit
def test_cold_start_says_what_compiles(tmp_path) -> None:
    """The first Controller on a machine (empty Numba cache) says on stderr, before it compiles, that it
    compiles the tick's kernels and about how long that takes.  The process is stopped once the line is
    out: the compile itself (about 60 s of CPU) is what every other test's warm cache already relies on."""
    code = textwrap.dedent("""
        import sys
        import qpnso
        from qpnso import compiled_cache
        assert compiled_cache.numba_cache_is_cold()
        print("cold", flush=True)
        qpnso.Controller(qpnso.load_robot("lwr4p"))
    """)
    proc = subprocess.Popen(
        [sys.executable, "-c", code],
        env=_env(tmp_path / "cache"),
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    line = "qpnso: compiling the control tick's kernels for this machine (once, about"
    try:
        assert proc.stdout.readline().strip() == "cold"
        deadline, seen = time.monotonic() + 120, []
        while time.monotonic() < deadline:
            text = proc.stderr.readline()
            if not text:
                break
            seen.append(text)
            if line in text:
                break
        assert any(line in text for text in seen), "".join(seen)
    finally:
        proc.kill()
        proc.wait()
    qpnso.Controller(qpnso.load_robot("lwr4p"))  # here, with this session's cache: compiled or loaded
    assert not compiled_cache.numba_cache_is_cold()


_TICKS = """
    import json, numpy as np, qpnso
    robot = qpnso.load_robot("lwr4p")
    out = {}
    for strategy in ("qp", "damped"):
        ctrl = qpnso.Controller(robot, qpnso.ControllerConfig(strategy=strategy))
        q = np.radians([10, 40, -10, -70, 20, 50, 0])
        ctrl.reset(q)
        rows = []
        for k in range(30):
            cmd = ctrl.step(q, tool_twist=[0.02 * np.sin(0.1 * k), 0.01, 0, 0, 0, 0.05])
            rows.append(cmd.dq.tolist() + cmd.tau.tolist() + [cmd.status.value])
            q = q + 0.001 * cmd.dq
        out[strategy] = rows
    print(json.dumps(out))
"""


def test_the_kernels_run_as_python_without_the_jit(tmp_path) -> None:
    """``NUMBA_DISABLE_JIT=1`` (a debugger in a kernel, mutation testing): the records are ``numpy.recarray``
    views (:func:`qpnso.records.new_record`), the kernels run as Python, nothing is announced as compiling,
    and 30 closed-loop ticks of ``qp`` and ``damped`` give the compiled kernels' commands and torques to
    round-off, with the same status."""
    import json

    with contextlib.redirect_stdout(io.StringIO()) as printed:
        exec(textwrap.dedent(_TICKS), {})  # this process: the compiled kernels
    jit = json.loads(printed.getvalue())
    python = _python(_TICKS, _env(tmp_path / "cache", NUMBA_DISABLE_JIT="1"), tmp_path)
    assert "compiling the control tick" not in python.stderr
    for strategy, rows in json.loads(python.stdout).items():
        a, b = np.array(rows), np.array(jit[strategy])
        np.testing.assert_array_equal(a[:, -1], b[:, -1])
        np.testing.assert_allclose(a[:, :-1], b[:, :-1], rtol=0, atol=1e-9 * np.abs(b[:, :-1]).max())
