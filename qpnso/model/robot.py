"""Robot model: a Pinocchio model with its tool frame, limits and joint friction.

``load_robot`` is the single entry point.  Everything numeric here is plain
Pinocchio; the symbolic twin lives in :mod:`qpnso.model.symbolic`.

Conventions (Pinocchio's):
* ``q`` in rad, ``dq`` in rad/s, torques in N·m;
* the tool Jacobian is ``LOCAL_WORLD_ALIGNED``: the 6×nq matrix that maps ``dq``
  to the tool point's linear velocity (rows 0–2, m/s) and the tool's angular
  velocity (rows 3–5, rad/s), both expressed in the world frame (docs/method.md §2).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import pinocchio as pin

from qpnso.errors import (
    ConfigError,
    FrameNotFoundError,
    InputError,
    JointLimitError,
    ModelError,
    RobotNotFoundError,
)
from qpnso.shipped import shipped_dir

MODELS_DIR = shipped_dir("models")
"""Folder of the robot description files shipped with qpnso (``models/`` of the source tree)."""

SHIPPED_URDF = {"lwr4p": "lwr4p.urdf", "iiwa14": "iiwa14.urdf"}
OPTIONAL_ROBOTS = ("panda",)
DEFAULT_TOOL_FRAME = {"panda": "panda_link8"}
TOOL_FRAME_NAME = "qpnso_tool"
"""Name of the frame qpnso adds at the tool point (tool frame × tool offset)."""


@dataclass(frozen=True)
class JointFriction:
    """Smooth Coulomb joint friction [M 23]: τf = τmax·(2/π)·atan(β·dq).

    ``tau_max`` (N·m) is the sliding torque, ``beta`` (s/rad) the slope
    parameter: dτf/ddq at rest is τmax·β·2/π.
    """

    tau_max: np.ndarray
    beta: np.ndarray

    def torque(self, dq: np.ndarray) -> np.ndarray:
        """Friction torque (N·m) at joint velocity ``dq`` (rad/s)."""
        return self.tau_max * (2.0 / np.pi) * np.arctan(self.beta * dq)


def _real_array(x: object, name: str, what: str) -> np.ndarray:
    """``x`` as a float array; :class:`InputError` for complex, boolean, object or text data (NumPy
    would cast complex with only a warning, dropping the imaginary part)."""
    try:
        a = np.asarray(x)
        if a.dtype.kind not in "fiu":
            raise TypeError(f"got {a.dtype.name} data" if a.dtype.kind != "O" else "got non-numeric entries")
        return a.astype(float, copy=False)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be {what} of real numbers: {exc}") from None


def finite_scalar(x: object, name: str) -> float:
    """``x`` as a finite real float, or :class:`InputError` naming ``name``."""
    a = _real_array(x, name, "a number")
    if a.shape not in ((), (1,)) or not math.isfinite(float(a.reshape(-1)[0])):
        raise InputError(f"{name} must be one finite number, got {x!r}")
    return float(a.reshape(-1)[0])


POSE_NOT_FINITE, POSE_NOT_ROTATION = 1, 2
"""Codes of :func:`pose_defect`."""


def pose_defect(R: np.ndarray, p: np.ndarray) -> int:
    """0 when ``R`` (3, 3) is a rotation (``RᵀR = I`` to 1e-6, det > 0) and ``R``, ``p`` (3,) are finite;
    else :data:`POSE_NOT_FINITE` or :data:`POSE_NOT_ROTATION`.  Scalar arithmetic on plain floats: a
    ``tool_pose`` given every tick is checked in about 5 µs (NumPy's isfinite, ``RᵀR`` and det took 36)."""
    r = R.tolist()
    values = r[0] + r[1] + r[2] + p.tolist()
    if not all(map(math.isfinite, values)):
        return POSE_NOT_FINITE
    for i in range(3):
        for j in range(i, 3):
            if abs(r[0][i] * r[0][j] + r[1][i] * r[1][j] + r[2][i] * r[2][j] - (i == j)) > 1e-6:
                return POSE_NOT_ROTATION
    det = (
        r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1])
        - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
        + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0])
    )
    return POSE_NOT_ROTATION if det < 0 else 0


def checked_pose(pose: object, name: str) -> tuple[np.ndarray, np.ndarray]:
    """``(rotation (3, 3), translation (3,) m)`` copies of a ``pinocchio.SE3``; :class:`InputError`
    for another type, a non-finite entry, or a rotation that is not orthonormal (to 1e-6)."""
    if not isinstance(pose, pin.SE3):
        raise InputError(f"{name} must be a pinocchio.SE3, got {type(pose).__name__}")
    R, p = np.array(pose.rotation, order="C"), np.array(pose.translation)  # C order: the tick's kernels' one type
    defect = pose_defect(R, p)
    if defect == POSE_NOT_FINITE:
        raise InputError(f"{name} contains NaN or inf")
    if defect == POSE_NOT_ROTATION:
        raise InputError(f"{name}.rotation is not a rotation matrix")
    return R, p


def as_vector(x: object, n: int, name: str) -> np.ndarray:
    """Return ``x`` as a finite float vector of length ``n`` or raise InputError."""
    v = _real_array(x, name, f"a numeric vector of length {n}")
    if v.ndim == 2 and 1 in v.shape:
        v = v.reshape(-1)
    if v.shape != (n,):
        raise InputError(f"{name} must have shape ({n},), got {v.shape}")
    total = float(v.sum())  # one reduction; finite sum <=> finite entries (overflow: full check)
    if total - total != 0.0 and not np.all(np.isfinite(v)):
        bad = np.flatnonzero(~np.isfinite(v)).tolist()
        raise InputError(f"{name} contains NaN or inf at index {bad}")
    if not (v.flags.c_contiguous and v.flags.writeable):  # one array type for the tick's Numba kernels:
        v = v.copy()  # a strided view or read-only buffer would load or compile another version mid-loop
    return v


def tick_vector(x: object, n: int, name: str) -> np.ndarray:
    """``x`` itself when it already is the control tick's one vector type (a writable, C-ordered float64
    NumPy array of shape (n,)), its finiteness then checked by the tick's kernel; else :func:`as_vector`
    (checked and converted here).  A caller's loop passing fresh arrays pays no Python check."""
    if (
        type(x) is np.ndarray
        and x.dtype == np.float64
        and x.shape == (n,)
        and x.flags.c_contiguous
        and x.flags.writeable
    ):
        return x
    return as_vector(x, n, name)


class Robot:
    """A serial arm: Pinocchio model and data, limits, tool frame and friction.

    Attributes use SI units: ``q_min``, ``q_max`` (rad), ``dq_max`` (rad/s),
    ``ddq_max`` (rad/s²: the bound on a command's change per second, ``models/acceleration.json`` for a shipped
    robot, else :data:`ASSUMED_DDQ_MAX`), ``tau_limit`` (N·m).  ``tool_frame_id`` is the Pinocchio frame at the tool
    point.  ``data`` is the model's scratch data, reused by every call (not
    thread-safe: give each thread its own ``Robot``).
    """

    def __init__(
        self,
        name: str,
        model: pin.Model,
        tool_frame_id: int,
        friction: JointFriction,
        source: str = "",
    ) -> None:
        self.name = name
        self.model = model
        self.data = model.createData()
        self.tool_frame_id = tool_frame_id
        self.friction = friction
        self.source = source
        self.nq = model.nq
        self.q_min = np.array(model.lowerPositionLimit, dtype=float)
        self.q_max = np.array(model.upperPositionLimit, dtype=float)
        self.dq_max = np.array(model.velocityLimit, dtype=float)
        self.tau_limit = np.array(model.effortLimit, dtype=float)
        self.ddq_max = _acceleration_limits(name, self.nq)
        self._check_model()

    def _check_model(self) -> None:
        if self.model.nq != self.model.nv:
            raise ModelError(f"{self.name}: only revolute/prismatic joints are supported (nq != nv)")
        if not np.all(np.isfinite(self.q_min)) or not np.all(np.isfinite(self.q_max)):
            raise ModelError(f"{self.name}: every joint needs finite position limits")
        if np.any(self.q_min >= self.q_max):
            raise ModelError(f"{self.name}: a lower position limit is not below the upper one")
        if np.any(self.dq_max <= 0):
            raise ModelError(f"{self.name}: every joint needs a positive velocity limit")

    # ------------------------------------------------------------------ input
    @property
    def joint_names(self) -> list[str]:
        """Names of the actuated joints, base to tip."""
        return [str(n) for n in self.model.names[1:]]

    def check_q(self, q: object, name: str = "q", tol: float = 1e-9) -> np.ndarray:
        """Validate a configuration: shape (nq,), finite, within joint limits (rad)."""
        v = as_vector(q, self.nq, name)
        low = v < self.q_min - tol
        high = v > self.q_max + tol
        if np.any(low | high):
            k = int(np.flatnonzero(low | high)[0])
            raise JointLimitError(
                f"{name}[{k}] ({self.joint_names[k]}) = {np.degrees(v[k]):.3f} deg is outside "
                f"its limits [{np.degrees(self.q_min[k]):.1f}, {np.degrees(self.q_max[k]):.1f}] deg"
            )
        return v

    def require_redundant_arm(self) -> None:
        """Raise :class:`ModelError` unless the arm has exactly 7 joints.

        qpnso keeps a 6-D tool task and moves the arm in what is left: the one
        redundant degree of freedom of a 7-DOF arm (the elbow's arm angle).  A
        6-DOF arm has none, an arm with more joints has no single arm angle.
        """
        if self.nq != 7:
            raise ModelError(
                f"qpnso needs a 7-DOF arm (one redundant degree of freedom for a 6-D tool task); "
                f"{self.name} has {self.nq} joints"
            )

    def sample_configuration(self) -> np.ndarray:
        """A non-singular configuration inside the limits (rad): elbow and wrist bent;
        the Panda's "ready" posture for ``panda``."""
        if self.name == "panda":
            q = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
        else:
            q = np.zeros(self.nq)
            q[1], q[3], q[5] = 0.5, -1.2, 0.8
        return np.clip(q, self.q_min, self.q_max)

    def random_q(self, rng: np.random.Generator, margin: float = 0.0) -> np.ndarray:
        """A configuration drawn uniformly within the limits shrunk by ``margin`` rad."""
        return rng.uniform(self.q_min + margin, self.q_max - margin)

    # ------------------------------------------------------------- kinematics
    def tool_pose(self, q: object) -> pin.SE3:
        """Pose of the tool frame in the world (``pinocchio.SE3``, metres)."""
        qv = as_vector(q, self.nq, "q")
        pin.framesForwardKinematics(self.model, self.data, qv)
        return pin.SE3(self.data.oMf[self.tool_frame_id])

    def jacobian(self, q: object) -> np.ndarray:
        """6×nq tool Jacobian, world-aligned at the tool point, linear rows first."""
        qv = as_vector(q, self.nq, "q")
        return pin.computeFrameJacobian(self.model, self.data, qv, self.tool_frame_id, pin.LOCAL_WORLD_ALIGNED).copy()

    def joint_placement(self, q: object, joint: int) -> pin.SE3:
        """World pose of joint ``joint``'s frame (1-based Pinocchio joint index)."""
        qv = as_vector(q, self.nq, "q")
        pin.forwardKinematics(self.model, self.data, qv)
        return pin.SE3(self.data.oMi[joint])

    # --------------------------------------------------------------- dynamics
    def mass_matrix(self, q: object) -> np.ndarray:
        """Joint-space inertia matrix A(q) (nq×nq, kg·m²), symmetric."""
        qv = as_vector(q, self.nq, "q")
        pin.crba(self.model, self.data, qv)
        a = self.data.M.copy()
        return np.triu(a) + np.triu(a, 1).T

    def gravity(self, q: object) -> np.ndarray:
        """Gravity torques g(q) (N·m): the torque that holds the arm still."""
        qv = as_vector(q, self.nq, "q")
        return pin.computeGeneralizedGravity(self.model, self.data, qv).copy()

    def friction_torque(self, dq: object) -> np.ndarray:
        """Joint friction torques (N·m) of the smooth Coulomb model [M 23]."""
        return self.friction.torque(as_vector(dq, self.nq, "dq"))

    def __repr__(self) -> str:
        return f"Robot({self.name!r}, nq={self.nq}, tool={self.model.frames[self.tool_frame_id].name!r})"


# ---------------------------------------------------------------------- loading
def load_robot(
    name_or_path: str | Path = "lwr4p",
    tool_frame: str | None = None,
    tool_offset: object = None,
    friction: JointFriction | None = None,
    armature: object = None,
) -> Robot:
    """Load a shipped robot (``"lwr4p"``, ``"iiwa14"``, ``"panda"``) or a URDF file.

    ``tool_frame`` names the frame the tool is mounted on (default ``"tool"``,
    the flange, for shipped URDFs; ``"panda_link8"`` for the Panda).
    ``tool_offset`` is the tool point in that frame: a 3-vector (m) or a
    ``pinocchio.SE3``.  ``friction`` overrides the per-joint friction of
    ``models/friction.json``.  ``armature`` (kg·m², one per joint) overrides the reflected rotor inertia of
    ``models/armature.json`` (shipped robots; a user URDF gets none unless given): it is part of the model's
    A(q) (Pinocchio's ``model.armature``), so of the costs, the projector and the simulated plant alike.
    """
    name, model, source = _load_model(name_or_path)
    model.armature = _armature(name, model) if armature is None else _checked_armature(armature, model.nv)
    frame_name = tool_frame or DEFAULT_TOOL_FRAME.get(name, "tool")
    tool_id = _add_tool_frame(model, frame_name, _as_se3(tool_offset))
    return Robot(name, model, tool_id, friction or _default_friction(name, model), source)


def robot_spec(robot: Robot) -> dict:
    """What :func:`load_robot_spec` needs to load ``robot``'s kinematics again, as plain data (a result file's
    ``scene`` record): ``robot`` (a shipped name or the URDF path), ``tool_frame`` (the frame the tool is mounted
    on) and ``tool_offset`` (the tool frame in it, a 4×4 homogeneous matrix, m)."""
    tool = robot.model.frames[robot.tool_frame_id]
    parent = robot.model.frames[tool.parentFrame]
    shipped = robot.name in SHIPPED_URDF or robot.name in OPTIONAL_ROBOTS
    return {
        "robot": robot.name if shipped else robot.source,
        "tool_frame": parent.name,
        "tool_offset": (parent.placement.inverse() * tool.placement).homogeneous.tolist(),
    }


def load_robot_spec(spec: object) -> Robot:
    """The robot of a :func:`robot_spec` record (a ModelError names what is wrong with the record)."""
    if not isinstance(spec, dict):
        raise ModelError(f"not a robot record (robot, tool_frame, tool_offset): {spec!r}")
    try:
        offset = pin.SE3(np.array(spec["tool_offset"], dtype=np.float64))
        name, frame = str(spec["robot"]), str(spec["tool_frame"])
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise ModelError(f"not a robot record (robot, tool_frame, tool_offset): {exc}") from None
    return load_robot(name, tool_frame=frame, tool_offset=offset)


def _load_model(name_or_path: str | Path) -> tuple[str, pin.Model, str]:
    key = str(name_or_path)
    if key in SHIPPED_URDF:
        path = MODELS_DIR / SHIPPED_URDF[key]
        return key, _model_from_urdf(path), str(path)
    if key in OPTIONAL_ROBOTS:
        return key, _panda_model(), "example-robot-data"
    path = Path(key)
    if path.suffix.lower() == ".urdf" or path.exists():
        return path.stem, _model_from_urdf(path), str(path)
    known = ", ".join([*SHIPPED_URDF, *OPTIONAL_ROBOTS])
    raise RobotNotFoundError(f"unknown robot {key!r}: give one of {known} or a URDF file path")


def _model_from_urdf(path: Path) -> pin.Model:
    if not path.is_file():
        raise RobotNotFoundError(f"URDF file not found: {path}")
    try:
        return pin.buildModelFromUrdf(str(path))
    except (RuntimeError, ValueError) as exc:
        raise ModelError(f"cannot parse URDF {path}: {exc}") from None


PANDA_URDF = Path("share/example-robot-data/robots/panda_description/urdf/panda.urdf")
"""Where the PyPI ``example-robot-data`` wheel puts the Panda, below its ``cmeel.prefix``."""


def _panda_urdf() -> Path | None:
    """The Panda URDF of an installed ``example-robot-data``, if any."""
    import importlib.metadata

    try:
        dist = importlib.metadata.distribution("example-robot-data")
    except importlib.metadata.PackageNotFoundError:
        return None
    path = Path(str(dist.locate_file(Path("cmeel.prefix") / PANDA_URDF)))
    return path if path.is_file() else None


def _panda_model() -> pin.Model:
    """Franka Panda arm (fingers locked) from the optional ``example-robot-data``."""
    urdf = _panda_urdf()
    if urdf is None:
        raise RobotNotFoundError(
            "robot 'panda' needs the optional package example-robot-data (pip install 'qpnso[robots]')"
        )
    full = _model_from_urdf(urdf)
    fingers = [full.getJointId(n) for n in full.names if "finger" in n]
    return pin.buildReducedModel(full, fingers, pin.neutral(full)) if fingers else full


def _as_se3(offset: object) -> pin.SE3:
    if offset is None:
        return pin.SE3.Identity()
    if isinstance(offset, pin.SE3):
        return pin.SE3(offset)
    return pin.SE3(np.eye(3), as_vector(offset, 3, "tool_offset"))


def _add_tool_frame(model: pin.Model, frame_name: str, offset: pin.SE3) -> int:
    if not model.existFrame(frame_name):
        names = [f.name for f in model.frames if f.type in (pin.FrameType.BODY, pin.FrameType.OP_FRAME)]
        raise FrameNotFoundError(f"unknown tool frame {frame_name!r}; frames in the model: {names}")
    parent_id = model.getFrameId(frame_name)
    parent = model.frames[parent_id]
    frame = pin.Frame(TOOL_FRAME_NAME, parent.parentJoint, parent_id, parent.placement * offset, pin.FrameType.OP_FRAME)
    return model.addFrame(frame)


def _default_friction(name: str, model: pin.Model) -> JointFriction:
    """Friction of ``models/friction.json`` for shipped robots, else the URDF's.

    For a user URDF, τmax is the URDF ``<dynamics friction>`` where given
    (1.5 N·m otherwise) and β the LWR4+ default.
    """
    table = load_friction_table()
    if name in table:
        entry = table[name]
        return friction_from_lists(entry["tau_max_Nm"], entry["beta_s_per_rad"], model.nv)
    default = table.get("lwr4p", {"tau_max_Nm": [1.5], "beta_s_per_rad": [20.0]})
    tau = np.where(np.asarray(model.friction) > 0, model.friction, default["tau_max_Nm"][0])
    return friction_from_lists(tau, [default["beta_s_per_rad"][0]] * model.nv, model.nv)


def load_robot_with_armature(name_or_path: str | Path, armature_kgm2: float | None) -> Robot:
    """:func:`load_robot` with the rotor inertia ``armature_kgm2`` (kg·m², >= 0) on every joint, or with the
    model's own (``models/armature.json``) when it is None; :class:`ConfigError` for any other value."""
    value = checked_armature_kgm2(armature_kgm2)
    robot = load_robot(name_or_path)
    return robot if value is None else load_robot(name_or_path, armature=np.full(robot.nq, value))


def checked_armature_kgm2(value: object, name: str = "armature_kgm2") -> float | None:
    """``value`` as one rotor inertia for every joint (kg·m², a finite number >= 0), None kept (the model's
    own); :class:`ConfigError` naming ``name`` otherwise."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise ConfigError(f"{name} must be a rotor inertia in kg·m² (a number >= 0) or None, got {value!r}")
    if not (math.isfinite(value) and value >= 0):
        raise ConfigError(f"{name} must be a finite rotor inertia >= 0 kg·m², got {value!r}")
    return float(value)


def _armature(name: str, model: pin.Model) -> np.ndarray:
    """The reflected rotor inertias (kg·m²) of ``models/armature.json`` for a shipped robot, else the
    model's own (zero for a URDF, which has no field for it)."""
    table = _json_table(MODELS_DIR / "armature.json")
    if name in table:
        return _checked_armature(table[name]["armature_kgm2"], model.nv)
    return np.array(model.armature, dtype=float)


ASSUMED_DDQ_MAX = 10.0
"""rad/s²: the joint acceleration bound of a robot that ``models/acceleration.json`` does not list (a URDF has
no field for it): the value assumed for the KUKA arms there, within the 7.5–20 rad/s² the Franka Panda's maker
publishes.  An assumption: give ``ControllerConfig.ddq_max`` for your robot."""


def _acceleration_limits(name: str, n: int) -> np.ndarray:
    """The joint acceleration bounds (rad/s²) of ``models/acceleration.json`` for a shipped robot, else
    :data:`ASSUMED_DDQ_MAX` on every joint."""
    table = _json_table(MODELS_DIR / "acceleration.json")
    if name in table:
        return as_vector(table[name]["ddq_max_rad_s2"], n, "ddq_max")
    return np.full(n, ASSUMED_DDQ_MAX)


def _checked_armature(values: object, n: int) -> np.ndarray:
    """``values`` as ``n`` armatures >= 0 kg·m², or :class:`InputError`."""
    a = as_vector(values, n, "armature")
    if np.any(a < 0):
        raise InputError(f"armature must be >= 0 kg·m² for every joint, got {a.tolist()}")
    return a


def _json_table(path: Path) -> dict:
    """A per-robot table of ``models/`` (empty when the file is missing)."""
    return json.loads(path.read_text()) if path.is_file() else {}


def load_friction_table(path: Path | None = None) -> dict:
    """The per-robot friction parameters of ``models/friction.json``."""
    return _json_table(path or MODELS_DIR / "friction.json")


def friction_from_lists(tau_max: Sequence[float], beta: Sequence[float], n: int) -> JointFriction:
    """Build a :class:`JointFriction`, checking n positive entries each."""
    t = as_vector(tau_max, n, "tau_max")
    b = as_vector(beta, n, "beta")
    if np.any(t < 0) or np.any(b <= 0):
        raise InputError("friction needs tau_max >= 0 N·m and beta > 0 s/rad for every joint")
    return JointFriction(tau_max=t, beta=b)
