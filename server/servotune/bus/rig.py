"""The rig agent: a rig's own server on the bus (``servotune serve --bus URL --rig NAME``).

What it does, beside everything the rig's server does anyway:

* publishes its manifest (links, axes, descriptors) on ``servotune.v1.<rig>.manifest``
  and its presence on ``servotune.v1.<rig>.presence`` every ``presence_period_s`` (both
  kept as last values by the lab's JetStream, see ``subjects``);
* forwards the hub's fan-out, exactly as a websocket client gets it: telemetry batches
  (about 30 a second per axis, never one message per sample) on
  ``servotune.v1.<rig>.<link>.<axis>.telemetry``, status, parameters and events on
  ``servotune.v1.<rig>.events``; a slow bus loses old telemetry batches, never status;
* answers ``...<axis>.cmd.<verb>`` requests (``write_params``, ``read_params``,
  ``console``, a descriptor command) through the SAME path as a local REST request:
  the permission of the verb (``auth.routes_table.command_permission``), the rig's
  control lock (``ControlLock.require``), the hub's validation against the
  descriptor (422-equivalent reply naming the field, nothing sent);
* answers STOP (``cmd.stop``, ``cmd.stop_all``), the hub sessions' keep-alives and the
  hub's clock probes (``cmd.clock``) on a connection of their own: NATS has no
  priorities, and a STOP must not queue behind telemetry;
* runs a command only before its deadline (``CommandRequest.deadline_s``, on this
  rig's clock): one that comes later (the rig was stalled, the network held it) is
  dropped and reported, since the hub has told its user it failed; so is one from a
  hub session the dead-man ended. The first answer to a request says it was taken
  (``ACK_HEADER``), sent before it runs, so the hub can tell "not run" from "no
  outcome". A hub STOP that was pressed before the axis was commanded or stopped again
  is not sent (``Hub.stop_overtaken``);
* keeps the dead-man on the rig: each hub session is a ``ControlClient`` of the rig's
  own ``ControlLock`` whose heartbeats are the session's keep-alives over the bus;
  when they stop (hub dead, leaf link cut) for the rig's lease, the axes that session
  moved or held are stopped by the rig;
* publishes every finished run to the ``SERVOTUNE_RUNS`` stream (deduplicated by
  ``Nats-Msg-Id``), retrying those the bus did not acknowledge (leaf link down).

The hub is not trusted for safety: it may be anyone holding the hub's credentials.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import secrets
import time
from typing import TYPE_CHECKING, Any

from fastapi import HTTPException
from nats.aio.client import Client
from nats.aio.msg import Msg
from nats.errors import Error as NatsError
from nats.js.errors import Error as JetStreamError
from pydantic import ValidationError

from servotune import __version__
from servotune.auth.permissions import permissions_of
from servotune.auth.principal import AUTOTUNE, BENCH, CONSOLE, STOP, TUNE, VIEW, Principal
from servotune.auth.routes_table import (
    UnknownConsoleLineError,
    command_permission,
    console_permission,
)
from servotune.bench.service import BenchTestRequest, TestBench
from servotune.bus import subjects
from servotune.bus.connection import BusSettings, connect_bus
from servotune.bus.leaf import ensure_rig_streams
from servotune.bus.messages import (
    ACK_HEADER,
    CommandReply,
    CommandRequest,
    KeepAlive,
    Presence,
    RemoteAxisInfo,
    RemoteLinkInfo,
    RigManifest,
    RunRecord,
)
from servotune.bus.tasks import BackgroundTasks
from servotune.hub.control_client import ControlClient
from servotune.hub.control_lock import ControlLock
from servotune.hub.hub import Hub
from servotune.hub.state import ClientQueue, StopOvertakenError, UnknownAxisError
from servotune.link.base import (
    DeviceRefusedError,
    DeviceTimeoutError,
    DriverError,
    InvalidArgumentError,
    LinkDownError,
    ProtocolError,
)
from servotune.storage import Storage, StorageError

if TYPE_CHECKING:
    from servotune.autotune.service import AutoTuner

logger = logging.getLogger(__name__)

# What a hub session may do on this rig at most: an operator's permissions. Admin
# actions (limits, EEPROM/flash, forced hand-over) stay with the rig's own dashboard.
BUS_ROLE = "operator"
# A hub session silent this long is forgotten (its lapse stopped its axes long before).
SESSION_FORGET_S = 60.0
RUN_RETRY_S = 2.0
_PUBLISHED_META = "bus.published_runs"


def _reply(**fields: Any) -> bytes:
    return CommandReply(**fields).model_dump_json().encode()


class NotRunError(DriverError):
    """A request the rig does not run at all (``kind``: expired, session_ended)."""

    def __init__(self, kind: str, detail: str) -> None:
        super().__init__(detail)
        self.kind = kind


def _error_reply(exc: Exception) -> bytes:
    """The rig's REST error for ``exc``, as a reply (``kind`` ~ status code)."""
    if isinstance(exc, NotRunError):
        return _reply(ok=False, kind=exc.kind, detail=str(exc))
    if isinstance(exc, StopOvertakenError):
        return _reply(ok=False, kind="overtaken", detail=str(exc))
    if isinstance(exc, InvalidArgumentError):
        return _reply(ok=False, kind="invalid", field=exc.field, detail=str(exc))
    if isinstance(exc, HTTPException):
        kind = "locked" if exc.status_code == 423 else "forbidden"
        return _reply(ok=False, kind=kind, detail=str(exc.detail))
    if isinstance(exc, UnknownAxisError):
        return _reply(ok=False, kind="invalid", field="axis", detail=f"no axis {exc.args[0]!r}")
    if isinstance(exc, DeviceRefusedError):
        return _reply(ok=False, kind="refused", detail=str(exc))
    if isinstance(exc, LinkDownError):
        return _reply(ok=False, kind="link_down", detail=str(exc))
    if isinstance(exc, DeviceTimeoutError):
        return _reply(ok=False, kind="timeout", detail=str(exc))
    if isinstance(exc, ProtocolError):
        return _reply(ok=False, kind="protocol", detail=str(exc))
    return _reply(ok=False, kind="device", detail=str(exc))


def _invalid(exc: ValidationError) -> InvalidArgumentError:
    """A request body the rig cannot use, as its REST's 422 naming the field."""
    first = exc.errors()[0]
    field = ".".join(str(p) for p in first.get("loc", ())) or "body"
    return InvalidArgumentError(field, f"{field}: {first.get('msg')}")


class RigAgent:
    """One rig on the bus; lives for the app's lifespan (``start`` .. ``stop``)."""

    def __init__(
        self,
        settings: BusSettings,
        hub: Hub,
        control: ControlLock,
        storage: Storage,
        bench: TestBench | None = None,
        autotuner: AutoTuner | None = None,
    ) -> None:
        if settings.rig is None:
            raise ValueError("a rig agent needs the rig's name")
        self.rig = subjects.check_token("--rig", settings.rig)
        self._settings = settings
        self._hub = hub
        self._control = control
        self._storage = storage
        self._bench = bench
        self._autotuner = autotuner
        # (link id, axis id) of the subject -> the rig's axis id; checked to be tokens.
        self._axes: dict[tuple[str, str], str] = {}
        for info in hub.axes_info():
            subjects.check_token("link id", info.link)
            subjects.check_token("axis id", info.id)
            self._axes[(info.link, info.id)] = info.id
        self._link_of = {info.id: info.link for info in hub.axes_info()}
        self._nc: Client | None = None
        self._stop_nc: Client | None = None
        self._queue: ClientQueue | None = None
        self._tasks = BackgroundTasks(logger)
        self._sessions: dict[str, tuple[ControlClient, float]] = {}
        # Hub sessions the rig's dead-man ended (their keep-alives stopped while they
        # moved an axis): nothing they send runs any more; the hub starts a new one.
        self._ended: dict[str, float] = {}
        # This run of the agent: a hub that sees another id estimates the clock anew.
        self.instance = secrets.token_hex(8)
        self._unpublished: set[str] = set()
        self._published: set[str] = set()
        self._principal = Principal(
            user="hub", role=BUS_ROLE, permissions=permissions_of(BUS_ROLE), via="bus"
        )
        # Counters a test or benchmark reads.
        self.telemetry_sent = 0
        self.commands_handled = 0
        self.verbs_handled: list[str] = []
        # Fan-out messages not published because the bus connection was down (nats-py
        # would buffer them and deliver old telemetry as new after the outage).
        self.unsent_while_down = 0
        # Requests not run: (verb, kind) each, and the keep-alives' arrival times.
        self.not_run: list[tuple[str, str]] = []
        self.keepalives: list[float] = []

    # --- lifespan ---------------------------------------------------------------------

    async def start(self) -> None:
        """Join the bus in the background: a rig whose lab network is down at start-up
        starts anyway (local dashboard, STOP, recording) and joins when it can."""
        self._tasks.spawn(self._join(), "bus: joining")

    async def _join(self) -> None:
        backoff_s = 0.5
        while True:
            try:
                await self._connect()
            except (NatsError, OSError, TimeoutError) as exc:
                logger.warning("bus %s not reachable (%s): trying again", self._settings.url, exc)
                await self._close_connections()
                await asyncio.sleep(backoff_s)
                backoff_s = min(2 * backoff_s, 5.0)
                continue
            break
        published = await asyncio.to_thread(self._storage.get_meta, _PUBLISHED_META)
        self._published = set(published) if isinstance(published, list) else set()
        self._queue = self._hub.subscribe()
        self._tasks.spawn(self._forward(self._queue), "bus: forward fan-out")
        self._tasks.spawn(self._presence(), "bus: presence")
        self._tasks.spawn(self._publish_runs(), "bus: runs")

    async def _connect(self) -> None:
        """Both connections and their subscriptions (once connected, nats-py reconnects)."""
        inbox = subjects.inbox_prefix(self.rig)
        self._nc = await connect_bus(self._settings, name=f"rig-{self.rig}", inbox_prefix=inbox)
        self._stop_nc = await connect_bus(
            self._settings, name=f"rig-{self.rig}-stop", inbox_prefix=inbox
        )
        root = f"{subjects.PREFIX}.{self.rig}"
        await self._stop_nc.subscribe(f"{root}.*.*.cmd.{subjects.STOP}", cb=self._on_stop)
        await self._stop_nc.subscribe(subjects.rig_cmd(self.rig, "stop_all"), cb=self._on_stop)
        await self._stop_nc.subscribe(subjects.rig_cmd(self.rig, "keepalive"), cb=self._on_alive)
        await self._stop_nc.subscribe(subjects.rig_cmd(self.rig, subjects.CLOCK), cb=self._on_clock)
        await self._nc.subscribe(f"{root}.*.*.cmd.*", cb=self._on_command)
        await self._nc.subscribe(subjects.rig_cmd(self.rig, "snapshot"), cb=self._on_snapshot)
        await self._nc.subscribe(subjects.rig_cmd(self.rig, "manifest"), cb=self._on_manifest)
        await self._stop_nc.flush()
        await self._nc.flush()

    async def _close_connections(self) -> None:
        for nc in (self._nc, self._stop_nc):
            if nc is not None:
                # A connection already cut (network down) fails its last flush.
                with contextlib.suppress(NatsError, TimeoutError, OSError):
                    await nc.close()
        self._nc = self._stop_nc = None

    async def stop(self, *, graceful: bool = True) -> None:
        """Leave the bus. ``graceful``: delete the presence key so the hub shows the rig
        offline at once (a killed rig is found by the presence's silence instead)."""
        if self._queue is not None:
            self._hub.unsubscribe(self._queue)
        await self._tasks.cancel_all()
        if graceful and self._nc is not None and self._nc.is_connected:
            with contextlib.suppress(NatsError, TimeoutError):
                await self._nc.publish(
                    subjects.presence(self.rig),
                    b"{}",
                    headers={subjects.GONE_HEADER: "1", **self._clock_headers()},
                )
                await self._nc.flush(timeout=1)
        for client, _ in self._sessions.values():
            self._control.disconnect(client)
        self._sessions.clear()
        await self._close_connections()

    @property
    def connected(self) -> bool:
        """Both connections to the rig's nats-server (commands and STOP) are up; says
        nothing about the lab network behind a leaf node."""
        return all(nc is not None and nc.is_connected for nc in (self._nc, self._stop_nc))

    # --- what the rig offers ----------------------------------------------------------

    def manifest(self) -> RigManifest:
        links = []
        for link in self._hub.links_info():
            axes = [
                RemoteAxisInfo(
                    info=info,
                    descriptor=self._hub.descriptor(info.id),
                    bench_kinds=self._bench.kinds(info.id) if self._bench else [],
                )
                for info in self._hub.axes_info()
                if info.link == link.id
            ]
            links.append(RemoteLinkInfo(info=link, axes=axes))
        return RigManifest(
            rig=self.rig,
            server_version=__version__,
            links=links,
            domain=self.rig if self._settings.leaf else None,
        )

    async def _put_manifest(self) -> None:
        """The manifest on the rigs stream (the hub lists the rig from it), acknowledged."""
        assert self._nc is not None
        await self._nc.jetstream().publish(
            subjects.manifest(self.rig),
            self.manifest().model_dump_json().encode(),
            timeout=self._settings.request_timeout_s,
        )

    async def _presence(self) -> None:
        assert self._nc is not None
        period = self._settings.presence_period_s
        manifest_put = False
        while True:
            try:
                if not manifest_put:
                    # Until the lab's server has the bucket (the hub creates it) and the
                    # leaf link is up: the rig works meanwhile, it is just not listed.
                    # On a leaf node: the rig's own streams, in its own domain.
                    if self._settings.leaf:
                        await ensure_rig_streams(self._nc, self.rig)
                    await self._put_manifest()
                    manifest_put = True
                body = Presence(rig=self.rig, period_s=period, sent_wall_s=time.time())
                # Not acknowledged: the next one follows in ``period``. Not published
                # while the connection is down: nats-py would buffer it and deliver it
                # late. The rig's clock: the hub dates it with its estimate of that
                # clock (``bus.clock``), so a late one is taken for what it is.
                if self._nc.is_connected:
                    await self._nc.publish(
                        subjects.presence(self.rig),
                        body.model_dump_json().encode(),
                        headers=self._clock_headers(),
                    )
            except (NatsError, JetStreamError, TimeoutError) as exc:
                # Lab network down: the rig keeps working; presence resumes with it.
                logger.debug("presence not published: %s", exc)
            self._forget_silent_sessions()
            await asyncio.sleep(period)

    def _clock_headers(self) -> dict[str, str]:
        return {
            subjects.RIG_NOW_HEADER: f"{self._hub.now():.6f}",
            subjects.RIG_ID_HEADER: self.instance,
        }

    async def _forward(self, queue: ClientQueue) -> None:
        """The hub's fan-out, as it would go to a websocket client, onto the bus."""
        assert self._nc is not None
        nc = self._nc
        events = subjects.events(self.rig)
        while True:
            text = await queue.get()
            message = json.loads(text)
            kind = message.get("type")
            if not nc.is_connected:
                # nats-py would buffer it while it reconnects and deliver minutes-old
                # telemetry and statuses as new; the hub asks for a fresh snapshot when
                # the rig is back. A finished run still goes to the stream.
                self.unsent_while_down += 1
                if kind == "run" and message.get("status") in ("complete", "incomplete"):
                    self._unpublished.add(str(message["run_id"]))
                continue
            headers = {"St-Rig-Now": f"{self._hub.now():.6f}", "St-Wall": f"{time.time():.6f}"}
            try:
                if kind == "telemetry":
                    axis_id = message["axis"]
                    subject = subjects.telemetry(self.rig, self._link_of[axis_id], axis_id)
                    await nc.publish(subject, text.encode(), headers=headers)
                    self.telemetry_sent += 1
                elif kind in ("link_status", "axis_status", "params", "event", "control_status"):
                    await nc.publish(events, text.encode(), headers=headers)
                elif kind == "run":
                    # Progress for the hub's tabs; the finished run goes to the stream.
                    await nc.publish(events, text.encode(), headers=headers)
                    if message.get("status") in ("complete", "incomplete"):
                        self._unpublished.add(str(message["run_id"]))
            except NatsError as exc:
                # Disconnected: nats-py buffers while reconnecting, then refuses; the
                # rig's own clients are not affected.
                logger.debug("bus publish failed: %s", exc)

    # --- requests ---------------------------------------------------------------------

    async def _on_command(self, msg: Msg) -> None:
        tokens = msg.subject.split(".")
        if len(tokens) != 7 or tokens[6] == subjects.STOP:
            return  # STOP is answered on the STOP connection
        # Each request in a task of its own: a parameter write waiting for its read-back
        # must not hold the next request back.
        self._tasks.spawn(self._answer(msg, tokens[3], tokens[4], tokens[6]), f"bus: {msg.subject}")

    async def _on_stop(self, msg: Msg) -> None:
        tokens = msg.subject.split(".")
        if tokens[-1] == "stop_all":
            self.verbs_handled.append("stop_all")
            failed = await self._hub.stop_all()
            await msg.respond(_reply(ok=not failed, result={"failed": failed}, kind=None))
            return
        await self._answer(msg, tokens[3], tokens[4], subjects.STOP)

    async def _on_clock(self, msg: Msg) -> None:
        """The hub's clock probe (``bus.clock``): this rig's clock, answered at once."""
        if msg.reply and self._stop_nc is not None:
            with contextlib.suppress(NatsError):
                await self._stop_nc.publish(msg.reply, b"", headers=self._clock_headers())

    async def _on_alive(self, msg: Msg) -> None:
        try:
            alive = KeepAlive.model_validate_json(msg.data)
        except ValidationError:
            return
        self.keepalives.append(self._hub.now())
        del self.keepalives[:-2000]
        if self._session_ended(alive.session):
            return  # the hub starts a new session when it hears of it
        client = self._session(alive.session)
        self._control.heartbeat(client)

    def _session_ended(self, session: str) -> bool:
        """Has the rig's dead-man ended ``session``? (Its lease lapsed while it moved
        or held an axis: the control lock stopped them; whatever the session sent
        before is void, and its later keep-alives do not revive it.)"""
        if session in self._ended:
            return True
        known = self._sessions.get(session)
        if known is not None and known[0].lapsing:
            self._ended[session] = time.monotonic()
            self._hub.on_event(
                "warning",
                None,
                f"hub session {session[:8]}: its keep-alives stopped while it moved an axis "
                "(the dead-man stopped it); nothing more it sent is run",
            )
            return True
        return False

    async def _on_manifest(self, msg: Msg) -> None:
        """A hub that hears this rig's presence but does not know it yet asks this."""
        with contextlib.suppress(NatsError):
            await msg.respond(self.manifest().model_dump_json().encode())

    async def _on_snapshot(self, msg: Msg) -> None:
        """What a hub needs when it (re)finds the rig: statuses and parameters."""
        messages = [m for m in self._hub.snapshot_messages() if '"type":"event"' not in m[:30]]
        await msg.respond(json.dumps(messages).encode())

    def _session(self, session: str) -> ControlClient:
        known = self._sessions.get(session)
        if known is not None:
            self._sessions[session] = (known[0], time.monotonic())
            return known[0]
        client = self._control.connect(self._principal, f"bus:{session[:8]}", lambda _: None)
        self._sessions[session] = (client, time.monotonic())
        return client

    def _forget_silent_sessions(self) -> None:
        now = time.monotonic()
        for session, (client, seen) in list(self._sessions.items()):
            if now - seen > SESSION_FORGET_S:
                del self._sessions[session]
                self._control.disconnect(client)
        for session, ended in list(self._ended.items()):
            if now - ended > SESSION_FORGET_S:
                del self._ended[session]

    async def _answer(self, msg: Msg, link: str, axis: str, verb: str) -> None:
        request: CommandRequest | None = None
        try:
            try:
                request = CommandRequest.model_validate_json(msg.data)
            except ValidationError as exc:
                raise _invalid(exc) from None
            self._admit(verb, request)
            nc = self._nc
            command = verb != subjects.STOP and verb not in subjects.READ_VERBS
            if command and msg.reply and nc is not None:
                # Taken: said before it runs (and on the server before the device is
                # touched), so a hub that hears nothing by the deadline knows it never
                # runs. Checked once more after, the flush may have taken long.
                await nc.publish(msg.reply, b"", headers={ACK_HEADER: "1"})
                await nc.flush(timeout=2)
                self._admit(verb, request)
            body = await self._execute(link, axis, verb, request)
        except NotRunError as exc:
            # Not run: counted apart (``not_run``), not among the verbs handled.
            self.not_run.append((verb, exc.kind))
            if msg.reply:
                with contextlib.suppress(NatsError):
                    await msg.respond(_error_reply(exc))
            return
        except (DriverError, HTTPException, UnknownAxisError) as exc:
            body = _error_reply(exc)
        except StorageError as exc:
            body = _reply(ok=False, kind="device", detail=str(exc))
        except (NatsError, TimeoutError) as exc:
            # The taken message could not go out: the request is not run.
            body = _reply(ok=False, kind="expired", detail=f"not run: the bus failed ({exc})")
        self.commands_handled += 1
        self.verbs_handled.append(verb)
        if request is not None and request.reply_by_s is not None:
            late_s = self._hub.now() - request.reply_by_s
            if late_s > 0 and b'"ok":true' in body[:12]:
                self._hub.on_event(
                    "warning",
                    self._axes.get((link, axis)),
                    f"{verb} from hub {request.hub} was done {late_s:.1f} s after the hub "
                    "stopped waiting for it (it may have shown it failed): it DID run",
                )
        if msg.reply:
            with contextlib.suppress(NatsError):
                await msg.respond(body)

    def _admit(self, verb: str, request: CommandRequest) -> None:
        """Run this request at all? ``NotRunError`` (and reported) if it came after its
        deadline, lacks one, or its hub session was ended by the dead-man."""
        if verb == subjects.STOP or verb in subjects.READ_VERBS:
            return  # a STOP always acts (unless overtaken); a read changes nothing
        now = self._hub.now()
        if request.deadline_s is None:
            raise NotRunError(
                "expired", f"{verb}: not run: a command needs a deadline (deadline_s)"
            )
        if now > request.deadline_s:
            sent = (
                f" {now - request.sent_s:.1f} s after it was sent,"
                if request.sent_s is not None
                else ""
            )
            detail = (
                f"{verb} from hub {request.hub} came{sent} {now - request.deadline_s:.1f} s "
                "after its deadline: dropped, nothing was sent (the hub reported it failed)"
            )
            self._hub.on_event("warning", None, detail)
            raise NotRunError("expired", detail)
        if self._session_ended(request.session):
            raise NotRunError(
                "session_ended",
                f"{verb}: not run: this hub session was ended by the rig's dead-man (its "
                "keep-alives stopped while it moved an axis; the axis was stopped)",
            )

    async def _execute(self, link: str, axis: str, verb: str, request: CommandRequest) -> bytes:
        """One request, exactly as the rig's REST route would run it."""
        axis_id = self._axes.get((link, axis))
        if axis_id is None:
            raise InvalidArgumentError("axis", f"no axis {axis!r} on link {link!r} of {self.rig}")
        principal = self._principal
        if verb == subjects.READ_PARAMS:
            self._need(principal, VIEW)
            return _reply(ok=True, result={"values": await self._hub.read_params(axis_id)})
        if verb == subjects.BENCH_RUNS:
            self._need(principal, VIEW)
            return _reply(ok=True, result={"runs": await self._rig_bench().list_runs(axis_id)})
        client = self._session(request.session)
        if verb in subjects.AUTOTUNE_VERBS:
            return await self._autotune(axis_id, verb, request, client, principal)
        if verb == subjects.BENCH_START:
            # The rig's bench route: its permission, the lock, then the bench's own
            # checks (the rig's limits, the plan against the descriptor) before anything
            # moves; the hub session becomes the axis' mover (its dead-man applies).
            self._need(principal, BENCH)
            bench = self._rig_bench()
            try:
                test = BenchTestRequest.model_validate(request.args)
            except ValidationError as exc:
                raise _invalid(exc) from None
            await self._control.require(axis_id, client.client_id, principal)
            run = await bench.start_run(axis_id, test)
            return _reply(ok=True, result={"run": run})
        if verb == subjects.WRITE_PARAMS:
            self._need(principal, TUNE)
            await self._control.require(axis_id, client.client_id, principal)
            values = await self._hub.write_params(axis_id, request.values)
            return _reply(ok=True, result={"values": values})
        if verb == subjects.CONSOLE:
            # The rig's console route: its permission and that of what the line is
            # (routes_table.console_permission: pg needs persist, ma move ...), the lock
            # unless it is a stop, the hub's line check (control characters refused
            # naming ``line``) and the driver's own refusals.
            self._need(principal, CONSOLE)
            line = request.args.get("line")
            if not isinstance(line, str):
                raise InvalidArgumentError("line", "line must be a string")
            try:
                needed = console_permission(self._hub.descriptor(axis_id), line)
            except UnknownConsoleLineError as exc:
                raise InvalidArgumentError("line", str(exc)) from None
            self._need(principal, needed)
            if needed != STOP:
                await self._control.require(axis_id, client.client_id, principal)
            try:
                sent, reply = await self._hub.console(axis_id, line)
            except (DeviceRefusedError, InvalidArgumentError, LinkDownError):
                raise
            except DriverError as exc:
                # As the rig's REST: an exchange error is an answer, shown with the line.
                return _reply(ok=True, result={"sent": line, "reply": [], "error": str(exc)})
            return _reply(ok=True, result={"sent": sent, "reply": reply, "error": None})
        permission = command_permission(self._hub.descriptor(axis_id), verb)
        self._need(principal, permission)
        if permission != STOP:
            # STOP is never locked (docs/control.md); every other command is.
            await self._control.require(axis_id, client.client_id, principal)
        elif request.pressed_s is not None:
            self._check_stop_current(axis_id, request)
        outcome = await self._hub.command(axis_id, verb, request.args)
        return _reply(ok=True, result={"sent": outcome.sent, "message": outcome.message})

    def _check_stop_current(self, axis_id: str, request: CommandRequest) -> None:
        """A hub STOP acts on the motion its user saw: not sent (``StopOvertakenError``,
        reported here too) when this axis was commanded or stopped after it was
        pressed (its local user moved it during a network cut, the dead-man stopped
        it); said when it was pressed if it comes late."""
        assert request.pressed_s is not None
        ago_s = self._hub.now() - request.pressed_s
        why = self._hub.stop_overtaken(axis_id, self._hub.clock_at(request.pressed_s))
        if why is not None:
            self._hub.on_event(
                "info",
                axis_id,
                f"STOP from hub {request.hub} (pressed {ago_s:.1f} s ago) not sent: {why}",
            )
            raise StopOvertakenError(why)
        if ago_s > 1.0:
            self._hub.on_event(
                "warning", axis_id, f"STOP from hub {request.hub}, pressed {ago_s:.1f} s ago"
            )

    async def _autotune(
        self,
        axis_id: str,
        verb: str,
        request: CommandRequest,
        client: ControlClient,
        principal: Principal,
    ) -> bytes:
        """The rig's auto-tune routes: their permission, the lock (the hub session
        becomes the axis' mover: its dead-man applies while the tests run), then the
        rig's own AutoTuner, which checks the limits against the rig's bench limits
        and the device before anything moves. The reply carries the rig's session so
        the hub can show it."""
        from servotune.autotune.session import IdentifyRequest  # the rig's own model

        tuner = self._autotuner
        if tuner is None:
            raise DeviceRefusedError(f"rig {self.rig} runs no auto-tune")
        self._need(principal, AUTOTUNE)
        if verb == subjects.AUTOTUNE_IDENTIFY:
            try:
                limits = IdentifyRequest.model_validate(request.args)
            except ValidationError as exc:
                raise _invalid(exc) from None
        await self._control.require(axis_id, client.client_id, principal)
        result: dict[str, Any]
        if verb == subjects.AUTOTUNE_IDENTIFY:
            result = await tuner.identify(axis_id, limits)
        elif verb == subjects.AUTOTUNE_ACCEPT:
            confirm = request.args.get("confirm_unstable") is True
            result = await tuner.accept(axis_id, confirm_unstable=confirm)
        elif verb == subjects.AUTOTUNE_KEEP:
            result = await tuner.keep(axis_id)
        else:
            result = dict(await tuner.revert(axis_id))
        return _reply(ok=True, result={"result": result, "session": tuner.session(axis_id)})

    def _rig_bench(self) -> TestBench:
        if self._bench is None:
            raise DeviceRefusedError(f"rig {self.rig} runs no test bench")
        return self._bench

    @staticmethod
    def _need(principal: Principal, permission: str) -> None:
        if permission not in principal.permissions:
            raise HTTPException(403, detail=f"not permitted over the bus: needs '{permission}'")

    # --- runs -------------------------------------------------------------------------

    async def _publish_runs(self) -> None:
        """Every finished run onto the runs stream, until the bus has acknowledged it."""
        assert self._nc is not None
        js = self._nc.jetstream()
        self._unpublished.update(await asyncio.to_thread(self._finished_runs))
        while True:
            for run_id in sorted(self._unpublished):
                record = await asyncio.to_thread(self._run_record, run_id)
                if record is None:
                    self._unpublished.discard(run_id)
                    continue
                try:
                    await js.publish(
                        subjects.runs(self.rig),
                        record.model_dump_json().encode(),
                        headers={"Nats-Msg-Id": f"{self.rig}/{run_id}"},
                        timeout=self._settings.request_timeout_s,
                    )
                except (NatsError, JetStreamError, TimeoutError) as exc:
                    logger.info("run %s not published yet (%s): retrying", run_id, exc)
                    break
                self._unpublished.discard(run_id)
                self._published.add(run_id)
                await asyncio.to_thread(
                    self._storage.set_meta, _PUBLISHED_META, sorted(self._published)
                )
            await asyncio.sleep(RUN_RETRY_S)

    def _finished_runs(self) -> list[str]:
        """Runs of this rig's axes not yet on the bus (worker thread)."""
        found = []
        for info in self._hub.axes_info():
            for run in self._storage.list_runs(self._hub.entry(info.id).storage_key):
                if run["status"] != "recording" and run["id"] not in self._published:
                    found.append(str(run["id"]))
        return found

    def _run_record(self, run_id: str) -> RunRecord | None:
        run = self._storage.get_run(run_id)
        if run is None or run["status"] == "recording":
            return None
        samples = run.pop("samples")
        axis_key = next(
            (
                self._hub.entry(i.id).storage_key
                for i in self._hub.axes_info()
                if i.id == run.get("axis_id")
            ),
            "",
        )
        return RunRecord(rig=self.rig, run=run, axis_key=axis_key, samples=samples)
