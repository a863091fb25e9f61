"""Where the microscope of ``examples/scenarios/microscope.toml`` stands: a reproducible construction.

Scenario B (elbow horizontal, ROM ±10°) with the head of a surgical microscope hanging over the arm.  The box is
placed by geometry alone, never by trying simulations:

1. Scenario B's tool pose at the path centre, its branch and its start arm angle ns0 (the ROM's centre); the ROM's
   upper edge is ``ns_edge = ns0 + rom_half_width_deg`` (-90° + 10° = -80°: turning the arm angle up raises the
   elbow).  ``q_edge`` is the closed-form IK there (same tool pose, same branch).
2. The upper arm capsule (``link_2-link_3``: shoulder to elbow, radius r, :mod:`qpnso.model.collision`); at
   ``q_edge`` take the end of its axis that is higher (z, world), P.
3. The box, aligned with the world axes, 0.25 × 0.25 m wide and 0.30 m tall (a microscope head), its footprint
   centred on P's (x, y), its bottom face ``OVERLAP`` = 1 cm below the capsule's top there: ``P.z + r - OVERLAP``.
   So at the ROM's upper edge (with the tool at the path centre) the upper arm reaches 1 cm into the box.

Why along z and not away from the shoulder–wrist axis: the arm angle turns the upper arm *about* that axis, so each
of its points keeps its distance from it; a box beyond the edge position along that direction is as near at the
start (1 - cos 10° = 1.5 % of the radius).  The elbow end moves most (the shoulder is fixed): 5.5 cm between ns0
and the edge, the capsule's midpoint half as much, less than the 3 cm obstacle margin plus any overlap.

Run: python examples/place_microscope.py  (prints the ``[[obstacles]]`` table and the coal clearances of every link
capsule at the start, at both ROM edges, in m).
"""

from __future__ import annotations

import numpy as np

from qpnso.elbow.srs import Branch, ik
from qpnso.lab.scenarios import Scenario, load_scenario
from qpnso.model.collision import clearances, link_capsules
from qpnso.model.obstacles import Box
from qpnso.model.robot import Robot, load_robot

HALF_EXTENTS = (0.125, 0.125, 0.15)
"""m: a 0.25 × 0.25 × 0.30 m microscope head (x, y, z; world-aligned)."""
OVERLAP = 0.01
"""m: how far the upper arm's top reaches into the box at the ROM's upper edge."""
UPPER_ARM = "link_2-link_3"
"""The upper arm's capsule (shoulder to elbow)."""


def edge_configuration(robot: Robot, sc: Scenario, sign: float = 1.0) -> np.ndarray:
    """The configuration (rad) at the ROM's upper (``sign`` 1) or lower (-1) edge: the closed-form IK of the tool
    pose at the path centre at arm angle ``ns0 ± rom_half_width_deg`` on the scenario's branch."""
    half = float(sc.controller.get("rom_half_width_deg", 50.0))
    return ik(robot, sc.tool_pose(), np.radians(sc.ns0_deg + sign * half), Branch(*sc.branch))


def place_microscope(scenario: str = "B") -> Box:
    """The microscope box (m, world frame) by the construction of the module docstring."""
    sc = load_scenario(scenario)
    robot = load_robot(sc.robot)
    caps = link_capsules(robot)
    k = caps.names.index(UPPER_ARM)
    a, b = caps.segments(robot, edge_configuration(robot, sc))
    top = a[k] if a[k][2] > b[k][2] else b[k]
    bottom = top[2] + caps.radius[k] - OVERLAP
    center = (top[0], top[1], bottom + HALF_EXTENTS[2])
    return Box(center=tuple(round(float(x), 4) for x in center), half_extents=HALF_EXTENTS)


def toml_table(box: Box) -> str:
    """The box as a ``[[obstacles]]`` table of a scenario file."""
    fields = box.to_dict()
    lines = ["[[obstacles]]"] + [f"{key} = {_toml(value)}" for key, value in fields.items()]
    return "\n".join(lines)


def _toml(value: object) -> str:
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, (tuple, list)):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    return repr(float(value))


def main() -> None:
    sc = load_scenario("B")
    robot = load_robot(sc.robot)
    box = place_microscope("B")
    print(toml_table(box))
    names = link_capsules(robot).names
    rows = [
        ("start", sc.start(robot)),
        ("ROM upper edge", edge_configuration(robot, sc, 1.0)),
        ("ROM lower edge", edge_configuration(robot, sc, -1.0)),
    ]
    print("\n# coal clearance (m) of each link capsule, tool at the path centre:")
    for label, q in rows:
        d = clearances(robot, q, [box])[:, 0]
        print(f"# {label:<15}" + "  ".join(f"{n} {x:+.4f}" for n, x in zip(names, d)))


if __name__ == "__main__":
    main()
