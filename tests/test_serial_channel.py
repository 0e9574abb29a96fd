"""SerialChannel.read_at_least over a real pseudo-terminal: one wake-up for a reply that
arrives in pieces, the arrival stamped when the last needed byte came, and a timeout
that hands back what came so far."""

from __future__ import annotations

import asyncio
import os
import time
import tty
from collections.abc import AsyncIterator

import pytest

from servotune.transports.base import LinkClosedError
from servotune.transports.serial import SerialChannel, SerialConnector


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
