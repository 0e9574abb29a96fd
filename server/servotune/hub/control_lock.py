"""The control lock per axis and the dead-man: who may change an axis, and what happens
when they vanish.

Sits between the hub and the api: the api asks ``ControlLock.require`` before every
change of an axis, the websocket endpoint feeds it the control messages of its
connection (``servotune.schema``: take / request / release / answer / force / heartbeat).
The hub knows nothing of it except the small ``AutopilotGate`` hook.
The dead-man's judgement (who went silent, who is forgiven, why) is ``hub/deadman.py``;
the client, settings and audit types the api and the lab bus share are
``hub/control_client.py``.

Rules (docs/control.md has the reasoning):

* A *holder* is one websocket connection (a browser tab: its ``client_id``), not a user:
  two tabs of the same user are two clients. The demo autopilot and the server itself
  (the start-up stop) are holders too.
* An axis held by a client can be changed only with that client's id (REST header
  ``X-Servotune-Client``) by the same user; everyone else gets 423 with the holder's
  name, and nothing is sent.
* An axis that nobody holds (or that the autopilot holds) may be changed by anyone with
  the permission: exclusivity is the operator's explicit choice (Take control), not a
  side effect of nudging a gain. A change that carries the id of a connected client
  makes that client the axis' *mover*: the axis stays free, but the dead-man covers
  what the tab set in motion (its lapse stops the axis) until another client changes or
  takes the axis. A change without a client id (scripts, the test suite) changes
  nothing of that. The autopilot yields to any change.
* Every transfer of an axis (take, grant, force, release, lapse) first brings it to its
  rest (``ControlLock._safe_stop``: a controlled stop that holds); the new holder starts
  with nothing moving. While that stop runs the axis answers 423 "being handed over".
* Dead-man: a holder renews its lease with heartbeats (``heartbeat_period_s``); when no
  heartbeat came for ``lease_s`` of time in which the server was listening, or the
  socket closed, every axis it holds is stopped and freed.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import secrets
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from fastapi import HTTPException
from pydantic import BaseModel

from servotune.auth.principal import CONTROL, FORCE_CONTROL, Principal
from servotune.hub.control_client import AuditSink, ControlClient, ControlSettings
from servotune.hub.deadman import DeadMan
from servotune.hub.hub import Hub
from servotune.hub.state import UnknownAxisError
from servotune.hub.stops import StopKind
from servotune.link.base import DeviceRefusedError, DriverError, LinkDownError
from servotune.schema import (
    AnswerControl,
    ControlAction,
    ControlHolder,
    ControlHolderKind,
    ControlPending,
    ControlPrompt,
    ControlReply,
    ControlStatus,
    ForceControl,
    ReleaseControl,
    RequestControl,
    TakeControl,
    Welcome,
)

logger = logging.getLogger(__name__)

# Event-loop turns the watchdog yields before it confirms a lapse: enough for a frame
# already in the socket to reach ``heartbeat`` (transport -> websocket -> endpoint).
_READ_TURNS = 10
# A STOP garbled on the wire (echo mismatch, no answer) is sent again, at once.
_STOP_ATTEMPTS = 3

ControlMessage = TakeControl | RequestControl | ReleaseControl | AnswerControl | ForceControl


@dataclass(eq=False, slots=True)
class _Pending:
    requester: ControlClient
    expires_s: float
    task: asyncio.Task[None] | None = None


@dataclass(eq=False, slots=True)
class _Axis:
    axis_id: str
    kind: ControlHolderKind | None = "server"  # held by the start-up stop until it is sent
    client: ControlClient | None = None
    since_s: float = 0.0
    # The holder's last change or control action (heartbeats are not activity).
    activity_s: float = 0.0
    # The last change or release by anyone; the autopilot resumes only after a quiet while.
    quiet_since_s: float = -math.inf
    pending: _Pending | None = None
    # The client that last changed the free axis: its lapse stops the axis too.
    mover: ControlClient | None = None
    handing_over: bool = False
    mutex: asyncio.Lock = field(default_factory=asyncio.Lock)
    ready: asyncio.Event = field(default_factory=asyncio.Event)


def _can_control(principal: Principal) -> bool:
    return CONTROL in principal.permissions or FORCE_CONTROL in principal.permissions


class ControlLock:
    """The lock of every axis of ``hub``; lives for the app's lifespan (``app.state.control``)."""

    def __init__(
        self,
        hub: Hub,
        settings: ControlSettings | None = None,
        *,
        audit: Callable[[], AuditSink | None] = lambda: None,
        clock: Callable[[], float] = time.monotonic,
        startup_stop: bool = True,
        shutdown_stop: bool = True,
    ) -> None:
        """``startup_stop``: send every axis the start-up STOP (``start``, ``add_link``);
        False only for a server whose axes are another server's (the lab hub,
        ``servotune.bus``): that server sent its own; the axes are free at once and
        nothing is sent. ``shutdown_stop``: STOP every axis when the server stops
        (``shutdown``); False likewise for the lab hub: a rig's local user may be
        driving its axes, and what the hub's own sessions set in motion is stopped by
        the rig's dead-man when their keep-alives end."""
        self.startup_stop = startup_stop
        self.shutdown_stop = shutdown_stop
        self._hub = hub
        self.settings = settings or ControlSettings()
        self._audit = audit
        self._clock = clock
        self._axes = {info.id: _Axis(info.id) for info in hub.axes_info()}
        self._clients: dict[str, ControlClient] = {}
        self._tasks: set[asyncio.Task[None]] = set()
        self._watchdog_task: asyncio.Task[None] | None = None
        self._deadman = DeadMan(
            lambda: self.settings,
            clock,
            self._clients.values,
            lambda client: bool(self._responsible(client)),
        )
        # Lapses seen and how late each was detected after the lease ran out (benchmark).
        self.lapses = 0
        # Passes of the watchdog begun (a test that steps the clock waits for two: one
        # whole pass then ran on the new time).
        self.watchdog_passes = 0
        hub.autopilot_gate = self
        for info in hub.axes_info():
            # The autopilot starts paused: it may move only once the start-up stop is out.
            hub.mark_operated(hub.entry(info.id))

    # --- lifespan ---------------------------------------------------------------------

    async def start(self) -> None:
        """Start the dead-man watchdog and send every axis its start-up STOP."""
        self._watchdog_task = asyncio.create_task(self._watchdog(), name="control watchdog")
        links: dict[str, list[str]] = {}
        for info in self._hub.axes_info():
            links.setdefault(info.link, []).append(info.id)
        for link_id, axis_ids in links.items():
            self._begin(link_id, axis_ids)

    def add_link(self, link_id: str) -> None:
        """Lock the axes of ``link_id``, a link the hub registered after ``start`` (a
        rig that joined the lab's bus): from now on they are locked like the others,
        and they get the start-up STOP unless ``startup_stop`` is False."""
        axis_ids = [
            info.id
            for info in self._hub.axes_info()
            if info.link == link_id and info.id not in self._axes
        ]
        for axis_id in axis_ids:
            self._axes[axis_id] = _Axis(axis_id)
            self._hub.mark_operated(self._hub.entry(axis_id))
        self._begin(link_id, axis_ids)

    def _begin(self, link_id: str, axis_ids: list[str]) -> None:
        if self.startup_stop:
            self._spawn(self._startup_stop(link_id, axis_ids), f"start-up stop of {link_id}")
            return
        for axis_id in axis_ids:
            self._release_startup(self._axes[axis_id])

    async def shutdown(self) -> None:
        """Stop every axis (before the links close), then end the lock's tasks."""
        if self._watchdog_task is not None:
            self._watchdog_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._watchdog_task
        for ax in self._axes.values():
            if ax.pending is not None and ax.pending.task is not None:
                ax.pending.task.cancel()
        if not self.shutdown_stop:
            logger.info(
                "shutdown: no STOP sent to the axes (another server's); what this "
                "server's sessions set in motion is stopped by their dead-man on the rig"
            )
        else:
            try:
                failed = await asyncio.wait_for(self._hub.stop_all(), self.settings.stop_timeout_s)
            except TimeoutError:
                logger.error("shutdown: the STOP of every axis did not finish in time")
            else:
                if failed:
                    logger.error("shutdown: STOP failed on %s", ", ".join(failed))
        for task in list(self._tasks):
            task.cancel()
        for task in list(self._tasks):
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task

    async def _startup_stop(self, link_id: str, axis_ids: list[str]) -> None:
        """Before anything else reaches an axis: STOP, as soon as its link is connected.

        Changes wait for it (``require``) up to ``startup_wait_s``; if the link is not
        up by then they go ahead (the driver refuses them while it is down) and the
        stop is still sent first thing when the link comes up.
        """
        while True:  # the hub reports link states by callback only: poll it
            if self._hub.link_status(link_id).state == "connected":
                break
            await asyncio.sleep(0.02)
        await asyncio.gather(
            *(self._safe_stop(a, "server start-up", kind="stop") for a in axis_ids)
        )
        for axis_id in axis_ids:
            self._release_startup(self._axes[axis_id])

    def _release_startup(self, ax: _Axis) -> None:
        if ax.kind == "server":
            ax.kind, ax.client = None, None
        ax.ready.set()
        self._broadcast_status(ax)

    # --- connections ------------------------------------------------------------------

    def connect(
        self, principal: Principal, address: str, send: Callable[[str], None]
    ) -> ControlClient:
        """A websocket connection opened; returns its client (``welcome`` is queued)."""
        client = ControlClient(
            client_id=secrets.token_urlsafe(18),
            tag=secrets.token_hex(4),
            principal=principal,
            address=address,
            send=send,
        )
        self._clients[client.client_id] = client
        welcome = Welcome(
            client_id=client.client_id,
            client_tag=client.tag,
            user=principal.user,
            permissions=sorted(principal.permissions),
            heartbeat_period_s=self.settings.heartbeat_period_s,
            lease_s=self.settings.lease_s,
        )
        self._send(client, welcome)
        return client

    def disconnect(self, client: ControlClient) -> None:
        """The connection closed (or was closed): its axes lapse now, not after the lease."""
        client.connected = False
        self._clients.pop(client.client_id, None)
        for ax in self._axes.values():
            if ax.pending is not None and ax.pending.requester is client:
                self._drop_pending(ax)
                self._broadcast_status(ax)
        if self._responsible(client):
            self._spawn(self._lapse(client, "the connection closed"), f"lapse of {client.tag}")

    def snapshot(self) -> list[str]:
        """``control_status`` of every axis, for a new connection."""
        return [self._status(ax).model_dump_json() for ax in self._axes.values()]

    def heartbeat(self, client: ControlClient, page_age_ms: int | None = None) -> None:
        """Renew the client's lease (cheap: called a few times a second per tab).

        ``page_age_ms``: from the tab's heartbeat worker, how long ago the page itself
        last ran. Ignored from a principal that may not control: it can hold and move
        nothing.
        """
        if _can_control(client.principal):
            self._heard(client)
            client.heartbeats += 1
            client.page_age_s = (page_age_ms or 0) / 1000

    def client(self, client_id: str) -> ControlClient | None:
        """The connected client with this (secret) id, if any."""
        return self._clients.get(client_id)

    # --- control messages -------------------------------------------------------------

    def submit(self, client: ControlClient, message: ControlMessage) -> None:
        """Handle ``message`` in a task of the lock's (see ``handle``)."""
        self._spawn(self.handle(client, message), f"{message.type} from {client.tag}")

    async def handle(self, client: ControlClient, message: ControlMessage) -> None:
        """One control message of ``client``; the answer goes back as ``control_reply``."""
        axis_id = message.axis
        action: ControlAction = {
            "take_control": "take",
            "request_control": "request",
            "release_control": "release",
            "answer_control": "answer",
            "force_control": "force",
        }[message.type]  # type: ignore[assignment]
        ax = self._axes.get(axis_id)
        if ax is None:
            self._reply(client, axis_id, action, False, f"no axis {axis_id!r}")
            return
        needed_ok = (
            FORCE_CONTROL in client.principal.permissions
            if action == "force"
            else _can_control(client.principal)
        )
        if not needed_ok:
            needed = "force_control" if action == "force" else "control"
            self._reply(client, axis_id, action, False, f"not permitted: needs '{needed}'")
            self._record(client, action, axis_id, "refused", f"missing permission {needed}")
            return
        if isinstance(message, TakeControl):
            await self._take(client, ax)
        elif isinstance(message, RequestControl):
            await self._request(client, ax)
        elif isinstance(message, ReleaseControl):
            await self._release(client, ax)
        elif isinstance(message, AnswerControl):
            await self._answer(client, ax, message.allow)
        else:
            await self._force(client, ax)

    async def _take(self, client: ControlClient, ax: _Axis) -> None:
        if ax.client is client:
            self._reply(client, ax.axis_id, "take", True, "you hold this axis")
            return
        await self._wait_startup(ax)
        if not await self._transfer(ax, client, "take", unless_held=True):
            message = f"held by {self._holder_name(ax)}: press Request control"
            self._reply(client, ax.axis_id, "take", False, message)
            return
        self._reply(client, ax.axis_id, "take", True, "you hold this axis")

    async def _request(self, client: ControlClient, ax: _Axis) -> None:
        if ax.kind != "user" or ax.client is None:
            await self._take(client, ax)
            return
        if ax.client is client:
            self._reply(client, ax.axis_id, "request", True, "you hold this axis")
            return
        if ax.pending is not None:
            message = f"{ax.pending.requester.user} asked first: wait for that answer"
            self._reply(client, ax.axis_id, "request", False, message)
            return
        timeout_s = self.settings.request_timeout_s
        pending = _Pending(client, self._clock() + timeout_s)
        ax.pending = pending
        pending.task = self._spawn(self._decide_later(ax, pending), f"request {ax.axis_id}")
        self._send(
            ax.client,
            ControlPrompt(
                axis=ax.axis_id,
                requester=client.user,
                requester_tag=client.tag,
                timeout_s=timeout_s,
                idle_grant_s=self.settings.idle_grant_s,
            ),
        )
        self._record(client, "control request", ax.axis_id, "pending", f"held by {ax.client.user}")
        self._broadcast_status(ax)

    async def _decide_later(self, ax: _Axis, pending: _Pending) -> None:
        """No answer in time: granted if the holder has been idle, else denied."""
        await asyncio.sleep(max(0.0, pending.expires_s - self._clock()))
        if ax.pending is not pending:
            return
        idle_s = self._clock() - ax.activity_s
        if idle_s >= self.settings.idle_grant_s:
            await self._grant(ax, f"no answer, holder idle for {idle_s:.0f} s")
        else:
            await self._deny(ax, f"no answer, holder active {idle_s:.0f} s ago")

    async def _answer(self, client: ControlClient, ax: _Axis, allow: bool) -> None:
        if ax.client is not client or ax.pending is None:
            self._reply(client, ax.axis_id, "answer", False, "no request to answer")
            return
        ax.activity_s = self._clock()
        if allow:
            await self._grant(ax, f"allowed by {client.user}")
        else:
            await self._deny(ax, f"denied by {client.user}")

    async def _grant(self, ax: _Axis, reason: str) -> None:
        pending = ax.pending
        assert pending is not None
        self._drop_pending(ax, cancel=False)
        requester, previous = pending.requester, ax.client
        if not requester.connected:
            self._broadcast_status(ax)
            return
        await self._transfer(ax, requester, "grant")
        self._reply(requester, ax.axis_id, "grant", True, f"you hold this axis ({reason})")
        if previous is not None:
            self._reply(previous, ax.axis_id, "grant", True, f"handed to {requester.user}")
        self._record(requester, "control granted", ax.axis_id, "ok", reason)

    async def _deny(self, ax: _Axis, reason: str) -> None:
        pending = ax.pending
        assert pending is not None
        self._drop_pending(ax, cancel=False)
        self._reply(pending.requester, ax.axis_id, "deny", False, f"request {reason}")
        self._record(pending.requester, "control denied", ax.axis_id, "denied", reason)
        self._broadcast_status(ax)

    async def _release(self, client: ControlClient, ax: _Axis) -> None:
        if ax.client is not client:
            self._reply(client, ax.axis_id, "release", False, "you do not hold this axis")
            return
        pending = ax.pending
        if pending is not None and pending.requester.connected:
            await self._grant(ax, f"released by {client.user}")
            return
        await self._transfer(ax, None, "release")
        self._reply(client, ax.axis_id, "release", True, "released (axis stopped)")
        self._record(client, "control release", ax.axis_id, "ok", "axis stopped")

    async def _force(self, client: ControlClient, ax: _Axis) -> None:
        previous = ax.client
        if previous is client:
            self._reply(client, ax.axis_id, "force", True, "you hold this axis")
            return
        if ax.pending is not None:
            self._drop_pending(ax)
        await self._wait_startup(ax)
        await self._transfer(ax, client, "force")
        self._reply(client, ax.axis_id, "force", True, "you hold this axis (forced)")
        if previous is not None:
            message = f"taken over by {client.user} (admin)"
            self._reply(previous, ax.axis_id, "force", False, message)
        holder = previous.user if previous is not None else "nobody"
        self._record(client, "control forced", ax.axis_id, "ok", f"from {holder}")

    # --- the REST check -----------------------------------------------------------------

    async def require(self, axis_id: str, client_id: str | None, principal: Principal) -> None:
        """Allow a change of ``axis_id`` by ``principal`` from connection ``client_id``.

        Raises ``HTTPException(423)`` naming the holder when another client holds the
        axis (nothing is sent then). A free axis may be changed by anyone (who passed
        the permission check); with the id of a connected client of the same user it
        is taken for that client first (STOP included, see the module doc). Unknown
        axes pass: the route answers 404.
        """
        ax = self._axes.get(axis_id)
        if ax is None:
            return
        client = self._clients.get(client_id) if client_id else None
        if client is not None and client.user != principal.user:
            client = None  # someone else's connection id authorises nothing
        if ax.kind == "server":
            await self._wait_startup(ax)
        for _ in range(3):
            if not ax.handing_over:
                break
            async with ax.mutex:  # a hand-over's STOP is under way: wait for its outcome
                pass
        else:
            raise HTTPException(423, detail=f"axis {axis_id} is being handed over (stopping)")
        if ax.kind == "user" and ax.client is not None:
            if ax.client is client:
                ax.activity_s = self._clock()
                return
            holder = ax.client
            detail = (
                f"axis {axis_id} is controlled by {holder.user}"
                + (" in another tab" if holder.user == principal.user else "")
                + ": ask them to release it, or press Request control"
            )
            self._record_principal(principal, "change refused", axis_id, "locked", detail)
            raise HTTPException(423, detail=detail)
        if ax.kind == "autopilot":
            # The autopilot yields to any change; its bounded demo move may finish.
            self._hub.mark_operated(self._hub.entry(axis_id))
            ax.kind = None
            self._broadcast_status(ax)
        if client is not None:
            # Not a take (see the module doc): this tab answers for what it sets in
            # motion. Its change proves it alive, so its lease starts afresh.
            ax.mover = client
            self._heard(client)
        ax.quiet_since_s = self._clock()

    async def _wait_startup(self, ax: _Axis) -> None:
        if ax.ready.is_set():
            return
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(ax.ready.wait(), self.settings.startup_wait_s)

    # --- transfers and the safe state -----------------------------------------------------

    async def _transfer(
        self, ax: _Axis, client: ControlClient | None, action: str, *, unless_held: bool = False
    ) -> bool:
        """Hand ``ax`` to ``client`` after its safe stop; waits for a transfer under way.

        ``unless_held``: do nothing (False) if another user's client holds it by then.
        """
        async with ax.mutex:
            if unless_held and ax.kind == "user" and ax.client is not client:
                return False
            await self._transfer_locked(ax, client, action)
            return True

    async def _transfer_locked(self, ax: _Axis, client: ControlClient | None, action: str) -> None:
        """Safe state first, then the new holder (``None``: free). Caller holds the mutex."""
        previous = self._holder_name(ax)
        if ax.kind == "autopilot":
            # The autopilot loop stops issuing before the STOP (which fails what it queued).
            self._hub.mark_operated(self._hub.entry(ax.axis_id))
        ax.handing_over = True
        ax.mover = None
        self._broadcast_status(ax)
        try:
            target = client.user if client is not None else "nobody"
            await self._safe_stop(ax.axis_id, f"control {action}: {previous} -> {target}")
        finally:
            ax.handing_over = False
        now = self._clock()
        if client is not None and client.connected:
            ax.kind, ax.client, ax.since_s, ax.activity_s = "user", client, now, now
            self._heard(client)
            self._hub.mark_operated(self._hub.entry(ax.axis_id))
        else:
            ax.kind, ax.client, ax.since_s = None, None, now
        ax.quiet_since_s = now
        ax.ready.set()
        if action == "take" and client is not None:
            self._record(client, "control take", ax.axis_id, "ok", f"from {previous}")
        self._broadcast_status(ax)

    async def _safe_stop(self, axis_id: str, reason: str, *, kind: StopKind = "controlled") -> bool:
        """Bring one axis to rest ahead of everything, through the hub's stop service
        (``servotune.hub.stops``, docs/control.md "Stops").

        A hand-over or a lapse is a *controlled* stop that keeps holding (SLAP2: pm where
        the shaft is; Z1100: Estop, holding; EP7047: the emergency ramp with Enable kept),
        unless the loop is not working (then its power is cut, as STOP would). The
        start-up stop is the device's STOP (``kind="stop"``). A bounded move in position
        mode is stopped too, not allowed to finish: nobody is watching it any more
        (lapse) or somebody else is about to act (transfer). Every stop also fails the
        axis' queued motion and ends its bench / auto-tune sequence (stop generation).
        A stop that cannot reach the axis is sent on reconnect.
        """
        entry = self._hub.entry(axis_id)
        entry.stopped(f"STOP ({reason})")
        for attempt in range(1, _STOP_ATTEMPTS + 1):
            try:
                await asyncio.wait_for(
                    self._hub.stops.stop(axis_id, kind, f"STOP ({reason})"),
                    self.settings.stop_timeout_s,
                )
            except (DriverError, TimeoutError) as exc:
                detail = str(exc) or type(exc).__name__
                retry = attempt < _STOP_ATTEMPTS and not isinstance(
                    exc, LinkDownError | DeviceRefusedError
                )
                if isinstance(exc, LinkDownError):
                    self._hub.pend_stop(entry)  # the hub sends it when the axis is back
                again = f" (attempt {attempt}, sending again)" if retry else ""
                self._hub.on_event("error", axis_id, f"STOP ({reason}) failed: {detail}{again}")
                if retry:
                    continue
                return False
            self._hub.note_stopped(entry)  # a STOP pressed before has nothing left to stop
            self._hub.on_event("warning", axis_id, f"STOP ({reason})")
            return True
        return False

    async def _lapse(self, client: ControlClient, reason: str) -> None:
        """The dead-man: every axis ``client`` holds or moved to its safe state at once."""
        axes = self._responsible(client)
        self.lapses += 1
        await asyncio.gather(*(self._lapse_axis(ax, client, reason) for ax in axes))

    async def _lapse_axis(self, ax: _Axis, client: ControlClient, reason: str) -> None:
        held = ax.client is client
        if not held and ax.mover is not client:
            return
        # Free the axis before the STOP so the lapsed client cannot change it meanwhile.
        if held:
            ax.kind, ax.client = None, None
        ax.mover = None
        ax.handing_over = True
        if ax.pending is not None:
            pending = ax.pending
            self._drop_pending(ax)
            self._reply(pending.requester, ax.axis_id, "lapse", True, "the holder went away")
        try:
            async with ax.mutex:
                await self._safe_stop(ax.axis_id, f"dead-man: {client.user}, {reason}")
        finally:
            ax.handing_over = False
        ax.quiet_since_s = self._clock()
        lost = "control lost" if held else "dead-man"
        self._reply(client, ax.axis_id, "lapse", False, f"{lost}: {reason} (axis stopped)")
        self._record(client, "control lapsed", ax.axis_id, "stopped", reason)
        self._broadcast_status(ax)

    async def _watchdog(self) -> None:
        """Lapse the lease of every holder or mover silent for more than ``lease_s``.

        A suspect is confirmed only after the event loop has had a few turns to read
        what already arrived: after a stall of the server's own loop (a heavy request,
        a starved process) the client's heartbeats sit unread in the socket, and that is
        not the client's silence. Real time is used otherwise, so a starved server is
        not slower to stop than it has to be.
        """
        period = self.settings.watchdog_period_s
        while True:
            await asyncio.sleep(period)
            self.watchdog_passes += 1
            self._deadman.probe_late_clients()
            suspects = self._deadman.silent_clients()
            if not suspects:
                continue
            for _ in range(_READ_TURNS):
                await asyncio.sleep(0)
            for client in suspects:
                client.alive_cache = (-math.inf, None)  # ask afresh: a probe may be acked
            confirmed = set(self._deadman.silent_clients())
            for client in suspects:
                if client in confirmed:
                    client.lapsing = True  # once; a heartbeat or a new hold resets it
                    why = self._deadman.lapse_reason(client, self._clock())
                    self._spawn(self._lapse(client, why), f"lapse of {client.tag}")

    # --- demo autopilot (hub.autopilot.AutopilotGate) ---------------------------------------

    def autopilot_paused(self, axis_id: str) -> None:
        """The autopilot stopped driving the axis (a user acted, or STOP)."""
        ax = self._axes.get(axis_id)
        if ax is not None and ax.kind == "autopilot":
            ax.kind, ax.client = None, None
            ax.quiet_since_s = self._clock()
            self._broadcast_status(ax)

    def autopilot_may_resume(self, axis_id: str) -> bool:
        """Free and quiet for ``autopilot_resume_s``: the autopilot takes the axis."""
        ax = self._axes.get(axis_id)
        if ax is None or ax.kind is not None or ax.handing_over or ax.pending is not None:
            return False
        if self._clock() - ax.quiet_since_s < self.settings.autopilot_resume_s:
            return False
        ax.kind, ax.client, ax.since_s, ax.mover = "autopilot", None, self._clock(), None
        self._broadcast_status(ax)
        return True

    # --- helpers ------------------------------------------------------------------------

    def holder(self, axis_id: str) -> ControlHolder | None:
        try:
            ax = self._axes[axis_id]
        except KeyError:
            raise UnknownAxisError(axis_id) from None
        return self._status(ax).holder

    def _heard(self, client: ControlClient) -> None:
        now = self._clock()
        gap_s = now - client.heard_s
        held = bool(self._responsible(client))
        if client.held_when_heard and held and gap_s > client.worst_gap_s:
            client.worst_gap_s = gap_s
            if gap_s > self.settings.lease_s / 2:
                logger.info(
                    "dead-man: %s heard after %.0f ms (its longest gap while holding; "
                    "lease %.0f ms)",
                    client.tag,
                    1000 * gap_s,
                    1000 * self.settings.lease_s,
                )
        client.heard_s = now
        client.held_when_heard = held
        client.lapsing = False

    def _responsible(self, client: ControlClient) -> list[_Axis]:
        """Axes ``client`` holds, or moved while they were free."""
        return [
            ax
            for ax in self._axes.values()
            if ax.client is client or (ax.kind is None and ax.mover is client)
        ]

    def _holder_name(self, ax: _Axis) -> str:
        if ax.kind == "user" and ax.client is not None:
            return ax.client.user
        return ax.kind or "nobody"

    def _status(self, ax: _Axis) -> ControlStatus:
        holder = None
        if ax.kind is not None:
            holder = ControlHolder(
                kind=ax.kind,
                user=ax.client.user if ax.client is not None else ax.kind,
                client_tag=ax.client.tag if ax.client is not None else None,
                since_s=round(ax.since_s - self._hub_t0(), 3),
            )
        pending = None
        if ax.pending is not None:
            pending = ControlPending(
                user=ax.pending.requester.user,
                client_tag=ax.pending.requester.tag,
                expires_s=round(ax.pending.expires_s - self._hub_t0(), 3),
            )
        return ControlStatus(axis=ax.axis_id, holder=holder, pending=pending)

    def _hub_t0(self) -> float:
        # Server times on the wire are seconds since the hub started (servotune.schema.websocket).
        return self._clock() - self._hub.now()

    def _broadcast_status(self, ax: _Axis) -> None:
        self._hub.broadcast_model(self._status(ax))

    def _drop_pending(self, ax: _Axis, *, cancel: bool = True) -> None:
        pending, ax.pending = ax.pending, None
        task = pending.task if pending is not None else None
        if cancel and task is not None and task is not asyncio.current_task():
            task.cancel()

    def _send(self, client: ControlClient, message: BaseModel) -> None:
        if client.connected:
            client.send(message.model_dump_json())

    def _reply(
        self, client: ControlClient, axis_id: str, action: ControlAction, ok: bool, message: str
    ) -> None:
        self._send(client, ControlReply(axis=axis_id, action=action, ok=ok, message=message))

    def _record(
        self, client: ControlClient, action: str, axis_id: str, result: str, detail: str
    ) -> None:
        self._record_principal(client.principal, action, axis_id, result, detail, client.address)

    def _record_principal(
        self,
        principal: Principal | None,
        action: str,
        axis_id: str,
        result: str,
        detail: str,
        address: str | None = None,
    ) -> None:
        audit = self._audit()
        if audit is None:
            return
        try:
            audit.record(
                who=principal.user if principal is not None else "server",
                action=action,
                axis=axis_id,
                address=address,
                result=result,
                detail=detail,
            )
        except Exception:  # the audit must never break the lock or the dead-man
            logger.exception("audit record failed")

    def _spawn(self, job: object, name: str) -> asyncio.Task[None]:
        task: asyncio.Task[None] = asyncio.get_running_loop().create_task(job, name=name)  # type: ignore[arg-type]
        self._tasks.add(task)
        task.add_done_callback(self._forget)
        return task

    def _forget(self, task: asyncio.Task[None]) -> None:
        self._tasks.discard(task)
        if not task.cancelled() and task.exception() is not None:
            logger.error("control task %s failed", task.get_name(), exc_info=task.exception())
