"""The arm's collision geometry: a capsule per link (docs/method.md §10).

From the URDF's collision elements when it has them and every one is a capsule, cylinder (the capsule around
it) or sphere (a capsule of length 0), each held by its link's joint.  Otherwise — the shipped URDFs have no
collision elements, the Panda's are meshes — fitted to the joint centres: the *chain points* are the base
origin, the origin of every joint (on its axis) and the tool frame; consecutive points make a segment, rigid
in the link between them; segments that stay collinear in every configuration (a joint turning about the
segment itself: the LWR4+'s upper arm holds joints 2–4) are merged and zero-length ones dropped.  Each fitted
capsule's radius is the largest of its links' radii in ``models/collision.json`` (their source there and in
``models/README.md``).

The control tick reads the chain points and their Jacobians from its state (:mod:`qpnso.control.state`)
and the capsules from its params (:mod:`qpnso.control.params`); :func:`geometry_model` gives the same
capsules as a Pinocchio ``GeometryModel`` of coal shapes, and :func:`clearances` coal's distances through it
(an independent computation: tests, the simulation's recorded clearance).
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

    ``anchors``: each chain point as ``(joint, point in that joint's frame, m)`` (joint 0: the world);
    ``a``, ``b``: each capsule's chain points (indices into ``anchors``); ``radius`` (m) each; ``names``: the
    links each covers (``"link_2-link_3"``), or the URDF's collision element; ``source``: ``"fitted"`` (joint
    centres, ``models/collision.json``) or ``"urdf"`` (the URDF's collision elements)."""

    anchors: tuple[tuple[int, tuple[float, float, float]], ...]
    a: tuple[int, ...]
    b: tuple[int, ...]
    radius: tuple[float, ...]
    names: tuple[str, ...]
    source: str = "fitted"

    @property
    def count(self) -> int:
        return len(self.a)

    @property
    def points_count(self) -> int:
        return len(self.anchors)

    def points(self, robot: Robot, q: np.ndarray) -> np.ndarray:
        """The chain points (k, 3) at ``q`` (rad), m, world (Pinocchio's forward kinematics)."""
        pin.forwardKinematics(robot.model, robot.data, q)
        return np.array([robot.data.oMi[j].act(np.array(local)) for j, local in self.anchors])

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
    """Whether ``robot`` has capsules: collision primitives in its URDF or link radii in
    ``models/collision.json`` (else :func:`link_capsules` raises)."""
    return robot.name in load_radii() or bool(_urdf_elements(robot))


def link_capsules(robot: Robot) -> LinkCapsules:
    """The capsules of ``robot`` (module docstring; cached per robot).  Raises ModelError when
    ``models/collision.json`` has no radii for it."""
    return _cached(robot)


def _build(robot: Robot) -> LinkCapsules:
    elements = _urdf_elements(robot)
    return _from_urdf(elements) if elements else _fitted(robot)


PRIMITIVES = ("Capsule", "Cylinder", "Sphere")
"""coal shapes of a URDF's collision elements that are capsules (a cylinder: the capsule around it)."""


@functools.lru_cache(maxsize=16)
def _urdf_elements(robot: Robot) -> tuple:
    """The collision elements of ``robot``'s URDF (Pinocchio's ``GeometryModel``) when every one is a capsule,
    cylinder or sphere; else (none, a mesh, a box, no URDF file) none: the capsules are fitted.  Read once per
    robot (:func:`has_capsules` and :func:`link_capsules` both ask)."""
    path = Path(robot.source)
    if not path.is_file():
        return ()
    try:
        geom = pin.buildGeomFromUrdf(robot.model, str(path), pin.GeometryType.COLLISION)
    except (RuntimeError, ValueError):  # (a mesh Pinocchio cannot find, say)
        return ()
    objects = tuple(geom.geometryObjects)
    return objects if objects and all(type(o.geometry).__name__ in PRIMITIVES for o in objects) else ()


def _from_urdf(objects: tuple) -> LinkCapsules:
    """Capsules of the URDF's collision elements: a capsule or cylinder along its local z axis (its half length
    each way), a sphere a capsule of length 0, each held by the element's joint."""
    anchors, a, b, radius, names = [], [], [], [], []
    for o in objects:
        g, M = o.geometry, o.placement
        half = float(getattr(g, "halfLength", 0.0))
        for end in (-half, half):
            anchors.append((int(o.parentJoint), _vec3(M.act(np.array([0.0, 0.0, end])))))
        a.append(len(anchors) - 2)
        b.append(len(anchors) - 1)
        radius.append(float(g.radius))
        names.append(o.name)
    return LinkCapsules(tuple(anchors), tuple(a), tuple(b), tuple(radius), tuple(names), "urdf")


def _fitted(robot: Robot) -> LinkCapsules:
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
        anchors=tuple(_anchor(robot, chain[k][0]) for k in used),
        a=tuple(index[k] for k in a),
        b=tuple(index[k] for k in b),
        radius=tuple(radius),
        names=tuple(names),
    )


def _anchor(robot: Robot, frame: int) -> tuple[int, tuple[float, float, float]]:
    """A frame's origin as ``(joint, point in the joint's frame)``."""
    f = robot.model.frames[frame]
    return int(f.parentJoint), _vec3(f.placement.translation)


def _vec3(v: np.ndarray) -> tuple[float, float, float]:
    """A 3-vector as three floats."""
    return float(v[0]), float(v[1]), float(v[2])


def point_expressions(sym, capsules: LinkCapsules) -> tuple[ca.SX, ca.SX]:
    """The chain points (k·3,) and their Jacobian ∂p/∂q (k·3, n), CasADi over ``sym.q``
    (:class:`qpnso.model.symbolic.SymbolicModel`), points stacked in order, x, y, z each."""
    points = ca.vertcat(*[sym.oMi[j].point(np.array(local)) for j, local in capsules.anchors])
    return points, ca.jacobian(points, sym.q)


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
        joint = capsules.anchors[capsules.a[k]][0]  # (every point of a capsule is held by its first end's joint)
        world = pin.SE3(_z_to(b - a), 0.5 * (a + b))
        placement = robot.data.oMi[joint].inverse() * world
        shape = coal.Capsule(capsules.radius[k], float(np.linalg.norm(b - a)))
        geom.addGeometryObject(pin.GeometryObject(capsules.names[k], joint, placement, shape))
    return geom


def _z_to(d: np.ndarray) -> np.ndarray:
    """A rotation taking the z axis to the direction of ``d`` (the identity for ``d`` = 0: a sphere)."""
    if np.linalg.norm(d) < 1e-12:
        return np.eye(3)
    return pin.Quaternion.FromTwoVectors(np.array([0.0, 0.0, 1.0]), d).matrix()


@functools.lru_cache(maxsize=16)
def _shared_geometry(robot: Robot) -> pin.GeometryModel:
    """:func:`geometry_model` of ``robot``, built once (:func:`clearances` only reads it)."""
    return geometry_model(robot)


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

    geom = geom or _shared_geometry(robot)
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
