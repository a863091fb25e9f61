"""The 3-D replay (qpnso.view): the scene's transforms against Pinocchio's forward kinematics, read back from the
written page itself; the elbow circle against the arm angle; the result file's scene record; the live server;
the command line; and the page in a real headless Chromium (skipped where none is installed).

Run the browser test on a machine with Debian's Chromium (``apt-get install chromium``):
``python -m pytest tests/test_view.py -k chromium -rP`` prints where the screenshot is.
"""

from __future__ import annotations

import base64
import os
import re
import urllib.request
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import headless
import numpy as np
import pinocchio as pin
import pytest
from conftest import ALL_ROBOTS, SRS_ROBOTS, reference_arm_angle

import qpnso
from qpnso.cli import main
from qpnso.control.offline import scene_record
from qpnso.elbow.arm_angle import elbow_circle, elbow_points
from qpnso.errors import InputError, JointLimitError
from qpnso.model.collision import link_capsules
from qpnso.model.robot import load_robot_spec, robot_spec

viser = pytest.importorskip("viser")
zstandard = pytest.importorskip("zstandard")
msgspec = pytest.importorskip("msgspec")

from qpnso.view import Replay, load_replay  # noqa: E402
from qpnso.view.geometry import arc, framing_distance, inside_capsules  # noqa: E402
from qpnso.view.scene import (  # noqa: E402
    INTERVAL_OFFSET_M,
    REFERENCE,
    TOOL_PATH,
    free_port,
    html_page,
    path_points,
    readout,
    serve,
    write_html,
)

# ------------------------------------------------------------------ fixtures
RUN_S = 6.0
"""s of scenario B run for the tests: long enough for the tool path to be seen on a 640-pixel screenshot
(10 cm of path, 3 cm across; 1.5 s gave 1 cm)."""


@pytest.fixture(scope="module")
def run():
    """A short hands-on run of scenario B: RUN_S of the plant (one run for every test here: the suite's time)."""
    from qpnso.lab.scenarios import simulate_scenario

    return simulate_scenario("B", "qp", RUN_S / 36.14)


@pytest.fixture(scope="module")
def result_file(run, tmp_path_factory) -> Path:
    return run.save(tmp_path_factory.mktemp("view") / "result.npz")


@pytest.fixture(scope="module")
def page(result_file) -> tuple[Replay, str]:
    replay = load_replay(result_file)
    return replay, html_page(replay, fps=20.0)


def recording(html: str) -> tuple[dict, list[np.ndarray]]:
    """The recording embedded in a page (viser's format: zstd of msgpack and aligned binary buffers), decoded
    here without viser: the message list and the binary buffers."""
    match = re.search(r'window\.__VISER_EMBED_DATA__="([^"]*)"', html)
    assert match, "the page embeds no recording"
    raw = base64.b64decode(match.group(1))
    inner = zstandard.ZstdDecompressor().decompress(raw[8:], max_output_size=int.from_bytes(raw[:8], "little"))
    n = int.from_bytes(inner[:8], "little")
    record = msgspec.msgpack.decode(inner[8 : 8 + n])
    buffers, at = [], 8 + n
    for length in record["binaryBufferLengths"]:
        at = (at + 7) // 8 * 8  # aligned to 8 bytes
        buffers.append(inner[at : at + length])
        at += length
    return record, buffers


def states(record: dict) -> list[tuple[float, dict]]:
    """The scene after each recorded instant: ``(time, {node: {"position", "wxyz", "visible", "props"}})``, the
    messages applied in order; one entry per distinct time (the state once all its messages are applied)."""
    out: list[tuple[float, dict]] = []
    nodes: dict[str, dict] = {}
    for t, m in record["messages"]:
        if out and t != out[-1][0]:
            out[-1] = (out[-1][0], {k: dict(v) for k, v in nodes.items()})
        name = m.get("name")
        node = nodes.setdefault(name, {"position": np.zeros(3), "wxyz": np.array([1.0, 0, 0, 0]), "props": {}})
        if m["type"] == "SetPositionMessage":
            node["position"] = np.array(m["position"])
        elif m["type"] == "SetOrientationMessage":
            node["wxyz"] = np.array(m["wxyz"])
        elif m["type"] == "SetSceneNodeVisibilityMessage":
            node["visible"] = m["visible"]
        elif m["type"] == "SceneNodeUpdateMessage":
            node["props"] = {**node["props"], **m["updates"]}
        elif "props" in m:
            node["props"] = dict(m["props"])
            node["type"] = m["type"]
        if not out or t != out[-1][0]:
            out.append((t, {}))
    out[-1] = (out[-1][0], {k: dict(v) for k, v in nodes.items()})
    return out


def world(nodes: dict, name: str) -> pin.SE3:
    """A node's world pose: its parents' poses composed (viser's scene tree, names ``/a/b/c``)."""
    pose = pin.SE3.Identity()
    parts = name.strip("/").split("/")
    for k in range(1, len(parts) + 1):
        node = nodes.get("/" + "/".join(parts[:k]))
        if node is None:
            continue
        w, x, y, z = node["wxyz"]
        pose = pose * pin.SE3(pin.Quaternion(w, x, y, z).normalized().matrix(), node["position"])
    return pose


def array(buffers: list, ref: dict) -> np.ndarray:
    """A binary placeholder of a message's props as an array."""
    return np.frombuffer(buffers[ref["__binary_index"]], dtype=ref["dtype"])


# -------------------------------------------------------------- the geometry
@pytest.mark.parametrize("name", SRS_ROBOTS)
def test_elbow_circle_at_the_arm_angle_is_the_elbow(robots, rng, name):
    """[E 2]–[E 4] read backwards: the circle's point at the arm angle (computed independently, conftest) is
    Pinocchio's elbow; every point of the circle is as far from the shoulder as the elbow and turns about
    the shoulder–wrist axis."""
    robot = robots[name]
    pts = elbow_points(robot)
    for _ in range(50):
        q = rng.uniform(robot.q_min, robot.q_max)
        pin.forwardKinematics(robot.model, robot.data, q)
        ps, pe, pw = pts.world(robot.data)
        circle = elbow_circle(ps, pe, pw)
        assert np.linalg.norm(circle.point(reference_arm_angle(robot, q)) - pe) < 1e-12
        ring = circle.point(np.linspace(-np.pi, np.pi, 13))
        assert np.allclose(np.linalg.norm(ring - ps, axis=1), np.linalg.norm(pe - ps), atol=1e-12)
        assert np.allclose((ring - circle.centre) @ (pw - ps), 0.0, atol=1e-12)


def test_arcs_are_cut_half_a_turn_around_the_arm_angle():
    """An unbounded interval is the whole circle around the arm angle; an arc beyond half a turn, reversed or
    unknown is not drawn; every point is at the radius, in the circle's plane."""
    whole = arc(-np.inf, np.inf, 0.3, 1.0)
    angles = np.arctan2(whole[:, 1], whole[:, 0])
    assert np.allclose(np.linalg.norm(whole[:, :2], axis=1), 0.3) and np.all(whole[:, 2] == 0)
    assert np.allclose(whole[0], whole[-1]) and np.isclose(angles[0], 1.0 - np.pi)
    assert np.allclose(arc(0.2, 0.5, 1.0, 0.0)[[0, -1], :2], [[np.cos(0.2), np.sin(0.2)], [np.cos(0.5), np.sin(0.5)]])
    assert arc(3.5, 4.0, 1.0, 0.0) is None and arc(0.5, 0.2, 1.0, 0.0) is None and arc(np.nan, 1.0, 1.0, 0.0) is None


def test_inside_capsules_is_the_distance_to_the_capsule_axis(robots, rng):
    """Against the control tick's segment–point kernel (qpnso.model.distance.segment_point): a point is inside
    a capsule exactly when its distance to the capsule's axis is below the radius (points scattered around
    every capsule's middle, about half of them inside)."""
    from qpnso.model.distance import segment_point

    for robot in robots.values():
        caps = link_capsules(robot)
        q = rng.uniform(robot.q_min, robot.q_max)
        a, b = caps.segments(robot, q)
        points = (0.5 * (a + b))[:, None, :] + rng.normal(scale=max(caps.radius), size=(caps.count, 40, 3))
        points = points.reshape(-1, 3)
        inside = inside_capsules(robot, q, points)
        for c in range(caps.count):
            distance = np.array([segment_point(a[c], b[c], p)[0] for p in points])
            assert np.array_equal(inside[c], distance < caps.radius[c]), (robot.name, c)
        assert 0.1 < inside.any(axis=0).mean() < 0.9


def test_framing_distance_puts_every_point_in_view(rng):
    """A pinhole camera that far from the target, looking at it with z up: every point in front of it and
    within half the field of view of its axis, across and up, and one point on that edge (no nearer camera
    keeps them all in view)."""
    points = rng.normal(size=(300, 3)) * [0.3, 0.2, 0.4] + [0.4, -0.1, 0.5]
    target, direction, fov = np.array([0.35, -0.05, 0.45]), np.array([0.9, -0.9, 0.5]), np.radians(75.0)
    distance = framing_distance(points, target, direction, fov)
    eye = target + distance * direction / np.linalg.norm(direction)
    forward = (target - eye) / distance
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    rel = points - eye
    depth = rel @ forward
    assert np.all(depth > 0)
    angle = np.maximum(np.abs(np.arctan2(rel @ right, depth)), np.abs(np.arctan2(rel @ up, depth)))
    assert angle.max() == pytest.approx(0.5 * fov, abs=1e-12)


def test_robot_spec_loads_the_same_kinematics(rng):
    """A robot record gives back the tool frame (with a rotated offset) to round-off."""
    offset = pin.SE3(pin.rpy.rpyToMatrix(0.1, -0.2, 0.3), np.array([0.01, -0.02, 0.15]))
    robot = qpnso.load_robot("iiwa14", tool_offset=offset)
    again = load_robot_spec(robot_spec(robot))
    for _ in range(5):
        q = rng.uniform(robot.q_min, robot.q_max)
        assert np.allclose(again.tool_pose(q).homogeneous, robot.tool_pose(q).homogeneous, atol=1e-14)
    with pytest.raises(qpnso.ModelError, match="not a robot record"):
        load_robot_spec({"robot": "lwr4p"})


# ------------------------------------------------------------ the result file
BOX = qpnso.Box(center=(0.3, -0.4, 0.5), half_extents=(0.1, 0.12, 0.15), rpy_deg=(0.0, 0.0, 30.0))


def test_result_file_records_robot_and_room(run, result_file, lwr, tmp_path):
    """The saved run says which robot ran it and which keep-out volumes were in the room (scenario B: none; a
    room the controller was not given: its box, none known), and the replay reads them back."""
    replay = load_replay(result_file)
    assert replay.robot.name == "lwr4p" and replay.obstacles == () and run.scene["known_obstacles"] == 0
    assert np.array_equal(replay.q, run.arrays["q"])
    blind = SimpleNamespace(robot=lwr, obstacles=(), config=SimpleNamespace(strategy="qp"))
    record = scene_record(blind, (BOX,))
    assert record["obstacles"] == [BOX.to_dict()] and record["known_obstacles"] == 0
    path = replace(run, scene=record).save(tmp_path / "room.npz")
    assert load_replay(path).obstacles == (BOX,) and "0 of 1 obstacles known" in load_replay(path).title


def test_old_result_file_needs_the_robot(run, tmp_path, lwr):
    """A file without the scene record: refused by name unless the robot is given."""
    path = replace(run, scene={}).save(tmp_path / "old.npz")
    with pytest.raises(InputError, match="--robot"):
        load_replay(path)
    assert load_replay(path, lwr).obstacles == ()


def test_a_robot_that_contradicts_the_record_is_refused(result_file, robots):
    """The file records the LWR4+ with its tool point at the flange: another robot (by name), or the LWR4+ with
    the tool elsewhere, is refused; the recorded robot itself is accepted."""
    for name in ALL_ROBOTS[1:]:
        with pytest.raises(InputError, match=f"recorded on lwr4p, not {name}: leave --robot out"):
            load_replay(result_file, robots[name])
    longer = qpnso.load_robot("lwr4p", tool_offset=pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.1])))
    with pytest.raises(InputError, match=r"tool at tool \+ \(0, 0, 0\) m, not at tool \+ \(0, 0, 0\.1\) m"):
        load_replay(result_file, longer)
    assert load_replay(result_file, robots["lwr4p"]).robot is robots["lwr4p"]


@pytest.fixture(scope="module")
def old_file(run, tmp_path_factory) -> Path:
    """The run saved without its scene record (a file written before qpnso recorded it)."""
    return replace(run, scene={}).save(tmp_path_factory.mktemp("old") / "old.npz")


def test_an_old_file_on_a_robot_whose_limits_it_breaks_is_refused(run, lwr, tmp_path):
    """Without a record, a given robot is refused when on more than half of the ticks a recorded joint is
    beyond its limits by more than the controller's tolerance (2°): JointLimitError naming the joint, its value
    and the first such tick.  On fewer (a run with a larger tolerance, bringing the joint back) it is drawn.
    Joint 7 is moved: it turns the flange about its own axis, so the recorded tool point still fits."""
    n = len(run.arrays["t"])
    for start, refused in ((n // 2 - 10, True), (n // 2 + 10, False)):
        q = run.arrays["q"].copy()
        q[start:, 6] = lwr.q_max[6] + np.radians(2.5)
        path = replace(run, arrays={**run.arrays, "q": q}, scene={}).save(tmp_path / f"from_{start}.npz")
        if refused:
            value = f"{np.degrees(q[start, 6]):.4g}°"
            message = (
                rf"cannot be a run of lwr4p: at tick {start} \(t = .* s\) q\[6\] \({lwr.joint_names[6]}\) = {value}"
            )
            with pytest.raises(JointLimitError, match=message):
                load_replay(path, lwr)
        else:
            assert np.array_equal(load_replay(path, lwr).q, q)


@pytest.mark.skipif("panda" not in ALL_ROBOTS, reason="the Panda needs example-robot-data")
def test_an_old_lwr4p_file_on_the_panda_is_refused(old_file, robots):
    """Every tick of the LWR4+'s run is outside the Panda's limits (its joint 4 bends the other way)."""
    with pytest.raises(JointLimitError, match=r"cannot be a run of panda: at tick 0 .*panda_joint\d.* of \d+ ticks"):
        load_replay(old_file, robots["panda"])


def test_an_old_file_on_another_arm_or_tool_is_refused_by_the_tool_point(old_file, robots):
    """The iiwa's limits hold the LWR4+'s run, but its tool point at the recorded q is not the recorded one;
    nor is the LWR4+'s with a 10 cm tool: both refused, naming the first tick and the distance."""
    with pytest.raises(InputError, match=r"cannot be a run of iiwa14 with this tool: at tick 0 .* is \d"):
        load_replay(old_file, robots["iiwa14"])
    longer = qpnso.load_robot("lwr4p", tool_offset=pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.1])))
    with pytest.raises(InputError, match=r"tool point at the recorded q is 0\.1 m from the recorded one"):
        load_replay(old_file, longer)
    assert load_replay(old_file, robots["lwr4p"]).robot is robots["lwr4p"]


def test_cli_view_refuses_a_robot_that_contradicts_the_file(result_file, old_file, tmp_path, capsys):
    """One line on stderr, exit 2, nothing written."""
    out = tmp_path / "run.html"
    for path, message in ((result_file, "recorded on lwr4p, not iiwa14"), (old_file, "cannot be a run of iiwa14")):
        assert main(["view", str(path), "--robot", "iiwa14", "--html", str(out)]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1
    assert not out.exists()


@pytest.mark.parametrize(
    ("scene", "message"),
    [
        ({"robot": {"robot": "/nowhere/arm.urdf", "tool_frame": "tool", "tool_offset": np.eye(4).tolist()}}, "robot"),
        ({"robot": {"robot": "lwr4p"}}, "not a robot record"),
        ({"robot": robot_spec(qpnso.load_robot("lwr4p")), "obstacles": [{"type": "cone"}]}, "type"),
    ],
)
def test_a_bad_scene_record_is_refused_by_name(run, tmp_path, scene, message):
    path = replace(run, scene=scene).save(tmp_path / "bad.npz")
    with pytest.raises(InputError, match=message):
        load_replay(path)


@pytest.mark.parametrize(("text", "message"), [("{not json", "not JSON"), ("[1, 2]", "not a table")])
def test_a_scene_entry_that_is_not_a_json_table_is_refused(run, tmp_path, text, message):
    path = tmp_path / "bad.npz"
    np.savez(path, **run.arrays, scene=np.array(text))
    with pytest.raises(InputError, match=message):
        load_replay(path)


def test_the_scene_record_names_the_strategy_that_ran(run):
    assert run.scene["strategy"] == "qp"


def test_replay_and_scene_refuse_what_they_cannot_show(run, lwr):
    """A run without an array the replay reads; an obstacle kind the scene cannot draw."""
    from qpnso.view.scene import add_obstacle

    with pytest.raises(InputError, match="lacks"):
        Replay.of({k: v for k, v in run.arrays.items() if k != "ns"}, lwr)
    with pytest.raises(InputError, match="cannot draw"):
        add_obstacle(None, "/obstacles/0", object())


def test_replay_refuses_bad_arrays(run, lwr, iiwa=None):
    """Wrong joint count, a NaN configuration, a time axis that goes back: each named."""
    arrays = dict(run.arrays)
    with pytest.raises(InputError, match=r"q has shape"):
        Replay.of({**arrays, "q": arrays["q"][:, :6]}, lwr)
    q = arrays["q"].copy()
    q[7, 2] = np.nan
    with pytest.raises(InputError, match="q at tick 7"):
        Replay.of({**arrays, "q": q}, lwr)
    t = arrays["t"].copy()
    t[3] = t[2]
    with pytest.raises(InputError, match="increasing"):
        Replay.of({**arrays, "t": t}, lwr)


def test_frames_sample_the_run_at_the_frame_rate(run, lwr):
    replay = Replay.of(run.arrays, lwr)
    frames = replay.frames(20.0)
    assert frames[0] == 0 and frames[-1] == len(replay.t) - 1
    assert np.allclose(np.diff(replay.t[frames])[:-1], 0.05, atol=1e-9)
    with pytest.raises(InputError, match="positive"):
        replay.frames(0.0)


# ------------------------------------------------------------------- the page
VISER_SKIP = 2e-5
"""viser sends a node's new position or orientation only when it is not ``np.allclose`` to the last one sent
(relative 1e-5, absolute 1e-8): a shown pose may lag Pinocchio's by that much (m within 2 m of the base,
quaternion entries).  Measured on the 36 s guidance solve: 3.8e-6 at worst."""


def assert_links_are_forward_kinematics(replay: Replay, html: str, fps: float) -> None:
    """Every frame of the page: each joint frame's world pose equals Pinocchio's oMi at the recorded q of the
    tick shown (to :data:`VISER_SKIP`), and every vertex of every link capsule lies on that capsule (its radius
    from the axis that LinkCapsules gives at that q); the recording lasts as long as the frames it shows."""
    record, buffers = recording(html)
    frames = replay.frames(fps)
    shown = states(record)
    assert len(shown) == len(frames)
    assert record["durationSeconds"] == pytest.approx(replay.t[frames[-1]] - replay.t[frames[0]], abs=1e-9)
    robot = replay.robot
    caps = link_capsules(robot)
    model, data = robot.model, robot.model.createData()
    for (t, nodes), k in zip(shown, frames):
        assert t == pytest.approx(replay.t[k] - replay.t[frames[0]], abs=1e-9)
        pin.forwardKinematics(model, data, replay.q[k])
        for j in range(1, model.njoints):
            pose = world(nodes, f"/arm/joint_{j}")
            assert np.allclose(pose.homogeneous, data.oMi[j].homogeneous, rtol=0, atol=VISER_SKIP), (k, j)
        a, b = caps.segments(robot, replay.q[k])
        meshes = [n for n in nodes if "/capsule_" in str(n)]
        assert len(meshes) == caps.count
        for name in meshes:
            i = int(name.rsplit("_", 1)[1])
            vertices = array(buffers, nodes[name]["props"]["vertices"]).reshape(-1, 3).astype(float)
            pose = world(nodes, name)
            v = vertices @ pose.rotation.T + pose.translation
            s = np.clip((v - a[i]) @ (b[i] - a[i]) / np.dot(b[i] - a[i], b[i] - a[i]), 0.0, 1.0)
            dist = np.linalg.norm(v - (a[i] + s[:, None] * (b[i] - a[i])), axis=1)
            assert np.allclose(dist, caps.radius[i], atol=VISER_SKIP + 1e-5), (k, name)  # vertices in float32


def test_page_link_poses_are_pinocchio_forward_kinematics(page):
    """The LWR4+'s hands-on run in scenario B, read back from its page."""
    replay, html = page
    assert_links_are_forward_kinematics(replay, html, 20.0)


@pytest.mark.parametrize("name", ALL_ROBOTS[1:])
def test_page_link_poses_of_other_arms(robots, name, rng):
    """The iiwa (and the Panda, where installed): a straight joint-space path between two configurations."""
    robot = robots[name]
    a, b = robot.sample_configuration(), rng.uniform(robot.q_min, robot.q_max)
    q = a + np.linspace(0.0, 1.0, 40)[:, None] * (b - a)
    ns = np.array([qpnso.arm_angle_status(robot, x).value for x in q])
    n = len(q)
    arrays = {"t": 0.01 * np.arange(n), "q": q, "ns": ns, "rom_lo": ns - 0.3, "rom_hi": ns + 0.3}
    arrays |= {"interval_lo": np.full(n, -np.inf), "interval_hi": np.full(n, np.nan)}
    arrays |= {"tool_position": np.zeros((n, 3)), "ref_position": np.zeros((n, 3))}
    replay = Replay.of(arrays, robot)
    assert_links_are_forward_kinematics(replay, html_page(replay, fps=25.0), 25.0)


def test_page_elbow_marker_is_at_the_recorded_arm_angle(page):
    """The ball of the arm angle lies on the spoke from the circle's centre through Pinocchio's elbow (the LWR4+
    is S-R-S, so the recorded arm angle's point is the elbow), INTERVAL_OFFSET_M beyond the circle."""
    replay, html = page
    record, _ = recording(html)
    robot, data = replay.robot, replay.robot.model.createData()
    pts = elbow_points(robot)
    for (_, nodes), k in zip(states(record), replay.frames(20.0)):
        pin.forwardKinematics(robot.model, data, replay.q[k])
        ps, pe, pw = pts.world(data)
        centre = world(nodes, "/elbow").translation
        ball = world(nodes, "/elbow/arm_angle").translation
        radius = np.linalg.norm(pe - centre)
        assert np.allclose(ball, centre + (1 + INTERVAL_OFFSET_M / radius) * (pe - centre), atol=VISER_SKIP), k


def test_page_hides_the_elbow_where_the_arm_angle_is_undefined(lwr):
    """The arm straight up (the wrist on the vertical through the shoulder: no circle) and a tick whose recorded
    arm angle is NaN: the elbow's drawing is hidden there and shown again after."""
    q = np.tile(lwr.sample_configuration(), (3, 1))
    q[0] = 0.0
    ns = np.array([0.0, np.nan, qpnso.arm_angle(lwr, q[2])])
    arrays = {"t": np.array([0.0, 0.1, 0.2]), "q": q, "ns": ns, "rom_lo": ns - 0.2, "rom_hi": ns + 0.2}
    arrays |= {"interval_lo": ns - 1.0, "interval_hi": ns + 1.0, "tool_position": np.zeros((3, 3))}
    arrays |= {"ref_position": np.zeros((3, 3))}
    record, _ = recording(html_page(Replay.of(arrays, lwr), fps=10.0))
    assert [nodes["/elbow"]["visible"] for _, nodes in states(record)] == [False, False, True]


def test_page_draws_the_room_and_paths(result_file):
    """A box given for the room (``--obstacles``), the recorded tool path and its reference, in world
    coordinates."""
    replay = load_replay(result_file, obstacles=(BOX,))
    record, buffers = recording(html_page(replay, fps=5.0))
    nodes = states(record)[-1][1]
    box = replay.obstacles[0]
    assert np.allclose(world(nodes, "/obstacles/0").rotation, box.matrix)
    assert np.allclose(world(nodes, "/obstacles/0").translation, box.center)
    assert np.allclose(nodes["/obstacles/0"]["props"]["dimensions"], 2 * np.array(box.half_extents))
    for name, path in (("tool", replay.tool), ("reference", replay.ref)):
        points = array(buffers, nodes[f"/paths/{name}"]["props"]["points"]).reshape(-1, 2, 3)
        assert np.allclose(points[0, 0], path[0], atol=1e-6) and np.allclose(points[-1, 1], path[-1], atol=1e-6)


def within(a: np.ndarray, b: np.ndarray, radius: float, points: np.ndarray) -> np.ndarray:
    """Which ``points`` lie inside the capsule of axis ``a``–``b`` and ``radius`` (m): the distance to their
    projection on the axis, clamped to its ends, below the radius."""
    axis = b - a
    s = np.clip((points - a) @ axis / max(axis @ axis, 1e-300), 0.0, 1.0)
    return np.linalg.norm(points - (a + s[:, None] * axis), axis=1) < radius


def test_page_paths_show_through_every_capsule_that_holds_them(page):
    """With the tool point at the flange (scenario B), the arm's capsules hold most of the drawn tool path and
    reference at every frame, so an opaque arm hides them; in the page, every capsule that holds a point of
    either at some frame is see-through (its opacity below 1), so that no point is inside an opaque capsule at
    any frame, and the others are opaque; both paths are drawn at a constant width on the screen."""
    replay, html = page
    record, buffers = recording(html)
    nodes = states(record)[-1][1]
    drawn = [array(buffers, nodes[f"/paths/{n}"]["props"]["points"]).reshape(-1, 3) for n in ("tool", "reference")]
    points = np.vstack(drawn).astype(float)
    caps = link_capsules(replay.robot)
    frames = replay.frames(20.0)
    inside = np.zeros((len(frames), caps.count, len(points)), dtype=bool)
    for f, k in enumerate(frames):
        a, b = caps.segments(replay.robot, replay.q[k])
        inside[f] = [within(a[c], b[c], caps.radius[c], points) for c in range(caps.count)]
    held_by_any = inside.any(axis=1).mean(axis=1)
    assert held_by_any.min() > 0.5, "the premise: the capsules hold most of the paths"
    opacity = {int(n.rsplit("_", 1)[1]): nodes[n]["props"]["opacity"] for n in nodes if "/capsule_" in str(n)}
    see_through = np.array([opacity[c] is not None and opacity[c] < 1.0 for c in range(caps.count)])
    assert np.array_equal(see_through, inside.any(axis=(0, 2)))
    hidden = inside[:, ~see_through].any(axis=1).mean(axis=1)
    print(f"path points inside a capsule: {held_by_any.mean():.3f} on average, {hidden.max():.3f} in an opaque one")
    assert hidden.max() == 0.0
    for name in ("tool", "reference"):
        assert nodes[f"/paths/{name}"]["props"]["thickness_units"] == "screen"
    assert set(path_points(replay)) == {"tool", "reference"}


def test_page_is_one_file_with_no_address_to_fetch(page, tmp_path):
    """No script, style or image is loaded from elsewhere; the page is written where asked."""
    replay, html = page
    assert not re.search(r"""<(script|link|img)[^>]+(src|href)=["']?(https?:)?//""", html)
    assert f"<title>qpnso: {replay.title}</title>" in html and 'id="qpnso-caption"' in html and "ROM_t (blue" in html
    path = write_html(replay, tmp_path / "run.html", fps=5.0)
    assert path.read_text().startswith("<!doctype html>")


# --------------------------------------------------------------- live server
def test_server_serves_the_client_and_plays(result_file):
    """The live server answers with viser's client, and playing advances the time slider and the scene."""
    replay = load_replay(result_file)
    port = free_port()
    server, view, player = serve(replay, port=port, fps=50.0, block=False)
    try:
        page = urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10).read().decode()
        assert "<html" in page.lower()
        player.playing.value = True
        for _ in range(100):
            if view.shown > 0:
                break
            player._stop.wait(0.05)
        assert view.shown > 0 and player.time.value > replay.t[0]
        player.time.value = float(replay.t[-1])
        assert view.shown == len(replay.t) - 1
        assert player.readout.content.startswith(f"t = {replay.t[-1]:.3f} s: arm angle ")
    finally:
        player.stop()
        server.stop()


def test_readout_in_degrees(run, lwr):
    """The live server's line: time (s), arm angle, ROM_t and interval in degrees; unbounded and unknown ends."""
    arrays = dict(run.arrays)
    arrays |= {"ns": np.full_like(arrays["ns"], np.radians(12.34)), "rom_lo": np.full_like(arrays["ns"], -np.inf)}
    arrays |= {"interval_hi": np.full_like(arrays["ns"], np.nan)}
    line = readout(Replay.of(arrays, lwr), 3)
    assert line.startswith(f"t = {arrays['t'][3]:.3f} s: arm angle 12.3°, ROM_t [-∞°, ")
    assert line.endswith(", unknown°]")


# ----------------------------------------------------------- command line
def test_cli_view_writes_a_page(result_file, tmp_path, capsys):
    out = tmp_path / "run.html"
    assert main(["view", str(result_file), "--html", str(out), "--fps", "10"]) == 0
    assert "frames" in capsys.readouterr().out and out.stat().st_size > 100_000


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["view"], "not both"),
        (["view", "x.npz", "--scenario", "B"], "not both"),
        (["view", "nowhere.npz", "--html", "o.html"], "not found"),
        (["view", "x.npz", "--fps", "0"], "--fps"),
        (["view", "x.npz", "--strategy", "qp", "--ignore-obstacles"], "--strategy, --ignore-obstacles do not apply"),
        (["view", "--scenario", "B", "--robot", "iiwa14"], "--robot do not apply to a scenario"),
        (["view", "--scenario", "B", "--duration-scale", "-1"], "--duration-scale"),
        (["view", "x.npz", "--tool-offset", "0,0,0.1"], "--tool-frame and --tool-offset apply with --robot"),
    ],
)
def test_cli_view_refuses_bad_input(argv, message, capsys):
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_cli_view_without_viser_says_how_to_install(monkeypatch, result_file, capsys):
    monkeypatch.setitem(__import__("sys").modules, "viser", None)
    assert main(["view", str(result_file), "--html", "x.html"]) == 2
    assert "pip install 'qpnso[view]'" in capsys.readouterr().err


# ------------------------------------------------------------ real browser
def colour_pixels(png: bytes) -> dict[str, int]:
    """How many pixels of a screenshot have each colour the browser test looks for, outside viser's orange
    notice stripe along the left edge: ``arm``, the arm's orange, lit or shaded (not the red box); ``tool`` and
    ``reference``, the hues of :data:`PATH_HUES` (the paths' colours, pure or seen through a see-through
    capsule's orange), saturated and not dark (no other node of scenario B's scene has those hues)."""
    import io

    import matplotlib.image
    from matplotlib.colors import rgb_to_hsv

    rgb = matplotlib.image.imread(io.BytesIO(png))[..., :3]
    r, g, b = np.moveaxis((rgb * 255).astype(int), -1, 0)
    hue, saturation, value = np.moveaxis(rgb_to_hsv(rgb), -1, 0)
    masks = {"arm": (r > 150) & (r - g > 50) & (g - b > 30)}
    for name, (lo, hi) in PATH_HUES.items():
        masks[name] = (lo <= 360 * hue) & (360 * hue <= hi) & (saturation >= 0.2) & (value >= 0.35)
    return {name: int(mask[:, 30:].sum()) for name, mask in masks.items()}


PATH_HUES = {"tool": (290.0, 345.0), "reference": (150.0, 200.0)}
"""Hue bands (degrees) of the tool path's magenta and the reference's cyan in a screenshot: the pure colours
(300°, 189°) and their mixtures with 30 % of the see-through capsules' orange (measured: about 327° and 160°)."""
PATH_PIXELS_MIN = 20
"""Pixels of each path's colour the screenshot must show (6 s of scenario B at 640×480: 56 and 47 measured;
with the paths hidden in opaque capsules 2 and 0, without the paths 0 and 0)."""


def test_path_hues_hold_the_scene_colours():
    from matplotlib.colors import rgb_to_hsv

    for name, colour in (("tool", TOOL_PATH), ("reference", REFERENCE)):
        hue = 360 * rgb_to_hsv(np.array(colour) / 255)[0]
        assert PATH_HUES[name][0] <= hue <= PATH_HUES[name][1]


def visible(counts: dict[str, int]) -> bool:
    """The arm, the tool path and the reference all drawn (the browser test's bars)."""
    return counts["arm"] > 2000 and min(counts["tool"], counts["reference"]) >= PATH_PIXELS_MIN


@pytest.mark.skipif(headless.CHROMIUM is None, reason="no Chromium installed (apt-get install chromium)")
def test_page_of_scenario_b_opens_in_chromium_without_network(page, tmp_path):
    """A scenario B run's page, opened from a file in headless Chromium with every network address refused,
    draws the arm, the tool path and its reference: a screenshot (its path printed) has more than 2000 pixels
    of the arm's orange and at least PATH_PIXELS_MIN of each path's colour within 90 s."""
    path = tmp_path / "B.html"
    path.write_text(page[1])
    png = headless.screenshot_when(path, lambda png: visible(colour_pixels(png)), tmp_path / "profile")
    out = Path(os.environ.get("QPNSO_TEST_OUTPUT", tmp_path)) / "view_scenario_B.png"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(png)
    counts = colour_pixels(png)
    print(f"screenshot: {out} (pixels of the arm's, the tool path's and the reference's colours: {counts})")
    assert visible(counts), counts
