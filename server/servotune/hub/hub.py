"""The hub: owns the links, validates every change, and fans telemetry out to clients.

Every command that changes a device goes through ``Hub.write_params``,
``Hub.command``, ``Hub.console`` or ``Hub.stop_all``: one path where input is checked
against the device descriptor before anything is sent and where the axis is marked as
operated (which switches the demo autopilot off for it). Who may call it is decided
before, in the api: the user's role (``servotune.auth``) and the axis's control lock
(``hub.control_lock``); ``auth.audit`` records what was done.

``Hub`` is a facade over its parts, each a concrete class it has:

* ``state`` (``hub.state.HubState``): the records of links and axes kept from what the
  drivers report (``DriverSink``), supervision, events, queries; it has the stop
  service (``stops``) and the delivery of pending STOPs (``delivery``, ``hub.stops``);
* ``fanout`` (``hub.fanout.FanOut``): the websocket clients' queues and the loop that
  batches telemetry;
* the demo autopilot (``hub.autopilot.DemoAutopilot``).

What stays here: the lifecycle (the links' owner tasks, restarted with backoff), the
command path, and explicit delegating methods for the surface the api, auth, bus,
control lock, twin, bench and auto-tune use, so they need not know the parts.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import deque
from collections.abc import Callable, Mapping

from pydantic import BaseModel

from servotune.descriptor import DeviceDescriptor
from servotune.hub.autopilot import AutopilotGate, DemoAutopilot
from servotune.hub.fanout import ClientQueue, FanOut
from servotune.hub.movewatch import MovePlan, plan_move, watch_move
from servotune.hub.records import AxisEntry, LinkEntry
from servotune.hub.state import HubState
from servotune.hub.stops import StopKind
from servotune.link.base import (
    Autopilot,
    CommandOutcome,
    DeviceRefusedError,
    DriverError,
    InvalidArgumentError,
    Link,
    Sample,
    StopOutcome,
    check_console_line,
)
from servotune.link.validation import validate_command, validate_params
from servotune.schema import (
    AxisHealth,
    AxisInfo,
    AxisState,
    Event,
    EventLevel,
    Hello,
    LinkInfo,
    LinkState,
    LinkStatus,
    MoveOutcome,
    Params,
)
from servotune.storage import Storage

logger = logging.getLogger(__name__)

LINK_RESTART_MAX_S = 5.0


class NotFoundError(LookupError):
    """A stored thing (run, parameter set) that does not exist: HTTP 404."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(message)
        self.field = field


class Hub:
    """Owns links and their tasks for the lifetime of the app (see ``api.app``); the
    ``DriverSink`` its links report to."""

    def __init__(
        self,
        links: list[Link],
        storage: Storage,
        *,
        autopilot: bool = False,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._clock = clock
        self._storage = storage
        self.fanout = FanOut(clock)
        self.state = HubState(storage, self.fanout, autopilot=autopilot, clock=clock)
        # Every stop of an axis goes through it (servotune.hub.stops).
        self.stops = self.state.stops
        self.delivery = self.state.delivery
        self._pilot = DemoAutopilot(self, clock)
        # Set by servotune.hub.control_lock: the autopilot yields to a holder and resumes later.
        self.autopilot_gate: AutopilotGate | None = None
        # The last gains an auto-tune verified per axis (what the bench puts back when a
        # run leaves the axis oscillating with the gains that were in force before it).
        self.verified_gains: dict[str, dict[str, int]] = {}
        # The links' owner tasks, the fan-out and the autopilot (``start``).
        self._tasks: list[asyncio.Task[None]] = []
        # The watch of each axis' last move to a target (servotune.hub.movewatch).
        self._move_watches: dict[str, asyncio.Task[None]] = {}
        for link in links:
            self.add_link(link)

    # --- lifecycle --------------------------------------------------------------------

    async def start(self) -> None:
        """Load stored settings and start every link's owner task and the fan-out."""
        for entry in self.state.entries():
            entry.last_known = await asyncio.to_thread(self._storage.last_params, entry.storage_key)
        for link_entry in self.state.link_entries():
            link_entry.updated_at = self._clock()
            self._tasks.append(asyncio.create_task(self._run_link(link_entry)))
        self._tasks.append(asyncio.create_task(self.fanout.run(self.state)))
        if self.autopilot:
            for entry in self.state.entries():
                self._tasks.append(asyncio.create_task(self._pilot.run(entry)))

    async def stop(self) -> None:
        """Cancel every task; the links close their ports."""
        tasks = [*self._tasks, *self.state.tasks, *self._move_watches.values()]
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._tasks.clear()
        self._move_watches.clear()

    async def _run_link(self, link_entry: LinkEntry) -> None:
        """Supervise a link's task: whatever ends it (a driver bug out of ``run``, or
        ``run`` returning although it must not), the link is shown down with the
        reason, its axes offline, and it is started again with backoff."""
        link = link_entry.link
        backoff_s = 0.25
        while True:
            started = self._clock()
            link_entry.running = True
            try:
                await link.run()
                problem = "its task ended"
            except asyncio.CancelledError:
                link_entry.running = False
                raise
            except Exception as exc:
                # A driver bug must be visible, not silently kill the link.
                logger.exception("link %s crashed", link.id)
                problem = f"internal error: {type(exc).__name__}: {exc}"
            link_entry.running = False
            link_entry.restarts += 1
            if self._clock() - started > 30.0:
                backoff_s = 0.25
            message = f"link task stopped ({problem}); restarting in {backoff_s:g} s"
            self.on_event("error", None, f"link {link.id}: {message}")
            self.state.show_link_down(link_entry, message)
            await asyncio.sleep(backoff_s)
            backoff_s = min(backoff_s * 2, LINK_RESTART_MAX_S)

    # --- the one command path ---------------------------------------------------------

    async def take_over(self, entry: AxisEntry, timeout_s: float = 8.0) -> None:
        """Mark the axis operated; if the demo autopilot was moving it, wait (up to
        ``timeout_s``) for that move to end, so a test can start from rest."""
        was_operated = entry.operated
        self._operate(entry)
        driver = entry.driver
        if was_operated or not self.autopilot or not isinstance(driver, Autopilot):
            return
        deadline = self._clock() + timeout_s
        while self._clock() < deadline:
            latest = entry.latest
            if latest is not None and driver.autopilot_settled(latest):
                return
            await asyncio.sleep(0.05)

    def mark_operated(self, entry: AxisEntry) -> None:
        """A user acts on the axis: the demo autopilot leaves it alone from now on."""
        self._operate(entry)

    def _operate(self, entry: AxisEntry) -> None:
        # A new change ends the watch of an earlier stop: what follows is the user's.
        self.stops.cancel_watch(entry.info.id)
        if not entry.operated:
            entry.operated = True
            self.state.show_status(entry)

    async def read_params(self, axis_id: str) -> dict[str, int]:
        entry = self.entry(axis_id)
        return await entry.driver.read_params()

    async def write_params(self, axis_id: str, values: Mapping[str, object]) -> dict[str, int]:
        """Validate all values (422 before anything is sent), write, read back."""
        entry = self.entry(axis_id)
        # Cross-field constraints are checked against the device's values as last seen.
        checked = validate_params(entry.driver.descriptor, values, entry.device_values)
        self._operate(entry)
        written = await entry.driver.write_params(checked)
        self.note_commanded(entry, "parameters written")
        return written

    async def command(
        self,
        axis_id: str,
        name: str,
        args: Mapping[str, object],
        *,
        origin: str = "user",
        stop_generation: int | None = None,
    ) -> CommandOutcome:
        """Validate and run a descriptor command.

        ``origin`` is who asks (the user, the bench, auto-tune). A user's ``stop``
        bumps the axis' stop generation; a sequence that passes the generation it
        started with (``stop_generation``) is refused from then on, so a STOP ends a
        bench test or an auto-tune run instead of being overtaken by its next step.
        """
        entry = self.entry(axis_id)
        if stop_generation is not None and entry.stop_generation != stop_generation:
            raise DeviceRefusedError(f"not sent: {entry.stop_cause} during this sequence")
        checked = validate_command(entry.driver.descriptor, name, args)
        self._operate(entry)
        if name == "restore_parameters":
            return await self._restore(entry)
        descriptor = entry.driver.descriptor
        group = descriptor.command(name).group
        # Every stop-group command of the user (STOP, stop and hold, halt) ends a
        # running bench or auto-tune sequence, not only ``stop``.
        if origin == "user" and group == "stop":
            label = descriptor.command(name).label
            entry.stopped("STOP was pressed" if name == "stop" else f"{label} was pressed")
        pressed_at = self._clock()
        # A user's move to a target is watched to its end (servotune.hub.movewatch); a
        # bench or auto-tune sequence judges its own moves.
        move = plan_move(entry, name, checked) if origin == "user" else None
        self._end_move_watch(axis_id)
        try:
            if name == "stop" or name == descriptor.stop.power_off_command:
                kind: StopKind = "stop" if name == "stop" else "power_off"
                stopped = await self.stops.stop(axis_id, kind, "STOP" if kind == "stop" else name)
                outcome = (
                    CommandOutcome(stopped.sent, stopped.message)
                    if stopped is not None
                    else CommandOutcome([name], "sent")
                )
            else:
                outcome = await entry.driver.command(name, checked)
                if group == "stop":
                    # A stop of the descriptor's that keeps the axis held (stop and hold,
                    # decelerate, halt): watched like a STOP until the axis is at rest.
                    self.stops.follow(axis_id, StopOutcome(outcome.sent, "hold"), name)
        except DriverError as exc:
            if name == "stop" and not isinstance(exc, DeviceRefusedError):
                # The stop could not reach the axis: deliver it as soon as it can go.
                self.delivery.schedule(entry, exc, pressed_at)
            raise
        if group == "stop":
            # STOP, or a stop that holds or unpowers the axis: a pending STOP has
            # nothing left to stop.
            self.note_stopped(entry)
        else:
            self.note_commanded(entry, name)
        if (scope := descriptor.command(name).stores_parameters) is not None:
            self._stored(entry, scope)
        level: EventLevel = "warning" if group == "stop" else "info"
        said = f": {outcome.message}" if group == "stop" and outcome.message else ""
        self.on_event(level, axis_id, f"{name} {checked or ''} -> {', '.join(outcome.sent)}{said}")
        if move is not None:
            self._move_watches[axis_id] = asyncio.create_task(
                self._watch_move(entry, name, move, entry.stop_generation),
                name=f"move watch {axis_id}",
            )
            outcome.outcome_pending = True
            outcome.message = f"moving to {move.target:.0f}"
        return outcome

    def _stored(self, entry: AxisEntry, scope: str) -> None:
        """The device's save command succeeded: the persisted parameters in force are
        the stored ones (of this axis, or of every axis of its link)."""
        axes = [
            e
            for e in self.state.entries()
            if e is entry or (scope == "link" and e.link is entry.link)
        ]
        for each in axes:
            persisted = {p.name for p in each.driver.descriptor.parameters if p.persisted}
            each.stored_values = {k: v for k, v in each.device_values.items() if k in persisted}
            self.broadcast_model(
                Params(axis=each.info.id, values=each.stored_values, source="stored")
            )

    def _end_move_watch(self, axis_id: str) -> None:
        """A new command ends the watch of the axis' previous move (a jog's steps)."""
        task = self._move_watches.pop(axis_id, None)
        if task is not None:
            task.cancel()

    async def _watch_move(
        self, entry: AxisEntry, name: str, move: MovePlan, generation: int
    ) -> None:
        end = await watch_move(entry, move, generation, self._clock)
        if self._move_watches.get(entry.info.id) is asyncio.current_task():
            del self._move_watches[entry.info.id]
        if end.outcome in ("limit", "fault", "short"):
            self.on_event("warning", entry.info.id, end.message)
        elif end.outcome != "arrived":
            self.on_event("info", entry.info.id, end.message)
        self.broadcast_model(
            MoveOutcome(
                axis=entry.info.id,
                command=name,
                target=move.target,
                outcome=end.outcome,
                position=end.position,
                message=end.message,
            )
        )

    async def _restore(self, entry: AxisEntry) -> CommandOutcome:
        values = dict(entry.last_known)
        if not values:
            raise InvalidArgumentError(
                "command", "no earlier settings of this axis are stored: nothing to re-apply"
            )
        readback = await entry.driver.write_params(values)
        self.note_commanded(entry, "stored settings re-applied")
        entry.health, entry.health_message = "ok", ""
        entry.silent, entry.last_sample_at = False, self._clock()
        self.state.show_status(entry)
        self.on_event("info", entry.info.id, f"re-applied {len(readback)} stored settings")
        return CommandOutcome([f"{k}={v}" for k, v in readback.items()], "settings re-applied")

    async def console(self, axis_id: str, line: str) -> tuple[str, list[str]]:
        """Send a raw line; returns (the line as sent, the reply lines).

        A line with control characters is refused (InvalidArgumentError, field
        ``line``) before anything is sent; every line sent is logged as an event with
        its reply or its error.
        """
        entry = self.entry(axis_id)
        check_console_line(line)
        self._operate(entry)
        try:
            sent, reply = await entry.driver.console(line)
        except InvalidArgumentError:
            raise
        except DriverError as exc:
            self.on_event("warning", axis_id, f"console {line!r}: {exc}")
            raise
        self.note_commanded(entry, f"console {sent!r}")
        shown = " | ".join(reply)
        if len(shown) > 200:
            shown = shown[:200] + " …"
        self.on_event("info", axis_id, f"console {sent!r} -> {shown!r}")
        return sent, reply

    # --- links registered while the hub runs (servotune.bus) ---------------------------

    async def add_running_link(self, link: Link) -> None:
        """Register ``link`` while the hub runs (a rig that joined the lab's bus after
        the hub started, ``servotune.bus``): its stored settings are loaded, its task
        is started, and every client gets a new ``hello`` (the web client rebuilds its
        navigation from it, as after a reconnect). ValueError for a duplicate id."""
        self.add_link(link)
        for axis in link.axes:
            entry = self.state.entry(axis.id)
            entry.last_known = await asyncio.to_thread(self._storage.last_params, entry.storage_key)
        if self._tasks:  # started: the link needs its owner task (else ``start`` does it)
            link_entry = self.state.link_entry(link.id)
            link_entry.updated_at = self._clock()
            self._tasks.append(asyncio.create_task(self._run_link(link_entry)))
        self.fanout.broadcast(self.hello().model_dump_json(), droppable=False)

    # --- the parts' surface (explicit delegation) ---------------------------------------

    @property
    def autopilot(self) -> bool:
        """The demo autopilot drives the axes nobody operates (``--autopilot``)."""
        return self.state.autopilot

    def add_link(self, link: Link) -> None:
        """Register ``link`` and its axes (before ``start``; see ``add_running_link``).
        ValueError for a duplicate id."""
        self.state.add_link(link)

    def now(self) -> float:
        return self.state.now()

    def clock_at(self, now_s: float) -> float:
        return self.state.clock_at(now_s)

    def axes_info(self) -> list[AxisInfo]:
        return self.state.axes_info()

    def links_info(self) -> list[LinkInfo]:
        return self.state.links_info()

    def entry(self, axis_id: str) -> AxisEntry:
        """UnknownAxisError for an axis that does not exist."""
        return self.state.entry(axis_id)

    def descriptor(self, axis_id: str) -> DeviceDescriptor:
        return self.state.descriptor(axis_id)

    def link_status(self, link_id: str) -> LinkStatus:
        return self.state.link_status(link_id)

    def link_state(self, link_id: str) -> LinkState:
        """The link's state as last published (the autopilot's ``AutopilotHost``)."""
        return self.state.link_entry(link_id).status.state

    def axis_state(self, axis_id: str) -> AxisState | None:
        return self.state.axis_state(axis_id)

    def hello(self) -> Hello:
        return self.state.hello()

    def snapshot_messages(self) -> list[str]:
        return self.state.snapshot_messages()

    def show_status(self, entry: AxisEntry) -> None:
        self.state.show_status(entry)

    # DriverSink: what the links report.

    def on_sample(self, axis_id: str, sample: Sample) -> None:
        self.state.on_sample(axis_id, sample)

    def on_link_status(
        self,
        link_id: str,
        state: LinkState,
        message: str,
        rate_hz: float,
        wire_limit_hz: float,
        errors: int,
    ) -> None:
        self.state.on_link_status(link_id, state, message, rate_hz, wire_limit_hz, errors)

    def on_axis_health(self, axis_id: str, health: AxisHealth, message: str) -> None:
        self.state.on_axis_health(axis_id, health, message)

    def on_params(self, axis_id: str, values: Mapping[str, int], source: str) -> None:
        self.state.on_params(axis_id, values, source)

    def on_event(self, level: EventLevel, axis_id: str | None, message: str) -> None:
        self.state.on_event(level, axis_id, message)

    def add_sample_listener(self, listener: Callable[[str, Sample], None]) -> None:
        """Call ``listener`` with every sample of every axis (the bench's recorder)."""
        self.state.add_sample_listener(listener)

    # Clients.

    def subscribe(self) -> ClientQueue:
        return self.fanout.subscribe()

    def unsubscribe(self, queue: ClientQueue) -> None:
        self.fanout.unsubscribe(queue)

    def broadcast_model(self, message: BaseModel) -> None:
        """Send a message to every client (never dropped for slowness)."""
        self.fanout.broadcast_model(message)

    def _broadcast(self, text: str, *, droppable: bool) -> None:
        self.fanout.broadcast(text, droppable=droppable)

    @property
    def _events(self) -> deque[Event]:
        """The recent events (tests and the stop benchmark read them)."""
        return self.state.events

    # STOPs.

    async def stop_all(self) -> list[str]:
        """STOP every axis at once; returns the ids of axes whose stop failed."""
        return await self.delivery.stop_all()

    async def stop_axis(self, entry: AxisEntry, kind: StopKind, reason: str) -> StopOutcome | None:
        """Stop one axis through the stop service (``servotune.hub.stops``): the STOP
        button (``"stop"``), every other stop (``"controlled"``: hand-over, dead-man,
        bench and auto-tune ends) or the power-off (``"power_off"``). Bumps the stop
        generation (ends a bench or auto-tune sequence); raises the driver's error when
        nothing could be sent."""
        entry.stop_generation += 1
        return await self.stops.stop(entry.info.id, kind, reason)

    def pend_stop(self, entry: AxisEntry, pressed_at: float | None = None) -> None:
        """Keep a STOP that could not reach the axis, pressed at ``pressed_at`` (now if
        None), for the axis' return (the control lock's dead-man uses this too)."""
        self.delivery.pend(entry, pressed_at)

    def note_stopped(self, entry: AxisEntry) -> None:
        """A STOP reached the axis: a STOP pressed before it has nothing left to stop."""
        self.delivery.note_stopped(entry)

    def note_commanded(self, entry: AxisEntry, what: str) -> None:
        """A command reached the axis: a STOP pressed before it must not act on the
        motion it may have started."""
        self.delivery.note_commanded(entry, what)

    def stop_overtaken(self, axis_id: str, pressed_at: float) -> str | None:
        """Why a STOP pressed at ``pressed_at`` (this hub's clock) must not be sent any
        more (the axis was commanded or stopped since), or None: send it."""
        return self.delivery.overtaken(self.state.entry(axis_id), pressed_at)
