"""Keep-out volumes of the operating room: the equipment around the patient as world-frame primitives
(docs/method.md §10).

:class:`Sphere`, :class:`Capsule` and :class:`Box` are settings (frozen dataclasses, metres, world frame):
given as ``ControllerConfig(obstacles=[...])``, ``[[obstacles]]`` tables in a TOML file (``type = "box"``,
the fields below; a box's orientation as ``rotation`` rows or ``rpy_deg``) or a scenario file, and moved
between ticks with :meth:`qpnso.Controller.set_obstacles`.  :func:`obstacle_arrays` lays them out as the
arrays the control tick's kernels read (:mod:`qpnso.model.distance`'s ``segment_obstacle``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import ClassVar

import numpy as np
import pinocchio as pin

from qpnso.model.distance import BOX, CAPSULE, SPHERE
from qpnso.settings import SettingError, check, from_dict, out_of_range, show

Vec3 = tuple[float, float, float]
Rows3 = tuple[Vec3, Vec3, Vec3]

ROTATION_TOL = 1e-6
"""A box's ``rotation`` is accepted when ``RᵀR`` is within this of the identity and ``det R`` of 1."""


@dataclass(frozen=True)
class Obstacle:
    """A keep-out volume (world frame, m).  :meth:`from_dict` builds the subclass a table's ``type`` names."""

    kind: ClassVar[int]
    type_name: ClassVar[str]

    @classmethod
    def from_dict(cls, values: object, where: str = "") -> "Obstacle":
        """The obstacle of a table ``{type = "sphere" | "capsule" | "box", ...}`` (the class's fields)."""
        if not isinstance(values, Mapping):
            raise SettingError(where or "obstacle", "", "expected a table with a type", show(values))
        kinds = {k.type_name: k for k in (Sphere, Capsule, Box)}
        name = values.get("type")
        if name not in kinds:
            raise SettingError(where or "obstacle", "type", f"must be one of {', '.join(kinds)}", show(name))
        rest = {k: v for k, v in values.items() if k != "type"}
        return from_dict(kinds[name], rest, where or kinds[name].__name__)

    def __post_init__(self) -> None:
        """Types (:func:`qpnso.settings.check`), then a radius, where the shape has one, > 0 m."""
        check(self)
        if not getattr(self, "radius", 1.0) > 0:
            raise out_of_range(self, "radius", "must be > 0 m")

    def to_dict(self) -> dict:
        """Plain data, ``type`` first, fields that are None left out (a TOML table): :meth:`from_dict` of it gives
        an equal obstacle."""
        return {"type": self.type_name} | {k: v for k, v in asdict(self).items() if v is not None}

    def arrays(self) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
        """``(kind, center, second, R, half, radius)`` as :func:`qpnso.model.distance.segment_obstacle` reads
        them (m; ``R`` world ← obstacle)."""
        raise NotImplementedError


@dataclass(frozen=True)
class Sphere(Obstacle):
    """A ball: ``center`` (m, world), ``radius`` (m, > 0)."""

    center: Vec3
    radius: float
    kind: ClassVar[int] = SPHERE
    type_name: ClassVar[str] = "sphere"

    def arrays(self):
        c = np.array(self.center)
        return self.kind, c, c, np.eye(3), np.zeros(3), self.radius


@dataclass(frozen=True)
class Capsule(Obstacle):
    """The points within ``radius`` (m, > 0) of the segment ``a``–``b`` (m, world): a rod, an arm of a stand."""

    a: Vec3
    b: Vec3
    radius: float
    kind: ClassVar[int] = CAPSULE
    type_name: ClassVar[str] = "capsule"

    def arrays(self):
        return self.kind, np.array(self.a), np.array(self.b), np.eye(3), np.zeros(3), self.radius


@dataclass(frozen=True)
class Box(Obstacle):
    """An oriented box: ``center`` (m, world), ``half_extents`` (m, > 0, along its own axes) and its
    orientation, world ← box: ``rotation`` (3×3 rows) or ``rpy_deg`` (roll, pitch, yaw about the fixed world
    x, y, z axes, degrees, as ``pinocchio.rpy.rpyToMatrix``); neither: aligned with the world."""

    center: Vec3
    half_extents: Vec3
    rotation: Rows3 | None = None
    rpy_deg: Vec3 | None = None
    kind: ClassVar[int] = BOX
    type_name: ClassVar[str] = "box"

    def __post_init__(self) -> None:
        super().__post_init__()
        if not min(self.half_extents) > 0:
            raise out_of_range(self, "half_extents", "must be > 0 m each")
        if self.rotation is not None and self.rpy_deg is not None:
            raise SettingError("Box", "rotation", "give rotation or rpy_deg, not both")
        if self.rotation is not None:
            R = np.array(self.rotation)
            if np.abs(R.T @ R - np.eye(3)).max() > ROTATION_TOL or abs(np.linalg.det(R) - 1.0) > ROTATION_TOL:
                raise out_of_range(self, "rotation", "must be a rotation matrix (orthonormal, det 1)")

    @property
    def matrix(self) -> np.ndarray:
        """World ← box rotation (3, 3)."""
        if self.rotation is not None:
            return np.array(self.rotation)
        if self.rpy_deg is not None:
            return pin.rpy.rpyToMatrix(*np.radians(self.rpy_deg))
        return np.eye(3)

    def arrays(self):
        c = np.array(self.center)
        return self.kind, c, c, self.matrix, np.array(self.half_extents), 0.0


def as_obstacles(values: object, where: str = "obstacles") -> tuple[Obstacle, ...]:
    """``values`` (obstacles or their tables, a list) as a tuple of :class:`Obstacle`; a
    :class:`~qpnso.settings.SettingError` names the entry that is not one."""
    if isinstance(values, (Obstacle, Mapping)) or not isinstance(values, Sequence):
        raise SettingError(
            where, "", "expected a list of obstacles (Sphere, Capsule, Box or their tables)", show(values)
        )
    out = []
    for i, item in enumerate(values):
        if isinstance(item, Obstacle):
            out.append(item)
        elif isinstance(item, Mapping):
            try:
                out.append(Obstacle.from_dict(item))
            except SettingError as exc:
                raise exc.within(f"{where}[{i}]", where.split(".")[0]) from None
        else:
            raise SettingError(where, f"[{i}]", "expected a Sphere, Capsule or Box (or its table)", show(item))
    return tuple(out)


def obstacle_arrays(obstacles: Sequence[Obstacle], room: int) -> dict[str, np.ndarray]:
    """The obstacles as arrays with room for ``room`` of them: ``ob_kind`` (room,), ``ob_center``,
    ``ob_second``, ``ob_half`` (room, 3), ``ob_R`` (room, 3, 3), ``ob_radius`` (room,); the unused entries zero."""
    if len(obstacles) > room:
        raise SettingError("obstacles", "", f"at most {room} obstacles (this controller's room); got {len(obstacles)}")
    out = {
        "ob_kind": np.zeros(room),
        "ob_center": np.zeros((room, 3)),
        "ob_second": np.zeros((room, 3)),
        "ob_R": np.zeros((room, 3, 3)),
        "ob_half": np.zeros((room, 3)),
        "ob_radius": np.zeros(room),
    }
    for i, ob in enumerate(obstacles):
        kind, center, second, R, half, radius = ob.arrays()
        out["ob_kind"][i], out["ob_center"][i], out["ob_second"][i] = kind, center, second
        out["ob_R"][i], out["ob_half"][i], out["ob_radius"][i] = R, half, radius
    return out
