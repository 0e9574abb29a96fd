"""The SLAP2 echo-per-character exchange as receive handlers (sans-IO), and the line
operations the exchange makes with them on a ``ByteChannel``.

``EchoExchange`` is the manual's "sstring"/"rstring" as a ``ReceiveHandler``: send a
byte, compare its echo, send the next; then collect the reply up to the terminator;
then, if asked and allowed, start the next read at once (a chained read). It reads no
clock and touches no port: the channel hands it the bytes and the time they came, and
writes what it returns, from its receive callback (no task wake-up per character).

``EchoLine`` holds one open channel's chained read: the next ``transact`` with exactly
its payload takes it over; anything else first lets it end and drops its outcome
(``chains_dropped`` counts those).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from servotune.transports.base import ByteChannel


@dataclass(frozen=True, slots=True)
class EchoResult:
    """How many bytes of a payload were echoed correctly.

    ``echoed == len(data)`` means every byte came back. Otherwise byte ``echoed`` was
    sent and either nothing came back in time (``got is None``) or ``got`` came back.
    """

    echoed: int
    got: int | None


@dataclass(frozen=True, slots=True)
class Transaction:
    """Outcome of ``EchoLine.transact``: the echo, the reply, and when their last bytes came.

    ``reply`` is the reply up to and including the terminator, ``None`` if the echo
    failed (see ``echo``) or a reply gap exceeded its timeout (the bytes received so
    far stay buffered). ``t_echo_s`` / ``t_reply_s`` are ``time.monotonic()`` read in
    the channel's receive callback when the last echo byte / the terminator arrived,
    not when the awaiting task resumed: a busy event loop delays the task's resumption
    by far more than it delays the callback (``None`` where that byte never came).
    Both can only be late. ``t_sent_s`` is read just before the last byte of ``data``
    was written: it can only be early, so the device received that byte after it (a
    host that ran the echo's callback late leaves the two far apart).
    """

    echo: EchoResult
    reply: bytes | None
    t_echo_s: float | None
    t_reply_s: float | None
    t_sent_s: float | None = None


class EchoExchange:
    """An echoed write, a read up to ``terminator``, or both in a row (a ``ReceiveHandler``).

    ``payload``: sent one byte at a time, each after the previous one's echo; stops at
    the first wrong echo or a gap over ``char_timeout_s`` (``first_timeout_s`` for the
    first byte). Empty: no echo phase. ``terminator`` None: done after the echo (bytes
    that came after it stay received); otherwise the reply is read up to it, its
    first byte within ``first_reply_timeout_s`` of the last echo (``first_timeout_s``
    without a payload), every other gap within ``char_timeout_s``; a timeout leaves
    the reply's bytes received. ``then``: the exchange to start as ``follow_up`` when
    the reply is complete, nothing else was received, and ``may_chain()`` (asked
    then) allows it.
    """

    def __init__(
        self,
        payload: bytes = b"",
        *,
        terminator: int | None = None,
        first_timeout_s: float,
        char_timeout_s: float,
        first_reply_timeout_s: float | None = None,
        then: bytes = b"",
        may_chain: Callable[[], bool] | None = None,
    ) -> None:
        self.payload = payload
        self.terminator = terminator
        self.first_timeout_s = first_timeout_s
        self.char_timeout_s = char_timeout_s
        self.first_reply_timeout_s = (
            first_timeout_s if first_reply_timeout_s is None else first_reply_timeout_s
        )
        self.then = then
        self.may_chain = may_chain
        self.index = 0  # the payload byte whose echo is due
        self.echo: EchoResult | None = None if payload else EchoResult(0, None)
        self.reply: bytes | None = None
        self.t_echo_s: float | None = None
        self.t_reply_s: float | None = None
        self.t_sent_s: float | None = None  # just before the last payload byte left
        self.deadline_s: float | None = None
        self.done = False
        self.started = False
        self._next: EchoExchange | None = None
        # The follow-up handed to the channel (``follow_up``): it runs on the line.
        self.chained: EchoExchange | None = None

    def start(self, now_s: float) -> bytes:
        self.started = True
        self.deadline_s = now_s + self.first_timeout_s
        return self._send_next(now_s) if self.payload else b""

    def _send_next(self, now_s: float) -> bytes:
        """Payload byte ``index`` (stamping ``t_sent_s`` for the last one)."""
        index = self.index
        if index == len(self.payload) - 1:
            self.t_sent_s = now_s
        return self.payload[index : index + 1]

    def feed(self, received: bytearray, now_s: float) -> bytes:
        out = b""
        if self.echo is None:
            payload = self.payload
            while received:
                got = received[0]
                del received[0]
                if got != payload[self.index]:
                    self.echo = EchoResult(self.index, got)
                    self.done = True
                    return out
                self.index += 1
                if self.index == len(payload):
                    self.echo = EchoResult(self.index, None)
                    self.t_echo_s = now_s
                    if self.terminator is None:
                        self.done = True
                        return out
                    self.deadline_s = now_s + self.first_reply_timeout_s
                    break
                out += self._send_next(now_s)
                self.deadline_s = now_s + self.char_timeout_s
            else:
                return out
        if self.terminator is None:
            return out
        end = received.find(self.terminator)
        if end < 0:
            if received:  # the reply has begun: the gap between characters applies
                self.deadline_s = now_s + self.char_timeout_s
            return out
        self.reply = bytes(received[: end + 1])
        del received[: end + 1]
        self.t_reply_s = now_s
        self.done = True
        if self.then and not received and (self.may_chain is None or self.may_chain()):
            self._next = EchoExchange(
                self.then,
                terminator=self.terminator,
                first_timeout_s=self.char_timeout_s,
                char_timeout_s=self.char_timeout_s,
                first_reply_timeout_s=self.first_reply_timeout_s,
            )
        return out

    def expire(self, now_s: float) -> bytes:
        if self.echo is None:
            self.echo = EchoResult(self.index, None)
        self.done = True
        return b""

    def follow_up(self) -> EchoExchange | None:
        self.chained, self._next = self._next, None
        return self.chained

    def outcome(self) -> Transaction:
        """What it got so far (an echo cut short where the port closed)."""
        echo = self.echo if self.echo is not None else EchoResult(self.index, None)
        return Transaction(echo, self.reply, self.t_echo_s, self.t_reply_s, self.t_sent_s)


class ReadByte:
    """One received byte within ``timeout_s`` (a ``ReceiveHandler``); the rest stays."""

    def __init__(self, timeout_s: float) -> None:
        self.timeout_s = timeout_s
        self.deadline_s: float | None = None
        self.done = False
        self.byte: int | None = None

    def start(self, now_s: float) -> bytes:
        self.deadline_s = now_s + self.timeout_s
        return b""

    def feed(self, received: bytearray, now_s: float) -> bytes:
        if received:
            self.byte = received[0]
            del received[0]
            self.done = True
        return b""

    def expire(self, now_s: float) -> bytes:
        self.done = True
        return b""

    def follow_up(self) -> None:
        return None


class EchoLine:
    """The SLAP2 line operations on one open ``channel`` (the exchange keeps one per
    channel). Every operation raises ``LinkClosedError`` once the port is gone."""

    def __init__(self, channel: ByteChannel) -> None:
        self.channel = channel
        self._chained: EchoExchange | None = None
        self.chains_dropped = 0
        """Reads started with ``transact(then=...)`` that the caller did not take over
        (it asked for something else): sent, their reply dropped."""

    async def read_byte(self, timeout_s: float) -> int | None:
        """The next received byte; None on a timeout."""
        await self.settle()
        handler = ReadByte(timeout_s)
        await self.channel.drive(handler)
        return handler.byte

    async def write_echoed(self, data: bytes, char_timeout_s: float) -> EchoResult:
        """Send ``data`` one byte at a time, each only after the previous one's echo.

        Stops at the first missing (``char_timeout_s``) or wrong echo. Bytes that
        arrive after the last echo stay buffered for the next read.
        """
        await self.settle()
        if not data:
            return EchoResult(0, None)
        handler = EchoExchange(data, first_timeout_s=char_timeout_s, char_timeout_s=char_timeout_s)
        await self.channel.drive(handler)
        return handler.outcome().echo

    async def read_until(
        self, terminator: int, first_timeout_s: float, char_timeout_s: float
    ) -> bytes | None:
        """Read up to and including ``terminator``; ``None`` if a gap exceeds its timeout.

        ``first_timeout_s`` applies to the first byte, ``char_timeout_s`` between bytes.
        On a timeout the bytes received so far stay buffered.
        """
        await self.settle()
        handler = EchoExchange(
            terminator=terminator, first_timeout_s=first_timeout_s, char_timeout_s=char_timeout_s
        )
        await self.channel.drive(handler)
        return handler.reply

    async def transact(
        self,
        data: bytes,
        terminator: int,
        char_timeout_s: float,
        first_reply_timeout_s: float,
        *,
        then: bytes = b"",
        may_chain: Callable[[], bool] | None = None,
    ) -> Transaction:
        """``write_echoed(data)`` then ``read_until(terminator)`` as one exchange.

        The reply is collected from the same receive callback that checks the last
        echo (no task wake-up in between), and both arrival times are stamped there
        (see ``Transaction``). ``first_reply_timeout_s`` applies from the last echo to
        the reply's first byte, ``char_timeout_s`` to every other gap.

        ``then``: the exchange the caller expects to make next (only one that may
        be sent for nothing: a read). That same callback starts it when the reply is
        complete, nothing else is buffered, and ``may_chain()`` (checked then, e.g.
        "no STOP is waiting") allows it, so the line does not idle while the caller
        wakes up and parses. The next ``transact`` with exactly that payload takes it
        over; any other call first lets it end and drops its outcome. A caller that
        must know how a dropped one ended calls ``settle`` before its next exchange.
        """
        chained = self._chained
        if chained is not None and chained.payload != data:
            await self.settle()
            chained = None
        if chained is not None:
            # Chained by the previous transact: already under way (or done).
            chained.then, chained.may_chain = then, may_chain
            if not chained.done or self.channel.closed:
                await self.channel.drive(chained)  # waits for it (raises if closed)
            self._chained = None
            handler = chained
        else:
            handler = EchoExchange(
                data,
                terminator=terminator,
                first_timeout_s=char_timeout_s,
                char_timeout_s=char_timeout_s,
                first_reply_timeout_s=first_reply_timeout_s,
                then=then,
                may_chain=may_chain,
            )
            try:
                await self.channel.drive(handler)
            finally:  # (cancelled right after it chained: the chain is still known)
                self._chained = handler.chained
            return handler.outcome()
        self._chained = handler.chained
        return handler.outcome()

    async def settle(self, adopt: bytes = b"") -> Transaction | None:
        """End a chained exchange (``transact(then=...)``) other than ``adopt``: wait
        for it, drop it, and return how it ended (a reply of None: it failed before
        its reply was complete, so the device may hold part of that command). None
        when nothing is chained, or when it is ``adopt`` (left to be taken over)."""
        chained = self._chained
        if chained is None or (adopt and chained.payload == adopt):
            return None
        if not chained.done or self.channel.closed:
            await self.channel.drive(chained)  # waits for its end (raises if closed)
        self._chained = None
        self.chains_dropped += 1
        return chained.outcome()


__all__ = ["EchoExchange", "EchoLine", "EchoResult", "ReadByte", "Transaction"]
