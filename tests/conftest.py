"""Shared fixtures.  Tests use CasADi's virtual machine (no C compilation) unless
a test asks for compiled code itself, so the suite does not spend its time in gcc."""

from __future__ import annotations

import os

import numpy as np
import pytest

os.environ.setdefault("QPNSO_COMPILE", "off")

import qpnso  # noqa: E402
import qpnso.model.robot  # noqa: E402

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
