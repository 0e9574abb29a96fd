"""The hub's view of a rig's links: ``drivers.base.Link``/``AxisDriver`` over NATS.

Registered into the ordinary ``Hub`` (``servotune hub``), so the api, the control lock
and the web client work unchanged: a remote axis is an axis. Every change is a NATS
request to the rig, which validates it again against its own descriptor, limits and
control lock (the hub is not trusted for safety); the rig's answer comes back as the
same error the rig's REST would give (``InvalidArgumentError`` naming the field, ...).

A rig that does not answer is offline at once: NATS answers a request nobody listens
to with ``NoRespondersError`` (no timeout to wait for), and a rig whose presence has
been silent for ``offline_after_s`` is shown offline, its axes too, with every request
refused before it is sent. Telemetry of a rig is never replayed as if it were live.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from nats.aio.client import Client
from nats.errors import Error as NatsError
from nats.errors import NoRespondersError
from nats.errors import TimeoutError as NatsTimeoutError
from pydantic import BaseModel

from servotune.bus import subjects
from servotune.bus.messages import CommandReply, CommandRequest, RemoteAxisInfo, RemoteLinkInfo
from servotune.descriptor import DeviceDescriptor
from servotune.drivers.base import (
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
from servotune.wire import LinkState, RunUpdate, Telemetry


def hub_id(rig: str, local_id: str) -> str:
    """The hub's id of a rig's link or axis: ``<rig>.<id>`` (unique in the lab)."""
    return f"{rig}.{local_id}"


class RemoteLockedError(DeviceRefusedError):
    """The rig's control lock refused the change (its REST would answer 423)."""


class RemoteForbiddenError(DeviceRefusedError):
    """The rig does not allow this over the bus (its REST would answer 403)."""


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
    raise DriverError(detail)


# A presence's lateness at the hub (RemoteLink.on_presence) is judged against the
# quickest delivery of the presences of the last PRESENCE_BASELINE_S (the clocks'
# drift over that time is microseconds); a presence more than
# PRESENCE_MAX_LATENESS_S late is another clock (the rig's machine rebooted).
PRESENCE_BASELINE_S = 30.0
PRESENCE_MAX_LATENESS_S = 10.0


@dataclass(slots=True)
class BusPort:
    """What the remote drivers share: the connections, the session, liveness.

    ``nc`` operates (commands, parameter writes, console), ``view_nc`` reads (parameter
    reads, snapshots; it may not publish a command: nats-server refuses it), ``stop_nc``
    stops. Each is its own NATS user (``accounts``); which one a request takes follows
    from the permission its verb needs at the hub (``connection_for``), the same table
    the hub's REST checks its user against first."""

    nc: Client
    stop_nc: Client
    session: str
    hub_name: str
    request_timeout_s: float
    stop_timeout_s: float
    clock: Callable[[], float] = time.monotonic
    # Set when the hub shuts down: nothing more goes to the rigs (their own dead-man
    # stops what this hub set in motion once its keep-alives end).
    closing: bool = False
    view_nc: Client | None = None

    def connection_for(self, verb: str) -> Client:
        if verb == subjects.STOP:
            return self.stop_nc
        if verb in subjects.READ_VERBS:
            return self.view_nc or self.nc
        return self.nc


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
        self, verb: str, body: CommandRequest, timeout_s: float | None = None
    ) -> dict[str, object]:
        return await self._link.request(
            subjects.axis_cmd(self._link.rig, self._link.local_id, self.local_id, verb),
            body,
            verb=verb,
            timeout_s=timeout_s,
        )

    async def autotune(
        self, verb: str, args: Mapping[str, object], timeout_s: float
    ) -> dict[str, object]:
        """An auto-tune step run by the rig's own AutoTuner (``bus.autotune``): the
        rig's answer ``{result, session}``, or the rig's refusal raised."""
        return await self._request(verb, self._body(args=dict(args)), timeout_s)

    def _body(self, **fields: object) -> CommandRequest:
        port = self._link.port
        return CommandRequest(session=port.session, hub=port.hub_name, **fields)  # type: ignore[arg-type]

    async def read_params(self) -> dict[str, int]:
        result = await self._request(subjects.READ_PARAMS, self._body())
        return _int_values(result.get("values"))

    async def write_params(self, values: Mapping[str, int]) -> dict[str, int]:
        result = await self._request(subjects.WRITE_PARAMS, self._body(values=dict(values)))
        return _int_values(result.get("values"))

    async def command(self, name: str, args: Mapping[str, int]) -> CommandOutcome:
        result = await self._request(name, self._body(args=dict(args)))
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
        await self._request(subjects.STOP, self._body())

    # --- bench tests run on the rig (``testbench.BenchDelegate``) ----------------------

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
    """One link of a rig, seen from the hub (``Link``); fed by ``HubBus``."""

    def __init__(
        self,
        rig: str,
        info: RemoteLinkInfo,
        port: BusPort,
        sink: DriverSink,
        offline_after_s: float,
        broadcast: Callable[[BaseModel], None] | None = None,
    ) -> None:
        self.rig = rig
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
        self._offline_after_s = offline_after_s
        # Hub clock of the rig's last presence; 0: never seen since the hub started.
        self.seen_at = 0.0
        self.online = False
        # Rig clock -> hub clock: hub_t = rig_t + offset, from the last telemetry batch.
        self._offset: float | None = None
        # (hub clock, hub clock - rig clock) of the presences of the last
        # PRESENCE_BASELINE_S: the smallest difference is the clocks' offset plus the
        # quickest delivery; a presence above it came that much late (see on_presence).
        self._presence_delays: deque[tuple[float, float]] = deque()
        # Hub clock when the rig was last shown offline: a presence sent before that
        # is old news and does not bring it back (None: shown present since).
        self._offline_at: float | None = None
        self.snapshot_wanted = asyncio.Event()

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

    def present(self) -> bool:
        return self.online and self.port.clock() - self.seen_at <= self._offline_after_s

    async def request(
        self, subject: str, body: CommandRequest, *, verb: str, timeout_s: float | None = None
    ) -> dict[str, object]:
        """A request to the rig; refused at once (LinkDownError) when the rig is offline.
        ``timeout_s``: for the long requests (auto-tune), else the port's."""
        if self.port.closing:
            raise LinkDownError(
                f"the hub is shutting down: nothing sent to {self.rig} (the rig's own "
                "dead-man stops what this hub set in motion)"
            )
        if not self.present():
            raise LinkDownError(f"rig {self.rig} is offline: nothing was sent")
        nc = self.port.connection_for(verb)
        stop = verb == subjects.STOP
        timeout = self.port.stop_timeout_s if stop else self.port.request_timeout_s
        if timeout_s is not None:
            timeout = timeout_s
        try:
            msg = await nc.request(subject, body.model_dump_json().encode(), timeout=timeout)
        except NoRespondersError:
            raise LinkDownError(f"rig {self.rig} is offline (nobody answers on the bus)") from None
        except NatsTimeoutError:
            raise DeviceTimeoutError(f"rig {self.rig} did not answer in {timeout:g} s") from None
        except NatsError as exc:
            raise LinkDownError(f"the bus is down: {exc}") from None
        try:
            reply = CommandReply.model_validate_json(msg.data)
        except ValueError:
            raise ProtocolError(f"rig {self.rig} answered something that is not a reply") from None
        raise_for_reply(self.rig, reply)
        return reply.result

    # --- fed by HubBus ----------------------------------------------------------------

    def on_presence(self, rig_now: float | None = None) -> None:
        """The rig is there. ``rig_now``: the rig machine's monotonic clock when it
        sent this presence (header ``St-Rig-Mono``).

        A presence the hub takes in late (its loop was held up, e.g. on a loaded
        machine) is dated back by that lateness: it must not show a rig that went
        silent present again (the hub would then send it requests that time out,
        instead of refusing them at once; seen in CI). The lateness is how much the
        clock difference exceeds the smallest one of the last PRESENCE_BASELINE_S,
        so neither the clocks' offset nor their drift matters. And once the rig was
        shown offline, only a presence sent after that brings it back: one sent
        before is old news (the state would flap, and a request sent in that
        window waits for its timeout)."""
        now = self.port.clock()
        seen = now
        if rig_now is not None:
            delays = self._presence_delays
            delays.append((now, now - rig_now))
            while delays and now - delays[0][0] > PRESENCE_BASELINE_S:
                delays.popleft()
            lateness_s = delays[-1][1] - min(delay for _, delay in delays)
            if lateness_s > PRESENCE_MAX_LATENESS_S:
                # Not a late message but another clock (the rig restarted on a machine
                # that rebooted): start the baseline again.
                delays.clear()
                delays.append((now, now - rig_now))
                lateness_s = 0.0
            seen = now - lateness_s
        if seen <= self.seen_at:
            return  # no news: an older presence than the last one counted
        if self._offline_at is not None and seen <= self._offline_at:
            return  # sent before the rig was shown offline
        was = self.present()
        self.seen_at = seen
        self.online = True
        if self.present():
            self._offline_at = None
            if not was:
                self.snapshot_wanted.set()

    def on_gone(self) -> None:
        """The rig deleted its presence (a graceful stop): offline now."""
        self.online = False

    def on_telemetry(self, data: bytes, rig_now: float | None) -> None:
        if not self.present():
            return  # a late batch of a rig shown offline is not shown as live
        message = Telemetry.model_validate_json(data)
        axis = self._by_local.get(message.axis)
        if axis is None or not message.t:
            return
        now = self.port.clock()
        if rig_now is not None:
            self._offset = now - rig_now
        offset = self._offset if self._offset is not None else now - message.t[-1]
        names = list(message.channels)
        flag_names = list(message.flags)
        for index, t in enumerate(message.t):
            channels = {name: message.channels[name][index] for name in names}
            flags = {name: bool(message.flags[name][index]) for name in flag_names}
            # The hub's Sample times are on its own clock; samples keep their spacing.
            self._sink.on_sample(axis.id, Sample(t=t + offset, channels=channels, flags=flags))

    def on_message(self, message: dict[str, object]) -> None:
        """A status, parameter or event message of the rig (``servotune.wire`` JSON)."""
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
        self._offline_at = self.port.clock()
        self._state = "disconnected"
        self._sink.on_link_status(self._id, "disconnected", why, 0.0, 0.0, 0)
        for axis in self._axes:
            self._sink.on_axis_health(axis.id, "offline", why)

    async def run(self) -> None:
        """Watch the rig's presence: offline within ``offline_after_s`` of its silence,
        and back with a fresh snapshot (statuses, parameters) when it returns."""
        shown_offline = False
        while True:
            if self.present():
                if self.snapshot_wanted.is_set():
                    self.snapshot_wanted.clear()
                    await self._snapshot()
                shown_offline = False
            elif not shown_offline:
                silent = self.port.clock() - self.seen_at if self.seen_at else None
                why = (
                    f"rig {self.rig} is offline (no presence for {silent:.1f} s)"
                    if silent is not None and self.online
                    else f"rig {self.rig} is offline"
                )
                self.show_offline(why)
                shown_offline = True
            await asyncio.sleep(0.1)

    async def _snapshot(self) -> None:
        subject = subjects.rig_cmd(self.rig, "snapshot")
        try:
            nc = self.port.view_nc or self.port.nc
            msg = await nc.request(subject, b"{}", timeout=self.port.request_timeout_s)
            messages = json.loads(msg.data)
        except (NatsError, ValueError):
            self.snapshot_wanted.set()  # try again on the next turn
            await asyncio.sleep(0.5)
            return
        for text in messages:
            self.on_message(json.loads(text))
