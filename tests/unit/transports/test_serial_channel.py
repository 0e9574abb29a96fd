"""SerialChannel over a real pseudo-terminal. read_at_least: one wake-up for a reply
that arrives in pieces, the arrival stamped when the last needed byte came, and a
timeout that hands back what came so far. transact(then=...): the next read chained
from the receive callback, taken over by the next transact, or waited out and dropped
when something else is asked for."""

from __future__ import annotations

import asyncio
import os
import time
import tty
from collections.abc import AsyncIterator
from typing import Any

import pytest

from servotune.transports.base import LinkClosedError
from servotune.transports.serial import SerialChannel, SerialConnector
from tests.support.pty_peer import PtyPeer


@pytest.fixture
async def line() -> AsyncIterator[tuple[int, SerialChannel]]:
    master, slave = os.openpty()
    tty.setraw(master)
    path = os.ttyname(slave)
    channel = await SerialConnector(path, 38400).open()
    try:
        yield master, channel
    finally:
        await channel.close()
        os.close(master)
        os.close(slave)


async def test_read_at_least_waits_for_the_whole_count(line: tuple[int, SerialChannel]) -> None:
    master, channel = line
    loop = asyncio.get_running_loop()
    written: list[float] = []

    def send(piece: bytes) -> None:
        written.append(time.monotonic())
        os.write(master, piece)

    for i, piece in enumerate((b"\x01\x02", b"\x03", b"\x04\x05\x06\x07")):
        loop.call_later(0.02 * (i + 1), send, piece)
    data, t_s = await channel.read_at_least(6, 2.0)
    # all that had come when the 6th byte arrived: the last piece brings two more
    assert data == bytes(range(1, 8))
    assert t_s is not None and t_s >= written[-1]


async def test_read_at_least_takes_what_is_buffered_at_once(
    line: tuple[int, SerialChannel],
) -> None:
    master, channel = line
    os.write(master, b"abcdef")
    await asyncio.sleep(0.05)
    data, t_s = await channel.read_at_least(6, 0.0)
    assert data == b"abcdef" and t_s is not None


async def test_read_at_least_timeout_returns_the_partial_data(
    line: tuple[int, SerialChannel],
) -> None:
    master, channel = line
    os.write(master, b"xyz")
    started = time.monotonic()
    data, t_s = await channel.read_at_least(6, 0.15)
    assert (data, t_s) == (b"xyz", None)
    assert time.monotonic() - started >= 0.15
    assert await channel.read_at_least(1, 0.05) == (b"", None)  # nothing left behind


async def test_read_at_least_on_a_closed_port_raises(line: tuple[int, SerialChannel]) -> None:
    _, channel = line
    await channel.close()
    with pytest.raises(LinkClosedError):
        await channel.read_at_least(6, 0.1)


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
async def peer(line: tuple[int, SerialChannel]) -> AsyncIterator[tuple[EchoPeer, SerialChannel]]:
    master, channel = line
    device = EchoPeer(master)
    try:
        yield device, channel
    finally:
        device.stop()


async def _transact(channel: SerialChannel, data: bytes, **kwargs: Any) -> bytes | None:
    done = await channel.transact(data, 0x0D, 0.5, 0.5, **kwargs)
    assert done.echo.echoed == len(data), done.echo
    return done.reply


async def test_a_chained_read_is_on_the_wire_before_it_is_asked_for(
    peer: tuple[EchoPeer, SerialChannel],
) -> None:
    device, channel = peer
    assert await _transact(channel, b"rp\r", then=b"pe\r") == b"rp=ok\r"
    await asyncio.sleep(0.2)  # the caller is busy: the line is not idle meanwhile
    asked_at = time.monotonic()
    assert device.commands() == [b"rp", b"pe"]
    assert device.started[1][1] < asked_at
    done = await channel.transact(b"pe\r", 0x0D, 0.5, 0.5)
    assert done.reply == b"pe=ok\r" and done.echo.echoed == 3
    assert done.t_reply_s is not None and done.t_reply_s < asked_at  # stamped when it came
    assert channel.chains_dropped == 0


async def test_no_chain_while_may_chain_says_no(peer: tuple[EchoPeer, SerialChannel]) -> None:
    device, channel = peer
    assert await _transact(channel, b"rp\r", then=b"pe\r", may_chain=lambda: False) == b"rp=ok\r"
    await asyncio.sleep(0.2)
    assert device.commands() == [b"rp"]  # a STOP waiting: nothing more went out
    assert await _transact(channel, b"st\r") == b"st=ok\r"
    assert device.commands() == [b"rp", b"st"]


async def test_chains_follow_each_other(peer: tuple[EchoPeer, SerialChannel]) -> None:
    device, channel = peer
    assert await _transact(channel, b"rp\r", then=b"pe\r") == b"rp=ok\r"
    assert await _transact(channel, b"pe\r", then=b"rss\r") == b"pe=ok\r"
    assert await _transact(channel, b"rss\r") == b"rss=ok\r"
    assert device.commands() == [b"rp", b"pe", b"rss"]
    assert channel.chains_dropped == 0


async def test_another_call_waits_for_the_chain_and_drops_its_reply(
    peer: tuple[EchoPeer, SerialChannel],
) -> None:
    device, channel = peer
    assert await _transact(channel, b"rp\r", then=b"pe\r") == b"rp=ok\r"
    assert channel.discard_input() == b""  # the chain's bytes are not stray input
    # Not the read that was guessed: it ends first, its reply never reaches this one.
    assert await _transact(channel, b"se1\r") == b"se1=ok\r"
    assert device.commands() == [b"rp", b"pe", b"se1"]
    assert channel.chains_dropped == 1


async def test_a_plain_write_waits_for_the_chain(peer: tuple[EchoPeer, SerialChannel]) -> None:
    device, channel = peer
    assert await _transact(channel, b"rp\r", then=b"pe\r") == b"rp=ok\r"
    await channel.write(b"\x18")  # e.g. Ctrl-X: not inside the chained read's bytes
    data, _ = await channel.read_at_least(1, 0.5)
    assert data == b"\x18"  # its echo, after the whole chained read
    assert device.commands()[:2] == [b"rp", b"pe"]
    assert channel.chains_dropped == 1


async def test_a_chain_on_a_port_that_closed_raises_when_taken_over(
    line: tuple[int, SerialChannel],
) -> None:
    master, channel = line
    device = EchoPeer(master)
    try:
        assert await _transact(channel, b"rp\r", then=b"pe\r") == b"rp=ok\r"
    finally:
        device.stop()
    await channel.close()
    with pytest.raises(LinkClosedError):
        await channel.transact(b"pe\r", 0x0D, 0.5, 0.5)


async def test_settle_says_how_a_dropped_chain_ended(peer: tuple[EchoPeer, SerialChannel]) -> None:
    _, channel = peer
    assert await _transact(channel, b"rp\r", then=b"pe\r") == b"rp=ok\r"
    assert await channel.settle(b"pe\r") is None  # the one asked for: left to take over
    assert channel.chains_dropped == 0
    dropped = await channel.settle(b"st\r")
    assert dropped is not None and dropped.reply == b"pe=ok\r" and dropped.echo.echoed == 3
    assert await channel.settle() is None and channel.chains_dropped == 1
    assert await _transact(channel, b"st\r") == b"st=ok\r"


async def test_a_cancelled_wait_leaves_the_chain_to_the_next_call(
    line: tuple[int, SerialChannel],
) -> None:
    master, channel = line
    device = EchoPeer(master, slow=b"pe", delay_s=0.1)  # the chained read takes 0.2 s
    try:
        assert await _transact(channel, b"rp\r", then=b"pe\r") == b"rp=ok\r"
        waiting = asyncio.create_task(channel.read_available(1.0))
        await asyncio.sleep(0.05)
        waiting.cancel()
        with pytest.raises(asyncio.CancelledError):
            await waiting
        dropped = await channel.settle()  # still known, still running, then ended
        assert dropped is not None and dropped.reply == b"pe=ok\r"
        assert await _transact(channel, b"st\r") == b"st=ok\r"
    finally:
        device.stop()


async def test_a_timeout_the_stalled_host_noticed_late_is_reported_once(
    line: tuple[int, SerialChannel],
) -> None:
    """The loop is blocked (an injected stall: a callback that does not return) across a
    read's deadline: the channel reports how late its timeout was noticed, once."""
    _, channel = line
    loop = asyncio.get_running_loop()
    channel.take_timeout_late_s()
    for read in (
        lambda: channel.read_until(0x0D, 0.05, 0.05),  # the exchange path (its timer)
        lambda: channel.read_available(0.05),  # the plain wait
    ):
        loop.call_later(0.01, time.sleep, 0.4)  # the host stalls for 0.4 s
        assert not await read()
        assert channel.take_timeout_late_s() >= 0.3
        assert channel.take_timeout_late_s() == 0.0
