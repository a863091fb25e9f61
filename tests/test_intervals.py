"""Continuity intervals against brute force (dense circle sampling), the numerical
self-motion follower against the closed form, and the Panda (numerical only)."""

from __future__ import annotations

import glob
import math
import site

import numpy as np
import pinocchio as pin
import pytest

from qpnso.elbow import arm_angle as E
from qpnso.elbow import intervals as I
from qpnso.elbow import srs as S
from qpnso.errors import JointLimitError, RobotNotFoundError, SingularityError
from qpnso.model.robot import Robot, friction_from_lists, load_robot

TWO_PI = 2 * math.pi
GRID = np.linspace(-math.pi, math.pi, 721)[:-1]
STEP = GRID[1] - GRID[0]


@pytest.fixture(scope="module", params=["lwr4p", "iiwa14"])
def robot(request) -> Robot:
    return load_robot(request.param)


def _regular_qs(robot: Robot, rng: np.random.Generator, n: int, margin: float = 0.0) -> list[np.ndarray]:
    qs = (robot.random_q(rng, margin) for _ in range(2 * n))
    return [q for q in qs if E.arm_angle_status(robot, q).ok][:n]


def _inside(arcs: list[tuple[float, float]], x: np.ndarray) -> np.ndarray:
    out = np.zeros(x.shape, bool)
    for lo, hi in arcs:
        out |= (x - lo) % TWO_PI <= hi - lo
    return out


def _near_end(arcs: list[tuple[float, float]], x: np.ndarray, tol: float) -> np.ndarray:
    out = np.zeros(x.shape, bool)
    for end in [e for arc in arcs for e in arc]:
        out |= np.abs(np.angle(np.exp(1j * (x - end)))) < tol
    return out


def _end_is_exact(robot: Robot, pose: pin.SE3, b: S.Branch, ns: float, cause: I.Cause) -> None:
    q = S.ik(robot, pose, ns, b)
    if cause.kind == "limit":
        limit = robot.q_max[cause.joint] if cause.bound == "max" else robot.q_min[cause.joint]
        assert abs(q[cause.joint] - limit) < 1e-9
        assert np.all(q >= robot.q_min - 1e-9) and np.all(q <= robot.q_max + 1e-9)
    else:
        assert abs(q[cause.joint]) < 1e-4  # joint 2 or 6 through 0


def test_brute_force_1000_poses(robot: Robot) -> None:
    """Ψ equals the feasible samples of the circle, and the continuity interval is exact."""
    rng = np.random.default_rng(2024)
    data = robot.model.createData()
    n_checked = n_bounded = 0
    for q in _regular_qs(robot, rng, 1000):
        pose, b = robot.tool_pose(q), S.branch(robot, q)
        psi, per_joint = I.feasible_intervals(robot, pose, b, per_joint=True)
        joints = S.ik(robot, pose, GRID, b)
        feasible = np.all((joints >= robot.q_min) & (joints <= robot.q_max), axis=1)
        inside = _inside(psi, GRID)
        away = ~_near_end(psi, GRID, STEP)
        assert np.array_equal(inside[away], feasible[away])
        for k in (0, 3, 5):  # per-joint sets (checked on a few joints to stay fast)
            ok_k = (joints[:, k] >= robot.q_min[k]) & (joints[:, k] <= robot.q_max[k])
            far_k = ~_near_end(per_joint[k], GRID, STEP)
            assert np.array_equal(_inside(per_joint[k], GRID)[far_k], ok_k[far_k])
        for i in rng.choice(GRID.size, 3, replace=False):  # the sampled joints hold the pose (Pinocchio)
            pin.framesForwardKinematics(robot.model, data, joints[i])
            assert np.abs(data.oMf[robot.tool_frame_id].homogeneous - pose.homogeneous).max() < 1e-9
        interval = I.continuity_interval(robot, q)
        ns = E.arm_angle(robot, q)
        assert interval.lo <= ns <= interval.hi and interval.width <= TWO_PI + 1e-12
        assert interval.contains(ns + TWO_PI) and interval.contains(ns - TWO_PI)
        if interval.full_circle:
            assert psi == [(-math.pi, math.pi)]
        else:
            n_bounded += 1
            for end, cause in ((interval.lo, interval.lo_cause), (interval.hi, interval.hi_cause)):
                _end_is_exact(robot, pose, b, end, cause)
            arc = [a for a in psi if abs(np.angle(np.exp(1j * (a[0] - interval.lo)))) < 1e-9]
            assert len(arc) == 1 and arc[0][1] - arc[0][0] == pytest.approx(interval.width, abs=1e-9)
        n_checked += 1
    assert n_checked >= 950 and n_bounded > 500


def test_arc_convention_across_pi(robot: Robot) -> None:
    rng = np.random.default_rng(5)
    for q in _regular_qs(robot, rng, 300):
        psi = I.feasible_intervals(robot, robot.tool_pose(q), S.branch(robot, q))
        assert psi == sorted(psi)
        for lo, hi in psi:
            assert -math.pi <= lo < math.pi and lo < hi <= lo + TWO_PI
        if any(hi > math.pi for lo, hi in psi if (lo, hi) != (-math.pi, math.pi)):
            return
    pytest.fail("no arc crossing ±π found in 300 poses")


def test_numerical_follower_matches_closed_form(robot: Robot) -> None:
    rng = np.random.default_rng(11)
    for q in _regular_qs(robot, rng, 4, margin=0.1):
        exact = I.continuity_interval(robot, q)
        numeric = I.numerical_interval(robot, q)
        assert numeric.method == "numerical" and exact.method == "closed_form"
        assert numeric.full_circle == exact.full_circle
        if not exact.full_circle:
            assert numeric.lo == pytest.approx(exact.lo, abs=1e-8)
            assert numeric.hi == pytest.approx(exact.hi, abs=1e-8)
            assert (numeric.lo_cause, numeric.hi_cause) == (exact.lo_cause, exact.hi_cause)


def test_errors(robot: Robot) -> None:
    q = np.full(7, 0.5)
    q[0] = robot.q_max[0] + 0.01
    with pytest.raises(JointLimitError, match="outside"):
        I.continuity_interval(robot, q)
    with pytest.raises(SingularityError):
        I.continuity_interval(robot, np.zeros(7))  # wrist straight above the shoulder
    q = np.array([0.3, 0.0, 0.2, 1.0, 0.1, 0.5, 0.0])
    with pytest.raises(SingularityError, match="joint 2"):
        I.continuity_interval(robot, q)  # branch undefined


# ------------------------------------------------------------------ Panda
def _panda() -> Robot:
    try:
        return load_robot("panda")
    except RobotNotFoundError:
        pass
    pattern = "/cmeel.prefix/share/example-robot-data/robots/panda_description/urdf/panda.urdf"
    paths = [p for d in site.getsitepackages() for p in glob.glob(d + pattern)]
    if not paths:
        pytest.skip("Panda model not available (pip install example-robot-data)")
    full = pin.buildModelFromUrdf(paths[0])
    fingers = [full.getJointId(n) for n in full.names if "finger" in n]
    model = pin.buildReducedModel(full, fingers, pin.neutral(full))
    return Robot("panda", model, model.getFrameId("panda_link8"), friction_from_lists([1.5] * 7, [20.0] * 7, 7))


def test_panda_numerical_interval_ends_are_limit_crossings() -> None:
    robot = _panda()
    assert not S.is_srs(robot)
    rng = np.random.default_rng(3)
    for q in _regular_qs(robot, rng, 4, margin=0.1):
        interval = I.continuity_interval(robot, q)
        assert interval.method == "numerical"
        pose = robot.tool_pose(q)
        assert interval.lo <= E.arm_angle(robot, q) <= interval.hi
        if interval.full_circle:
            continue
        for end, cause, q_end in (
            (interval.lo, interval.lo_cause, interval.lo_q),
            (interval.hi, interval.hi_cause, interval.hi_q),
        ):
            assert np.abs(robot.tool_pose(q_end).homogeneous - pose.homogeneous).max() < 1e-9
            assert abs(np.angle(np.exp(1j * (E.arm_angle(robot, q_end) - end)))) < 1e-9
            if cause.kind == "limit":
                limit = robot.q_max[cause.joint] if cause.bound == "max" else robot.q_min[cause.joint]
                assert abs(q_end[cause.joint] - limit) < 1e-9
                assert np.all(q_end >= robot.q_min - 1e-9) and np.all(q_end <= robot.q_max + 1e-9)


def test_a_walk_in_pieces_takes_the_pieces_it_is_given_and_ends_where_a_whole_one_does(monkeypatch) -> None:
    """``NumericalWalk.advance(k)`` does at most k pieces of work a call — each at most one tool Jacobian (a Newton
    iteration of a pose correction or of a limit crossing's exact solve, or a step's null direction), counted by
    wrapping Pinocchio's ``computeFrameJacobian`` — and, whatever the pieces, ends with the interval of
    ``numerical_interval``, ends and causes equal."""
    robot = _panda()
    rng = np.random.default_rng(4)
    jacobians = []
    jacobian = pin.computeFrameJacobian

    def counted(*args):
        jacobians.append(1)
        return jacobian(*args)

    for q, pieces in zip(_regular_qs(robot, rng, 3, margin=0.1), (1, 2, 7)):
        whole = I.numerical_interval(robot, q)
        walk = I.NumericalWalk(robot, q)
        monkeypatch.setattr(pin, "computeFrameJacobian", counted)
        result, calls = None, 0
        while result is None:
            before = len(jacobians)
            result = walk.advance(pieces)
            assert len(jacobians) - before <= pieces
            calls += 1
        monkeypatch.setattr(pin, "computeFrameJacobian", jacobian)
        assert walk.steps > 10 and calls == -(-walk.steps // pieces)  # every call but the last took all it was given
        assert len(jacobians) > walk.steps / 2  # (the count sees the walk's work: not vacuous)
        jacobians.clear()
        assert (result.lo, result.hi, result.lo_cause, result.hi_cause) == (
            whole.lo,
            whole.hi,
            whole.lo_cause,
            whole.hi_cause,
        )


@pytest.mark.parametrize("joint", [1, 5])
@pytest.mark.parametrize("side", [1.0, -1.0])
def test_a_singular_cut_ends_the_interval_and_is_named(robot: Robot, joint: int, side: float) -> None:
    """A pose whose self-motion takes joint 2 (or 6) through 0 at a known arm angle: from 0.3 rad on either
    side, the continuity interval ends exactly there and names the singular cut (it once named a limit of
    joint 3, 80° away from it, from one side).  Checked by brute force on the closed-form IK (the branch
    held): every sample inside is within the limits, the cut joint goes to 0 at the end, and just past it
    joints 1 and 3 (5 and 7) jump by about π."""
    q_cut = np.radians([10, 40, -10, -70, 20, 50, 0])
    q_cut[joint] = 0.0
    pose = robot.tool_pose(q_cut)
    ns_cut = E.arm_angle(robot, q_cut)
    near = q_cut.copy()
    near[joint] = side * np.radians(5)  # picks the branch on that side of the cut
    b = S.branch(robot, near)
    start = S.ik(robot, pose, ns_cut + side * 0.3, b).reshape(-1)
    assert np.all((start >= robot.q_min) & (start <= robot.q_max))
    interval = I.continuity_interval(robot, start)
    end, cause = (interval.lo, interval.lo_cause) if side > 0 else (interval.hi, interval.hi_cause)
    assert cause == I.Cause("singular", joint)
    assert end == pytest.approx(ns_cut, abs=1e-9)
    inside = S.ik(robot, pose, np.linspace(ns_cut + side * 0.3, ns_cut + side * 1e-6, 200), b)
    assert np.all((inside >= robot.q_min) & (inside <= robot.q_max))
    assert abs(inside[-1, joint]) < 1e-4
    before, after = (S.ik(robot, pose, ns_cut + s * 1e-7, b).reshape(-1) for s in (side, -side))
    jump = np.abs(np.angle(np.exp(1j * (after - before))))
    partners = (0, 2) if joint == 1 else (4, 6)
    assert np.all(jump[list(partners)] > 3.0)


def test_limits_at_or_beyond_pi_go_to_the_numerical_method() -> None:
    """The closed form cannot read a limit at or beyond ±π (it aliased: ±7 rad limits bounded the interval at
    ±0.24 rad): such an arm's continuity interval is the numerical one (here a full circle, which a walk of
    the self-motion with the IK confirms, from ns − π to ns + π), and the closed-form arcs refuse it by name."""
    import copy

    from qpnso.errors import ModelError

    robot = load_robot("lwr4p")
    wide = copy.copy(robot)
    wide.q_min, wide.q_max = np.full(7, -7.0), np.full(7, 7.0)
    q = np.radians([10, 40, -10, -70, 20, 50, 0])
    interval = I.continuity_interval(wide, q)
    assert interval.method == "numerical" and interval.full_circle
    ns = E.arm_angle(robot, q)  # a full circle is the circle around the start's arm angle, ends half a turn away
    assert (interval.lo, interval.hi) == (ns - math.pi, ns + math.pi)
    with pytest.raises(ModelError, match=r"inside ±π; joint 1 has \[-7, 7\] rad"):
        I.feasible_intervals(wide, wide.tool_pose(q), S.branch(wide, q))
    assert I.continuity_interval(robot, q).method == "closed_form"  # real limits: unchanged


def test_closed_form_arcs_end_at_a_singular_cut_and_name_their_ends() -> None:
    """The LWR4+ pose with joint 6 through 0 at a known arm angle ns_cut (Pinocchio's, of that configuration):
    the closed-form arcs Ψ are cut there into two arcs that meet at ns_cut, and both ends at the cut are named
    ``Cause("singular", 5)``, with joint 6 at 0 there (closed-form IK)."""
    robot = load_robot("lwr4p")
    q_cut = np.radians([10, 40, -10, -70, 20, 50, 0])
    q_cut[5] = 0.0
    pose, ns_cut = robot.tool_pose(q_cut), E.arm_angle(robot, q_cut)
    near = q_cut.copy()
    near[5] = np.radians(5)
    b = S.branch(robot, near)
    psi = I.feasible_intervals(robot, pose, b)
    assert [hi for _, hi in psi if hi == pytest.approx(ns_cut, abs=1e-9)] and [
        lo for lo, _ in psi if lo == pytest.approx(ns_cut, abs=1e-9)
    ]
    arcs = I._arcs(I.self_motion(robot, pose, b), robot.q_min, robot.q_max, I._ALL_JOINTS)
    ends = [(lo, lo_c) for lo, _, lo_c, _ in arcs] + [(hi, hi_c) for _, hi, _, hi_c in arcs]
    at_cut = [cause for end, cause in ends if abs(I.wrap(end - ns_cut)) < 1e-9]
    assert at_cut == [I.Cause("singular", 5)] * 2
    assert abs(S.ik(robot, pose, ns_cut, b).reshape(-1)[5]) < 1e-6


def test_numerical_options_are_frozen_and_end_walks_early() -> None:
    """``NumericalOptions`` is an immutable value (frozen, hashable).  A walk of ``max_steps`` = 2 steps ends
    "unfinished" on both sides (joint −1: not a joint), two joint-space steps of 0.03 rad from the start; with
    ``sigma_min`` just below the tool Jacobian's smallest singular value at q (NumPy's SVD) one side meets a
    "singular" end (joint −1) where that singular value is below ``sigma_min``.  Each end holds the pose and
    its arm angle is the one reported (Pinocchio)."""
    import dataclasses

    options = I.NumericalOptions(max_steps=2)
    with pytest.raises(dataclasses.FrozenInstanceError):
        options.max_steps = 3  # type: ignore[misc]
    assert hash(options) == hash(I.NumericalOptions(max_steps=2))
    robot = load_robot("lwr4p")
    q = np.radians([10, 40, -10, -70, 20, 50, 0])
    ns, pose = E.arm_angle(robot, q), robot.tool_pose(q)
    short = I.numerical_interval(robot, q, options)
    assert short.lo_cause == short.hi_cause == I.Cause("unfinished", -1)
    assert short.lo < ns < short.hi and not short.full_circle
    for q_end in (short.lo_q, short.hi_q):
        assert 0.05 < np.linalg.norm(q_end - q) < 0.061
    sigma = np.linalg.svd(robot.jacobian(q), compute_uv=False)[-1]
    tight = I.numerical_interval(robot, q, I.NumericalOptions(max_steps=3, sigma_min=sigma * (1 - 1e-6)))
    singular = [
        (end, q_end)
        for end, cause, q_end in ((tight.lo, tight.lo_cause, tight.lo_q), (tight.hi, tight.hi_cause, tight.hi_q))
        if cause == I.Cause("singular", -1)
    ]
    assert len(singular) == 1
    end, q_end = singular[0]
    assert np.linalg.svd(robot.jacobian(q_end), compute_uv=False)[-1] < sigma * (1 - 1e-6)
    assert E.arm_angle(robot, q_end) == pytest.approx(end, abs=1e-12)
    assert np.abs(robot.tool_pose(q_end).homogeneous - pose.homogeneous).max() < 1e-9


@pytest.mark.parametrize("side", ["min", "max"])
def test_a_joint_out_of_its_limits_at_every_arm_angle_empties_its_arcs(side: str) -> None:
    """Joint 4 of an S-R-S arm keeps its angle along the self-motion, so its Ψ_4 [E 7] has no limit crossing:
    it is the full circle when joint 4 is inside its limits and empty when it is outside, on either side
    (here the LWR4+ at q4 = −70° with joint 4's limit moved 10° past it). Checked against the closed-form IK
    sampled over the circle."""
    import copy

    robot = load_robot("lwr4p")
    q = np.radians([10, 40, -10, -70, 20, 50, 0])
    pose, b = robot.tool_pose(q), S.branch(robot, q)
    _, per = I.feasible_intervals(robot, pose, b, per_joint=True)
    assert per[3] == [(-math.pi, math.pi)]
    narrowed = copy.copy(robot)
    narrowed.q_min, narrowed.q_max = robot.q_min.copy(), robot.q_max.copy()
    if side == "min":
        narrowed.q_min[3] = np.radians(-60)
    else:
        narrowed.q_max[3] = np.radians(-80)
    psi, per = I.feasible_intervals(narrowed, pose, b, per_joint=True)
    assert per[3] == [] and psi == []
    joints = S.ik(robot, pose, np.linspace(-math.pi, math.pi, 73), b)
    assert np.allclose(joints[:, 3], q[3], atol=1e-9)  # the sampled self-motion: q4 never moves


@pytest.mark.parametrize(("inside", "beyond", "limit"), [(0.2, 1.2, 1.0), (-0.2, -1.2, -1.0), (1.0, 1.5, 1.0)])
def test_the_limit_fraction_is_where_the_chord_meets_the_limit(inside: float, beyond: float, limit: float) -> None:
    """From a point inside its limit (or on it), the fraction is where ``inside + t·(beyond − inside)`` equals the
    limit, found here by bisection."""
    lo, hi = 0.0, 1.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        past = (inside + mid * (beyond - inside) - limit) * (beyond - limit) > 0
        lo, hi = (lo, mid) if past else (mid, hi)
    assert I._limit_fraction(inside, beyond, limit) == pytest.approx(0.5 * (lo + hi), abs=1e-12)


def test_a_crossing_from_a_start_past_its_limit_is_at_the_start_without_warnings(robot: Robot, rng) -> None:
    """A walk may start up to ``check_q``'s 1e-9 rad past a limit (a controller's measured q).  A step that leaves
    that joint where it was has it past the limit at both ends of the chord: its fraction is 0 (the walk is at the
    limit already), not a division by its zero motion (a divide-by-zero RuntimeWarning in ``_crossing``, issue 31)
    nor a negative fraction.  Run with warnings as errors; the answer keeps the start's tool pose with that joint
    on its limit and names it."""
    import warnings

    q_in = _regular_qs(robot, rng, 1, margin=0.2)[0]
    q_in[2] = robot.q_max[2] + 5e-10  # (accepted by check_q: within its 1e-9 rad)
    robot.check_q(q_in)
    target = robot.tool_pose(q_in)
    q_out = q_in.copy()
    q_out[0] = robot.q_max[0] + 0.01  # another joint past its limit; joint 2 unmoved, past at both ends
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        walk = I._crossing(robot, q_in, q_out, target, 1e-12)
        try:
            while True:
                next(walk)
        except StopIteration as done:
            q, cause = done.value
    assert cause == I.Cause("limit", 2, "max") and q[2] == robot.q_max[2]
    err = (robot.tool_pose(q).inverse() * target).homogeneous - np.eye(4)
    assert np.abs(err).max() < 1e-9
