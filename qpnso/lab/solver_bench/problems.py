"""A recorded QP and its files: :class:`BenchProblem` (one level's QP of one tick, in the two-sided form
ProxSuite gets), :func:`standard_form` (the ``Gv ≤ h, Av = b, lb ≤ v ≤ ub`` form every ``qpsolvers`` back
end gets, with the map of its rows back to the two-sided ones) and the problem-set files
(:func:`save_problems`, :func:`load_problems`: one compressed ``.npz``, no pickle).

Every other module of the benchmark speaks in these two forms; the files keep a set reproducible
without re-running the controller.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np

from qpnso.errors import InputError
from qpnso.shipped import shipped_dir

if TYPE_CHECKING:
    import qpsolvers

PROBLEM_DIR = shipped_dir("solver_problems")
"""Where the committed problem set is (``solvers/problems`` of the source tree; a wheel ships ``quick.npz``)."""


@dataclass
class BenchProblem:
    """One level's QP of one tick, in the variable ``v = [z; σ]`` of its cascade level (:mod:`qpnso.qp.cascade_state`).

    ``min ½vᵀPv + qᵀv`` s.t. ``l ≤ Cv ≤ u`` and ``box_l ≤ v ≤ box_u`` (None: no box).
    ``x_prev`` (n,) and ``Z`` (n, r) decode a solution into joint velocity
    ``x = x_prev + Z v[:r]`` (rad/s); ``x_controller`` is what the controller's
    solver answered for this level (rad/s).  ``ref_v``/``ref_obj``: high-accuracy
    reference solution and cost (:func:`compute_reference`).  ``sequence`` groups
    consecutive ticks of one run (one warm-started ProxSuite object per sequence and level).
    """

    name: str
    sequence: str
    level: int  # 1-based
    tick: int
    P: np.ndarray
    q: np.ndarray
    C: np.ndarray
    l: np.ndarray
    u: np.ndarray
    box_l: np.ndarray | None
    box_u: np.ndarray | None
    x_prev: np.ndarray
    Z: np.ndarray
    x_controller: np.ndarray | None = None
    ref_v: np.ndarray | None = None
    ref_obj: float | None = None
    ref_solver: str = ""
    ref_spread: float | None = None  # largest |cost − ref_obj| of the cross-checking solvers

    @property
    def nv(self) -> int:
        return self.P.shape[0]

    def objective(self, v: np.ndarray) -> float:
        """``½vᵀPv + qᵀv``."""
        return float(0.5 * v @ self.P @ v + self.q @ v)

    def decode(self, v: np.ndarray) -> np.ndarray:
        """Joint velocity (rad/s) of a solution ``v``."""
        return self.x_prev + self.Z @ v[: self.Z.shape[1]]


@dataclass
class StandardForm:
    """``qpsolvers.Problem`` of a :class:`BenchProblem` and how its rows map back.

    ``g_src``/``g_sign``: each row of ``G`` is ``g_sign·C[g_src]`` (``g_src ≥ 0``)
    or ``g_sign·e_j`` of a folded box entry ``j = −1 − g_src``; ``a_src``: the
    ``C`` row of each equality; ``box``: the box is ``lb/ub`` of the problem.
    """

    problem: qpsolvers.Problem
    g_src: np.ndarray
    g_sign: np.ndarray
    a_src: np.ndarray
    box: bool

    def duals(self, z_rows: np.ndarray, z_box: np.ndarray | None):
        """``(y, z, z_box)`` of the standard form from two-sided duals (ProxSuite's sign:
        ``> 0`` upper side active, ``< 0`` lower side active)."""
        zb = np.zeros(0) if z_box is None else z_box
        src = np.where(
            self.g_src >= 0,
            z_rows[np.maximum(self.g_src, 0)] if z_rows.size else 0.0,
            zb[np.maximum(-1 - self.g_src, 0)] if zb.size else 0.0,
        )
        z = np.maximum(self.g_sign * src, 0.0)
        y = z_rows[self.a_src]
        return (y if y.size else None), (z if z.size else None), (z_box if self.box else None)


def standard_form(p: BenchProblem) -> StandardForm:
    """``Gv ≤ h, Av = b, lb ≤ v ≤ ub`` of a two-sided problem (finite sides only).

    A box with an infinite side (a slack) is folded into ``G`` (quadprog & co.
    turn a box into rows, where ∓inf breaks them); a finite box stays a box.
    """
    import qpsolvers

    eq = np.isfinite(p.l) & (p.l == p.u)
    up = np.isfinite(p.u) & ~eq
    down = np.isfinite(p.l) & ~eq
    rows = [p.C[up], -p.C[down]]
    h = [p.u[up], -p.l[down]]
    g_src = [np.flatnonzero(up), np.flatnonzero(down)]
    g_sign = [np.ones(up.sum()), -np.ones(down.sum())]
    box_l, box_u = p.box_l, p.box_u  # both None (no box) or both arrays
    box = box_l is not None and box_u is not None and bool(np.isfinite(box_l).all() and np.isfinite(box_u).all())
    if box_l is not None and box_u is not None and not box:
        eye = np.eye(p.nv)
        for side, bound, sign in ((np.isfinite(box_u), box_u, 1.0), (np.isfinite(box_l), box_l, -1.0)):
            idx = np.flatnonzero(side)
            rows.append(sign * eye[idx])
            h.append(sign * bound[idx])
            g_src.append(-1 - idx)
            g_sign.append(np.full(idx.size, sign))
    G, hv = np.vstack(rows), np.concatenate(h)
    A, b = p.C[eq], p.l[eq]
    problem = qpsolvers.Problem(
        p.P,
        p.q,
        G if hv.size else None,
        hv if hv.size else None,
        A if b.size else None,
        b if b.size else None,
        p.box_l if box else None,
        p.box_u if box else None,
    )
    return StandardForm(problem, np.concatenate(g_src).astype(int), np.concatenate(g_sign), np.flatnonzero(eq), box)


_ARRAYS = ("P", "q", "C", "l", "u", "box_l", "box_u", "x_prev", "Z", "x_controller", "ref_v")
_SCALARS = ("name", "sequence", "level", "tick", "ref_obj", "ref_solver", "ref_spread")


def save_problems(path: Path, problems: Sequence[BenchProblem], meta: dict | None = None) -> Path:
    """Write a problem set as one compressed ``.npz`` (each field's arrays concatenated, no pickle)."""
    if not problems:
        raise InputError("no problems to save")
    data: dict[str, np.ndarray] = {}
    for name in _ARRAYS:
        arrays = [getattr(p, name) for p in problems]
        shapes = np.array(
            [(-1, -1) if a is None else (a.shape + (1,))[:2] if a.ndim == 1 else a.shape for a in arrays],
            dtype=np.int64,
        )
        ndims = np.array([0 if a is None else a.ndim for a in arrays], dtype=np.int8)
        data[f"{name}__data"] = np.concatenate([np.zeros(0)] + [a.ravel() for a in arrays if a is not None])
        data[f"{name}__shape"], data[f"{name}__ndim"] = shapes, ndims
    table = [{k: getattr(p, k) for k in _SCALARS} for p in problems]
    data["__index"] = np.array(json.dumps(table))
    data["__meta"] = np.array(json.dumps(meta or {}))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **data)  # type: ignore[arg-type]  # NumPy's stub: **data could be allow_pickle
    return path


def load_problems(path: Path) -> tuple[list[BenchProblem], dict]:
    """Read a set written by :func:`save_problems`: ``(problems, meta)``."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"problem set not found: {path}")
    with np.load(path, allow_pickle=False) as f:
        table = json.loads(str(f["__index"]))
        meta = json.loads(str(f["__meta"]))
        columns = {}
        for name in _ARRAYS:
            flat, shapes, ndims = f[f"{name}__data"], f[f"{name}__shape"], f[f"{name}__ndim"]
            col: list[np.ndarray | None] = []
            pos = 0
            for (r, c), nd in zip(shapes, ndims):
                if nd == 0:
                    col.append(None)
                    continue
                size = int(r * c)
                a = flat[pos : pos + size]
                col.append(a.reshape(r, c) if nd == 2 else a.copy())
                pos += size
            columns[name] = col
    problems = [BenchProblem(**{**row, **{k: columns[k][i] for k in _ARRAYS}}) for i, row in enumerate(table)]
    return problems, meta
