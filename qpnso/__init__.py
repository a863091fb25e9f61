"""qpnso: hierarchical-QP null-space optimisation of 7-DOF arms for hands-on surgery.

The tool stays the surgeon's (level 1 of a hierarchical QP); the rest of the arm
moves so that the tool feels light (mass and friction costs, level 2) and the
elbow stays in its range of motion, clipped to the arm-angle interval the joint
limits allow.  See docs/method.md for the equations each module implements.
"""

__version__ = "0.1.0"

# First: Numba picks a kernel's cache folder when the kernel is decorated (module import).
from qpnso import compiled_cache as _compiled_cache  # noqa: E402

_compiled_cache.begin_keyed_numba_cache(__version__)

from qpnso.control.config import STRATEGIES, Command, ControllerConfig, Status
from qpnso.control.controller import Controller
from qpnso.elbow.arm_angle import (
    ArmAngle,
    ElbowPoints,
    arm_angle,
    arm_angle_gradient,
    arm_angle_status,
    elbow_points,
)
from qpnso.elbow.intervals import Interval, continuity_interval, feasible_intervals
from qpnso.elbow.rom import ClippedRom, ElbowConfig, clip_rom, rom_bounds, setpoint, stiffness
from qpnso.elbow.srs import Branch, branch, ik, self_motion
from qpnso.errors import (
    ConfigError,
    FrameNotFoundError,
    InputError,
    JobError,
    JointLimitError,
    ModelError,
    QpnsoError,
    RobotNotFoundError,
    SingularityError,
    SolverError,
    TrajectoryError,
    UnreachableError,
)
from qpnso.model.costs import TERMS, CostModel, CostWeights, DirectionalCost
from qpnso.model.obstacles import Box, Capsule, Sphere
from qpnso.model.robot import JointFriction, Robot, load_robot
from qpnso.model.symbolic import SymbolicModel
from qpnso.qp import HierarchicalQP, Level, QPSettings

_compiled_cache.end_keyed_numba_cache()  # last: other code's Numba kernels keep the user's setting

__all__ = [
    "STRATEGIES",
    "TERMS",
    "ArmAngle",
    "Box",
    "Capsule",
    "Branch",
    "ClippedRom",
    "Command",
    "Controller",
    "ControllerConfig",
    "ElbowConfig",
    "ElbowPoints",
    "HierarchicalQP",
    "Interval",
    "Level",
    "QPSettings",
    "Status",
    "arm_angle",
    "arm_angle_gradient",
    "arm_angle_status",
    "branch",
    "clip_rom",
    "continuity_interval",
    "elbow_points",
    "feasible_intervals",
    "ik",
    "rom_bounds",
    "self_motion",
    "setpoint",
    "stiffness",
    "ConfigError",
    "CostModel",
    "CostWeights",
    "DirectionalCost",
    "FrameNotFoundError",
    "InputError",
    "JobError",
    "JointFriction",
    "JointLimitError",
    "ModelError",
    "QpnsoError",
    "Robot",
    "RobotNotFoundError",
    "SingularityError",
    "SolverError",
    "Sphere",
    "SymbolicModel",
    "TrajectoryError",
    "UnreachableError",
    "load_robot",
    "__version__",
]
