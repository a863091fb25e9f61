"""Obstacle-aware arm-angle intervals (qpnso.elbow.intervals with obstacles) against an independent computation:
the closed-form IK sampled over the circle, the joint limits compared with ``q_min``/``q_max`` and the clearance
from coal (``qpnso.model.collision.clearances``: Pinocchio's GeometryModel and GJK), not the intervals' kernels.
Also: the continuity interval is the arc that holds q and the one the control tick reports, the causes name the
link and the obstacle, a configuration within the margin is refused, no obstacle changes nothing, the Panda's
numerical walk ends at an obstacle, and ``qpnso intervals --obstacles`` draws it."""

from __future__ import annotations

import math

import coal
import numpy as np
import pinocchio as pin
import pytest
from conftest import HAS_PANDA
from test_intervals import _inside, _regular_qs

from qpnso import Controller, ControllerConfig
from qpnso.cli import main
from qpnso.elbow import arm_angle as E
from qpnso.elbow import intervals as I
from qpnso.elbow import srs as S
from qpnso.elbow.clearance import OBSTACLE_END
from qpnso.errors import InputError
from qpnso.model.collision import LinkCapsules, _z_to, clearances, coal_shape, geometry_model, link_capsules
from qpnso.model.obstacles import Box, Capsule, Obstacle, Sphere
from qpnso.model.robot import Robot, load_robot

TWO_PI = 2 * math.pi
MARGIN = 0.03  # m
SAMPLES = 180
GRID = np.linspace(-math.pi, math.pi, SAMPLES + 1)[:-1] + math.pi / SAMPLES  # rad (off ±π and 0)
NEAR_END = 1e-3  # rad: samples this near an arc end are not compared
SIDE = 1e-5  # rad: an obstacle end has coal's clearance on either side of the margin this far from it
END_TOL = 1e-6  # rad: an obstacle end is this near the sign change coal finds


@pytest.fixture(scope="module")
def lwr() -> Robot:
    return load_robot("lwr4p")


class CoalClearance:
    """``clearances(robot, q, [obstacle], geom).min()`` (m, coal) with the geometry data and the obstacle's coal
    shape made once: the least distance of the link capsules to ``obstacle`` at q (rad)."""

    def __init__(self, robot: Robot, geom: pin.GeometryModel, obstacle: Obstacle) -> None:
        self.robot, self.geom = robot, geom
        self.gdata, self.data = pin.GeometryData(geom), robot.model.createData()
        shape, M = coal_shape(obstacle)
        self.shape, self.M = shape, coal.Transform3s(M.rotation, M.translation)

    def __call__(self, q: np.ndarray) -> float:
        pin.updateGeometryPlacements(self.robot.model, self.data, self.geom, self.gdata, q)
        placed = zip(self.geom.geometryObjects, self.gdata.oMg)
        return min(
            coal.distance(
                obj.geometry,
                coal.Transform3s(M.rotation, M.translation),
                self.shape,
                self.M,
                coal.DistanceRequest(),
                coal.DistanceResult(),
            )  # fmt: skip
            for obj, M in placed
        )


def _turns(a: float, b: float) -> float:
    """|a − b| modulo whole turns (rad)."""
    return abs(math.remainder(a - b, TWO_PI))


def _near_end(arcs: list[tuple[float, float]], x: np.ndarray, tol: float) -> np.ndarray:
    out = np.zeros(x.shape, bool)
    for end in [e for arc in arcs for e in arc]:
        out |= np.abs(np.angle(np.exp(1j * (x - end)))) < tol
    return out


def _near_the_arm(rng: np.random.Generator, capsules: LinkCapsules, points: np.ndarray) -> Obstacle:
    """A random sphere, capsule or box (m) near the upper arm (capsule 1) or the forearm (capsule 2) at the chain
    ``points``: its surface from −3 to +8 cm beyond the margin around a random point of the link's axis, on the
    side away from the shoulder–wrist axis (the elbow circle's outside)."""
    c = int(rng.integers(1, 3))
    a, b = points[capsules.a[c]], points[capsules.b[c]]
    at = a + rng.uniform(0.3, 0.7) * (b - a)
    shoulder, wrist = points[capsules.a[1]], points[capsules.b[2]]
    axis = (wrist - shoulder) / np.linalg.norm(wrist - shoulder)
    radial = (at - shoulder) - ((at - shoulder) @ axis) * axis
    u = rng.normal(size=3)
    u /= np.linalg.norm(u) * np.sign(u @ radial)
    size = rng.uniform(0.02, 0.08)
    center = at + u * (capsules.radius[c] + MARGIN + size + rng.uniform(-0.03, 0.08))
    kind = int(rng.integers(3))
    if kind == 0:
        return Sphere(tuple(center), size)
    if kind == 1:
        v = rng.normal(size=3)
        v *= rng.uniform(0.03, 0.15) / np.linalg.norm(v)
        return Capsule(tuple(center - v), tuple(center + v), size)
    return Box(tuple(center), tuple(rng.uniform(0.5, 1.5, 3) * size), rpy_deg=tuple(rng.uniform(-180, 180, 3)))


def _obstacle_ends(arcs, plain) -> list[tuple[float, float]]:
    """``(end, inward)`` of every arc end (rad) that is not an end of the joint-limit arcs ``plain`` (modulo whole
    turns): the ends at obstacles; ``inward`` +1 for a lower end, −1 for an upper one."""
    plain_ends = [e for arc in plain for e in arc]
    ends = [(lo, 1.0) for lo, _ in arcs] + [(hi, -1.0) for _, hi in arcs]
    return [(e, s) for e, s in ends if all(_turns(e, x) > 1e-9 for x in plain_ends)]


def _coal_crossing(clear: CoalClearance, sm: S.SelfMotion, end: float, inward: float) -> float:
    """The margin crossing of coal's clearance between ``end ± SIDE`` (rad) along the self-motion ``sm`` (the
    closed-form IK), bisected to 3e-10 rad."""
    inside, outside = end + inward * SIDE, end - inward * SIDE
    for _ in range(16):
        mid = 0.5 * (inside + outside)
        if clear(sm.joints(mid)) >= MARGIN:
            inside = mid
        else:
            outside = mid
    return 0.5 * (inside + outside)


def _check_pose(
    robot: Robot, geom: pin.GeometryModel, q: np.ndarray, rng: np.random.Generator, per_joint: bool, stats: dict
) -> None:
    """One pose of the brute-force test: an obstacle near the arm at a random arm angle of Ψ; the arcs agree with
    the sampled circle away from their ends; every obstacle end is the sign change of coal's clearance."""
    capsules = link_capsules(robot)
    pose, b = robot.tool_pose(q), S.branch(robot, q)
    sm = S.self_motion(robot, pose, b)  # (the closed-form IK: S.ik)
    plain = I.feasible_intervals(robot, pose, b)
    candidates = GRID[_inside(plain, GRID)]
    psi = rng.choice(candidates) if candidates.size else E.arm_angle(robot, q)
    obstacle = _near_the_arm(rng, capsules, capsules.points(robot, sm.joints(psi)))
    result = I.feasible_intervals(robot, pose, b, per_joint=per_joint, obstacles=[obstacle], margin=MARGIN)
    arcs, per = result if per_joint else (result, None)
    assert arcs == sorted(arcs) and all(-math.pi <= lo < math.pi and lo < hi <= lo + TWO_PI for lo, hi in arcs)
    joints = sm.joints(GRID)
    within = np.all((joints >= robot.q_min) & (joints <= robot.q_max), axis=1)
    clear = CoalClearance(robot, geom, obstacle)
    distance = np.array([clear(joints[i]) if within[i] or per_joint else np.nan for i in range(SAMPLES)])
    feasible = within & (distance >= MARGIN)
    away = ~_near_end(arcs, GRID, NEAR_END)
    assert np.array_equal(_inside(arcs, GRID)[away], feasible[away])
    if per is not None:  # "obstacles": the clearance alone, limits left out
        far = ~_near_end(per["obstacles"], GRID, NEAR_END)
        assert np.array_equal(_inside(per["obstacles"], GRID)[far], (distance >= MARGIN)[far])
    for end, inward in _obstacle_ends(arcs, plain):
        inner, outer = (clear(sm.joints(end + side * SIDE)) for side in (inward, -inward))
        assert inner >= MARGIN > outer
        stats["worst_end"] = max(stats["worst_end"], abs(_coal_crossing(clear, sm, end, inward) - end))
        stats["ends"] += 1
    stats["poses"] += 1
    stats["cut"] += bool(arcs) and arcs != plain
    stats["emptied"] += not arcs


@pytest.mark.parametrize(("name", "poses"), [("lwr4p", 1000), ("iiwa14", 200)])
def test_obstacle_intervals_agree_with_ik_sampling(name: str, poses: int) -> None:
    """Must-hold: on random poses (the LWR4+: 1000) with a random sphere, capsule or box near the elbow circle,
    Ψ with obstacles equals the arm angles whose closed-form IK is within the joint limits and keeps every link
    capsule the margin from the obstacle (coal), except within 1e-3 rad of an arc end; every end the obstacle
    makes has coal's clearance on either side of the margin 1e-5 rad from it and is within 1e-6 rad of coal's
    sign change (bisected).  The obstacle cuts part of the circle in more than 30 % of the poses."""
    robot = load_robot(name)
    geom = geometry_model(robot)
    rng = np.random.default_rng(2025)
    qs = _regular_qs(robot, rng, poses)
    sphere = Sphere((0.3, 0.2, 0.6), 0.05)
    assert CoalClearance(robot, geom, sphere)(qs[0]) == clearances(robot, qs[0], [sphere], geom).min()  # (its loop)
    stats = {"poses": 0, "cut": 0, "emptied": 0, "ends": 0, "worst_end": 0.0}
    for i, q in enumerate(qs):
        _check_pose(robot, geom, q, rng, i % 10 == 0, stats)
    print(f"\n{name}: {stats}, cut in {stats['cut'] / stats['poses']:.0%} of the poses")
    assert stats["poses"] == poses
    assert stats["cut"] > 0.3 * poses and stats["ends"] > poses / 2
    assert stats["worst_end"] < END_TOL


def _cut_cases(robot: Robot, rng: np.random.Generator, n: int) -> list[tuple[np.ndarray, Sphere]]:
    """``n`` configurations (rad) with a sphere near the elbow 0.3–2 rad of arm angle away, q outside its
    margin."""
    capsules, cases = link_capsules(robot), []
    for q in _regular_qs(robot, rng, 10 * n, margin=0.1):
        pose, b, ns = robot.tool_pose(q), S.branch(robot, q), E.arm_angle(robot, q)
        away = ns + rng.choice([-1.0, 1.0]) * rng.uniform(0.3, 2.0)
        points = capsules.points(robot, S.ik(robot, pose, away, b))
        sphere = Sphere(tuple(points[2] + 0.03 * rng.normal(size=3)), 0.05)
        if clearances(robot, q, [sphere]).min() > MARGIN + 1e-3:
            cases.append((q, sphere))
    return cases[:n]


def test_the_continuity_interval_is_the_arc_holding_q_and_the_ticks(lwr: Robot) -> None:
    """With an obstacle, ``continuity_interval`` is the arc of ``feasible_intervals`` that holds the arm angle of
    q (both bisect the obstacle's ends to 1e-7 rad: equal to 1e-6) and, to 1e-9, the interval a ``Controller``
    with the obstacle reports at its first tick (the tick runs the same kernel)."""
    ctrl = Controller(lwr, ControllerConfig(obstacles=[Sphere((5.0, 0.0, 0.0), 0.1)], obstacle_margin=MARGIN))
    cut = 0
    for q, sphere in _cut_cases(lwr, np.random.default_rng(3), 24):
        ns, pose, b = E.arm_angle(lwr, q), lwr.tool_pose(q), S.branch(lwr, q)
        interval = I.continuity_interval(lwr, q, obstacles=[sphere], margin=MARGIN)
        arcs = I.feasible_intervals(lwr, pose, b, obstacles=[sphere], margin=MARGIN)
        holding = [(lo, hi) for lo, hi in arcs if (ns - lo) % TWO_PI <= hi - lo]
        assert len(holding) == 1
        lo, hi = holding[0]
        assert _turns(lo, interval.lo) < 1e-6 and abs((hi - lo) - interval.width) < 1e-6
        assert interval.lo <= ns <= interval.hi
        ctrl.set_obstacles([sphere])
        ctrl.reset(q)
        cmd = ctrl.step(q)
        assert cmd.interval == pytest.approx((interval.lo, interval.hi), abs=1e-9)
        cut += "obstacle" in (interval.lo_cause.kind, interval.hi_cause.kind)
    assert cut >= 12


def test_an_obstacle_end_names_the_link_and_the_obstacle(lwr: Robot) -> None:
    """An interval ended by the second of two obstacles names it (``obstacle=1``) and the link capsule that coal
    finds nearest it at the end; the end codes of ``qpnso.elbow.clearance`` decode to that cause, and the joint
    ones as before."""
    q = np.radians([10, 40, -10, -70, 20, 50, 0])
    pose, b, ns = lwr.tool_pose(q), S.branch(lwr, q), E.arm_angle(lwr, q)
    capsules = link_capsules(lwr)
    elbow = capsules.points(lwr, S.ik(lwr, pose, ns + 1.5, b))[2]
    obstacles = [Box((2.0, 2.0, 0.0), (0.1, 0.1, 0.1)), Sphere(tuple(elbow), 0.05)]
    interval = I.continuity_interval(lwr, q, obstacles=obstacles, margin=MARGIN)
    cause = interval.hi_cause
    assert cause.kind == "obstacle" and cause.joint == -1 and cause.obstacle == 1
    at_end = clearances(lwr, S.ik(lwr, pose, interval.hi, b), obstacles)
    k, j = (int(i) for i in np.unravel_index(np.argmin(at_end), at_end.shape))
    assert (cause.link, cause.obstacle) == (geometry_model(lwr).geometryObjects[k].name, j)
    assert at_end.min() == pytest.approx(MARGIN, abs=1e-6)
    assert interval.lo_cause == I.Cause("limit", 2, "max")  # (the other end: as without the obstacle)
    c = capsules.names.index(cause.link)
    assert I.end_cause(OBSTACLE_END - (100 * c + 1), capsules.names) == cause
    assert I.end_cause(OBSTACLE_END - 203) == I.Cause("obstacle", -1, link="capsule 2", obstacle=3)
    assert I.end_cause(5) == I.Cause("limit", 2, "max") and I.end_cause(-6) == I.Cause("singular", 5)


def test_a_configuration_within_the_margin_is_refused(lwr: Robot) -> None:
    """q with a link within the margin of an obstacle: no obstacle-free interval holds it (InputError naming the
    link, its distance and the obstacle).  The hand, which the arm angle does not move, within the margin empties
    Ψ.  A margin that is not a number >= 0 is refused."""
    q = np.radians([10, 40, -10, -70, 20, 50, 0])
    pose, b = lwr.tool_pose(q), S.branch(lwr, q)
    capsules = link_capsules(lwr)
    points = capsules.points(lwr, q)
    near_forearm = Sphere(tuple(0.5 * (points[2] + points[3])), 0.02)
    with pytest.raises(InputError, match=r"link link_4-link_5 is -0\.09 m from obstacle 0, within the margin 0\.03"):
        I.continuity_interval(lwr, q, obstacles=[near_forearm], margin=MARGIN)
    on_the_hand = Sphere(tuple(points[-1]), 0.02)
    assert I.feasible_intervals(lwr, pose, b, obstacles=[on_the_hand]) == []
    psi, per = I.feasible_intervals(lwr, pose, b, per_joint=True, obstacles=[on_the_hand])
    assert psi == [] and per["obstacles"] == []
    with pytest.raises(InputError, match="link link_6-link_7"):
        I.continuity_interval(lwr, q, obstacles=[on_the_hand])
    for margin in (-0.01, math.nan):
        with pytest.raises(InputError, match="margin must be a finite number >= 0"):
            I.continuity_interval(lwr, q, obstacles=[Sphere((2.0, 0.0, 0.0), 0.1)], margin=margin)


def test_no_obstacle_changes_nothing(lwr: Robot) -> None:
    """No obstacles, or one out of reach: the arcs, the per-joint arcs (no "obstacles" key without obstacles)
    and the continuity intervals — closed form and numerical — are exactly those computed without the argument."""
    far = [Sphere((3.0, 0.0, 0.0), 0.1)]
    for q in _regular_qs(lwr, np.random.default_rng(8), 30):
        pose, b = lwr.tool_pose(q), S.branch(lwr, q)
        psi, per = I.feasible_intervals(lwr, pose, b, per_joint=True)
        assert I.feasible_intervals(lwr, pose, b, per_joint=True, obstacles=()) == (psi, per)
        psi_far, per_far = I.feasible_intervals(lwr, pose, b, per_joint=True, obstacles=far)
        assert psi_far == psi and per_far.pop("obstacles") == [(-math.pi, math.pi)] and per_far == per
        interval = I.continuity_interval(lwr, q)
        assert I.continuity_interval(lwr, q, obstacles=far) == interval
        assert I.continuity_interval(lwr, q, obstacles=()) == interval
    q = np.radians([10, 40, -10, -70, 20, 50, 0])
    walk = I.numerical_interval(lwr, q)
    walk_far = I.numerical_interval(lwr, q, obstacles=far)
    assert (walk_far.lo, walk_far.hi, walk_far.lo_cause, walk_far.hi_cause) == (
        walk.lo,
        walk.hi,
        walk.lo_cause,
        walk.hi_cause,
    )


def _segment_clearance(robot: Robot, q: np.ndarray, obstacle: Obstacle) -> float:
    """The least distance (m) of the link capsules to ``obstacle`` at q, coal on capsules placed on the chain points
    (Pinocchio frames)."""
    capsules = link_capsules(robot)
    points = capsules.points(robot, q)
    shape, M = coal_shape(obstacle)
    placed = coal.Transform3s(M.rotation, M.translation)
    best = math.inf
    for k in range(capsules.count):
        a, b = points[capsules.a[k]], points[capsules.b[k]]
        capsule = coal.Capsule(capsules.radius[k], float(np.linalg.norm(b - a)))
        T = coal.Transform3s(_z_to(b - a), 0.5 * (a + b))
        best = min(best, coal.distance(capsule, T, shape, placed, coal.DistanceRequest(), coal.DistanceResult()))
    return best


@pytest.mark.skipif(not HAS_PANDA, reason="Panda model not available (pip install example-robot-data)")
def test_the_pandas_walk_ends_at_an_obstacle() -> None:
    """The Panda (numerical walk): a small sphere where a link will be near the end of the obstacle-free walk
    ends the walk on that side at the obstacle — the end holds the tool pose, its arm angle is the one reported,
    coal's clearance there is the margin (1e-6 m: the end bisected to 1e-7 rad) and the cause names the link
    nearest it — while the other end stays where it was.  (Coal's clearance on capsules placed on the chain points:
    ``geometry_model`` places the Panda's link 4–5 capsule on joint 5, which does not carry it.)"""
    robot = load_robot("panda")
    rng = np.random.default_rng(4)
    checked = 0
    for q in _regular_qs(robot, rng, 40, margin=0.1):
        ns = E.arm_angle(robot, q)
        free = I.numerical_interval(robot, q)
        upper = free.hi - ns >= ns - free.lo
        far = free.hi_q if upper else free.lo_q
        p0, p1 = link_capsules(robot).points(robot, q), link_capsules(robot).points(robot, far)
        k = int(np.argmax(np.linalg.norm(p1 - p0, axis=1)))
        if free.full_circle or np.linalg.norm(p1[k] - p0[k]) < 0.25:
            continue
        sphere = Sphere(tuple(p1[k]), 0.02)
        interval = I.numerical_interval(robot, q, obstacles=[sphere], margin=MARGIN)
        end, cause, q_end = (interval.hi, interval.hi_cause, interval.hi_q) if upper else (
            interval.lo, interval.lo_cause, interval.lo_q
        )  # fmt: skip
        assert cause.kind == "obstacle" and cause.obstacle == 0
        assert np.abs(robot.tool_pose(q_end).homogeneous - robot.tool_pose(q).homogeneous).max() < 1e-9
        assert abs(math.remainder(E.arm_angle(robot, q_end) - end, TWO_PI)) < 1e-9
        assert _segment_clearance(robot, q_end, sphere) == pytest.approx(MARGIN, abs=1e-6)
        assert (interval.lo if upper else interval.hi) == (free.lo if upper else free.hi)
        assert interval.lo < ns < interval.hi and interval.width < free.width
        checked += 1
        if checked == 3:
            return
    pytest.fail(f"only {checked} Panda poses with a link moving 0.25 m along the walk")


def test_cli_intervals_draws_the_obstacles(tmp_path, capsys) -> None:
    """``qpnso intervals --obstacles file.toml --obstacle-margin M`` reads ``[[obstacles]]`` tables and writes the
    figure (a PNG) with the obstacle-aware interval; without the option it prints the interval as before; a file
    without obstacle tables, or with a wrong one, is an error naming the file (exit 2)."""
    robot = load_robot("lwr4p")
    q_deg = [0, 30, 0, -60, 0, 45, 0]
    q = np.radians(q_deg)
    pose, b, ns = robot.tool_pose(q), S.branch(robot, q), E.arm_angle(robot, q)
    elbow = link_capsules(robot).points(robot, S.ik(robot, pose, ns + 1.2, b))[2]
    toml = tmp_path / "room.toml"
    toml.write_text(
        f'[[obstacles]]\ntype = "sphere"\ncenter = [{elbow[0]}, {elbow[1]}, {elbow[2]}]\nradius = 0.05\n\n'
        '[[obstacles]]\ntype = "box"\ncenter = [2.0, 0.0, 0.0]\nhalf_extents = [0.1, 0.1, 0.1]\nrpy_deg = [0, 0, 30]\n'
    )
    out = tmp_path / "iv.png"
    argv = ["intervals", "--q-deg", ",".join(map(str, q_deg)), "--obstacles", str(toml)]
    assert main([*argv, "--obstacle-margin", "0.02", "--out", str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    printed = capsys.readouterr().out
    interval = I.continuity_interval(robot, q, obstacles=[Sphere(tuple(elbow), 0.05)], margin=0.02)
    assert interval.hi_cause.kind == "obstacle"
    assert f"{np.degrees(interval.hi):.2f}] deg" in printed and "2 obstacle(s) kept 0.02 m away" in printed
    assert main([*argv[:3], "--out", str(tmp_path / "plain.png")]) == 0  # (without: as before)
    plain = I.continuity_interval(robot, q)
    assert (
        f"[{np.degrees(plain.lo):.2f}, {np.degrees(plain.hi):.2f}] deg (closed_form); figure" in capsys.readouterr().out
    )
    empty, cone = tmp_path / "empty.toml", tmp_path / "cone.toml"
    empty.write_text("[scenario]\n")
    cone.write_text('[[obstacles]]\ntype = "cone"\n')
    for toml, error in ((empty, "empty.toml: no [[obstacles]] tables"), (cone, "cone.toml: obstacles[0].type")):
        assert main([*argv[:3], "--obstacles", str(toml), "--out", str(tmp_path / "x.png")]) == 2
        assert error in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()
