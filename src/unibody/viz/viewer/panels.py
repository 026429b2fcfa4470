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
    """The Identity and Pose folders, and picking a body and joint by clicking it."""
    edit = _Edits(viewer, panels)
    for s in panels.identity:
        s.on_update(edit.on_identity)
    for s in panels.rotation:
        s.on_update(edit.on_rotation)
    panels.joint.on_update(lambda _: edit.load_rotation())
    edit.reset.on_click(lambda _: edit.reset_identity())
    edit.reset_pose.on_click(lambda _: edit.reset_joint())
    if panels.body is not None:
        panels.body.on_update(lambda _: edit.select(edit.labels.index(str(panels.body.value))))
    for i, b in enumerate(viewer._bodies):
        b.mesh.on_click(lambda event, i=i: edit.pick(i, event))
    edit.load_identity()


class _Edits:
    """State of the edit panels: the body they edit, its identity values and joint turns."""

    def __init__(self, viewer: Viewer, panels: Panels) -> None:
        self.viewer, self.panels, self.bodies = viewer, panels, viewer.bodies
        self.labels = [f"{i}: {b.name}" for i, b in enumerate(self.bodies)]
        self.quiet = _Quiet()
        self.edits: dict[tuple[int, int], np.ndarray] = {}  # (body, joint) -> axis-angle turn
        self.values: dict[int, np.ndarray] = {}  # identity values set by the sliders, per body
        self.body = 0
        gui = viewer.server.gui
        with gui.add_folder("Identity"):
            if len(self.bodies) > 1:
                panels.body = gui.add_dropdown("Body", self.labels, initial_value=self.labels[0])
            self.box = gui.add_markdown("")
            width = max((len(b.identity.names) for b in self.bodies if b.identity is not None), default=0)
            for k in range(width):
                panels.identity.append(gui.add_slider(f"p{k}", min=0.0, max=1.0, step=0.01, initial_value=0.5))
            self.reset = gui.add_button("Reset identity")
        with gui.add_folder("Pose"):
            # The rig's names (a body of stored meshes has none: its joint edits do nothing).
            self.names = list(max((b.joint_names for b in self.bodies), key=len)[1:]) or ["(no joints)"]
            panels.joint = gui.add_dropdown("Joint", self.names, initial_value=self.names[0])
            for axis in "xyz":
                panels.rotation.append(
                    gui.add_slider(f"Rotate {axis} (deg)", min=-180, max=180, step=1, initial_value=0)
                )
            self.reset_pose = gui.add_button("Reset joint")

    @property
    def current(self) -> BodySource:
        return self.bodies[self.body]

    @property
    def joint(self) -> int:
        return 1 + self.names.index(str(self.panels.joint.value))

    def load_identity(self) -> None:
        """Relabel, range and set the sliders for the current body's identity."""
        ident = self.current.identity
        self.box.content = f"**{ident.backend}** identity" if ident is not None else "no identity sliders for this body"
        with self.quiet():
            for k, s in enumerate(self.panels.identity):
                if ident is None or k >= len(ident.names):
                    s.visible = False
                    continue
                s.visible, s.label = True, ident.names[k]
                s.min, s.max = float(ident.low[k]), float(ident.high[k])
                s.step = (s.max - s.min) / 100
                s.value = float(self.values.get(self.body, ident.values)[k])

    def load_rotation(self) -> None:
        aa = self.edits.get((self.body, self.joint), np.zeros(3))
        with self.quiet():
            for s, v in zip(self.panels.rotation, np.degrees(aa), strict=True):
                s.value = float(round(v))

    def on_identity(self, _) -> None:
        ident = self.current.identity
        if self.quiet.on or ident is None:
            return
        values = np.array([s.value for s in self.panels.identity[: len(ident.names)]], dtype=np.float64)
        self.values[self.body] = values
        self.current.set_identity(values)
        self.viewer.refresh(self.current)

    def on_rotation(self, _) -> None:
        if self.quiet.on:
            return
        aa = np.radians([float(s.value) for s in self.panels.rotation])
        self.edits[(self.body, self.joint)] = aa
        self.current.set_joint_rotation(self.joint, aa)
        self.viewer.refresh(self.current)

    def reset_identity(self) -> None:
        ident = self.current.identity
        if ident is not None:
            self.values.pop(self.body, None)
            self.current.set_identity(ident.values)
            self.load_identity()
            self.viewer.refresh(self.current)

    def reset_joint(self) -> None:
        self.edits.pop((self.body, self.joint), None)
        self.current.set_joint_rotation(self.joint, np.zeros(3))
        self.load_rotation()
        self.viewer.refresh(self.current)

    def select(self, i: int) -> None:
        """Edit body ``i``: its identity on the sliders, its turn of the picked joint."""
        self.body = i
        self.load_identity()
        self.load_rotation()

    def pick(self, i: int, event) -> None:
        """A click on body ``i`` picks it and the joint nearest the click's ray."""
        b = self.viewer._bodies[i]
        if b.joints is None or len(b.joints) != len(self.names) + 1:
            return
        j = nearest_joint(b.joints + b.offset, np.asarray(event.ray_origin), np.asarray(event.ray_direction))
        if self.panels.body is not None:
            self.panels.body.value = self.labels[i]  # its callback selects the body
        self.select(i)
        self.panels.joint.value = self.names[j - 1]
