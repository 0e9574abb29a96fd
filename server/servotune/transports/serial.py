"""Serial ports (real adapters and pseudo-terminals) on the event loop.

pyserial opens and configures the port; the fd is then watched with the loop's
``add_reader`` and read and written directly (see ``_SerialProtocol`` for why). POSIX
only (Linux, macOS): a serial port on Windows would need a polling reader.
"""

from __future__ import annotations

import asyncio
import contextlib
import os

import serial

from servotune.transports.base import ByteChannel, EchoResult, LinkClosedError

_READ_CHUNK = 4096


class _Exchange:
    """An echoed write or a read-until in progress, advanced from ``data_received``.

    Running the per-character steps in the protocol callback, instead of waking the
    waiting task for every echo, takes one task switch per character out of the
    round trip (the SLAP2 protocol is nothing but round trips).
    """

    def __init__(
        self,
        protocol: _SerialProtocol,
        *,
        payload: bytes = b"",
        terminator: int | None = None,
        min_bytes: int = 0,
        first_timeout_s: float,
        char_timeout_s: float,
    ) -> None:
        self.protocol = protocol
        self.payload = payload
        self.terminator = terminator
        self.min_bytes = min_bytes
        self.char_timeout_s = char_timeout_s
        self.index = 0
        self.loop = asyncio.get_running_loop()
        self.future: asyncio.Future[EchoResult | bytes | None] = self.loop.create_future()
        self.deadline = self.loop.time() + first_timeout_s
        protocol.arm_timer(self.deadline)

    def restart_timer(self) -> None:
        # Only move the deadline; the armed timer re-arms itself when it fires early.
        # Cancelling and re-arming a timer for every character would cost more than
        # the rest of the per-character work.
        self.deadline = self.loop.time() + self.char_timeout_s

    def finish(self, result: EchoResult | bytes | None) -> None:
        if self.protocol.exchange is self:
            self.protocol.exchange = None
        if not self.future.done():
            self.future.set_result(result)

    def on_timeout(self) -> None:
        if self.min_bytes:
            data = bytes(self.protocol.buffer)
            self.protocol.buffer.clear()
            self.finish(data)
        elif self.terminator is None:
            self.finish(EchoResult(self.index, None))
        else:
            self.finish(None)

    def step(self) -> None:
        """Consume what the buffer holds; called after every ``data_received``."""
        buffer = self.protocol.buffer
        if self.min_bytes:
            if len(buffer) >= self.min_bytes:
                data = bytes(buffer)
                buffer.clear()
                self.finish(data)
            return
        if self.terminator is not None:
            end = buffer.find(self.terminator)
            if end < 0:
                if buffer:
                    self.restart_timer()
                return
            line = bytes(buffer[: end + 1])
            del buffer[: end + 1]
            self.finish(line)
            return
        while buffer:
            expected = self.payload[self.index]
            got = buffer[0]
            del buffer[0]
            if got != expected:
                self.finish(EchoResult(self.index, got))
                return
            self.index += 1
            if self.index == len(self.payload):
                self.finish(EchoResult(self.index, None))
                return
            self.protocol.send(self.payload[self.index : self.index + 1])
            self.restart_timer()


class _SerialProtocol:
    """The open port on the event loop: reads straight from the fd, writes straight to it.

    Why not pyserial-asyncio(-fast): its reader calls ``Serial.read``, which runs two
    ``select`` calls and builds a timeout object for every readiness event, and its
    writer does the same per write. The SLAP2 protocol is one byte per round trip, so
    that was most of the host's per-character cost (profiled: ``Serial.read``/
    ``Serial.write`` were the hottest frames of the demo's event loop). pyserial still
    opens and configures the port (termios, exclusive lock, baud); after that the fd
    is read with one ``os.read`` per readiness event and written with ``os.write``
    (what does not fit waits for writability, in order).
    """

    def __init__(self, port: serial.Serial, loop: asyncio.AbstractEventLoop) -> None:
        self.port = port
        self.fd: int = port.fileno()
        self.loop = loop
        self.buffer = bytearray()
        self.data_event = asyncio.Event()
        self.lost: Exception | None = None
        self.is_closed = False
        self.exchange: _Exchange | None = None
        self._pending = bytearray()  # written but not yet accepted by the kernel
        # One timer for all exchanges, armed at the earliest deadline it must catch.
        # Exchanges end long before their timeouts almost always; a loop timer created
        # and cancelled for each of them was the single hottest line of the serial
        # path in the demo's profile (two per SLAP2 transaction). When it fires it
        # checks the exchange running then and re-arms for its deadline.
        self._timer: asyncio.TimerHandle | None = None
        self._timer_at = 0.0
        os.set_blocking(self.fd, False)
        loop.add_reader(self.fd, self._on_readable)

    def arm_timer(self, deadline: float) -> None:
        """Make sure the timer fires no later than ``deadline`` (loop time)."""
        if self._timer is not None:
            if self._timer_at <= deadline:
                return
            self._timer.cancel()
        self._timer_at = deadline
        self._timer = self.loop.call_at(deadline, self._on_timer)

    def _on_timer(self) -> None:
        self._timer = None
        exchange = self.exchange
        if exchange is None:
            return
        if self.loop.time() < exchange.deadline:
            self.arm_timer(exchange.deadline)
        else:
            exchange.on_timeout()

    def send(self, data: bytes) -> None:
        if self.is_closed:
            return
        if self._pending:
            self._pending += data
            return
        try:
            written = os.write(self.fd, data)
        except (BlockingIOError, InterruptedError):
            written = 0
        except OSError as exc:
            self.connection_lost(exc)
            return
        if written < len(data):
            self._pending += data[written:]
            self.loop.add_writer(self.fd, self._on_writable)

    def _on_writable(self) -> None:
        try:
            written = os.write(self.fd, self._pending)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self.connection_lost(exc)
            return
        del self._pending[:written]
        if not self._pending:
            self.loop.remove_writer(self.fd)

    def _on_readable(self) -> None:
        try:
            data = os.read(self.fd, _READ_CHUNK)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:  # EIO: the adapter was unplugged or the pty closed
            self.connection_lost(exc)
            return
        if not data:
            # Ready to read but nothing there: a vanished device (what pyserial reports
            # as "device reports readiness to read but returned no data").
            self.connection_lost(OSError("the device reports data but returned none"))
            return
        self.data_received(data)

    def data_received(self, data: bytes) -> None:
        self.buffer += data
        if self.exchange is not None:
            self.exchange.step()
        self.data_event.set()

    def connection_lost(self, exc: Exception | None) -> None:
        if self.is_closed:
            return
        self.is_closed = True
        self.lost = exc
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self.loop.remove_reader(self.fd)
        if self._pending:
            self._pending.clear()
            self.loop.remove_writer(self.fd)
        with contextlib.suppress(OSError, serial.SerialException):
            self.port.close()
        if self.exchange is not None:
            self.exchange.finish(None)
        self.data_event.set()


class SerialChannel(ByteChannel):
    """A ``ByteChannel`` over an open serial port."""

    def __init__(self, protocol: _SerialProtocol, path: str):
        self._protocol = protocol
        self._path = path

    def _check_open(self) -> None:
        if self._protocol.is_closed:
            reason = f": {self._protocol.lost}" if self._protocol.lost else ""
            raise LinkClosedError(f"{self._path} closed{reason}")

    async def write(self, data: bytes) -> None:
        self._check_open()
        self._protocol.send(data)

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

    async def write_echoed(self, data: bytes, char_timeout_s: float) -> EchoResult:
        self._check_open()
        if not data:
            return EchoResult(0, None)
        exchange = _Exchange(
            self._protocol,
            payload=data,
            first_timeout_s=char_timeout_s,
            char_timeout_s=char_timeout_s,
        )
        self._protocol.exchange = exchange
        try:
            self._protocol.send(data[:1])
            exchange.step()  # an echo may already sit in the buffer (it would be stale)
            result = await exchange.future
        finally:
            if self._protocol.exchange is exchange:
                self._protocol.exchange = None
        if result is None:  # the port closed meanwhile
            self._check_open()
        assert isinstance(result, EchoResult)
        return result

    async def read_until(
        self, terminator: int, first_timeout_s: float, char_timeout_s: float
    ) -> bytes | None:
        self._check_open()
        exchange = _Exchange(
            self._protocol,
            terminator=terminator,
            first_timeout_s=first_timeout_s,
            char_timeout_s=char_timeout_s,
        )
        self._protocol.exchange = exchange
        try:
            exchange.step()
            result = await exchange.future
        finally:
            if self._protocol.exchange is exchange:
                self._protocol.exchange = None
        if result is None:
            self._check_open()
            return None
        assert isinstance(result, bytes)
        return result

    async def read_at_least(self, count: int, timeout_s: float) -> bytes:
        if count <= 0:
            raise ValueError("count must be positive")
        self._check_open()
        exchange = _Exchange(
            self._protocol, min_bytes=count, first_timeout_s=timeout_s, char_timeout_s=timeout_s
        )
        self._protocol.exchange = exchange
        try:
            exchange.step()
            result = await exchange.future
        finally:
            if self._protocol.exchange is exchange:
                self._protocol.exchange = None
        if result is None:  # the port closed meanwhile
            self._check_open()
            return b""
        assert isinstance(result, bytes)
        if not result:
            self._check_open()
        return result

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
        # Synchronous: the fd is released (and the exclusive lock with it) before a
        # reopen. Bytes not yet accepted by the kernel are dropped, as a pulled cable
        # would drop them.
        self._protocol.connection_lost(None)


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
        try:
            # Opening and configuring a tty is a few fast syscalls (pyserial-asyncio
            # did the same on the loop).
            port = serial.Serial(
                self.path,
                baudrate=self.baud,
                bytesize=8,
                parity="N",
                stopbits=1,
                timeout=0,
                exclusive=True,
            )
        except (OSError, ValueError) as exc:  # serial.SerialException is an OSError
            raise LinkClosedError(f"cannot open {self.path}: {exc}") from exc
        try:
            protocol = _SerialProtocol(port, loop)
        except (OSError, NotImplementedError) as exc:  # e.g. a loop without add_reader
            port.close()
            raise LinkClosedError(f"cannot watch {self.path}: {exc!r}") from exc
        return SerialChannel(protocol, self.path)
