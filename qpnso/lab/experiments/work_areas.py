"""Work areas for the mass/friction experiment, chosen from the model alone before any trial (pre-registration).

[M] §V compares a fixed posture "pre-optimised for the work area" with elbow up.  The comparison can only say
something where the two postures differ: at scenario A's pose with MuJoCo Menagerie's rotor inertia the fixed
optimum *was* elbow up (−1.3°, the same felt mass), and the experiment compared a posture with itself.  This
module states the rule that picks the work areas, from the robot model only:

* candidates: tool positions on a grid in front of the robot (:data:`GRID`), the tool pointing down and tilted
  by each of :data:`PITCHES_DEG` about y (the scenario-A orientation family, rpy (180, pitch, 180)°);
* at each candidate and each rotor inertia of :data:`ARMATURES_KGM2`: the elbow-up posture (arm angle 0 on
  scenario A's branch), its continuity interval [E 9], and the fixed posture: the minimum of the controller's
  default cost (50 % mass, 50 % friction force) over the interval (0.5° grid, then bounded Brent), as
  :func:`fixed_posture`;
* the premise, on the plant (:meth:`qpnso.lab.plant.Plant.felt`, the nominal plant): the fixed posture is
  ≥ :data:`MIN_ANGLE_DEG` from elbow up and feels ≥ :data:`MIN_REDUCTION` less mass or friction force;
* every target of the trial (:func:`qpnso.lab.surgeon.dome_targets`) is reachable within the joint limits at
  both postures' arm angles;
* chosen: the :data:`AREAS` candidates where the premise holds at every rotor inertia of the sweep at which
  some candidate of the grid satisfies it (:func:`required_armatures`), ranked by the smallest (over those) of
  the larger of the two reductions; at most one per tool position.  At 0.1 kg·m² no candidate satisfies it
  (the survey, written into the file, counts them: the rotor inertia dominates A(q), so every posture feels
  nearly the same); there the fixed-posture claims cannot be tested, and the experiment says so.

:func:`preregistration` writes the result (every parameter, its source, the postures and the premise at each
rotor inertia) as TOML: ``docs/preregistration/mass-friction.toml``, committed before the runs it governs;
:func:`load_preregistration` reads it back for the experiment, which refuses a file the model no longer gives.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
from scipy.optimize import minimize_scalar

from qpnso.errors import ConfigError, QpnsoError
from qpnso.shipped import shipped_dir

GRID = {"x": (0.45, 0.55, 0.65), "y": (-0.2, 0.0, 0.2), "z": (0.3, 0.4, 0.5)}
"""m, world frame: the candidate tool positions (ours: the LWR4+'s front workspace at an operating table)."""
PITCHES_DEG = (0.0, 30.0)
"""deg: tilts of the downward tool about y (0: vertical; 30: scenario A's)."""
ARMATURES_KGM2 = (0.0, 0.01, 0.03, 0.1)
"""kg·m²: the rotor-inertia sweep (0: the rigid-body robot [M] states; 0.1: MuJoCo Menagerie's stabiliser)."""
MIN_ANGLE_DEG = 20.0
"""deg: the least arm-angle distance of the fixed posture from elbow up (issue 32)."""
MIN_REDUCTION = 0.15
"""The least relative reduction in felt mass or friction force at the fixed posture (issue 32)."""
AREAS = 2
"""How many work areas the experiment uses (subjects alternate between them)."""
ELBOW_UP_BRANCH = (-1, 1, -1)
"""Branch (signs of joints 2, 4, 6) of the work-area postures: scenario A's."""
DOME_RADIUS = 0.05
"""m: the targets' cap radius (:func:`qpnso.lab.surgeon.dome_targets`; the paper's layout is not published)."""
MOVES = 6
"""Targets per trial ([M] §V: six reference points)."""
FILE = "mass-friction.toml"


@dataclass(frozen=True)
class Postures:
    """One work area at one rotor inertia: elbow-up and fixed joint positions (rad), the fixed arm angle (rad),
    and the premise on the plant (felt mass kg, friction force N at each posture)."""

    q_up: np.ndarray
    q_fixed: np.ndarray
    ns_fixed: float
    mass_up_kg: float
    mass_fixed_kg: float
    friction_up_N: float
    friction_fixed_N: float

    @property
    def mass_reduction(self) -> float:
        """Relative felt-mass reduction of the fixed posture against elbow up."""
        return 1.0 - self.mass_fixed_kg / self.mass_up_kg

    @property
    def friction_reduction(self) -> float:
        """Relative friction-force reduction of the fixed posture against elbow up."""
        return 1.0 - self.friction_fixed_N / self.friction_up_N

    @property
    def discriminates(self) -> bool:
        """The premise: ≥ :data:`MIN_ANGLE_DEG` apart and ≥ :data:`MIN_REDUCTION` less mass or friction."""
        far = abs(math.degrees(self.ns_fixed)) >= MIN_ANGLE_DEG
        return far and max(self.mass_reduction, self.friction_reduction) >= MIN_REDUCTION

    def record(self) -> dict[str, Any]:
        """As plain data (degrees, kg, N)."""
        return {
            "fixed_arm_angle_deg": round(math.degrees(self.ns_fixed), 3),
            "q_up_deg": [round(v, 3) for v in np.degrees(self.q_up).tolist()],
            "q_fixed_deg": [round(v, 3) for v in np.degrees(self.q_fixed).tolist()],
            "mass_elbow_up_kg": round(self.mass_up_kg, 4),
            "mass_fixed_kg": round(self.mass_fixed_kg, 4),
            "friction_elbow_up_N": round(self.friction_up_N, 4),
            "friction_fixed_N": round(self.friction_fixed_N, 4),
            "mass_reduction": round(self.mass_reduction, 4),
            "friction_reduction": round(self.friction_reduction, 4),
            "discriminates": self.discriminates,
        }


def area_pose(center: tuple[float, float, float], pitch_deg: float) -> pin.SE3:
    """The tool pose of a work area (world frame): at ``center`` (m), pointing down, tilted by ``pitch_deg``."""
    return pin.SE3(pin.rpy.rpyToMatrix(*np.radians([180.0, pitch_deg, 180.0])), np.asarray(center, dtype=float))


def fixed_posture(robot, pose: pin.SE3, cost=None) -> tuple[np.ndarray, np.ndarray, float]:
    """``(q_up, q_fixed, ns_fixed)`` (rad) at ``pose``: elbow up (arm angle 0, :data:`ELBOW_UP_BRANCH`) and the
    cost's minimum over elbow up's continuity interval (0.5° grid, then bounded Brent to 1e-9 rad): the fixed
    posture "pre-optimised for the work area" ([M] §V).  ``cost``: default the controller's (50/50)."""
    from qpnso.elbow.intervals import continuity_interval
    from qpnso.elbow.srs import Branch, ik
    from qpnso.model.costs import CostModel

    b = Branch(*ELBOW_UP_BRANCH)
    q_up = ik(robot, pose, 0.0, b)
    iv = continuity_interval(robot, q_up)
    cost = cost or CostModel(robot)
    value = lambda ns: cost.value(ik(robot, pose, ns, b))  # noqa: E731
    grid = np.arange(iv.lo + 1e-3, iv.hi - 1e-3, math.radians(0.5))
    k = int(np.argmin([value(ns) for ns in grid]))
    lo, hi = grid[max(0, k - 1)], grid[min(len(grid) - 1, k + 1)]
    ns = float(minimize_scalar(value, bounds=(lo, hi), method="bounded", options={"xatol": 1e-9}).x)
    return q_up, ik(robot, pose, ns, b), ns


def postures(robot, pose: pin.SE3) -> Postures:
    """:func:`fixed_posture` and the premise measured on the nominal plant (felt mass [M 8], friction force
    [M 15] at the controller's cost's potential speed)."""
    from qpnso.lab.plant import Plant
    from qpnso.model.costs import CostModel

    cost = CostModel(robot)
    q_up, q_fixed, ns = fixed_posture(robot, pose, cost)
    mass, friction = Plant(robot).felt(np.array([q_up, q_fixed]), cost.potential_speed)
    return Postures(q_up, q_fixed, ns, float(mass[0]), float(mass[1]), float(friction[0]), float(friction[1]))


def targets_reachable(robot, pose: pin.SE3, arm_angles: tuple[float, ...]) -> bool:
    """Whether every target of the trial's dome above ``pose`` (same orientation) has the closed-form IK within
    the joint limits at each of ``arm_angles`` (rad) on :data:`ELBOW_UP_BRANCH`."""
    from qpnso.elbow.srs import Branch, ik
    from qpnso.lab.surgeon import dome_targets

    b = Branch(*ELBOW_UP_BRANCH)
    for p in dome_targets(pose.translation, DOME_RADIUS, MOVES):
        for ns in arm_angles:
            try:
                q = ik(robot, pin.SE3(pose.rotation, p), ns, b)
            except QpnsoError:
                return False
            if np.any(q < robot.q_min) or np.any(q > robot.q_max):
                return False
    return True


def survey(robot_name: str = "lwr4p") -> list[dict[str, Any]]:
    """Every candidate of :data:`GRID` × :data:`PITCHES_DEG` with its postures and premise at each rotor inertia
    of :data:`ARMATURES_KGM2` (candidates without the postures or the targets are dropped)."""
    from qpnso.model.robot import load_robot_with_armature

    robots = {a: load_robot_with_armature(robot_name, a) for a in ARMATURES_KGM2}
    out = []
    for x, y, z, pitch in itertools.product(GRID["x"], GRID["y"], GRID["z"], PITCHES_DEG):
        pose = area_pose((x, y, z), pitch)
        try:
            at = {a: postures(robots[a], pose) for a in ARMATURES_KGM2}
        except QpnsoError:
            continue
        angles = (0.0, *(p.ns_fixed for p in at.values()))
        if not targets_reachable(robots[0.0], pose, angles):
            continue
        out.append({"center_m": [x, y, z], "pitch_deg": pitch, "by_armature": at})
    return out


def required_armatures(candidates: list[dict[str, Any]]) -> tuple[float, ...]:
    """The rotor inertias (kg·m²) of the sweep at which at least one candidate satisfies the premise."""
    return tuple(a for a in ARMATURES_KGM2 if any(c["by_armature"][a].discriminates for c in candidates))


def choose(candidates: list[dict[str, Any]], count: int = AREAS) -> list[dict[str, Any]]:
    """The rule: candidates whose premise holds at every rotor inertia of :func:`required_armatures`, by
    decreasing worst reduction (over those), one per tool position, the first ``count``; :class:`ConfigError` when fewer
    qualify."""
    required = required_armatures(candidates)
    if not required:
        raise ConfigError("only 0 work areas satisfy the premise: none at any rotor inertia of the sweep")

    def worst(c: dict[str, Any]) -> float:
        return min(max(c["by_armature"][a].mass_reduction, c["by_armature"][a].friction_reduction) for a in required)

    ok = sorted(
        (c for c in candidates if all(c["by_armature"][a].discriminates for a in required)), key=lambda c: -worst(c)
    )
    chosen: list[dict[str, Any]] = []
    for c in ok:
        if all(c["center_m"] != d["center_m"] for d in chosen):
            chosen.append(c)
    if len(chosen) < count:
        raise ConfigError(f"only {len(chosen)} work areas satisfy the premise ({count} needed)")
    return chosen[:count]


SOURCES = {
    "MIN_ANGLE_DEG": "issue 32: the fixed posture at least 20 deg from elbow up",
    "MIN_REDUCTION": "issue 32: at least 15 % less felt mass or friction force at the fixed posture, on the plant",
    "ARMATURES_KGM2": "issue 32: 0 (the rigid-body robot [M] states) and 0.1 (MuJoCo Menagerie's stabiliser) as "
    "bounds, 0.01 and 0.03 between",
    "GRID": "ours: the LWR4+'s front workspace at an operating table",
    "PITCHES_DEG": "ours: scenario A's orientation family (elbow paper), vertical and 30 deg",
    "cost": "the controller's default: 50 % mass, 50 % friction force ([M] §V's active optimisation weights)",
    "felt": "the nominal MuJoCo plant: largest principal mass [M 8], potential friction force [M 15] at 0.05 m/s",
    "DOME_RADIUS": "ours: a surgical target's size; [M] does not publish its six points' layout",
    "AREAS": "ours: two work areas, subjects alternate between them",
    "required_armatures_kgm2": "ours: every rotor inertia of the sweep at which some candidate satisfies the "
    "premise (survey)",
}


def preregistration(robot_name: str = "lwr4p") -> str:
    """The pre-registration file's text (TOML): the rule's parameters and their sources, then each chosen work
    area with its postures and premise at every rotor inertia."""
    candidates = survey(robot_name)
    chosen = choose(candidates)
    counts = [sum(c["by_armature"][a].discriminates for c in candidates) for a in ARMATURES_KGM2]
    lines = [
        "# Pre-registration of the mass/friction experiment's work areas (issue 32).",
        "# Written by `qpnso experiment preregister` from the robot model alone, before any trial;",
        "# the rule is qpnso.lab.experiments.work_areas. The experiment reads this file and refuses to run",
        "# when the model no longer gives these postures.",
        "",
        "[rule]",
        f'robot = "{robot_name}"',
        f"min_angle_deg = {MIN_ANGLE_DEG}",
        f"min_reduction = {MIN_REDUCTION}",
        f"armatures_kgm2 = {list(ARMATURES_KGM2)}",
        f"required_armatures_kgm2 = {list(required_armatures(candidates))}",
        f"grid_x_m = {list(GRID['x'])}",
        f"grid_y_m = {list(GRID['y'])}",
        f"grid_z_m = {list(GRID['z'])}",
        f"pitches_deg = {list(PITCHES_DEG)}",
        f"dome_radius_m = {DOME_RADIUS}",
        f"moves = {MOVES}",
        f"areas = {AREAS}",
        "",
        "[survey]",
        f"candidates = {len(candidates)}",
        f"discriminating_by_armature = {counts}",
        "",
        "[sources]",
        *(f'{k} = "{v}"' for k, v in SOURCES.items()),
    ]
    for c in chosen:
        lines += ["", "[[area]]", f"center_m = {c['center_m']}", f"pitch_deg = {c['pitch_deg']}"]
        for a, p in c["by_armature"].items():
            lines += ["", "[[area.at]]", f"armature_kgm2 = {a}"]
            lines += [f"{k} = {_toml(v)}" for k, v in p.record().items()]
    return "\n".join(lines) + "\n"


def _toml(v: object) -> str:
    return ("true" if v else "false") if isinstance(v, bool) else str(v)


def preregistration_path() -> Path:
    """The shipped pre-registration file."""
    return shipped_dir("preregistration") / FILE


@dataclass(frozen=True)
class WorkAreaSpec:
    """A pre-registered work area: centre (m), tilt (deg), and the recorded fixed arm angle (deg) by rotor
    inertia (kg·m²)."""

    center: tuple[float, float, float]
    pitch_deg: float
    fixed_arm_angle_deg: dict[float, float]

    def pose(self) -> pin.SE3:
        """The tool pose at the area's centre (world frame)."""
        return area_pose(self.center, self.pitch_deg)


def load_preregistration(path: Path | None = None) -> list[WorkAreaSpec]:
    """The work areas of the pre-registration file (default: the shipped one)."""
    import tomllib

    data = tomllib.loads((path or preregistration_path()).read_text())
    try:
        return [
            WorkAreaSpec(
                tuple(float(v) for v in a["center_m"]),  # type: ignore[arg-type]
                float(a["pitch_deg"]),
                {float(r["armature_kgm2"]): float(r["fixed_arm_angle_deg"]) for r in a["at"]},
            )
            for a in data["area"]
        ]
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"the pre-registration file is malformed: {exc!r}") from None
