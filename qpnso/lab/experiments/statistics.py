"""The papers' statistics on groups of trial values: SciPy's tests and scikit-posthocs' Dunn–Šidák.

* Mass/friction paper ([M] §V-C): Kolmogorov–Smirnov for normality, Kruskal–Wallis across strategies,
  Dunn's pairwise test with Šidák's correction; its Table I marks 1 where a pair differs at 0.01.
* Elbow paper ([E] §III): Kruskal–Wallis on medians, Bartlett on variances.

Every function takes ``groups``: strategy name → the trial values (1-D), in the order tables show them.
"""

from __future__ import annotations

import math
import warnings
from typing import Mapping

import numpy as np
from scipy import stats

from qpnso.errors import ConfigError


def spread(values) -> dict[str, float]:
    """Median, first and third quartiles, and count of ``values`` (NaNs dropped)."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if not v.size:
        return {"median": math.nan, "q1": math.nan, "q3": math.nan, "n": 0}
    q1, med, q3 = np.percentile(v, [25, 50, 75])
    return {"median": float(med), "q1": float(q1), "q3": float(q3), "n": int(v.size)}


def _clean(groups: Mapping[str, object]) -> dict[str, np.ndarray]:
    out = {}
    for name, values in groups.items():
        v = np.asarray(values, dtype=float)
        out[name] = v[np.isfinite(v)]
    return out


def normality(groups: Mapping[str, object]) -> dict[str, float]:
    """Kolmogorov–Smirnov p-value of each group against a normal law with the group's own mean and standard
    deviation (SciPy's ``kstest``; NaN for a group of fewer than 3 values or no spread)."""
    out = {}
    for name, v in _clean(groups).items():
        sd = float(np.std(v, ddof=1)) if v.size > 1 else 0.0
        out[name] = float(stats.kstest((v - v.mean()) / sd, "norm").pvalue) if v.size >= 3 and sd > 0 else math.nan
    return out


def kruskal(groups: Mapping[str, object]) -> dict[str, float]:
    """Kruskal–Wallis H and its p-value across the groups (NaN when all values are equal)."""
    g = [v for v in _clean(groups).values()]
    if len(g) < 2 or any(v.size == 0 for v in g):
        raise ConfigError("Kruskal-Wallis needs at least two non-empty groups")
    try:
        h, p = stats.kruskal(*g)
    except ValueError:  # (SciPy: all numbers are identical)
        return {"H": math.nan, "p": math.nan}
    return {"H": float(h), "p": float(p)}


def bartlett(groups: Mapping[str, object]) -> dict[str, float]:
    """Bartlett's statistic and p-value for equal variances across the groups."""
    g = [v for v in _clean(groups).values()]
    if len(g) < 2 or any(v.size < 2 for v in g):
        raise ConfigError("Bartlett's test needs at least two groups of two values or more")
    stat, p = stats.bartlett(*g)
    return {"statistic": float(stat), "p": float(p)}


def dunn_sidak(groups: Mapping[str, object]) -> dict[str, dict[str, float]]:
    """Pairwise Dunn's test p-values, Šidák-corrected (scikit-posthocs' ``posthoc_dunn``), as
    ``{a: {b: p}}`` for every ordered pair of groups (1 on the diagonal)."""
    try:
        import scikit_posthocs as sp
    except ImportError:
        raise ConfigError("the Dunn–Šidák test needs scikit-posthocs: pip install 'qpnso[experiments]'") from None
    clean = _clean(groups)
    names = list(clean)
    with warnings.catch_warnings():  # (statsmodels' Šidák takes log1p(-p): a p of exactly 1 warns, and stays 1)
        warnings.simplefilter("ignore", RuntimeWarning)
        table = sp.posthoc_dunn([clean[n] for n in names], p_adjust="sidak")
    values = np.asarray(table, dtype=float)
    return {a: {b: float(values[i, j]) for j, b in enumerate(names)} for i, a in enumerate(names)}


def significance_table(pvalues: Mapping[str, Mapping[str, float]], alpha: float = 0.01) -> str:
    """The layout of the mass/friction paper's Table I: 1 where a pair differs at ``alpha``, 0 where not,
    X on the diagonal; rows and columns in the groups' order (Markdown)."""
    names = list(pvalues)
    lines = ["| | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    for a in names:
        cells = ["X" if a == b else str(int(pvalues[a][b] < alpha)) for b in names]
        lines.append(f"| {a} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def pvalue_table(pvalues: Mapping[str, Mapping[str, float]]) -> str:
    """The Šidák-corrected p-values of :func:`dunn_sidak` as a Markdown table."""
    names = list(pvalues)
    lines = ["| | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    for a in names:
        lines.append(f"| {a} | " + " | ".join("—" if a == b else f"{pvalues[a][b]:.2g}" for b in names) + " |")
    return "\n".join(lines)
