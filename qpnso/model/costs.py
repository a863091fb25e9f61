"""Mass, inertia and friction costs felt at the tool, with exact derivatives.

The measures of the mass/friction paper (docs/method.md §2–3), as CasADi expressions of
``q`` built once per robot from :class:`qpnso.model.symbolic.SymbolicModel`:

* ``Λv⁻¹ = Jv A⁻¹ Jvᵀ``, ``Λw⁻¹ = Jw A⁻¹ Jwᵀ`` [M 2] (3×3, 1/kg and
  1/(kg·m²)), with ``J`` the world-aligned tool Jacobian;
* mass ``c_m = -det(Λv⁻¹)`` and inertia ``c_i = -det(Λw⁻¹)`` [M 8];
* friction force ``c_f = Σ_i ‖J̄vᵀ τf(J̄v s e_i)‖²`` [M 13], [M 15] (N²) and
  friction torque ``c_τ = Σ_i ‖J̄wᵀ τf(J̄w s_w e_i)‖²`` [M 16] (N²·m²), with the
  dynamically consistent inverses ``J̄ = A⁻¹ Jᵀ Λ`` [M 2], the potential
  speeds ``s`` (m/s), ``s_w`` (rad/s) and the smooth Coulomb model [M 23];
* the weighted total ``c = Σ_k w_k c_k / scale_k`` [M 18].

The terms have different units, so by default each is divided by its median
magnitude over random configurations of the robot (``CostModel.scales``):
weights of 1 and 1 then mean "50 % mass, 50 % friction" as in the paper.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import casadi as ca
import numpy as np

from qpnso.errors import InputError
from qpnso.model.codegen import FastFunction
from qpnso.model.robot import Robot, as_vector
from qpnso.model.symbolic import SymbolicModel
from qpnso.settings import check, keywords_checked, out_of_range
from qpnso.settings import from_dict as settings_from_dict

TERMS = ("mass", "inertia", "friction_force", "friction_torque")

FELT_CHUNK = 256
"""Configurations per call of :meth:`CostModel.felt_function` (a run is evaluated in chunks of this many)."""


def principal_masses(lambda_inv_v: np.ndarray) -> np.ndarray:
    """Largest principal mass (kg) of each Λv⁻¹ (…, 3, 3; 1/kg) [M 8]: 1/λ_min."""
    return 1.0 / np.linalg.eigvalsh(lambda_inv_v)[..., 0]


"""Names of the four cost terms of [M 18], in order."""


@keywords_checked
@dataclass(frozen=True)
class CostWeights:
    """Weights ``w_m, w_i, w_f, w_τ`` of the combined cost [M 18] (dimensionless).

    Default: 50 % mass, 50 % friction force, as in the paper.
    """

    mass: float = 1.0
    inertia: float = 0.0
    friction_force: float = 1.0
    friction_torque: float = 0.0

    def __post_init__(self) -> None:
        """Types first (finite numbers, :func:`qpnso.settings.check`), then each weight >= 0."""
        check(self)
        for f in fields(self):
            if getattr(self, f.name) < 0:
                raise out_of_range(self, f.name, "cost weight must be >= 0")

    @classmethod
    def from_dict(cls, values: dict, where: str = "") -> "CostWeights":
        """Build from plain data (a ``[weights]`` table); unknown keys are listed with the valid ones."""
        return settings_from_dict(cls, values, where)

    def as_array(self) -> np.ndarray:
        """Weights in the order of :data:`TERMS`."""
        return np.array([getattr(self, t) for t in TERMS], dtype=float)


@dataclass(frozen=True)
class ToolExpressions:
    """CasADi expressions of the quantities of docs/method.md §2 at the tool point."""

    lambda_inv_v: ca.SX  # Λv⁻¹ (3×3, 1/kg)
    lambda_inv_w: ca.SX  # Λw⁻¹ (3×3, 1/(kg·m²))
    jbar_v: ca.SX  # J̄v (nq×3)
    jbar_w: ca.SX  # J̄w (nq×3)


def tool_expressions(sym: SymbolicModel, tool_frame_id: int) -> ToolExpressions:
    """Λ⁻¹ and dynamically consistent inverses [M 1]–[M 6] as expressions of q."""
    a = sym.mass_matrix()
    jac = sym.frame_jacobian(tool_frame_id)
    parts = []
    for rows in (slice(0, 3), slice(3, 6)):
        jt = jac[rows, :].T
        a_inv_jt = ca.solve(a, jt)  # A⁻¹ Jᵀ (nq×3)
        lam_inv = ca.mtimes(jac[rows, :], a_inv_jt)
        lam_inv = 0.5 * (lam_inv + lam_inv.T)
        parts.append((lam_inv, ca.mtimes(a_inv_jt, ca.inv(lam_inv))))
    return ToolExpressions(parts[0][0], parts[1][0], parts[0][1], parts[1][1])


def smooth_coulomb(dq: ca.SX, tau_max: np.ndarray, beta: np.ndarray) -> ca.SX:
    """τf = τmax·(2/π)·atan(β·dq) [M 23], row k scaled by joint k's parameters."""
    n, m = dq.shape
    tau = ca.repmat(ca.DM(tau_max), 1, m)
    b = ca.repmat(ca.DM(beta), 1, m)
    return tau * (2.0 / np.pi) * ca.atan(b * dq)


def potential_friction(jbar: ca.SX, speed: float, tau_max: np.ndarray, beta: np.ndarray) -> ca.SX:
    """Σ_i ‖J̄ᵀ τf(J̄ · speed · e_i)‖² [M 13]–[M 16]: squared tool friction over 3 axes."""
    torques = smooth_coulomb(speed * jbar, tau_max, beta)  # column i: τf(q̇P,i)
    forces = ca.mtimes(jbar.T, torques)  # column i: friction felt at the tool
    return ca.sumsqr(forces)


class CostModel:
    """Weighted mass/friction cost of a robot, its exact gradient and Hessian.

    ``potential_speed`` (m/s) is the tool speed ``s`` of [M 13] (0.05 m/s in the
    paper); ``potential_angular_speed`` (rad/s) is ``s_w`` for the friction
    torque (our choice: 0.5 rad/s).  ``scales`` fixes the normaliser of each
    term; by default it is the median |term| over ``n_scale_samples`` random
    configurations (seed 0), or 1 with ``normalize=False``.  ``compile``
    chooses how the value/gradient function is evaluated (see
    :mod:`qpnso.model.codegen`; default from ``QPNSO_COMPILE``).
    """

    def __init__(
        self,
        robot: Robot,
        weights: CostWeights | None = None,
        potential_speed: float = 0.05,
        potential_angular_speed: float = 0.5,
        normalize: bool = True,
        scales: dict[str, float] | None = None,
        n_scale_samples: int = 200,
        compile: str | None = None,
    ) -> None:
        if not (potential_speed > 0 and potential_angular_speed > 0):
            raise InputError("potential speeds must be > 0 (m/s, rad/s)")
        self.robot = robot
        self.weights = weights or CostWeights()
        self.potential_speed = float(potential_speed)
        self.potential_angular_speed = float(potential_angular_speed)
        mode = compile
        self.sym = SymbolicModel(robot.model)
        self.tool = tool_expressions(self.sym, robot.tool_frame_id)
        self._term_exprs = self._build_terms()
        self._terms_sym = self.sym.function("cost_terms", {"terms": ca.vertcat(*self._term_exprs)})
        self._terms_fn = FastFunction(self._terms_sym, mode)
        self._lambda_fn = FastFunction(
            self.sym.function("lambda_inv", {"v": self.tool.lambda_inv_v, "w": self.tool.lambda_inv_w}), "off"
        )
        self._mode = mode
        self._felt_fn: FastFunction | None = None  # felt_function(), made when first asked for
        self.scales = self._resolve_scales(normalize, scales, n_scale_samples)
        total = self._total_expression()
        self.expression = total
        """The weighted total as a CasADi SX of ``sym.q`` (for embedding in other functions)."""
        self._value_grad_fn = FastFunction(
            self.sym.function("cost_value_gradient", {"value": total, "gradient": ca.gradient(total, self.sym.q)}),
            mode,
        )
        self._last_q: np.ndarray | None = None
        self._last: tuple[float, np.ndarray] = (0.0, np.zeros(robot.nq))
        self._hessian_fn: ca.Function | None = None
        self._hvp_fn: ca.Function | None = None

    # --------------------------------------------------------- construction
    def _build_terms(self) -> list[ca.SX]:
        f = self.robot.friction
        return [
            -ca.det(self.tool.lambda_inv_v),
            -ca.det(self.tool.lambda_inv_w),
            potential_friction(self.tool.jbar_v, self.potential_speed, f.tau_max, f.beta),
            potential_friction(self.tool.jbar_w, self.potential_angular_speed, f.tau_max, f.beta),
        ]

    def _resolve_scales(self, normalize: bool, scales: dict[str, float] | None, n: int) -> dict[str, float]:
        if scales is not None:
            unknown = set(scales) - set(TERMS)
            if unknown:
                raise InputError(f"unknown cost term(s) in scales: {sorted(unknown)}; known: {TERMS}")
            out = {t: float(scales.get(t, 1.0)) for t in TERMS}
        elif not normalize:
            out = {t: 1.0 for t in TERMS}
        else:
            out = self._sampled_scales(n)
        if any(not np.isfinite(v) or v <= 0 for v in out.values()):
            raise InputError(f"cost scales must be finite and > 0, got {out}")
        return out

    def _sampled_scales(self, n: int) -> dict[str, float]:
        """Median |term| over ``n`` random configurations (seed 0, 0.1 rad inside limits)."""
        rng = np.random.default_rng(0)
        qs = np.array([self.robot.random_q(rng, margin=0.1) for _ in range(n)]).T
        values = np.abs(np.array(self._terms_sym.map(n)(qs)))
        values = values[:, np.all(np.isfinite(values), axis=0)]
        return {t: float(np.median(values[k])) for k, t in enumerate(TERMS)}

    def _total_expression(self) -> ca.SX:
        total = ca.SX(0)
        for w, t, expr in zip(self.weights.as_array(), TERMS, self._term_exprs):
            if w != 0.0:
                total += (w / self.scales[t]) * expr
        return total

    # ------------------------------------------------------------ evaluation
    def _q(self, q: object) -> np.ndarray:
        return as_vector(q, self.robot.nq, "q")

    def value(self, q: object) -> float:
        """Weighted total cost c(q) [M 18] (dimensionless with normalisation)."""
        return self.value_and_gradient(q)[0]

    def gradient(self, q: object) -> np.ndarray:
        """Exact gradient ∇c(q) (per rad), from CasADi's automatic differentiation."""
        return self.value_and_gradient(q)[1].copy()

    def value_and_gradient(self, q: object) -> tuple[float, np.ndarray]:
        """Both from one evaluation; the last one is reused for the same ``q``."""
        qv = self._q(q)
        if self._last_q is None or not np.array_equal(qv, self._last_q):
            self._last = self._value_grad_fn(qv)
            self._last_q = qv.copy()
        return self._last

    def hessian(self, q: object) -> np.ndarray:
        """Exact Hessian ∇²c(q) (nq×nq); its function is built on first use."""
        if self._hessian_fn is None:
            h, _ = ca.hessian(self.expression, self.sym.q)
            self._hessian_fn = self.sym.function("cost_hessian", {"hessian": h})
        return np.array(self._hessian_fn(self._q(q)))

    def hessian_vector(self, q: object, v: object) -> np.ndarray:
        """Exact Hessian-vector product ∇²c(q)·v (forward over reverse AD)."""
        if self._hvp_fn is None:
            vs = ca.SX.sym("v", self.robot.nq)
            hv = ca.jtimes(ca.gradient(self.expression, self.sym.q), self.sym.q, vs)
            self._hvp_fn = ca.Function("cost_hvp", [self.sym.q, vs], [hv], ["q", "v"], ["hv"])
        vv = as_vector(v, self.robot.nq, "v")
        return np.array(self._hvp_fn(self._q(q), vv)).reshape(-1)

    def terms(self, q: object) -> dict[str, float]:
        """Unweighted, unscaled measures c_m, c_i, c_f, c_τ of docs/method.md §3."""
        (values,) = self._terms_fn(self._q(q))
        return {t: float(v) for t, v in zip(TERMS, values)}

    def lambda_inv(self, q: object) -> tuple[np.ndarray, np.ndarray]:
        """(Λv⁻¹ in 1/kg, Λw⁻¹ in 1/(kg·m²)), 3×3 each, world axes."""
        return self._lambda_fn(self._q(q))

    # ---------------------------------------------- what a user understands
    def principal_mass(self, q: object) -> float:
        """Largest principal mass felt at the tool (kg): 1/λ_min(Λv⁻¹) (:func:`principal_masses`)."""
        return float(principal_masses(self.lambda_inv(q)[0]))

    def felt(self, qs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What the hand feels at each configuration of ``qs`` (N, nq; rad): the largest principal mass
        (kg, 1/λ_min(Λv⁻¹) [M 8]) and the potential friction force magnitude (N, √c_f [M 15]), each (N,); one
        mapped CasADi evaluation per chunk of :data:`FELT_CHUNK` (a run's recorder evaluates its whole run at once;
        one configuration: :meth:`principal_mass`, :meth:`friction_force_magnitude`)."""
        qs = np.asarray(qs, dtype=float).reshape(-1, self.robot.nq)
        n = qs.shape[0]
        fn = self.felt_function()
        lam, friction = np.empty((n, 3, 3)), np.empty(n)
        for start in range(0, n, FELT_CHUNK):
            chunk = qs[start : start + FELT_CHUNK]
            k = chunk.shape[0]
            if k < FELT_CHUNK:  # the last chunk padded with its last configuration
                chunk = np.vstack([chunk, np.repeat(chunk[-1:], FELT_CHUNK - k, axis=0)])
            lam_v, force = fn(chunk.T)
            lam[start : start + k] = lam_v.T[:k].reshape(k, 3, 3)  # (Λv⁻¹ is symmetric: either order)
            friction[start : start + k] = np.ravel(force)[:k]
        return principal_masses(lam), np.sqrt(friction)

    def felt_function(self) -> FastFunction:
        """``(nq × FELT_CHUNK configurations) → (Λv⁻¹ as 9 × FELT_CHUNK, c_f as 1 × FELT_CHUNK)``: one mapped
        CasADi function, compiled like the tick's (``QPNSO_COMPILE``) when first asked for (a run's recorder
        asks at its start, so that a background compile is done by its end)."""
        if self._felt_fn is None:
            one = self.sym.function(
                "felt",
                {
                    "lambda_v": ca.reshape(self.tool.lambda_inv_v, 9, 1),
                    "friction_force": self._term_exprs[TERMS.index("friction_force")],
                },
            )
            self._felt_fn = FastFunction(one.map(FELT_CHUNK), self._mode)
        return self._felt_fn

    def effective_mass(self, q: object, direction: object) -> float:
        """Effective mass (kg) along a world direction: 1/(uᵀΛv⁻¹u) [M 10]."""
        u = unit_vector(direction)
        return float(1.0 / (u @ self.lambda_inv(q)[0] @ u))

    def friction_force_magnitude(self, q: object) -> float:
        """Magnitude (N) of the stacked potential friction forces: √c_f [M 15]."""
        return float(np.sqrt(self.terms(q)["friction_force"]))

    def directional(
        self, directions: object, weights: object = None, exponent: int = 1, kind: str = "mass"
    ) -> "DirectionalCost":
        """The multi-direction measure Σ w_i (u_iᵀΛ⁻¹u_i)^exponent [M 11], [M 12]."""
        return DirectionalCost(self, directions, weights, exponent, kind)

    def wait_compiled(self, timeout: float | None = None) -> bool:
        """Block until the compiled evaluation is ready (benchmarks call this)."""
        return self._value_grad_fn.wait(timeout) and self._terms_fn.wait(timeout)

    def describe(self) -> dict[str, object]:
        """Settings as plain data (for summaries and ``qpnso info``)."""
        return {
            "weights": asdict(self.weights),
            "scales": dict(self.scales),
            "potential_speed_m_per_s": self.potential_speed,
            "potential_angular_speed_rad_per_s": self.potential_angular_speed,
        }


def unit_vector(u: object) -> np.ndarray:
    """``u`` normalised; InputError for a zero, NaN or wrong-shape vector."""
    v = as_vector(u, 3, "direction")
    norm = np.linalg.norm(v)
    if norm < 1e-12:
        raise InputError("direction must be a non-zero 3-vector")
    return v / norm


class DirectionalCost:
    """Σ_i w_i (u_iᵀ Λ⁻¹ u_i)^p over world directions u_i [M 11], [M 12].

    With one direction, weight −1 and p = 1 this is ``c_dm = -uᵀΛv⁻¹u`` [M 11];
    with p = −1 and positive weights, a weighted sum of effective masses (kg).
    ``kind`` is ``"mass"`` (Λv) or ``"inertia"`` (Λw).
    """

    def __init__(self, cost: CostModel, directions: object, weights: object, exponent: int, kind: str) -> None:
        if kind not in ("mass", "inertia"):
            raise InputError(f"kind must be 'mass' or 'inertia', got {kind!r}")
        if exponent not in (1, -1):
            raise InputError(f"exponent must be 1 or -1, got {exponent}")
        dirs = np.atleast_2d(np.asarray(directions, dtype=float))
        units = np.array([unit_vector(d) for d in dirs])
        w = -np.ones(len(units)) if weights is None else as_vector(weights, len(units), "weights")
        lam = cost.tool.lambda_inv_v if kind == "mass" else cost.tool.lambda_inv_w
        expr = ca.SX(0)
        for wi, u in zip(w, units):
            quad = ca.mtimes([ca.DM(u).T, lam, ca.DM(u)])
            expr += wi * (quad if exponent == 1 else 1.0 / quad)
        self._nq = cost.robot.nq
        self._fn = cost.sym.function("directional", {"value": expr, "gradient": ca.gradient(expr, cost.sym.q)})

    def value(self, q: object) -> float:
        return float(self._fn(as_vector(q, self._nq, "q"))[0])

    def gradient(self, q: object) -> np.ndarray:
        return np.array(self._fn(as_vector(q, self._nq, "q"))[1]).reshape(-1)
