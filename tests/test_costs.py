"""Costs of docs/method.md §3 against an independent NumPy/Pinocchio computation and
finite differences."""

from __future__ import annotations

import numpy as np
import pytest

import qpnso
from qpnso.model.codegen import FastFunction


def reference_terms(robot: qpnso.Robot, q: np.ndarray, s: float, s_w: float) -> dict[str, float]:
    """docs/method.md §2–3 written directly with Pinocchio's A(q), J(q) and NumPy."""
    a, jac = robot.mass_matrix(q), robot.jacobian(q)
    out = {}
    for key, rows, speed in (("v", slice(0, 3), s), ("w", slice(3, 6), s_w)):
        j = jac[rows]
        lam_inv = j @ np.linalg.solve(a, j.T)
        jbar = np.linalg.solve(a, j.T) @ np.linalg.inv(lam_inv)
        total = 0.0
        for i in range(3):
            dq_potential = jbar @ (speed * np.eye(3)[i])
            tau_f = robot.friction_torque(dq_potential)
            total += np.sum((jbar.T @ tau_f) ** 2)
        out["det_" + key] = np.linalg.det(lam_inv)
        out["fric_" + key] = total
    return {
        "mass": -out["det_v"],
        "inertia": -out["det_w"],
        "friction_force": out["fric_v"],
        "friction_torque": out["fric_w"],
    }


@pytest.fixture(scope="module")
def cost(lwr) -> qpnso.CostModel:
    return qpnso.CostModel(
        lwr,
        qpnso.CostWeights(mass=1, inertia=0.5, friction_force=1, friction_torque=0.3),
        potential_speed=0.05,
        potential_angular_speed=0.4,
    )


def test_terms_match_the_reference(lwr, cost, rng) -> None:
    for _ in range(20):
        q = lwr.random_q(rng)
        ref = reference_terms(lwr, q, 0.05, 0.4)
        got = cost.terms(q)
        for name in qpnso.TERMS:
            assert np.isclose(got[name], ref[name], rtol=1e-9, atol=0), name


def test_total_is_the_weighted_normalised_sum(lwr, cost, rng) -> None:
    q = lwr.random_q(rng)
    terms = cost.terms(q)
    w = cost.weights
    expected = sum(getattr(w, t) * terms[t] / cost.scales[t] for t in qpnso.TERMS)
    assert np.isclose(cost.value(q), expected, rtol=1e-12)


def test_scales_are_typical_magnitudes(lwr, cost) -> None:
    """Each scale is the median |term| over random poses: a fresh sample of
    poses has a median of the same order."""
    rng = np.random.default_rng(7)
    samples = [cost.terms(lwr.random_q(rng, margin=0.1)) for _ in range(60)]
    for t in qpnso.TERMS:
        ratio = np.median([abs(s[t]) for s in samples]) / cost.scales[t]
        assert 0.5 < ratio < 2.0, t


def test_gradient_matches_central_differences(lwr, cost, rng) -> None:
    for _ in range(5):
        q = lwr.random_q(rng, margin=0.2)
        g = cost.gradient(q)
        h = 1e-6
        fd = np.array([(cost.value(q + h * e) - cost.value(q - h * e)) / (2 * h) for e in np.eye(7)])
        assert np.allclose(g, fd, rtol=1e-5, atol=1e-7 * max(1.0, np.abs(fd).max()))


def test_hessian_matches_differences_of_the_gradient(lwr, cost, rng) -> None:
    q = lwr.random_q(rng, margin=0.2)
    h = 1e-6
    fd = np.array([(cost.gradient(q + h * e) - cost.gradient(q - h * e)) / (2 * h) for e in np.eye(7)]).T
    hess = cost.hessian(q)
    scale = np.abs(fd).max()
    assert np.allclose(hess, hess.T, atol=1e-9 * scale)
    assert np.allclose(hess, fd, atol=1e-5 * scale)
    v = rng.normal(size=7)
    assert np.allclose(cost.hessian_vector(q, v), hess @ v, atol=1e-9 * scale)


def test_value_and_gradient_is_one_evaluation_of_both(lwr, cost, rng) -> None:
    q = lwr.random_q(rng)
    v, g = cost.value_and_gradient(q)
    assert v == cost.value(q) and np.array_equal(g, cost.gradient(q))


def test_user_facing_measures(lwr, cost, rng) -> None:
    q = lwr.random_q(rng)
    lam_v, lam_w = cost.lambda_inv(q)
    a, jac = lwr.mass_matrix(q), lwr.jacobian(q)
    lam_ref = np.linalg.inv(jac[:3] @ np.linalg.solve(a, jac[:3].T))  # Λv, kg
    assert np.isclose(cost.principal_mass(q), np.linalg.eigvalsh(lam_ref)[-1], rtol=1e-9)
    u = np.array([1.0, 2.0, -0.5])
    un = u / np.linalg.norm(u)
    assert np.isclose(cost.effective_mass(q, u), 1 / (un @ np.linalg.inv(lam_ref) @ un), rtol=1e-9)
    assert np.isclose(cost.friction_force_magnitude(q), np.sqrt(reference_terms(lwr, q, 0.05, 0.4)["friction_force"]))
    # the friction felt at the tool is bounded by the joints' sliding torques through J̄
    assert cost.friction_force_magnitude(q) > 0


def test_directional_measures(lwr, cost, rng) -> None:
    q = lwr.random_q(rng, margin=0.2)
    lam_v = cost.lambda_inv(q)[0]
    u = np.array([0.0, 0.0, 1.0])
    c_dm = cost.directional(u)  # [M 11]: -uᵀΛv⁻¹u
    assert np.isclose(c_dm.value(q), -lam_v[2, 2], rtol=1e-10)
    dirs = np.eye(3)[:2]
    masses = cost.directional(dirs, weights=[0.3, 0.7], exponent=-1)  # [M 12]: Σ w m_u
    assert np.isclose(masses.value(q), 0.3 / lam_v[0, 0] + 0.7 / lam_v[1, 1], rtol=1e-10)
    h = 1e-6
    fd = np.array([(masses.value(q + h * e) - masses.value(q - h * e)) / (2 * h) for e in np.eye(7)])
    assert np.allclose(masses.gradient(q), fd, rtol=1e-5, atol=1e-8)
    lam_w = cost.lambda_inv(q)[1]
    assert np.isclose(cost.directional(u, kind="inertia").value(q), -lam_w[2, 2], rtol=1e-10)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"directions": [0, 0, 0]}, "non-zero"),
        ({"directions": [1, 0, 0], "exponent": 2}, "exponent"),
        ({"directions": [1, 0, 0], "kind": "torque"}, "kind"),
    ],
)
def test_directional_bad_input(cost, kwargs, match) -> None:
    with pytest.raises(qpnso.InputError, match=match):
        cost.directional(**kwargs)


def test_bad_weights_and_scales(lwr) -> None:
    with pytest.raises(qpnso.InputError, match="mass"):
        qpnso.CostWeights(mass=-1)
    with pytest.raises(qpnso.InputError, match="unknown cost term"):
        qpnso.CostModel(lwr, scales={"weight": 1.0})
    with pytest.raises(qpnso.InputError, match="potential"):
        qpnso.CostModel(lwr, potential_speed=0)


def test_cost_rejects_bad_q(cost) -> None:
    with pytest.raises(qpnso.InputError, match="NaN"):
        cost.value([np.nan] * 7)
    with pytest.raises(qpnso.InputError, match="shape"):
        cost.gradient(np.zeros(3))


def test_compiled_code_agrees_with_the_virtual_machine(lwr, rng, tmp_path, monkeypatch) -> None:
    """The C path (generated, compiled, cached on disk, reloaded) gives the VM's numbers."""
    monkeypatch.setenv("QPNSO_CACHE_DIR", str(tmp_path))
    cost = qpnso.CostModel(lwr, compile="off")
    fn = cost._value_grad_fn.function
    compiled = FastFunction(fn, mode="sync")
    if not compiled.compiled:
        pytest.skip("no working C compiler on this machine")
    assert len(list(tmp_path.glob("*.so"))) == 1
    again = FastFunction(fn, mode="sync")  # from the cache
    for _ in range(5):
        q = lwr.random_q(rng)
        v0, g0 = cost.value_and_gradient(q)
        for ff in (compiled, again):
            v1, g1 = ff(q)
            assert np.isclose(v1, v0, rtol=1e-12) and np.allclose(g1, g0, rtol=1e-10, atol=1e-14)


def test_cost_weights_default_is_half_mass_half_friction_force() -> None:
    """``CostWeights()`` is the paper's documented default: 50 % mass, 50 % friction force, no inertia and no
    friction torque."""
    w = qpnso.CostWeights()
    assert (w.mass, w.inertia, w.friction_force, w.friction_torque) == (1.0, 0.0, 1.0, 0.0)
    np.testing.assert_array_equal(w.as_array(), [1.0, 0.0, 1.0, 0.0])


def test_default_cost_model_speeds_and_scales(lwr) -> None:
    """``CostModel(robot)`` uses the documented defaults: s = 0.05 m/s (the paper's), s_w = 0.5 rad/s, and scales
    that are the median |term| over 200 random configurations (seed 0, 0.1 rad inside the limits), here
    recomputed with the NumPy/Pinocchio reference terms on the same sample of poses."""
    cost = qpnso.CostModel(lwr)
    assert cost.potential_speed == 0.05 and cost.potential_angular_speed == 0.5
    rng = np.random.default_rng(0)
    qs = [lwr.random_q(rng, margin=0.1) for _ in range(200)]
    ref = [reference_terms(lwr, q, 0.05, 0.5) for q in qs]
    np.testing.assert_allclose(cost.terms(qs[3])["friction_torque"], ref[3]["friction_torque"], rtol=1e-9)
    for t in qpnso.TERMS:
        assert cost.scales[t] == pytest.approx(np.median([abs(r[t]) for r in ref]), rel=1e-9), t


def test_explicit_scales_are_used_and_must_be_positive(lwr) -> None:
    """A valid ``scales=`` dict is taken as given (terms not named keep the scale 1); a zero or negative scale
    and a zero angular potential speed are refused."""
    cost = qpnso.CostModel(lwr, scales={"mass": 2.0, "friction_force": 4.0})
    assert cost.scales == {"mass": 2.0, "inertia": 1.0, "friction_force": 4.0, "friction_torque": 1.0}
    for bad in (0.0, -1.0):
        with pytest.raises(qpnso.InputError, match="cost scales must be finite and > 0"):
            qpnso.CostModel(lwr, scales={"inertia": bad})
    with pytest.raises(qpnso.InputError, match="potential speeds must be > 0"):
        qpnso.CostModel(lwr, potential_angular_speed=0.0)


def test_unnormalised_costs_have_unit_scales(lwr) -> None:
    """``normalize=False`` without scales: every term's scale is 1 (its value in SI units, unscaled)."""
    from qpnso.model.costs import TERMS

    cost = qpnso.CostModel(lwr, normalize=False, compile="off")
    assert cost.scales == dict.fromkeys(TERMS, 1.0)


def test_felt_mass_and_friction_of_a_run_at_once(cost, lwr) -> None:
    """``CostModel.felt`` (a whole run's felt quantities in mapped chunks, padded) against one configuration at
    a time through other functions: 1/λ_min of ``lambda_inv``'s Λv⁻¹ and √ of ``terms``' c_f; 300 random
    configurations (a partial last chunk), none, and one."""
    rng = np.random.default_rng(7)
    qs = np.array([lwr.random_q(rng, margin=0.05) for _ in range(300)])
    mass, force = cost.felt(qs)
    want_mass = [1.0 / np.linalg.eigvalsh(cost.lambda_inv(q)[0])[0] for q in qs]
    want_force = [np.sqrt(cost.terms(q)["friction_force"]) for q in qs]
    np.testing.assert_allclose(mass, want_mass, rtol=1e-12)
    np.testing.assert_allclose(force, want_force, rtol=1e-12)
    assert [a.shape for a in cost.felt(np.zeros((0, 7)))] == [(0,), (0,)]
    assert cost.principal_mass(qs[5]) == mass[5] and cost.friction_force_magnitude(qs[5]) == force[5]
