"""The hub's state: what it knows of every link and axis, kept from what their drivers report.

What lives here: ``HubState`` with the ``DriverSink`` callbacks that keep the records
(``hub.records``: samples, link status, axis health, params, with the compare against
the last applied settings and their saving), the hub's own judgement of a link that
stopped reporting (``STATUS_STALE_S``) and of an axis that sent no sample
(``AXIS_SILENT_S``), the event log and the queries. It has the stop service and the
delivery of a STOP that could not be sent at once (``hub.stops``; set off from here:
when an axis is back, and on the fan-out's status tick), and sends what it learns to
the clients through the fan-out (``hub.fanout``).

The seam is the direction: the state takes in what the drivers report and sends it out
to clients; ``hub.hub.Hub``, which has the state, sends what users ask for to the
devices. Nothing here calls into ``hub/hub.py``. ``ClientQueue``, the records,
``StopOvertakenError`` and ``PressTimedStop`` stay importable from here.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import deque
from collections.abc import Callable, Coroutine, Mapping
from typing import Any, Final

from pydantic import BaseModel

from servotune import __version__
from servotune.descriptor import DeviceDescriptor
from servotune.hub.fanout import STATUS_PERIOD_S, FanOut
from servotune.hub.fanout import ClientQueue as ClientQueue
from servotune.hub.records import AxisEntry as AxisEntry
from servotune.hub.records import LinkEntry as LinkEntry
from servotune.hub.stops import PressTimedStop as PressTimedStop
from servotune.hub.stops import StopDelivery, StopService
from servotune.hub.stops import StopOvertakenError as StopOvertakenError
from servotune.link.base import HasCounters, HasWireBusy, Link, Sample
from servotune.schema import (
    AxisHealth,
    AxisInfo,
    AxisState,
    AxisStatus,
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

# A link that has not published its status for this long is shown stalled, not connected.
STATUS_STALE_S = 3.5
# The server's own loop: the fan-out takes the telemetry every ``BATCH_PERIOD_S``; a
# take this much later than the one before means the whole server did not run (a
# host far beyond its cores), its links included. Their silence over that time is
# not theirs: they are judged for staleness from the loop's return.
LOOP_STALL_S: Final = 1.0
# An axis shown "ok" whose link is up (connected, or error while it still polls) and
# that sent no telemetry sample for this long is shown offline. A module on a
# shared line can stop answering its polls while the others answer: the link then
# stays connected, the driver counts desyncs but never sees 3 failures in a row, and
# without this rule the silent axis would be shown "ok" forever. 3 s is many poll
# cycles of every driver (each samples every axis several times a second) and close
# to STATUS_STALE_S, the hub's horizon for a link that stopped reporting, so a short
# hold-up of a busy host does not trip it.
AXIS_SILENT_S: Final = 3.0
# When its link excused timeouts because the host itself held the bytes back
# (``host_stalls`` grew within the last HOST_HELD_RECENT_S), the axis is shown offline
# all the same - it has no live values, and "ok" would claim some - but the message
# names the host, not the device.
HOST_HELD_RECENT_S: Final = 2.0


class UnknownAxisError(KeyError):
    pass


class HubState:
    """The records of the hub's links and axes, kept from what their drivers report
    (``DriverSink``), the queries on them, the event log, and the parts that act on
    them: the stop service and the delivery of pending STOPs. It implements the
    fan-out's ``FanOutSource`` and the delivery's ``StopTarget``; ``hub.hub.Hub`` is
    the one to construct."""

    def __init__(
        self,
        storage: Storage,
        fanout: FanOut,
        *,
        autopilot: bool = False,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._clock = clock
        self._t0 = clock()
        self._storage = storage
        self.fanout = fanout
        self.autopilot = autopilot
        self._links: dict[str, LinkEntry] = {}
        self._axes: dict[str, AxisEntry] = {}
        self.events: deque[Event] = deque(maxlen=200)
        # Background tasks: saves and pending STOP deliveries (cancelled by the hub's stop).
        self.tasks: list[asyncio.Task[None]] = []
        self._sample_listeners: list[Callable[[str, Sample], None]] = []
        # The fan-out's last telemetry take (None: not running), and when the server's
        # loop last came back from a stall (see LOOP_STALL_S).
        self._loop_beat: float | None = None
        self._loop_back_at = 0.0
        # Every stop of an axis goes through it (servotune.hub.stops).
        self.stops = StopService(self.on_event, clock=clock)
        self.delivery = StopDelivery(self, self.stops, clock=clock)

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

    def show_link_down(self, link_entry: LinkEntry, message: str) -> None:
        """The hub's own view when the link cannot report: error, rate 0, axes offline."""
        status = link_entry.status
        self.on_link_status(status.link, "error", message, 0.0, status.wire_limit_hz, status.errors)
        for entry in self._axes.values():
            if entry.link is link_entry.link and entry.health != "offline":
                self.on_axis_health(entry.info.id, "offline", message)

    # --- queries ----------------------------------------------------------------------

    def entries(self) -> list[AxisEntry]:
        return list(self._axes.values())

    def link_entries(self) -> list[LinkEntry]:
        return list(self._links.values())

    def link_entry(self, link_id: str) -> LinkEntry:
        return self._links[link_id]

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
            self.show_link_down(link_entry, "the link's task is not running")
            return
        now = self._clock()
        beat = self._loop_beat
        if beat is not None and now - beat >= LOOP_STALL_S:
            return  # the loop is just back from a stall: the fan-out will say so
        silent_s = now - max(link_entry.updated_at, self._loop_back_at)
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
            messages.append(self.axis_status(entry).model_dump_json())
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
        messages.extend(event.model_dump_json() for event in self.events)
        return messages

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
                self.show_status(entry)
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
        host_stalls = counters.get("host_stalls", 0)
        if host_stalls > link_entry.host_stalls:
            link_entry.host_stalled_at = link_entry.updated_at
        link_entry.host_stalls = host_stalls
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
            self.delivery.ensure_task(entry)
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
        self.show_status(entry)

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
            self.show_status(entry)

    def _save_soon(self, entry: AxisEntry, values: dict[str, int]) -> None:
        """Save the last applied values in a worker thread; a failure is told, not lost.

        If the database cannot be written, every client gets an error event and a
        ``storage_status`` message (the "settings are not being saved" banner); the
        values stay in ``Storage.unsaved`` and go with the next save that works, which
        also clears the banner."""
        self.spawn(self._save_params(entry, values), f"saving settings of {entry.info.id}")

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

    def spawn(self, coro: Coroutine[Any, Any, None], name: str) -> asyncio.Task[None]:
        """Run ``coro`` as a background task: kept in ``tasks`` until it ends, an error
        event if it fails."""
        task = asyncio.get_running_loop().create_task(coro, name=name)
        self.tasks.append(task)
        task.add_done_callback(self._forget_task)
        return task

    def _forget_task(self, task: asyncio.Task[None]) -> None:
        with contextlib.suppress(ValueError):
            self.tasks.remove(task)
        if not task.cancelled() and task.exception() is not None:
            logger.error("background task %s failed: %s", task.get_name(), task.exception())
            self.on_event("error", None, f"{task.get_name()} failed: {task.exception()}")

    def on_event(self, level: EventLevel, axis_id: str | None, message: str) -> None:
        event = Event(t=round(self.now(), 3), level=level, axis=axis_id, message=message)
        self.events.append(event)
        log = logger.warning if level != "info" else logger.info
        log("%s%s", f"[{axis_id}] " if axis_id else "", message)
        self._broadcast(event.model_dump_json(), droppable=False)

    # --- what goes to the clients (servotune.hub.fanout) --------------------------------

    def _broadcast(self, text: str, *, droppable: bool) -> None:
        self.fanout.broadcast(text, droppable=droppable)

    def axis_status(self, entry: AxisEntry) -> AxisStatus:
        return AxisStatus(
            axis=entry.info.id,
            health=entry.health,
            message=entry.health_message,
            operated=entry.operated or not self.autopilot,
        )

    def show_status(self, entry: AxisEntry) -> None:
        """Send every client the axis' status."""
        self._broadcast(self.axis_status(entry).model_dump_json(), droppable=False)

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

    def take_telemetry(self, build: bool) -> list[str]:
        """Every axis' samples since the last call, taken; one telemetry message (JSON)
        per axis that had any if ``build`` (the fan-out has clients). Also the
        server's heartbeat (``LOOP_STALL_S``): a take that comes that late after the
        last one means the server did not run meanwhile; said once in a warning
        event, and the links' staleness is judged from now."""
        now = self._clock()
        beat, self._loop_beat = self._loop_beat, now
        if beat is not None and now - beat >= LOOP_STALL_S:
            self._loop_back_at = now
            if now - beat >= STATUS_STALE_S:
                self.on_event(
                    "warning",
                    None,
                    f"the server did not run for {now - beat:.1f} s (the host is "
                    "overloaded): telemetry and link status were held up meanwhile",
                )
        messages = []
        for entry in self._axes.values():
            if not entry.pending:
                continue
            samples, entry.pending = entry.pending, []
            if build:
                messages.append(self._telemetry(entry, samples).model_dump_json())
        return messages

    def status_tick(self, now: float) -> None:
        """Once a second (the fan-out): links that stalled, the repeat of a status a
        link did not publish, silent axes, and pending STOPs to expire or deliver."""
        for link_entry in self._links.values():
            self._check_stale(link_entry)
            if now - link_entry.updated_at >= STATUS_PERIOD_S:
                # Links publish their own status every second; repeat the last
                # one only for a link that did not.
                self._broadcast(link_entry.status.model_dump_json(), droppable=False)
        self._check_silent_axes(now)
        for entry in self._axes.values():
            self.delivery.tick(entry)

    def _check_silent_axes(self, now: float) -> None:
        """Show offline every axis shown "ok" whose link is connected (or error) and
        that got no sample for ``AXIS_SILENT_S``: its device does not answer its polls
        although the line works. Its next sample shows it ok again (``on_sample``).
        Axes paused, offline or reset and links connecting or disconnected are not
        judged: no telemetry is expected from them. When its link excused timeouts
        because the host held its bytes back (``HOST_HELD_RECENT_S``), the message says
        so instead of blaming the device. The server's own stall (``LOOP_STALL_S``) is
        not the device's: judged from its end."""
        for entry in self._axes.values():
            if entry.health != "ok" or entry.silent:
                continue
            link_entry = self._links[entry.link.id]
            if link_entry.status.state not in ("connected", "error"):
                continue
            # Judged from the server's return from a stall, if later (LOOP_STALL_S).
            silent_s = now - max(entry.last_sample_at, self._loop_back_at)
            if silent_s < AXIS_SILENT_S:
                continue
            held_at = link_entry.host_stalled_at
            if held_at is not None and now - held_at < HOST_HELD_RECENT_S:
                cause = (
                    "this computer's serial (tty) layer is holding the bytes back "
                    "(the host is overloaded); the device's answers come late"
                )
            else:
                cause = "the device does not answer its polls"
            entry.silent = True
            entry.health = "offline"
            entry.health_message = (
                f"no telemetry for {silent_s:.0f} s while its link is up: {cause}"
            )
            self.on_event("warning", entry.info.id, entry.health_message)
            self.show_status(entry)
