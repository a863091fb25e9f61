"""One job of each study: ``job(index, seed, opts) -> dict``, the record of one pose (or pair).

Jobs run in worker processes (:mod:`qpnso.lab.parallel`, Dask): they are module-level
functions, and each draws its random numbers from ``(seed, index)`` alone, so a study's
results do not depend on how its jobs are spread.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from qpnso.errors import ConfigError, InputError
from qpnso.lab.parallel import job_rng, job_seed_sequence
from qpnso.lab.studies.curves import SelfMotionCurve, sample_start
from qpnso.lab.studies.measures import friction_objective, mass_objective, weighted_objective, workbench
from qpnso.lab.studies.options import StudyOptions

SCENARIO_JOBS = tuple((sc, st) for sc in ("A", "B") for st in ("damped", "fixed", "rom", "gradient", "qp"))
"""The (scenario, strategy) pairs of the ``scenarios`` study, in job order."""


def _start_curve(index: int, seed: int, opts: StudyOptions) -> tuple[SelfMotionCurve, int, np.random.Generator]:
    bench = workbench(opts.robot, opts.compile, opts.armature_kgm2)
    rng = job_rng(seed, index)
    q0, rejected = sample_start(bench.robot, rng, opts.singular_threshold)
    return SelfMotionCurve(bench, q0, math.radians(opts.grid_step_deg)), rejected, rng


def _pose_record(curve: SelfMotionCurve, rejected: int) -> dict[str, Any]:
    iv = curve.interval
    return {
        "q0": curve.q0.tolist(),
        "ns0_deg": math.degrees(curve.ns0),
        "interval_lo_deg": math.degrees(iv.lo),
        "interval_hi_deg": math.degrees(iv.hi),
        "full_circle": bool(iv.full_circle),
        "rejected_draws": rejected,
    }


def reduction_pct(high: float, low: float) -> float:
    """The paper's reduction ``(high − low)/high · 100`` (%)."""
    return (high - low) / high * 100.0


# ------------------------------------------------------------------ jobs
def workspace_job(index: int, seed: int, opts: StudyOptions) -> dict[str, Any]:
    """IV-A for one random start: local min/max of c_m and of c_f along the self-motion."""
    curve, rejected, _ = _start_curve(index, seed, opts)
    tau = curve.bench.tau_max()
    out = _pose_record(curve, rejected)
    out["principal_mass_start_kg"] = float(curve.samples.principal_mass()[curve.start])
    out["friction_force_start_N"] = float(curve.samples.friction_force(tau)[curve.start])
    for name, objective, measure in (
        ("mass", mass_objective, lambda m: float(m.principal_mass()[0])),
        ("friction", friction_objective(tau), lambda m: float(m.friction_force(tau)[0])),
    ):
        unit = "kg" if name == "mass" else "N"
        ext = {s: curve.extremum(objective, s) for s in ("min", "max")}
        for s, e in ext.items():
            out[f"{name}_{s}_ns_deg"] = math.degrees(e.ns)
            out[f"{name}_{s}_at_end"] = e.at_end
            out[f"{name}_at_{s}_{unit}"] = measure(e.measures)
        out[f"{name}_reduction_pct"] = reduction_pct(out[f"{name}_at_max_{unit}"], out[f"{name}_at_min_{unit}"])
    return out


def _share_label(w: float) -> str:
    return f"w{round(100 * w):02d}"


def tradeoff_job(index: int, seed: int, opts: StudyOptions) -> dict[str, Any]:
    """IV-B for one random start: weighted optima against the single mass and friction optima."""
    curve, rejected, _ = _start_curve(index, seed, opts)
    bench, tau = curve.bench, curve.bench.tau_max()
    out = _pose_record(curve, rejected)
    m0 = float(curve.samples.principal_mass()[curve.start])
    f0 = float(curve.samples.friction_force(tau)[curve.start])
    mass_opt = curve.extremum(mass_objective)
    fric_opt = curve.extremum(friction_objective(tau))
    m_opt = float(mass_opt.measures.principal_mass()[0])
    f_opt = float(fric_opt.measures.friction_force(tau)[0])
    out.update(
        principal_mass_start_kg=m0,
        friction_force_start_N=f0,
        mass_opt_kg=m_opt,
        friction_opt_N=f_opt,
        optima_distance_rad=float(np.linalg.norm(mass_opt.q - fric_opt.q)),
    )
    for w in opts.mass_shares:
        e = curve.extremum(weighted_objective(w, bench.cost.scales, tau))
        m_w, f_w = float(e.measures.principal_mass()[0]), float(e.measures.friction_force(tau)[0])
        key = _share_label(w)
        out[f"{key}_mass_kg"], out[f"{key}_friction_N"] = m_w, f_w
        out[f"{key}_mass_change_pct"] = (m_w - m_opt) / m_opt * 100.0
        out[f"{key}_friction_change_pct"] = (f_w - f_opt) / f_opt * 100.0
        out[f"{key}_mass_share_of_reduction_pct"] = _share(m0, m_w, m_opt)
        out[f"{key}_friction_share_of_reduction_pct"] = _share(f0, f_w, f_opt)
    return out


def _share(start: float, weighted: float, best: float) -> float | None:
    """Part (%) of the single-objective reduction ``start → best`` that ``weighted`` achieves (None if none)."""
    gain = start - best
    return None if gain <= 1e-9 * abs(start) else (start - weighted) / gain * 100.0


def uncertainty_job(index: int, seed: int, opts: StudyOptions) -> dict[str, Any]:
    """IV-C for one random start: ``opts.trials`` perturbed friction models."""
    curve, rejected, rng = _start_curve(index, seed, opts)
    tau = curve.bench.tau_max()
    true_opt = curve.extremum(friction_objective(tau))
    f_true = float(true_opt.measures.friction_force(tau)[0])
    increase, ns = [], []
    for _ in range(opts.trials):
        factor = 1.0 + opts.friction_sd * rng.standard_normal(tau.size)
        if np.any(factor <= 0):
            raise InputError(f"a perturbed sliding torque is not positive (factors {factor})")
        e = curve.extremum(friction_objective(tau * factor))
        increase.append((float(e.measures.friction_force(tau)[0]) - f_true) / f_true * 100.0)
        ns.append(math.degrees(e.ns))
    return {
        **_pose_record(curve, rejected),
        "friction_opt_N": f_true,
        "friction_opt_ns_deg": math.degrees(true_opt.ns),
        "increase_pct": increase,
        "perturbed_opt_ns_deg": ns,
    }


def scenarios_job(index: int, seed: int, opts: StudyOptions) -> dict[str, Any]:
    """One (scenario, strategy) pair of :data:`SCENARIO_JOBS` through ``run_scenario``."""
    try:
        from qpnso.lab.scenarios import load_scenario, run_scenario
    except ImportError as exc:
        raise ConfigError(f"the scenarios study needs qpnso.lab.scenarios, which cannot be imported: {exc}") from None
    name, strategy = SCENARIO_JOBS[index]
    job_seed = int(job_seed_sequence(seed, index).generate_state(1)[0])
    metrics = run_scenario(name, strategy, seed=job_seed, duration_scale=opts.duration_scale)
    margin = float(load_scenario(name).controller.get("safety_margin_deg", 10.0))
    return {
        "scenario": name,
        "strategy": strategy,
        "safety_margin_deg": margin,
        **{k: float(v) for k, v in metrics.items()},
    }
