"""qpnso: hierarchical-QP null-space optimisation of 7-DOF arms for hands-on surgery.

The tool stays the surgeon's (level 1 of a hierarchical QP); the rest of the arm
moves so that the tool feels light (mass and friction costs, level 2) and the
elbow stays in its range of motion, clipped to the arm-angle interval the joint
limits allow.  See METHOD.md for the equations each module implements.
"""

from qpnso.costs import TERMS, CostModel, CostWeights, DirectionalCost
from qpnso.errors import (
    ConfigError,
    FrameNotFoundError,
    InputError,
    JointLimitError,
    ModelError,
    QpnsoError,
    RobotNotFoundError,
    SingularityError,
    SolverError,
    TrajectoryError,
    UnreachableError,
)
from qpnso.robot import JointFriction, Robot, load_robot
from qpnso.symbolic import SymbolicModel

__version__ = "0.1.0"

__all__ = [
    "TERMS",
    "ConfigError",
    "CostModel",
    "CostWeights",
    "DirectionalCost",
    "FrameNotFoundError",
    "InputError",
    "JointFriction",
    "JointLimitError",
    "ModelError",
    "QpnsoError",
    "Robot",
    "RobotNotFoundError",
    "SingularityError",
    "SolverError",
    "SymbolicModel",
    "TrajectoryError",
    "UnreachableError",
    "load_robot",
    "__version__",
]
