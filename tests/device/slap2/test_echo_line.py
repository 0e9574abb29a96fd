"""EchoLine over a SerialChannel on a real pseudo-terminal: transact(then=...) chains
the next read from the receive callback; the next transact takes it over, anything
else waits it out and drops its reply (counted)."""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator
from typing import Any

import pytest

from servotune.devices.slap2.echo import EchoLine
from servotune.transports.base import LinkClosedError
from tests.support.pty_peer import PtyPeer, pty_channel


@pytest.fixture
async def pty_echo_line() -> AsyncIterator[tuple[int, EchoLine]]:
    async with pty_channel() as (master, channel):
        yield master, EchoLine(channel)


# --- transact(then=...): the next read chained from the receive callback --------------


class EchoPeer(PtyPeer):
    """A device on the pty's master side: echoes every byte; after a CR answers
    ``<command>=ok`` CR. Records when each command's first byte arrived."""

    def __init__(self, master: int, slow: bytes = b"", delay_s: float = 0.0) -> None:
        self.started: list[tuple[bytes, float]] = []  # (command, first byte's arrival)
        self.slow, self.delay_s = slow, delay_s  # echo a command starting so late
        self._pending = b""
        super().__init__(master)

    def handle(self, byte: int) -> bytes:
        if not self._pending:
            self.started.append((b"", time.monotonic()))
        self._pending += bytes([byte])
        if self.slow and self._pending.startswith(self.slow):
            time.sleep(self.delay_s)
        if byte != 0x0D:
            return bytes([byte])
        command, self._pending = self._pending[:-1], b""
        self.started[-1] = (command, self.started[-1][1])
        return b"\r" + command + b"=ok\r"

    def commands(self) -> list[bytes]:
        return [command for command, _ in self.started]


@pytest.fixture
async def peer(pty_echo_line: tuple[int, EchoLine]) -> AsyncIterator[tuple[EchoPeer, EchoLine]]:
    master, echo = pty_echo_line
    device = EchoPeer(master)
    try:
        yield device, echo
    finally:
        device.stop()


async def _transact(echo: EchoLine, data: bytes, **kwargs: Any) -> bytes | None:
    done = await echo.transact(data, 0x0D, 0.5, 0.5, **kwargs)
    assert done.echo.echoed == len(data), done.echo
    return done.reply


async def test_a_chained_read_is_on_the_wire_before_it_is_asked_for(
    peer: tuple[EchoPeer, EchoLine],
) -> None:
    device, echo = peer
    assert await _transact(echo, b"rp\r", then=b"pe\r") == b"rp=ok\r"
    await asyncio.sleep(0.2)  # the caller is busy: the line is not idle meanwhile
    asked_at = time.monotonic()
    assert device.commands() == [b"rp", b"pe"]
    assert device.started[1][1] < asked_at
    done = await echo.transact(b"pe\r", 0x0D, 0.5, 0.5)
    assert done.reply == b"pe=ok\r" and done.echo.echoed == 3
    assert done.t_reply_s is not None and done.t_reply_s < asked_at  # stamped when it came
    assert echo.chains_dropped == 0


async def test_no_chain_while_may_chain_says_no(peer: tuple[EchoPeer, EchoLine]) -> None:
    device, echo = peer
    assert await _transact(echo, b"rp\r", then=b"pe\r", may_chain=lambda: False) == b"rp=ok\r"
    await asyncio.sleep(0.2)
    assert device.commands() == [b"rp"]  # a STOP waiting: nothing more went out
    assert await _transact(echo, b"st\r") == b"st=ok\r"
    assert device.commands() == [b"rp", b"st"]


async def test_chains_follow_each_other(peer: tuple[EchoPeer, EchoLine]) -> None:
    device, echo = peer
    assert await _transact(echo, b"rp\r", then=b"pe\r") == b"rp=ok\r"
    assert await _transact(echo, b"pe\r", then=b"rss\r") == b"pe=ok\r"
    assert await _transact(echo, b"rss\r") == b"rss=ok\r"
    assert device.commands() == [b"rp", b"pe", b"rss"]
    assert echo.chains_dropped == 0


async def test_another_call_waits_for_the_chain_and_drops_its_reply(
    peer: tuple[EchoPeer, EchoLine],
) -> None:
    device, echo = peer
    assert await _transact(echo, b"rp\r", then=b"pe\r") == b"rp=ok\r"
    assert echo.channel.discard_input() == b""  # the chain's bytes are not stray input
    # Not the read that was guessed: it ends first, its reply never reaches this one.
    assert await _transact(echo, b"se1\r") == b"se1=ok\r"
    assert device.commands() == [b"rp", b"pe", b"se1"]
    assert echo.chains_dropped == 1


async def test_a_plain_write_waits_for_the_chain(peer: tuple[EchoPeer, EchoLine]) -> None:
    device, echo = peer
    assert await _transact(echo, b"rp\r", then=b"pe\r") == b"rp=ok\r"
    await echo.channel.write(b"\x18")  # e.g. Ctrl-X: not inside the chained read's bytes
    data, _ = await echo.channel.read_at_least(1, 0.5)
    assert data == b"\x18"  # its echo, after the whole chained read
    assert device.commands()[:2] == [b"rp", b"pe"]
    dropped = await echo.settle()  # how the dropped read ended is still known
    assert dropped is not None and dropped.reply == b"pe=ok\r" and echo.chains_dropped == 1


async def test_a_chain_on_a_port_that_closed_raises_when_taken_over(
    pty_echo_line: tuple[int, EchoLine],
) -> None:
    master, echo = pty_echo_line
    device = EchoPeer(master)
    try:
        assert await _transact(echo, b"rp\r", then=b"pe\r") == b"rp=ok\r"
    finally:
        device.stop()
    await echo.channel.close()
    with pytest.raises(LinkClosedError):
        await echo.transact(b"pe\r", 0x0D, 0.5, 0.5)


async def test_settle_says_how_a_dropped_chain_ended(peer: tuple[EchoPeer, EchoLine]) -> None:
    _, echo = peer
    assert await _transact(echo, b"rp\r", then=b"pe\r") == b"rp=ok\r"
    assert await echo.settle(b"pe\r") is None  # the one asked for: left to take over
    assert echo.chains_dropped == 0
    dropped = await echo.settle(b"st\r")
    assert dropped is not None and dropped.reply == b"pe=ok\r" and dropped.echo.echoed == 3
    assert await echo.settle() is None and echo.chains_dropped == 1
    assert await _transact(echo, b"st\r") == b"st=ok\r"


async def test_a_cancelled_wait_leaves_the_chain_to_the_next_call(
    pty_echo_line: tuple[int, EchoLine],
) -> None:
    master, echo = pty_echo_line
    device = EchoPeer(master, slow=b"pe", delay_s=0.1)  # the chained read takes 0.2 s
    try:
        assert await _transact(echo, b"rp\r", then=b"pe\r") == b"rp=ok\r"
        waiting = asyncio.create_task(echo.channel.read_available(1.0))
        await asyncio.sleep(0.05)
        waiting.cancel()
        with pytest.raises(asyncio.CancelledError):
            await waiting
        dropped = await echo.settle()  # still known, still running, then ended
        assert dropped is not None and dropped.reply == b"pe=ok\r"
        assert await _transact(echo, b"st\r") == b"st=ok\r"
    finally:
        device.stop()
