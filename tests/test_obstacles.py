"""Keep-out volumes (docs/method.md §10): the obstacle settings, the link capsules against Pinocchio and coal,
the chain points and their Jacobians in the tick's state, the keep-out rows' exact gradient against finite
differences of coal's distance, and in closed loop over 10⁴ ticks (tool held and moving, a posture pulling
the elbow into an obstacle): no link capsule ever enters an obstacle — checked by sampling the capsules'
axes against each primitive in NumPy, independently of coal and of the controller's kernels — while the same
runs with the obstacle unknown to the controller go through it."""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest

import qpnso
from qpnso.control.config import ControllerConfig, Status
from qpnso.control.controller import Controller
from qpnso.control.rows.obstacles import EXIT_SPEED
from qpnso.elbow.arm_angle import arm_angle
from qpnso.elbow.clearance import keep_out_record, least_clearance
from qpnso.elbow.srs import branch, ik
from qpnso.model.collision import clearances, link_capsules
from qpnso.model.obstacles import Box, Capsule, Sphere
from qpnso.settings import SettingError

DT = 1e-3


@pytest.fixture(scope="module")
def robot() -> qpnso.Robot:
    return qpnso.load_robot("lwr4p")


@pytest.fixture(scope="module")
def caps(robot):
    return link_capsules(robot)


# ------------------------------------------------------------------ settings
def test_obstacles_are_checked_settings() -> None:
    with pytest.raises(SettingError, match="radius"):
        Sphere((0, 0, 1), -0.1)
    with pytest.raises(SettingError, match="half_extents"):
        Box((0, 0, 1), (0.1, 0.0, 0.1))
    with pytest.raises(SettingError, match="rotation"):
        Box((0, 0, 1), (0.1, 0.1, 0.1), rotation=((1, 0, 0), (0, 1, 0), (0, 0, -1)))
    with pytest.raises(SettingError, match="center"):
        Sphere((0, 0), 0.1)
    with pytest.raises(SettingError, match=r"obstacles\[1\]\.type"):
        ControllerConfig.from_dict(
            {"obstacles": [{"type": "sphere", "center": [0, 0, 1], "radius": 0.1}, {"type": "cube"}]}
        )
    with pytest.raises(SettingError, match="obstacle_margin"):
        ControllerConfig(obstacle_margin=0.2, obstacle_influence=0.1)


def test_a_box_s_rpy_is_pinocchio_s() -> None:
    rpy = (10.0, -25.0, 70.0)
    box = Box((0, 0, 0), (0.1, 0.2, 0.3), rpy_deg=rpy)
    np.testing.assert_allclose(box.matrix, pin.rpy.rpyToMatrix(*np.radians(rpy)), atol=1e-15)
    same = Box((0, 0, 0), (0.1, 0.2, 0.3), rotation=tuple(map(tuple, box.matrix)))
    np.testing.assert_allclose(same.matrix, box.matrix, atol=1e-15)


def test_obstacles_round_trip_through_toml_tables() -> None:
    config = ControllerConfig(
        obstacles=[Sphere((0.1, 0.2, 0.3), 0.05), Capsule((0, 0, 0), (0, 0, 1), 0.02), Box((1, 0, 0), (0.1, 0.1, 0.1))]
    )
    assert ControllerConfig.from_dict(config.to_dict()) == config
    assert config.to_dict()["obstacles"][2] == {"type": "box", "center": (1.0, 0.0, 0.0), "half_extents": (0.1,) * 3}


# ------------------------------------------------------------------ capsules
def test_the_capsules_follow_the_chain_and_are_rigid(robot, caps) -> None:
    """Every capsule's axis joins two chain points (Pinocchio frame origins) and keeps its length in every
    configuration (one link holds it); together they run from the base to the tool."""
    rng = np.random.default_rng(1)
    lengths = None
    for _ in range(20):
        q = robot.random_q(rng)
        a, b = caps.segments(robot, q)
        L = np.linalg.norm(b - a, axis=1)
        lengths = L if lengths is None else lengths
        np.testing.assert_allclose(L, lengths, atol=1e-12)
        np.testing.assert_allclose(a[0], 0.0, atol=1e-15)
        np.testing.assert_allclose(b[-1], robot.tool_pose(q).translation, atol=1e-12)
        np.testing.assert_allclose(a[1:], b[:-1], atol=1e-15)  # (a chain: each starts where the last ends)
    assert caps.names == ("base-link_1", "link_2-link_3", "link_4-link_5", "link_6-link_7")


def random_obstacle(rng, near: np.ndarray):
    kind = rng.integers(3)
    c = near + rng.normal(scale=0.15, size=3)
    if kind == 0:
        return Sphere(tuple(c), float(rng.uniform(0.02, 0.1)))
    if kind == 1:
        return Capsule(tuple(c), tuple(c + rng.normal(scale=0.2, size=3)), float(rng.uniform(0.02, 0.06)))
    R = pin.rpy.rpyToMatrix(*rng.uniform(-np.pi, np.pi, 3))
    return Box(tuple(c), tuple(rng.uniform(0.02, 0.15, 3)), rotation=tuple(map(tuple, R)))


def test_the_kernels_distances_are_coal_s(robot, caps) -> None:
    """The tick's least capsule–obstacle distance (its kernels on the chain points, through the entry the
    intervals use: no kernel compiled for the test alone) against coal on Pinocchio's ``GeometryModel`` of the
    same capsules, each obstacle alone, where they do not overlap; per capsule the rows' test checks them."""
    rng = np.random.default_rng(2)
    compared = 0
    for _ in range(60):
        q = robot.random_q(rng)
        points = caps.points(robot, q)
        for obstacle in (random_obstacle(rng, points[2]) for _ in range(4)):
            G = keep_out_record(robot, caps, 8, [obstacle])[0]
            reference = clearances(robot, q, [obstacle])[:, 0]
            d, c, o = least_clearance(G, points, False)
            if reference.min() > 1e-6:
                assert d == pytest.approx(reference.min(), abs=1e-8) and o == 0
                assert reference[c] == pytest.approx(reference.min(), abs=1e-8)  # (its pair: ties at the elbow)
                compared += 1
            else:
                assert d <= 1e-8
    assert compared > 100


# --------------------------------------------------------------------- state
def test_the_state_holds_the_chain_points_and_their_jacobians(robot, caps) -> None:
    ctrl = Controller(robot, ControllerConfig())
    rng = np.random.default_rng(3)
    for _ in range(5):
        q = robot.random_q(rng)
        s = ctrl.evaluate.record(q, np.zeros(7), np.zeros(6), np.zeros(6))[0]
        np.testing.assert_allclose(s["points"], caps.points(robot, q), atol=1e-14)
        h = 1e-6
        fd = np.stack(
            [(caps.points(robot, q + h * e) - caps.points(robot, q - h * e)) / (2 * h) for e in np.eye(7)], axis=-1
        )
        np.testing.assert_allclose(s["points_J"], fd, atol=1e-8)


# ---------------------------------------------------------------------- rows
def test_a_keep_out_row_is_the_distance_s_exact_gradient(robot, caps) -> None:
    """Each keep-out row is ``scale·∇d`` with lower bound ``scale·damper(d)``: ∇d against central differences
    of coal's distance, d against coal's."""
    rng = np.random.default_rng(4)
    checked = 0
    for _ in range(6):
        q = robot.random_q(rng, margin=0.3)
        points = caps.points(robot, q)
        obstacle = Sphere(tuple(points[2] + rng.normal(scale=0.05, size=3) + [0.0, 0.0, 0.0]), 0.03)
        d0 = clearances(robot, q, [obstacle])[:, 0]
        if d0.min() < 0.04 or d0.min() > 0.14:
            obstacle = Sphere(tuple(points[2] + 0.2 * _unit(rng)), 0.05)
            d0 = clearances(robot, q, [obstacle])[:, 0]
        ctrl = Controller(robot, ControllerConfig(strategy="damped", obstacles=[obstacle]))
        ctrl.reset(q)
        ctrl.step(q)
        r, pb, G = ctrl.records.report[0], ctrl.records.problem[0], ctrl.records.params[0]["geo"]
        assert r["clearance"] == pytest.approx(d0.min(), abs=1e-9)
        near = np.flatnonzero(d0 < ctrl.config.obstacle_influence)
        assert r["obstacle_rows"] == len(near)
        h = 1e-6
        for k, c in enumerate(near):
            fd = [
                (clearances(robot, q + h * e, [obstacle])[c, 0] - clearances(robot, q - h * e, [obstacle])[c, 0])
                / (2 * h)
                for e in np.eye(7)
            ]
            row = r["obstacle_first"] + k
            np.testing.assert_allclose(pb["soft_C"][row] / G["row_scale"], fd, atol=1e-6)
            gap = d0[c] - G["margin"]
            expected = min(-G["gain"] * gap, G["recovery_speed"])  # (within the margin: back at most this fast,
            if gap < 0:  # and at least EXIT_SPEED)
                expected = max(expected, min(EXIT_SPEED, G["recovery_speed"]))
            assert pb["soft_l"][row] / G["row_scale"] == pytest.approx(expected, abs=1e-9)
            checked += 1
    assert checked >= 6


def _unit(rng) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


# ------------------------------------------------------------- closed loop
def sampled_clearance(robot, caps, q: np.ndarray, obstacle) -> float:
    """The least distance (m) of the link capsules to ``obstacle`` at ``q``, from 401 points along each axis
    (Pinocchio's forward kinematics) against the primitive in NumPy: independent of coal and of the kernels
    (the sampling can only overstate it, by under 0.1 mm here)."""
    a, b = caps.segments(robot, q)
    x = a[:, None, :] + _T * (b - a)[:, None, :]  # (capsules, 401, 3)
    d = _point_distance(x.reshape(-1, 3), obstacle).reshape(len(a), -1).min(axis=1)
    return float(np.min(d - np.array(caps.radius)))


_T = np.linspace(0.0, 1.0, 401)[None, :, None]


def _point_distance(x: np.ndarray, ob) -> np.ndarray:
    """Distances (m) of the points ``x`` (N, 3) to the obstacle ``ob``, in NumPy."""
    if isinstance(ob, Sphere):
        return np.linalg.norm(x - np.array(ob.center), axis=1) - ob.radius
    if isinstance(ob, Capsule):
        a, b = np.array(ob.a), np.array(ob.b)
        s = np.clip((x - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
        return np.linalg.norm(x - (a + s[:, None] * (b - a)), axis=1) - ob.radius
    local = (x - np.array(ob.center)) @ _box_matrix(ob)
    outside = np.maximum(np.abs(local) - np.array(ob.half_extents), 0.0)
    return np.linalg.norm(outside, axis=1)


_MATRICES: dict = {}


def _box_matrix(box) -> np.ndarray:
    """``box.matrix``, once per box (it is built from the box's angles)."""
    return _MATRICES.setdefault(box, box.matrix)


def episode(robot, caps, rng, moving: bool):
    """A start, an arm angle 2–3 rad away along a self-motion within the joint limits (the elbow-up strategy
    pulls the elbow there at up to 1 rad/s: its target, deg) and an obstacle on the elbow's way, a third of the
    way (at least 5 cm from the start's links); the tool held or moving back and forth along a random
    ``direction`` (0 when held)."""
    while True:
        q0 = robot.random_q(rng, margin=0.35)
        try:
            ns0, b = arm_angle(robot, q0), branch(robot, q0)
        except qpnso.QpnsoError:
            continue
        delta = float(rng.choice([-1.0, 1.0]) * rng.uniform(2.0, 3.0))
        pose = robot.tool_pose(q0)
        mid = ik(robot, pose, ns0 + 0.35 * delta, b)
        way = ik(robot, pose, ns0 + delta * np.linspace(0.0, 1.0, 60), b)  # (the self-motion to the target:
        # within the limits, and continuous — no branch switch where joint 2 or 6 passes through 0)
        inside = np.all(way > robot.q_min + 0.05) and np.all(way < robot.q_max - 0.05)
        if not (inside and np.abs(np.diff(way, axis=0)).max() < 0.3):
            continue
        p = caps.points(robot, mid)
        centre = p[2]  # the elbow, a third of the way
        kind = rng.integers(3)
        size = 0.06
        if kind == 0:
            obstacle = Sphere(tuple(centre), size)
        elif kind == 1:
            axis = np.cross(p[2] - p[1], p[3] - p[1])
            axis = 0.1 * axis / np.linalg.norm(axis)
            obstacle = Capsule(tuple(centre - axis), tuple(centre + axis), size)
        else:
            obstacle = Box(tuple(centre), (size, size, size), rpy_deg=tuple(rng.uniform(-180, 180, 3)))
        if sampled_clearance(robot, caps, q0, obstacle) < 0.05:
            continue
        direction = _unit(rng) if moving else np.zeros(3)
        return q0, math.degrees(ns0 + delta), obstacle, direction


def closed_loop(ctrl: Controller, q0: np.ndarray, direction: np.ndarray, ticks: int):
    """``ticks`` ticks of ``ctrl`` from ``q0`` (reset there), the joints following the command: ``(q, cmd)``; the
    tool moving along ``direction`` at ``5·cos(2π·t/1 s)`` cm/s (±8 mm: the elbow's way stays near the obstacle)."""
    ctrl.reset(q0)
    q = q0.copy()
    twist = np.zeros(6)
    for k in range(ticks):
        twist[:3] = 0.05 * math.cos(2 * math.pi * k * DT) * direction
        cmd = ctrl.step(q, tool_twist=twist)
        q = q + DT * cmd.dq
        yield q, cmd


def test_no_link_enters_an_obstacle_over_ten_thousand_ticks(robot, caps) -> None:
    """Must hold: 1.5·10⁴ ticks (ten 1.5 s episodes, five with the tool held, five moving at up to 5 cm/s), elbow-up
    pulling the elbow through an obstacle on its way: no capsule ever overlaps it (NumPy sampling), the margin
    kept to 1 mm, ``OBSTACLE`` exactly on the ticks with a link inside the margin (if any); the same runs with the
    obstacle unknown to the controller go into it."""
    rng = np.random.default_rng(5)
    for i in range(10):
        q0, target_deg, obstacle, twist = episode(robot, caps, rng, moving=i >= 5)
        config = ControllerConfig(strategy="elbow-up", elbow_up_angle_deg=target_deg, obstacles=[obstacle])
        ctrl = Controller(robot, config)
        least, flagged, inside = math.inf, 0, 0
        for q, cmd in closed_loop(ctrl, q0, twist, 1500):
            least = min(least, sampled_clearance(robot, caps, q, obstacle))
            flagged += bool(cmd.status & Status.OBSTACLE)
            inside += cmd.clearance < config.obstacle_margin
        assert least >= 0.0, (i, least)
        assert least >= config.obstacle_margin - 1e-3, (i, least)
        assert flagged >= inside  # (every tick inside the margin; more where the acceleration bound let a link
        # approach faster than its row allows while the self-motion braked: the keep-out rows do not brake at ddq_max)
        ctrl.set_obstacles([])  # (the room still has it: measured, not known)
        blind = (sampled_clearance(robot, caps, q, obstacle) for q, _ in closed_loop(ctrl, q0, twist, 1500))
        assert any(d < 0.0 for d in blind), i  # (not vacuous: the pull goes into it)


def test_set_obstacles_moves_them_and_renews_the_interval(robot, caps) -> None:
    q = robot.sample_configuration()
    ctrl = Controller(robot, ControllerConfig())
    ctrl.reset(q)
    free = ctrl.step(q)
    assert free.clearance == math.inf
    p = caps.points(robot, ik(robot, robot.tool_pose(q), arm_angle(robot, q) + 0.8, branch(robot, q)))
    ctrl.set_obstacles([Sphere(tuple(p[2]), 0.03)])
    cmd = ctrl.step(q)
    assert cmd.clearance == pytest.approx(clearances(robot, q, ctrl.obstacles).min(), abs=1e-9)
    assert cmd.interval[1] - cmd.interval[0] < free.interval[1] - free.interval[0] - 0.1  # cut by the sphere
    ctrl.set_obstacles([])
    assert ctrl.step(q).interval == pytest.approx(free.interval)
    with pytest.raises(SettingError, match="at most 8"):
        ctrl.set_obstacles([Sphere((5.0, 0, 0), 0.1)] * 9)


def test_a_tool_pushed_into_an_obstacle_says_obstacle(robot, caps) -> None:
    """The tool's own motion drives the hand into a sphere 12 cm ahead (the first of a few directions across
    the hand's axis whose sphere is clear of every link at the start): the redundancy cannot clear it, the
    tool goes on (level 1 first) and the command says ``OBSTACLE`` with the clearance and the link."""
    q = robot.sample_configuration()
    T = robot.tool_pose(q)
    axis = T.rotation[:, 2]
    for v in (np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0]), np.array([-1.0, 0, 0])):
        v = v - (v @ axis) * axis
        v /= np.linalg.norm(v)
        sphere = Sphere(tuple(T.translation + 0.12 * v), 0.02)
        if sampled_clearance(robot, caps, q, sphere) > 0.05:
            break
    ctrl = Controller(robot, ControllerConfig(obstacles=[sphere]))
    ctrl.reset(q)
    twist = np.concatenate([0.1 * v, np.zeros(3)])
    seen = None
    for _ in range(1500):
        cmd = ctrl.step(q, tool_twist=twist)
        q = q + DT * cmd.dq
        if cmd.status & Status.OBSTACLE:
            seen = cmd
            break
    assert seen is not None  # (said as soon as a row cannot be kept: before the margin is crossed)
    assert any(name in seen.message for name in caps.names) and "obstacle 0" in seen.message
    assert seen.clearance < ctrl.config.obstacle_influence
    statuses = []
    for _ in range(1000):
        cmd = ctrl.step(q, tool_twist=twist)
        q = q + DT * cmd.dq
        statuses.append(bool(cmd.status & Status.OBSTACLE))
        if cmd.clearance < -0.01:
            break
    assert cmd.clearance < -0.01 and all(statuses)  # the tool went on into it, saying so every tick
    assert np.linalg.norm(robot.tool_pose(q).translation - T.translation) > 0.04  # (the tool was not stopped)


def test_the_torque_wall_is_the_rows_damper_projected(robot, caps) -> None:
    """A measured motion toward an obstacle faster than its rows allow adds ``Nᵀ·Σ D_ob·(l − ∇dᵀq̇)₊·∇d`` to
    the torque command (∇d, l from coal's distances and the damper; N the dynamically consistent projector,
    by NumPy); a motion away adds nothing."""
    q = robot.sample_configuration()
    p = caps.points(robot, ik(robot, robot.tool_pose(q), arm_angle(robot, q) + 0.8, branch(robot, q)))
    sphere = Sphere(tuple(p[2]), 0.03)
    cfg = ControllerConfig()
    d = clearances(robot, q, [sphere])[:, 0]
    near = np.flatnonzero(d < cfg.obstacle_influence)
    h = 1e-6
    grads = [
        np.array(
            [
                clearances(robot, q + h * e, [sphere])[c, 0] - clearances(robot, q - h * e, [sphere])[c, 0]
                for e in np.eye(7)
            ]
        )
        / (2 * h)
        for c in near
    ]
    toward = -0.5 * grads[0] / (grads[0] @ grads[0])  # the nearest link at 0.5 m/s into the sphere
    taus = {}
    for damping in (0.0, 500.0):
        ctrl = Controller(robot, ControllerConfig(strategy="damped", obstacles=[sphere], obstacle_damping=damping))
        ctrl.reset(q)
        taus[damping] = [ctrl.step(q, dq=v).tau for v in (toward, -toward)]
    gain = cfg.obstacle_speed / (cfg.obstacle_influence - cfg.obstacle_margin)
    wall = sum(500.0 * max(-gain * (d[c] - cfg.obstacle_margin) - g @ toward, 0.0) * g for c, g in zip(near, grads))
    A, J = robot.mass_matrix(q), robot.jacobian(q)
    Ai = np.linalg.inv(A)
    expected = (np.eye(7) - J.T @ np.linalg.solve(J @ Ai @ J.T, J @ Ai)) @ wall
    assert len(near) >= 1 and np.abs(expected).max() > 1.0
    np.testing.assert_allclose(taus[500.0][0] - taus[0.0][0], expected, atol=1e-6 * np.abs(expected).max())
    np.testing.assert_allclose(taus[500.0][1], taus[0.0][1], atol=1e-12)  # (moving away: no wall)


def urdf_with_collisions(tmp_path) -> str:
    """The LWR4+ URDF with collision elements: a cylinder on each arm link, a sphere on the base and link 7."""
    text = (qpnso.model.robot.MODELS_DIR / "lwr4p.urdf").read_text()
    shapes = {
        "base_link": '<origin xyz="0 0 0.05"/><geometry><sphere radius="0.09"/></geometry>',
        "link_7": '<origin xyz="0 0 0.02"/><geometry><sphere radius="0.05"/></geometry>',
    }
    for k in range(1, 7):
        cylinder = f'<cylinder radius="0.0{5 + k % 3}" length="0.2"/>'
        shapes[f"link_{k}"] = f'<origin xyz="0 0.01 0.1" rpy="0.1 0 0"/><geometry>{cylinder}</geometry>'
    for link, shape in shapes.items():
        text = text.replace(f'<link name="{link}">', f'<link name="{link}"><collision>{shape}</collision>', 1)
    path = tmp_path / "lwr4p.urdf"
    path.write_text(text)
    return str(path)


def test_a_urdf_s_collision_primitives_are_the_capsules(tmp_path) -> None:
    """Where the URDF has collision elements (all capsules, cylinders or spheres) they are the capsules: a
    sphere's distance equals coal's on the URDF's own ``GeometryModel``, a cylinder's capsule is never farther
    than the cylinder nor nearer by more than its radius (no Controller nor kernel here: eight capsules are
    another record type, compiled anew)."""
    import coal

    path = urdf_with_collisions(tmp_path)
    robot = qpnso.load_robot(path)
    caps = link_capsules(robot)
    assert caps.source == "urdf" and caps.count == 8
    urdf = pin.buildGeomFromUrdf(robot.model, path, pin.GeometryType.COLLISION)
    data = pin.GeometryData(urdf)
    rng = np.random.default_rng(7)
    obstacle = Sphere((0.3, -0.2, 0.6), 0.1)
    ball = coal.Sphere(0.1)
    T_ball = coal.Transform3s(np.eye(3), np.array(obstacle.center))
    for _ in range(20):
        q = robot.random_q(rng)
        pin.updateGeometryPlacements(robot.model, robot.data, urdf, data, q)
        ours = clearances(robot, q, [obstacle])[:, 0]
        for k, obj in enumerate(urdf.geometryObjects):
            M = data.oMg[k]
            truth = coal.distance(obj.geometry, coal.Transform3s(M.rotation, M.translation), ball, T_ball,
                                  coal.DistanceRequest(), coal.DistanceResult())  # fmt: skip
            if truth <= 0:
                continue
            if isinstance(obj.geometry, coal.Sphere):
                assert ours[k] == pytest.approx(truth, abs=1e-8)
            else:
                assert truth - obj.geometry.radius - 1e-8 <= ours[k] <= truth + 1e-8


def test_the_torque_wall_s_spring_acts_inside_the_margin(robot, caps) -> None:
    """A link inside the margin adds ``Nᵀ·Σ K_ob·(d_s − d)₊·∇d`` (∇d from coal's distances) to the torque, at
    rest; outside the margin nothing."""
    q = robot.sample_configuration()
    p = caps.points(robot, ik(robot, robot.tool_pose(q), arm_angle(robot, q) + 0.8, branch(robot, q)))
    pull = caps.points(robot, q)[2] - p[2]
    cfg = ControllerConfig()
    depth = {}  # the sphere moved toward the arm until a link is 1–2 cm inside the margin (the torque unsaturated)
    for f in np.linspace(0.0, 1.0, 101):
        d = clearances(robot, q, [Sphere(tuple(p[2] + f * pull), 0.03)]).min()
        if cfg.obstacle_margin - 0.02 < d < cfg.obstacle_margin - 0.01:
            depth[True] = f
            break
    depth[False] = 0.0
    for inside in (True, False):
        sphere = Sphere(tuple(p[2] + depth[inside] * pull), 0.03)
        d = clearances(robot, q, [sphere])[:, 0]
        assert (d.min() < cfg.obstacle_margin) == inside
        near = np.flatnonzero(d < cfg.obstacle_influence)
        h = 1e-6
        step = [
            clearances(robot, q + h * e, [sphere])[near, 0] - clearances(robot, q - h * e, [sphere])[near, 0]
            for e in np.eye(7)
        ]
        grads = np.array(step).T / (2 * h)  # (rows, joints)
        taus = []
        for stiffness in (0.0, 1e4):
            ctrl = Controller(
                robot, ControllerConfig(strategy="damped", obstacles=[sphere], obstacle_stiffness=stiffness)
            )
            ctrl.reset(q)
            taus.append(ctrl.step(q, dq=np.zeros(7)).tau)
        wall = sum(1e4 * max(cfg.obstacle_margin - d[c], 0.0) * g for c, g in zip(near, grads))
        A, J = robot.mass_matrix(q), robot.jacobian(q)
        Ai = np.linalg.inv(A)
        expected = (np.eye(7) - J.T @ np.linalg.solve(J @ Ai @ J.T, J @ Ai)) @ wall
        np.testing.assert_allclose(taus[1] - taus[0], expected, atol=1e-6 * max(np.abs(expected).max(), 1.0))
        assert (np.abs(expected).max() > 1.0) == inside


def test_links_that_do_not_turn_rigidly_take_the_numerical_walk(robot, caps) -> None:
    """An arm whose capsules do not turn rigidly with the arm angle (``geo.arcs`` 0: capsules off the joint
    axes) has no closed-form cut: with obstacles its controller walks the interval numerically, obstacles and
    all, and finds the closed form's interval (the LWR4+ here, its record told otherwise); without them the
    tick renews it again."""
    q = robot.sample_configuration()
    p = caps.points(robot, ik(robot, robot.tool_pose(q), arm_angle(robot, q) + 0.8, branch(robot, q)))
    sphere = Sphere(tuple(p[2]), 0.03)
    ctrl = Controller(robot, ControllerConfig())
    params = ctrl.records.params
    params[0]["geo"]["arcs"] = 0.0
    ctrl.set_obstacles([sphere])
    assert params[0]["closed_form_interval"] == 0.0
    ctrl.reset(q)
    walked = ctrl.step(q).interval
    closed = qpnso.continuity_interval(robot, q, obstacles=[sphere])
    assert walked == pytest.approx((closed.lo, closed.hi), abs=1e-6)
    assert closed.hi_cause.kind == "obstacle" or closed.lo_cause.kind == "obstacle"
    ctrl.set_obstacles([])
    assert params[0]["closed_form_interval"] == 1.0


def test_reset_forgets_the_clearance(robot, caps) -> None:
    """A stop tick reports the clearance its run last found; after ``reset`` none (inf)."""
    q = robot.sample_configuration()
    p = caps.points(robot, ik(robot, robot.tool_pose(q), arm_angle(robot, q) + 0.8, branch(robot, q)))
    ctrl = Controller(robot, ControllerConfig(obstacles=[Sphere(tuple(p[2]), 0.03)]))
    ctrl.reset(q)
    assert ctrl.step(q).clearance < 0.2
    ctrl.reset(q)
    report = ctrl.records.report[0]
    assert report["clearance"] == math.inf and report["clear_capsule"] == -1 and report["obstacle_rows"] == 0


def test_with_more_pairs_than_room_the_nearest_keep_their_rows(robot, caps) -> None:
    """Eight spheres (the controller's room: no other record type) on circles across the arm's plane — six
    16 cm round the elbow, two 15 cm round a point of the forearm near the wrist — put 17 link–obstacle pairs
    within the influence distance, more than a tick has keep-out rows (16): the 16 nearest keep theirs (coal's
    distances)."""
    q = robot.sample_configuration()
    S, E, W = caps.points(robot, q)[1:4]
    n = np.cross(S - E, W - E)
    n /= np.linalg.norm(n)

    def circle(centre, count, first, last, radius):
        m = centre - 0.5 * (S + W)
        m -= (m @ n) * n
        m /= np.linalg.norm(m)
        angles = np.radians(np.linspace(first, last, count))
        return [Sphere(tuple(centre + radius * (np.cos(a) * n + np.sin(a) * m)), 0.02) for a in angles]

    spheres = circle(E, 6, -180.0, 160.0, 0.16) + circle(0.2 * E + 0.8 * W, 2, -90.0, 90.0, 0.15)
    d = clearances(robot, q, spheres).ravel()
    near = np.sort(d[d < ControllerConfig().obstacle_influence])
    assert len(near) > 16
    ctrl = Controller(robot, ControllerConfig(obstacles=spheres))
    ctrl.reset(q)
    ctrl.step(q)
    kept = ctrl.records.memory[0]["keep_out_d"][: int(ctrl.records.report[0]["obstacle_rows"])]
    np.testing.assert_allclose(np.sort(kept), near[:16], atol=1e-9)
