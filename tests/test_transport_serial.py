"""The serial transport on a bare pseudo-terminal: the far end is this test (the pty
master), so every byte and every timing is under the test's control."""

from __future__ import annotations

import asyncio
import os
import tty
from collections.abc import AsyncIterator

import pytest

from servotune.transports.base import EchoResult, LinkClosedError
from servotune.transports.serial import SerialChannel, SerialConnector


@pytest.fixture
async def line() -> AsyncIterator[tuple[SerialChannel, int]]:
    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    channel = await SerialConnector(os.ttyname(slave), 19200).open()
    os.close(slave)  # the channel holds its own fd
    try:
        yield channel, master
    finally:
        await channel.close()
        os.close(master)


async def _read_master(master: int, count: int, timeout_s: float = 2.0) -> bytes:
    data = b""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    while len(data) < count and loop.time() < deadline:
        try:
            data += os.read(master, count - len(data))
        except BlockingIOError:
            await asyncio.sleep(0.001)
    return data


async def test_read_at_least_wakes_once_the_count_is_there(
    line: tuple[SerialChannel, int],
) -> None:
    channel, master = line
    reader = asyncio.create_task(channel.read_at_least(6, 2.0))
    os.write(master, b"abc")
    await asyncio.sleep(0.05)
    assert not reader.done()  # three of six bytes: still waiting
    os.write(master, b"defg")
    assert await asyncio.wait_for(reader, 2.0) == b"abcdefg"  # everything buffered


async def test_read_at_least_returns_what_came_when_the_time_is_up(
    line: tuple[SerialChannel, int],
) -> None:
    channel, master = line
    os.write(master, b"xy")
    loop = asyncio.get_running_loop()
    started = loop.time()
    assert await channel.read_at_least(6, 0.1) == b"xy"
    assert loop.time() - started >= 0.1 - 0.005  # the loop clock's resolution
    assert await channel.read_at_least(1, 0.05) == b""  # nothing: empty, no error


async def test_a_short_timeout_fires_after_an_exchange_with_a_long_one(
    line: tuple[SerialChannel, int],
) -> None:
    """One timer serves every exchange: a later exchange with an earlier deadline must
    still time out on time, and one with a later deadline must not time out early."""
    channel, master = line
    slow = asyncio.create_task(channel.read_until(0x0D, 5.0, 5.0))
    await asyncio.sleep(0.02)
    os.write(master, b"ok\r")
    assert await asyncio.wait_for(slow, 2.0) == b"ok\r"
    loop = asyncio.get_running_loop()
    started = loop.time()
    assert await asyncio.wait_for(channel.read_until(0x0D, 0.1, 0.1), 2.0) is None
    assert 0.1 - 0.005 <= loop.time() - started < 1.0
    # A long exchange after the short one: the timer armed for it fires early and
    # re-arms; the reply that comes after the short deadline is still taken.
    later = asyncio.create_task(channel.read_until(0x0D, 0.5, 0.5))
    await asyncio.sleep(0.2)
    os.write(master, b"late\r")
    assert await asyncio.wait_for(later, 2.0) == b"late\r"


async def test_echoed_write_sends_each_byte_after_the_previous_echo(
    line: tuple[SerialChannel, int],
) -> None:
    channel, master = line
    exchange = asyncio.create_task(channel.write_echoed(b"rp\r", 1.0))
    sent = b""
    for expected in b"rp\r":
        byte = await _read_master(master, 1)
        assert byte == bytes([expected])
        await asyncio.sleep(0.01)
        assert await _read_master(master, 1, 0.01) == b""  # nothing ahead of the echo
        sent += byte
        os.write(master, byte)  # the echo
    assert await asyncio.wait_for(exchange, 2.0) == EchoResult(3, None)
    assert sent == b"rp\r"


async def test_wrong_echo_and_missing_echo(line: tuple[SerialChannel, int]) -> None:
    channel, master = line
    exchange = asyncio.create_task(channel.write_echoed(b"ab", 1.0))
    assert await _read_master(master, 1) == b"a"
    os.write(master, b"z")
    assert await asyncio.wait_for(exchange, 2.0) == EchoResult(0, ord("z"))
    assert await channel.write_echoed(b"c", 0.05) == EchoResult(0, None)


async def test_a_closed_channel_ends_its_reader(line: tuple[SerialChannel, int]) -> None:
    channel, _master = line
    reader = asyncio.create_task(channel.read_at_least(1, 5.0))
    await asyncio.sleep(0.02)
    await channel.close()
    with pytest.raises(LinkClosedError):
        await asyncio.wait_for(reader, 2.0)
    with pytest.raises(LinkClosedError):
        await channel.write(b"x")


async def test_a_hung_up_line_raises_link_closed() -> None:
    """The far end goes away (a pty master closed, like a USB adapter pulled): the
    read fails with EIO and the channel reports the port as closed."""
    master, slave = os.openpty()
    tty.setraw(slave)
    channel = await SerialConnector(os.ttyname(slave), 19200).open()
    os.close(slave)
    reader = asyncio.create_task(channel.read_at_least(1, 5.0))
    await asyncio.sleep(0.02)
    os.close(master)
    with pytest.raises(LinkClosedError):
        await asyncio.wait_for(reader, 2.0)
    assert channel.closed
    await channel.close()  # idempotent
