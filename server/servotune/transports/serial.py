"""Serial ports (real adapters and pseudo-terminals) through pyserial-asyncio-fast."""

from __future__ import annotations

import asyncio
import errno
import functools
import os
import time

import serial
import serial_asyncio_fast

from servotune.transports.base import ByteChannel, LinkClosedError, ReceiveHandler


class _Run:
    """A handler being driven: the tasks waiting for its end, its deadline timer."""

    __slots__ = ("ended", "handler", "timer", "waiters")

    def __init__(self, handler: ReceiveHandler) -> None:
        self.handler = handler
        self.ended = False
        # One future per waiting task: a cancelled wait cancels its own only.
        self.waiters: list[asyncio.Future[None]] = []
        self.timer: asyncio.TimerHandle | None = None

    async def wait(self, loop: asyncio.AbstractEventLoop) -> None:
        if not self.ended:
            waiter = loop.create_future()
            self.waiters.append(waiter)
            await waiter


class _SerialProtocol(asyncio.Protocol):
    """Buffers received bytes, advances the driven handler from ``data_received``,
    wakes a waiting reader; records a lost connection.

    Running a handler's steps in the protocol callback, instead of waking the waiting
    task for every byte, takes one task switch per step out of a round trip (an
    echo-per-character protocol is nothing but round trips).
    """

    def __init__(self) -> None:
        self.buffer = bytearray()
        self.data_event = asyncio.Event()
        self.lost: Exception | None = None
        self.is_closed = False
        self.transport: asyncio.Transport | None = None
        self.loop = asyncio.get_running_loop()
        self.run: _Run | None = None  # the handler fed from data_received
        # A follow-up started from the receive callback (``ReceiveHandler.follow_up``)
        # that no ``drive`` has taken over yet; it may still be running (``run``).
        self.detached: _Run | None = None
        # The latest any read that timed out was noticed (SerialChannel.take_timeout_late_s).
        self.timeout_late_s = 0.0

    def note_late(self, late_s: float) -> None:
        self.timeout_late_s = max(self.timeout_late_s, late_s)

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport

    def send(self, data: bytes) -> None:
        assert self.transport is not None
        self.transport.write(data)

    def data_received(self, data: bytes) -> None:
        self.buffer += data
        run = self.run
        if run is not None:
            now_s = time.monotonic()
            self.advance(run, run.handler.feed(self.buffer, now_s), now_s)
        self.data_event.set()

    def begin(self, handler: ReceiveHandler, now_s: float, *, detached: bool = False) -> _Run:
        """Install ``handler``, send what it starts with, feed it what is buffered."""
        run = _Run(handler)
        self.run = run
        if detached:
            self.detached = run
        out = handler.start(now_s)
        if not handler.done:
            if out:
                self.send(out)
            out = handler.feed(self.buffer, now_s)
        self.advance(run, out, now_s)
        return run

    def advance(self, run: _Run, out: bytes, now_s: float) -> None:
        """After a step of ``run``'s handler: send ``out``; end it (and start its
        follow-up) once done, else keep a timer for its deadline."""
        if out:
            self.send(out)
        handler = run.handler
        if handler.done:
            self.end(run)
            follow = handler.follow_up()
            if follow is not None:
                self.begin(follow, now_s, detached=True)
            return
        # A moved deadline leaves the armed timer (it re-arms itself when it fires
        # early): cancelling and re-arming for every byte would cost more than the
        # rest of the per-byte work. So one moved earlier is checked only when the
        # armed one fires (see ``ByteChannel.drive``).
        if run.timer is None:
            deadline_s = handler.deadline_s
            if deadline_s is not None:
                self.arm(run, deadline_s, now_s)

    def arm(self, run: _Run, deadline_s: float, now_s: float) -> None:
        # The loop's clock may differ from time.monotonic() (uvloop): arm by the delay.
        run.timer = self.loop.call_at(self.loop.time() + (deadline_s - now_s), self.on_timer, run)

    def on_timer(self, run: _Run) -> None:
        run.timer = None
        if self.run is not run:
            return
        handler = run.handler
        deadline_s = handler.deadline_s
        if deadline_s is None:
            return
        now_s = time.monotonic()
        if now_s < deadline_s:
            self.arm(run, deadline_s, now_s)
            return
        self.note_late(now_s - deadline_s)
        self.advance(run, handler.expire(now_s), now_s)

    def end(self, run: _Run) -> None:
        if run.timer is not None:
            run.timer.cancel()
            run.timer = None
        if self.run is run:
            self.run = None
        if not run.ended:
            run.ended = True
            for waiter in run.waiters:
                if not waiter.done():
                    waiter.set_result(None)

    def connection_lost(self, exc: Exception | None) -> None:
        self.is_closed = True
        self.lost = exc
        if self.run is not None:
            self.end(self.run)
        self.data_event.set()


class _AtLeast:
    """``read_at_least`` as a handler: done once ``count`` bytes are buffered."""

    __slots__ = ("count", "data", "deadline_s", "done", "t_s", "timeout_s")

    def __init__(self, count: int, timeout_s: float) -> None:
        self.count = count
        self.timeout_s = timeout_s
        self.deadline_s: float | None = None
        self.done = False
        self.data: bytes | None = None
        self.t_s: float | None = None

    def start(self, now_s: float) -> bytes:
        self.deadline_s = now_s + self.timeout_s
        return b""

    def feed(self, received: bytearray, now_s: float) -> bytes:
        if len(received) >= self.count:
            self.data = bytes(received)
            received.clear()
            self.t_s = now_s
            self.done = True
        return b""

    def expire(self, now_s: float) -> bytes:
        self.done = True
        return b""

    def follow_up(self) -> None:
        return None


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

    def take_timeout_late_s(self) -> float:
        late_s, self._protocol.timeout_late_s = self._protocol.timeout_late_s, 0.0
        return late_s

    async def _settle(self) -> None:
        """Before any other use of the line: wait for a running follow-up to end, so
        that its bytes never mix with the next exchange's. A cancelled caller leaves
        it running, for the next call to wait out."""
        protocol = self._protocol
        detached = protocol.detached
        if detached is None:
            return
        await detached.wait(protocol.loop)
        if protocol.detached is detached:
            protocol.detached = None

    async def drive(self, handler: ReceiveHandler) -> None:
        protocol = self._protocol
        detached = protocol.detached
        if detached is not None and detached.handler is handler:
            if not detached.ended:
                waiter = protocol.loop.create_future()
                detached.waiters.append(waiter)
                await waiter
            if protocol.detached is detached:
                protocol.detached = None
            self._check_open()
            return
        if detached is not None:
            await self._settle()
        self._check_open()
        run = protocol.begin(handler, time.monotonic())
        try:
            if not run.ended:  # (inline: this is every exchange's path)
                waiter = protocol.loop.create_future()
                run.waiters.append(waiter)
                await waiter
        finally:
            if protocol.run is run:
                protocol.end(run)  # cancelled: the handler ends where it is
        if not handler.done:
            self._check_open()

    async def write(self, data: bytes) -> None:
        await self._settle()
        self._check_open()
        self._transport.write(data)

    async def _wait_data(self, timeout_s: float) -> None:
        protocol = self._protocol
        if protocol.buffer or protocol.is_closed:
            return
        protocol.data_event.clear()
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        try:
            async with asyncio.timeout(timeout_s):
                await protocol.data_event.wait()
        except TimeoutError:
            protocol.note_late(loop.time() - deadline)

    async def read_available(self, timeout_s: float) -> bytes:
        await self._settle()
        await self._wait_data(timeout_s)
        data = bytes(self._protocol.buffer)
        self._protocol.buffer.clear()
        if not data:
            self._check_open()
        return data

    async def read_at_least(self, count: int, timeout_s: float) -> tuple[bytes, float | None]:
        await self._settle()
        self._check_open()
        handler = _AtLeast(count, timeout_s)
        try:
            await self.drive(handler)
        except LinkClosedError:
            data = self.discard_input()  # what came before the port closed
            if not data:
                raise
            return data, None
        if handler.data is not None:
            return handler.data, handler.t_s
        return self.discard_input(), None  # a timeout: what came so far

    def discard_input(self) -> bytes:
        detached = self._protocol.detached
        if detached is not None and not detached.ended:
            return b""  # what came belongs to the follow-up under way
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


class _DirectSerial(serial.Serial):  # type: ignore[misc]  # pyserial has no types
    """pyserial's POSIX port with a direct non-blocking ``read`` and ``write``.

    pyserial-asyncio-fast calls ``read`` when the event loop saw the port readable and
    ``write`` with both timeouts 0. pyserial's versions then run a ``select`` of their
    own before every read and build timeout objects for every call: at 19200 baud the
    SLAP2 line is one byte each way per round trip, so that sat on the critical path
    of every echo. Here they are one
    system call each, with pyserial's semantics: no data -> ``b""``; a readable port
    that yields nothing (a vanished adapter, a closed pty) or any other error ->
    ``SerialException``; a full output buffer -> ``BlockingIOError``, which the
    transport buffers and retries. Configuration (termios, exclusive lock) stays
    pyserial's.
    """

    def read(self, size: int = 1) -> bytes:
        if self._timeout != 0:  # not the transport's non-blocking use
            return bytes(super().read(size))
        try:
            data = os.read(self.fd, size)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as exc:
            raise serial.SerialException(f"read failed: {exc}") from exc
        if not data:
            raise serial.SerialException(
                "device reports readiness to read but returned no data "
                "(device disconnected or multiple access on port?)"
            )
        return data

    def write(self, data: bytes | bytearray | memoryview) -> int | None:
        if self._write_timeout != 0:
            return super().write(data)  # type: ignore[no-any-return]
        try:
            return os.write(self.fd, data)
        except OSError as exc:
            if exc.errno in (errno.EAGAIN, errno.EINTR):
                raise BlockingIOError(exc.errno, str(exc)) from exc
            raise serial.SerialException(f"write failed: {exc}") from exc


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
        port_class = _DirectSerial if os.name == "posix" else serial.Serial
        open_port = functools.partial(
            port_class,
            self.path,
            baudrate=self.baud,
            bytesize=8,
            parity="N",
            stopbits=1,
            exclusive=True,
        )
        try:
            # Opening blocks (termios, the exclusive lock): in a thread, as
            # create_serial_connection does it.
            port = await loop.run_in_executor(None, open_port)
            transport, _ = await serial_asyncio_fast.connection_for_serial(
                loop, lambda: protocol, port
            )
        except (OSError, ValueError) as exc:  # serial.SerialException is an OSError
            raise LinkClosedError(f"cannot open {self.path}: {exc}") from exc
        assert isinstance(transport, asyncio.Transport)
        return SerialChannel(transport, protocol, self.path)
