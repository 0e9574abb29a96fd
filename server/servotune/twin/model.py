"""What the 3D twin shows for one axis, computed from its descriptor and telemetry.

Pure functions and small value types, no viser: the scene code in
``servotune.twin.scene`` only turns these into node poses, colours and texts, so the
rules (which state wins, when a picture is stale, how counts become angles and rail
positions) are tested without a browser.

Conventions (docs/twin.md): the disc faces the viewer; position 0 puts the index mark
at 12 o'clock and positive counts turn it counter-clockwise as seen from the front.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

from servotune.descriptor import DeviceDescriptor, TwinDescriptor

# No sample for this long (seconds) and the picture turns grey: the slowest demo link
# (Z1100 at 9600 baud, three axes) delivers about 11 samples per second per axis.
STALE_AFTER_S = 1.0

StateKind = Literal["stale", "fault", "moving", "in_position", "idle"]
Rgb = tuple[int, int, int]

COLOURS: dict[StateKind, Rgb] = {
    "stale": (130, 130, 130),
    "fault": (214, 48, 49),
    "moving": (41, 121, 255),
    "in_position": (39, 174, 96),
    "idle": (240, 222, 150),
}
SWITCH_ON: Rgb = (230, 30, 30)
SWITCH_OFF: Rgb = (70, 80, 90)


@dataclass(frozen=True, slots=True)
class AxisState:
    """The one state an axis is drawn in, and the text of its label."""

    kind: StateKind
    text: str

    @property
    def colour(self) -> Rgb:
        return COLOURS[self.kind]


def node_slot(axis_id: str) -> str:
    """A scene-tree name segment for an axis id ('/' separates viser's tree)."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", axis_id)


def classify(
    descriptor: DeviceDescriptor,
    twin: TwinDescriptor,
    flags: Mapping[str, bool] | None,
    *,
    link_state: str,
    health: str,
    sample_age_s: float | None,
) -> AxisState:
    """The state that matters most, in this order: stale (link down, axis offline or
    no recent sample: never a frozen picture that looks live), a fault-severity flag
    (current limit, stall, error: named by its label), moving, in position, at rest."""
    if link_state != "connected":
        return AxisState("stale", f"STALE — link {link_state}")
    if health == "offline":
        return AxisState("stale", "STALE — axis offline")
    if sample_age_s is None or flags is None:
        return AxisState("stale", "STALE — no telemetry yet")
    if sample_age_s > STALE_AFTER_S:
        return AxisState("stale", f"STALE — no telemetry for {sample_age_s:.0f} s")
    faults = [f.label for f in descriptor.flags if f.severity == "fault" and flags.get(f.name)]
    if faults:
        return AxisState("fault", " · ".join(faults))
    if twin.moving_flag is not None and flags.get(twin.moving_flag):
        return AxisState("moving", "moving")
    if twin.in_position_flag is not None and flags.get(twin.in_position_flag):
        return AxisState("in_position", "in position")
    return AxisState("idle", "at rest")


def angle_rad(counts: float, counts_per_rev: int) -> float:
    """Shaft angle of a position in counts (one revolution = 2π)."""
    return 2 * math.pi * counts / counts_per_rev


def disc_wxyz(angle: float) -> tuple[float, float, float, float]:
    """Quaternion of a rotation by ``angle`` about the disc axis.

    The disc axis points from the disc towards the viewer (-y in the scene), so a
    positive angle turns counter-clockwise as seen from the front."""
    half = angle / 2
    return (math.cos(half), 0.0, -math.sin(half), 0.0)


class Rail:
    """Maps positions (counts) to the carriage place on a rail of fixed length.

    Devices rarely know where their limit switches sit, so the rail spans what has
    been seen: every position, every switch position the descriptor gives, and the
    position at which a switch flag last turned on (learned). The span only grows,
    in whole revolutions, so the scale changes seldom; ``version`` counts the changes
    (the scene then moves the switch markers).
    """

    def __init__(self, counts_per_rev: int, known_switches: Sequence[int | None]) -> None:
        self._rev = counts_per_rev
        self.switches: list[float | None] = [
            None if p is None else float(p) for p in known_switches
        ]
        self._lo: float | None = None
        self._hi: float | None = None
        self.version = 0
        for position in self.switches:
            if position is not None:
                self._include(position)

    def _include(self, counts: float) -> None:
        lo = self._lo if self._lo is not None else counts
        hi = self._hi if self._hi is not None else counts
        if self._lo is not None and self._hi is not None and lo <= counts <= hi:
            return
        # Grow to whole revolutions with a revolution of margin beyond what was seen.
        new_lo = math.floor(min(lo, counts) / self._rev - 1) * self._rev
        new_hi = math.ceil(max(hi, counts) / self._rev + 1) * self._rev
        if (new_lo, new_hi) != (self._lo, self._hi):
            self._lo, self._hi = new_lo, new_hi
            self.version += 1

    def observe(self, counts: float, switch_states: Sequence[bool]) -> None:
        """Take a sample: widen the span if needed, learn where a switch is on."""
        self._include(counts)
        for index, on in enumerate(switch_states):
            if on and index < len(self.switches) and self.switches[index] is None:
                self.switches[index] = counts

    @property
    def span_counts(self) -> tuple[float, float]:
        lo = self._lo if self._lo is not None else -float(self._rev)
        hi = self._hi if self._hi is not None else float(self._rev)
        return lo, hi

    def place(self, counts: float) -> float:
        """0..1 along the rail."""
        lo, hi = self.span_counts
        return min(1.0, max(0.0, (counts - lo) / (hi - lo)))

    def switch_place(self, index: int, count: int) -> float:
        """Where switch ``index`` of ``count`` is drawn, 0..1: at its known or learned
        position, else at its end of the rail (the first at the negative end)."""
        position = self.switches[index] if index < len(self.switches) else None
        if position is not None:
            return self.place(position)
        if count == 1:
            return 0.0
        return index / (count - 1)

    def switch_known(self, index: int) -> bool:
        return index < len(self.switches) and self.switches[index] is not None
