"""Keep-out volumes of the operating room: the equipment around the patient as world-frame primitives
(docs/method.md §10).

:class:`Sphere`, :class:`Capsule` and :class:`Box` are settings (frozen dataclasses, metres, world frame):
given as ``ControllerConfig(obstacles=[...])``, ``[[obstacles]]`` tables in a TOML file (``type = "box"``,
the fields below; a box's orientation as ``rotation`` rows or ``rpy_deg``) or a scenario file, and moved
between ticks with :meth:`qpnso.Controller.set_obstacles`.  :func:`obstacle_arrays` lays them out as the
arrays the control tick's kernels read (:mod:`qpnso.model.distance`'s ``segment_obstacle``).

A moving volume's velocity (world frame) is that of its :attr:`Obstacle.centre` (m/s) and its angular
velocity about it (rad/s): given by the user (:func:`checked_velocities`) or estimated from two placements
(:func:`placement_velocity`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import ClassVar

import numpy as np
import pinocchio as pin

from qpnso.errors import InputError
from qpnso.model.distance import BOX, CAPSULE, SPHERE
from qpnso.settings import SettingError, check, from_dict, out_of_range, show

Vec3 = tuple[float, float, float]
Rows3 = tuple[Vec3, Vec3, Vec3]

ROTATION_TOL = 1e-6
"""A box's ``rotation`` is accepted when ``RᵀR`` is within this of the identity and ``det R`` of 1."""

PLACEMENT_JUMP_SPEED = 2.0
"""m/s: two placements of a volume whose farthest-moving point (a sphere's centre, a capsule's end, a box's
corner) would have moved faster than this are a re-placement, not a motion: no velocity is estimated from them
(an assumption: equipment, and a hand, in an operating room move slower; a faster volume's velocity can be
given)."""


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

    @property
    def centre(self) -> np.ndarray:
        """The point (m, world) whose velocity is the volume's and about which it turns: the midpoint of
        :meth:`arrays`' ``center`` and ``second`` (a sphere's or box's centre, a capsule's midpoint)."""
        _, center, second, _, _, _ = self.arrays()
        return 0.5 * (center + second)

    def corners(self) -> np.ndarray:
        """(k, 3) points (m, world), always the same ones in the same order, whose motion bounds every point's
        (a sphere's centre, a capsule's ends, a box's corners): :func:`placement_velocity`'s jump test."""
        _, center, second, _, _, _ = self.arrays()
        return np.stack([center, second])

    def turn_to(self, after: "Obstacle") -> np.ndarray:
        """The rotation (3,) rad, world frame (axis × angle), that turns this volume into its placement
        ``after`` (same kind), as far as the shape shows one (:func:`placement_velocity`): none for a sphere."""
        return np.zeros(3)


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

    def turn_to(self, after):
        """The least rotation of the axis ``b − a`` onto ``after``'s (a turn about the axis itself moves none of
        the capsule's points and is not seen); none when either has no length."""
        u, v = (np.array(c.b, dtype=float) - np.array(c.a, dtype=float) for c in (self, after))
        if not (np.linalg.norm(u) > 0 and np.linalg.norm(v) > 0):
            return np.zeros(3)
        return pin.log3(pin.Quaternion.FromTwoVectors(u, v).toRotationMatrix())


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

    def corners(self):
        signs = np.array([[i, j, k] for i in (-1.0, 1.0) for j in (-1.0, 1.0) for k in (-1.0, 1.0)])
        return np.array(self.center) + (signs * np.array(self.half_extents)) @ self.matrix.T

    def turn_to(self, after):
        return pin.log3(after.matrix @ self.matrix.T)


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


def placement_velocity(before: Obstacle, after: Obstacle, seconds: float) -> np.ndarray:
    """The velocity (6,) of a volume placed at ``before`` then, ``seconds`` (s, > 0) later, at ``after``, taken
    as a rigid motion: its :attr:`~Obstacle.centre`'s displacement over ``seconds`` (m/s, world), then the
    angular velocity: its turn (:meth:`Obstacle.turn_to`; a box's ``log₃(R_after R_beforeᵀ)``) over ``seconds``
    (rad/s, world).  Zero when they are not the same kind of volume, or when a point of it
    (:meth:`Obstacle.corners`) would have moved faster than :data:`PLACEMENT_JUMP_SPEED` (a re-placement)."""
    out = np.zeros(6)
    if type(before) is not type(after) or not seconds > 0:
        return out
    if np.linalg.norm(after.corners() - before.corners(), axis=1).max() > PLACEMENT_JUMP_SPEED * seconds:
        return out
    out[:3] = (after.centre - before.centre) / seconds
    out[3:] = before.turn_to(after) / seconds
    return out


def checked_velocities(values: object, count: int) -> list[np.ndarray | None]:
    """The velocities given for ``count`` volumes (``Controller.set_obstacles(velocities=...)``): one entry per
    volume, each None (estimated: :func:`placement_velocity`), 3 numbers (its centre's velocity, m/s, world;
    not turning) or 6 (then its angular velocity about its centre, rad/s, world), finite; as (6,) arrays or
    None.  :class:`~qpnso.errors.InputError` naming the entry that is not."""
    if isinstance(values, (str, bytes, Mapping)) or not isinstance(values, (Sequence, np.ndarray)):
        raise InputError(
            f"velocities must be a list with one entry per obstacle (None or 3 or 6 numbers), got {show(values)}"
        )
    if len(values) != count:
        raise InputError(f"velocities has {len(values)} entries for {count} obstacles: give one per obstacle")
    out: list[np.ndarray | None] = []
    for i, value in enumerate(values):
        if value is None:
            out.append(None)
            continue
        try:
            v = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            v = np.full(0, np.nan)
        if v.shape not in ((3,), (6,)) or not np.all(np.isfinite(v)):
            raise InputError(
                f"velocities[{i}] must be None, 3 finite numbers (m/s, world) or 6 (m/s then rad/s), got {show(value)}"
            )
        out.append(np.concatenate([v, np.zeros(6 - v.size)]))
    return out
