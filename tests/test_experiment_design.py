"""The experiments' design (issue 32): pre-registered work areas that discriminate, controls that can fail,
[M 24]'s two readings, three-valued verdicts."""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest

from qpnso.errors import ConfigError
from qpnso.lab.experiments import analysis
from qpnso.lab.experiments import mass_friction_analysis as mfa
from qpnso.lab.experiments import work_areas as wa
from qpnso.lab.experiments.mass_friction import MassFrictionOptions, light_robot, work_areas_of
from qpnso.model.robot import load_robot_with_armature


def felt_mass_pinocchio(robot, q: np.ndarray) -> float:
    """Largest principal mass at the tool [M 8] from Pinocchio's CRBA and frame Jacobian (independent of qpnso's
    cost model and of MuJoCo)."""
    model, data = robot.model, robot.model.createData()
    a = pin.crba(model, data, q)
    a = np.triu(a) + np.triu(a, 1).T
    pin.computeJointJacobians(model, data, q)
    pin.updateFramePlacements(model, data)
    jv = pin.getFrameJacobian(model, data, robot.tool_frame_id, pin.LOCAL_WORLD_ALIGNED)[:3]
    return float(1.0 / np.linalg.eigvalsh(jv @ np.linalg.solve(a, jv.T)).min())


# ------------------------------------------------------------------ the pre-registered work areas
def test_the_preregistered_areas_discriminate_by_an_independent_computation() -> None:
    """Must hold: in every pre-registered area at the default rotor inertia, the fixed posture is ≥ 20° from
    elbow up, holds the area's tool pose, and feels ≥ 15 % less mass (Pinocchio) or friction than elbow up."""
    specs = wa.load_preregistration()
    assert len(specs) == wa.AREAS
    robot = load_robot_with_armature("lwr4p", 0.0)
    for area in work_areas_of(MassFrictionOptions(armature_kgm2=0.0)):
        p = area.premise
        assert abs(math.degrees(area.ns_opt)) >= wa.MIN_ANGLE_DEG
        for q in (area.q_up, area.q_opt):
            assert np.allclose(robot.tool_pose(q).homogeneous, area.pose.homogeneous, atol=1e-9)
        up, fixed = felt_mass_pinocchio(robot, area.q_up), felt_mass_pinocchio(robot, area.q_opt)
        assert up == pytest.approx(p["mass_elbow_up_kg"], rel=1e-3) and fixed == pytest.approx(
            p["mass_fixed_kg"], rel=1e-3
        )
        assert max(1 - fixed / up, p["friction_reduction"]) >= wa.MIN_REDUCTION and p["discriminates"]


def test_the_fixed_posture_is_the_cost_minimum_over_the_interval_by_brute_force() -> None:
    """Brute force at 0.1° steps over elbow up's continuity interval: nothing below the fixed posture's cost."""
    from qpnso.elbow.intervals import continuity_interval
    from qpnso.elbow.srs import Branch, ik
    from qpnso.model.costs import CostModel

    robot = load_robot_with_armature("lwr4p", 0.0)
    spec = wa.load_preregistration()[0]
    q_up, q_fixed, ns = wa.fixed_posture(robot, spec.pose())
    cost, iv = CostModel(robot), continuity_interval(robot, q_up)
    grid = np.arange(iv.lo + 1e-3, iv.hi - 1e-3, np.radians(0.1))
    values = [cost.value(ik(robot, spec.pose(), s, Branch(*wa.ELBOW_UP_BRANCH))) for s in grid]
    assert cost.value(q_fixed) <= min(values) + 1e-9 and iv.lo < ns < iv.hi
    assert math.degrees(ns) == pytest.approx(spec.fixed_arm_angle_deg[0.0], abs=wa_tolerance())


def wa_tolerance() -> float:
    from qpnso.lab.experiments.mass_friction import PREREGISTERED_TOLERANCE_DEG

    return PREREGISTERED_TOLERANCE_DEG


def test_the_rule_rejects_an_area_where_the_fixed_posture_is_elbow_up() -> None:
    """Negative control of the premise: at 0.1 kg·m² the pre-registered areas' fixed posture is within a few
    degrees of elbow up and the premise says so; the rule's choice refuses such candidates."""
    robot = load_robot_with_armature("lwr4p", 0.1)
    p = wa.postures(robot, wa.load_preregistration()[0].pose())
    assert abs(math.degrees(p.ns_fixed)) < wa.MIN_ANGLE_DEG and not p.discriminates
    fake = [{"center_m": [0.0, 0.0, 0.0], "pitch_deg": 0.0, "by_armature": {a: p for a in wa.ARMATURES_KGM2}}]
    with pytest.raises(ConfigError, match="only 0 work areas"):
        wa.choose(fake, 1)


def test_the_experiment_refuses_a_preregistration_the_model_no_longer_gives(monkeypatch) -> None:
    specs = wa.load_preregistration()
    moved = [
        wa.WorkAreaSpec(s.center, s.pitch_deg, {a: v + 1.0 for a, v in s.fixed_arm_angle_deg.items()}) for s in specs
    ]
    monkeypatch.setattr(wa, "load_preregistration", lambda path=None: moved)
    with pytest.raises(ConfigError, match="the model changed since"):
        work_areas_of(MassFrictionOptions(armature_kgm2=0.0, posture_stiffness=99.0))


def test_the_light_robot_feels_exactly_the_factor_lighter() -> None:
    """The positive control's plant: every link's mass and inertia × 0.7 gives a felt mass × 0.7 (no rotor
    inertia: A(q) scales), by Pinocchio."""
    robot = load_robot_with_armature("lwr4p", 0.0)
    light = light_robot(robot, 0.7)
    q = np.radians([20, -30, 10, 90, -40, -20, 60])
    assert felt_mass_pinocchio(light, q) == pytest.approx(0.7 * felt_mass_pinocchio(robot, q), rel=1e-12)
    assert np.allclose(pin.computeGeneralizedGravity(light.model, light.model.createData(), q), 0.7 * robot.gravity(q))


# ------------------------------------------------------------------ controls and verdicts
def synthetic_rows(light_factor: float, seed: int = 0, n: int = 40) -> list[dict]:
    """Rows of damped, damped-again and damped-light with work ~ N(1, 0.05²) (damped-light times the factor)."""
    rng = np.random.default_rng(seed)
    rows = []
    for g, f in (("damped", 1.0), ("damped-again", 1.0), ("damped-light", light_factor)):
        for i in range(n):
            w = f * (1.0 + 0.05 * rng.standard_normal())
            rows.append(
                {"subject": i % 4, "strategy": g, "rep": 0, "error": "", "mass_mean_kg": 6.0 * f}
                | {"work_measured": w, "work_nominal": w, "orthogonal_torque": w}
            )
    return rows


def test_the_controls_pass_on_a_detectable_change_and_fail_without_one() -> None:
    ok = mfa.control_stats(synthetic_rows(0.7), control_reps=1)
    assert ok["work_measured"]["positive_ok"] and ok["work_measured"]["negative_ok"]
    assert ok["felt_mass_ratio"] == pytest.approx(0.7)
    blind = mfa.control_stats(synthetic_rows(1.0), control_reps=1)  # (a metric blind to the felt mass)
    assert not blind["work_measured"]["positive_ok"] and blind["work_measured"]["negative_ok"]


def test_a_verdict_is_untestable_when_the_readings_disagree_or_a_control_fails() -> None:
    v = analysis.three_valued("c", {"measured": True, "nominal": False}, "m", [])
    assert v["verdict"] == "untestable" and "readings disagree" in v["why"]
    v = analysis.three_valued("c", {"measured": True, "nominal": True}, "m", ["", "the positive control failed"])
    assert v["verdict"] == "untestable" and v["why"] == "the positive control failed"
    assert analysis.three_valued("c", {"a": True, "b": True}, "m", [""])["verdict"] == "reproduced"
    assert analysis.three_valued("c", {"a": False}, "m", [], "why")["verdict"] == "not reproduced"
    s = {"controls": mfa.control_stats(synthetic_rows(1.0), 1)}
    assert mfa.controls_failed(s, "work_measured").startswith("the positive control failed")


def test_elbow_verdicts_are_untestable_where_the_plant_or_the_motion_cannot_say() -> None:
    """E2 needs DP's elbow to drift in A (≥ 20°); E3 needs an intended motion whose own S is under 500."""

    def block(delta, s_med, intended):
        spread = lambda m: {k: {"median": m, "q1": m, "q3": m, "n": 3} for k in ("DP", "FOP", "NSO", "qp")}  # noqa: E731
        tests = {"kruskal": {"p": 0.5}, "bartlett_NSO_DP": {"p": 0.5}, "bartlett_NSO_FOP": {"p": 0.5}}
        return {
            "elbow_mobility_deg": {"spread": spread(delta), **tests},
            "constraint_proximity_deg": {"spread": spread(20.0), **tests},
            "smoothness_per_segment": {"spread": spread(s_med)},
            "smoothness_quiet": spread(s_med),
            "intended_smoothness": {"median": intended},
        }

    rows = [{"scenario": "B", "strategy": k, "constraint_proximity_deg": 20.0} for k in ("DP", "FOP", "NSO")]
    still = analysis.elbow_verdicts({"A": block(2.0, 900, 519), "B": block(2.0, 900, 519)}, rows)
    assert still[1]["verdict"] == "untestable" and "does not produce" in still[1]["why"]
    assert still[2]["verdict"] == "untestable" and "no controller can meet" in still[2]["why"]
    moving = analysis.elbow_verdicts({"A": block(30.0, 900, 100), "B": block(30.0, 900, 100)}, rows)
    assert moving[1]["verdict"] == "not reproduced" and moving[2]["verdict"] == "not reproduced"


def test_a_reading_whose_controls_fail_is_set_aside_and_the_other_decides() -> None:
    """Pre-registration v2: a claim is judged on the readings whose work metric passed its controls; with none,
    it is untestable."""
    rows = synthetic_rows(0.7)
    blind = synthetic_rows(1.0, seed=1)
    for r, b in zip(rows, blind):  # (the measured reading blind to the felt mass, the intended one not)
        r["work_measured"] = b["work_measured"]
    s = {"controls": mfa.control_stats(rows, 1)}
    assert not s["controls"]["work_measured"]["positive_ok"] and s["controls"]["work_nominal"]["positive_ok"]
    kept, blockers, aside = mfa.valid_readings(s, {"measured": True, "nominal": False})
    assert kept == {"nominal": False} and blockers == [] and "measured reading set aside" in aside
    blind = {"controls": mfa.control_stats(synthetic_rows(1.0), 1)}
    kept, blockers, aside = mfa.valid_readings(blind, {"measured": True, "nominal": True})
    assert len(blockers) == 2 and aside == ""
    assert analysis.three_valued("c", kept, "m", blockers)["verdict"] == "untestable"


def test_the_guard_holds_at_1_2_times_and_fails_above_it_or_with_a_stopped_trial() -> None:
    """qp against damped: medians of path and hand work; 1.2× holds, 1.25× fails, a stopped trial fails."""

    def rows(path_ratio: float, work_ratio: float, error: str = "") -> list[dict]:
        out = [{"strategy": "damped", "path_length_m": 1.0, "hand_work_J": 2.0, "error": ""} for _ in range(3)]
        out += [{"strategy": "qp", "path_length_m": path_ratio, "hand_work_J": 2.0 * work_ratio, "error": ""}] * 3
        out[-1] = {**out[-1], "error": error}
        return out

    assert mfa.guard(rows(1.2, 1.0))["holds"]
    g = mfa.guard(rows(1.25, 1.0))
    assert g["path_ratio"] == pytest.approx(1.25) and not g["holds"]
    assert not mfa.guard(rows(1.0, 1.21))["holds"]
    stopped = mfa.guard(rows(1.0, 1.0, "InputError: a joint past its limit"))
    assert stopped["stopped"] == {"qp": 1, "damped": 0} and not stopped["holds"]


def test_a_malformed_preregistration_is_named(tmp_path) -> None:
    bad = tmp_path / "p.toml"
    bad.write_text('[[area]]\ncenter_m = [0.4, 0.0]\npitch_deg = "steep"\n')
    with pytest.raises(ConfigError, match="the pre-registration file is malformed"):
        wa.load_preregistration(bad)


@pytest.mark.parametrize(
    "options, message",
    [
        ({"strategies": ("damped", "walking")}, "unknown group 'walking'"),
        ({"strategies": ("qp",)}, "must include 'damped'"),
        ({"control_reps": 0}, "control_reps must be >= 1"),
    ],
)
def test_bad_groups_are_named(options, message) -> None:
    with pytest.raises(ConfigError, match=message):
        MassFrictionOptions(**options)
