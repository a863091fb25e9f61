"""The arm's collision geometry: a capsule per link, fitted to the joint centres (docs/method.md §10).

The shipped URDFs have no collision elements, and the Panda's are meshes; every arm therefore gets the
capsules of its kinematic chain: the *chain points* are the base origin, the origin of every joint (on its
axis) and the tool frame; consecutive points make a segment, rigid in the link between them; segments that
stay collinear in every configuration (a joint turning about the segment itself: the LWR4+'s upper arm
holds joints 2–4) are merged and zero-length ones dropped.  Each capsule's radius is the largest of its
links' radii in ``models/collision.json`` (their source there and in ``models/README.md``).

The control tick reads the chain points and their Jacobians from its state (:mod:`qpnso.control.state`)
and the capsules from its params (:mod:`qpnso.control.params`); :func:`geometry_model` gives the same
capsules as a Pinocchio ``GeometryModel`` of coal shapes (an independent distance computation, tests).
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np
import pinocchio as pin

from qpnso.errors import ModelError
from qpnso.model.distance import CAPSULE, SPHERE
from qpnso.model.robot import MODELS_DIR, Robot

COLLINEAR_TOL = 1e-9
"""m: a chain point this close to the line of its neighbours in every sampled configuration merges their
segments."""


@dataclass(frozen=True)
class LinkCapsules:
    """The capsules of an arm (module docstring).

    ``frames``: the Pinocchio frame of each chain point (its origin is the point; frame 0, the universe, is the
    base origin); ``a``, ``b``: each capsule's chain points (indices into ``frames``); ``radius`` (m) each;
    ``names``: the links each covers (``"link_2-link_3"``)."""

    frames: tuple[int, ...]
    a: tuple[int, ...]
    b: tuple[int, ...]
    radius: tuple[float, ...]
    names: tuple[str, ...]

    @property
    def count(self) -> int:
        return len(self.a)

    @property
    def points_count(self) -> int:
        return len(self.frames)

    def points(self, robot: Robot, q: np.ndarray) -> np.ndarray:
        """The chain points (k, 3) at ``q`` (rad), m, world (Pinocchio's forward kinematics)."""
        pin.framesForwardKinematics(robot.model, robot.data, q)
        return np.array([robot.data.oMf[f].translation for f in self.frames])

    def segments(self, robot: Robot, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The capsules' axes at ``q``: ends ``(a, b)``, (count, 3) each, m, world."""
        p = self.points(robot, q)
        return p[list(self.a)], p[list(self.b)]


def load_radii(path: Path | None = None) -> dict:
    """``models/collision.json``: per robot, the link radii (m) by link name."""
    return json.loads((path or MODELS_DIR / "collision.json").read_text())


def _chain_frames(robot: Robot) -> list[tuple[int, str]]:
    """The chain points as ``(frame id, link)``: the base origin, every joint's origin (the joint's own frame)
    and the tool frame; ``link`` the link that begins at the point."""
    model = robot.model
    frames = [(0, "base")]
    for j in range(1, model.njoints):
        fid = next(i for i, f in enumerate(model.frames) if f.parentJoint == j and f.type == pin.FrameType.JOINT)
        frames.append((fid, _child_link(model, j)))
    frames.append((robot.tool_frame_id, "tool"))
    return frames


def _child_link(model: pin.Model, j: int) -> str:
    """The body that joint ``j`` moves (its first BODY frame)."""
    return next((f.name for f in model.frames if f.parentJoint == j and f.type == pin.FrameType.BODY), f"joint{j}")


def _collinear(p: np.ndarray, q: np.ndarray, r: np.ndarray) -> bool:
    """Whether ``q`` lies on the segment ``p``–``r`` (to :data:`COLLINEAR_TOL`)."""
    d = r - p
    L = float(d @ d)
    if L < COLLINEAR_TOL**2:
        return bool(np.linalg.norm(q - p) < COLLINEAR_TOL)
    t = float((q - p) @ d) / L
    return -1e-9 <= t <= 1 + 1e-9 and bool(np.linalg.norm(p + t * d - q) < COLLINEAR_TOL)


@functools.lru_cache(maxsize=16)
def _cached(robot: Robot) -> LinkCapsules:
    return _build(robot)


def has_capsules(robot: Robot) -> bool:
    """Whether ``models/collision.json`` has link radii for ``robot`` (else :func:`link_capsules` raises)."""
    return robot.name in load_radii()


def link_capsules(robot: Robot) -> LinkCapsules:
    """The capsules of ``robot`` (module docstring; cached per robot).  Raises ModelError when
    ``models/collision.json`` has no radii for it."""
    return _cached(robot)


def _build(robot: Robot) -> LinkCapsules:
    table = load_radii()
    if robot.name not in table:
        raise ModelError(f"{robot.name}: no link radii in models/collision.json (needed for obstacles)")
    radii = table[robot.name]["radius_m"]
    chain = _chain_frames(robot)
    rng = np.random.default_rng(0)
    qs = [rng.uniform(robot.q_min, robot.q_max) for _ in range(8)]
    pts = []
    for q in qs:
        pin.framesForwardKinematics(robot.model, robot.data, q)
        pts.append(np.array([robot.data.oMf[f].translation for f, _ in chain]))
    keep = [0]  # chain points that start or end a capsule
    for i in range(1, len(chain) - 1):
        if not all(_collinear(p[keep[-1]], p[i], p[i + 1]) for p in pts):
            keep.append(i)
    keep.append(len(chain) - 1)
    a, b, radius, names = [], [], [], []
    for i, j in zip(keep[:-1], keep[1:]):
        if all(np.linalg.norm(p[i] - p[j]) < COLLINEAR_TOL for p in pts):
            continue
        links = [chain[k][1] for k in range(i, j)]
        missing = [name for name in links if name not in radii]
        if missing:
            raise ModelError(f"{robot.name}: models/collision.json has no radius for {', '.join(missing)}")
        a.append(i)
        b.append(j)
        radius.append(max(float(radii[name]) for name in links))
        names.append(links[0] if len(links) == 1 else f"{links[0]}-{links[-1]}")
    used = sorted(set(a) | set(b))
    index = {k: n for n, k in enumerate(used)}
    return LinkCapsules(
        frames=tuple(chain[k][0] for k in used),
        a=tuple(index[k] for k in a),
        b=tuple(index[k] for k in b),
        radius=tuple(radius),
        names=tuple(names),
    )


def point_expressions(sym, capsules: LinkCapsules) -> tuple[ca.SX, ca.SX]:
    """The chain points (k·3,) and their Jacobian ∂p/∂q (k·3, n), CasADi over ``sym.q``
    (:class:`qpnso.model.symbolic.SymbolicModel`), points stacked in order, x, y, z each."""
    points = ca.vertcat(*[sym.frame_placement(f).p if f else ca.SX.zeros(3) for f in capsules.frames])
    return points, ca.jacobian(points, sym.q)


def _holding_joint(robot: Robot, frame: int) -> int:
    """The joint whose link holds a capsule that starts at chain point ``frame`` (a joint's origin, or the base):
    that joint (every point of a merged capsule lies on the axes of the joints after it)."""
    return robot.model.frames[frame].parentJoint


def geometry_model(robot: Robot, capsules: LinkCapsules | None = None) -> pin.GeometryModel:
    """The capsules as a Pinocchio ``GeometryModel`` of coal capsules, each attached to the joint whose link
    holds its segment (placed from the neutral configuration), for Pinocchio's ``updateGeometryPlacements``."""
    import coal

    capsules = capsules or link_capsules(robot)
    q0 = pin.neutral(robot.model)
    p = capsules.points(robot, q0)
    pin.forwardKinematics(robot.model, robot.data, q0)
    geom = pin.GeometryModel()
    for k in range(capsules.count):
        a, b = p[capsules.a[k]], p[capsules.b[k]]
        joint = _holding_joint(robot, capsules.frames[capsules.a[k]])
        world = pin.SE3(_z_to(b - a), 0.5 * (a + b))
        placement = robot.data.oMi[joint].inverse() * world
        shape = coal.Capsule(capsules.radius[k], float(np.linalg.norm(b - a)))
        geom.addGeometryObject(pin.GeometryObject(capsules.names[k], joint, placement, shape))
    return geom


def _z_to(d: np.ndarray) -> np.ndarray:
    """A rotation taking the z axis to the direction of ``d``."""
    z = d / np.linalg.norm(d)
    x = np.cross([0.0, 1.0, 0.0] if abs(z[1]) < 0.9 else [1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def coal_shape(obstacle) -> tuple[object, pin.SE3]:
    """A :mod:`qpnso.model.obstacles` obstacle as a coal shape and its world placement."""
    import coal

    kind, center, second, R, half, radius = obstacle.arrays()
    if kind == SPHERE:
        return coal.Sphere(radius), pin.SE3(np.eye(3), center)
    if kind == CAPSULE:
        d = second - center
        return coal.Capsule(radius, float(np.linalg.norm(d))), pin.SE3(_z_to(d), 0.5 * (center + second))
    return coal.Box(*(2.0 * half)), pin.SE3(R, center)


def clearances(robot: Robot, q: np.ndarray, obstacles, geom: pin.GeometryModel | None = None) -> np.ndarray:
    """The distance (m) between every link capsule and every obstacle at ``q`` (rad), (capsules, obstacles),
    through Pinocchio's ``GeometryModel`` and coal (GJK; negative: penetration depth where coal gives one).
    An independent check of the control tick's own distances (:mod:`qpnso.model.distance`)."""
    import coal

    geom = geom or geometry_model(robot)
    gdata = pin.GeometryData(geom)
    pin.updateGeometryPlacements(robot.model, robot.data, geom, gdata, np.asarray(q, dtype=float))
    shapes = [coal_shape(ob) for ob in obstacles]
    out = np.empty((len(geom.geometryObjects), len(shapes)))
    req = coal.DistanceRequest()
    for k, obj in enumerate(geom.geometryObjects):
        T = coal.Transform3s(gdata.oMg[k].rotation, gdata.oMg[k].translation)
        for j, (shape, M) in enumerate(shapes):
            res = coal.DistanceResult()
            out[k, j] = coal.distance(obj.geometry, T, shape, coal.Transform3s(M.rotation, M.translation), req, res)
    return out
