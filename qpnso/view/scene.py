"""A replay drawn with viser (the optional extra ``view``): a live server with a timeline, or one HTML page.

The scene (names are viser's scene-tree paths):

* ``/arm/joint_k``: joint k's frame, moved to Pinocchio's ``oMi`` at each shown tick; the link capsules
  (:func:`~qpnso.view.geometry.capsule_shapes`) are its children, the tool frame a child of its joint; a
  capsule that holds a point of the tool path or of its reference at some shown tick is see-through
  (:data:`SEE_THROUGH_OPACITY`): with the tool point at the flange the hand's capsule holds nearly all of both;
* ``/paths/reference`` (cyan) and ``/paths/tool`` (magenta, drawn after it): the tool point's reference and
  its recorded path (:func:`path_points`), :data:`PATH_PX` wide on the screen whatever the zoom, in colours
  that no other part has, even seen through a see-through capsule;
* ``/elbow``: the elbow circle's frame (:func:`~qpnso.view.geometry.circle_frame`), with the circle (grey),
  ROM_t (blue) and the continuity interval (green) as arcs outside it (:data:`ROM_OFFSET_M`,
  :data:`INTERVAL_OFFSET_M`: clear of the arm's capsules), the spoke from the centre through the elbow at the
  recorded arm angle out to the interval's arc, a ball at its end (black), labels at ROM_t's upper end and the
  interval's lower end; hidden where the arm angle is undefined;
* ``/obstacles/k``: the room's keep-out volumes (translucent red).

:func:`write_html` records the shown ticks at a frame rate into viser's scene serializer and writes its
self-contained page (viser's client and the recording, base64, in one file: no server, no network); the page
has viser's timeline to play and scrub.  :func:`serve` runs a viser server with a time slider, play and speed.
"""

from __future__ import annotations

import contextlib
import html
import io
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pinocchio as pin

from qpnso.errors import InputError, SingularityError
from qpnso.model.collision import link_capsules
from qpnso.model.obstacles import Box, Capsule, Obstacle, Sphere
from qpnso.view.geometry import (
    arc,
    capsule_shapes,
    capsules_holding,
    circle_frame,
    elbow_circle_at,
    framing_distance,
    joint_placements,
    polyline_segments,
    unit_circle,
)
from qpnso.view.replay import Replay

NO_VISER = "the 3-D view needs viser, which is not installed (pip install 'qpnso[view]')"

ARM = (232, 120, 32)
TOOL_PATH = (200, 0, 200)
REFERENCE = (0, 170, 200)
CIRCLE = (150, 150, 150)
ROM = (30, 90, 225)
INTERVAL = (40, 170, 60)
ELBOW = (20, 20, 20)
OBSTACLE = (220, 40, 40)

ROM_OFFSET_M = 0.10
"""ROM_t's arc is drawn this far (m) outside the elbow circle, clear of the upper arm's capsule."""
INTERVAL_OFFSET_M = 0.16
"""The continuity interval's arc, and the ball of the arm angle's spoke, this far (m) outside the circle."""
PATH_POINTS_MAX = 4000
"""At most this many points of the tool's path and of its reference are drawn."""
PATH_PX = 3.0
"""Width of the tool's recorded path and of its reference on the screen (pixels, whatever the zoom)."""
VIEW_DIRECTION = np.array([0.9, -0.9, 0.5])
"""From where the page's camera looks at the scene (world frame; only its direction counts)."""
FRAMING_MARGIN = 1.1
"""The camera this much farther than the nearest distance at which everything drawn is in view."""
SEE_THROUGH_OPACITY = 0.3
"""Opacity of a link capsule that would hide the tool path or its reference (the paths drawn inside it show
through, tinted by it); the other capsules are opaque."""


def viser_module():
    """viser, or an InputError saying how to install it."""
    try:
        import viser
    except ImportError:
        raise InputError(NO_VISER) from None
    return viser


def wxyz(rotation: np.ndarray) -> np.ndarray:
    """A rotation matrix as viser's quaternion ``(w, x, y, z)``."""
    x, y, z, w = pin.Quaternion(rotation).coeffs()
    return np.array([w, x, y, z])


def capsule_mesh(a: np.ndarray, b: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (m) and faces of the capsule of axis ``a``–``b`` and ``radius`` (trimesh's capsule)."""
    import trimesh

    axis = np.asarray(b, float) - a
    length = float(np.linalg.norm(axis))
    mesh = trimesh.creation.capsule(height=length, radius=radius, count=[16, 16])
    z = axis / length if length > 0 else np.array([0.0, 0.0, 1.0])
    transform = trimesh.geometry.align_vectors([0.0, 0.0, 1.0], z)
    transform[:3, 3] = 0.5 * (np.asarray(a, float) + b)
    mesh.apply_transform(transform)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` now."""
    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


class ReplayScene:
    """The scene of ``replay`` on a viser ``server`` (module docstring), showing the ticks ``frames`` (indices;
    the capsules that hold part of the paths at one of them are see-through); :meth:`show` moves it to a
    tick."""

    def __init__(self, server, replay: Replay, frames: np.ndarray) -> None:
        self.replay = replay
        self.scene = server.scene
        robot = replay.robot
        self.frames = frames
        self.paths = path_points(replay)
        self.see_through = capsules_holding(robot, replay.q[frames], np.vstack(list(self.paths.values())))
        self.joints = [self.scene.add_frame(f"/arm/joint_{j}", show_axes=False) for j in range(1, robot.model.njoints)]
        self._add_arm()
        self._add_paths()
        self._add_obstacles()
        self._add_elbow()
        self.shown = -1
        self._lock = threading.Lock()  # the player's thread and viser's event thread both move the scene
        self.show(0)

    # ------------------------------------------------------------ static parts
    def _add_arm(self) -> None:
        robot = self.replay.robot
        for k, shape in enumerate(capsule_shapes(robot)):
            parent = f"/arm/joint_{shape.joint}" if shape.joint > 0 else "/arm/base"
            vertices, faces = capsule_mesh(shape.a, shape.b, shape.radius)
            opacity = SEE_THROUGH_OPACITY if self.see_through[k] else None
            self.scene.add_mesh_simple(f"{parent}/capsule_{k}", vertices, faces, color=ARM, opacity=opacity)
        tool = robot.model.frames[robot.tool_frame_id]
        self.scene.add_frame(
            f"/arm/joint_{tool.parentJoint}/tool",
            axes_length=0.08,
            axes_radius=0.004,
            origin_radius=0.004,  # (viser's default, twice the axes' radius, hides the tool path's last 8 mm)
            position=tool.placement.translation,
            wxyz=wxyz(tool.placement.rotation),
        )
        self.scene.add_grid("/floor", width=2.0, height=2.0, cell_size=0.1)

    def _add_paths(self) -> None:
        for name, colour in (("reference", REFERENCE), ("tool", TOOL_PATH)):
            segments = polyline_segments(self.paths[name])
            self.scene.add_line_segments(
                f"/paths/{name}", segments, colour, thickness=PATH_PX, thickness_units="screen"
            )

    def _add_obstacles(self) -> None:
        for k, obstacle in enumerate(self.replay.obstacles):
            add_obstacle(self.scene, f"/obstacles/{k}", obstacle)

    def _add_elbow(self) -> None:
        s = self.scene
        self.elbow = s.add_frame("/elbow", show_axes=False)
        empty = np.zeros((1, 2, 3))
        self.circle = s.add_line_segments("/elbow/circle", empty, CIRCLE, thickness=0.003)
        self.rom = s.add_line_segments("/elbow/rom", empty, ROM, thickness=0.012)
        self.interval = s.add_line_segments("/elbow/interval", empty, INTERVAL, thickness=0.006)
        self.spoke = s.add_line_segments("/elbow/spoke", empty, ELBOW, thickness=0.004)
        self.marker = s.add_icosphere("/elbow/arm_angle", radius=0.02, color=ELBOW)
        self.labels = {name: s.add_label(f"/elbow/label_{name}", name) for name in ("ROM_t", "interval")}

    def set_camera(self, server) -> None:
        """Look along :data:`VIEW_DIRECTION` (from the front right, above) at the middle of what the shown ticks
        draw (:meth:`drawn_points`), :data:`FRAMING_MARGIN` times as far as keeps it all in viser's field of
        view."""
        points = self.drawn_points()
        target = 0.5 * (points.min(axis=0) + points.max(axis=0))
        distance = FRAMING_MARGIN * framing_distance(points, target, VIEW_DIRECTION, server.initial_camera.fov)
        server.initial_camera.look_at = tuple(target)
        server.initial_camera.position = tuple(target + distance * VIEW_DIRECTION / np.linalg.norm(VIEW_DIRECTION))
        server.initial_camera.up = (0.0, 0.0, 1.0)

    def drawn_points(self) -> np.ndarray:
        """Points (k, 3; m, world) around what the shown ticks draw: the ends of the arm's capsules pushed out by
        their radii along the world axes, the paths, and each elbow circle at the radius of the interval's arc."""
        robot, caps = self.replay.robot, link_capsules(self.replay.robot)
        reach = max(caps.radius) * np.vstack([np.eye(3), -np.eye(3)])
        ring = unit_circle(0.0)[:: max(1, len(unit_circle(0.0)) // 24)]
        points = [*self.paths.values()]
        for k in self.frames:
            points.append((caps.points(robot, self.replay.q[k])[:, None, :] + reach[None]).reshape(-1, 3))
            try:
                circle = elbow_circle_at(robot, self.replay.q[k])
            except SingularityError:
                continue
            frame = circle_frame(circle)
            points.append(frame.translation + (circle.radius + INTERVAL_OFFSET_M) * ring @ frame.rotation.T)
        return np.vstack(points)

    # ------------------------------------------------------------------ motion
    def show(self, k: int) -> None:
        """Move the scene to tick ``k``: the joints' frames, the elbow circle, ROM_t, the interval, the arm angle."""
        with self._lock:
            r = self.replay
            for node, placement in zip(self.joints, joint_placements(r.robot, r.q[k])):
                node.position = placement.translation
                node.wxyz = wxyz(placement.rotation)
            self._show_elbow(k)
            self.shown = k

    def _show_elbow(self, k: int) -> None:
        r = self.replay
        ns = float(r.ns[k])
        try:
            circle = elbow_circle_at(r.robot, r.q[k])
        except SingularityError:  # the wrist on the vertical through the shoulder: no circle to draw
            circle = None
        if circle is None or np.isnan(ns):
            self.elbow.visible = False
            return
        frame = circle_frame(circle)
        self.elbow.position, self.elbow.wxyz, self.elbow.visible = frame.translation, wxyz(frame.rotation), True
        rad = circle.radius
        self.circle.points = polyline_segments(rad * unit_circle(ns))
        arcs = ((self.rom, r.rom[k], rad + ROM_OFFSET_M), (self.interval, r.interval[k], rad + INTERVAL_OFFSET_M))
        for (handle, (lo, hi), radius), label in zip(arcs, self.labels.values()):
            points = arc(lo, hi, radius, ns)
            handle.visible = label.visible = points is not None
            if points is not None:
                handle.points = polyline_segments(points)
                label.position = points[-1] if label is self.labels["ROM_t"] else points[0]
        tip = (rad + INTERVAL_OFFSET_M) * np.array([np.cos(ns), np.sin(ns), 0.0])
        self.spoke.points = np.array([[np.zeros(3), tip]])
        self.marker.position = tip


def path_points(replay: Replay) -> dict[str, np.ndarray]:
    """The drawn points (k, 3; m, world) of the reference and of the tool's recorded path: every tick's, or
    evenly spaced ticks when there are more than :data:`PATH_POINTS_MAX`, the last tick included."""
    step = max(1, len(replay.t) // PATH_POINTS_MAX)
    return {name: np.vstack([p[::step], p[-1:]]) for name, p in (("reference", replay.ref), ("tool", replay.tool))}


def add_obstacle(scene, name: str, obstacle: Obstacle) -> None:
    """A keep-out volume (world frame, m) as a translucent solid."""
    if isinstance(obstacle, Box):
        scene.add_box(
            name,
            OBSTACLE,
            dimensions=2.0 * np.asarray(obstacle.half_extents),
            opacity=0.35,
            position=obstacle.center,
            wxyz=wxyz(obstacle.matrix),
        )
    elif isinstance(obstacle, Sphere):
        scene.add_icosphere(name, obstacle.radius, OBSTACLE, opacity=0.35, position=obstacle.center)
    elif isinstance(obstacle, Capsule):
        vertices, faces = capsule_mesh(np.asarray(obstacle.a), np.asarray(obstacle.b), obstacle.radius)
        scene.add_mesh_simple(name, vertices, faces, color=OBSTACLE, opacity=0.35)
    else:
        raise InputError(f"cannot draw obstacle {obstacle!r}")


# ---------------------------------------------------------------- page, server
def html_page(replay: Replay, fps: float = 20.0) -> str:
    """The self-contained page that plays ``replay`` at ``fps`` frames per second (each frame the tick nearest
    its time, :meth:`Replay.frames`)."""
    viser = viser_module()
    frames = replay.frames(fps)
    with contextlib.redirect_stdout(io.StringIO()):  # viser prints its server's addresses: none here
        server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    try:
        view = ReplayScene(server, replay, frames)
        view.show(int(frames[0]))
        recording = server.get_scene_serializer()
        view.set_camera(server)
        for before, k in zip(frames[:-1], frames[1:]):
            recording.insert_sleep(float(replay.t[k] - replay.t[before]))
            view.show(int(k))
        return with_caption(recording.as_html(), replay.title)
    finally:
        with contextlib.redirect_stdout(io.StringIO()):
            server.stop()


def with_caption(page: str, title: str) -> str:
    """viser's page with ``title`` as its title and, at the top right, the title and :data:`LEGEND` (the page
    has no panel of its own for them), in the font viser's page embeds (Inter)."""
    text = html.escape(title)
    caption = (
        '<div id="qpnso-caption" style="position:fixed;top:8px;right:8px;max-width:280px;z-index:1000;'
        "padding:6px 10px;background:rgba(255,255,255,0.85);font-size:11px;font-family:Inter,sans-serif;"
        f'color:#222;border-radius:4px;pointer-events:none"><b>{text}</b><br>{html.escape(LEGEND)}</div>'
    )
    page = page.replace("<title>Viser</title>", f"<title>qpnso: {text}</title>", 1)
    at = page.rindex("</body>")
    return page[:at] + caption + page[at:]


def write_html(replay: Replay, path: str | Path, fps: float = 20.0) -> Path:
    """Write :func:`html_page` to ``path`` (atomically); returns the path."""
    from qpnso.control.offline import atomic_write

    text = html_page(replay, fps).encode()
    return atomic_write(Path(path), lambda f: f.write(text))


def serve(replay: Replay, host: str = "127.0.0.1", port: int = 8080, fps: float = 20.0, block: bool = True):
    """Serve ``replay`` on ``http://host:port``: the scene, a time slider (s), play, speed and the legend.  With
    ``block`` it plays until Ctrl+C, then stops the server; otherwise it returns ``(server, view, player)``,
    ``player`` a :class:`Player` the caller stops."""
    viser = viser_module()
    server = viser.ViserServer(host=host, port=port, verbose=False)
    try:
        view = ReplayScene(server, replay, replay.frames(fps))
        view.set_camera(server)
        player = Player(server, view, fps)
    except BaseException:
        server.stop()
        raise
    if not block:
        return server, view, player
    print(f"qpnso view: {replay.title}: http://{host}:{server.get_port()} (Ctrl+C stops)", flush=True)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        player.stop()
        server.stop()
    return None


class Player:
    """The live server's controls: a time slider (s), play and speed, and a thread that advances the slider
    at ``fps`` frames per second while playing."""

    def __init__(self, server, view: ReplayScene, fps: float) -> None:
        r = view.replay
        self.fps, self.view = fps, view
        gui = server.gui
        gui.add_markdown(f"**{r.title}**\n\n{LEGEND}")
        self.readout = gui.add_markdown(readout(r, 0))
        self.time = gui.add_slider(
            "t (s)", min=float(r.t[0]), max=float(r.t[-1]), step=max(1.0 / fps, 1e-3), initial_value=float(r.t[0])
        )
        self.playing = gui.add_checkbox("play", initial_value=False)
        self.speed = gui.add_dropdown("speed", ("0.25", "0.5", "1", "2", "4"), initial_value="1")
        self.time.on_update(lambda _: self.show(r.at(self.time.value)))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        r = self.view.replay
        while not self._stop.wait(1.0 / self.fps):
            if self.playing.value:
                t = self.time.value + float(self.speed.value) / self.fps
                self.time.value = float(r.t[0]) if t > r.t[-1] else t

    def show(self, k: int) -> None:
        """Move the scene to tick ``k`` and say where the elbow is."""
        self.view.show(k)
        self.readout.content = readout(self.view.replay, k)

    def stop(self) -> None:
        """Stop advancing the slider."""
        self._stop.set()
        self._thread.join()


LEGEND = (
    "arm: link capsules (orange; see-through where they would hide the tool path); tool path: recorded "
    "(magenta), reference (cyan); elbow circle (grey) with "
    "ROM_t (blue, 10 cm outside) and the continuity interval (green, 16 cm outside); the arm angle: spoke "
    "through the elbow and ball (black); "
    "keep-out volumes (translucent red)."
)


def readout(replay: Replay, k: int) -> str:
    """Tick ``k`` in one line: its time (s), the arm angle, ROM_t and the continuity interval (degrees)."""

    def deg(x: float) -> str:
        return f"{np.degrees(x):.1f}" if np.isfinite(x) else ("unknown" if np.isnan(x) else f"{'-' if x < 0 else '+'}∞")

    rom, interval = replay.rom[k], replay.interval[k]
    return (
        f"t = {replay.t[k]:.3f} s: arm angle {deg(replay.ns[k])}°, ROM_t [{deg(rom[0])}°, {deg(rom[1])}°], "
        f"interval [{deg(interval[0])}°, {deg(interval[1])}°]"
    )
