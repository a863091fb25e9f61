"""The velocity damper every constraint row uses (docs/method.md §7.2)."""

from __future__ import annotations

from numba import njit


@njit(cache=True)
def damper(value, lo, hi, gain, recovery):
    """``(l, u)`` of the row ``l ≤ ḣ ≤ u`` that keeps ``value`` = h(q) in ``[lo, hi]``: ``γ(lo − h) ≤ ḣ ≤
    γ(hi − h)`` (γ = ``gain``, 1/s; γ·dt ≤ 1: h never crosses a bound), and outside ``[lo, hi]`` back at
    rate γ but at most ``recovery`` (units of h per s): a fast return would drag the held tool (its
    second-order drift grows as q̇²).  ∓inf bounds give ∓inf sides."""
    return min(gain * (lo - value), recovery), max(gain * (hi - value), -recovery)
