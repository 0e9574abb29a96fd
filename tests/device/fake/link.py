"""The fake servo's link and axis: a ``servotune.link.base.Link`` and ``AxisDriver``.

The link implements the Link Protocol itself, to show what the hub needs of a link and
nothing more (a real device builds on ``servotune.link.engine.LinkEngine`` for the
silence rule, counters and the wire's busy share). One owner task (``run``): open the
channel through the injected connector, probe (read the speed), then poll the position;
between two polls it runs the jobs the axis submits, a STOP before anything else, each
with the line to itself. A lost port is reported and reopened with backoff; jobs are
refused at once while the link is down (a motion must never be replayed later).
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections import deque
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass
from typing import TypeVar

from servotune.config import LinkSpec
from servotune.descriptor import DeviceDescriptor
from servotune.link.base import (
    AxisDriver,
    CommandOutcome,
    DeviceRefusedError,
    DeviceTimeoutError,
    DriverSink,
    LinkDownError,
    Sample,
    StopOutcome,
    check_console_line,
)
from servotune.link.engine import recent_rate_hz
from servotune.schema import LinkState
from servotune.transports.base import ByteChannel, Connector, LinkClosedError

from . import NAME, codec
from .descriptor import fake_descriptor

T = TypeVar("T")

REPLY_TIMEOUT_S = 0.5
POLL_PERIOD_S = 0.02
STATUS_PERIOD_S = 1.0
FAILED_POLLS_FOR_ERROR = 3
# One poll cycle on the wire: "R\n" out, "P<up to 8 digits> 0\n" back, 10 bits a character.
POLL_CHARACTERS = len(b"R\n") + len(b"P00000000 0\n")


@dataclass(slots=True)
class _Job:
    run: Callable[[], Awaitable[object]]
    future: asyncio.Future[object]


class FakeLink:
    """One fake servo on one serial line (see the module docstring)."""

    device = NAME

    def __init__(self, spec: LinkSpec, connector: Connector, sink: DriverSink) -> None:
        self._spec = spec
        self._connector = connector
        self._sink = sink
        self._state: LinkState = "connecting"
        self._message = ""
        self._errors = 0
        self._channel: ByteChannel | None = None
        self._decoder = codec.LineDecoder()
        self._urgent: deque[_Job] = deque()
        self._normal: deque[_Job] = deque()
        self._wakeup = asyncio.Event()
        self._sample_times: deque[float] = deque(maxlen=256)
        self._axis = FakeAxis(self, spec.names.get(0, "Fake servo"))

    # --- Link ---------------------------------------------------------------------------

    @property
    def id(self) -> str:
        return self._spec.link_id

    @property
    def path(self) -> str:
        return self._spec.path

    @property
    def baud(self) -> int:
        return self._spec.baud

    @property
    def axes(self) -> list[AxisDriver]:
        return [self._axis]

    @property
    def state(self) -> LinkState:
        return self._state

    @property
    def sink(self) -> DriverSink:
        return self._sink

    async def run(self) -> None:
        backoff_s = 0.25
        while True:
            try:
                channel = await self._connector.open()
            except LinkClosedError as exc:
                self._set_state("error", str(exc))
                await asyncio.sleep(backoff_s)
                backoff_s = min(2 * backoff_s, 5.0)
                continue
            self._channel = channel
            try:
                await self._session(channel)
            except LinkClosedError as exc:
                self._sink.on_event("error", None, f"{self.id}: link lost: {exc}")
                self._set_state("reconnecting", f"link lost: {exc}")
            finally:
                self._channel = None
                self._fail_jobs(LinkDownError(f"link {self.id} is down"))
                self._sink.on_axis_health(self._axis.id, "offline", "link down")
                with contextlib.suppress(Exception):
                    await channel.close()
            await asyncio.sleep(backoff_s)

    # --- the owner task -----------------------------------------------------------------

    async def _session(self, channel: ByteChannel) -> None:
        while not isinstance(speed := await self.exchange(codec.make_read_speed()), codec.Speed):
            self._set_state("error", "the fake servo does not answer")
            await asyncio.sleep(REPLY_TIMEOUT_S)
        self._sink.on_params(self._axis.id, {"speed": speed.counts_s}, "read")
        self._set_state("connected", self.path)
        self._sink.on_axis_health(self._axis.id, "ok", "")
        failed = 0
        published = time.monotonic()
        while True:
            job = self._urgent.popleft() if self._urgent else None
            job = job or (self._normal.popleft() if self._normal else None)
            if job is not None:
                await self._run_job(job)
                continue
            reply = await self.exchange(codec.make_read())
            if isinstance(reply, codec.Position):
                now = time.monotonic()
                self._sample_times.append(now)
                channels = {"position": float(reply.counts)}
                self._sink.on_sample(self._axis.id, Sample(now, channels, {"moving": reply.moving}))
                failed = 0
                if self._state != "connected":
                    self._set_state("connected", self.path)
            else:
                self._errors += 1
                failed += 1
                if failed >= FAILED_POLLS_FOR_ERROR:
                    self._set_state("error", f"no answer to {failed} polls in a row")
            if time.monotonic() - published >= STATUS_PERIOD_S:
                published = time.monotonic()
                self._publish_status()
            if not self._urgent and not self._normal:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._wakeup.wait(), POLL_PERIOD_S)
            self._wakeup.clear()

    async def exchange(self, request: bytes) -> codec.Reply | None:
        """``request`` out, its reply back (None: no reply within REPLY_TIMEOUT_S).
        Owner task only. Anything late from an earlier exchange is dropped first."""
        channel = self._channel
        if channel is None:
            raise LinkDownError(f"link {self.id} is down")
        channel.discard_input()
        self._decoder = codec.LineDecoder()
        await channel.write(request)
        deadline = time.monotonic() + REPLY_TIMEOUT_S
        while (left_s := deadline - time.monotonic()) > 0:
            replies = self._decoder.feed(await channel.read_available(left_s))
            if replies:
                return replies[0]
        return None

    async def submit(self, run: Callable[[], Awaitable[T]], *, urgent: bool = False) -> T:
        """Run ``run()`` on the owner task with the line to itself (``urgent``: before
        every queued job and poll). LinkDownError at once while the link is down."""
        if self._channel is None:
            raise LinkDownError(f"link {self.id} is down: nothing was sent")
        future: asyncio.Future[object] = asyncio.get_running_loop().create_future()
        (self._urgent if urgent else self._normal).append(_Job(run, future))
        self._wakeup.set()
        return await future  # type: ignore[return-value]

    async def _run_job(self, job: _Job) -> None:
        try:
            result = await job.run()
        except LinkClosedError as exc:
            job.future.set_exception(LinkDownError(f"link {self.id} lost: {exc}"))
            raise
        except Exception as exc:
            job.future.set_exception(exc)
        else:
            job.future.set_result(result)

    def _fail_jobs(self, error: Exception) -> None:
        while self._urgent or self._normal:
            job = (self._urgent or self._normal).popleft()
            if not job.future.done():
                job.future.set_exception(error)

    # --- status -------------------------------------------------------------------------

    def _set_state(self, state: LinkState, message: str) -> None:
        if (state, message) != (self._state, self._message):
            self._state, self._message = state, message
            self._publish_status()

    def _publish_status(self) -> None:
        rate_hz = recent_rate_hz(self._sample_times, time.monotonic())
        limit_hz = self.baud / 10 / POLL_CHARACTERS
        self._sink.on_link_status(
            self.id, self._state, self._message, rate_hz, limit_hz, self._errors
        )


class FakeAxis:
    """The fake servo's one axis (a ``servotune.link.base.AxisDriver``)."""

    def __init__(self, link: FakeLink, name: str) -> None:
        self._link = link
        self._name = name
        self._descriptor = fake_descriptor()

    @property
    def id(self) -> str:
        return f"{self._link.id}-0"

    @property
    def name(self) -> str:
        return self._name

    @property
    def address(self) -> int:
        return 0

    @property
    def descriptor(self) -> DeviceDescriptor:
        return self._descriptor

    async def _ask(self, request: bytes) -> codec.Reply:
        reply = await self._link.exchange(request)
        if reply is None:
            raise DeviceTimeoutError(f"{self.id}: no reply to {request.decode().strip()!r}")
        if isinstance(reply, codec.Refused):
            raise DeviceRefusedError(f"{self.id}: {request.decode().strip()!r} was refused")
        return reply

    async def _read_speed(self) -> int:
        reply = await self._ask(codec.make_read_speed())
        if not isinstance(reply, codec.Speed):
            raise DeviceTimeoutError(f"{self.id}: {reply} is no speed")
        return reply.counts_s

    async def read_params(self) -> dict[str, int]:
        values = {"speed": await self._link.submit(self._read_speed)}
        self._link.sink.on_params(self.id, values, "read")
        return values

    async def write_params(self, values: Mapping[str, int]) -> dict[str, int]:
        async def write() -> dict[str, int]:
            if "speed" in values:
                await self._ask(codec.make_set_speed(values["speed"]))
            return {"speed": await self._read_speed()}

        read_back = await self._link.submit(write)
        self._link.sink.on_params(self.id, read_back, "write")
        return read_back

    async def command(self, name: str, args: Mapping[str, int]) -> CommandOutcome:
        if name == "stop":
            outcome = await self.stop()
            return CommandOutcome(outcome.sent, outcome.message)
        if name != "move_absolute":
            raise DeviceRefusedError(f"{self.id}: no command {name!r}")
        request = codec.make_move(args["position"])
        await self._link.submit(lambda: self._ask(request))
        return CommandOutcome([request.decode().strip()], "sent")

    async def console(self, line: str) -> tuple[str, list[str]]:
        check_console_line(line)
        reply = await self._link.submit(lambda: self._link.exchange(f"{line}\n".encode()))
        return line, [] if reply is None else [codec.encode_reply(reply).decode().strip()]

    async def stop(self) -> StopOutcome:
        await self._link.submit(lambda: self._ask(codec.make_stop()), urgent=True)
        return StopOutcome(["S"], "hold", "stopped where it is, held")
