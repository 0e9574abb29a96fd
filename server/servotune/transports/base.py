"""Byte transports: the small interface drivers talk through.

A driver never opens a port itself: it is given a ``Connector`` and calls ``open()``
each time it (re)connects. This keeps drivers testable against a simulator on a
pseudo-terminal and lets the demo use exactly the path real hardware uses.
"""

from __future__ import annotations

from typing import Protocol


class LinkClosedError(ConnectionError):
    """The port went away (USB adapter unplugged, pty closed)."""


class ReceiveHandler(Protocol):
    """A device's exchange rules, run by ``ByteChannel.drive`` inside the channel's
    receive callback (sans-IO: it sends and reads nothing itself).

    The channel calls ``start`` once, then ``feed`` with everything received and not
    yet taken (at once for what is already buffered, then after every arrival), and
    ``expire`` once ``deadline_s`` has passed. Each returns the bytes to write at once
    (``b""``: none). ``feed`` takes what it consumes from the front of ``received``;
    what it leaves stays buffered for the next read. Times are ``time.monotonic()``
    seconds, read in the callback when the bytes came (or the deadline fired). Once
    ``done`` the handler is called no more, except ``follow_up`` once, right then.
    """

    def start(self, now_s: float) -> bytes: ...

    def feed(self, received: bytearray, now_s: float) -> bytes: ...

    def expire(self, now_s: float) -> bytes: ...

    @property
    def deadline_s(self) -> float | None:
        """When ``expire`` is due (None: never)."""
        ...

    @property
    def done(self) -> bool: ...

    def follow_up(self) -> ReceiveHandler | None:
        """The handler to start from the same callback, now that this one is done
        (None: none). The channel runs it as a follow-up: see ``ByteChannel.drive``."""
        ...


class ByteChannel(Protocol):
    """An open, full-duplex byte stream.

    ``read_available`` returns ``b""`` on timeout; every call raises
    ``LinkClosedError`` once the port is gone. Received bytes are buffered in the
    channel, so no byte is lost between calls.
    """

    async def write(self, data: bytes) -> None: ...

    async def read_available(self, timeout_s: float) -> bytes: ...

    async def read_at_least(self, count: int, timeout_s: float) -> tuple[bytes, float | None]:
        """Wait until ``count`` bytes are buffered (or ``timeout_s``), then take all of
        them: ``(data, t_s)``. ``t_s`` is ``time.monotonic()`` read in the receive
        callback when the ``count``-th byte came (``None`` on a timeout, where ``data``
        is whatever had come). One task wake-up for a fixed-size reply however many
        pieces it arrives in (a paced line delivers it a character at a time).
        """
        ...

    async def drive(self, handler: ReceiveHandler) -> None:
        """Run ``handler`` from the receive callback until it is ``done`` (one task
        wake-up for a whole exchange, however many steps it has).

        A handler's ``follow_up`` is started from the callback that finished it and
        runs on unawaited; every other call first waits for it to end, except
        ``drive`` of that very follow-up, which waits for it instead of starting it
        (a cancelled wait leaves it running). Cancelling ``drive`` of any other
        handler ends that handler where it is. Raises ``LinkClosedError`` if the port
        is closed, or closes before the handler is done.

        ``expire`` comes when the deadline armed first has passed and then whenever
        the handler's current ``deadline_s`` has: a deadline that moves earlier than
        the armed one (a long first wait, then a short gap) is noticed only when the
        armed one fires.
        """
        ...

    def take_timeout_late_s(self) -> float:
        """The longest any read or handler deadline that passed since the last call
        was noticed after it (0: all on time); resets it. More than a read listened:
        the host itself did not run for longer than it listened, so that silence is no
        evidence against the device (its bytes may be held up in the host's tty
        layer, which a starved host starves too)."""
        ...

    def discard_input(self) -> bytes:
        """Drop and return everything received but not yet read (``b""`` while a
        follow-up runs: what came is its own)."""
        ...

    @property
    def closed(self) -> bool: ...

    async def close(self) -> None: ...


class Connector(Protocol):
    """Knows how to open a channel to one physical link; called on every (re)connect."""

    @property
    def description(self) -> str: ...

    async def open(self) -> ByteChannel: ...
