"""Serial ports (real adapters and pseudo-terminals) through pyserial-asyncio-fast."""

from __future__ import annotations

import asyncio
import errno
import functools
import os
import time
from collections.abc import Callable

import serial
import serial_asyncio_fast

from servotune.transports.base import ByteChannel, EchoResult, LinkClosedError, Transaction


class _Exchange:
    """An echoed write, a read-until, or both in a row, advanced from ``data_received``.

    Running the per-character steps in the protocol callback, instead of waking the
    waiting task for every echo, takes one task switch per character out of the
    round trip (the SLAP2 protocol is nothing but round trips). With both a payload
    and a terminator (``transact``) the reply is read on from the callback that took
    the last echo: one task wake-up per transaction, and the arrival times stamped
    where the bytes come in.
    """

    def __init__(
        self,
        protocol: _SerialProtocol,
        *,
        payload: bytes = b"",
        terminator: int | None = None,
        count: int | None = None,
        first_timeout_s: float,
        char_timeout_s: float,
        first_reply_timeout_s: float | None = None,
        then: bytes = b"",
        may_chain: Callable[[], bool] | None = None,
    ) -> None:
        self.protocol = protocol
        self.payload = payload
        self.then = then
        self.may_chain = may_chain
        self.terminator = terminator
        self.count = count
        self.char_timeout_s = char_timeout_s
        self.first_reply_timeout_s = first_reply_timeout_s
        self.index = 0
        self.echo: EchoResult | None = None if payload else EchoResult(0, None)
        self.t_echo_s: float | None = None
        self.t_reply_s: float | None = None
        self.t_sent_s: float | None = None  # just before the last payload byte left
        self.loop = asyncio.get_running_loop()
        self.future: asyncio.Future[EchoResult | bytes | None] = self.loop.create_future()
        self.deadline = self.loop.time() + first_timeout_s
        self.timer = self.loop.call_at(self.deadline, self.on_timer)

    def restart_timer(self, timeout_s: float | None = None) -> None:
        # Only move the deadline; the armed timer re-arms itself when it fires early.
        # Cancelling and re-arming a timer for every character would cost more than
        # the rest of the per-character work.
        self.deadline = self.loop.time() + (self.char_timeout_s if timeout_s is None else timeout_s)

    def on_timer(self) -> None:
        if self.loop.time() < self.deadline:
            self.timer = self.loop.call_at(self.deadline, self.on_timer)
        else:
            self.on_timeout()

    def finish(self, result: EchoResult | bytes | None) -> None:
        self.timer.cancel()
        self.protocol.exchange = None
        if not self.future.done():
            self.future.set_result(result)

    def on_timeout(self) -> None:
        self.protocol.note_late(self.loop.time() - self.deadline)
        if self.echo is None:
            self.echo = EchoResult(self.index, None)
            self.finish(self.echo)
        else:
            self.finish(None)

    def step(self, now_s: float) -> None:
        """Consume what the buffer holds; called after every ``data_received`` with
        the time it was called."""
        buffer = self.protocol.buffer
        if self.echo is None:
            while buffer:
                expected = self.payload[self.index]
                got = buffer[0]
                del buffer[0]
                if got != expected:
                    self.echo = EchoResult(self.index, got)
                    self.finish(self.echo)
                    return
                self.index += 1
                if self.index == len(self.payload):
                    self.echo = EchoResult(self.index, None)
                    self.t_echo_s = now_s
                    if self.terminator is None:
                        self.finish(self.echo)
                        return
                    self.restart_timer(self.first_reply_timeout_s)
                    break
                self.send_next(now_s)
                self.restart_timer()
            else:
                return
        if self.count is not None:
            if len(buffer) >= self.count:
                data = bytes(buffer)
                buffer.clear()
                self.t_reply_s = now_s
                self.finish(data)
            return
        if self.terminator is not None:
            end = buffer.find(self.terminator)
            if end < 0:
                if buffer:  # the reply has begun: the gap between characters applies
                    self.restart_timer()
                return
            line = bytes(buffer[: end + 1])
            del buffer[: end + 1]
            self.t_reply_s = now_s
            self.finish(line)
            if self.then and not buffer and (self.may_chain is None or self.may_chain()):
                self._chain()

    def send_next(self, now_s: float) -> None:
        """Write payload byte ``index`` (stamping ``t_sent_s`` for the last one)."""
        if self.index == len(self.payload) - 1:
            self.t_sent_s = now_s
        self.protocol.send(self.payload[self.index : self.index + 1])

    def _chain(self) -> None:
        """Start the follow-up exchange ``then`` from this callback: its first byte
        leaves now, not after the waiting task has woken up and parsed this reply.
        ``SerialChannel.transact`` adopts it when that task asks for it."""
        chained = _Exchange(
            self.protocol,
            payload=self.then,
            terminator=self.terminator,
            first_timeout_s=self.char_timeout_s,
            char_timeout_s=self.char_timeout_s,
            first_reply_timeout_s=self.first_reply_timeout_s,
        )
        self.protocol.exchange = chained
        self.protocol.chained = chained
        chained.send_next(time.monotonic())


class _SerialProtocol(asyncio.Protocol):
    """Buffers received bytes and wakes a waiting reader; records a lost connection."""

    def __init__(self) -> None:
        self.buffer = bytearray()
        self.data_event = asyncio.Event()
        self.lost: Exception | None = None
        self.is_closed = False
        self.transport: asyncio.Transport | None = None
        self.exchange: _Exchange | None = None
        # A follow-up started from the receive callback (``_Exchange.then``) that no
        # ``transact`` has taken over yet; it may still be running (``exchange``).
        self.chained: _Exchange | None = None
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
        if self.exchange is not None:
            self.exchange.step(time.monotonic())
        self.data_event.set()

    def connection_lost(self, exc: Exception | None) -> None:
        self.is_closed = True
        self.lost = exc
        if self.exchange is not None:
            self.exchange.finish(None)
        self.data_event.set()


class SerialChannel(ByteChannel):
    """A ``ByteChannel`` over an open serial port."""

    def __init__(self, transport: asyncio.Transport, protocol: _SerialProtocol, path: str):
        self._transport = transport
        self._protocol = protocol
        self._path = path
        self._chains_dropped = 0

    def _check_open(self) -> None:
        if self._protocol.is_closed:
            reason = f": {self._protocol.lost}" if self._protocol.lost else ""
            raise LinkClosedError(f"{self._path} closed{reason}")

    @property
    def chains_dropped(self) -> int:
        return self._chains_dropped

    def take_timeout_late_s(self) -> float:
        late_s, self._protocol.timeout_late_s = self._protocol.timeout_late_s, 0.0
        return late_s

    async def settle(self, adopt: bytes = b"") -> Transaction | None:
        """End an exchange chained with ``transact(then=...)`` that is not ``adopt``:
        wait for it (its own timeouts bound that), drop it and return its outcome;
        None when there is none, or when it is ``adopt`` (left to be taken over)."""
        chained = self._protocol.chained
        if chained is None or (adopt and chained.payload == adopt):
            return None
        await self._settle()
        return self._outcome(chained)

    async def _settle(self, adopt: bytes = b"") -> _Exchange | None:
        """Before any other use of the line: the chained exchange, if it is the one
        asked for now (``adopt``, the next ``transact``'s payload), is handed back to
        be awaited; any other is waited out and dropped, so that its bytes never mix
        with the next exchange's. A caller that must know how a dropped one ended
        (the SLAP2 driver sends Ctrl-X after a half-sent command) calls ``settle``
        first."""
        protocol = self._protocol
        chained = protocol.chained
        if chained is None:
            return None
        if adopt and chained.payload == adopt:
            protocol.chained = None
            return chained
        # Shielded: a cancelled caller leaves the chain running and still pending, for
        # the next call to settle (cancelling its future would orphan its bytes).
        await asyncio.shield(chained.future)
        if protocol.chained is chained:
            protocol.chained = None
            self._chains_dropped += 1
        chained.timer.cancel()
        if protocol.exchange is chained:
            protocol.exchange = None
        return None

    @staticmethod
    def _outcome(exchange: _Exchange) -> Transaction:
        """What an ended exchange got: its echo, and its reply line or None."""
        echo = exchange.echo
        if echo is None:  # the port closed during the echo
            echo = EchoResult(exchange.index, None)
        future = exchange.future
        result = future.result() if future.done() and not future.cancelled() else None
        reply = result if isinstance(result, bytes) else None
        return Transaction(echo, reply, exchange.t_echo_s, exchange.t_reply_s, exchange.t_sent_s)

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

    async def read_byte(self, timeout_s: float) -> int | None:
        await self._settle()
        await self._wait_data(timeout_s)
        buffer = self._protocol.buffer
        if buffer:
            byte = buffer[0]
            del buffer[0]
            return byte
        self._check_open()
        return None

    async def write_echoed(self, data: bytes, char_timeout_s: float) -> EchoResult:
        await self._settle()
        self._check_open()
        if not data:
            return EchoResult(0, None)
        exchange = _Exchange(
            self._protocol,
            payload=data,
            first_timeout_s=char_timeout_s,
            char_timeout_s=char_timeout_s,
        )
        result = await self._run(exchange, data[:1])
        if result is None:  # the port closed meanwhile
            self._check_open()
        assert isinstance(result, EchoResult)
        return result

    async def read_until(
        self, terminator: int, first_timeout_s: float, char_timeout_s: float
    ) -> bytes | None:
        await self._settle()
        self._check_open()
        exchange = _Exchange(
            self._protocol,
            terminator=terminator,
            first_timeout_s=first_timeout_s,
            char_timeout_s=char_timeout_s,
        )
        result = await self._run(exchange, b"")
        if result is None:
            self._check_open()
            return None
        assert isinstance(result, bytes)
        return result

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
        exchange = await self._settle(data)
        self._check_open()
        if exchange is not None:
            # Chained by the previous transact: already under way (or done).
            exchange.then, exchange.may_chain = then, may_chain
            result = await self._run(exchange, b"", started=True)
        else:
            exchange = _Exchange(
                self._protocol,
                payload=data,
                terminator=terminator,
                first_timeout_s=char_timeout_s,
                char_timeout_s=char_timeout_s,
                first_reply_timeout_s=first_reply_timeout_s,
                then=then,
                may_chain=may_chain,
            )
            result = await self._run(exchange, data[:1])
        echo = exchange.echo
        if echo is None:  # the port closed during the echo
            self._check_open()
            echo = EchoResult(exchange.index, None)
        reply = result if isinstance(result, bytes) else None
        if reply is None and echo.echoed == len(data):
            self._check_open()
        return Transaction(echo, reply, exchange.t_echo_s, exchange.t_reply_s, exchange.t_sent_s)

    async def _run(
        self, exchange: _Exchange, first: bytes, *, started: bool = False
    ) -> EchoResult | bytes | None:
        """Install ``exchange``, send ``first`` (the first payload byte, or nothing),
        and wait for its outcome, advanced from ``data_received``. ``started``: it was
        chained from the receive callback and runs already."""
        protocol = self._protocol
        if not started:
            protocol.exchange = exchange
        try:
            if first:
                exchange.send_next(time.monotonic())
            if not started:
                exchange.step(time.monotonic())  # what already sits in the buffer
            return await exchange.future
        finally:
            exchange.timer.cancel()
            # Not a follow-up this exchange chained from its last callback.
            if protocol.exchange is exchange:
                protocol.exchange = None

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
        exchange = _Exchange(
            self._protocol, count=count, first_timeout_s=timeout_s, char_timeout_s=timeout_s
        )
        result = await self._run(exchange, b"")
        if isinstance(result, bytes):
            return result, exchange.t_reply_s
        data = self.discard_input()  # a timeout: what came so far
        if not data:
            self._check_open()
        return data, None

    def discard_input(self) -> bytes:
        chained = self._protocol.chained
        if chained is not None and not chained.future.done():
            return b""  # what came belongs to the chained exchange under way
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
