"""Byte transports: the small interface drivers talk through.

A driver never opens a port itself: it is given a ``Connector`` and calls ``open()``
each time it (re)connects. This keeps drivers testable against a simulator on a
pseudo-terminal and lets the demo use exactly the path real hardware uses.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol


class LinkClosedError(ConnectionError):
    """The port went away (USB adapter unplugged, pty closed)."""


@dataclass(frozen=True, slots=True)
class EchoResult:
    """Outcome of ``write_echoed``: how many bytes were echoed correctly.

    ``echoed == len(data)`` means every byte came back. Otherwise byte ``echoed`` was
    sent and either nothing came back in time (``got is None``) or ``got`` came back.
    """

    echoed: int
    got: int | None


@dataclass(frozen=True, slots=True)
class Transaction:
    """Outcome of ``transact``: the echo, the reply, and when their last bytes came.

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


class ByteChannel(Protocol):
    """An open, full-duplex byte stream.

    ``read_byte`` and ``read_available`` return ``None`` / ``b""`` on timeout and raise
    ``LinkClosedError`` once the port is gone. Received bytes are buffered in the
    channel, so no byte is lost between calls.
    """

    async def write(self, data: bytes) -> None: ...

    async def read_byte(self, timeout_s: float) -> int | None: ...

    async def write_echoed(self, data: bytes, char_timeout_s: float) -> EchoResult:
        """Send ``data`` one byte at a time, each only after the previous one's echo.

        Stops at the first missing (``char_timeout_s``) or wrong echo. Bytes that
        arrive after the last echo stay buffered for the next read.
        """
        ...

    async def read_until(
        self, terminator: int, first_timeout_s: float, char_timeout_s: float
    ) -> bytes | None:
        """Read up to and including ``terminator``; ``None`` if a gap exceeds its timeout.

        ``first_timeout_s`` applies to the first byte, ``char_timeout_s`` between bytes.
        On a timeout the bytes received so far stay buffered.
        """
        ...

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
        over; any other call first lets it end and drops its outcome
        (``chains_dropped`` counts those). A caller that must know how a dropped
        one ended calls ``settle`` before its next exchange.
        """
        ...

    async def settle(self, adopt: bytes = b"") -> Transaction | None:
        """End a chained exchange (``transact(then=...)``) other than ``adopt``: wait
        for it, drop it, and return how it ended (a reply of None: it failed before
        its reply was complete, so the device may hold part of that command). None
        when nothing is chained, or when it is ``adopt`` (left to be taken over)."""
        ...

    def take_timeout_late_s(self) -> float:
        """The longest any read that timed out since the last call was noticed after
        its deadline (0: all on time); resets it. More than a read listened: the host
        itself did not run for longer than it listened, so that silence is no evidence
        against the device (its bytes may be held up in the host's tty layer, which a
        starved host starves too)."""
        ...

    @property
    def chains_dropped(self) -> int:
        """Exchanges started with ``transact(then=...)`` that the caller did not
        take over (it asked for something else): sent, their reply dropped."""
        ...

    async def read_available(self, timeout_s: float) -> bytes: ...

    async def read_at_least(self, count: int, timeout_s: float) -> tuple[bytes, float | None]:
        """Wait until ``count`` bytes are buffered (or ``timeout_s``), then take all of
        them: ``(data, t_s)``. ``t_s`` is ``time.monotonic()`` read in the receive
        callback when the ``count``-th byte came (``None`` on a timeout, where ``data``
        is whatever had come). One task wake-up for a fixed-size reply however many
        pieces it arrives in (a paced line delivers it a character at a time).
        """
        ...

    def discard_input(self) -> bytes:
        """Drop and return everything received but not yet read."""
        ...

    @property
    def closed(self) -> bool: ...

    async def close(self) -> None: ...


class Connector(Protocol):
    """Knows how to open a channel to one physical link; called on every (re)connect."""

    @property
    def description(self) -> str: ...

    async def open(self) -> ByteChannel: ...
