"""What the surgeon does during an episode: random phases (held tool, smooth twists, violent pulls,
overshoots past a limit), the tool twist of each tick, and the tool reference integrated by the
controller's own documented rule.

The fuzzer integrates the reference itself so that the drift and recovery checks measure the tool
against what the controller was told, not against what it believes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from qpnso.control.strategies import clip_norm
from qpnso.lab.fuzz.config import FuzzConfig


@dataclass
class Phase:
    """A stretch of an episode: ``kind`` hold | twist | pull | overshoot (an instant: the joint nearest a limit
    pushed past it, when near one; then held), ``ticks`` long;
    twists are smooth random sinusoids (``amp`` (6,), ``freq`` Hz, ``phi`` rad) or a constant pull (``amp``)."""

    kind: str
    ticks: int
    amp: np.ndarray | None = None
    freq: np.ndarray | None = None
    phi: np.ndarray | None = None


def plan_phases(rng: np.random.Generator, config: FuzzConfig, ticks: int) -> list[Phase]:
    """Random phases covering ``ticks``: a held start, then held, twist, pull (+ settle) and overshoot (+ settle)."""
    phases = [Phase("hold", int(rng.integers(50, 200)))]
    total = phases[0].ticks
    while total < ticks:
        r = rng.random()
        if r < config.p_pull:
            lin = _unit(rng) * config.pull_speed
            ang = _unit(rng) * config.pull_angular_speed
            new = [Phase("pull", config.pull_ticks, amp=np.concatenate([lin, ang])), Phase("hold", config.settle_ticks)]
        elif r < config.p_pull + config.p_overshoot:
            new = [Phase("overshoot", 0), Phase("hold", config.settle_ticks)]
        elif r < config.p_pull + config.p_overshoot + config.p_twist:
            amp = np.concatenate(
                [rng.uniform(-1, 1, 3) * config.twist_max_linear, rng.uniform(-1, 1, 3) * config.twist_max_angular]
            )
            new = [
                Phase(
                    "twist",
                    int(rng.integers(100, 600)),
                    amp=amp,
                    freq=rng.uniform(0.3, 2.0, 6),
                    phi=rng.uniform(0, 2 * np.pi, 6),
                )
            ]
        else:
            new = [Phase("hold", int(rng.integers(50, 300)))]
        phases += new
        total += sum(p.ticks for p in new)
    return phases


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def twist_at(
    phase: Phase,
    k: int,
    dt: float,
    config: FuzzConfig,
    reference: tuple[np.ndarray, np.ndarray],
    home: tuple[np.ndarray, np.ndarray],
) -> np.ndarray | None:
    """The tool twist (m/s, rad/s, world) of tick ``k`` of ``phase``: None when held; a pull's constant; a
    twist's sinusoids with a spring back to the episode's start pose, under a sin² envelope, clipped."""
    if phase.kind == "pull":
        return phase.amp.copy()  # type: ignore[union-attr]
    if phase.kind != "twist":
        return None
    t = k * dt
    envelope = math.sin(math.pi * (k + 1) / (phase.ticks + 1)) ** 2
    wave = phase.amp * np.sin(2 * np.pi * phase.freq * t + phase.phi)  # type: ignore[operator]
    spring = -config.twist_spring * np.concatenate([reference[1] - home[1], pin.log3(reference[0] @ home[0].T)])
    v = envelope * (wave + spring)
    return np.concatenate([clip_norm(v[:3], config.twist_max_linear), clip_norm(v[3:], config.twist_max_angular)])


def advance_reference(
    reference: tuple[np.ndarray, np.ndarray], twist: np.ndarray | None, dt: float
) -> tuple[np.ndarray, np.ndarray]:
    """The controller's documented rule: ``p += dt·v``, ``R ← exp₃(dt·ω) R`` (held: unchanged)."""
    if twist is None or not np.any(twist):
        return reference
    return pin.exp3(dt * twist[3:]) @ reference[0], reference[1] + dt * twist[:3]
