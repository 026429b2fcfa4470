"""The viewer's GUI: timeline, display switches, identity sliders, pose of a picked joint.

Each control calls one :class:`~unibody.viz.viewer.app.Viewer` method; the identity and pose
panels hand new values to the body (:class:`~unibody.viz.viewer.tracks.BodySource`) and ask
the viewer to show it again.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from .tracks import nearest_joint

if TYPE_CHECKING:
    from .app import Viewer
    from .tracks import BodySource

__all__ = ["Panels", "build_panels"]


@dataclass
class Panels:
    """Handles of the controls (tests and scripts drive the viewer through them)."""

    play: object
    frame: object
    speed: object
    loop: object
    mesh: object
    skeleton: object
    joint_names: object
    marker_names: object
    intersections: object
    body: object | None = None
    identity: list = field(default_factory=list)
    joint: object | None = None
    rotation: list = field(default_factory=list)


def build_panels(viewer: Viewer) -> Panels:
    """Add the controls to ``viewer.server.gui`` and wire them to ``viewer``."""
    gui = viewer.server.gui
    with gui.add_folder("Playback"):
        play = gui.add_button("Play")
        frame = gui.add_slider("Frame", min=0, max=max(viewer.num_frames - 1, 1), step=1, initial_value=0)
        speed = gui.add_slider("Speed", min=0.1, max=4.0, step=0.1, initial_value=1.0)
        loop = gui.add_checkbox("Loop", initial_value=True)
        gui.add_markdown(f"{viewer.num_frames} frames at {viewer.fps:g} fps")
    with gui.add_folder("Display"):
        mesh = gui.add_checkbox("Mesh", initial_value=True)
        skeleton = gui.add_checkbox("Skeleton", initial_value=False)
        joint_names = gui.add_checkbox("Joint names", initial_value=False)
        marker_names = gui.add_checkbox("Marker names", initial_value=False)
        intersections = gui.add_checkbox(
            "Self-intersections", initial_value=False, hint="triangles that cut the body, in red (drawn when paused)"
        )
    panels = Panels(play, frame, speed, loop, mesh, skeleton, joint_names, marker_names, intersections)

    @play.on_click
    def _(_) -> None:
        viewer.play(not viewer.playing)
        play.label = "Pause" if viewer.playing else "Play"

    @frame.on_update
    def _(event) -> None:
        # A user's drag moves the play clock; the playback thread's own steps only show.
        (viewer.seek if event.client is not None else viewer.show)(int(frame.value))

    speed.on_update(lambda _: setattr(viewer, "speed", float(speed.value)))
    loop.on_update(lambda _: setattr(viewer, "loop", bool(loop.value)))
    mesh.on_update(lambda _: viewer.set_mesh(bool(mesh.value)))
    skeleton.on_update(lambda _: viewer.set_skeleton(bool(skeleton.value)))
    joint_names.on_update(lambda _: viewer.set_joint_names(bool(joint_names.value)))
    marker_names.on_update(lambda _: viewer.set_marker_names(bool(marker_names.value)))
    intersections.on_update(lambda _: viewer.set_intersections(bool(intersections.value)))
    if viewer.bodies:
        _edit_panels(viewer, panels)
    return panels


class _Quiet:
    """A flag that mutes slider callbacks while the panel itself sets slider values."""

    def __init__(self) -> None:
        self.on = False

    @contextlib.contextmanager
    def __call__(self):
        self.on = True
        try:
            yield
        finally:
            self.on = False


def _edit_panels(viewer: Viewer, panels: Panels) -> None:
    gui = viewer.server.gui
    bodies = viewer.bodies
    labels = [f"{i}: {b.name}" for i, b in enumerate(bodies)]
    quiet = _Quiet()
    edits: dict[tuple[int, int], np.ndarray] = {}
    values: dict[int, np.ndarray] = {}  # identity values set by the sliders, per body
    state = {"body": 0}

    def current() -> BodySource:
        return bodies[state["body"]]

    with gui.add_folder("Identity"):
        if len(bodies) > 1:
            panels.body = gui.add_dropdown("Body", labels, initial_value=labels[0])
        box = gui.add_markdown("")
        width = max((len(b.identity.names) for b in bodies if b.identity is not None), default=0)
        for k in range(width):
            panels.identity.append(gui.add_slider(f"p{k}", min=0.0, max=1.0, step=0.01, initial_value=0.5))
        reset = gui.add_button("Reset identity")
    with gui.add_folder("Pose"):
        # The rig's names (a body of stored meshes has none: its joint edits do nothing).
        names = list(max((b.joint_names for b in bodies), key=len)[1:]) or ["(no joints)"]
        panels.joint = gui.add_dropdown("Joint", names, initial_value=names[0])
        for axis in "xyz":
            panels.rotation.append(gui.add_slider(f"Rotate {axis} (deg)", min=-180, max=180, step=1, initial_value=0))
        reset_pose = gui.add_button("Reset joint")

    def load_identity() -> None:
        """Relabel, range and set the sliders for the current body's identity."""
        ident = current().identity
        box.content = f"**{ident.backend}** identity" if ident is not None else "no identity sliders for this body"
        with quiet():
            for k, s in enumerate(panels.identity):
                if ident is None or k >= len(ident.names):
                    s.visible = False
                    continue
                s.visible, s.label = True, ident.names[k]
                s.min, s.max = float(ident.low[k]), float(ident.high[k])
                s.step = (s.max - s.min) / 100
                s.value = float(values.get(state["body"], ident.values)[k])

    def joint_index() -> int:
        return 1 + names.index(str(panels.joint.value))

    def load_rotation() -> None:
        aa = edits.get((state["body"], joint_index()), np.zeros(3))
        with quiet():
            for s, v in zip(panels.rotation, np.degrees(aa), strict=True):
                s.value = float(round(v))

    def on_identity(_) -> None:
        ident = current().identity
        if quiet.on or ident is None:
            return
        values[state["body"]] = np.array([s.value for s in panels.identity[: len(ident.names)]], dtype=np.float64)
        current().set_identity(values[state["body"]])
        viewer.refresh(current())

    def on_rotation(_) -> None:
        if quiet.on:
            return
        aa = np.radians([float(s.value) for s in panels.rotation])
        edits[(state["body"], joint_index())] = aa
        current().set_joint_rotation(joint_index(), aa)
        viewer.refresh(current())

    for s in panels.identity:
        s.on_update(on_identity)
    for s in panels.rotation:
        s.on_update(on_rotation)
    panels.joint.on_update(lambda _: load_rotation())

    @reset.on_click
    def _(_) -> None:
        ident = current().identity
        if ident is not None:
            values.pop(state["body"], None)
            current().set_identity(ident.values)
            load_identity()
            viewer.refresh(current())

    @reset_pose.on_click
    def _(_) -> None:
        edits.pop((state["body"], joint_index()), None)
        current().set_joint_rotation(joint_index(), np.zeros(3))
        load_rotation()
        viewer.refresh(current())

    if panels.body is not None:

        @panels.body.on_update
        def _(_) -> None:
            state["body"] = labels.index(str(panels.body.value))
            load_identity()
            load_rotation()

    def pick(i: int, event) -> None:
        """A click on body ``i`` picks it and the joint nearest the click's ray for the Pose panel."""
        b = viewer._bodies[i]
        if b.joints is None or len(b.joints) != len(names) + 1:
            return
        j = nearest_joint(b.joints + b.offset, np.asarray(event.ray_origin), np.asarray(event.ray_direction))
        if panels.body is not None:
            panels.body.value = labels[i]
        state["body"] = i
        panels.joint.value = names[j - 1]
        load_rotation()

    for i, b in enumerate(viewer._bodies):
        b.mesh.on_click(lambda event, i=i: pick(i, event))

    load_identity()
