"""Byte transports: the small interface drivers talk through.

A driver never opens a port itself: it is given a ``Connector`` and calls ``open()``
each time it (re)connects. This keeps drivers testable against a simulator on a
pseudo-terminal and lets the demo use exactly the path real hardware uses.
"""

from __future__ import annotations

from typing import Protocol


class LinkClosedError(ConnectionError):
    """The port went away (USB adapter unplugged, pty closed)."""


class ByteChannel(Protocol):
    """An open, full-duplex byte stream.

    ``read_byte`` and ``read_available`` return ``None`` / ``b""`` on timeout and raise
    ``LinkClosedError`` once the port is gone. Received bytes are buffered in the
    channel, so no byte is lost between calls.
    """

    async def write(self, data: bytes) -> None: ...

    async def read_byte(self, timeout_s: float) -> int | None: ...

    async def read_available(self, timeout_s: float) -> bytes: ...

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
