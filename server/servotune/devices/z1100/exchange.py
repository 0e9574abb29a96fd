"""The Z1100 exchange: one request, one reply on the chip's line (owner task only).

``Z1100Exchange`` sends a request and returns its reply, retrying and bringing the
line back in step as below; it stamps the moment the chip latched the reply's data
(``last_latch_t``) and notes a stall bit (``stall_noted``). ``Z1100Link``
(``devices.z1100.link``) has one and decides what to poll.

Rules (``shared/spec/z1100.md``), and decisions where it is silent:

* One request, one reply, 100 ms reply timeout. Stale input is flushed before every
  request (line noise can make the chip send a reply nobody asked for; it is counted
  and logged). A reply with a bad checksum is skipped by the decoder, so it ends as a
  timeout; a timeout, or a reply with bit 0 (the chip saw a bad checksum), bit 2
  (packet incomplete) or bit 3 (line noise) is retried, up to ``retries`` attempts.
* Bit 7 (stall) rides on valid data: the reply is used and a stall is noted; the next
  GetStop says which motor.
* Bits 4..6 (forbidden while motor n moves) become a ``DeviceRefusedError`` with the
  chip's reason. The server refuses first when it knows the axis moves (GetStart).
  A Start whose reply was lost and whose retry is refused as "moving" did start: the
  retry is taken as success.
* A Get can never be "forbidden while moving", nor unknown to the chip: a reply with
  those bits to a Get is the reply to *another* request (a late one: replies have no
  header). Nor is a known Set ever "unknown". Either is a desynchronisation: counted
  (``desyncs``) and retried after a resynchronisation. Never a refusal, never the end
  of a session.
* Resynchronisation (before every retry, after a failed poll, and before a reset cue is
  confirmed) is a *fence*: a command byte the chip does not know
  (``codec.make_fence``), which it answers in order with reply bit 1. Every reply that
  arrives before that answer was late and is dropped; once it is in, the line is in
  step. Waiting for a quiet line instead proves nothing on a starved host, where late
  replies trickle in behind their requests (a GetError 0 read late would be taken for
  a reset witness). A fence unanswered within ``fence_timeout_s`` is counted
  (``fence_timeouts``) and the line is then left to go quiet for a reply timeout.
* Every sample is stamped with the moment the chip latched it: it answers a request
  once the request is complete, so the latch is the write time plus the request's 7
  characters on the wire (bounded by the reply's arrival less its 6 characters), not
  the time the reply was parsed.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Protocol

from servotune.devices.z1100 import codec
from servotune.devices.z1100.codec import request_name
from servotune.link.base import DeviceRefusedError, DeviceTimeoutError, ProtocolError
from servotune.link.engine import LinkEngine
from servotune.transports.base import ByteChannel

RETRYABLE = codec.ReplyCode.CHECKSUM | codec.ReplyCode.TIMEOUT | codec.ReplyCode.COMMUNICATION
MOVING_BITS = codec.ReplyCode.MOVING_1 | codec.ReplyCode.MOVING_2 | codec.ReplyCode.MOVING_3
TRANSACTION_CHARS = codec.REQUEST_SIZE + codec.REPLY_SIZE


class ExchangeSettings(Protocol):
    """The settings the exchange needs (``Z1100LinkConfig`` has them)."""

    @property
    def baud(self) -> int: ...
    @property
    def reply_timeout_s(self) -> float: ...
    @property
    def retries(self) -> int: ...
    @property
    def fence_timeout_s(self) -> float: ...


class Z1100Exchange:
    """Requests and replies on one Z1100 line through its ``engine``'s channel; see the
    module docstring. ``transactions`` counts the requests written, ``last_latch_t``
    is when the chip latched the last reply's data (the link's clock)."""

    def __init__(
        self,
        settings: ExchangeSettings,
        engine: LinkEngine,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._settings = settings
        self._engine = engine
        self._clock = clock
        self.transactions = 0
        self.last_latch_t = 0.0
        # A reply carried the stall bit: the link reads GetStop next and clears it.
        self.stall_noted = False

    async def request(self, request: codec.Request) -> codec.Reply:
        """Send one request and return its reply; retries per the module docstring."""
        channel = self._engine.require_channel()
        packet = request.encode()
        name = request_name(request)
        last_problem = "no reply"
        is_get = request.command is not None and request.command.is_get
        for attempt in range(self._settings.retries):
            if attempt:
                # Replies have no header, and a rotation of a valid reply sums to 0 as
                # well: a late reply to the failed attempt, or its tail plus the head
                # of the next reply, would decode as a wrong but "valid" reply. So
                # before a retry the line is brought back in step with a fence.
                self._engine.count("retries")
                await self.resync(channel)
            stray = channel.discard_input()
            if stray:
                # Late bytes (of a reply that timed out, or noise): counted and shown
                # in the link's counters, not an event each time.
                self._engine.add_error()
                self._engine.count("dropped_bytes", len(stray))
            channel.take_timeout_late_s()  # only this attempt's own timeout may excuse it
            written = self._clock()
            await channel.write(packet)
            got = await self._read_reply(channel)
            self.transactions += 1
            char_s = 10 / self._settings.baud
            # The request's characters, and the reply's if one came (wire_busy).
            self._engine.wire_used((TRANSACTION_CHARS if got else codec.REQUEST_SIZE) * char_s)
            if got is None:
                self._engine.add_error()
                last_problem = (
                    f"no valid reply within {self._settings.reply_timeout_s * 1000:.0f} ms"
                )
                self._engine.unanswered_request(self._settings.reply_timeout_s)
                continue
            reply, reply_t = got
            self._engine.answered()
            self.last_latch_t = min(
                written + codec.REQUEST_SIZE * char_s, reply_t - codec.REPLY_SIZE * char_s
            )
            if reply.code & RETRYABLE:
                self._engine.add_error()
                last_problem = codec.error_message(reply.code) or "rejected"
                continue
            if is_get and reply.code & (codec.ReplyCode.UNKNOWN_COMMAND | MOVING_BITS):
                # Impossible for a Get: this reply answered another request.
                self._engine.add_error()
                self._engine.count("desyncs")
                last_problem = (
                    f"reply 0x{int(reply.code):02X} belongs to another request "
                    f"({codec.error_message(reply.code) or 'unknown command'})"
                )
                continue
            if reply.code & codec.ReplyCode.UNKNOWN_COMMAND and request.command is None:
                raise ProtocolError(f"{name}: the chip does not know this command")
            if reply.code & codec.ReplyCode.UNKNOWN_COMMAND:
                # Every known command is known to the chip: this is the (late) answer
                # to a fence, and the Set's own reply is still to come. Not executed
                # as far as we know: retried after a resynchronisation.
                self._engine.add_error()
                self._engine.count("desyncs")
                last_problem = "the reply to a fence came instead of this command's"
                continue
            if reply.code & MOVING_BITS:
                if attempt > 0 and request.command is codec.Command.SET_START:
                    return codec.Reply(codec.ReplyCode.OK)  # the lost first Start ran
                raise DeviceRefusedError(f"{name}: refused, {codec.error_message(reply.code)}")
            if reply.stall:
                self.stall_noted = True
            return reply
        raise DeviceTimeoutError(f"{name}: {last_problem} after {self._settings.retries} tries")

    async def resync(self, channel: ByteChannel) -> bool:
        """Bring the line back in step: send a fence and drop every reply that arrives
        before its answer (those answered earlier requests). The chip answers in order,
        so after the fence's answer nothing late is left on the line: True. Falls back
        to a quiet line when the fence itself goes unanswered within
        ``fence_timeout_s``: False, and a late reply may still be on its way."""
        stray = channel.discard_input()
        if stray:
            self._engine.add_error()
            self._engine.count("dropped_bytes", len(stray))
        await channel.write(codec.make_fence().encode())
        decoder = codec.ReplyDecoder()
        deadline = self._clock() + self._settings.fence_timeout_s
        heard = False  # any byte at all: the chip is alive, only late or noisy
        while True:
            remaining = max(deadline - self._clock(), 0.0)
            data = await channel.read_available(remaining)
            if not data:
                break
            heard = True
            for reply in decoder.feed(data):
                if codec.is_fence_reply(reply):
                    if decoder.pending:  # bytes after the answer: noise, dropped
                        self._engine.count("dropped_bytes", decoder.pending)
                    self._engine.answered()
                    return True
                self._engine.add_error()
                self._engine.count("dropped_bytes", codec.REPLY_SIZE)  # a late reply
            if remaining <= 0:
                break
        self._engine.add_error()
        self._engine.count("fence_timeouts")
        if not heard:
            self._engine.unanswered_request(self._settings.fence_timeout_s)
        await self._drain_quiet(channel)
        return False

    async def _drain_quiet(self, channel: ByteChannel) -> None:
        deadline = self._clock() + 1.0
        while self._clock() < deadline:
            data = await channel.read_available(self._settings.reply_timeout_s)
            if not data:
                return
            self._engine.add_error()
            self._engine.count("dropped_bytes", len(data))

    async def _read_reply(self, channel: ByteChannel) -> tuple[codec.Reply, float] | None:
        """The first valid reply within the reply timeout and the moment its last byte
        came (stamped in the receive callback where the channel can, else when this
        task resumed), or ``None``."""
        decoder = codec.ReplyDecoder()
        deadline = self._clock() + self._settings.reply_timeout_s
        while True:
            # Past the deadline, still take what is already buffered (once): on a host
            # that was stalled the reply may have arrived while nobody looked.
            remaining = max(deadline - self._clock(), 0.0)
            # Wait for a whole reply's worth in one wake-up (the line delivers it a
            # character at a time: 6 wake-ups per reply cost more than the rest).
            need = max(codec.REPLY_SIZE - decoder.pending, 1)
            data, t_s = await channel.read_at_least(need, remaining)
            if not data:
                return None
            replies = decoder.feed(data)
            if replies:
                return replies[0], self._clock() if t_s is None else t_s
            if remaining <= 0:
                return None

    async def get(self, command: codec.Command, axis: int | None = None) -> codec.GetValue:
        reply = await self.request(codec.make_get(command, axis))
        return codec.decode_get(command, reply.data)

    async def get_int(self, command: codec.Command, axis: int | None = None) -> int:
        value = await self.get(command, axis)
        assert isinstance(value, int)
        return int(value)
