"""Shared fixtures.  Tests use CasADi's virtual machine (no C compilation) unless
a test asks for compiled code itself, so the suite does not spend its time in gcc."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

os.environ.setdefault("QPNSO_COMPILE", "off")

import qpnso  # noqa: E402
import qpnso.model.robot  # noqa: E402
from qpnso.compiled_cache import jit_disabled  # noqa: E402
from qpnso.records import new_record  # noqa: E402


def _source_tree() -> Path:
    """The qpnso source tree the tests read examples/ from (its scripts, trajectories): ``QPNSO_SOURCE_TREE``
    when the tests run from a copy (``.ci/run`` runs them so against the installed wheel), else the folder
    above tests/.  The package's own data (models, scenarios) are read from the package under test."""
    tree = Path(os.environ.get("QPNSO_SOURCE_TREE") or Path(__file__).resolve().parent.parent).resolve()
    if not (tree / "examples").is_dir():
        raise RuntimeError(f"{tree} is not a qpnso source tree (no examples/): set QPNSO_SOURCE_TREE to one")
    return tree


SOURCE_TREE = _source_tree()
if os.environ.get("QPNSO_TEST_INSTALLED") and Path(qpnso.__file__).resolve().is_relative_to(SOURCE_TREE):
    raise RuntimeError(f"QPNSO_TEST_INSTALLED is set but qpnso is imported from the source tree: {qpnso.__file__}")

SRS_ROBOTS = ["lwr4p", "iiwa14"]
HAS_PANDA = qpnso.model.robot._panda_urdf() is not None
ALL_ROBOTS = SRS_ROBOTS + (["panda"] if HAS_PANDA else [])


@pytest.fixture(scope="session")
def lwr() -> qpnso.Robot:
    return qpnso.load_robot("lwr4p")


@pytest.fixture(scope="session")
def robots() -> dict[str, qpnso.Robot]:
    return {name: qpnso.load_robot(name) for name in ALL_ROBOTS}


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


def reference_arm_angle(robot: qpnso.Robot, q: np.ndarray) -> float:
    """[E 2]–[E 4] literally, with explicitly normalised u_sin, u_cos, from Pinocchio placements."""
    data = robot.model.createData()
    pin.forwardKinematics(robot.model, data, q)
    pts = qpnso.elbow_points(robot)
    ps = data.oMi[pts.shoulder_joint].act(np.array(pts.shoulder_offset))
    pe = data.oMi[pts.elbow_joint].act(np.array(pts.elbow_offset))
    pw = data.oMi[pts.wrist_joint].act(np.array(pts.wrist_offset))
    p_sw, p_se = pw - ps, pe - ps
    u_sin = np.cross([0, 0, 1.0], p_sw)
    u_sin /= np.linalg.norm(u_sin)
    u_cos = np.cross(p_sw, u_sin)
    u_cos /= np.linalg.norm(u_cos)
    return float(np.arctan2(p_se @ u_sin, p_se @ u_cos))


def limit_params(q_min: np.ndarray, q_max: np.ndarray, dq_max: np.ndarray, gain: float, recovery: float):
    """A params record (qpnso.control.params) holding only the joint limits and their damper's gain (1/s) and
    recovery speed (rad/s): what ``velocity_bounds`` reads, given by hand."""
    from qpnso.control.params import params_dtype

    params = new_record(params_dtype(len(q_min)))
    P = params[0]
    P["q_min"], P["q_max"], P["dq_max"] = q_min, q_max, dq_max
    P["joint_limit_gain"], P["recovery_speed"] = gain, recovery
    return P


def kernel_signatures() -> dict[str, int]:
    """Signature counts of every Numba kernel of every qpnso module (walked, not listed by hand)."""
    import importlib
    import pkgutil

    import numba

    out = {}
    for info in pkgutil.walk_packages(qpnso.__path__, "qpnso."):
        try:
            module = importlib.import_module(info.name)
        except ImportError:  # an optional dependency (extras) missing
            continue
        for name, value in vars(module).items():
            if isinstance(value, numba.core.dispatcher.Dispatcher) and value.py_func.__module__ == module.__name__:
                out[f"{module.__name__}.{name}"] = len(value.signatures)
    return out


def pytest_collection_modifyitems(config, items) -> None:
    """Skip the tests marked ``jit`` (they count compiled kernels) when the kernels run as Python."""
    if jit_disabled():
        skip = pytest.mark.skip(reason="counts compiled kernels: NUMBA_DISABLE_JIT=1")
        for item in items:
            if "jit" in item.keywords:
                item.add_marker(skip)


def without_second_pass(monkeypatch) -> None:
    """Make every Controller keep its first solve when the solved q̇ misses the prediction (no
    ``Controller._second_pass``): what the held tool did before the second pass, for tests that show its effect."""
    from qpnso.control.controller import Controller
    from qpnso.control.flags import PREDICTION_MISSED
    from qpnso.control.tick import finish_tick

    def first_solve_kept(self, qv, dq_meas):
        return "", finish_tick(qv, dq_meas, self.tick) & ~PREDICTION_MISSED, 0.0

    monkeypatch.setattr(Controller, "_second_pass", first_solve_kept)
