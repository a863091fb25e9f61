"""Segment–obstacle distances (qpnso.model.distance) against coal and against brute force over a fine grid
of the segment parameter t; the normal against finite differences (envelope theorem); special cases
(parallel, degenerate, touching, inside the box)."""

from __future__ import annotations

import coal
import numpy as np
import pytest
from hypothesis import given
from hypothesis import settings as hsettings
from hypothesis import strategies as st

from qpnso.model.distance import (
    BOX,
    CAPSULE,
    SPHERE,
    segment_box,
    segment_obstacle,
    segment_point,
    segment_segment,
)

KINDS = [SPHERE, CAPSULE, BOX]
GRID = np.linspace(0.0, 1.0, 20001)
STEP = GRID[1] - GRID[0]


# ------------------------------------------------------------------ helpers


def frame(u: np.ndarray) -> np.ndarray:
    """A rotation whose third column is u/|u| (coal capsules lie along their local z)."""
    u = u / np.linalg.norm(u)
    h = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(h, u)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(u, x), u])


def coal_segment(a: np.ndarray, b: np.ndarray):
    """The segment a–b as a zero-radius coal capsule and its placement."""
    return coal.Capsule(0.0, float(np.linalg.norm(b - a))), coal.Transform3s(frame(b - a), 0.5 * (a + b))


def coal_obstacle(kind: int, c, e, R, half, r):
    if kind == SPHERE:
        return coal.Sphere(r), coal.Transform3s(np.eye(3), c)
    if kind == CAPSULE:
        return coal.Capsule(r, float(np.linalg.norm(e - c))), coal.Transform3s(frame(e - c), 0.5 * (c + e))
    return coal.Box(2.0 * half), coal.Transform3s(R, c)


def coal_distance(a, b, kind, c, e, R, half, r) -> float:
    g1, T1 = coal_segment(a, b)
    g2, T2 = coal_obstacle(kind, c, e, R, half, r)
    return float(coal.distance(g1, T1, g2, T2, coal.DistanceRequest(), coal.DistanceResult()))


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    Q, Rr = np.linalg.qr(rng.normal(size=(3, 3)))
    Q = Q * np.sign(np.diag(Rr))
    if np.linalg.det(Q) < 0:
        Q[:, 0] = -Q[:, 0]
    return Q


def random_case(rng: np.random.Generator, spread: float = 2.0):
    """Segment a, b; obstacle center c, second point e, rotation R, half extents, radius."""
    a, b = rng.normal(size=3), rng.normal(size=3)
    c, e = spread * rng.normal(size=3), spread * rng.normal(size=3)
    return a, b, c, e, random_rotation(rng), rng.uniform(0.1, 0.6, 3), float(rng.uniform(0.05, 0.3))


def points_to_obstacle(x: np.ndarray, kind: int, c, e, R, half, r) -> np.ndarray:
    """Distance (surface, r subtracted; box: outside distance, 0 inside) from the points x (N, 3), NumPy."""
    if kind == SPHERE:
        return np.linalg.norm(x - c, axis=1) - r
    if kind == CAPSULE:
        d = e - c
        dd = d @ d
        s = np.clip((x - c) @ d / dd, 0.0, 1.0) if dd > 0 else np.zeros(len(x))
        return np.linalg.norm(x - (c + s[:, None] * d), axis=1) - r
    xl = (x - c) @ R
    return np.linalg.norm(xl - np.clip(xl, -half, half), axis=1)


def box_margin(x: np.ndarray, c, R, half) -> np.ndarray:
    """min_i (h_i − |x_i|) in the box frame: > 0 inside, the depth of each point."""
    return np.min(half - np.abs((x - c) @ R), axis=1)


def on_grid(a, b, t=GRID) -> np.ndarray:
    t = np.atleast_1d(t)
    return a + t[:, None] * (b - a)


def call(a, b, kind, c, e, R, half, r):
    dist, t, n0, n1, n2 = segment_obstacle(a, b, kind, c, e, R, half, r)
    return dist, t, np.array([n0, n1, n2])


def grid_tolerance(a, b, dist) -> float:
    """Bound on (grid min − exact min) of a distance g(t) to a convex set: g'' ≤ |b − a|²/g, |g'| ≤ |b − a|."""
    ab = float(np.linalg.norm(b - a))
    return min(ab * STEP / 2, ab**2 * STEP**2 / (8.0 * max(dist, 1e-300))) + 1e-12


# ------------------------------------------------------------------ against coal


@pytest.mark.parametrize("kind", KINDS)
def test_matches_coal_outside(kind):
    rng = np.random.default_rng(100 + kind)
    checked = 0
    for _ in range(300):
        case = random_case(rng)
        a, b, c, e, R, half, r = case
        dc = coal_distance(*case[:2], kind, *case[2:])
        if dc < 1e-3:
            continue
        dist, t, n = call(a, b, kind, c, e, R, half, r)
        assert dist == pytest.approx(dc, abs=1e-7)
        assert 0.0 <= t <= 1.0
        checked += 1
    assert checked > 250


def test_box_intersecting_matches_coal_sign():
    """Segments through or into the box: dist ≤ 0, and coal's penetration depth (a translation that separates
    them) is at least the depth of the segment's deepest point, so coal's signed distance ≤ ours."""
    rng = np.random.default_rng(7)
    inside = 0
    for _ in range(300):
        c = rng.normal(size=3)
        R, half = random_rotation(rng), rng.uniform(0.2, 0.8, 3)
        a = c + rng.uniform(-1.2, 1.2, 3) * half
        b = c + rng.uniform(-2.0, 2.0, 3)
        e = np.zeros(3)
        dc = coal_distance(a, b, BOX, c, e, R, half, 0.0)
        dist, t, n = call(a, b, BOX, c, e, R, half, 0.5)  # radius ignored for boxes
        if dc < -1e-6:
            inside += 1
            assert dist <= 0.0
            assert dc - 1e-6 <= dist
            assert np.linalg.norm(n) == pytest.approx(1.0, abs=1e-12)
            assert np.max(np.abs(R.T @ n)) == pytest.approx(1.0, abs=1e-12)  # a face normal
        elif dc > 1e-6:
            assert dist == pytest.approx(dc, abs=1e-7)
    assert inside > 100


# ------------------------------------------------------------------ against brute force


@pytest.mark.parametrize("kind", KINDS)
def test_matches_brute_force(kind):
    rng = np.random.default_rng(200 + kind)
    checked = 0
    for _ in range(150):
        a, b, c, e, R, half, r = random_case(rng)
        dist, t, n = call(a, b, kind, c, e, R, half, r)
        g = points_to_obstacle(on_grid(a, b), kind, c, e, R, half, r)
        core = dist + (r if kind != BOX else 0.0)
        if core < 1e-3:
            continue
        assert dist <= g.min() + 1e-12  # the exact minimum is a lower bound of every sample
        assert g.min() - dist <= grid_tolerance(a, b, core)
        witness = points_to_obstacle(on_grid(a, b, t), kind, c, e, R, half, r)[0]
        assert witness == pytest.approx(dist, abs=1e-12)  # the distance is attained at t
        checked += 1
    assert checked > 120


def test_box_depth_matches_brute_force():
    rng = np.random.default_rng(300)
    checked = 0
    for _ in range(150):
        c, R, half = rng.normal(size=3), random_rotation(rng), rng.uniform(0.2, 0.8, 3)
        a = c + R @ (rng.uniform(-1.5, 1.5, 3) * half)
        b = c + R @ (rng.uniform(-1.5, 1.5, 3) * half)
        dist, t, n0, n1, n2 = segment_box(a, b, c, R, half)
        m = box_margin(on_grid(a, b), c, R, half)
        if m.max() <= 1e-3:
            continue
        slope = np.max(np.abs(R.T @ (b - a)))
        assert dist == pytest.approx(-m.max(), abs=slope * STEP / 2 + 1e-12)
        assert -dist >= m.max() - 1e-12  # the exact maximum is an upper bound of every sample
        assert box_margin(on_grid(a, b, t), c, R, half)[0] == pytest.approx(-dist, abs=1e-12)
        checked += 1
    assert checked > 100


# ------------------------------------------------------------------ normal: envelope theorem


@pytest.mark.parametrize("kind", KINDS)
def test_normal_is_gradient(kind):
    rng = np.random.default_rng(400 + kind)
    h = 1e-6
    checked = 0
    for _ in range(100):
        a, b, c, e, R, half, r = random_case(rng)
        dist, t, n = call(a, b, kind, c, e, R, half, r)
        if dist + (r if kind != BOX else 0.0) < 0.05:
            continue
        assert np.linalg.norm(n) == pytest.approx(1.0, abs=1e-12)
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)

        def fd(da, db):
            plus = call(a + h * da, b + h * db, kind, c, e, R, half, r)[0]
            minus = call(a - h * da, b - h * db, kind, c, e, R, half, r)[0]
            return (plus - minus) / (2 * h)

        zero = np.zeros(3)
        assert fd(u, u) == pytest.approx(n @ u, abs=1e-6)
        assert fd(u, zero) == pytest.approx((1 - t) * (n @ u), abs=1e-6)
        assert fd(zero, u) == pytest.approx(t * (n @ u), abs=1e-6)
        checked += 1
    assert checked > 60


# ------------------------------------------------------------------ special cases


def v(*xs) -> np.ndarray:
    return np.array(xs, dtype=float)


def test_segment_point_cases():
    a, b = v(0, 0, 0), v(2, 0, 0)
    dist, t, *n = segment_point(a, b, v(1, 3, 0))
    assert (dist, t, n) == (pytest.approx(3.0), pytest.approx(0.5), pytest.approx([0, -1, 0]))
    dist, t, *n = segment_point(a, b, v(-1, 0, 0))  # beyond a: t clamped to 0
    assert (dist, t, n) == (pytest.approx(1.0), 0.0, pytest.approx([1, 0, 0]))
    dist, t, *n = segment_point(a, b, v(3, 0, 4))  # beyond b
    assert (dist, t, n) == (pytest.approx(np.sqrt(17)), 1.0, pytest.approx(np.array([-1, 0, -4]) / np.sqrt(17)))
    # The point on the segment: distance 0, a unit normal perpendicular to the segment.
    dist, t, *n = segment_point(a, b, v(0.7, 0, 0))
    assert dist == 0.0 and t == pytest.approx(0.35)
    assert np.linalg.norm(n) == pytest.approx(1.0) and abs(n[0]) < 1e-15
    # Degenerate segment a = b: the point–point distance; the point itself: any unit normal.
    dist, t, *n = segment_point(a, a, v(0, 2, 0))
    assert (dist, t, n) == (pytest.approx(2.0), 0.0, pytest.approx([0, -1, 0]))
    dist, t, *n = segment_point(a, a, a)
    assert dist == 0.0 and np.linalg.norm(n) == pytest.approx(1.0) and np.all(np.isfinite(n))


def test_segment_segment_parallel():
    a, b = v(0, 0, 0), v(1, 0, 0)
    # Overlapping, either direction, or ce covering ab: distance 1, n from ce (y = 1) toward ab: −y.
    for c, e in [(v(0.5, 1, 0), v(2, 1, 0)), (v(2, 1, 0), v(0.5, 1, 0)), (v(-1, 1, 0), v(3, 1, 0))]:
        dist, t, *n = segment_segment(a, b, c, e)
        assert dist == pytest.approx(1.0, abs=1e-15)
        assert n == pytest.approx([0, -1, 0])
        assert a[0] + t >= min(c[0], e[0]) - 1e-15 and a[0] + t <= max(c[0], e[0]) + 1e-15
    # Disjoint along the axis: end to end.
    dist, t, *n = segment_segment(a, b, v(2, 1, 0), v(3, 1, 0))
    assert (dist, t) == (pytest.approx(np.sqrt(2)), 1.0)
    assert n == pytest.approx(np.array([-1, -1, 0]) / np.sqrt(2))
    dist, t, *n = segment_segment(a, b, v(-3, 1, 0), v(-2, 1, 0))
    assert (dist, t) == (pytest.approx(np.sqrt(5)), 0.0)
    # Collinear, overlapping: distance 0, unit normal perpendicular to the segment.
    dist, t, *n = segment_segment(a, b, v(0.5, 0, 0), v(2, 0, 0))
    assert dist == 0.0 and np.linalg.norm(n) == pytest.approx(1.0) and abs(n[0]) < 1e-15


def test_segment_segment_nearly_parallel():
    rng = np.random.default_rng(500)
    for angle in [1e-4, 1e-7, 1e-9, 1e-12, 0.0]:
        for _ in range(20):
            a, b = rng.normal(size=3), rng.normal(size=3)
            d = b - a
            w = np.cross(d, rng.normal(size=3))
            w /= np.linalg.norm(w)
            c = a + rng.uniform(-1, 1) * d + rng.uniform(0.1, 1) * w
            e = c + rng.uniform(-1.5, 1.5) * (d + angle * np.linalg.norm(d) * np.cross(w, d) / np.linalg.norm(d))
            dist, t, *n = segment_segment(a, b, c, e)
            g = points_to_obstacle(on_grid(a, b), CAPSULE, c, e, None, None, 0.0)
            assert dist <= g.min() + 1e-12
            assert g.min() - dist <= grid_tolerance(a, b, dist)
            assert points_to_obstacle(on_grid(a, b, t), CAPSULE, c, e, None, None, 0.0)[0] == pytest.approx(
                dist, abs=1e-12
            )


def test_segment_segment_degenerate_and_crossing():
    a, b = v(0, 0, 0), v(1, 0, 0)
    dist, t, *n = segment_segment(a, b, v(0.5, 2, 0), v(0.5, 2, 0))  # ce a point
    assert (dist, t, n) == (pytest.approx(2.0), pytest.approx(0.5), pytest.approx([0, -1, 0]))
    dist, t, *n = segment_segment(a, a, v(-1, 1, 0), v(1, 1, 0))  # ab a point
    assert (dist, t, n) == (pytest.approx(1.0), 0.0, pytest.approx([0, -1, 0]))
    dist, t, *n = segment_segment(a, a, v(0, 0, 3), v(0, 0, 3))  # both points
    assert (dist, t, n) == (pytest.approx(3.0), 0.0, pytest.approx([0, 0, -1]))
    dist, t, *n = segment_segment(a, a, a, a)
    assert dist == 0.0 and np.linalg.norm(n) == pytest.approx(1.0) and np.all(np.isfinite(n))
    # Crossing segments: distance 0, normal along (b − a) × (e − c).
    dist, t, *n = segment_segment(a, b, v(0.25, -1, 0), v(0.25, 1, 0))
    assert dist == 0.0 and t == pytest.approx(0.25)
    assert np.abs(n) == pytest.approx([0, 0, 1])


def test_box_touching_and_near():
    c, R, half = v(0, 0, 0), np.eye(3), v(1, 1, 1)
    dist, t, *n = segment_box(v(1, -0.5, 0), v(1, 0.5, 0.2), c, R, half)  # lying on the face x = 1
    assert dist == pytest.approx(0.0, abs=1e-15) and n == pytest.approx([1, 0, 0])
    dist, t, *n = segment_box(v(2, 0.3, 0.1), v(1, 0.3, 0.1), c, R, half)  # touching with its end b
    assert dist == pytest.approx(0.0, abs=1e-15) and t == 1.0 and n == pytest.approx([1, 0, 0])
    dist, t, *n = segment_box(v(1 + 1e-9, -0.5, 0), v(1 + 1e-9, 0.5, 0.2), c, R, half)  # just off the face
    assert dist == pytest.approx(1e-9, rel=1e-6) and n == pytest.approx([1, 0, 0])
    dist, t, *n = segment_box(v(2, 2, 0), v(2, 2, 5), c, R, half)  # nearest an edge of the box
    assert dist == pytest.approx(np.sqrt(2)) and n == pytest.approx(np.array([1, 1, 0]) / np.sqrt(2))
    assert 0.0 <= t <= 0.2 + 1e-15
    dist, t, *n = segment_box(v(3, 3, 3), v(2, 2, 2), c, R, half)  # nearest a corner, from b
    assert (dist, t) == (pytest.approx(np.sqrt(3)), 1.0) and n == pytest.approx(np.ones(3) / np.sqrt(3))


def test_box_inside():
    rng = np.random.default_rng(600)
    R, c, half = random_rotation(rng), v(0.3, -0.2, 1.0), v(1, 2, 3)
    # Wholly inside: the deepest point is a (margin 0.8 to the face +x), normal the face's outward normal.
    dist, t, *n = segment_box(c + R @ v(0.2, 0, 0), c + R @ v(0.6, 0.5, 0), c, R, half)
    assert (dist, t, n) == (pytest.approx(-0.8), pytest.approx(0.0, abs=1e-15), pytest.approx(R[:, 0]))
    # Through the box along x at y = 0.5 (box frame): deepest at x = 0, margin min(1 − |x|, 2 − 0.5, 3) = 1.
    dist, t, *n = segment_box(c + R @ v(-3, 0.5, 0), c + R @ v(3, 0.5, 0), c, R, half)
    assert dist == pytest.approx(-1.0) and abs(-3 + 6 * t) <= 1e-12
    assert np.abs(n) == pytest.approx(np.abs(R[:, 0]))
    # At y = 1.8 the margin 0.2 of the face +y binds all along |x| ≤ 0.8 (ends tied with the faces ±x).
    dist, t, *n = segment_box(c + R @ v(-3, 1.8, 0), c + R @ v(3, 1.8, 0), c, R, half)
    assert dist == pytest.approx(-0.2) and n == pytest.approx(R[:, 1])
    assert abs(-3 + 6 * t) <= 0.8 + 1e-12
    # A point (degenerate segment) inside and outside.
    dist, t, *n = segment_box(c + R @ v(0.1, -1.5, 2), c + R @ v(0.1, -1.5, 2), c, R, half)
    assert (dist, t, n) == (pytest.approx(-0.5), 0.0, pytest.approx(-R[:, 1]))
    dist, t, *n = segment_box(c + R @ v(0.1, -2.5, 2), c + R @ v(0.1, -2.5, 2), c, R, half)
    assert (dist, t, n) == (pytest.approx(0.5), 0.0, pytest.approx(-R[:, 1]))


def test_obstacle_dispatch():
    a, b = v(0, 0, 0), v(1, 0, 0)
    R, half, e = np.eye(3), v(0.5, 0.5, 0.5), v(0, 0, 0)
    assert segment_obstacle(a, b, SPHERE, v(0.5, 2, 0), e, R, half, 0.5)[0] == pytest.approx(1.5)
    assert segment_obstacle(a, b, SPHERE, v(0.5, 0.2, 0), e, R, half, 0.5)[0] == pytest.approx(-0.3)
    assert segment_obstacle(a, b, CAPSULE, v(0.5, 2, -1), v(0.5, 2, 1), R, half, 0.25)[0] == pytest.approx(1.75)
    assert segment_obstacle(a, b, BOX, v(0.5, 2, 0), e, R, half, 9.0)[0] == pytest.approx(1.5)  # radius ignored
    with pytest.raises(ValueError):
        segment_obstacle(a, b, 7, v(0.5, 2, 0), e, R, half, 0.5)


# ------------------------------------------------------------------ lattice configurations (ties, touching)

coord = st.integers(-3, 3).map(float)
point = st.tuples(coord, coord, coord).map(np.array)


@hsettings(max_examples=150, deadline=None)
@given(a=point, b=point, c=point, e=point, half=st.tuples(*[st.integers(1, 2).map(float)] * 3).map(np.array))
def test_lattice_cases(a, b, c, e, half):
    """Integer coordinates: parallel, collinear, degenerate, touching and crossing configurations."""
    x = on_grid(a, b)
    for kind in KINDS:
        dist, t, n = call(a, b, kind, c, e, np.eye(3), half, 0.0)
        assert np.all(np.isfinite([dist, t, *n])) and 0.0 <= t <= 1.0
        assert np.linalg.norm(n) == pytest.approx(1.0, abs=1e-12)
        g = points_to_obstacle(x, kind, c, e, np.eye(3), half, 0.0)
        at_t = points_to_obstacle(on_grid(a, b, t), kind, c, e, np.eye(3), half, 0.0)[0]
        if dist > 0.0:
            assert dist <= g.min() + 1e-12 and at_t == pytest.approx(dist, abs=1e-12)
            assert g.min() - dist <= grid_tolerance(a, b, dist)
        else:
            assert g.min() <= np.linalg.norm(b - a) * STEP
            if kind == BOX:
                m = box_margin(x, c, np.eye(3), half)
                assert -dist >= m.max() - 1e-12
                assert -dist <= m.max() + np.linalg.norm(b - a) * STEP
