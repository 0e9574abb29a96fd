"""The viser scene of one axis: built once from its descriptor, updated per tick.

Runs on viser's own thread (see ``servotune.twin.service``). Every setter of a viser
handle queues a message (tens of µs each), so ``AxisScene.apply`` calls a setter only
when what it shows changes visibly: an angle by more than ``MIN_TURN_RAD``, a carriage
by more than ``MIN_SLIDE``, a colour or a text. An axis at rest costs nothing.

Layout (scene units, z up, the viewer in front at -y): each axis is a group at
(x, 0, 0) — a motor body, the disc (radius ``DISC_RADIUS``) with its index mark, two
ghost marks (setpoint, target), a label above; axes with switches get a rail with a
carriage and the switches below the disc.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import viser

from servotune.descriptor import DeviceDescriptor, TwinDescriptor
from servotune.link.base import Sample
from servotune.twin.model import (
    COLOURS,
    SWITCH_OFF,
    SWITCH_ON,
    AxisState,
    Rail,
    angle_rad,
    classify,
    disc_wxyz,
)

DISC_RADIUS = 0.32
DISC_THICKNESS = 0.06
AXIS_PITCH = 1.1  # distance between neighbouring axes
LINK_GAP = 0.4  # extra distance between the axes of two links
RAIL_LENGTH = 0.8
RAIL_Z = -0.62
MIN_TURN_RAD = math.radians(0.25)
MIN_SLIDE = 0.002  # of the rail length
READOUT_PERIOD_S = 0.2  # the position readout is text: 5 updates a second are plenty

# The cylinder primitive's axis is z; a quarter turn about x makes it face -y.
FACE_VIEWER = (math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0)
BODY = (55, 62, 70)
MARK = (250, 250, 250)
SETPOINT_GHOST = (255, 170, 0)
TARGET_GHOST = (120, 80, 255)


@dataclass(frozen=True, slots=True)
class AxisInput:
    """What one tick knows about one axis (a snapshot taken on the app's loop)."""

    sample: Sample | None
    sample_age_s: float | None
    link_state: str
    health: str
    serial: int  # bumped by every sample: unchanged means nothing new arrived


@dataclass(frozen=True, slots=True)
class CameraView:
    """Where a camera looking at a group of nodes sits (viser world coordinates)."""

    position: tuple[float, float, float]
    look_at: tuple[float, float, float]

    def query(self) -> str:
        """URL parameters of viser's client that start the camera here."""

        def vec(v: tuple[float, float, float]) -> str:
            return ",".join(f"{c:.3f}" for c in v)

        return (
            f"initialCameraPosition={vec(self.position)}&initialCameraLookAt="
            f"{vec(self.look_at)}&initialCameraUp=0,0,1"
        )


def camera_for_span(x_min: float, x_max: float, has_stage: bool) -> CameraView:
    """A front view, slightly from above, that fits the x range (and the rails)."""
    centre_x = (x_min + x_max) / 2
    centre_z = -0.2 if has_stage else 0.0
    # The client's vertical field of view is 75°; in a frame at least 4:3 wide the
    # horizontal half-angle is 45° or more, so the half-width fits at that distance.
    half_width = (x_max - x_min) / 2 + 0.6
    distance = max(2.0, half_width)
    return CameraView(
        position=(centre_x, -distance, centre_z + 0.35 * distance),
        look_at=(centre_x, 0.0, centre_z),
    )


class AxisScene:
    """The nodes of one axis and the last values sent to them."""

    def __init__(
        self,
        server: viser.ViserServer,
        root: str,
        x: float,
        name: str,
        descriptor: DeviceDescriptor,
        twin: TwinDescriptor,
    ) -> None:
        self.root = root
        self.x = x
        self._descriptor = descriptor
        self._twin = twin
        scene = server.scene
        scene.add_frame(root, show_axes=False, position=(x, 0.0, 0.0))
        scene.add_box(
            f"{root}/body",
            color=BODY,
            dimensions=(0.3, 0.3, 0.3),
            position=(0.0, 0.2, 0.0),
        )
        scene.add_cylinder(
            f"{root}/shaft",
            radius=0.04,
            height=0.12,
            color=BODY,
            wxyz=FACE_VIEWER,
            position=(0.0, 0.02, 0.0),
        )
        self._rotor = scene.add_frame(f"{root}/rotor", show_axes=False)
        self._disc = scene.add_cylinder(
            f"{root}/rotor/disc",
            radius=DISC_RADIUS,
            height=DISC_THICKNESS,
            color=COLOURS["stale"],
            wxyz=FACE_VIEWER,
            position=(0.0, -0.05, 0.0),
            radial_segments=48,
        )
        # The index mark runs from near the centre to the rim; the ghosts are pointers
        # outside the rim, so they never hide the mark and their angle to it reads as
        # following error (setpoint) and remaining travel (target).
        self._mark = scene.add_box(
            f"{root}/rotor/mark",
            color=MARK,
            dimensions=(0.04, 0.012, DISC_RADIUS * 0.78),
            position=(0.0, -0.085, DISC_RADIUS * 0.59),
        )
        self._setpoint = self._ghost(
            scene, f"{root}/setpoint", SETPOINT_GHOST, 0.6, (0.9, 1.3), 0.05
        )
        self._target = self._ghost(scene, f"{root}/target", TARGET_GHOST, 0.45, (1.0, 1.5), 0.035)
        self._label = scene.add_label(
            f"{root}/label",
            name,
            position=(0.0, 0.0, DISC_RADIUS + 0.16),
            anchor="bottom-center",
            font_screen_scale=0.9,
        )
        self._state_label = scene.add_label(
            f"{root}/state",
            "STALE — connecting",
            position=(0.0, 0.0, DISC_RADIUS + 0.05),
            anchor="bottom-center",
            font_screen_scale=0.8,
        )
        self._readout = scene.add_label(
            f"{root}/readout",
            "",
            position=(0.0, -0.1, -DISC_RADIUS - 0.04),
            anchor="top-center",
            font_screen_scale=0.75,
        )
        self._angle: dict[str, float | None] = {"rotor": None, "setpoint": None, "target": None}
        self._visible: dict[str, bool | None] = {"setpoint": True, "target": True}
        self._state: AxisState | None = None
        self._readout_text = ""
        self._readout_at = -math.inf
        self._serial = -1
        self._stage: _Stage | None = None
        if twin.switch_flags:
            self._stage = _Stage(server, f"{root}/stage", descriptor, twin)

    @staticmethod
    def _ghost(
        scene: viser.SceneApi,
        name: str,
        colour: tuple[int, int, int],
        opacity: float,
        radii: tuple[float, float],
        width: float,
    ) -> viser.FrameHandle:
        """A translucent pointer from ``radii[0]`` to ``radii[1]`` disc radii."""
        frame = scene.add_frame(name, show_axes=False)
        inner, outer = radii[0] * DISC_RADIUS, radii[1] * DISC_RADIUS
        scene.add_box(
            f"{name}/pointer",
            color=colour,
            opacity=opacity,
            dimensions=(width, 0.01, outer - inner),
            position=(0.0, -0.09, (inner + outer) / 2),
        )
        return frame

    def invalidate(self) -> None:
        """Forget what was sent: the next ``apply`` sends every value again (a new
        viewer joined while nothing was being sent)."""
        self._angle = dict.fromkeys(self._angle)
        self._visible = dict.fromkeys(self._visible)
        self._state = None
        self._readout_text = ""
        self._readout_at = -math.inf
        self._serial = -1
        if self._stage is not None:
            self._stage.invalidate()

    @property
    def has_stage(self) -> bool:
        return self._stage is not None

    def apply(self, data: AxisInput, now_s: float) -> None:
        """Update what changed since the last tick (called inside ``atomic()``)."""
        twin = self._twin
        sample = data.sample
        state = classify(
            self._descriptor,
            twin,
            sample.flags if sample is not None else None,
            link_state=data.link_state,
            health=data.health,
            sample_age_s=data.sample_age_s,
        )
        if state != self._state:
            if self._state is None or state.colour != self._state.colour:
                self._disc.color = state.colour
            self._state_label.text = state.text
            self._state = state
        stale = state.kind == "stale"
        if sample is None or data.serial == self._serial:
            if stale and self._stage is not None:
                self._stage.dim()
            self._show_ghosts(
                setpoint=not stale and self._angle["setpoint"] is not None,
                target=not stale and self._angle["target"] is not None,
            )
            return
        self._serial = data.serial
        cpr = twin.counts_per_rev
        position = sample.channels.get("position")
        if position is not None:
            self._turn("rotor", self._rotor, angle_rad(position, cpr))
            if now_s - self._readout_at >= READOUT_PERIOD_S:
                self._readout_at = now_s
                text = f"{position / cpr:+.3f} rev"
                if text != self._readout_text:
                    self._readout.text = text
                    self._readout_text = text
        ghosts: dict[str, bool] = {}
        for key, handle, channel in (
            ("setpoint", self._setpoint, twin.setpoint_channel),
            ("target", self._target, twin.target_channel),
        ):
            value = sample.channels.get(channel) if channel is not None else None
            if value is not None:
                self._turn(key, handle, angle_rad(value, cpr))
            ghosts[key] = value is not None and not stale
        self._show_ghosts(**ghosts)
        if self._stage is not None and position is not None:
            setpoint = sample.channels.get(twin.setpoint_channel or "") if not stale else None
            self._stage.apply(position, setpoint, sample.flags, stale)

    def _turn(self, key: str, handle: viser.FrameHandle, angle: float) -> None:
        last = self._angle[key]
        if last is not None and abs(angle - last) < MIN_TURN_RAD:
            return
        self._angle[key] = angle
        handle.wxyz = disc_wxyz(angle)

    def _show_ghosts(self, *, setpoint: bool, target: bool) -> None:
        for key, handle, show in (
            ("setpoint", self._setpoint, setpoint),
            ("target", self._target, target),
        ):
            if self._visible[key] != show:
                handle.visible = show
                self._visible[key] = show


class _Stage:
    """The linear view of an axis with switches: rail, carriage, setpoint ghost,
    switches (lit red when their flag is on)."""

    def __init__(
        self,
        server: viser.ViserServer,
        root: str,
        descriptor: DeviceDescriptor,
        twin: TwinDescriptor,
    ) -> None:
        scene = server.scene
        count = len(twin.switch_flags)
        known = list(twin.switch_positions_counts) + [None] * count
        self._rail = Rail(twin.counts_per_rev, known[:count])
        self._flags = list(twin.switch_flags)
        labels = {f.name: f.label for f in descriptor.flags}
        scene.add_frame(root, show_axes=False, position=(0.0, -0.1, RAIL_Z))
        scene.add_box(f"{root}/rail", color=BODY, dimensions=(RAIL_LENGTH + 0.08, 0.06, 0.03))
        self._carriage = scene.add_box(
            f"{root}/carriage",
            color=(225, 230, 235),
            dimensions=(0.07, 0.09, 0.07),
            position=(-RAIL_LENGTH / 2, -0.01, 0.05),
        )
        self._ghost = scene.add_box(
            f"{root}/setpoint",
            color=SETPOINT_GHOST,
            opacity=0.45,
            dimensions=(0.07, 0.09, 0.07),
            position=(-RAIL_LENGTH / 2, -0.012, 0.05),
            visible=False,
        )
        self._switches: list[viser.BoxHandle] = []
        self._switch_labels: list[viser.LabelHandle] = []
        for index, flag in enumerate(self._flags):
            self._switches.append(
                scene.add_box(
                    f"{root}/switch{index}",
                    color=SWITCH_OFF,
                    dimensions=(0.03, 0.1, 0.1),
                    position=(self._x(self._rail.switch_place(index, count)), 0.0, 0.05),
                )
            )
            self._switch_labels.append(
                scene.add_label(
                    f"{root}/switch{index}/label",
                    self._switch_text(labels.get(flag, flag), index),
                    position=(0.0, 0.0, -0.07),
                    anchor="top-center",
                    font_screen_scale=0.6,
                )
            )
        self._labels = [labels.get(f, f) for f in self._flags]
        self._lit: list[bool | None] = [None] * count
        self._rail_version = self._rail.version
        self._known = [self._rail.switch_known(i) for i in range(count)]
        self._carriage_at: float | None = None
        self._ghost_at: float | None = None
        self._ghost_shown: bool | None = False
        self._force_switches = False

    def dim(self) -> None:
        """Stale: no switch lit, no setpoint ghost (the carriage stays where it was)."""
        for index, lit in enumerate(self._lit):
            if lit is not False:
                self._switches[index].color = SWITCH_OFF
                self._lit[index] = False
        if self._ghost_shown is not False:
            self._ghost.visible = False
            self._ghost_shown = False

    def invalidate(self) -> None:
        self._lit = [None] * len(self._lit)
        self._carriage_at = None
        self._ghost_at = None
        self._ghost_shown = None
        self._force_switches = True

    def _switch_text(self, label: str, index: int) -> str:
        return label if self._rail.switch_known(index) else f"{label} ?"

    @staticmethod
    def _x(place: float) -> float:
        return (place - 0.5) * RAIL_LENGTH

    def apply(
        self, position: float, setpoint: float | None, flags: Mapping[str, bool], stale: bool
    ) -> None:
        states = [bool(flags.get(f)) for f in self._flags]
        self._rail.observe(position, states)
        count = len(self._flags)
        rescaled = self._rail.version != self._rail_version or self._force_switches
        self._rail_version = self._rail.version
        self._force_switches = False
        for index in range(count):
            known = self._rail.switch_known(index)
            if rescaled or known != self._known[index]:
                self._switches[index].position = (
                    self._x(self._rail.switch_place(index, count)),
                    0.0,
                    0.05,
                )
            if known != self._known[index]:
                self._switch_labels[index].text = self._switch_text(self._labels[index], index)
                self._known[index] = known
            lit = states[index] and not stale
            if lit != self._lit[index]:
                self._switches[index].color = SWITCH_ON if lit else SWITCH_OFF
                self._lit[index] = lit
        place = self._rail.place(position)
        if rescaled or self._carriage_at is None or abs(place - self._carriage_at) >= MIN_SLIDE:
            self._carriage.position = (self._x(place), -0.01, 0.05)
            self._carriage_at = place
        show = setpoint is not None
        if show and setpoint is not None:
            ghost = self._rail.place(setpoint)
            if rescaled or self._ghost_at is None or abs(ghost - self._ghost_at) >= MIN_SLIDE:
                self._ghost.position = (self._x(ghost), -0.012, 0.05)
                self._ghost_at = ghost
        if show != self._ghost_shown:
            self._ghost.visible = show
            self._ghost_shown = show
