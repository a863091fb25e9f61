"""Tests of qpnso.qp (the hierarchical QP) against an independent sequential reference (equality form,
exact active-set solvers)."""

from __future__ import annotations

import numpy as np
import pytest
import qpsolvers
from hypothesis import given
from hypothesis import settings as hsettings
from hypothesis import strategies as st
from scipy.optimize import linprog

from qpnso.errors import InputError, SolverError
from qpnso.qp import HierarchicalQP, Level, LevelStatus, QPSettings
from qpnso.qp.cascade import level_parts
from qpnso.qp.cascade_state import LEVEL_ADVANCED, LEVEL_VIOLATED, CascadeState, check_level, state_arrays
from qpnso.qp.levels import _validate_level
from qpnso.qp.settings import tolerance_record

N = 7
BACKENDS = ["proxsuite", "daqp", "quadprog"]
DELTA = 1e-10  # reference's Tikhonov term on x where a level is not strictly convex


# ---------------------------------------------------------------- reference


def cascade_on(levels, lb, ub, settings=QPSettings()):
    """A cascade record started under ``lb ≤ x ≤ ub`` for ``levels``, and their parts as its kernels take them."""
    n = lb.shape[0]
    data = [_validate_level(level, n, f"levels[{k}]") for k, level in enumerate(levels)]
    rows = sum(0 if d.C is None else d.C.shape[0] for d in data)
    state = CascadeState(n, rows, max(d.n_slack for d in data), tolerance_record(settings))
    state.start(lb, ub)
    return state, [level_parts(d, n) for d in data]


def _ref_level(P, q, lb, ub, eq, ineq, solver="quadprog"):
    """min ½xᵀPx + qᵀx (x may be extended by slacks) s.t. equalities, two-sided rows, bounds."""
    G, h = [], []
    for C, lo, hi in ineq:
        fu, fl = np.isfinite(hi), np.isfinite(lo)
        G += [C[fu], -C[fl]]
        h += [hi[fu], -lo[fl]]
    A = np.vstack([e[0] for e in eq]) if eq else None
    b = np.concatenate([e[1] for e in eq]) if eq else None
    x = qpsolvers.solve_qp(
        P, q, np.vstack(G) if G else None, np.concatenate(h) if h else None, A, b, lb=lb, ub=ub, solver=solver
    )
    assert x is not None, "reference solve failed"
    return x


def reference(levels: list[Level], lb, ub, solver="quadprog", band: float = 0.0):
    """Lexicographic solution, level by level, in the *equality* form (independent of the
    null-space implementation): a higher task's A_j x is fixed to its optimal value; its
    soft rows keep their optimal slack; its hard rows stay; pure (H, g) levels keep their
    optimal value through Lᵀx fixed (H = LLᵀ) and gᵀx fixed.  Returns x after each level.
    ``band > 0``: a task's value is kept within ±band instead of exactly (with active bounds the
    exact equality form leaves a degenerate feasible set that the solvers reject)."""
    eq, ineq, xs = [], [], []
    for level in levels:
        ns = 0 if level.C is None or level.slack_weight is None else level.C.shape[0]
        P = np.zeros((N + ns, N + ns))
        q = np.zeros(N + ns)
        if level.A is not None:
            P[:N, :N] += 2 * level.A.T @ level.A
            q[:N] -= 2 * level.A.T @ level.b
        if level.H is not None:
            P[:N, :N] += level.H
        if level.g is not None:
            q[:N] += level.g
        P[:N, :N] += DELTA * np.eye(N)
        if ns:
            P[N:, N:] = 2 * level.slack_weight * np.eye(ns)
        pad = lambda M: np.hstack([M, np.zeros((M.shape[0], ns))])  # noqa: E731
        eq_k = [(pad(A), b) for A, b in eq]
        ineq_k = [(pad(C), lo, hi) for C, lo, hi in ineq]
        if level.C is not None:
            C = np.hstack([level.C, np.eye(ns)]) if ns else level.C
            ineq_k.append((C, level.l, level.u))
        v = _ref_level(P, q, np.r_[lb, -1e9 * np.ones(ns)], np.r_[ub, 1e9 * np.ones(ns)], eq_k, ineq_k, solver)
        x = v[:N]
        xs.append(x)
        if level.A is not None and band > 0:
            ineq.append((level.A, level.A @ x - band, level.A @ x + band))
        elif level.A is not None:
            eq.append((level.A, level.A @ x))
        if level.H is not None:
            w, V = np.linalg.eigh(level.H)
            L = V[:, w > 1e-9]
            if L.shape[1]:
                eq.append((L.T, L.T @ x))
        if level.C is not None:
            cx = level.C @ x
            ineq.append((level.C, np.minimum(level.l, cx), np.maximum(level.u, cx)))
    return xs


# ----------------------------------------------------------------- problems
def random_problem(seed: int, m1: int = 6, bound: float = 1.0, v_scale: float = 0.3):
    rng = np.random.default_rng(seed)
    while True:
        J = rng.standard_normal((m1, N))
        if np.linalg.svd(J, compute_uv=False).min() > 0.05:  # away from the damping threshold
            break
    M = rng.standard_normal((N, N))
    H = M @ M.T / N + 0.5 * np.eye(N)
    C = rng.standard_normal((2, N))
    lo = np.array([-0.05, -np.inf])
    hi = np.array([0.05, 0.02])
    levels = [
        Level(A=J, b=v_scale * rng.standard_normal(m1)),
        Level(H=H, g=rng.standard_normal(N), C=C, l=lo, u=hi, slack_weight=1e3),
    ]
    return levels, -bound * np.ones(N), bound * np.ones(N)


def level_cost(level: Level, x: np.ndarray) -> float:
    cost = 0.0
    if level.A is not None:
        cost += float(np.sum((level.A @ x - level.b) ** 2))
    if level.H is not None:
        cost += 0.5 * float(x @ level.H @ x)
    if level.g is not None:
        cost += float(level.g @ x)
    return cost


def assert_lexicographic(res, levels, lb, ub, xs_ref, tol_x=1e-6):
    assert res.ok, res.status
    assert np.all(np.isfinite(res.x))
    assert np.all(res.x >= lb - 1e-8) and np.all(res.x <= ub + 1e-8)
    np.testing.assert_allclose(res.x, xs_ref[-1], atol=tol_x)
    for k, level in enumerate(levels):
        if level.A is not None:  # lower levels do not change a higher task's residual
            r_final = np.linalg.norm(level.A @ res.x - level.b)
            assert abs(r_final - res.levels[k].residual) < 1e-9
            assert abs(r_final - np.linalg.norm(level.A @ xs_ref[k] - level.b)) < 1e-6


# -------------------------------------------------------------------- tests
FAST = [pytest.param(True, id="line"), pytest.param(False, id="cascade")]
LINE_MESSAGE = "closed form"


@pytest.mark.parametrize("fast", FAST)
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("seed", range(6))
def test_two_levels_match_sequential_reference(backend, seed, fast):
    levels, lb, ub = random_problem(seed)
    res = HierarchicalQP(N, backend=backend, settings=QPSettings(line_fast_path=fast)).solve(levels, lb, ub)
    assert_lexicographic(res, levels, lb, ub, reference(levels, lb, ub))
    assert [lv.status for lv in res.levels] == [LevelStatus.SOLVED] * 2
    exact = res.levels[0].residual < 1e-9  # the line of exact tool solutions meets the bounds
    assert (LINE_MESSAGE in res.levels[0].message) == (fast and exact)


@pytest.mark.parametrize("backend", BACKENDS)
def test_active_bounds_at_level_one(backend):
    levels, lb, ub = random_problem(11, bound=0.2, v_scale=3.0)
    res = HierarchicalQP(N, backend=backend).solve(levels, lb, ub)
    active = np.isclose(res.levels[0].x, lb, atol=1e-7) | np.isclose(res.levels[0].x, ub, atol=1e-7)
    assert active.sum() >= 2 and res.levels[0].residual > 1e-2  # the bounds bite at level 1
    assert LINE_MESSAGE not in res.levels[0].message  # the line misses the bounds: the general cascade
    assert_lexicographic(res, levels, lb, ub, reference(levels, lb, ub))


@pytest.mark.parametrize("backend", BACKENDS)
def test_three_levels_with_psd_middle_level(backend):
    """Level 2 has a rank-2 H and a g in its range: level 3 must not raise its cost."""
    rng = np.random.default_rng(3)
    J = rng.standard_normal((3, N))
    L = rng.standard_normal((N, 2))
    levels = [
        Level(A=J, b=0.2 * rng.standard_normal(3)),
        Level(H=L @ L.T, g=L @ rng.standard_normal(2)),
        Level(H=np.eye(N), g=rng.standard_normal(N)),
    ]
    lb, ub = -0.5 * np.ones(N), 0.5 * np.ones(N)
    res = HierarchicalQP(N, backend=backend).solve(levels, lb, ub)
    assert_lexicographic(res, levels, lb, ub, reference(levels, lb, ub))
    assert abs(level_cost(levels[1], res.x) - level_cost(levels[1], res.levels[1].x)) < 1e-9


def test_linear_middle_level_keeps_its_optimum():
    """A pure linear level (an LP over the null space, blocked by bounds) owns its gradient
    direction: checked against an exact LP (HiGHS) and an equality-form final level."""
    rng = np.random.default_rng(5)
    J = rng.standard_normal((4, N))
    b = 0.1 * rng.standard_normal(4)
    g2 = rng.standard_normal(N)
    g3 = rng.standard_normal(N)
    lb, ub = -0.3 * np.ones(N), 0.3 * np.ones(N)
    levels = [Level(A=J, b=b), Level(g=g2), Level(H=np.eye(N), g=g3)]
    res = HierarchicalQP(N, backend="daqp").solve(levels, lb, ub)
    assert res.ok, res.status
    x1 = reference(levels[:1], lb, ub)[0]
    lp = linprog(g2, A_eq=J, b_eq=J @ x1, bounds=list(zip(lb, ub)), method="highs")
    assert abs(g2 @ res.x - lp.fun) < 1e-8
    x3 = _ref_level(np.eye(N), g3, lb, ub, [(J, J @ x1), (g2[None], np.array([lp.fun]))], [], "quadprog")
    np.testing.assert_allclose(res.x, x3, atol=1e-6)


@pytest.mark.parametrize("backend", BACKENDS)
def test_three_levels_two_tasks(backend):
    rng = np.random.default_rng(8)
    levels = [
        Level(A=rng.standard_normal((3, N)), b=0.2 * rng.standard_normal(3)),
        Level(A=rng.standard_normal((2, N)), b=0.2 * rng.standard_normal(2), weight=np.array([1.0, 4.0])),
        Level(H=np.diag(rng.uniform(0.5, 2, N)), g=rng.standard_normal(N)),
    ]
    lb, ub = -0.4 * np.ones(N), 0.4 * np.ones(N)
    ref_levels = [
        levels[0],
        Level(A=np.array([[1.0], [2.0]]) * levels[1].A, b=np.array([1.0, 2.0]) * levels[1].b),
        levels[2],
    ]
    res = HierarchicalQP(N, backend=backend).solve(levels, lb, ub)
    xs = reference(ref_levels, lb, ub)
    np.testing.assert_allclose(res.x, xs[-1], atol=1e-6)
    assert abs(np.linalg.norm(levels[0].A @ res.x - levels[0].b) - res.levels[0].residual) < 1e-9
    assert abs(np.linalg.norm(levels[1].A @ res.x - levels[1].b) - res.levels[1].residual) < 1e-9


@pytest.mark.parametrize("backend", BACKENDS)
def test_rank_deficient_task_two_equal_rows(backend):
    levels, lb, ub = random_problem(4)
    J = levels[0].A.copy()
    J[1] = J[0]
    b = levels[0].b.copy()
    b[1] = b[0] + 0.1  # inconsistent rows: the residual cannot vanish
    levels[0] = Level(A=J, b=b)
    res = HierarchicalQP(N, backend=backend).solve(levels, lb, ub)
    assert res.levels[0].residual > 0.05
    assert_lexicographic(res, levels, lb, ub, reference(levels, lb, ub))
    # the exactly null direction is free for level 2: x differs from level 1's in a 2-D null space
    assert np.linalg.norm(res.x - res.levels[0].x) > 1e-3


def test_near_singular_task_is_damped_in_closed_form():
    """σ < ε is damped to curvature ε² (gain σ/ε²), σ ≥ ε untouched: closed-form damped pseudo-inverse."""
    rng = np.random.default_rng(2)
    U, _ = np.linalg.qr(rng.standard_normal((6, 6)))
    V, _ = np.linalg.qr(rng.standard_normal((N, N)))
    sigma = np.array([2.0, 1.0, 0.5, 0.2, 3e-3, 1e-4])
    J = U @ np.diag(sigma) @ V[:, :6].T
    b = rng.standard_normal(6)
    eps = 1e-2
    hqp = HierarchicalQP(N, backend="daqp", settings=QPSettings(damping_threshold=eps))
    res = hqp.solve([Level(A=J, b=b), Level(H=np.eye(N), g=rng.standard_normal(N))])
    assert LINE_MESSAGE not in res.levels[0].message  # damped directions: no line fast path
    expected = V[:, :6] @ (sigma / np.maximum(sigma, eps) ** 2 * (U.T @ b))
    np.testing.assert_allclose(res.levels[0].x, expected, atol=1e-7)
    assert np.abs(res.levels[0].x).max() < np.linalg.norm(b) / eps
    # damped directions stay owned by level 1: its residual is unchanged by level 2
    assert abs(np.linalg.norm(J @ res.x - b) - res.levels[0].residual) < 1e-9


@pytest.mark.parametrize("backend", BACKENDS)
def test_weighted_overdetermined_task_closed_form(backend):
    rng = np.random.default_rng(6)
    A, b, w = rng.standard_normal((9, N)), rng.standard_normal(9), rng.uniform(0.5, 3, 9)
    res = HierarchicalQP(N, backend=backend).solve([Level(A=A, b=b, weight=w)])
    x = np.linalg.solve(A.T @ (w[:, None] * A), A.T @ (w * b))
    np.testing.assert_allclose(res.x, x, atol=1e-7)


@pytest.mark.parametrize("fast", FAST)
@pytest.mark.parametrize("backend", BACKENDS)
def test_infeasible_soft_rows_take_slack(backend, fast):
    levels, lb, ub = random_problem(7)
    J = levels[0].A
    c = levels[0].A[0] + 0.5 * levels[0].A[1]  # a row of J: C x is fixed by level 1
    level2 = Level(
        H=np.eye(N),
        g=np.zeros(N),
        C=np.vstack([c, -c]),
        l=np.array([5.0, 5.0]),
        u=np.array([np.inf, np.inf]),
        slack_weight=1e4,
    )  # c·x >= 5 and c·x <= -5
    hqp = HierarchicalQP(N, backend=backend, settings=QPSettings(line_fast_path=fast))
    res = hqp.solve([Level(A=J, b=levels[0].b), level2], lb, ub)
    assert res.ok and np.all(np.isfinite(res.x))
    assert np.all(res.levels[1].slack > 1.0)
    np.testing.assert_allclose(res.levels[1].slack, np.maximum(level2.l - level2.C @ res.x, 0), atol=1e-9)
    assert_lexicographic(res, [levels[0], level2], lb, ub, reference([Level(A=J, b=levels[0].b), level2], lb, ub))


@pytest.mark.parametrize("fast", FAST)
@pytest.mark.parametrize("backend", BACKENDS)
def test_hard_infeasible_level_two_falls_back_to_level_one(backend, fast):
    levels, lb, ub = random_problem(1)
    bad = Level(H=np.eye(N), C=np.eye(N)[:1], l=np.array([5.0]), u=np.array([6.0]))  # x0 >= 5 > ub
    res = HierarchicalQP(N, backend=backend, settings=QPSettings(line_fast_path=fast)).solve([levels[0], bad], lb, ub)
    assert not res.ok and res.failed_level == 1
    assert res.levels[1].status is not LevelStatus.SOLVED and "level 2" in res.status
    assert np.all(np.isfinite(res.x))
    np.testing.assert_array_equal(res.x, res.levels[0].x)


@pytest.mark.parametrize("backend", BACKENDS)
def test_hard_infeasible_level_one_gives_no_x(backend):
    bad = Level(A=np.eye(N), b=np.zeros(N), C=np.ones((1, N)), l=np.array([100.0]), u=np.array([200.0]))
    hqp = HierarchicalQP(N, backend=backend)
    res = hqp.solve([bad, Level(H=np.eye(N))], -np.ones(N), np.ones(N))
    assert not res.ok and res.x is None and res.failed_level == 0
    assert res.levels[1].status is LevelStatus.SKIPPED
    assert hqp.stats.failures == 1
    # the next, feasible tick recovers (a failed ProxSuite result is not used as warm start)
    ok = hqp.solve([Level(A=np.eye(N), b=0.1 * np.ones(N)), Level(H=np.eye(N))], -np.ones(N), np.ones(N))
    assert ok.ok
    np.testing.assert_allclose(ok.x, 0.1 * np.ones(N), atol=1e-7)


def _sequence(T: int, seed: int = 0):
    levels, lb, ub = random_problem(seed, bound=0.25)
    rng = np.random.default_rng(seed + 100)
    dJ, dg = rng.standard_normal(levels[0].A.shape), rng.standard_normal(N)
    for t in range(T):
        s = np.sin(2 * np.pi * t / T)
        yield (
            [
                Level(A=levels[0].A + 0.05 * s * dJ, b=levels[0].b * (1 + s)),
                Level(
                    H=levels[1].H,
                    g=levels[1].g + s * dg,
                    C=levels[1].C,
                    l=levels[1].l,
                    u=levels[1].u,
                    slack_weight=levels[1].slack_weight,
                ),
            ],
            lb,
            ub,
        )


@pytest.mark.parametrize("fast", FAST)
def test_warm_started_proxsuite_matches_cold_and_daqp(fast):
    warm = HierarchicalQP(N, settings=QPSettings(line_fast_path=fast))
    cold = HierarchicalQP(N, settings=QPSettings(warm_start=False, line_fast_path=fast))
    exact = HierarchicalQP(N, backend="daqp", settings=QPSettings(line_fast_path=fast))
    for levels, lb, ub in _sequence(60):
        xw, xc, xe = (h.solve(levels, lb, ub) for h in (warm, cold, exact))
        assert xw.ok and xc.ok and xe.ok
        np.testing.assert_allclose(xw.x, xc.x, atol=1e-6)
        np.testing.assert_allclose(xw.x, xe.x, atol=1e-6)


def test_qp_objects_created_once_per_level_and_shape():
    hqp = HierarchicalQP(N, settings=QPSettings(line_fast_path=False))
    seq = list(_sequence(100))
    hqp.solve(*seq[0])
    assert hqp.stats.qp_created == 2
    for p in seq:
        assert hqp.solve(*p).ok
    assert hqp.stats.qp_created == 2 and hqp.stats.solves == 101
    levels, lb, ub = seq[0]
    no_rows = [levels[0], Level(H=levels[1].H, g=levels[1].g)]  # level 2 changes shape (elbow dropped)
    hqp.solve(no_rows, lb, ub)
    assert hqp.stats.qp_created == 3
    hqp.solve(levels, lb, ub)
    hqp.solve(no_rows, lb, ub)
    assert hqp.stats.qp_created == 3  # both shapes are kept, no re-allocation when toggling


def test_build_level_qp_is_the_level_objective():
    """The built QP of level 2, evaluated at z, equals the level's cost at x = x1 + Z z (up to a constant)."""
    levels, lb, ub = random_problem(0)
    hqp = HierarchicalQP(N, settings=QPSettings(regularization=0.0))
    res = hqp.solve(levels, lb, ub)
    state, parts = cascade_on(levels, lb, ub)
    qp1, _ = state.build(parts[0])
    assert qp1.C.shape == (0, N) and qp1.box_l.shape == (N,)  # the bounds as a box on z
    state.advance(parts[0], res.levels[0].x)
    Z, x1 = state.Z, state.x
    assert Z.shape == (N, 1)  # a full-rank 6×7 task leaves one direction
    np.testing.assert_allclose(Z.T @ Z, np.eye(1), atol=1e-14)
    np.testing.assert_allclose(levels[0].A @ Z, 0, atol=1e-12)
    np.testing.assert_array_equal(x1, res.levels[0].x)
    qp2, _ = state.build(parts[1])
    assert qp2.H.shape == (1 + 2, 1 + 2) and qp2.C.shape == (2 + N, 1 + 2) and qp2.box_l.shape == (0,)
    np.testing.assert_allclose(qp2.C[-N:, :1], Z)  # the bounds as rows Z z
    np.testing.assert_allclose(qp2.l[-N:], lb - x1)
    rng = np.random.default_rng(0)
    vals = []
    for _ in range(3):
        v = np.r_[rng.standard_normal(1), 0, 0]  # zero slack
        vals.append(0.5 * v @ qp2.H @ v + qp2.g @ v - level_cost(levels[1], x1 + Z @ v[:1]))
    np.testing.assert_allclose(vals, vals[0], atol=1e-9)


def _controller_ticks(T: int, seed: int = 21, v_scale: float = 0.4):
    """Controller-like ticks: 6×7 tool Jacobian, soft 1×7 elbow row (ρ = 1e6), tight finite joint
    velocity bounds, level 2 in the three forms the controller uses."""
    rng = np.random.default_rng(seed)
    J0, dJ = rng.standard_normal((6, N)), 0.1 * rng.standard_normal((6, N))
    v0, row = v_scale * rng.standard_normal(6), rng.standard_normal((1, N))
    lb, ub = -0.35 * np.ones(N), 0.3 * np.ones(N)
    for t in range(T):
        s = np.sin(0.3 * t)
        J, v = J0 + s * dJ, v0 * (1 + 0.5 * s)
        g = rng.standard_normal(N)
        elbow = Level(H=np.eye(N), g=g, C=row, l=np.array([-0.02]), u=np.array([0.01]), slack_weight=1e6)
        second = [elbow, Level(A=np.eye(N), b=0.2 * g), Level(A=row, b=np.array([0.05]))][t % 3 if t >= 6 else 0]
        yield [Level(A=J, b=v), second], lb, ub


@pytest.mark.parametrize("fast", FAST)
def test_controller_problem_fast_form_matches_reference(fast):
    """The per-tick problem of the controller: level 2 is solved in the one-direction null-space
    basis (fast form) — on the line of level 1's exact solutions or through the general cascade —
    warm-started, with and without input checks; answers match the independent equality-form
    reference, the tool task's residual is preserved, bounds bind."""
    settings = QPSettings(line_fast_path=fast)
    hqp = HierarchicalQP(N, settings=settings)
    trusted = HierarchicalQP(N, settings=settings)
    n_active = n_line = 0
    for levels, lb, ub in _controller_ticks(24):
        res = hqp.solve(levels, lb, ub)
        assert_lexicographic(res, levels, lb, ub, _banded_reference(levels, lb, ub))
        np.testing.assert_allclose(trusted.solve(levels, lb, ub, check=False).x, res.x, atol=1e-9)
        n_active += int(np.any(np.isclose(res.x, lb, atol=1e-7) | np.isclose(res.x, ub, atol=1e-7)))
        n_line += int(LINE_MESSAGE in res.levels[0].message)
        if levels[1].slack_weight is not None:
            np.testing.assert_allclose(res.levels[1].slack, _soft_violation(levels[1], res.x), atol=1e-9)
        state, parts = cascade_on(levels, lb, ub, hqp.settings)
        state.build(parts[0])
        state.advance(parts[0], res.levels[0].x)
        assert state.Z.shape == (N, 1)  # level 2 has one free variable (plus its slack)
    assert n_active >= 12  # the bounds bite on most ticks
    assert hqp.stats.failures == 0
    # the tool asks more than the bounds allow: level 1, and level 2 as (z, σ) with 8 rows or as z
    # with the 7 bound rows (A = I and A = row alike), in the general cascade
    assert n_line == 0 and hqp.stats.qp_created == 3


@pytest.mark.parametrize("seed", [21, 22, 23])
def test_line_fast_path_matches_the_general_cascade(seed):
    """Controller-like ticks whose tool motion the bounds allow: the line form is taken, gives the
    reference's answer like the general cascade and DAQP on the line, its level 1 is the least-norm
    exact solution, and no QP object is created once every shape has been seen."""
    line, general = HierarchicalQP(N), HierarchicalQP(N, settings=QPSettings(line_fast_path=False))
    exact = HierarchicalQP(N, backend="daqp")
    ticks = list(_controller_ticks(30, seed=seed, v_scale=0.1))
    n_line = 0
    for levels, lb, ub in ticks:
        a, b, c = line.solve(levels, lb, ub), general.solve(levels, lb, ub), exact.solve(levels, lb, ub)
        assert a.ok and b.ok and c.ok, (a.status, b.status, c.status)
        np.testing.assert_allclose(a.x, b.x, atol=1e-6)
        np.testing.assert_allclose(a.x, c.x, atol=1e-6)
        assert_lexicographic(a, levels, lb, ub, _banded_reference(levels, lb, ub))
        if LINE_MESSAGE in a.levels[0].message:
            n_line += 1
            x_min = np.linalg.pinv(levels[0].A) @ levels[0].b
            if np.all(x_min >= lb) and np.all(x_min <= ub):
                np.testing.assert_allclose(a.levels[0].x, x_min, atol=1e-12)
    assert n_line >= 10  # (the others: a bound cuts the line, the general cascade runs)
    created = line.stats.qp_created
    for levels, lb, ub in ticks:
        line.solve(levels, lb, ub)
    assert line.stats.qp_created == created <= 2 + 3  # line shapes: (t, σ) with one row, t alone


def _banded_reference(levels, lb, ub):
    """The exact equality form is degenerate with bounds this active: the tool task is held to
    ±1e-10; quadprog and DAQP (both exact active-set) each rejected a tick of the 24, never the same."""
    try:
        return reference(levels, lb, ub, solver="quadprog", band=1e-10)
    except AssertionError:
        return reference(levels, lb, ub, solver="daqp", band=1e-10)


def _soft_violation(level: Level, x: np.ndarray) -> np.ndarray:
    cx = level.C @ x
    return np.maximum(np.maximum(level.l - cx, cx - level.u), 0.0)


@hsettings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), m1=st.integers(1, 6))
def test_property_level_two_never_changes_level_one_residual(seed, m1):
    """Whatever level 2 does, level 1's residual stands; where ProxQP fails level 2 (a degenerate
    feasible set, see the next test), the cascade says so and keeps level 1's answer."""
    levels, lb, ub = random_problem(seed, m1=m1, bound=0.3, v_scale=1.0)
    res = HierarchicalQP(N).solve(levels, lb, ub)
    assert res.levels[0].ok, res.status
    assert res.ok or (
        res.failed_level == 1 and res.status.startswith("level 2 of 2") and np.array_equal(res.x, res.levels[0].x)
    )
    assert abs(np.linalg.norm(levels[0].A @ res.x - levels[0].b) - res.levels[0].residual) < 1e-9
    assert np.all(res.x >= lb - 1e-8) and np.all(res.x <= ub + 1e-8)


@pytest.mark.parametrize("seed, m1", [(412, 1), (2142, 2), (2898, 3)])
def test_degenerate_level_two_is_solved_or_reported_and_daqp_solves_it(seed, m1):
    """Level 1 pushed onto many joint bounds (7, 6 and 5 of 7 here) leaves level 2 a feasible set
    with no interior: ProxQP (warm, then cold) often stops at max_iter or reports it infeasible
    (about 0.3 % of these random problems, 7 of 2574 measured; not always the same ones from run
    to run), while DAQP solves the same cascade.  Either way level 1's residual is the same, and a
    failure is reported with level 1's answer kept (the controller's safe command), never hidden."""
    levels, lb, ub = random_problem(seed, m1=m1, bound=0.3, v_scale=1.0)
    prox = HierarchicalQP(N).solve(levels, lb, ub)
    exact = HierarchicalQP(N, backend="daqp").solve(levels, lb, ub)
    assert exact.ok and prox.levels[0].ok
    assert abs(exact.levels[0].residual - prox.levels[0].residual) < 1e-9
    if prox.ok:  # (seen in one process out of about ten, after thousands of iterations)
        assert np.all(prox.x >= lb - 1e-8) and np.all(prox.x <= ub + 1e-8)
    else:
        assert prox.failed_level == 1 and np.array_equal(prox.x, prox.levels[0].x)


# ---------------------------------------------------------------- bad input
GOOD = dict(A=np.ones((2, N)), b=np.zeros(2))


@pytest.mark.parametrize(
    "levels, lb, ub, name",
    [
        ([Level(A=np.ones((2, N + 1)), b=np.zeros(2))], None, None, r"levels\[0\]\.A"),
        ([Level(A=np.ones((2, N)), b=np.zeros(3))], None, None, r"levels\[0\]\.b"),
        ([Level(**GOOD), Level(A=np.full((2, N), np.nan), b=np.zeros(2))], None, None, r"levels\[1\]\.A.*NaN"),
        ([Level(**GOOD), Level(H=np.diag([np.inf] + [1.0] * (N - 1)))], None, None, r"levels\[1\]\.H.*inf"),
        ([Level(**GOOD, g=np.zeros(N - 1))], None, None, r"levels\[0\]\.g"),
        (
            [Level(C=np.ones((1, N)), l=np.array([1.0]), u=np.array([0.0]))],
            None,
            None,
            r"levels\[0\]\.l.*levels\[0\]\.u",
        ),
        ([Level(C=np.ones((1, N)), l=np.array([np.nan]), u=np.array([0.0]))], None, None, r"levels\[0\]\.l.*NaN"),
        (
            [Level(C=np.ones((1, N)), l=np.array([0.0]), u=np.array([0.0]), slack_weight=-1.0)],
            None,
            None,
            "slack_weight",
        ),
        ([Level(**GOOD, weight=-1.0)], None, None, "weight"),
        ([Level()], None, None, "empty"),
        ([], None, None, "levels"),
        ([Level(**GOOD)], np.ones(N), np.zeros(N), r"lb\[0\].*ub\[0\]"),
        ([Level(**GOOD)], np.zeros(N - 1), np.ones(N), "lb"),
        ([Level(**GOOD)], np.zeros(N), np.full(N, np.nan), r"ub.*NaN"),
    ],
)
def test_bad_input_raises_input_error(levels, lb, ub, name):
    with pytest.raises(InputError, match=name):
        HierarchicalQP(N).solve(levels, lb, ub)


def test_unknown_backend_raises_solver_error_listing_solvers():
    with pytest.raises(SolverError, match=r"nosuchsolver.*daqp"):
        HierarchicalQP(N, backend="nosuchsolver")
    with pytest.raises(InputError):
        HierarchicalQP(0)


def test_line_fast_path_any_width():
    """The line fast path has no size limit: a 70-joint arm with a 69-row task and a pure
    (H, g) second level matches the general cascade."""
    rng = np.random.default_rng(4)
    n = 70
    levels = [
        Level(A=rng.standard_normal((n - 1, n)), b=0.1 * rng.standard_normal(n - 1)),
        Level(H=np.eye(n), g=rng.standard_normal(n)),
    ]
    lb, ub = -10 * np.ones(n), 10 * np.ones(n)
    line = HierarchicalQP(n).solve(levels, lb, ub)
    general = HierarchicalQP(n, settings=QPSettings(line_fast_path=False)).solve(levels, lb, ub)
    assert line.ok and general.ok and LINE_MESSAGE in line.levels[0].message
    np.testing.assert_allclose(line.x, general.x, atol=1e-6)


@pytest.mark.parametrize("seed", range(20))
def test_strictly_convex_is_a_positive_definite_hessian_in_z(seed):
    """The last level's answer is taken as unique (no advance, no least-norm step) exactly when its
    Hessian in z has no eigenvalue at or below ``rank_tol·max(1, λ_max)`` (NumPy's eigenvalues)."""
    from qpnso.qp.cascade import strictly_convex

    rng = np.random.default_rng(seed)
    r = int(rng.integers(1, 6))
    B = rng.normal(size=(r, int(rng.integers(1, r + 2))))  # rank ≤ r: singular when it has fewer columns
    H = B @ B.T
    state, parts = cascade_on([Level(H=H)], -np.ones(r), np.ones(r))
    qp, _ = state.build(parts[0])
    eig = np.linalg.eigvalsh(H)
    assert strictly_convex(qp.H, r, 1e-10) == bool(eig[0] > 1e-10 * max(1.0, eig[-1]))


@pytest.mark.jit
def test_warm_up_loads_every_cascade_kernel_and_forgets(tmp_path):
    """After ``HierarchicalQP.warm_up`` in a new process, both the general cascade's and the line fast path's
    kernels are loaded (a control tick that first takes a path must not load or compile one: 30–60 ms): solves
    of other data on both paths then add no signature; and the solver is as new.  (From an empty cache a kernel
    that another kernel calls also holds the signature compiled for that caller: counts are compared, not 1.)"""
    import subprocess
    import sys

    code = """
import numpy as np
from qpnso.qp import Level, backends, cascade_state, line, results, solver
qp = solver.HierarchicalQP(7)
kernels = (cascade_state.build_level, cascade_state.finish_level, cascade_state.check_level, line.line_qp_arrays,
           line.checked_line_answer, line.task_line,
           line.least_norm_point, backends.qp_data_finite)
assert all(len(k.signatures) == 0 for k in kernels)
qp.warm_up()
loaded = [len(k.signatures) for k in kernels]
fresh = qp.stats == results.HQPStats() and qp._backend.qp_objects == 0
rng = np.random.default_rng(0)
A, lb, ub = rng.standard_normal((6, 7)), -np.ones(7), np.ones(7)
soft = dict(C=rng.standard_normal((1, 7)), l=-np.ones(1) * 0.1, u=np.ones(1) * 0.1, slack_weight=1e3)
line_path = qp.solve([Level(A=A, b=0.1 * rng.standard_normal(6)), Level(H=np.eye(7), g=rng.standard_normal(7), **soft)],
                     lb, ub)
general = qp.solve([Level(A=A[:3], b=0.1 * rng.standard_normal(3)), Level(A=A[3:5], b=np.zeros(2), **soft),
                    Level(g=rng.standard_normal(7))], lb, ub)
assert line_path.levels[0].iterations == 0 and general.levels[0].iterations > 0  # one of each path
print([k.__name__ for k, n in zip(kernels, loaded) if n == 0 or len(k.signatures) != n], fresh)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().splitlines()[-1] == "[] True"


@pytest.mark.parametrize("soft", [True, False])
@pytest.mark.parametrize("seed", range(6))
def test_a_level_answer_is_judged_in_joint_space(seed, soft):
    """The check of a level's answer (``check_level`` kernel) against joint space, by NumPy: ``x = x_prev + Z z``;
    accepted iff the joint bounds and the hard rows hold within ``feasibility_tol`` — or the bounds within
    ``bound_repair_tol``, x then clipped onto them and the hard rows holding there; a soft row's slack is its
    violation at the x accepted.  Answers perturbed across a bound or a row are refused, with their worst
    violation."""
    levels, lb, ub = random_problem(seed)
    levels[1].C = np.vstack([levels[1].C, np.random.default_rng(seed).standard_normal((1, N))])
    levels[1].l, levels[1].u = np.r_[levels[1].l, -0.3], np.r_[levels[1].u, 0.3]
    hqp = HierarchicalQP(N)
    res = hqp.solve(levels, lb, ub)
    if not soft:  # hard rows around the soft answer's row values: feasible, and bind within 0.05
        rows = levels[1].C @ res.x
        levels[1].l, levels[1].u, levels[1].slack_weight = rows - 0.05, rows + 0.05, None
        res = hqp.solve(levels, lb, ub)
    assert res.ok
    state, parts = cascade_on(levels, lb, ub, hqp.settings)
    state.build(parts[0])
    state.advance(parts[0], res.levels[0].x)
    x1, Z = state.x, state.Z
    qp2, _ = state.build(parts[1])
    n_slack = qp2.g.shape[0] - Z.shape[1]
    rng = np.random.default_rng(seed)
    tol, repair = hqp.settings.feasibility_tol, hqp.settings.bound_repair_tol
    a = state_arrays(state.record[0], state.buffer)
    lo, hi = a.lb.copy(), a.ub.copy()  # (the bounds level 2 inherits: level 1's answer passed down into them)
    outcomes, repaired = set(), 0
    z_star = Z.T @ (res.x - x1)  # the cascade's own answer: feasible
    for k in range(60):
        scale = 10.0 ** -rng.integers(0, 7)  # (down to 1e-6: within the repair tolerance of a bound)
        z = z_star + (0.0 if k == 0 else rng.uniform(-5.0, 5.0, 1) * scale)
        v = np.r_[z, np.zeros(n_slack)]
        x = x1 + Z @ z
        rows = levels[1].C @ x
        violation = np.maximum(levels[1].l - rows, rows - levels[1].u)
        off = max(np.max(lo - x), np.max(x - hi), 0.0)
        worst = max(off, -np.inf if soft else np.max(violation))
        accepted = x
        if tol < worst <= repair:  # projected onto the bounds, the hard rows judged there
            accepted = np.clip(x, lo, hi)
            rows = levels[1].C @ accepted
            violation = np.maximum(levels[1].l - rows, rows - levels[1].u)
            worst = max(0.0, -np.inf if soft else np.max(violation))
            repaired += 1
        feasible = bool(worst <= tol)
        code = check_level(state.record, state.buffer, parts[1], v, state.tol)
        assert (code == LEVEL_ADVANCED) == feasible, (x, code)
        outcomes.add(feasible)
        np.testing.assert_allclose(state.xk, accepted, atol=1e-12)
        if soft:
            np.testing.assert_allclose(state.slack[:n_slack], np.maximum(violation, 0.0), atol=1e-12)  # its violation
        if not feasible:
            assert code == LEVEL_VIOLATED and state.worst[0] == pytest.approx(worst, abs=1e-12)
    assert outcomes == {True, False}  # both kinds of answer were judged


def test_a_crossed_bound_is_named_by_its_own_index() -> None:
    """Bounds with lb ≤ ub except at index 3: the error names index 3 and its two values, not the first index."""
    lb, ub = np.zeros(N), np.ones(N)
    ub[3] = -1.0
    with pytest.raises(InputError, match=r"lb\[3\] = 0\.0 > ub\[3\] = -1\.0"):
        HierarchicalQP(N).solve([Level(**GOOD)], lb, ub)


def test_a_zero_task_weight_ignores_its_row() -> None:
    """Two rows ask x₀ = 1 and x₀ = 3: with weights (1, 0) the second row does not count (zero entries are
    allowed), so x₀ = 1; with (1, 1) the least-squares compromise is x₀ = 2; the other joints stay at 0."""
    A = np.zeros((2, N))
    A[:, 0] = 1.0
    b = np.array([1.0, 3.0])
    expected = np.zeros(N)
    for weight, x0 in ((np.array([1.0, 0.0]), 1.0), (np.array([1.0, 1.0]), 2.0)):
        res = HierarchicalQP(N).solve([Level(A=A, b=b, weight=weight)])
        expected[0] = x0
        assert res.ok
        np.testing.assert_allclose(res.x, expected, atol=1e-6)


def test_a_level_below_a_task_keeps_an_inherited_row_and_its_own_row() -> None:
    """Level 1: a 3-row task with one hard row; level 2: a cost with one hard row of its own.  Level 2's QP is
    in the null space of level 1's task (Z not the identity) with 1 inherited and 1 own row: the answer is the
    independent sequential reference's (equality form, quadprog)."""
    rng = np.random.default_rng(4)
    levels = [
        Level(
            A=rng.standard_normal((3, N)),
            b=0.1 * rng.standard_normal(3),
            C=rng.standard_normal((1, N)),
            l=np.array([-0.05]),
            u=np.array([0.05]),
        ),
        Level(
            H=np.eye(N), g=rng.standard_normal(N), C=rng.standard_normal((1, N)), l=np.array([-0.1]), u=np.array([0.1])
        ),
    ]
    lb, ub = -np.ones(N), np.ones(N)
    res = HierarchicalQP(N).solve(levels, lb, ub)
    assert res.ok
    np.testing.assert_allclose(res.x, reference(levels, lb, ub)[-1], atol=1e-6)


def test_line_segment_of_a_still_joint_outside_or_on_its_bound() -> None:
    """Joint 1 does not move along the line (d₁ = 0): x0₁ = 2 above ub₁ = 1 (or −2 below lb₁) leaves no segment;
    x0₁ exactly on ub₁ is within bounds, and the segment is then joint 0's [−1, 1]."""
    from qpnso.qp.line import line_segment

    lb, ub = -np.ones(2), np.ones(2)
    for x1 in (2.0, -2.0):
        t_lo, t_hi = line_segment(np.array([0.0, x1]), np.array([1.0, 0.0]), lb, ub)
        assert t_lo > t_hi
    assert line_segment(np.array([0.0, 1.0]), np.array([1.0, 0.0]), lb, ub) == (-1.0, 1.0)


def test_a_short_first_task_leaves_its_whole_null_space_to_level_two() -> None:
    """n = 3, level 1 asks only x₀ = 1 (one row, fewer than n − 1: no line of solutions but a plane); level 2 asks
    x = (5, 2, 3): the answer is x = (1, 2, 3) exactly, with or without the line fast path."""
    A1 = np.array([[1.0, 0.0, 0.0]])
    levels = [Level(A=A1, b=np.array([1.0])), Level(A=np.eye(3), b=np.array([5.0, 2.0, 3.0]))]
    for fast in (True, False):
        res = HierarchicalQP(3, settings=QPSettings(line_fast_path=fast)).solve(
            levels, -10 * np.ones(3), 10 * np.ones(3)
        )
        assert res.ok
        np.testing.assert_allclose(res.x, [1.0, 2.0, 3.0], atol=1e-6)


def test_level_answer_reports_the_violation_of_the_box() -> None:
    """An answer z = (2, −0.5, 0) against the box [−1, 1]³ on z (no rows): the worst violation is 2 − 1 = 1 (by
    hand); inside the box it is 0; x = x_prev + z (Z the identity)."""
    from qpnso.qp.arrays import Basis, QPArrays
    from qpnso.qp.cascade import level_answer

    n = 3
    qp = QPArrays(np.eye(n), np.zeros(n), np.zeros((0, n)), np.zeros(0), np.zeros(0), -np.ones(n), np.ones(n))
    basis = Basis(np.full(n, 0.5), np.eye(n), True, True)
    x, worst, slack = level_answer(np.array([2.0, -0.5, 0.0]), basis, qp, 0, 0)
    assert worst == pytest.approx(1.0) and slack.shape == (0,)
    np.testing.assert_allclose(x, [2.5, 0.0, 0.5])
    assert level_answer(np.array([0.9, -0.5, 0.0]), basis, qp, 0, 0)[1] == 0.0


@pytest.mark.parametrize("scale", [1e-3, 0.5, 1.0, 2.0, 1e3])
def test_a_hard_row_folds_into_the_line_whatever_its_scale(scale: float) -> None:
    """A hard row ``l ≤ C(x0 + t·d)`` that the line's direction moves slowly (C d = 1e-8·‖C‖, far above the
    1e-12·‖C‖ below which a row counts as still) with ``C x0`` 1e-9·‖C‖ below ``l``: the segment is narrowed to
    t ≥ 0.1 (by hand: (l − C x0)/(C d)), not emptied, and the same for the row scaled by any factor."""
    from qpnso.qp.line import fold_rows

    x0, d = np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0])
    C = scale * np.array([[1e-8, 1.0, 0.0]])  # C d = 1e-8·scale, C x0 = scale
    l, u = np.array([scale * (1.0 + 1e-9)]), np.array([np.inf])
    t_lo, t_hi = fold_rows(x0, d, -1.0, 1.0, C, l, u)
    assert t_lo == pytest.approx(0.1, rel=1e-6) and t_hi == 1.0
    # a row the direction does not move at all must hold at x0: here it does not, the segment is empty
    still = scale * np.array([[1e-14, 1.0, 0.0]])
    t_lo, t_hi = fold_rows(x0, d, -1.0, 1.0, still, l, u)
    assert t_lo > t_hi
    # ... and holds it exactly on its bound (C x0 = l): the segment is kept whole
    assert fold_rows(x0, d, -1.0, 1.0, still, np.array([scale]), u) == (-1.0, 1.0)


@pytest.mark.parametrize("rho", [3.0, 1e6])
def test_a_soft_row_that_binds_on_the_line_is_weighted_as_in_the_cascade(rho: float) -> None:
    """Level 1 leaves a line of solutions (6×7 task); level 2 pulls along it (g) against a soft row with slack
    weight ρ: the row binds, and the line fast path, the general cascade and DAQP on the general form give the
    same answer and slack, that of the one-dimensional problem on the line ``x = x0 + t·d`` solved by hand:
    ``min_t ½t²‖d‖² + t·gᵀd + ρσ²``, ``σ = C(x0 + t·d) − u > 0`` (ρ sets how far the row is crossed)."""
    rng = np.random.default_rng(4)
    J, v = rng.standard_normal((6, N)), 0.05 * rng.standard_normal(6)
    x0 = np.linalg.pinv(J) @ v
    d = np.linalg.svd(J)[2][-1]
    row = rng.standard_normal(N)
    row *= np.sign(row @ d)  # C d > 0
    g = -5.0 * d  # level 2 pulls x along +d, the row's upper bound stops it
    u = np.array([row @ x0 + 0.02])
    levels = [Level(A=J, b=v), Level(H=np.eye(N), g=g, C=row[None], l=np.array([-np.inf]), u=u, slack_weight=rho)]
    lb, ub = -np.ones(N), np.ones(N)
    line = HierarchicalQP(N).solve(levels, lb, ub)
    general = HierarchicalQP(N, settings=QPSettings(line_fast_path=False)).solve(levels, lb, ub)
    exact = HierarchicalQP(N, backend="daqp", settings=QPSettings(line_fast_path=False)).solve(levels, lb, ub)
    assert LINE_MESSAGE in line.levels[0].message and LINE_MESSAGE not in general.levels[0].message
    cd, cx0, dd = row @ d, row @ x0, d @ d
    # the 1-D optimum on the line, with the row violated (σ > 0): t (dd + 2ρ cd²) = −gᵀd + 2ρ cd (u − C x0)
    t = (-(g @ d) + 2 * rho * cd * (u[0] - cx0)) / (dd + 2 * rho * cd**2)
    sigma = cx0 + t * cd - u[0]
    assert sigma > 1e-7
    for res in (line, general, exact):
        assert res.ok, res.status
        np.testing.assert_allclose(res.x, x0 + t * d, atol=1e-7)
        np.testing.assert_allclose(res.levels[1].slack, [sigma], atol=1e-7)
    # the same problem as a tick's record (qpnso.qp.problem), solved on the line (line_setup) as the tick does
    from qpnso.qp.problem import new_problem, new_solution, set_level2

    problem, solution = new_problem(N), new_solution(N)
    P = problem[0]
    P["A1"], P["b1"], P["lb"], P["ub"] = J, v, lb, ub
    set_level2(problem, Level(H=np.eye(N), g=g))
    P["soft_C"][0], P["soft_l"][0], P["soft_u"][0], P["n_soft"], P["slack_weight"] = row, -np.inf, u[0], 1, rho
    hqp = HierarchicalQP(N)
    hqp._solve_problem_levels = lambda *args: pytest.fail("the general cascade ran, not the line")
    assert hqp.solve_problem(problem, solution) == ""
    np.testing.assert_allclose(solution[0]["x"], x0 + t * d, atol=1e-7)
    assert solution[0]["slack_max"] == pytest.approx(sigma, abs=1e-7)


def test_the_slack_of_a_soft_level_below_hard_rows_is_its_own_rows_violation() -> None:
    """Level 1 (a task and a hard row, c₁·x ≤ 0.1) is inherited by level 2 as a hard row ahead of level 2's own
    soft rows (they start at row 1 of its QP): level 2 asks c₂·x ≥ 5 and c₃·x ≤ −5 (each unreachable within
    the bounds), and the slacks reported are each soft row's own violation at the answer (> 0), in its order."""
    rng = np.random.default_rng(12)
    J = rng.standard_normal((3, N))
    c1, c2, c3 = rng.standard_normal((3, N))
    levels = [
        Level(A=J, b=0.05 * rng.standard_normal(3), C=c1[None], l=np.array([-np.inf]), u=np.array([0.1])),
        Level(
            H=np.eye(N),
            C=np.vstack([c2, c3]),
            l=np.array([5.0, -np.inf]),
            u=np.array([np.inf, -5.0]),
            slack_weight=10.0,
        ),
    ]
    lb, ub = -0.2 * np.ones(N), 0.2 * np.ones(N)
    for fast in (True, False):
        res = HierarchicalQP(N, settings=QPSettings(line_fast_path=fast)).solve(levels, lb, ub)
        assert res.ok, res.status
        slack = res.levels[1].slack
        np.testing.assert_allclose(slack, _soft_violation(levels[1], res.x), atol=1e-8)
        assert np.all(slack > 1.0) and slack[0] != pytest.approx(slack[1])
        assert c1 @ res.x <= 0.1 + 1e-8


@pytest.mark.parametrize("r", [1, 2, 3])
def test_fix_signs_makes_each_columns_largest_entry_positive(r: int) -> None:
    """The null-space basis' sign convention (a stable warm start from tick to tick): after ``fix_signs`` each
    column's largest-magnitude entry is positive, the columns are the same up to that sign, and a column that
    already has it is left as it is."""
    from qpnso.qp.cascade import fix_signs

    rng = np.random.default_rng(r)
    Z = np.linalg.qr(rng.standard_normal((N, r)))[0]
    Z[:, 0] *= np.sign(Z[np.abs(Z[:, 0]).argmax(), 0])  # column 0 already positive: kept
    if r > 1:
        Z[:, 1] *= -np.sign(Z[np.abs(Z[:, 1]).argmax(), 1])  # column 1 negative: flipped
    fixed = fix_signs(Z.copy())
    for j in range(r):
        assert fixed[np.abs(fixed[:, j]).argmax(), j] > 0.0
    np.testing.assert_array_equal(np.abs(fixed), np.abs(Z))
    np.testing.assert_array_equal(fixed[:, 0], Z[:, 0])
    if r > 1:
        np.testing.assert_array_equal(fixed[:, 1], -Z[:, 1])


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("side", ["lower", "upper"])
def test_a_soft_rows_violation_on_either_side_does_not_grow_below(side: str, backend: str) -> None:
    """A soft row that level 2 cannot meet (c·x ≥ 3, or its mirror c·x ≤ −3) is passed down to level 3 widened to
    the value reached: level 3, pulling the other way, neither grows the violation nor fails (the side the row
    is crossed on does not matter)."""
    rng = np.random.default_rng(9)
    J = rng.standard_normal((4, N))
    c = rng.standard_normal(N)
    s = 1.0 if side == "lower" else -1.0
    l, u = (np.array([3.0]), np.array([np.inf])) if side == "lower" else (np.array([-np.inf]), np.array([-3.0]))
    levels = [
        Level(A=J, b=np.zeros(4)),
        Level(C=c[None], l=l, u=u, slack_weight=1e3),  # unreachable within the bounds
        Level(H=np.eye(N), g=-10 * s * c),  # pulls c·x the other way
    ]
    lb, ub = -0.2 * np.ones(N), 0.2 * np.ones(N)
    two = HierarchicalQP(N, backend=backend).solve(levels[:2], lb, ub)
    res = HierarchicalQP(N, backend=backend).solve(levels, lb, ub)
    assert two.ok and res.ok, (two.status, res.status)
    assert res.levels[1].slack[0] > 0.1
    assert 3.0 - s * (c @ res.x) <= two.levels[1].slack[0] + 1e-8  # no larger than level 2 alone left it
    np.testing.assert_allclose(res.x, reference(levels, lb, ub)[-1], atol=1e-6)


def test_a_problem_without_a_level_two_is_level_one_alone() -> None:
    """``set_level2(problem, None)`` after a level 2 was written: the record says no level 2 (``has_level2`` 0), its
    general-cascade form is level 1 alone, and the tick's answer is level 1's least-norm exact solution."""
    from qpnso.qp.problem import problem_levels, set_level2

    rng = np.random.default_rng(2)
    problem, solution, P = _line_problem(rng)
    set_level2(problem, Level(H=np.eye(N), g=rng.standard_normal(N)))
    set_level2(problem, Level())  # a level 2 with nothing in it: level 1 alone as well
    assert P["has_level2"] == 1 and len(problem_levels(problem)) == 1
    set_level2(problem, None)
    assert P["has_level2"] == 0 and len(problem_levels(problem)) == 1
    assert HierarchicalQP(N).solve_problem(problem, solution) == ""
    np.testing.assert_allclose(solution[0]["x"], np.linalg.pinv(P["A1"]) @ P["b1"], atol=1e-12)


def test_least_norm_point_of_a_segment_by_hand() -> None:
    """Level 1's answer on its line (``x0 ⊥ d``): the segment's point nearest the origin, t clamped to [t_lo, t_hi]
    (by hand: x0 itself when 0 is inside, else the nearer end, on either side)."""
    from qpnso.qp.line import least_norm_point

    x0, d = np.array([0.0, 1.0, 0.0]), np.array([0.6, 0.0, 0.8])
    np.testing.assert_array_equal(least_norm_point(x0, d, -1.0, 2.0), x0)
    np.testing.assert_allclose(least_norm_point(x0, d, 0.5, 2.0), [0.3, 1.0, 0.4], rtol=0, atol=1e-15)
    np.testing.assert_allclose(least_norm_point(x0, d, -2.0, -0.5), [-0.3, 1.0, -0.4], rtol=0, atol=1e-15)


@pytest.mark.parametrize("weight", [0.5, 2.0])
def test_a_weighted_level_two_is_refused_by_the_problem_record(weight: float) -> None:
    """A strategy's level 2 is unweighted (the record has no weight field): a weight other than 1, larger or
    smaller, is refused by name rather than silently dropped; an unweighted task is written with its rows
    (``m2``, not its columns)."""
    from qpnso.qp.problem import new_problem, set_level2

    with pytest.raises(InputError, match="unweighted"):
        set_level2(new_problem(N), Level(A=np.eye(N), b=np.zeros(N), weight=weight))
    set_level2(problem := new_problem(N), Level(A=np.eye(N), b=np.zeros(N), weight=1.0))
    assert problem[0]["has_level2"] == 1 and problem[0]["m2"] == N
    A = np.arange(3 * N, dtype=float).reshape(3, N)  # a task of 3 rows: its rows, not its columns, counted
    set_level2(problem, Level(A=A, b=np.ones(3)))
    assert problem[0]["m2"] == 3
    np.testing.assert_array_equal(problem[0]["A2"][:3], A)


def test_a_level_two_rewritten_without_its_linear_term_forgets_it() -> None:
    """A strategy's level 2 written with a linear term g, then without one (H only): the record keeps the old g's
    numbers but not its use, and the tick's line (line_setup) answers as the general cascade on the record's
    levels and as the level H alone given to ``solve``: the old g plays no part."""
    from qpnso.qp.problem import problem_levels, set_level2

    rng = np.random.default_rng(6)
    problem, solution, P = _line_problem(rng)
    set_level2(problem, Level(H=np.eye(N), g=3.0 * rng.standard_normal(N)))
    H = np.diag(rng.uniform(0.5, 2.0, N))
    set_level2(problem, Level(H=H))
    assert not P["use_g2"] and len(problem_levels(problem)) == 2 and problem_levels(problem)[1].g is None
    hqp = HierarchicalQP(N)
    hqp._solve_problem_levels = lambda *args: pytest.fail("the general cascade ran, not the line")
    assert hqp.solve_problem(problem, solution) == ""
    expected = HierarchicalQP(N, settings=QPSettings(line_fast_path=False)).solve(
        [Level(A=P["A1"], b=P["b1"]), Level(H=H)], P["lb"], P["ub"]
    )
    np.testing.assert_allclose(solution[0]["x"], expected.x, atol=1e-8)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("form", ["task+H", "task+g", "task+H+g"])
def test_a_middle_level_mixing_a_task_with_other_terms_keeps_its_optimum(form: str, backend: str) -> None:
    """Level 2 combines a one-row task with a PSD quadratic that fights it and/or a linear term (with a linear term
    its optimum is pressed against the bounds, its gradient along the free directions not zero), level 3 pulls
    back along level 2's gradient: level 3 must leave
    level 2's cost where level 2 put it, and each level's cost is the optimum found by a general nonlinear
    solver level after level where a linear term presses level 2 on the bounds (there the equality-form
    ``reference`` misses level 2's optimum by 0.68: it fixes the active bounds)."""
    rng = np.random.default_rng(14)
    J = rng.standard_normal((3, N))
    a = rng.standard_normal((1, N))
    L = a.T + 0.3 * rng.standard_normal((N, 1))  # the quadratic fights the task: neither gradient is zero
    middle = Level(A=a, b=np.array([0.3]))
    if "H" in form:
        middle.H = L @ L.T
    if "g" in form:
        middle.g = 2.0 * rng.standard_normal(N)
    pull = -5.0 * (middle.g if middle.g is not None else a[0])  # level 3 pulls level 2's way back
    levels = [Level(A=J, b=0.1 * rng.standard_normal(3)), middle, Level(H=np.eye(N), g=pull)]
    lb, ub = -0.3 * np.ones(N), 0.3 * np.ones(N)
    res = HierarchicalQP(N, backend=backend).solve(levels, lb, ub)
    assert res.ok, res.status
    costs = _sequential_optimal_costs(levels, lb, ub)  # SciPy's SLSQP, level after level
    for k, level in enumerate(levels):  # (each level's cost held to 1e-10 there: ~1e-5 of play below it)
        assert level_cost(level, res.x) == pytest.approx(costs[k], abs=1e-4)
    if "g" in form:  # a linear term over the free directions: a bound stops level 2
        assert np.any(np.isclose(res.levels[1].x, lb) | np.isclose(res.levels[1].x, ub))
    assert abs(level_cost(levels[1], res.x) - level_cost(levels[1], res.levels[1].x)) < 1e-9


def _sequential_optimal_costs(levels: list[Level], lb: np.ndarray, ub: np.ndarray) -> list[float]:
    """Level 1 a task met exactly (held as ``A x = b``); each level below at its optimal cost given the levels
    above (their costs held to 1e-10), by SciPy's SLSQP: an independent, slow, general reference for small
    cascades without rows."""
    from scipy.optimize import minimize

    first = levels[0]
    held: list[dict] = [{"type": "eq", "fun": lambda x: first.A @ x - first.b}]
    costs, x = [0.0], np.linalg.pinv(first.A) @ first.b
    for level in levels[1:]:
        r = minimize(
            lambda x, level=level: level_cost(level, x),
            x,
            bounds=list(zip(lb, ub)),
            constraints=held,
            method="SLSQP",
            options={"ftol": 1e-15, "maxiter": 2000},
        )
        x, best = r.x, float(r.fun)
        costs.append(best)
        held.append({"type": "ineq", "fun": lambda x, level=level, best=best: best + 1e-10 - level_cost(level, x)})
    return costs


@pytest.mark.parametrize("parts", ["A", "H", "g", "AH", "Ag", "Hg", "AHg"])
def test_objective_gradient_is_the_level_costs_gradient(parts: str) -> None:
    """The x-gradient a level passes to the cascade (which direction it gives up to the levels below) against
    central finite differences of the level's cost ‖W^½(Ax − b)‖² + ½xᵀHx + gᵀx, for every mix of its terms
    (weighted task, PSD quadratic, linear term)."""
    from qpnso.qp.cascade import objective_gradient

    rng = np.random.default_rng(len(parts))
    L = rng.standard_normal((N, 2))
    level = Level(
        A=rng.standard_normal((3, N)) if "A" in parts else None,
        b=rng.standard_normal(3) if "A" in parts else None,
        weight=np.array([1.0, 2.0, 0.5]) if "A" in parts else 1.0,
        H=L @ L.T if "H" in parts else None,
        g=rng.standard_normal(N) if "g" in parts else None,
    )
    x = rng.standard_normal(N)

    def cost(x: np.ndarray) -> float:
        c = 0.0
        if level.A is not None:
            r = level.A @ x - level.b
            c += float(r @ (level.weight * r))
        if level.H is not None:
            c += 0.5 * float(x @ level.H @ x)
        if level.g is not None:
            c += float(level.g @ x)
        return c

    h = 1e-6
    fd = np.array([(cost(x + h * e) - cost(x - h * e)) / (2 * h) for e in np.eye(N)])
    parts = level_parts(_validate_level(level, N, "level"), N)
    np.testing.assert_allclose(objective_gradient(parts, x), fd, rtol=1e-7, atol=1e-7)


def test_warm_up_leaves_a_solver_that_answers_as_a_new_one() -> None:
    """``HierarchicalQP.warm_up()`` (both forms: the general cascade and ``solve()``'s line) runs and forgets: the
    next answers and counters are a new solver's."""
    levels = [Level(A=np.eye(N)[: N - 1], b=0.1 * np.ones(N - 1)), Level(H=np.eye(N), g=np.linspace(-1, 1, N))]
    warmed, new = HierarchicalQP(N), HierarchicalQP(N)
    warmed.warm_up()
    assert warmed.stats == new.stats
    a, b = warmed.solve(levels, -np.ones(N), np.ones(N)), new.solve(levels, -np.ones(N), np.ones(N))
    np.testing.assert_array_equal(a.x, b.x)


def _line_problem(rng: np.random.Generator):
    """A tick's problem record with a random 6×7 level 1 (a line of exact solutions) inside ±1 rad/s bounds and
    no level 2; its solution record; the problem's element."""
    from qpnso.qp.problem import new_problem, new_solution

    problem, solution = new_problem(N), new_solution(N)
    P = problem[0]
    P["A1"], P["b1"], P["lb"], P["ub"] = (
        rng.standard_normal((6, N)),
        0.05 * rng.standard_normal(6),
        -np.ones(N),
        np.ones(N),
    )
    return problem, solution, P


def test_the_solution_record_says_how_each_outcome_ended() -> None:
    """The three outcomes of a tick's problem, on both paths: solved (level 2 too); level 2 failed (``TOOL_HELD``,
    not ``SOLVED``: the answer is level 1's); level 1 failed (``STOPPED``: ``x`` and ``x1`` zero).  On the general
    cascade without soft rows, ``slack_max`` is −1 (nothing to report), as on the line."""
    from qpnso.qp.problem import SOLVED, STOPPED, TOOL_HELD, set_level2
    from qpnso.qp.settings import QPSettings

    for fast in (True, False):
        rng = np.random.default_rng(5)
        qp = HierarchicalQP(N, settings=QPSettings(line_fast_path=fast))
        problem, solution, P = _line_problem(rng)
        assert qp.solve_problem(problem, solution) == ""
        S = solution[0]
        assert S["outcome"] == SOLVED and S["slack_max"] == -1.0
        set_level2(problem, Level(H=np.eye(N), g=np.full(N, np.nan)))
        assert qp.solve_problem(problem, solution) != ""
        assert S["outcome"] == TOOL_HELD and S["outcome"] not in (SOLVED, STOPPED)
        np.testing.assert_allclose(S["x"], np.linalg.pinv(P["A1"]) @ P["b1"], atol=1e-9)
        set_level2(problem, None)
        P["A1"][0, 0] = np.nan
        solution[0]["x1"] = 7.0  # (left from an earlier tick: must not survive)
        assert qp.solve_problem(problem, solution) != ""
        assert S["outcome"] == STOPPED
        np.testing.assert_array_equal(S["x"], 0.0)
        np.testing.assert_array_equal(S["x1"], 0.0)


def test_a_problem_record_holds_at_least_one_row_of_each_kind() -> None:
    """``new_problem(n, 0, 0)``: every row field has one slot (matrix and both sides alike), so that a kernel can
    slice it to ``[:0]`` and a caller can write one row; the counts say how many are in use."""
    from qpnso.qp.problem import new_problem

    P = new_problem(N, 0, 0)[0]
    for kind in ("hard", "soft"):
        assert P[f"{kind}_C"].shape == (1, N) and P[f"{kind}_l"].shape == P[f"{kind}_u"].shape == (1,)
    assert P["n_hard"] == P["n_soft"] == 0


@pytest.mark.parametrize("seed", range(8))
def test_complement_is_numpys_complete_qr(seed: int) -> None:
    """The directions a level's projected gradient leaves (``complement``: one Householder reflector) against
    NumPy's complete QR of the same unit vector (LAPACK): the same columns to round-off, orthonormal and
    orthogonal to it; a vector on the first axis (no reflection) and one of length 1 (no complement)."""
    from qpnso.qp.cascade import complement

    rng = np.random.default_rng(seed)
    r = int(rng.integers(1, 7))
    p = rng.standard_normal(r)
    if seed == 0:
        p = np.zeros(r)
        p[0] = -2.0
    p /= np.linalg.norm(p)
    Q = complement(p)
    assert Q.shape == (r, r - 1)
    np.testing.assert_allclose(Q, np.linalg.qr(p[:, None], mode="complete")[0][:, 1:], atol=1e-14)
    np.testing.assert_allclose(Q.T @ Q, np.eye(r - 1), atol=1e-14)
    np.testing.assert_allclose(p @ Q, 0.0, atol=1e-14)


@pytest.mark.parametrize("seed", range(12))
def test_a_problem_record_and_its_levels_give_the_same_cascade(seed: int) -> None:
    """The general cascade reading a tick's problem record in its kernels (``problem_level``) against the same
    problem given as levels (``qpnso.qp.problem.problem_levels``, Python): equal answers to round-off and the
    same status,
    for records with and without hard rows, soft rows, a level-2 task, quadratic and linear term."""
    from qpnso.qp.problem import new_problem, new_solution, problem_levels

    rng = np.random.default_rng(seed)
    p = new_problem(N, hard_rows=2, soft_rows=2)
    P = p[0]
    P["A1"] = rng.standard_normal((6, N)) * (np.arange(6) < 6 - seed % 3)[:, None]  # rank 6, 5 or 4
    P["b1"] = 0.3 * rng.standard_normal(6)
    P["lb"], P["ub"] = -rng.uniform(0.2, 1.0, N), rng.uniform(0.2, 1.0, N)
    P["n_hard"] = seed % 3
    P["hard_C"], P["hard_l"], P["hard_u"] = rng.standard_normal((2, N)), -np.ones(2), np.ones(2)
    P["has_level2"] = seed % 4 != 3
    P["m2"] = seed % 2
    P["A2"][:1], P["b2"][:1] = rng.standard_normal((1, N)), 0.2
    L = rng.standard_normal((N, N))
    P["use_H2"], P["H2"] = seed % 5 != 0, L @ L.T if seed % 2 else np.eye(N)
    P["use_g2"], P["g2"] = seed % 3 != 1, rng.standard_normal(N)
    P["n_soft"], P["slack_weight"] = seed % 3, 1e3
    P["soft_C"], P["soft_l"], P["soft_u"] = rng.standard_normal((2, N)), -0.05 * np.ones(2), 0.05 * np.ones(2)
    by_record, by_levels = HierarchicalQP(N, backend="daqp"), HierarchicalQP(N, backend="daqp")
    solution = new_solution(N)
    why = by_record._solve_problem_levels(p, solution, None)
    levels = problem_levels(p)
    res = by_levels.solve(levels, P["lb"], P["ub"], check=False)
    assert why == ("" if res.ok else res.status)
    np.testing.assert_allclose(solution[0]["x"], res.x if res.x is not None else 0.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(solution[0]["x1"], res.levels[0].x if res.levels[0].x is not None else 0.0, atol=1e-12)
    assert solution[0]["tool_residual"] == pytest.approx(res.levels[0].residual if res.levels[0].ok else -1.0)


@pytest.mark.parametrize(
    "answer, words",
    [
        ("nan", "non-finite or mis-shaped solution"),
        ("short", "non-finite or mis-shaped solution"),
        ("far", "violated by"),
    ],
)
def test_the_general_cascade_refuses_a_bad_answer(monkeypatch, answer: str, words: str) -> None:
    """A back end that says "solved" with a vector that is not finite, of the wrong length, or far outside the
    bounds: the general cascade's check refuses it (level 1 ``INACCURATE``, the message says why), no answer."""
    from qpnso.qp.backends import _Raw

    levels, lb, ub = random_problem(0)
    hqp = HierarchicalQP(N, settings=QPSettings(line_fast_path=False))

    def bad(k, qp):
        v = {"nan": np.full(qp.g.shape, np.nan), "short": np.zeros(qp.g.shape[0] - 1), "far": np.full(qp.g.shape, 1e3)}
        return _Raw(v[answer], LevelStatus.SOLVED, 1, "test")

    monkeypatch.setattr(hqp._backend, "solve_arrays", bad)
    res = hqp.solve(levels, lb, ub)
    assert not res.ok and res.failed_level == 0 and res.x is None
    assert res.levels[0].status is LevelStatus.INACCURATE and words in res.levels[0].message


@pytest.mark.parametrize("off", [3.4e-6, 1e-3])
def test_an_answer_a_little_off_its_bounds_is_projected_onto_them(off: float) -> None:
    """Issue 31 item 2: on one CPU, DAQP met a bound row of a joint the free directions barely moved (its row of Z
    ~1e-6) only to 3.4e-6, and the level was refused (QP_FAILED).  A back end's answer off its bounds by at most
    ``bound_repair_tol`` (1e-4 rad/s) is clipped onto them, its hard rows checked again; farther off, refused."""
    qp = HierarchicalQP(3)
    levels = [Level(A=np.array([[1.0, 0.0, 0.0]]), b=np.array([0.5])), Level(g=np.array([0.0, -1.0, -1.0]))]
    exact = qp.solve(levels, -np.ones(3), np.ones(3))
    np.testing.assert_allclose(exact.x, [0.5, 1.0, 1.0], atol=1e-9)
    real = qp._backend.solve_arrays

    def off_bound(k, arrays, warm=True):  # level 2's answer pushed `off` beyond the upper bound of joint 3
        raw = real(k, arrays, warm)
        if k == 1 and raw.v is not None:
            z = np.array(raw.v, dtype=float)
            Z = np.linalg.lstsq(arrays.C[-3:, : z.size], np.eye(3), rcond=None)[0]  # (z from x: the bound rows are Z)
            raw.v = z + Z @ np.array([0.0, 0.0, off])
        return raw

    qp._backend.solve_arrays = off_bound
    result = qp.solve(levels, -np.ones(3), np.ones(3))
    if off <= QPSettings().bound_repair_tol:
        assert result.ok
        np.testing.assert_allclose(result.x, [0.5, 1.0, 1.0], atol=1e-12)
        assert np.all(result.x <= 1.0)
    else:
        assert not result.ok and "violated by 0.001" in result.status
