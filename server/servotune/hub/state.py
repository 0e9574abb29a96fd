"""The hub's state and its fan-out: what it knows of every link and axis, and what it tells clients.

What lives here (the lower half of the hub): the per-link and
per-axis records (``LinkEntry``, ``AxisEntry``), ``HubState`` with the ``DriverSink``
callbacks that keep them (samples, link status, axis health, params, with the compare
against the last applied settings and their saving), the hub's own judgement of a link
that stopped reporting (``STATUS_STALE_S``) and of an axis that sent no sample
(``AXIS_SILENT_S``), the event log, the queries, the delivery of a STOP that could not
be sent at once (it is set off from here: when an axis is back, and on the fan-out's
status tick) and with it ``stop_all``, and the fan-out to websocket clients.
``hub.hub.Hub`` adds on top what drives the devices otherwise: the command path (writes,
commands, console), the link owner tasks and the demo autopilot.

The seam is the direction: this half takes in what the drivers report and sends it
out to clients; ``hub/hub.py`` sends what users ask for to the devices. The one
exception is the STOP, which lives here because its retry is set off by what the
drivers report. Nothing here calls into ``hub/hub.py``.

Fan-out: samples are batched per axis about 30 times a second and serialised once;
every websocket client has its own bounded queue. A slow client loses its oldest
telemetry batches (counted and reported to it), never status or events, and never
slows the serial side or the other clients.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Final, Protocol, runtime_checkable

from pydantic import BaseModel

from servotune import __version__
from servotune.descriptor import DeviceDescriptor
from servotune.hub.stops import StopKind, StopService
from servotune.link.base import (
    AxisDriver,
    DeviceRefusedError,
    DriverError,
    HasCounters,
    HasWireBusy,
    Link,
    LinkDownError,
    Sample,
    StopOutcome,
)
from servotune.schema import (
    AxisHealth,
    AxisInfo,
    AxisState,
    AxisStatus,
    ClientStats,
    Event,
    EventLevel,
    Hello,
    LinkInfo,
    LinkState,
    LinkStatus,
    Params,
    StorageStatus,
    Telemetry,
)
from servotune.storage import Storage, StorageError

logger = logging.getLogger(__name__)

BATCH_PERIOD_S = 1 / 30
STATUS_PERIOD_S = 1.0
# A link that has not published its status for this long is shown stalled, not connected.
STATUS_STALE_S = 3.5
CLIENT_QUEUE_MESSAGES = 256
# A STOP that could not be sent is sent again once the link and axis are back; while the
# link is connected it is tried this many times before the user is told to press again.
STOP_RETRIES_CONNECTED = 10
# A STOP acts on the motion the user saw when pressing it, never on motion started
# after it: a pending STOP is dropped by any command that reached the axis since, by a
# STOP that reached it since (the dead-man's, a hand-over's), and after this long. A
# STOP delivered 30 s late would cut whatever whoever stands at the machine started
# meanwhile (a network cut that ends late delivers it late); after 10 s the
# user is told it was not sent, and checks the axis.
PENDING_STOP_MAX_S: Final = 10.0
# An axis shown "ok" whose link is up (connected, or error while it still polls) and
# that sent no telemetry sample for this long is shown offline. A module on a
# shared line can stop answering its polls while the others answer: the link then
# stays connected, the driver counts desyncs but never sees 3 failures in a row, and
# without this rule the silent axis would be shown "ok" forever. 3 s is many poll
# cycles of every driver (each samples every axis several times a second) and close
# to STATUS_STALE_S, the hub's horizon for a link that stopped reporting, so a short
# hold-up of a busy host does not trip it.
AXIS_SILENT_S: Final = 3.0


class UnknownAxisError(KeyError):
    pass


class StopOvertakenError(DeviceRefusedError):
    """A STOP not sent because the axis was commanded or stopped after it was pressed."""


@runtime_checkable
class PressTimedStop(Protocol):
    """A driver whose STOP carries when it was pressed, so that the far end (a rig,
    ``servotune.bus``) can refuse it if its axis was commanded since
    (``StopOvertakenError``). ``pressed_at``: the hub's clock."""

    async def stop_pressed(self, pressed_at: float) -> None: ...


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
    # stop is sent as soon as the axis is back, unless overtaken (``PENDING_STOP_MAX_S``).
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
    # The task that delivers a STOP that could not be sent at once (see _deliver_stop).
    stop_task: asyncio.Task[None] | None = None
    # When the hub last got a sample of this axis (its own monotonic clock), reset when
    # the axis turns ok; ``silent``: the hub itself shows the axis offline because no
    # sample came for AXIS_SILENT_S while its link was up (see _check_silent_axes).
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


class ClientQueue:
    """Outgoing messages of one websocket client (JSON text), bounded.

    When full, the oldest *telemetry* message is dropped first; status, params and
    events are kept because a client must not miss a state change.
    """

    def __init__(self, max_messages: int = CLIENT_QUEUE_MESSAGES) -> None:
        self._items: deque[tuple[bool, str]] = deque()
        self._max = max_messages
        self._event = asyncio.Event()
        self.sent = 0
        self.dropped = 0

    def put(self, text: str, *, droppable: bool) -> None:
        self._items.append((droppable, text))
        while len(self._items) > self._max:
            for index, (is_droppable, _) in enumerate(self._items):
                if is_droppable:
                    del self._items[index]
                    self.dropped += 1
                    break
            else:
                # Only non-droppable messages: keep the newest ones.
                self._items.popleft()
                self.dropped += 1
        self._event.set()

    async def get(self) -> str:
        while not self._items:
            self._event.clear()
            await self._event.wait()
        self.sent += 1
        return self._items.popleft()[1]

    def __len__(self) -> int:
        return len(self._items)


class AutopilotGate(Protocol):
    """Who decides when the demo autopilot may drive an axis (``servotune.hub.control_lock``).

    Without a gate the autopilot stops for good the first time a user operates an axis.
    """

    def autopilot_paused(self, axis_id: str) -> None:
        """The autopilot stopped driving ``axis_id`` (someone operated it, or STOP)."""
        ...

    def autopilot_may_resume(self, axis_id: str) -> bool:
        """May the autopilot drive ``axis_id`` again now? True means it holds the axis."""
        ...


class HubState:
    """The records of the hub's links and axes, kept from what their drivers report,
    and the fan-out of it to clients; ``hub.hub.Hub`` is the one to construct."""

    def __init__(
        self,
        links: list[Link],
        storage: Storage,
        *,
        autopilot: bool = False,
        clock: Callable[[], float] = time.monotonic,
        link_sink_binder: Callable[[HubState], None] | None = None,
    ) -> None:
        self._clock = clock
        self._t0 = clock()
        self._storage = storage
        self.autopilot = autopilot
        self._links: dict[str, LinkEntry] = {}
        self._axes: dict[str, AxisEntry] = {}
        self._clients: set[ClientQueue] = set()
        self._events: deque[Event] = deque(maxlen=200)
        self._tasks: list[asyncio.Task[None]] = []
        # The watch of each axis' last move to a target (servotune.hub.movewatch, Hub).
        self._move_watches: dict[str, asyncio.Task[None]] = {}
        self._sample_listeners: list[Callable[[str, Sample], None]] = []
        # Set by servotune.hub.control_lock: the autopilot yields to a holder and resumes later.
        self.autopilot_gate: AutopilotGate | None = None
        # Every stop of an axis goes through it (servotune.hub.stops).
        self.stops = StopService(self.on_event, clock=clock)
        # The last gains an auto-tune verified per axis (what the bench puts back when a
        # run leaves the axis oscillating with the gains that were in force before it).
        self.verified_gains: dict[str, dict[str, int]] = {}
        for link in links:
            self.add_link(link)

    # --- construction -----------------------------------------------------------------

    def add_link(self, link: Link) -> None:
        if link.id in self._links:
            raise ValueError(f"duplicate link id {link.id!r}")
        self._links[link.id] = LinkEntry(
            link,
            LinkStatus(
                link=link.id,
                state="connecting",
                message="",
                rate_hz=0.0,
                wire_limit_hz=0.0,
                errors=0,
            ),
        )
        for axis in link.axes:
            info = AxisInfo(
                id=axis.id, device=link.device, link=link.id, address=axis.address, name=axis.name
            )
            key = f"{link.device}/{link.id}/{axis.address}"
            self._axes[axis.id] = AxisEntry(axis, link, info, key)
            self.stops.add_axis(axis.id, axis, axis.descriptor)

    def _show_link_down(self, link_entry: LinkEntry, message: str) -> None:
        """The hub's own view when the link cannot report: error, rate 0, axes offline."""
        status = link_entry.status
        self.on_link_status(status.link, "error", message, 0.0, status.wire_limit_hz, status.errors)
        for entry in self._axes.values():
            if entry.link is link_entry.link and entry.health != "offline":
                self.on_axis_health(entry.info.id, "offline", message)

    # --- queries ----------------------------------------------------------------------

    def now(self) -> float:
        return self._clock() - self._t0

    def clock_at(self, now_s: float) -> float:
        """The hub's clock reading at ``now()`` == ``now_s`` (e.g. a press time a rig
        was sent in its own ``now()`` seconds, for ``stop_overtaken``)."""
        return now_s + self._t0

    def axes_info(self) -> list[AxisInfo]:
        return [entry.info for entry in self._axes.values()]

    def links_info(self) -> list[LinkInfo]:
        return [
            LinkInfo(id=e.link.id, device=e.link.device, path=e.link.path, baud=e.link.baud)
            for e in self._links.values()
        ]

    def entry(self, axis_id: str) -> AxisEntry:
        try:
            return self._axes[axis_id]
        except KeyError:
            raise UnknownAxisError(axis_id) from None

    def descriptor(self, axis_id: str) -> DeviceDescriptor:
        return self.entry(axis_id).driver.descriptor

    def link_status(self, link_id: str) -> LinkStatus:
        """The link's status as last published, never ``connected`` for a link whose
        task is not running or has not reported for ``STATUS_STALE_S``."""
        link_entry = self._links[link_id]
        self._check_stale(link_entry)
        return link_entry.status

    def _check_stale(self, link_entry: LinkEntry) -> None:
        status = link_entry.status
        if status.state != "connected":
            return
        if not link_entry.running:
            self._show_link_down(link_entry, "the link's task is not running")
            return
        silent_s = self._clock() - link_entry.updated_at
        if link_entry.updated_at and silent_s > STATUS_STALE_S:
            self.on_link_status(
                status.link,
                "error",
                f"no status from the link for {silent_s:.0f} s: its task is stalled",
                0.0,
                status.wire_limit_hz,
                status.errors,
            )

    def axis_state(self, axis_id: str) -> AxisState | None:
        entry = self.entry(axis_id)
        sample = entry.latest
        if sample is None:
            return None
        self._check_stale(self._links[entry.link.id])
        channels = {k: float(v) for k, v in sample.channels.items() if v is not None}
        return AxisState(
            t=sample.t - self._t0,
            position=channels.get("position", 0.0),
            following_error=channels.get("following_error", 0.0),
            velocity=channels.get("velocity", 0.0),
            channels=channels,
            flags=dict(sample.flags),
            health=entry.health,
            link_state=self._links[entry.link.id].status.state,
        )

    def hello(self) -> Hello:
        return Hello(
            server_version=__version__,
            axes=self.axes_info(),
            links=self.links_info(),
            autopilot=self.autopilot,
        )

    def snapshot_messages(self) -> list[str]:
        """What a new client needs besides ``hello``: statuses, params, recent events."""
        messages = [e.status.model_dump_json() for e in self._links.values()]
        for entry in self._axes.values():
            messages.append(self._axis_status(entry).model_dump_json())
            if entry.stored_values is not None:
                messages.append(
                    Params(
                        axis=entry.info.id, values=entry.stored_values, source="stored"
                    ).model_dump_json()
                )
            if entry.device_values:
                messages.append(
                    Params(
                        axis=entry.info.id, values=entry.device_values, source="read"
                    ).model_dump_json()
                )
        messages.extend(event.model_dump_json() for event in self._events)
        return messages

    async def stop_axis(self, entry: AxisEntry, kind: StopKind, reason: str) -> StopOutcome | None:
        """Stop one axis through the stop service (``servotune.hub.stops``): the STOP
        button (``"stop"``), every other stop (``"controlled"``: hand-over, dead-man,
        bench and auto-tune ends) or the power-off (``"power_off"``). Bumps the stop
        generation (ends a bench or auto-tune sequence); raises the driver's error when
        nothing could be sent."""
        entry.stop_generation += 1
        return await self.stops.stop(entry.info.id, kind, reason)

    async def stop_all(self) -> list[str]:
        """STOP every axis at once; returns the ids of axes whose stop failed."""
        entries = list(self._axes.values())
        pressed_at = self._clock()
        for entry in entries:
            entry.operated = True
            entry.stopped("STOP was pressed")
        results = await asyncio.gather(
            *(self._send_stop(e, pressed_at) for e in entries), return_exceptions=True
        )
        failed = []
        for entry, result in zip(entries, results, strict=True):
            if isinstance(result, StopOvertakenError):
                self.on_event("info", entry.info.id, f"STOP not sent: {result}")
            elif isinstance(result, BaseException):
                failed.append(entry.info.id)
                if isinstance(result, Exception):
                    self._schedule_stop(entry, result, pressed_at)
                else:
                    raise result
            else:
                self.note_stopped(entry)
                said = f": {', '.join(result.sent)}: {result.message}" if result else ""
                self.on_event("warning", entry.info.id, f"STOP{said}")
        for entry in entries:
            self._broadcast(self._axis_status(entry).model_dump_json(), droppable=False)
        return failed

    async def _send_stop(self, entry: AxisEntry, pressed_at: float) -> StopOutcome | None:
        """The axis' STOP: a driver that can (a rig's axis, whose rig judges the stop)
        is told when it was pressed; every other goes through the stop service (the
        shortest safe stop, watched to rest)."""
        driver = entry.driver
        if isinstance(driver, PressTimedStop):
            self.stops.cancel_watch(entry.info.id)
            await driver.stop_pressed(pressed_at)
            return None
        return await self.stops.stop(entry.info.id, "stop", "STOP")

    # --- DriverSink -------------------------------------------------------------------

    def on_sample(self, axis_id: str, sample: Sample) -> None:
        entry = self._axes[axis_id]
        entry.latest = sample
        entry.pending.append(sample)
        entry.last_sample_at = self._clock()
        self.stops.on_sample(axis_id, sample)
        if entry.silent:
            entry.silent = False
            if entry.health == "offline":  # still the hub's own verdict: undo it
                entry.health, entry.health_message = "ok", ""
                self.on_event("info", axis_id, "telemetry again")
                self._broadcast(self._axis_status(entry).model_dump_json(), droppable=False)
        for listener in self._sample_listeners:
            listener(axis_id, sample)

    def add_sample_listener(self, listener: Callable[[str, Sample], None]) -> None:
        """Call ``listener`` with every sample of every axis (the bench's recorder)."""
        self._sample_listeners.append(listener)

    def broadcast_model(self, message: BaseModel) -> None:
        """Send a wire message to every client (never dropped for slowness)."""
        self._broadcast(message.model_dump_json(), droppable=False)

    def on_link_status(
        self,
        link_id: str,
        state: LinkState,
        message: str,
        rate_hz: float,
        wire_limit_hz: float,
        errors: int,
    ) -> None:
        link_entry = self._links[link_id]
        previous = link_entry.status.state
        link = link_entry.link
        counters = dict(link.counters) if isinstance(link, HasCounters) else {}
        busy = link.wire_busy if isinstance(link, HasWireBusy) else None
        if link_entry.restarts:
            counters["restarts"] = counters.get("restarts", 0) + link_entry.restarts
        link_entry.updated_at = self._clock()
        link_entry.status = LinkStatus(
            link=link_id,
            state=state,
            message=message,
            rate_hz=round(rate_hz, 2),
            wire_limit_hz=round(wire_limit_hz, 2),
            wire_busy=None if busy is None else round(busy, 3),
            errors=errors,
            counters=counters,
        )
        if previous != state and state == "connected":
            # Judged for silence from the (re)connection, not from a sample before it.
            for entry in self._axes.values():
                if entry.link.id == link_id:
                    entry.last_sample_at = link_entry.updated_at
        if previous != state:
            level: EventLevel = "info" if state == "connected" else "warning"
            self.on_event(level, None, f"link {link_id}: {state} {message}".strip())
        self._broadcast(link_entry.status.model_dump_json(), droppable=False)

    def on_axis_health(self, axis_id: str, health: AxisHealth, message: str) -> None:
        entry = self._axes[axis_id]
        # The driver's own verdict replaces the hub's "silent" one.
        entry.silent = False
        if health != "offline" and entry.stop_on_reconnect:
            self._ensure_stop_task(entry)
        if entry.health == "reset" and health in ("ok", "paused"):
            # A reset stays flagged until the user re-applies the settings (_restore).
            return
        if health == "offline":
            # After an outage the device may have been power-cycled: compare its
            # values with the last applied ones again when it is back.
            entry.compared_at_connect = False
        if health == "ok" and entry.health != "ok":
            # Judged for silence from now on, not from a sample before an outage.
            entry.last_sample_at = self._clock()
        entry.health, entry.health_message = health, message
        self._broadcast(self._axis_status(entry).model_dump_json(), droppable=False)

    def on_params(self, axis_id: str, values: Mapping[str, int], source: str) -> None:
        entry = self._axes[axis_id]
        entry.device_values.update(values)
        if source in ("write", "restore"):
            entry.last_known.update(values)
            self._save_soon(entry, dict(values))
        else:
            missing = {k: v for k, v in values.items() if k not in entry.last_known}
            if missing:
                entry.last_known.update(missing)
                self._save_soon(entry, missing)
            if not entry.compared_at_connect and len(values) > 1:
                entry.compared_at_connect = True
                self._compare_with_last_known(entry, values)
        msg_source = source if source in ("read", "write", "restore") else "read"
        self._broadcast(
            Params(axis=axis_id, values=dict(values), source=msg_source).model_dump_json(),  # type: ignore[arg-type]
            droppable=False,
        )

    def _compare_with_last_known(self, entry: AxisEntry, values: Mapping[str, int]) -> None:
        differing = [
            f"{name} {values[name]} (last {entry.last_known[name]})"
            for name in values
            if name in entry.last_known and entry.last_known[name] != values[name]
        ]
        if differing:
            entry.health = "reset"
            entry.health_message = (
                "device settings differ from the last ones servotune applied: "
                + ", ".join(differing[:6])
                + (" …" if len(differing) > 6 else "")
            )
            self.on_event("warning", entry.info.id, entry.health_message)
            self._broadcast(self._axis_status(entry).model_dump_json(), droppable=False)

    # --- STOPs that could not be sent at once -------------------------------------------

    def _schedule_stop(self, entry: AxisEntry, error: Exception, pressed_at: float) -> None:
        """A STOP pressed at ``pressed_at`` failed: say why and what happens next."""
        link_state = self.link_status(entry.link.id).state
        self.pend_stop(entry, pressed_at)
        if isinstance(error, LinkDownError) or link_state != "connected":
            plan = (
                f"link {entry.link.id} is {link_state}: the STOP will be sent the moment "
                f"the link and the axis are back, unless the axis is commanded or stopped "
                f"before, and not after {PENDING_STOP_MAX_S:g} s"
            )
        else:
            plan = "the STOP is being sent again now"
        self.on_event("error", entry.info.id, f"STOP not delivered: {error}; {plan}")
        if link_state == "connected":
            self._ensure_stop_task(entry)

    def pend_stop(self, entry: AxisEntry, pressed_at: float | None = None) -> None:
        """Keep a STOP that could not reach the axis, pressed at ``pressed_at`` (now if
        None), for the axis' return (the control lock's dead-man uses this too)."""
        entry.stop_on_reconnect = True
        entry.stop_pressed_at = self._clock() if pressed_at is None else pressed_at
        entry.stop_pressed_wall = time.time() - (self._clock() - entry.stop_pressed_at)

    def note_stopped(self, entry: AxisEntry) -> None:
        """A STOP reached the axis (any: a user's, STOP all, the dead-man's, a
        hand-over's): a STOP pressed before it has nothing left to stop."""
        entry.stopped_at = self._clock()
        if entry.stop_on_reconnect:
            self._drop_pending_stop(entry, "the axis was stopped since")

    def note_commanded(self, entry: AxisEntry, what: str) -> None:
        """A command reached the axis: a STOP pressed before it must not act on the
        motion it may have started."""
        entry.commanded_at = self._clock()
        if entry.stop_on_reconnect:
            self._drop_pending_stop(entry, f"the axis was commanded since ({what})")

    def stop_overtaken(self, axis_id: str, pressed_at: float) -> str | None:
        """Why a STOP pressed at ``pressed_at`` (this hub's clock) must not be sent any
        more (the axis was commanded or stopped since), or None: send it."""
        entry = self.entry(axis_id)
        if entry.commanded_at > pressed_at:
            ago = self._clock() - entry.commanded_at
            return (
                f"{axis_id} was commanded {ago:.1f} s ago, "
                f"{entry.commanded_at - pressed_at:.1f} s after this STOP was pressed"
            )
        if entry.stopped_at > pressed_at:
            ago = self._clock() - entry.stopped_at
            return f"{axis_id} was already stopped {ago:.1f} s ago, after this STOP was pressed"
        return None

    def _pressed_text(self, entry: AxisEntry) -> str:
        pressed = entry.stop_pressed_at if entry.stop_pressed_at is not None else self._clock()
        wall = time.strftime("%H:%M:%S", time.localtime(entry.stop_pressed_wall))
        return f"pressed at {wall}, {self._clock() - pressed:.1f} s ago"

    def _drop_pending_stop(self, entry: AxisEntry, why: str) -> None:
        self.on_event("info", entry.info.id, f"STOP ({self._pressed_text(entry)}) not sent: {why}")
        self._cancel_pending_stop(entry)

    def _expire_stop(self, entry: AxisEntry) -> bool:
        """Drop a pending STOP older than PENDING_STOP_MAX_S (told); True if it was."""
        if entry.stop_pressed_at is None:
            self.pend_stop(entry)  # set by someone who did not say when: from now
        assert entry.stop_pressed_at is not None
        if self._clock() - entry.stop_pressed_at <= PENDING_STOP_MAX_S:
            return False
        self.on_event(
            "error",
            entry.info.id,
            f"STOP ({self._pressed_text(entry)}) was never delivered and is no longer "
            f"pending (after {PENDING_STOP_MAX_S:g} s it could stop motion started later): "
            "check the axis and press STOP again if it moves",
        )
        self._cancel_pending_stop(entry)
        return True

    def _cancel_pending_stop(self, entry: AxisEntry) -> None:
        entry.stop_on_reconnect = False
        entry.stop_pressed_at = None
        task, entry.stop_task = entry.stop_task, None
        if task is not None and task is not asyncio.current_task():
            task.cancel()

    def _ensure_stop_task(self, entry: AxisEntry) -> None:
        if entry.stop_task is not None and not entry.stop_task.done():
            return
        task = asyncio.get_running_loop().create_task(
            self._deliver_stop(entry), name=f"delivering a STOP to {entry.info.id}"
        )
        entry.stop_task = task
        self._tasks.append(task)
        task.add_done_callback(self._forget_task)

    async def _deliver_stop(self, entry: AxisEntry) -> None:
        """Send the pending STOP as soon as the link is connected and the axis online;
        retried while the link stays connected, until it is on the wire. A link that
        goes down again keeps the STOP pending for its next return. Dropped, and
        told, when it expires or is overtaken (``PENDING_STOP_MAX_S``)."""
        tries = 0
        while entry.stop_on_reconnect:
            if self._expire_stop(entry):
                return
            link_state = self.link_status(entry.link.id).state
            if link_state != "connected" or entry.health == "offline":
                # Health turns ok while the link still probes its other axes.
                await asyncio.sleep(0.05)
                continue
            pressed_at = entry.stop_pressed_at
            assert pressed_at is not None
            why = self.stop_overtaken(entry.info.id, pressed_at)
            if why is not None:
                self._drop_pending_stop(entry, why)
                return
            try:
                await self._send_stop(entry, pressed_at)
            except StopOvertakenError as exc:
                # The far end (a rig) knows its axis better: commanded or stopped since.
                self._drop_pending_stop(entry, str(exc))
                return
            except LinkDownError:
                await asyncio.sleep(0.05)
                continue
            except DriverError as exc:
                tries += 1
                if tries >= STOP_RETRIES_CONNECTED:
                    entry.stop_on_reconnect = False
                    self.on_event(
                        "error",
                        entry.info.id,
                        f"STOP could not be delivered after {tries} tries: {exc} — "
                        "check the axis and press STOP again",
                    )
                    return
                await asyncio.sleep(0.1)
                continue
            pressed = self._pressed_text(entry)
            entry.stop_on_reconnect = False
            entry.stop_pressed_at = None
            entry.stopped_at = self._clock()
            self.on_event(
                "warning", entry.info.id, f"STOP sent ({pressed}; it could not go out before)"
            )
            self._broadcast(self._axis_status(entry).model_dump_json(), droppable=False)
            return

    def _save_soon(self, entry: AxisEntry, values: dict[str, int]) -> None:
        """Save the last applied values in a worker thread; a failure is told, not lost.

        If the database cannot be written, every client gets an error event and a
        ``storage_status`` message (the "settings are not being saved" banner); the
        values stay in ``Storage.unsaved`` and go with the next save that works, which
        also clears the banner."""
        task = asyncio.get_running_loop().create_task(
            self._save_params(entry, values), name=f"saving settings of {entry.info.id}"
        )
        self._tasks.append(task)
        task.add_done_callback(self._forget_task)

    async def _save_params(self, entry: AxisEntry, values: dict[str, int]) -> None:
        was_failing = self._storage.problem is not None
        try:
            await asyncio.to_thread(self._storage.save_params, entry.storage_key, values)
        except StorageError as exc:
            unsaved = self._storage.unsaved.get(entry.storage_key, values)
            names = ", ".join(sorted(unsaved)[:8]) + (" …" if len(unsaved) > 8 else "")
            self.on_event(
                "error",
                entry.info.id,
                f"settings are not being saved ({names} applied to the device only): {exc}",
            )
            self.broadcast_model(StorageStatus(writable=False, message=str(exc)))
            return
        if was_failing:
            self.on_event("info", entry.info.id, "settings are saved again")
            self.broadcast_model(StorageStatus(writable=True, message=""))

    def _forget_task(self, task: asyncio.Task[None]) -> None:
        with contextlib.suppress(ValueError):
            self._tasks.remove(task)
        if not task.cancelled() and task.exception() is not None:
            logger.error("background task %s failed: %s", task.get_name(), task.exception())
            self.on_event("error", None, f"{task.get_name()} failed: {task.exception()}")

    def on_event(self, level: EventLevel, axis_id: str | None, message: str) -> None:
        event = Event(t=round(self.now(), 3), level=level, axis=axis_id, message=message)
        self._events.append(event)
        log = logger.warning if level != "info" else logger.info
        log("%s%s", f"[{axis_id}] " if axis_id else "", message)
        self._broadcast(event.model_dump_json(), droppable=False)

    # --- fan-out ----------------------------------------------------------------------

    def subscribe(self) -> ClientQueue:
        queue = ClientQueue()
        self._clients.add(queue)
        return queue

    def unsubscribe(self, queue: ClientQueue) -> None:
        self._clients.discard(queue)

    def _broadcast(self, text: str, *, droppable: bool) -> None:
        for client in self._clients:
            client.put(text, droppable=droppable)

    def _axis_status(self, entry: AxisEntry) -> AxisStatus:
        return AxisStatus(
            axis=entry.info.id,
            health=entry.health,
            message=entry.health_message,
            operated=entry.operated or not self.autopilot,
        )

    def _telemetry(self, entry: AxisEntry, samples: list[Sample]) -> Telemetry:
        descriptor = entry.driver.descriptor
        return Telemetry(
            axis=entry.info.id,
            t=[round(s.t - self._t0, 5) for s in samples],
            channels={
                c.name: [s.channels.get(c.name) for s in samples] for c in descriptor.channels
            },
            flags={
                f.name: [int(s.flags.get(f.name, False)) for s in samples] for f in descriptor.flags
            },
        )

    async def _fan_out(self) -> None:
        last_status = self._clock()
        while True:
            await asyncio.sleep(BATCH_PERIOD_S)
            for entry in self._axes.values():
                if not entry.pending:
                    continue
                samples, entry.pending = entry.pending, []
                if self._clients:
                    self._broadcast(
                        self._telemetry(entry, samples).model_dump_json(), droppable=True
                    )
            now = self._clock()
            if now - last_status >= STATUS_PERIOD_S:
                last_status = now
                for link_entry in self._links.values():
                    self._check_stale(link_entry)
                    if now - link_entry.updated_at >= STATUS_PERIOD_S:
                        # Links publish their own status every second; repeat the last
                        # one only for a link that did not.
                        self._broadcast(link_entry.status.model_dump_json(), droppable=False)
                self._check_silent_axes(now)
                for entry in self._axes.values():
                    pending = entry.stop_on_reconnect and not self._expire_stop(entry)
                    if pending and entry.health != "offline":
                        self._ensure_stop_task(entry)
                for client in self._clients:
                    stats = ClientStats(sent=client.sent, dropped=client.dropped)
                    client.put(stats.model_dump_json(), droppable=True)

    def _check_silent_axes(self, now: float) -> None:
        """Show offline every axis shown "ok" whose link is connected (or error) and
        that got no sample for ``AXIS_SILENT_S``: its device does not answer its polls
        although the line works. Its next sample shows it ok again (``on_sample``).
        Axes paused, offline or reset and links connecting or disconnected are not
        judged: no telemetry is expected from them."""
        for entry in self._axes.values():
            if entry.health != "ok" or entry.silent:
                continue
            if self._links[entry.link.id].status.state not in ("connected", "error"):
                continue
            silent_s = now - entry.last_sample_at
            if silent_s < AXIS_SILENT_S:
                continue
            entry.silent = True
            entry.health = "offline"
            entry.health_message = (
                f"no telemetry for {silent_s:.0f} s while its link is up: "
                "the device does not answer its polls"
            )
            self.on_event("warning", entry.info.id, entry.health_message)
            self._broadcast(self._axis_status(entry).model_dump_json(), droppable=False)
