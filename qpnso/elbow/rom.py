"""Elbow range of motion (ROM), its clipping to the continuity interval, stiffness
and set-point (docs/method.md §6, [E 5], [E 6], [E 10], [E 11]).

Angles are in rad in the functions; :class:`ElbowConfig` takes degrees for
convenience (``*_deg`` fields) and converts once (``*_rad`` properties).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numba import njit

from qpnso.elbow.intervals import Interval
from qpnso.errors import ConfigError, InputError


@dataclass(frozen=True)
class ElbowConfig:
    """Elbow ROM parameters (paper scenario A: ±50°, 10°, 10–30 N·m/rad).

    * ``half_width_deg`` Δns: the ROM is ``[ns0 − Δns, ns0 + Δns]`` [E 5];
    * ``safety_margin_deg`` d_sg: distance kept from the continuity interval's ends [E 10], [E 11];
    * ``stiffness_min``/``stiffness_max`` K_min/K_max (N·m/rad) of the double sigmoid [E 6];
    * ``alpha`` (1/rad): sigmoid slope parameter; ``None`` → 12/Δns, so K rises from
      ~5 % to ~95 % of its span over ±Δns/4 around the inflection point;
    * ``d`` (rad): inflection distance from ns0; ``None`` → 0.75·Δns (soft over the
      inner three quarters of the ROM, stiff at its ends).
    """

    half_width_deg: float = 50.0
    safety_margin_deg: float = 10.0
    stiffness_min: float = 10.0
    stiffness_max: float = 30.0
    alpha: float | None = None
    d: float | None = None

    def __post_init__(self) -> None:
        values = {
            k: getattr(self, k) for k in ("half_width_deg", "safety_margin_deg", "stiffness_min", "stiffness_max")
        }
        for key, value in values.items():
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise ConfigError(f"ElbowConfig.{key} must be a finite number >= 0, got {value!r}")
        if not 0 < self.half_width_deg <= 180:
            raise ConfigError(f"ElbowConfig.half_width_deg must be in (0, 180] deg, got {self.half_width_deg}")
        if self.stiffness_max < self.stiffness_min:
            raise ConfigError("ElbowConfig.stiffness_max must be >= stiffness_min (N·m/rad)")
        for key in ("alpha", "d"):
            value = getattr(self, key)
            if value is not None and (not math.isfinite(value) or value <= 0):
                raise ConfigError(f"ElbowConfig.{key} must be a positive finite number or None, got {value!r}")

    @cached_property
    def half_width_rad(self) -> float:
        return math.radians(self.half_width_deg)

    @cached_property
    def safety_margin_rad(self) -> float:
        return math.radians(self.safety_margin_deg)

    @cached_property
    def alpha_per_rad(self) -> float:
        return self.alpha if self.alpha is not None else 12.0 / self.half_width_rad

    @cached_property
    def d_rad(self) -> float:
        return self.d if self.d is not None else 0.75 * self.half_width_rad


RangeOfMotion = ElbowConfig
"""Alias: the ROM is configured by an :class:`ElbowConfig`."""


@dataclass(frozen=True)
class ClippedRom:
    """ROM_t (rad) [E 10], [E 11].  ``empty`` is True when the ROM and the
    margin-shrunk interval do not overlap; then ``lo == hi`` is the point of the
    shrunk interval nearest the ROM (or the interval's midpoint if the interval
    is narrower than twice the margin)."""

    lo: float
    hi: float
    empty: bool = False


def _finite(x: object, name: str) -> float:
    try:
        v = float(x)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {x!r}") from None
    if not math.isfinite(v):
        raise InputError(f"{name} must be finite, got {v}")
    return v


def rom_bounds(ns0: float, half_width: float) -> tuple[float, float]:
    """ROM ``[ns0 − Δns, ns0 + Δns]`` (rad) [E 5]."""
    ns0, half_width = _finite(ns0, "ns0"), _finite(half_width, "half_width")
    if half_width < 0:
        raise InputError(f"half_width must be >= 0 rad, got {half_width}")
    return ns0 - half_width, ns0 + half_width


def clip_rom(ns0: float, half_width: float, interval: Interval, margin: float) -> ClippedRom:
    """ROM_t = ROM ∩ [lo_i + d_sg, hi_i − d_sg] (rad) [E 10], [E 11].

    ``interval`` is unwrapped around the current arm angle; ``ns0`` is brought
    to the same unwrapping (the 2π shift nearest the interval's centre) first.
    A full-circle interval does not clip.  See :class:`ClippedRom` for the empty case.
    """
    margin = _finite(margin, "margin")
    if margin < 0:
        raise InputError(f"margin must be >= 0 rad, got {margin}")
    ns0, half_width = _finite(ns0, "ns0"), _finite(half_width, "half_width")
    if half_width < 0:
        raise InputError(f"half_width must be >= 0 rad, got {half_width}")
    return ClippedRom(*clipped_bounds(ns0, half_width, interval.lo, interval.hi, interval.full_circle, margin))


@njit(cache=True)
def clipped_bounds(
    ns0: float, half_width: float, lo: float, hi: float, full_circle: bool, margin: float
) -> tuple[float, float, bool]:
    """The arithmetic of :func:`clip_rom` on plain floats (rad), inputs taken as valid:
    ``(lo, hi, empty)`` of ROM_t for the interval ``[lo, hi]`` (the controller's per-tick kernel)."""
    centre = 0.5 * (lo + hi)
    ns0 = ns0 + 2 * math.pi * round((centre - ns0) / (2 * math.pi))
    rom_lo, rom_hi = ns0 - half_width, ns0 + half_width
    if full_circle:
        return rom_lo, rom_hi, False
    safe_lo, safe_hi = lo + margin, hi - margin
    if safe_lo > safe_hi:
        return centre, centre, True
    lo, hi = max(rom_lo, safe_lo), min(rom_hi, safe_hi)
    if lo > hi:
        point = safe_lo if rom_hi < safe_lo else safe_hi
        return point, point, True
    return lo, hi, False


def stiffness(ns: float | np.ndarray, ns0: float, cfg: ElbowConfig) -> float | np.ndarray:
    """Elbow stiffness (N·m/rad), double symmetric sigmoid [E 6]:
    ``K = (Kmax − Kmin)/(1 + exp(α (d − |ns − ns0|))) + Kmin``."""
    value = ns if isinstance(ns, float) else np.asarray(ns, dtype=float)
    params = (float(ns0), cfg.stiffness_min, cfg.stiffness_max, cfg.alpha_per_rad, cfg.d_rad)
    if np.ndim(value) == 0:  # one arm angle: a float (also without the JIT, where the kernel gives NumPy's)
        return float(sigmoid_stiffness(float(value), *params))
    return sigmoid_stiffness(value, *params)


@njit(cache=True)
def sigmoid_stiffness(ns, ns0, k_min, k_max, alpha, d):
    """:func:`stiffness` of an arm angle or an array of them (rad) from plain parameters (N·m/rad,
    1/rad, rad): the per-tick kernel.  ``1/(1 + eˣ) = ½(1 − tanh(x/2))``, which cannot overflow."""
    x = alpha * (d - np.abs(ns - ns0))
    return (k_max - k_min) * 0.5 * (1.0 - np.tanh(0.5 * x)) + k_min


def setpoint(ns: float, rom_t: ClippedRom | tuple[float, float]) -> float:
    """Arm-angle set-point ns_des (rad): follows ``ns`` inside ROM_t, saturated at its ends ([E] Fig. 2)."""
    lo, hi = (rom_t.lo, rom_t.hi) if isinstance(rom_t, ClippedRom) else rom_t
    return min(max(_finite(ns, "ns"), lo), hi)
