"""The papers' studies, reproduced: workspace, trade-off, uncertainty, scenarios.

Mass/friction paper, section IV (docs/method.md §3, §9):

* ``workspace`` (IV-A, Fig. 2): random non-singular LWR4+ configurations; with
  the tool pose held, the arm is moved along its self-motion from the start
  configuration to the local minimum and the local maximum of the mass measure
  ``c_m`` [M 8] and of the friction-force measure ``c_f`` [M 15]; reported: the
  reduction of the largest principal mass (kg) between the local-max and
  local-min mass postures and of the friction-force magnitude ``√c_f`` (N)
  between the local-max and local-min friction postures, each
  ``(max − min)/max · 100`` %.
* ``tradeoff`` (IV-B, Figs. 4, 5a): the weighted cost ``w c_m/s_m + (1−w) c_f/s_f``
  [M 18] (``s`` = :attr:`CostModel.scales`) for mass shares ``w`` = 0.9, 0.5,
  0.1 against the single optima, and the joint distance between the mass and
  friction optima.
* ``uncertainty`` (IV-C, Fig. 6): per pose, trials with every joint's sliding
  torque scaled by ``1 + 0.1·ε``, ``ε ~ N(0, 1)`` (multiplicative on
  ``tau_max``, i.e. ``τf,e ~ N(τf, (0.1 τf)²)``); optimise with the perturbed
  model, evaluate the true friction there; reported: the % increase over the
  true optimum.

Elbow paper: ``scenarios`` runs scenarios A and B × strategies through
:func:`qpnso.lab.scenarios.run_scenario` and writes the layout of its Table I.

How an optimum is found.  The paper follows the null-space gradient from the
start posture until it stops.  Here the self-motion is parametrised exactly by
the arm angle ``ns`` (closed-form IK, :func:`qpnso.elbow.arm_angle.self_motion`) over the
continuity interval of the start [E 9]: the cost is sampled on a grid of arm
angles (``grid_step_deg``, ``ns0`` and the interval ends on the grid), followed
downhill (or uphill) from ``ns0`` to the first grid minimum (maximum), and
refined by bounded Brent on the two neighbouring grid cells (``xatol`` 1e-9
rad).  An interval end (a joint limit, or joint 2 or 6 through 0) stops the
search, as it stops the robot.  A bump narrower than one grid cell can be
stepped over (a gradient flow would stop in front of it); the tests compare
against 0.01° sampling.

Non-singular start: ``σ_min(J Jᵀ) ≥ singular_threshold`` (default 1e-4, i.e. the
smallest singular value of the 6×7 tool Jacobian ≥ 0.01 m/rad or rad/rad; it
rejects about 5 % of uniform draws on the LWR4+) and a defined arm angle
(:func:`qpnso.elbow.arm_angle.arm_angle_status`); singular draws are redrawn and counted.

Every study writes into ``OUT``: ``checkpoint.jsonl`` (see
:mod:`qpnso.lab.parallel`), ``results.csv``, a PNG and, last, ``summary.json``.
Entry point: :func:`run_study`.
"""

from __future__ import annotations

import csv
import io
import json
import math
import time
from dataclasses import asdict, dataclass, fields
from functools import partial
from pathlib import Path
from typing import Any, Callable, Sequence

import casadi as ca
import numpy as np
from scipy.optimize import minimize_scalar

from qpnso.model.codegen import FastFunction
from qpnso.model.costs import CostModel, smooth_coulomb
from qpnso.elbow.arm_angle import SelfMotion, arm_angle_status, branch, self_motion
from qpnso.errors import ConfigError, InputError, ModelError, SingularityError
from qpnso.elbow.intervals import Interval, continuity_interval
from qpnso.lab.parallel import RunSpec, job_rng, job_seed_sequence, run_jobs
from qpnso.model.robot import Robot, load_robot

PAPER = {
    "workspace": {"mass_reduction_pct": {"mean": 44.23, "sd": 20.97},
                  "friction_reduction_pct": {"mean": 41.44, "sd": 21.93}, "samples": 1000},
    "uncertainty": {"increase_pct": {"mean": 0.0631, "sd": 0.361, "worst": 5.298}, "poses": 100, "trials": 100},
    "scenarios": {"smoothness": {"A": {"damped": 482, "fixed": 446, "rom": 410},
                                 "B": {"damped": 1140, "fixed": 426, "rom": 408}},
                  "note": "elbow paper Table I: S for DP (damped), FOP (fixed), NSO (rom)"},
}
"""Figures of the papers, written beside ours in each summary."""

SCENARIO_JOBS = tuple((sc, st) for sc in ("A", "B") for st in ("damped", "fixed", "rom", "gradient", "qp"))
"""The (scenario, strategy) pairs of the ``scenarios`` study, in job order."""


# ------------------------------------------------------------------ options
@dataclass(frozen=True)
class StudyOptions:
    """Settings of the studies (each study stores the ones it uses in its checkpoint header).

    ``grid_step_deg``: arm-angle grid of the extremum search (deg);
    ``singular_threshold``: smallest admissible singular value of ``J Jᵀ``;
    ``mass_shares``: weights ``w`` of the trade-off (mass share, friction 1 − w);
    ``trials``, ``friction_sd``: uncertainty trials per pose and relative sd of
    ``tau_max``; ``duration_scale``: fraction of the scenario paths to run;
    ``compile``: CasADi evaluation mode of the workers (:mod:`qpnso.model.codegen`).
    """

    robot: str = "lwr4p"
    grid_step_deg: float = 1.0
    singular_threshold: float = 1e-4
    mass_shares: tuple[float, ...] = (0.9, 0.5, 0.1)
    trials: int = 100
    friction_sd: float = 0.10
    duration_scale: float = 1.0
    compile: str = "off"

    def __post_init__(self) -> None:
        if not 0 < self.grid_step_deg <= 30:
            raise ConfigError(f"grid_step_deg must be in (0, 30], got {self.grid_step_deg}")
        if not self.singular_threshold >= 0:
            raise ConfigError(f"singular_threshold must be >= 0, got {self.singular_threshold}")
        if not self.mass_shares or any(not 0 <= w <= 1 for w in self.mass_shares):
            raise ConfigError(f"mass_shares must be weights in [0, 1], got {self.mass_shares}")
        if self.trials < 1 or not 0 <= self.friction_sd < 1:
            raise ConfigError(f"need trials >= 1 and 0 <= friction_sd < 1, got {self.trials}, {self.friction_sd}")
        if not 0 < self.duration_scale <= 1:
            raise ConfigError(f"duration_scale must be in (0, 1], got {self.duration_scale}")

    @classmethod
    def from_dict(cls, values: dict[str, Any] | None) -> "StudyOptions":
        values = dict(values or {})
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ConfigError(f"unknown study option(s) {unknown}; known: {sorted(known)}")
        defaults = cls()
        for key, value in values.items():
            values[key] = _coerce(key, value, getattr(defaults, key))
        return cls(**values)

    def subset(self, names: Sequence[str]) -> dict[str, Any]:
        data = asdict(self)
        return {k: list(data[k]) if isinstance(data[k], tuple) else data[k] for k in names}


def _coerce(key: str, value: Any, default: Any) -> Any:
    """``value`` converted to the type of the option's default (CLI strings accepted)."""
    try:
        if isinstance(default, tuple):
            items = value.split(",") if isinstance(value, str) else value
            return tuple(float(x) for x in items)
        if isinstance(default, (int, float)) and isinstance(value, str):
            return type(default)(float(value)) if isinstance(default, float) else int(value)
        return type(default)(value)
    except (TypeError, ValueError):
        raise ConfigError(f"study option {key}={value!r} is not a {type(default).__name__}") from None


# --------------------------------------------------------- measures along q
def curve_function(cost: CostModel) -> ca.Function:
    """``q → (c_m, Λv⁻¹, G)``: mass measure [M 8], Λv⁻¹ [M 2] (1/kg) and the friction Gram matrix.

    ``c_f = τmaxᵀ G τmax`` [M 13], [M 15] with ``G = Σ_i M_iᵀ M_i``,
    ``M_i = J̄vᵀ diag(a_i)``, ``a_i = (2/π) atan(β s J̄v e_i)``: the smooth Coulomb
    torque [M 23] is linear in ``τmax``, so one evaluation of ``G`` gives the
    friction cost of any sliding torques (the uncertainty study needs this).
    """
    tool = cost.tool
    a = smooth_coulomb(cost.potential_speed * tool.jbar_v, np.ones(cost.robot.nq), cost.robot.friction.beta)
    gram = ca.SX.zeros(cost.robot.nq, cost.robot.nq)
    for i in range(3):
        m = ca.mtimes(tool.jbar_v.T, ca.diag(a[:, i]))
        gram += ca.mtimes(m.T, m)
    return cost.sym.function("study_measures", {
        "mass": -ca.det(tool.lambda_inv_v),
        "lambda_inv_v": ca.reshape(tool.lambda_inv_v, 9, 1),
        "gram": ca.reshape(0.5 * (gram + gram.T), cost.robot.nq ** 2, 1),
    })


@dataclass(frozen=True)
class Measures:
    """Measures at N configurations ``q`` (N×nq, rad)."""

    q: np.ndarray
    mass_cost: np.ndarray  # c_m = −det Λv⁻¹ (kg⁻³), (N,)
    lambda_inv_v: np.ndarray  # (N, 3, 3), 1/kg, world axes
    gram: np.ndarray  # (N, nq, nq), c_f = τᵀ G τ (N² per (N·m)²)

    def friction_cost(self, tau_max: np.ndarray) -> np.ndarray:
        """c_f (N²) for joint sliding torques ``tau_max`` (N·m)."""
        return np.einsum("i,nij,j->n", tau_max, self.gram, tau_max)

    def friction_force(self, tau_max: np.ndarray) -> np.ndarray:
        """Magnitude √c_f (N) of the stacked potential friction forces."""
        return np.sqrt(np.maximum(self.friction_cost(tau_max), 0.0))

    def principal_mass(self) -> np.ndarray:
        """Largest principal mass (kg): 1/λ_min(Λv⁻¹)."""
        return 1.0 / np.linalg.eigvalsh(self.lambda_inv_v)[:, 0]


class Workbench:
    """Per-worker state: the robot, its normalised cost model and the measure functions."""

    def __init__(self, robot_name: str = "lwr4p", compile: str = "off") -> None:
        self.robot: Robot = load_robot(robot_name)
        self.cost = CostModel(self.robot, compile=compile)
        self._fn = curve_function(self.cost)
        self._one = FastFunction(self._fn, compile)
        self._maps: dict[int, ca.Function] = {}

    def measures(self, q: np.ndarray) -> Measures:
        """:class:`Measures` at configurations ``q`` (N×nq)."""
        q = np.atleast_2d(q)
        n, nq = q.shape
        if n == 1:
            mass, lam, gram = self._one(q[0])
            mass, lam, gram = np.array([mass]), np.asarray(lam)[:, None], np.asarray(gram)[:, None]
        else:
            fn = self._maps.get(n)
            if fn is None:
                fn = self._maps[n] = self._fn.map(n)
            mass, lam, gram = (np.asarray(x) for x in fn(q.T))
        return Measures(q, np.asarray(mass).reshape(-1), lam.T.reshape(n, 3, 3).transpose(0, 2, 1),
                        gram.T.reshape(n, nq, nq).transpose(0, 2, 1))

    def tau_max(self) -> np.ndarray:
        return self.robot.friction.tau_max


_BENCHES: dict[tuple[str, str], Workbench] = {}


def workbench(robot: str = "lwr4p", compile: str = "off") -> Workbench:
    """The worker's :class:`Workbench` (built once per process)."""
    key = (robot, compile)
    if key not in _BENCHES:
        _BENCHES[key] = Workbench(robot, compile)
    return _BENCHES[key]


# ----------------------------------------------------------- objectives
Objective = Callable[[Measures], np.ndarray]


def mass_objective(m: Measures) -> np.ndarray:
    """c_m [M 8]."""
    return m.mass_cost


def friction_objective(tau_max: np.ndarray) -> Objective:
    """c_f [M 15] with sliding torques ``tau_max`` (N·m)."""
    return lambda m: m.friction_cost(tau_max)


def weighted_objective(mass_share: float, scales: dict[str, float], tau_max: np.ndarray) -> Objective:
    """``w c_m/s_m + (1 − w) c_f/s_f`` [M 18], the normalisation of :class:`CostModel`."""
    wm, wf = mass_share / scales["mass"], (1.0 - mass_share) / scales["friction_force"]
    return lambda m: wm * m.mass_cost + wf * m.friction_cost(tau_max)


# ------------------------------------------------------- extremum search
@dataclass(frozen=True)
class Extremum:
    """A local extremum along the self-motion: arm angle (rad, unwrapped), value, posture."""

    ns: float
    value: float
    measures: Measures
    at_end: bool  # stopped by an end of the continuity interval (joint limit or singular cut)

    @property
    def q(self) -> np.ndarray:
        return self.measures.q[0]


def arm_angle_grid(ns0: float, interval: Interval, step: float) -> tuple[np.ndarray, int, bool]:
    """Grid of arm angles (rad) over the continuity interval: ``(grid, index of ns0, cyclic)``.

    ``ns0`` and the interval ends are grid points; spacing ≤ ``step``.  A full
    circle gives a cyclic grid starting at ``ns0`` (the last point is not repeated).
    """
    if interval.full_circle:
        m = max(4, math.ceil(2 * math.pi / step))
        return ns0 + 2 * math.pi * np.arange(m) / m, 0, True

    def side(a: float, b: float) -> np.ndarray:
        if b - a <= 0:
            return np.array([a])
        return np.linspace(a, b, math.ceil((b - a) / step) + 1)

    left, right = side(interval.lo, ns0), side(ns0, interval.hi)
    left[-1] = right[0] = ns0
    return np.concatenate([left, right[1:]]), left.size - 1, False


def descend(values: np.ndarray, start: int, cyclic: bool, direction: int = 0) -> int:
    """Index where a walk from ``start`` to ever lower neighbours stops (a grid local minimum).

    ``direction`` (+1/−1) is the side on which the objective decreases at the
    start (the sign of −gradient, which the grid cannot resolve when the start
    is near an extremum); 0 takes the lower neighbour.
    """
    n = values.size

    def neighbour(i: int, d: int) -> int | None:
        j = i + d
        if cyclic:
            return j % n
        return j if 0 <= j < n else None

    if direction == 0:
        lower = [d for d in (-1, 1) if (j := neighbour(start, d)) is not None and values[j] < values[start]]
        if not lower:
            return start
        direction = min(lower, key=lambda d: values[neighbour(start, d)])  # type: ignore[index]
    i, d = start, direction
    while True:
        j = neighbour(i, d)
        if j is None or not values[j] < values[i]:
            return i
        i = j


class SelfMotionCurve:
    """The self-motion of a start configuration ``q0`` (tool pose held), sampled on an arm-angle grid."""

    def __init__(self, bench: Workbench, q0: np.ndarray, step_rad: float) -> None:
        robot = bench.robot
        self.bench = bench
        self.q0 = robot.check_q(q0, "q0")
        self.interval = continuity_interval(robot, self.q0)
        self.motion: SelfMotion = self_motion(robot, robot.tool_pose(self.q0), branch(robot, self.q0))
        state = arm_angle_status(robot, self.q0)
        self.ns0 = float(state.value)
        self.grid, self.start, self.cyclic = arm_angle_grid(self.ns0, self.interval, step_rad)
        self.samples = self.measure(self.grid)
        gap = float(np.abs(self.samples.q[self.start] - self.q0).max())
        if gap > 1e-6:
            raise ModelError(f"closed-form IK at the start arm angle misses q0 by {gap:.3g} rad")

    def measure(self, ns: np.ndarray) -> Measures:
        return self.bench.measures(self.motion.joints(np.asarray(ns, dtype=float).reshape(-1)))

    def _descent_side(self, f: Callable[[float], float], delta: float = 1e-6) -> int | None:
        """+1/−1: the side on which ``f`` decreases at ``ns0``; None if it decreases on neither side
        (the start is the extremum, or an interval end blocks the descent)."""
        iv = self.interval
        up = self.cyclic or self.ns0 + delta <= iv.hi
        down = self.cyclic or self.ns0 - delta >= iv.lo
        f0 = f(self.ns0)
        f_up = f(self.ns0 + delta) if up else math.inf
        f_down = f(self.ns0 - delta) if down else math.inf
        if min(f_up, f_down) >= f0:
            return None
        return 1 if f_up < f_down else -1

    def extremum(self, objective: Objective, sense: str = "min", xatol: float = 1e-9) -> Extremum:
        """Local minimum (``sense="min"``) or maximum of ``objective`` reached from ``ns0``."""
        if sense not in ("min", "max"):
            raise InputError(f"sense must be 'min' or 'max', got {sense!r}")
        sign = 1.0 if sense == "min" else -1.0
        def f(ns: float) -> float:
            return sign * float(objective(self.measure(np.array([ns])))[0])

        values = sign * objective(self.samples)
        direction = self._descent_side(f)
        if direction is None:  # the gradient flow does not leave the start
            return self._extremum_at(self.ns0, sign * f(self.ns0))
        i = descend(values, self.start, self.cyclic, direction)
        n, h = self.grid.size, 2 * math.pi / self.grid.size
        if self.cyclic:
            a, b = self.grid[i] - h, self.grid[i] + h
        else:
            a, b = self.grid[max(i - 1, 0)], self.grid[min(i + 1, n - 1)]
        if i == self.start:  # minimum within the first cell on the descent side
            a, b = (self.ns0, b) if direction > 0 else (a, self.ns0)
        best_ns, best = float(self.grid[i]), float(values[i])
        if b > a:
            res = minimize_scalar(f, bounds=(a, b), method="bounded", options={"xatol": xatol})
            if float(res.fun) < best:
                best_ns, best = float(res.x), float(res.fun)
        return self._extremum_at(best_ns, sign * best)

    def _extremum_at(self, ns: float, value: float) -> Extremum:
        at_end = not self.cyclic and min(ns - self.interval.lo, self.interval.hi - ns) < 1e-6
        return Extremum(ns, value, self.measure(np.array([ns])), at_end)


# ----------------------------------------------------------- start poses
def sample_start(robot: Robot, rng: np.random.Generator, threshold: float, max_draws: int = 10000
                 ) -> tuple[np.ndarray, int]:
    """A uniform random configuration with ``σ_min(J Jᵀ) ≥ threshold`` and a defined arm angle.

    Returns ``(q, rejected draws)``.
    """
    for rejected in range(max_draws):
        q = robot.random_q(rng)
        jac = robot.jacobian(q)
        if np.linalg.svd(jac @ jac.T, compute_uv=False)[-1] >= threshold and arm_angle_status(robot, q).ok:
            return q, rejected
    raise SingularityError(f"no non-singular configuration in {max_draws} draws (threshold {threshold})")


def _start_curve(index: int, seed: int, opts: StudyOptions) -> tuple[SelfMotionCurve, int, np.random.Generator]:
    bench = workbench(opts.robot, opts.compile)
    rng = job_rng(seed, index)
    q0, rejected = sample_start(bench.robot, rng, opts.singular_threshold)
    return SelfMotionCurve(bench, q0, math.radians(opts.grid_step_deg)), rejected, rng


def _pose_record(curve: SelfMotionCurve, rejected: int) -> dict[str, Any]:
    iv = curve.interval
    return {"q0": curve.q0.tolist(), "ns0_deg": math.degrees(curve.ns0), "interval_lo_deg": math.degrees(iv.lo),
            "interval_hi_deg": math.degrees(iv.hi), "full_circle": bool(iv.full_circle), "rejected_draws": rejected}


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
    out.update(principal_mass_start_kg=m0, friction_force_start_N=f0, mass_opt_kg=m_opt, friction_opt_N=f_opt,
               optima_distance_rad=float(np.linalg.norm(mass_opt.q - fric_opt.q)))
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
    return {**_pose_record(curve, rejected), "friction_opt_N": f_true, "friction_opt_ns_deg": math.degrees(true_opt.ns),
            "increase_pct": increase, "perturbed_opt_ns_deg": ns}


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
    return {"scenario": name, "strategy": strategy, "safety_margin_deg": margin,
            **{k: float(v) for k, v in metrics.items()}}


# --------------------------------------------------------------- summaries
def stats(values: Sequence[float | None]) -> dict[str, float | int]:
    """mean, sd (n − 1), median, min, max, n of the finite values."""
    a = np.array([v for v in values if v is not None], dtype=float)
    a = a[np.isfinite(a)]
    if a.size == 0:
        return {"n": 0}
    return {"mean": float(a.mean()), "sd": float(a.std(ddof=1)) if a.size > 1 else 0.0, "median": float(np.median(a)),
            "min": float(a.min()), "max": float(a.max()), "n": int(a.size)}


def _fraction(results: list[dict], key: str) -> float:
    return float(np.mean([bool(r[key]) for r in results]))


def workspace_summary(results: list[dict], opts: StudyOptions) -> dict[str, Any]:
    return {
        "samples": len(results),
        "mass_reduction_pct": stats([r["mass_reduction_pct"] for r in results]),
        "friction_reduction_pct": stats([r["friction_reduction_pct"] for r in results]),
        "definition": "reduction = (value at the local-max posture - value at the local-min posture) / "
                      "value at the local-max posture * 100; mass: largest principal mass (kg) at the c_m "
                      "extrema; friction: sqrt(c_f) (N) at the c_f extrema",
        "stopped_at_interval_end": {f"{n}_{s}": _fraction(results, f"{n}_{s}_at_end")
                                    for n in ("mass", "friction") for s in ("min", "max")},
        "interior_only": {  # both extrema of the measure strictly inside the continuity interval
            f"{n}_reduction_pct": stats([r[f"{n}_reduction_pct"] for r in results
                                         if not (r[f"{n}_min_at_end"] or r[f"{n}_max_at_end"])])
            for n in ("mass", "friction")},
        "full_circle_fraction": _fraction(results, "full_circle"),
        "rejected_singular_draws": int(sum(r["rejected_draws"] for r in results)),
        "paper": PAPER["workspace"],
    }


def tradeoff_summary(results: list[dict], opts: StudyOptions) -> dict[str, Any]:
    out: dict[str, Any] = {"samples": len(results),
                           "optima_distance_rad": stats([r["optima_distance_rad"] for r in results])}
    for w in opts.mass_shares:
        key = _share_label(w)
        out[key] = {"mass_share": w, **{m: stats([r[f"{key}_{m}"] for r in results]) for m in (
            "mass_change_pct", "friction_change_pct", "mass_share_of_reduction_pct",
            "friction_share_of_reduction_pct")}}
    out["definition"] = ("change = (value at the weighted optimum - value at the single-objective optimum) / "
                         "value at the single-objective optimum * 100 (paper Fig. 4); share_of_reduction = "
                         "(start - weighted) / (start - single optimum) * 100")
    return out


def uncertainty_summary(results: list[dict], opts: StudyOptions) -> dict[str, Any]:
    inc = np.concatenate([r["increase_pct"] for r in results])
    s = stats(inc.tolist())
    s["worst"] = s.pop("max")
    return {"poses": len(results), "trials_per_pose": opts.trials, "friction_sd": opts.friction_sd,
            "increase_pct": s, "fraction_increased": float(np.mean(inc > 1e-9)),
            "fraction_decreased": float(np.mean(inc < -1e-9)), "paper": PAPER["uncertainty"],
            "perturbation": "tau_max_k * (1 + friction_sd * N(0, 1)) per joint and trial; "
                            "increase = (true sqrt(c_f) at the perturbed optimum - true optimum) / true optimum * 100"}


def scenarios_summary(results: list[dict], opts: StudyOptions) -> dict[str, Any]:
    keys = ("elbow_mobility_deg", "constraint_proximity_deg", "smoothness")
    table: dict[str, dict] = {}
    for r in results:
        row = {k: r.get(k) for k in keys}
        row["margin_respected"] = r.get("constraint_proximity_deg", -math.inf) >= r["safety_margin_deg"]
        table.setdefault(r["scenario"], {})[r["strategy"]] = row
    return {"table": table, "duration_scale": opts.duration_scale, "paper": PAPER["scenarios"]}


# --------------------------------------------------------------- outputs
def _atomic_bytes(path: Path, data: bytes) -> None:
    from qpnso.control.offline import atomic_write

    atomic_write(path, lambda f: f.write(data))


def _csv_bytes(rows: list[dict]) -> bytes:
    buf = io.StringIO()
    columns = list(rows[0]) if rows else []
    writer = csv.DictWriter(buf, columns, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue().encode()


def _flat(result: dict) -> dict:
    out = {}
    for k, v in result.items():
        if isinstance(v, list):
            out.update({f"{k}_{i + 1}": x for i, x in enumerate(v)})
        else:
            out[k] = v
    return out


def csv_rows(name: str, results: list[dict]) -> list[dict]:
    """Rows of ``results.csv``: one per job (uncertainty: one per trial)."""
    if name == "uncertainty":
        return [{"pose": i, "trial": t, "increase_pct": x, "perturbed_opt_ns_deg": ns, "friction_opt_N": r["friction_opt_N"]}
                for i, r in enumerate(results) for t, (x, ns) in enumerate(zip(r["increase_pct"], r["perturbed_opt_ns_deg"]))]
    return [{"job": i, **_flat(r)} for i, r in enumerate(results)]


def _figure_bytes(fig) -> bytes:  # type: ignore[no-untyped-def]
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120)
    plt.close(fig)
    return buf.getvalue()


def _plt():  # type: ignore[no-untyped-def]
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def plot_study(name: str, results: list[dict], summary: dict, opts: StudyOptions) -> bytes:
    """The study's figure as PNG bytes (paper Figs. 2, 4+5a, 6; bars for the scenarios)."""
    plt = _plt()
    if name == "workspace":
        fig, ax = plt.subplots(figsize=(7, 4))
        for key, label, colour in (("mass_reduction_pct", "largest principal mass", "tab:blue"),
                                   ("friction_reduction_pct", "friction force magnitude", "tab:red")):
            ax.plot(np.sort([r[key] for r in results]), color=colour, label=f"{label} (mean {summary[key]['mean']:.1f} %)")
        ax.set(xlabel="trial (sorted)", ylabel="reduction local max → local min (%)",
               title=f"{opts.robot}: {len(results)} random poses (paper Fig. 2)")
    elif name == "tradeoff":
        fig, axes = plt.subplots(1, 3, figsize=(13, 4))
        for ax, metric, what in ((axes[0], "mass_change_pct", "principal mass"),
                                 (axes[1], "friction_change_pct", "friction force")):
            for w in opts.mass_shares:
                key = _share_label(w)
                ax.plot(np.sort([r[f"{key}_{metric}"] for r in results]), label=f"{round(100 * w)}/{round(100 * (1 - w))}")
            ax.set(xlabel="trial (sorted)", ylabel=f"{what}: weighted vs single optimum (%)")
        axes[0].set_title("Fig. 4a"), axes[1].set_title("Fig. 4b")
        axes[2].plot(np.sort([r["optima_distance_rad"] for r in results]), color="k")
        axes[2].set(xlabel="trial (sorted)", ylabel="‖q_mass − q_friction‖ (rad)", title="Fig. 5a")
        ax = axes[1]
    elif name == "uncertainty":
        fig, ax = plt.subplots(figsize=(7, 4))
        inc = np.sort(np.concatenate([r["increase_pct"] for r in results]))
        ax.plot(inc, color="tab:red", label=f"mean {summary['increase_pct']['mean']:.3g} %, worst "
                                            f"{summary['increase_pct']['worst']:.3g} %")
        ax.set(xlabel="trial (sorted)", ylabel="true friction increase (%)", title="paper Fig. 6")
    else:
        fig, axes = plt.subplots(1, 3, figsize=(13, 4))
        strategies = [st for _, st in SCENARIO_JOBS[:5]]
        x = np.arange(len(strategies))
        for ax, metric in zip(axes, ("elbow_mobility_deg", "constraint_proximity_deg", "smoothness")):
            for k, sc in enumerate(("A", "B")):
                row = summary["table"].get(sc, {})
                ax.bar(x + 0.4 * k, [row.get(st, {}).get(metric) or 0.0 for st in strategies], 0.4, label=f"scenario {sc}")
            ax.set_xticks(x + 0.2, strategies)
            ax.set_title(metric)
        ax = axes[0]
    ax.legend()
    fig.tight_layout()
    return _figure_bytes(fig)


def scenarios_table(summary: dict) -> str:
    """Markdown in the layout of the elbow paper's Table I (plus Δ, Δc and the margin check)."""
    lines = ["| scenario | strategy | Δ (deg) | Δc (deg) | Δc ≥ margin | S | S paper |", "|---|---|---|---|---|---|---|"]
    paper = PAPER["scenarios"]["smoothness"]
    for sc, rows in summary["table"].items():
        for st, row in rows.items():
            fmt = lambda v, f: "n/a" if v is None else format(v, f)  # noqa: E731
            lines.append(f"| {sc} | {st} | {fmt(row['elbow_mobility_deg'], '.1f')} | "
                         f"{fmt(row['constraint_proximity_deg'], '.1f')} | {'yes' if row['margin_respected'] else 'no'} | "
                         f"{fmt(row['smoothness'], '.0f')} | {paper.get(sc, {}).get(st, '')} |")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------- registry
@dataclass(frozen=True)
class Study:
    """A study: its job, default size, the options it depends on, and its summary."""

    job: Callable[[int, int, StudyOptions], dict]
    default_n: int
    uses: tuple[str, ...]
    summarize: Callable[[list[dict], StudyOptions], dict]
    needs_workbench: bool = True
    fixed_n: int | None = None


_POSE_OPTIONS = ("robot", "grid_step_deg", "singular_threshold")
STUDIES: dict[str, Study] = {
    "workspace": Study(workspace_job, 1000, _POSE_OPTIONS, workspace_summary),
    "tradeoff": Study(tradeoff_job, 1000, (*_POSE_OPTIONS, "mass_shares"), tradeoff_summary),
    "uncertainty": Study(uncertainty_job, 100, (*_POSE_OPTIONS, "trials", "friction_sd"), uncertainty_summary),
    "scenarios": Study(scenarios_job, len(SCENARIO_JOBS), ("duration_scale",), scenarios_summary,
                       needs_workbench=False, fixed_n=len(SCENARIO_JOBS)),
}
"""The studies :func:`run_study` knows."""


def _run_job(name: str, options: dict[str, Any], index: int, seed: int) -> dict:
    """Module-level (picklable) job: study ``name``, job ``index``."""
    return STUDIES[name].job(index, seed, StudyOptions.from_dict(options))


def _init_worker(options: dict[str, Any]) -> None:
    """Process-pool initialiser: build the worker's :class:`Workbench` once."""
    opts = StudyOptions.from_dict(options)
    workbench(opts.robot, opts.compile)


def run_study(
    name: str,
    out: Path | str,
    n: int | None = None,
    seed: int = 0,
    workers: int | None = None,
    scheduler: Any = None,
    progress: bool = False,
    options: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Run (or resume) study ``name`` into folder ``out``; returns the summary written to ``summary.json``.

    ``n``: number of poses (default 1000 for workspace/tradeoff, 100 for
    uncertainty; scenarios: always the 10 pairs of :data:`SCENARIO_JOBS`, ``n``
    must be None or 10).  ``seed``: the study's seed (results are identical for
    any ``workers``/``scheduler``).  ``workers``: processes (default: all
    cores).  ``scheduler``: a Dask scheduler address (or cluster object) to run
    the jobs on instead.  ``options``: fields of :class:`StudyOptions`.
    """
    if name not in STUDIES:
        raise ConfigError(f"unknown study {name!r}; choose one of {sorted(STUDIES)}")
    study = STUDIES[name]
    opts = StudyOptions.from_dict(options)
    if study.fixed_n is not None and n not in (None, study.fixed_n):
        raise ConfigError(f"study {name} has {study.fixed_n} jobs (scenarios × strategies); do not give n={n}")
    n_jobs = study.default_n if n is None else int(n)
    if n_jobs < 1:
        raise ConfigError(f"n must be >= 1, got {n}")
    if name == "scenarios":
        try:
            import qpnso.lab.scenarios  # noqa: F401
        except ImportError as exc:
            raise ConfigError(f"the scenarios study needs qpnso.lab.scenarios, which cannot be imported: {exc}") from None
    stored = opts.subset(study.uses)
    worker_options = {**stored, "compile": opts.compile}
    spec = RunSpec(name, n_jobs, int(seed), stored)
    out = Path(out)
    t0 = time.perf_counter()
    results = run_jobs(spec, partial(_run_job, name, worker_options), out,
                       init=partial(_init_worker, worker_options) if study.needs_workbench else None,
                       workers=workers, scheduler=scheduler, progress=progress)
    summary = {"study": name, "seed": int(seed), "options": stored, **study.summarize(results, opts),
               "seconds": time.perf_counter() - t0}
    summary = _json_safe(summary)
    _atomic_bytes(out / "results.csv", _csv_bytes(csv_rows(name, results)))
    _atomic_bytes(out / f"{name}.png", plot_study(name, results, summary, opts))
    if name == "scenarios":
        _atomic_bytes(out / "table.md", scenarios_table(summary).encode())
    _atomic_bytes(out / "summary.json", (json.dumps(summary, indent=2) + "\n").encode())
    return summary


def _json_safe(data: Any) -> Any:
    """NaN/inf → None so that summary.json is strict JSON."""
    if isinstance(data, dict):
        return {k: _json_safe(v) for k, v in data.items()}
    if isinstance(data, (list, tuple)):
        return [_json_safe(v) for v in data]
    if isinstance(data, float) and not math.isfinite(data):
        return None
    return data
