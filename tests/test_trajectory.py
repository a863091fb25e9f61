"""Tests of qpnso.control.trajectory: validation, CSV I/O, sampling, generators."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from conftest import SOURCE_TREE
from scipy.spatial.transform import Rotation

from qpnso.control.trajectory import (
    COLUMNS,
    PARABOLA_AXES,
    Trajectory,
    guidance_path,
    hold,
    min_jerk,
    point_to_point,
    read_csv,
    write_csv,
)
from qpnso.errors import TrajectoryError

DOWN = pin.utils.rotate("x", np.pi)  # tool z-axis pointing down
EXAMPLES = SOURCE_TREE / "examples" / "trajectories"


def random_traj(n: int = 12, seed: int = 0) -> Trajectory:
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.05, 0.2, n))
    p = rng.normal(size=(n, 3)) * 0.1
    # a smooth rotation path: small random steps, so slerp intervals are < π
    rotvecs = np.cumsum(rng.normal(size=(n, 3)) * 0.3, axis=0)
    q = Rotation.from_rotvec(rotvecs).as_quat()
    return Trajectory(t, p, q)


def write_text(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "traj.csv"
    path.write_text(text)
    return path


# ------------------------------------------------------------------ conventions


def test_quaternion_order_matches_pinocchio():
    r = pin.utils.rotate("z", 0.7) @ pin.utils.rotate("x", 0.3)
    traj = Trajectory([0.0, 1.0], np.zeros((2, 3)), np.tile(pin.Quaternion(r).coeffs(), (2, 1)))
    np.testing.assert_allclose(traj.sample(0.5)[1], r, atol=1e-12)
    np.testing.assert_allclose(pin.SE3ToXYZQUAT(pin.SE3(r, np.zeros(3)))[3:], traj.quaternion[0], atol=1e-12)


def test_validation_normalises_and_fixes_signs():
    q = Rotation.from_rotvec([[0, 0, 0.1 * k] for k in range(4)]).as_quat()
    q[2] *= -1.0  # same rotation, opposite sign
    q[1] *= 1.0005  # within tolerance: normalised
    traj = Trajectory(np.arange(4.0), np.zeros((4, 3)), q)
    np.testing.assert_allclose(np.linalg.norm(traj.quaternion, axis=1), 1.0, atol=1e-15)
    assert np.all(np.einsum("ij,ij->i", traj.quaternion[1:], traj.quaternion[:-1]) > 0)
    np.testing.assert_allclose(
        Rotation.from_quat(traj.quaternion).as_matrix(), Rotation.from_quat(q).as_matrix(), atol=1e-12
    )


@pytest.mark.parametrize(
    "case, pattern",
    [
        ("unsorted", "row 3"),
        ("repeated", "row 3.*repeats"),
        ("nan", "row 2 is not finite"),
        ("norm", "row 4 has norm"),
        ("short", "at least 2"),
        ("shape", r"shape \(N, 3\)"),
    ],
)
def test_validation_errors_name_the_row(case, pattern):
    t, p, q = np.arange(5.0), np.zeros((5, 3)), np.tile([0, 0, 0, 1.0], (5, 1))
    if case == "unsorted":
        t[2] = 0.5
    elif case == "repeated":
        t[2] = t[1]
    elif case == "nan":
        p[1, 2] = np.nan
    elif case == "norm":
        q[3] = [0, 0, 0, 1.01]
    elif case == "short":
        t, p, q = t[:1], p[:1], q[:1]
    elif case == "shape":
        p = np.zeros((5, 2))
    with pytest.raises(TrajectoryError, match=pattern):
        Trajectory(t, p, q)


# ------------------------------------------------------------------ CSV


def test_csv_round_trip_exact(tmp_path):
    traj = random_traj()
    path = write_csv(traj, tmp_path / "a.csv")
    assert path.read_text().splitlines()[0] == ",".join(COLUMNS)
    back = read_csv(path)
    for name in ("t", "position", "quaternion"):
        np.testing.assert_array_equal(getattr(back, name), getattr(traj, name))
    assert [p.name for p in tmp_path.iterdir()] == ["a.csv"]  # no temporary left


def test_csv_any_column_order_and_trailing_blank_lines(tmp_path):
    path = write_text(tmp_path, "qw,t,z,y,x,qx,qy,qz\n1,0,3,2,1,0,0,0\n1,0.5,3,2,1.5,0,0,0\n\n")
    traj = read_csv(path)
    np.testing.assert_array_equal(traj.position, [[1, 2, 3], [1.5, 2, 3]])
    np.testing.assert_array_equal(traj.quaternion[:, 3], [1, 1])


HEADER = "t,x,y,z,qx,qy,qz,qw\n"
GOOD = "0,0,0,0,0,0,0,1\n"


@pytest.mark.parametrize(
    "text, pattern",
    [
        ("", "empty file"),
        ("t,x,y,z,qx,qy,qw\n" + GOOD, "missing column.*'qz'"),
        (HEADER.replace("qw", "qw,speed") + "0,0,0,0,0,0,0,1,3\n", "unknown column 'speed'"),
        ("t,x,y,z,qx,qy,qz,qw,x\n", "'x' appears more than once"),
        (HEADER + GOOD + "0.1,0,abc,0,0,0,0,1\n", "data row 2, column 'y': cannot parse 'abc'"),
        (HEADER + GOOD + "0.1,0,0,nan,0,0,0,1\n", "data row 2, column 'z'.*not finite"),
        (HEADER + GOOD + "0.1,inf,0,0,0,0,0,1\n", "data row 2, column 'x'.*not finite"),
        (HEADER + GOOD + "0.2,0,0,0,0,0,0,1\n0.1,0,0,0,0,0,0,1\n", "data row 3 .*earlier than data row 2"),
        (HEADER + GOOD + "0,0,0,0,0,0,0,1\n", "data row 2 .*repeats data row 1"),
        (HEADER + GOOD + "0.1,0,0,0,0,0,0,0.9\n", "quaternion of data row 2 has norm 0.9"),
        (HEADER + GOOD, "at least 2 samples"),
        (HEADER, "at least 2 samples"),
        (HEADER + GOOD + "0.1,0,0\n", "data row 2 has 3 fields"),
        (HEADER + GOOD + "\n0.1,0,0,0,0,0,0,1\n", "data row 2 has 0 fields"),
    ],
)
def test_malformed_csv_names_row_or_column(tmp_path, text, pattern):
    path = write_text(tmp_path, text)
    with pytest.raises(TrajectoryError, match=pattern) as info:
        read_csv(path)
    assert str(path) in str(info.value)


def test_missing_file(tmp_path):
    with pytest.raises(TrajectoryError, match="not found"):
        read_csv(tmp_path / "nope.csv")


def test_failed_writes_leave_nothing(tmp_path):
    traj = random_traj()
    (tmp_path / "taken").mkdir()
    with pytest.raises(TrajectoryError, match="directory"):
        write_csv(traj, tmp_path / "taken")
    with pytest.raises(TrajectoryError, match="does not exist"):
        write_csv(traj, tmp_path / "no" / "x.csv")
    with pytest.raises(TrajectoryError, match="needs a Trajectory"):
        write_csv("not a trajectory", tmp_path / "x.csv")
    broken = random_traj()
    object.__setattr__(broken, "position", np.full((len(broken), 3), np.nan))  # bypass validation
    with pytest.raises(TrajectoryError, match="not finite"):
        write_csv(broken, tmp_path / "x.csv")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken"]


def test_failure_during_write_removes_temporary(tmp_path, monkeypatch):
    def fail(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", fail)
    with pytest.raises(OSError, match="disk full"):
        write_csv(random_traj(), tmp_path / "x.csv")
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------ sampling


def test_sample_hits_the_samples():
    traj = random_traj()
    for k in range(len(traj)):
        p, r, _, _ = traj.sample(traj.t[k])
        np.testing.assert_allclose(p, traj.position[k], atol=1e-12)
        np.testing.assert_allclose(r, Rotation.from_quat(traj.quaternion[k]).as_matrix(), atol=1e-12)


def test_velocities_are_derivatives_of_the_pose():
    traj = random_traj()
    h = 1e-6
    rng = np.random.default_rng(1)
    for t in rng.uniform(traj.t[0] + h, traj.t[-1] - h, 40):
        p0, r0, v, w = traj.sample(t)
        p1, r1, _, _ = traj.sample(t + h)
        pm, rm, _, _ = traj.sample(t - h)
        np.testing.assert_allclose(v, (p1 - pm) / (2 * h), rtol=1e-5, atol=1e-6)
        # world-frame angular velocity: R(t+h) = exp(h ω) R(t), on the same interval
        k = np.searchsorted(traj.t, t, side="right") - 1
        if traj.t[k] < t - h and t + h < traj.t[k + 1]:
            np.testing.assert_allclose(w, pin.log3(r1 @ r0.T) / h, rtol=1e-6, atol=1e-8)
            np.testing.assert_allclose(w, pin.log3(r0 @ rm.T) / h, rtol=1e-6, atol=1e-8)


def test_sample_is_clamped_outside():
    traj = random_traj()
    for t, k in ((traj.t[0] - 1.0, 0), (traj.t[-1] + 1.0, -1)):
        p, r, v, w = traj.sample(t)
        np.testing.assert_array_equal(p, traj.position[k])
        np.testing.assert_array_equal(v, np.zeros(3))
        np.testing.assert_array_equal(w, np.zeros(3))
    pose = traj.pose(traj.t[-1] + 1.0)
    assert isinstance(pose, pin.SE3)
    np.testing.assert_array_equal(pose.translation, traj.position[-1])
    with pytest.raises(TrajectoryError):
        traj.sample(np.nan)


def test_linear_data_gives_constant_velocity():
    t = np.linspace(0, 1, 6)
    p = np.outer(t, [0.1, -0.2, 0.3])
    traj = Trajectory(t, p, np.tile([0, 0, 0, 1.0], (6, 1)))
    for s in (0.0, 0.13, 0.5, 1.0):
        np.testing.assert_allclose(traj.sample(s)[2], [0.1, -0.2, 0.3], atol=1e-12)


# ------------------------------------------------------------------ generators


def test_min_jerk_closed_form():
    tau = np.linspace(0, 1, 101)
    s, ds = min_jerk(tau)
    h = 1e-6
    np.testing.assert_allclose(ds[1:-1], (min_jerk(tau[1:-1] + h)[0] - min_jerk(tau[1:-1] - h)[0]) / (2 * h), atol=1e-7)
    assert s[0] == 0 and s[-1] == 1 and ds[0] == 0 and ds[-1] == 0
    assert np.max(ds) == pytest.approx(1.875)


def speeds(traj: Trajectory) -> np.ndarray:
    return np.linalg.norm(np.diff(traj.position, axis=0), axis=1) / np.diff(traj.t)


def test_guidance_path_shape_and_limits():
    c = np.array([0.5, 0.0, 0.45])
    traj = guidance_path(c, size=0.08, speed=0.05, orientation=DOWN, dt=0.01)
    np.testing.assert_allclose(np.diff(traj.t), 0.01, atol=1e-12)
    np.testing.assert_allclose(traj.position[0], c, atol=1e-15)
    np.testing.assert_allclose(traj.position[-1], c, atol=1e-15)
    assert speeds(traj).max() <= 0.05
    assert speeds(traj).max() > 0.047  # and the speed budget is used
    # size: lemniscate tips at ±size/2; parabola ends at (size/2)(±e1 + e2), √2·size/2 from the centre
    assert np.max(np.linalg.norm(traj.position - c, axis=1)) <= np.sqrt(2) * 0.04 + 1e-15
    assert np.max(np.linalg.norm(traj.position - c, axis=1)) > np.sqrt(2) * 0.04 * (1 - 1e-4)
    # continuous: bounded steps; smooth: second and third differences small
    acc = np.diff(traj.position, n=2, axis=0) / 0.01**2
    jerk = np.diff(traj.position, n=3, axis=0) / 0.01**3
    assert np.linalg.norm(acc, axis=1).max() < 0.2  # m/s²
    assert np.linalg.norm(jerk, axis=1).max() < 2.0  # m/s³ (bounded at segment joints)
    # it passes through the centre at rest 5 times (start, 3 joins, end)
    at_rest = np.flatnonzero((np.linalg.norm(traj.position - c, axis=1) < 1e-12))
    assert {0, len(traj) - 1} <= set(at_rest) and len(at_rest) >= 5
    # the four segments: planar x-y, x-z, y-z figures, then the tilted parabola
    joins = sorted(set(at_rest))
    seg = [traj.position[a : b + 1] - c for a, b in zip(joins[:-1], joins[1:]) if b > a + 1]
    assert len(seg) == 4
    for s, flat in zip(seg[:3], (2, 1, 0)):
        assert np.max(np.abs(s[:, flat])) < 1e-15 and np.ptp(s[:, (flat + 1) % 3]) > 0.01
    e1, e2 = PARABOLA_AXES
    u = seg[3] @ e1 / 0.04
    np.testing.assert_allclose(seg[3] @ e2, 0.04 * u**2, atol=1e-12)
    np.testing.assert_allclose(seg[3] @ np.cross(e1, e2), 0.0, atol=1e-12)
    np.testing.assert_allclose(traj.quaternion, np.tile(pin.Quaternion(DOWN).coeffs(), (len(traj), 1)), atol=1e-12)


def test_lemniscate_is_bernoulli():
    traj = guidance_path(np.zeros(3), size=0.2, speed=0.1, orientation=np.eye(3), dt=0.01)
    xy = traj.position[: np.flatnonzero(np.abs(traj.position[1:, 2]) > 0)[0]][:, :2]
    a = 0.1
    r2 = np.sum(xy**2, axis=1)
    # (x² + y²)² = a² (x² − y²)
    np.testing.assert_allclose(r2**2, a**2 * (xy[:, 0] ** 2 - xy[:, 1] ** 2), atol=1e-15)
    assert np.max(xy[:, 0]) == pytest.approx(a, rel=1e-4) and np.min(xy[:, 0]) == pytest.approx(-a, rel=1e-4)


def test_guidance_orientation_sources_and_errors():
    pose = pin.SE3(DOWN, np.array([0.5, 0.0, 0.45]))
    a = guidance_path(pose, size=0.05, speed=0.1)
    b = guidance_path(pose.translation, size=0.05, speed=0.1, orientation=pin.Quaternion(DOWN).coeffs())
    np.testing.assert_allclose(a.quaternion, b.quaternion, atol=1e-12)
    np.testing.assert_array_equal(a.position, b.position)
    with pytest.raises(TrajectoryError, match="orientation is required"):
        guidance_path([0, 0, 0])
    with pytest.raises(TrajectoryError, match="rotation matrix"):
        guidance_path([0, 0, 0], orientation=np.ones((3, 3)))
    with pytest.raises(TrajectoryError, match="speed must be positive"):
        guidance_path(pose, speed=0.0)


def test_point_to_point_moves():
    targets = np.array([[0.5, 0, 0.4], [0.6, 0, 0.4], [0.6, 0.1, 0.45], [0.5, 0.05, 0.4]])
    traj = point_to_point(targets, peak_speed=0.1, dwell=0.3, lift=0.02, orientation=DOWN, dt=0.01)
    np.testing.assert_allclose(traj.position[0], targets[0])
    np.testing.assert_allclose(traj.position[-1], targets[-1])
    assert 0.095 < speeds(traj).max() <= 0.1
    for k, target in enumerate(targets[1:-1], start=1):  # dwell of 0.3 s at each intermediate target
        still = np.flatnonzero(np.linalg.norm(traj.position - target, axis=1) < 1e-12)
        assert len(still) == 31 and np.all(np.diff(still) == 1)
    # first move: chord plus parabola of height 0.02 m at mid-way (z up)
    first = traj.position[: np.flatnonzero(np.linalg.norm(traj.position - targets[1], axis=1) < 1e-12)[0] + 1]
    sigma = (first[:, 0] - 0.5) / 0.1
    np.testing.assert_allclose(first[:, 2], 0.4 + 0.08 * sigma * (1 - sigma), atol=1e-12)
    assert np.max(first[:, 2]) == pytest.approx(0.42, abs=1e-5)


def test_point_to_point_minimum_jerk_profile():
    traj = point_to_point([[0, 0, 0], [0.2, 0, 0]], duration_per_move=2.0, lift=0.0, orientation=np.eye(3), dt=0.01)
    assert traj.duration == pytest.approx(2.0)
    tau = traj.t / 2.0
    np.testing.assert_allclose(traj.position[:, 0], 0.2 * (10 * tau**3 - 15 * tau**4 + 6 * tau**5), atol=1e-15)
    assert speeds(traj).max() == pytest.approx(1.875 * 0.2 / 2.0, rel=1e-3)  # bell, peak 1.875× mean


def test_point_to_point_errors():
    with pytest.raises(TrajectoryError, match="exactly one"):
        point_to_point([[0, 0, 0], [1, 0, 0]], orientation=np.eye(3))
    with pytest.raises(TrajectoryError, match="targets 2 and 3 coincide"):
        point_to_point([[0, 0, 0], [1, 0, 0], [1, 0, 0]], peak_speed=0.1, lift=0.0, orientation=np.eye(3))
    with pytest.raises(TrajectoryError, match="at least 2"):
        point_to_point([[0, 0, 0]], peak_speed=0.1, orientation=np.eye(3))


def test_hold():
    pose = pin.SE3(DOWN, np.array([0.5, 0.0, 0.45]))
    traj = hold(pose, 2.0)
    assert len(traj) == 201 and traj.duration == pytest.approx(2.0)
    p, r, v, w = traj.sample(0.737)
    np.testing.assert_allclose(p, pose.translation, atol=1e-15)
    np.testing.assert_allclose(r, DOWN, atol=1e-12)
    assert np.all(v == 0) and np.all(w == 0)


# ------------------------------------------------------------------ shipped files


@pytest.mark.parametrize("name", ["guidance_lwr4p.csv", "hold_lwr4p.csv"])
def test_shipped_files(name):
    """The shipped paths are scenario A's pose (elbow-up start, far from limits), as generated."""
    from qpnso.lab.scenarios import load_scenario

    path = EXAMPLES / name
    assert path.stat().st_size < 400_000
    traj = read_csv(path)
    pose = load_scenario("A").tool_pose()
    np.testing.assert_allclose(traj.position[0], pose.translation, atol=1e-9)
    np.testing.assert_allclose(traj.position[-1], pose.translation, atol=1e-9)
    np.testing.assert_allclose(traj.sample(1.0)[1], pose.rotation, atol=1e-9)
    np.testing.assert_allclose(np.diff(traj.t), 0.01, atol=1e-9)
    if name.startswith("guidance"):
        regenerated = guidance_path(pose, size=0.08, speed=0.05, dt=0.01)
        np.testing.assert_allclose(traj.position, regenerated.position, atol=1e-9)


def test_samples_are_the_spline_and_the_slerp() -> None:
    """``Trajectory.samples`` (``sample`` is one of them) against SciPy's own cubic spline (position and its
    derivative) and slerp (rotation) at random times inside, at the samples themselves, and clamped outside:
    the end poses with zero velocities, the first interval's velocities at ``t_0`` exactly."""
    from scipy.interpolate import CubicSpline
    from scipy.spatial.transform import Slerp

    traj = random_traj(12, seed=3)
    rng = np.random.default_rng(3)
    inside = np.concatenate([rng.uniform(traj.t[0], traj.t[-1], 500), traj.t[1:]])
    p, R, v, w = traj.samples(inside)
    spline = CubicSpline(traj.t, traj.position, axis=0)
    np.testing.assert_allclose(p, spline(inside), atol=1e-12)
    np.testing.assert_allclose(v, spline(inside, 1), atol=1e-10)
    slerp = Slerp(traj.t, Rotation.from_quat(traj.quaternion))
    np.testing.assert_allclose(R, slerp(inside).as_matrix(), atol=1e-12)
    k = np.clip(np.searchsorted(traj.t, inside, side="right") - 1, 0, len(traj) - 2)
    dR = (Rotation.from_matrix(traj.rotation[k + 1]) * Rotation.from_matrix(traj.rotation[k]).inv()).as_rotvec()
    np.testing.assert_allclose(w, dR / np.diff(traj.t)[k][:, None], atol=1e-10)  # world frame, per interval
    outside = np.array([traj.t[0] - 1.0, traj.t[-1] + 1.0, traj.t[0]])
    p, R, v, w = traj.samples(outside)
    np.testing.assert_array_equal(p[:2], traj.position[[0, -1]])
    np.testing.assert_array_equal(R[:2], traj.rotation[[0, -1]])
    np.testing.assert_array_equal(v[:2], 0.0)
    np.testing.assert_array_equal(w[:2], 0.0)
    np.testing.assert_allclose(v[2], spline(traj.t[0], 1), atol=1e-10)
    for t, sample in zip(outside, zip(p, R, v, w)):
        for got, want in zip(traj.sample(t), sample):
            np.testing.assert_array_equal(got, want)
    with pytest.raises(TrajectoryError, match="finite"):
        traj.samples([0.0, np.nan])
