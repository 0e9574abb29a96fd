"""The hub: owns the links, validates every change, and fans telemetry out to clients.

Every command that changes a device goes through ``Hub.write_params``,
``Hub.command``, ``Hub.console`` or ``stop_all`` (in ``HubState``, beside the
delivery of a STOP that could not be sent at once, which shares it): one path where input is checked
against the device descriptor before anything is sent and where the axis is marked as
operated (which switches the demo autopilot off for it). Who may call it is decided
before, in the api: the user's role (``servotune.auth``) and the axis's control lock
(``hub.control_lock``); ``auth.audit`` records what was done.

What lives here (the upper half of the hub): ``Hub``, with what drives the devices:
its lifecycle (the links' owner tasks, restarted with backoff), the command path but
for the STOP, and the demo autopilot. What the hub knows of its links and axes (the ``DriverSink``
side, supervision, events, queries) and the fan-out to clients are in
``servotune.hub.state`` (``HubState``, which ``Hub`` extends); the seam is the
direction, see there.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Mapping

from servotune.hub.movewatch import MovePlan, plan_move, watch_move
from servotune.hub.state import AxisEntry, HubState, LinkEntry
from servotune.hub.stops import StopKind
from servotune.link.base import (
    Autopilot,
    CommandOutcome,
    DeviceRefusedError,
    DriverError,
    InvalidArgumentError,
    Link,
    StopOutcome,
    check_console_line,
)
from servotune.link.validation import validate_command, validate_params
from servotune.schema import EventLevel, MoveOutcome, Params

logger = logging.getLogger(__name__)

LINK_RESTART_MAX_S = 5.0


class NotFoundError(LookupError):
    """A stored thing (run, parameter set) that does not exist: HTTP 404."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(message)
        self.field = field


class Hub(HubState):
    """Owns links and their tasks for the lifetime of the app (see ``api.app``)."""

    # --- lifecycle --------------------------------------------------------------------

    async def start(self) -> None:
        """Load stored settings and start every link's owner task and the fan-out."""
        for entry in self._axes.values():
            entry.last_known = await asyncio.to_thread(self._storage.last_params, entry.storage_key)
        for link_entry in self._links.values():
            link_entry.updated_at = self._clock()
            self._tasks.append(asyncio.create_task(self._run_link(link_entry)))
        self._tasks.append(asyncio.create_task(self._fan_out()))
        if self.autopilot:
            for entry in self._axes.values():
                self._tasks.append(asyncio.create_task(self._autopilot(entry)))

    async def stop(self) -> None:
        """Cancel every task; the links close their ports."""
        tasks = [*self._tasks, *self._move_watches.values()]
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
            self._show_link_down(link_entry, message)
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
            self._broadcast(self._axis_status(entry).model_dump_json(), droppable=False)

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
                self._schedule_stop(entry, exc, pressed_at)
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
            for e in self._axes.values()
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
        self._broadcast(self._axis_status(entry).model_dump_json(), droppable=False)
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

    # --- demo autopilot ---------------------------------------------------------------

    async def _autopilot(self, entry: AxisEntry) -> None:
        """Gentle repeating moves while nobody else operates the axis (demo only).

        ``entry.operated`` means "the autopilot is not driving this axis now": a user
        change sets it. With an ``autopilot_gate`` (the control lock) the autopilot
        waits and resumes when the gate lets it; without one it stops for good.
        The moves come from the driver's ``autopilot_commands`` / ``autopilot_settled``
        (see ``link.base.Autopilot``); axes whose driver has none stay still.
        """
        driver = entry.driver
        if not isinstance(driver, Autopilot):
            return
        amplitude = driver.autopilot_amplitude()
        direction = 1
        paused = False
        while True:
            if entry.operated:
                gate = self.autopilot_gate
                if gate is None:
                    return
                if not paused:
                    paused = True
                    gate.autopilot_paused(entry.info.id)
                await asyncio.sleep(0.5)
                if entry.operated and gate.autopilot_may_resume(entry.info.id):
                    paused = False
                    entry.operated = False
                    self._broadcast(self._axis_status(entry).model_dump_json(), droppable=False)
                continue
            await asyncio.sleep(0.5)
            link_state = self._links[entry.link.id].status.state
            sample = entry.latest
            if link_state != "connected" or entry.health == "offline" or sample is None:
                continue
            try:
                for name, args in driver.autopilot_commands(sample, direction * amplitude):
                    if entry.operated:
                        break
                    await driver.command(name, args)
                    await asyncio.sleep(0.05)
                direction = -direction
                deadline = self._clock() + 8.0
                await asyncio.sleep(0.3)
                while not entry.operated and self._clock() < deadline:
                    latest = entry.latest
                    if latest is not None and driver.autopilot_settled(latest):
                        break
                    await asyncio.sleep(0.05)
                await asyncio.sleep(0.8)
            except DriverError as exc:
                logger.info("autopilot on %s: %s", entry.info.id, exc)
                await asyncio.sleep(1.0)

    # --- links registered while the hub runs (servotune.bus) ---------------------------

    async def add_running_link(self, link: Link) -> None:
        """Register ``link`` while the hub runs (a rig that joined the lab's bus after
        the hub started, ``servotune.bus``): its stored settings are loaded, its task
        is started, and every client gets a new ``hello`` (the web client rebuilds its
        navigation from it, as after a reconnect). ValueError for a duplicate id."""
        self.add_link(link)
        for axis in link.axes:
            entry = self._axes[axis.id]
            entry.last_known = await asyncio.to_thread(self._storage.last_params, entry.storage_key)
        if self._tasks:  # started: the link needs its owner task (else ``start`` does it)
            link_entry = self._links[link.id]
            link_entry.updated_at = self._clock()
            self._tasks.append(asyncio.create_task(self._run_link(link_entry)))
        self._broadcast(self.hello().model_dump_json(), droppable=False)
