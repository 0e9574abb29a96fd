"""The hub's record of each link and axis: what it knows of them, kept from what
their drivers report (``hub.state``) and read by every part of the hub."""

from __future__ import annotations

import asyncio
import math
from dataclasses import dataclass, field

from servotune.link.base import AxisDriver, Link, Sample
from servotune.schema import AxisHealth, AxisInfo, LinkStatus


@dataclass(slots=True)
class AxisEntry:
    driver: AxisDriver
    link: Link
    info: AxisInfo
    storage_key: str
    latest: Sample | None = None
    pending: list[Sample] = field(default_factory=list)
    health: AxisHealth = "offline"
    health_message: str = "connecting"
    operated: bool = False
    device_values: dict[str, int] = field(default_factory=dict)
    last_known: dict[str, int] = field(default_factory=dict)
    compared_at_connect: bool = False
    # Set when a stop could not reach the axis (link down during a bench test): the
    # stop is sent as soon as the axis is back, unless overtaken (``hub.stops.PENDING_STOP_MAX_S``).
    stop_on_reconnect: bool = False
    # When that STOP was pressed (hub clock, and wall clock for the messages); None
    # with ``stop_on_reconnect`` set by someone who did not say (stamped when noticed).
    stop_pressed_at: float | None = None
    stop_pressed_wall: float = 0.0
    # When a command last reached the axis and when a STOP last did (hub clock): a
    # STOP pressed before either does not act any more (``stop_overtaken``).
    commanded_at: float = -math.inf
    stopped_at: float = -math.inf
    # Bumped by every user STOP; sequences (bench, auto-tune) compare it before each step.
    stop_generation: int = 0
    # Why the axis was last stopped, as it was ("STOP was pressed", "stop and hold was
    # pressed", "STOP (dead-man: ...)"): what a sequence that the stop ended reports.
    stop_cause: str = "STOP was pressed"
    # The task that delivers a STOP that could not be sent at once (``hub.stops.StopDelivery``).
    stop_task: asyncio.Task[None] | None = None
    # When the hub last got a sample of this axis (its own monotonic clock), reset when
    # the axis turns ok; ``silent``: the hub itself shows the axis offline because no
    # sample came for AXIS_SILENT_S while its link was up (``hub.state.AXIS_SILENT_S``).
    last_sample_at: float = 0.0
    silent: bool = False
    # The persisted parameters as the device's save command stored them, since the
    # last save servotune saw succeed (None: not known, e.g. after a start).
    stored_values: dict[str, int] | None = None

    def stopped(self, cause: str) -> None:
        """A stop ends every sequence running on the axis; ``cause`` says what it was."""
        self.stop_generation += 1
        self.stop_cause = cause


@dataclass(slots=True)
class LinkEntry:
    link: Link
    status: LinkStatus
    # Supervision: is the link's task running, when it last published its status, how
    # often the hub had to restart it.
    running: bool = False
    updated_at: float = 0.0
    restarts: int = 0
    # The link's ``host_stalls`` counter as last published, and when it last grew (the
    # hub's clock; None: never): its timeouts were excused, the host held its bytes.
    host_stalls: int = 0
    host_stalled_at: float | None = None
