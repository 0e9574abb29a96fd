"""Serial ports (real adapters and pseudo-terminals) through pyserial-asyncio-fast."""

from __future__ import annotations

import asyncio
import contextlib
import os

import serial_asyncio_fast

from servotune.transports.base import ByteChannel, LinkClosedError


class _SerialProtocol(asyncio.Protocol):
    """Buffers received bytes and wakes a waiting reader; records a lost connection."""

    def __init__(self) -> None:
        self.buffer = bytearray()
        self.data_event = asyncio.Event()
        self.lost: Exception | None = None
        self.is_closed = False
        self.transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport

    def data_received(self, data: bytes) -> None:
        self.buffer += data
        self.data_event.set()

    def connection_lost(self, exc: Exception | None) -> None:
        self.is_closed = True
        self.lost = exc
        self.data_event.set()


class SerialChannel(ByteChannel):
    """A ``ByteChannel`` over an open serial port."""

    def __init__(self, transport: asyncio.Transport, protocol: _SerialProtocol, path: str):
        self._transport = transport
        self._protocol = protocol
        self._path = path

    def _check_open(self) -> None:
        if self._protocol.is_closed:
            reason = f": {self._protocol.lost}" if self._protocol.lost else ""
            raise LinkClosedError(f"{self._path} closed{reason}")

    async def write(self, data: bytes) -> None:
        self._check_open()
        self._transport.write(data)

    async def _wait_data(self, timeout_s: float) -> None:
        protocol = self._protocol
        if protocol.buffer or protocol.is_closed:
            return
        protocol.data_event.clear()
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(timeout_s):
                await protocol.data_event.wait()

    async def read_byte(self, timeout_s: float) -> int | None:
        await self._wait_data(timeout_s)
        buffer = self._protocol.buffer
        if buffer:
            byte = buffer[0]
            del buffer[0]
            return byte
        self._check_open()
        return None

    async def read_available(self, timeout_s: float) -> bytes:
        await self._wait_data(timeout_s)
        data = bytes(self._protocol.buffer)
        self._protocol.buffer.clear()
        if not data:
            self._check_open()
        return data

    def discard_input(self) -> bytes:
        data = bytes(self._protocol.buffer)
        self._protocol.buffer.clear()
        return data

    @property
    def closed(self) -> bool:
        return self._protocol.is_closed

    async def close(self) -> None:
        if not self._protocol.is_closed:
            self._transport.close()
            # Let the transport finish closing so the fd is released before a reopen.
            for _ in range(50):
                if self._protocol.is_closed:
                    break
                await asyncio.sleep(0.01)


class SerialConnector:
    """Opens ``path`` (``/dev/ttyUSB0``, a pty, or a symlink to one) at ``baud`` 8N1."""

    def __init__(self, path: str, baud: int) -> None:
        self.path = path
        self.baud = baud

    @property
    def description(self) -> str:
        return f"{self.path} @ {self.baud} baud"

    async def open(self) -> SerialChannel:
        if not os.path.exists(self.path):  # noqa: ASYNC240 - a stat, not blocking I/O
            raise LinkClosedError(f"{self.path} does not exist (adapter unplugged?)")
        loop = asyncio.get_running_loop()
        protocol = _SerialProtocol()
        try:
            transport, _ = await serial_asyncio_fast.create_serial_connection(
                loop,
                lambda: protocol,
                self.path,
                baudrate=self.baud,
                bytesize=8,
                parity="N",
                stopbits=1,
                exclusive=True,
            )
        except (OSError, ValueError) as exc:  # serial.SerialException is an OSError
            raise LinkClosedError(f"cannot open {self.path}: {exc}") from exc
        assert isinstance(transport, asyncio.Transport)
        return SerialChannel(transport, protocol, self.path)
