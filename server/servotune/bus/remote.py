"""The hub's view of a rig's links: ``link.base.Link``/``AxisDriver`` over NATS.

Registered into the ordinary ``Hub`` (``servotune hub``), so the api, the control lock
and the web client work unchanged: a remote axis is an axis. Every change is a NATS
request to the rig, which validates it again against its own descriptor, limits and
control lock (the hub is not trusted for safety); the rig's answer comes back as the
same error the rig's REST would give (``InvalidArgumentError`` naming the field, ...).

A rig that does not answer is offline at once: NATS answers a request nobody listens
to with a no-responders status (no timeout to wait for; the hub subscribes to nothing
it requests on), and a rig the safety lane has not heard for ``offline_after_s``
(``bus.lane``) is shown offline, its axes too, with every request refused before it
is sent.

A command carries its deadline (``CommandRequest``): the rig runs it only if it is
taken in time (``BusSettings.command_start_within_s``), and says so first. A hub that
hears nothing by then answers "not run" and is right: the rig drops what comes later.
One that heard "taken" but no outcome says "it may have run", and an outcome that
comes after the hub gave up is told as an event. Telemetry is judged by when it was
sampled, on the rig's clock as estimated from round trips (``bus.clock``): a sample
older than ``LIVE_MAX_AGE_S`` is not shown live (counted, and told), whatever the
presence says, so a rig's backlog after an outage never reaches the scope as now.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass

from nats.aio.client import Client
from nats.aio.msg import Msg
from nats.errors import Error as NatsError
from nats.errors import NoRespondersError
from nats.errors import TimeoutError as NatsTimeoutError
from pydantic import BaseModel, ValidationError

from servotune.bus import subjects
from servotune.bus.lane import RigLiveness, SafetyLane
from servotune.bus.messages import CommandReply, CommandRequest, RemoteAxisInfo, RemoteLinkInfo
from servotune.bus.replies import Call, ReplyMux
from servotune.descriptor import DeviceDescriptor
from servotune.hub.state import StopOvertakenError
from servotune.link.base import (
    AxisDriver,
    CommandOutcome,
    DeviceRefusedError,
    DeviceTimeoutError,
    DriverError,
    DriverSink,
    InvalidArgumentError,
    LinkDownError,
    ProtocolError,
    Sample,
)
from servotune.schema import LinkState, RunUpdate, Telemetry

logger = logging.getLogger(__name__)

# A sample older than this (sampled, on the hub's clock) when it reaches the hub is not
# shown live: the scope and the readouts show now, and a second is already long for
# an operator deciding on a STOP. Its loss is counted and told (``RemoteLink.counters``).
LIVE_MAX_AGE_S = 1.0
# After the rig's deadline the hub waits this much longer for "taken" before it says
# "not run" (the answer's way back, and the hub's own loop reading it).
TAKEN_GRACE_S = 1.0
# At most one event per link about samples not shown live or refused, this often.
NOTICE_PERIOD_S = 10.0


def hub_id(rig: str, local_id: str) -> str:
    """The hub's id of a rig's link or axis: ``<rig>.<id>`` (unique in the lab)."""
    return f"{rig}.{local_id}"


class RemoteLockedError(DeviceRefusedError):
    """The rig's control lock refused the change (its REST would answer 423)."""


class RemoteForbiddenError(DeviceRefusedError):
    """The rig does not allow this over the bus (its REST would answer 403)."""


class RemoteSessionEndedError(DeviceRefusedError):
    """The rig's dead-man ended the hub's session: not run (the hub starts a new one)."""


def raise_for_reply(rig: str, reply: CommandReply) -> None:
    """The rig's error reply as the exception the rig's own driver path raised."""
    if reply.ok:
        return
    detail = f"rig {rig}: {reply.detail}"
    if reply.kind == "invalid":
        raise InvalidArgumentError(reply.field or "body", reply.detail)
    if reply.kind == "locked":
        raise RemoteLockedError(detail)
    if reply.kind == "forbidden":
        raise RemoteForbiddenError(detail)
    if reply.kind == "refused":
        raise DeviceRefusedError(detail)
    if reply.kind == "link_down":
        raise LinkDownError(detail)
    if reply.kind == "timeout":
        raise DeviceTimeoutError(detail)
    if reply.kind == "protocol":
        raise ProtocolError(detail)
    if reply.kind == "expired":
        raise DeviceTimeoutError(f"{detail} (not run)")
    if reply.kind == "session_ended":
        raise RemoteSessionEndedError(f"{detail}; send it again")
    if reply.kind == "overtaken":
        raise StopOvertakenError(detail)
    raise DriverError(detail)


@dataclass(slots=True)
class BusPort:
    """What the remote drivers share: the connections and the timings.

    ``nc`` operates (commands, parameter writes, console; its answers through ``mux``),
    ``view_nc`` reads (parameter reads, snapshots; it may not publish a command:
    nats-server refuses it), ``lane`` stops (its own connection, loop and thread:
    ``bus.lane``). Each is its own NATS user (``accounts``); which one a request takes
    follows from the permission its verb needs at the hub, the same table the hub's
    REST checks its user against first."""

    nc: Client
    view_nc: Client
    lane: SafetyLane
    mux: ReplyMux
    hub_name: str
    request_timeout_s: float
    stop_timeout_s: float
    start_within_s: float = 3.0
    clock: Callable[[], float] = time.monotonic
    # Set when the hub shuts down: nothing more goes to the rigs (their own dead-man
    # stops what this hub set in motion once its keep-alives end).
    closing: bool = False


class RemoteAxis:
    """One axis of a rig, seen from the hub (``AxisDriver``)."""

    def __init__(self, link: RemoteLink, info: RemoteAxisInfo) -> None:
        self._link = link
        self.local_id = info.info.id
        self._id = hub_id(link.rig, info.info.id)
        self._name = f"{link.rig}: {info.info.name}"
        self._address = info.info.address
        self._descriptor = info.descriptor
        self._bench_kinds = list(info.bench_kinds)

    @property
    def id(self) -> str:
        return self._id

    @property
    def name(self) -> str:
        return self._name

    @property
    def address(self) -> int:
        return self._address

    @property
    def descriptor(self) -> DeviceDescriptor:
        return self._descriptor

    async def _request(
        self,
        verb: str,
        body: CommandRequest,
        timeout_s: float | None = None,
        pressed_at: float | None = None,
    ) -> dict[str, object]:
        return await self._link.request(
            subjects.axis_cmd(self._link.rig, self._link.local_id, self.local_id, verb),
            body,
            verb=verb,
            timeout_s=timeout_s,
            pressed_at=pressed_at,
            axis_id=self._id,
        )

    async def autotune(
        self, verb: str, args: Mapping[str, object], timeout_s: float
    ) -> dict[str, object]:
        """An auto-tune step run by the rig's own AutoTuner (``bus.autotune``): the
        rig's answer ``{result, session}``, or the rig's refusal raised."""
        return await self._request(verb, self._body(args=dict(args)), timeout_s)

    def _body(self, **fields: object) -> CommandRequest:
        port = self._link.port
        return CommandRequest(session=self._link.live.session, hub=port.hub_name, **fields)  # type: ignore[arg-type]

    async def read_params(self) -> dict[str, int]:
        result = await self._request(subjects.READ_PARAMS, self._body())
        return _int_values(result.get("values"))

    async def write_params(self, values: Mapping[str, int]) -> dict[str, int]:
        result = await self._request(subjects.WRITE_PARAMS, self._body(values=dict(values)))
        return _int_values(result.get("values"))

    async def command(self, name: str, args: Mapping[str, int]) -> CommandOutcome:
        pressed_at = self._link.port.clock() if name == subjects.STOP else None
        result = await self._request(name, self._body(args=dict(args)), pressed_at=pressed_at)
        sent = result.get("sent")
        return CommandOutcome(
            [str(s) for s in sent] if isinstance(sent, list) else [],
            str(result.get("message", "")),
        )

    async def console(self, line: str) -> tuple[str, list[str]]:
        """The line goes to the rig, which checks and sends it as its own console does;
        an exchange error the rig answered (no echo, ...) is raised as a DriverError,
        so the hub's console route shows it next to the line as the rig's would."""
        result = await self._request(subjects.CONSOLE, self._body(args={"line": line}))
        error = result.get("error")
        if error:
            raise DriverError(f"rig {self._link.rig}: {error}")
        reply = result.get("reply")
        lines = [str(r) for r in reply] if isinstance(reply, list) else []
        return str(result.get("sent", line)), lines

    async def stop(self) -> None:
        await self.stop_pressed(self._link.port.clock())

    async def stop_pressed(self, pressed_at: float) -> None:
        """The STOP pressed at ``pressed_at`` (hub clock; ``hub.stops.PressTimedStop``):
        the rig does not send it if its axis was commanded or stopped since
        (``StopOvertakenError``)."""
        await self._request(subjects.STOP, self._body(), pressed_at=pressed_at)

    # --- bench tests run on the rig (``bench.service.BenchDelegate``) ----------------------

    def bench_kinds(self) -> list[str]:
        return list(self._bench_kinds)

    async def bench_start(self, request: Mapping[str, object]) -> dict[str, object]:
        """Start a test on the rig: it plans, checks (its limits, its lock) and records
        it; the run arrives in the hub's store through the runs stream when done."""
        result = await self._request(subjects.BENCH_START, self._body(args=dict(request)))
        run = result.get("run")
        if not isinstance(run, dict):
            raise ProtocolError(f"rig {self._link.rig} answered a bench start without its run")
        return self._as_hub_run(run)

    async def bench_runs(self) -> list[dict[str, object]]:
        """The rig's runs of this axis (the hub lists those not collected yet), each
        marked ``on_rig``: not in the hub's store yet (its samples are on the rig)."""
        result = await self._request(subjects.BENCH_RUNS, self._body())
        runs = result.get("runs")
        if not isinstance(runs, list):
            raise ProtocolError(f"rig {self._link.rig} answered a run list without runs")
        return [self._as_hub_run(run) | {"on_rig": True} for run in runs if isinstance(run, dict)]

    def _as_hub_run(self, run: dict[str, object]) -> dict[str, object]:
        return {**run, "axis_id": self._id, "rig": self._link.rig}


def _int_values(values: object) -> dict[str, int]:
    if not isinstance(values, dict):
        raise ProtocolError("the rig's reply has no parameter values")
    return {str(k): int(v) for k, v in values.items()}


class RemoteLink:
    """One link of a rig, seen from the hub (``Link``); fed by ``HubBus``; its rig's
    liveness and clock come from the safety lane (``live``)."""

    def __init__(
        self,
        rig: str,
        info: RemoteLinkInfo,
        port: BusPort,
        sink: DriverSink,
        live: RigLiveness,
        broadcast: Callable[[BaseModel], None] | None = None,
    ) -> None:
        self.rig = rig
        self.live = live
        # To every hub tab: what the sink has no callback for (a bench run's progress).
        self._broadcast = broadcast
        self.local_id = info.info.id
        self.port = port
        self._sink = sink
        self._id = hub_id(rig, info.info.id)
        self._device = info.info.device
        self._path = f"nats:{rig}/{info.info.path}"
        self._baud = info.info.baud
        self._axes = [RemoteAxis(self, axis) for axis in info.axes]
        self._by_local = {axis.local_id: axis for axis in self._axes}
        self._state: LinkState = "connecting"
        # The rig's own link's wire_busy, as its last status said (HasWireBusy).
        self._wire_busy: float | None = None
        # Until then a rig not heard yet is "connecting", not announced offline: the
        # lane needs a presence and a clock probe first (a rig that just joined, or
        # every rig while the hub starts).
        self._judged_from = port.clock() + live.offline_after_s
        self._returns_seen = 0
        # Counters (``counters``: shown with the link's status).
        self.samples_live = 0
        self.samples_stale = 0
        self.samples_unclocked = 0
        self.batches_shed = 0
        self.refused = 0
        self._noticed: dict[str, float] = {}

    @property
    def id(self) -> str:
        return self._id

    @property
    def device(self) -> str:
        return self._device

    @property
    def path(self) -> str:
        return self._path

    @property
    def baud(self) -> int:
        return self._baud

    @property
    def axes(self) -> list[AxisDriver]:
        return list(self._axes)

    @property
    def remote_axes(self) -> list[RemoteAxis]:
        return self._axes

    @property
    def state(self) -> LinkState:
        return self._state

    @property
    def wire_busy(self) -> float | None:
        return self._wire_busy if self._state != "disconnected" else None

    @property
    def counters(self) -> Mapping[str, int]:
        """What the hub did not show live, and why (with the link's status)."""
        return {
            "samples_stale": self.samples_stale,
            "samples_unclocked": self.samples_unclocked,
            "batches_shed": self.batches_shed,
            "refused_not_its_own": self.refused,
        }

    def present(self) -> bool:
        return self.live.present(self.port.clock())

    async def request(
        self,
        subject: str,
        body: CommandRequest,
        *,
        verb: str,
        timeout_s: float | None = None,
        pressed_at: float | None = None,
        axis_id: str | None = None,
        renewed: bool = False,
    ) -> dict[str, object]:
        """A request to the rig; refused at once (LinkDownError) when the rig is offline.
        ``timeout_s``: for the long requests (auto-tune), else the port's;
        ``pressed_at``: a STOP's press time (hub clock); ``renewed``: sent again in a
        new session (once) because the rig's dead-man had ended the last one."""
        if self.port.closing:
            raise LinkDownError(
                f"the hub is shutting down: nothing sent to {self.rig} (the rig's own "
                "dead-man stops what this hub set in motion)"
            )
        if not self.present():
            raise LinkDownError(f"rig {self.rig} is offline: nothing was sent")
        now = self.port.clock()
        bounds = self.live.clock_bounds(now)
        if bounds is None:
            raise LinkDownError(f"rig {self.rig}: its clock is not known yet: nothing was sent")
        low, high = bounds
        if verb == subjects.STOP:
            # Rounded late: a command the rig ran before the press is never taken for
            # one after it (the STOP then acts on it).
            body.pressed_s = (now if pressed_at is None else pressed_at) + high
            msg = await self._plain(self.port.lane.request, subject, body, self.port.stop_timeout_s)
        elif verb in subjects.READ_VERBS:
            msg = await self._plain(self._view_request, subject, body, self.port.request_timeout_s)
        else:
            timeout = self.port.request_timeout_s if timeout_s is None else timeout_s
            start_by = now + self.port.start_within_s
            # Rounded early on the rig's clock: the rig never starts it later than the
            # hub allowed, and warns when it finishes after the hub may have given up.
            body.sent_s = now + (low + high) / 2
            body.deadline_s = start_by + low
            body.reply_by_s = now + timeout + low
            msg = await self._two_part(subject, body, verb, now, start_by, timeout, axis_id)
        reply = self._reply_of(msg)
        if reply.kind == "session_ended" and not renewed:
            # Not run: the rig's dead-man had ended this hub's session there (the axis
            # was stopped; its event says so). This request is the user's, sent now:
            # once more in a new session, with a new deadline.
            body.session = self.live.renew_session(body.session)
            return await self.request(
                subject,
                body,
                verb=verb,
                timeout_s=timeout_s,
                pressed_at=pressed_at,
                axis_id=axis_id,
                renewed=True,
            )
        raise_for_reply(self.rig, reply)
        return reply.result

    def _reply_of(self, msg: Msg) -> CommandReply:
        try:
            return CommandReply.model_validate_json(msg.data)
        except ValueError:
            raise ProtocolError(f"rig {self.rig} answered something that is not a reply") from None

    async def _view_request(self, subject: str, data: bytes, timeout_s: float) -> Msg:
        return await self.port.view_nc.request(subject, data, timeout=timeout_s)

    async def _plain(
        self,
        send: Callable[[str, bytes, float], Awaitable[Msg]],
        subject: str,
        body: CommandRequest,
        timeout_s: float,
    ) -> Msg:
        try:
            return await send(subject, body.model_dump_json().encode(), timeout_s)
        except NoRespondersError:
            raise LinkDownError(f"rig {self.rig} is offline (nobody answers on the bus)") from None
        except (NatsTimeoutError, TimeoutError):
            raise DeviceTimeoutError(f"rig {self.rig} did not answer in {timeout_s:g} s") from None
        except NatsError as exc:
            raise LinkDownError(f"the bus is down: {exc}") from None

    async def _two_part(
        self,
        subject: str,
        body: CommandRequest,
        verb: str,
        now: float,
        start_by: float,
        timeout_s: float,
        axis_id: str | None,
    ) -> Msg:
        """Send; wait for "taken" until the deadline (+ ``TAKEN_GRACE_S``), then for
        the outcome until ``timeout_s``; say which of the two did not come."""
        mux, clock = self.port.mux, self.port.clock
        call = mux.open(verb)
        try:
            await mux.publish(call, subject, body.model_dump_json().encode())
        except NatsError as exc:
            mux.close(call)
            raise LinkDownError(f"the bus is down: {exc}; nothing was sent") from None
        if not await _wait_taken(call, start_by + TAKEN_GRACE_S - clock()):
            mux.give_up(call, "not taken", self._late_reporter(axis_id))
            raise DeviceTimeoutError(
                f"rig {self.rig} did not take {verb} within {self.port.start_within_s:g} s: "
                "not run (the rig drops it if it comes later)"
            )
        if call.no_responders:
            mux.close(call)
            raise LinkDownError(
                f"rig {self.rig} is offline (nobody answers on the bus): nothing was sent"
            )
        try:
            msg = await asyncio.wait_for(
                asyncio.shield(call.outcome), max(0.0, now + timeout_s - clock())
            )
        except TimeoutError:
            mux.give_up(call, "no outcome", self._late_reporter(axis_id))
            raise DeviceTimeoutError(
                f"rig {self.rig} took {verb} but sent no outcome in {timeout_s:g} s: it may "
                "have run (check the axis; a late outcome is told)"
            ) from None
        mux.close(call)
        return msg

    def _late_reporter(self, axis_id: str | None) -> Callable[[Call, Msg], None]:
        def report(call: Call, msg: Msg) -> None:
            late_s = time.monotonic() - call.given_up_at
            try:
                reply = CommandReply.model_validate_json(msg.data)
            except ValidationError:
                return
            if reply.ok:
                text = (
                    f"rig {self.rig}: {call.verb}, reported as {call.given_up}, DID run "
                    f"(its outcome came {late_s:.1f} s later)"
                )
                self._sink.on_event("warning", axis_id, text)
            else:
                text = f"rig {self.rig}: {call.verb} ({call.given_up}): {reply.detail}"
                self._sink.on_event("info", axis_id, text)

        return report

    # --- fed by HubBus ----------------------------------------------------------------

    def on_telemetry(self, axis_token: str, data: bytes) -> None:
        """One telemetry batch of the rig's subject ``...<link>.<axis_token>.telemetry``.

        Attributed by the subject (nats-server lets the rig publish there only): a
        batch naming another axis is refused and logged. Each sample is dated on the
        hub's clock with the rig's clock estimate; one older than ``LIVE_MAX_AGE_S``
        is not shown live (counted, told at most every ``NOTICE_PERIOD_S``)."""
        if not self.present():
            return  # a late batch of a rig shown offline is not shown as live
        message = Telemetry.model_validate_json(data)
        axis = self._by_local.get(message.axis)
        if axis is None or message.axis != axis_token:
            self.refused += 1
            self._notice(
                "refused",
                "warning",
                f"rig {self.rig}: a telemetry batch on the subject of axis {axis_token!r} "
                f"names axis {message.axis!r}: refused",
            )
            return
        if not message.t:
            return
        now = self.port.clock()
        bounds = self.live.clock_bounds(now)
        if bounds is None:
            self.samples_unclocked += len(message.t)
            return
        offset = (bounds[0] + bounds[1]) / 2
        names = list(message.channels)
        flag_names = list(message.flags)
        stale = 0
        oldest_s = 0.0
        for index, t in enumerate(message.t):
            hub_t = t - offset
            age_s = now - hub_t
            if age_s > LIVE_MAX_AGE_S:
                stale += 1
                oldest_s = max(oldest_s, age_s)
                continue
            channels = {name: message.channels[name][index] for name in names}
            flags = {name: bool(message.flags[name][index]) for name in flag_names}
            self._sink.on_sample(axis.id, Sample(t=hub_t, channels=channels, flags=flags))
            self.samples_live += 1
        if stale:
            self.samples_stale += stale
            self._notice(
                "stale",
                "warning",
                f"rig {self.rig}: telemetry sampled up to {oldest_s:.1f} s ago not shown live "
                f"(older than {LIVE_MAX_AGE_S:g} s; {self.samples_stale} samples so far): the "
                "rig's own dashboard and its recorded runs have it",
            )

    def _notice(self, key: str, level: str, text: str) -> None:
        now = self.port.clock()
        if now - self._noticed.get(key, -NOTICE_PERIOD_S) < NOTICE_PERIOD_S:
            return
        self._noticed[key] = now
        logger.warning("%s", text)
        self._sink.on_event(level, None, text)  # type: ignore[arg-type]

    def on_message(self, message: dict[str, object]) -> None:
        """A status, parameter or event message of the rig (``servotune.schema`` JSON)."""
        kind = message.get("type")
        axis_local = message.get("axis")
        axis = self._by_local.get(str(axis_local)) if axis_local is not None else None
        if kind == "link_status" and message.get("link") == self.local_id:
            state = str(message.get("state"))
            self._state = state  # type: ignore[assignment]
            busy = message.get("wire_busy")
            self._wire_busy = float(busy) if isinstance(busy, int | float) else None
            self._sink.on_link_status(
                self._id,
                self._state,
                str(message.get("message", "")),
                float(message.get("rate_hz", 0.0)),  # type: ignore[arg-type]
                float(message.get("wire_limit_hz", 0.0)),  # type: ignore[arg-type]
                int(message.get("errors", 0)),  # type: ignore[call-overload]
            )
        elif kind == "axis_status" and axis is not None:
            health = str(message.get("health"))
            self._sink.on_axis_health(axis.id, health, str(message.get("message", "")))  # type: ignore[arg-type]
        elif kind == "params" and axis is not None:
            values = message.get("values")
            if isinstance(values, dict):
                source = str(message.get("source", "read"))
                self._sink.on_params(axis.id, {str(k): int(v) for k, v in values.items()}, source)
        elif kind == "run" and axis is not None and self._broadcast is not None:
            with contextlib.suppress(ValueError):
                self._broadcast(RunUpdate.model_validate({**message, "axis": axis.id}))
        elif kind == "event" and (axis is not None or axis_local is None):
            level = str(message.get("level", "info"))
            text = f"[{self.rig}] {message.get('message', '')}"
            self._sink.on_event(level, axis.id if axis else None, text)  # type: ignore[arg-type]

    def show_offline(self, why: str) -> None:
        self.live.shown_offline(self.port.clock())
        self._state = "disconnected"
        self._sink.on_link_status(self._id, "disconnected", why, 0.0, 0.0, 0)
        for axis in self._axes:
            self._sink.on_axis_health(axis.id, "offline", why)

    async def run(self) -> None:
        """Watch the rig's liveness: offline within ``offline_after_s`` of its silence,
        and back with a fresh snapshot (statuses, parameters) when it returns."""
        shown_offline = False
        while True:
            now = self.port.clock()
            if self.present():
                returns = self.live.returns
                if returns != self._returns_seen and await self._snapshot():
                    self._returns_seen = returns
                shown_offline = False
            elif (
                not shown_offline
                and now >= self._judged_from
                and self.port.lane.heard_until(self.live.seen_at + self.live.offline_after_s)
            ):
                seen_at = self.live.seen_at
                why = (
                    f"rig {self.rig} is offline (nothing heard for {now - seen_at:.1f} s)"
                    if seen_at
                    else f"rig {self.rig} is offline"
                )
                self.show_offline(why)
                shown_offline = True
            await asyncio.sleep(0.1)

    async def _snapshot(self) -> bool:
        subject = subjects.rig_cmd(self.rig, "snapshot")
        try:
            msg = await self.port.view_nc.request(
                subject, b"{}", timeout=self.port.request_timeout_s
            )
            messages = json.loads(msg.data)
        except (NatsError, TimeoutError, ValueError):
            await asyncio.sleep(0.5)  # tried again on the next turn
            return False
        for text in messages:
            self.on_message(json.loads(text))
        return True


async def _wait_taken(call: Call, timeout_s: float) -> bool:
    """Was ``call`` taken (or answered) within ``timeout_s``? Before saying no, the
    loop gets a few turns to read what already arrived: a hub whose loop was busy
    must not call "not run" what the rig took in time."""
    taken: asyncio.Future[object] = asyncio.ensure_future(call.taken.wait())
    outcome: asyncio.Future[object] = call.outcome  # type: ignore[assignment]
    try:
        await asyncio.wait(
            {taken, outcome}, timeout=max(0.0, timeout_s), return_when=asyncio.FIRST_COMPLETED
        )
    finally:
        taken.cancel()
    for _ in range(10):
        if call.taken.is_set() or call.outcome.done():
            return True
        await asyncio.sleep(0)
    return call.taken.is_set() or call.outcome.done()
