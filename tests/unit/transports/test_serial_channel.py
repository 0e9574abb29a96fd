"""SerialChannel over a real pseudo-terminal. read_at_least: one wake-up for a reply
that arrives in pieces, the arrival stamped when the last needed byte came, and a
timeout that hands back what came so far. drive: a handler advanced from the receive
callback, its deadline kept (also when it moves on), its follow-up run unawaited
and waited out by any other call or taken over by driving it."""

from __future__ import annotations

import asyncio
import os
import time
from collections.abc import AsyncIterator

import pytest

from servotune.transports.base import LinkClosedError
from servotune.transports.serial import SerialChannel
from tests.support.pty_peer import PtyPeer, pty_channel
from tests.support.waiting import wait_for


@pytest.fixture
async def line() -> AsyncIterator[tuple[int, SerialChannel]]:
    async with pty_channel() as opened:
        yield opened


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
    # Delivered by the kernel's tty worker, which a loaded host can hold for seconds.
    await wait_for(lambda: len(channel._protocol.buffer) >= 6, 10, "the bytes at the channel")
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


async def test_a_timeout_the_stalled_host_noticed_late_is_reported_once(
    line: tuple[int, SerialChannel],
) -> None:
    """The loop is blocked (an injected stall: a callback that does not return) across a
    read's deadline: the channel reports how late its timeout was noticed, once."""
    _, channel = line
    loop = asyncio.get_running_loop()
    channel.take_timeout_late_s()
    loop.call_later(0.01, time.sleep, 0.4)  # the host stalls for 0.4 s
    assert await channel.read_at_least(1, 0.05) == (b"", None)  # a handler's deadline
    assert channel.take_timeout_late_s() >= 0.3
    assert channel.take_timeout_late_s() == 0.0
    loop.call_later(0.01, time.sleep, 0.4)
    assert await channel.read_available(0.05) == b""  # the plain wait
    assert channel.take_timeout_late_s() >= 0.3
    assert channel.take_timeout_late_s() == 0.0


# --- drive: a device's handler in the receive callback ------------------------------


class Ask:
    """Sends ``question``, done at the first ``\\n`` received (the line taken), or when
    no byte came for ``gap_s`` (``first_s`` for the first); then ``then`` follows."""

    def __init__(
        self, question: bytes, *, first_s: float = 1.0, gap_s: float = 1.0, then: bytes = b""
    ) -> None:
        self.question, self.first_s, self.gap_s, self.then = question, first_s, gap_s, then
        self.deadline_s: float | None = None
        self.done = False
        self.answer: bytes | None = None
        self.fed: list[bytes] = []
        self.followed: Ask | None = None

    def start(self, now_s: float) -> bytes:
        self.deadline_s = now_s + self.first_s
        return self.question

    def feed(self, received: bytearray, now_s: float) -> bytes:
        self.fed.append(bytes(received))
        end = received.find(b"\n")
        if end < 0:
            if received:
                self.deadline_s = now_s + self.gap_s
            return b""
        self.answer = bytes(received[: end + 1])
        del received[: end + 1]
        self.done = True
        return b""

    def expire(self, now_s: float) -> bytes:
        self.done = True
        return b""

    def follow_up(self) -> Ask | None:
        self.followed = Ask(self.then) if self.then else None
        return self.followed


class Answerer(PtyPeer):
    """Answers every ``?`` with ``<n>\\n`` (n counts the questions), after ``delay_s``."""

    def __init__(self, master: int, delay_s: float = 0.0) -> None:
        self.asked, self.delay_s = 0, delay_s
        super().__init__(master)

    def handle(self, byte: int) -> bytes:
        if byte != ord("?"):
            return bytes([byte])
        self.asked += 1
        time.sleep(self.delay_s)
        return b"%d\n" % self.asked


async def test_drive_runs_a_handler_to_its_end(line: tuple[int, SerialChannel]) -> None:
    master, channel = line
    peer = Answerer(master)
    try:
        ask = Ask(b"?")
        await channel.drive(ask)
        assert ask.answer == b"1\n" and ask.done
    finally:
        peer.stop()


async def test_a_follow_up_runs_unawaited_and_is_waited_out_by_other_calls(
    line: tuple[int, SerialChannel],
) -> None:
    master, channel = line
    peer = Answerer(master, delay_s=0.1)
    try:
        ask = Ask(b"?", then=b"?")
        await channel.drive(ask)
        assert ask.answer == b"1\n" and ask.followed is not None
        assert channel.discard_input() == b""  # its bytes are the follow-up's
        await channel.write(b"x")  # after the follow-up ended, not inside it
        assert ask.followed.answer == b"2\n"
        data, _ = await channel.read_at_least(1, 1.0)
        assert data == b"x"
    finally:
        peer.stop()


async def test_driving_the_follow_up_takes_it_over(line: tuple[int, SerialChannel]) -> None:
    master, channel = line
    peer = Answerer(master, delay_s=0.1)
    try:
        ask = Ask(b"?", then=b"?")
        await channel.drive(ask)
        follow = ask.followed
        assert follow is not None and not follow.done
        await channel.drive(follow)  # waits for it: not sent again
        assert follow.answer == b"2\n" and peer.asked == 2
    finally:
        peer.stop()


async def test_a_deadline_moved_later_is_kept(line: tuple[int, SerialChannel]) -> None:
    """The first byte came in time and moved the deadline on: the timer armed for the
    first byte does not end the handler, the gap's deadline does not pass either."""
    master, channel = line
    ask = Ask(b"", first_s=0.05, gap_s=2.0)
    loop = asyncio.get_running_loop()
    loop.call_later(0.01, os.write, master, b"1")
    loop.call_later(0.3, os.write, master, b"\n")
    await channel.drive(ask)
    assert ask.answer == b"1\n"


async def test_a_cancelled_drive_ends_its_handler(line: tuple[int, SerialChannel]) -> None:
    master, channel = line
    ask = Ask(b"")
    task = asyncio.create_task(channel.drive(ask))
    await asyncio.sleep(0.05)
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    os.write(master, b"late\n")
    await asyncio.sleep(0.05)
    assert ask.fed == [b""] and not ask.done  # fed no more
    assert await channel.read_available(1.0) == b"late\n"


async def test_drive_raises_when_the_port_closes(line: tuple[int, SerialChannel]) -> None:
    _, channel = line
    task = asyncio.create_task(channel.drive(Ask(b"")))
    await asyncio.sleep(0.05)
    await channel.close()
    with pytest.raises(LinkClosedError):
        await task
    with pytest.raises(LinkClosedError):
        await channel.drive(Ask(b""))
