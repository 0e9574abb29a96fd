"""A canary through the host's tty layer: how long it is holding bytes back right now.

A serial device's bytes reach the server through the kernel's tty layer: a real
adapter's and a pseudo-terminal's alike are pushed to the line discipline by a kernel
worker thread (``tty_flip_buffer_push``) at normal priority. On a host loaded far
beyond its cores that worker can be starved for a second or two while the server
itself runs on time: the device answered, its bytes are held in the host. A read that
times out then is no evidence against the device.

``TtyProbe`` measures exactly that path: one byte at a time written into a private
pseudo-terminal and read back on its other side, a new one ``period_s`` after the
last came through. ``held_s(window_s)`` is the longest a byte was held among those in
flight during the last ``window_s`` (one still in flight counts until now). It runs on
the event loop that reads the serial ports, so a stalled loop shows in it too (that
is a host stall as well). Linux and other POSIX hosts; where no pty can be opened,
``start`` says so and ``held_s`` is 0 (no evidence, the rules as without it).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time
from collections import deque
from collections.abc import Callable
from typing import Final

logger = logging.getLogger(__name__)

# One canary byte this long after the last came through: a stall that starts is seen
# within this much (short against the 100-150 ms the serial links listen for a reply),
# at the cost of ~20 pty round trips a second per link.
PERIOD_S: Final = 0.05
# Flights kept for ``held_s`` (longer than any window asked for).
KEEP_S: Final = 10.0


class TtyProbe:
    """The host tty layer's canary (see the module docstring). ``start`` on the event
    loop that reads the serial ports, ``close`` when done; ``held_s`` at any time."""

    def __init__(
        self, *, period_s: float = PERIOD_S, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self._period_s = period_s
        self._clock = clock
        self._fds: tuple[int, int] | None = None
        self._task: asyncio.Task[None] | None = None
        self._arrived = asyncio.Event()
        self._sent_at: float | None = None  # the byte in flight, when it was written
        self._flights: deque[tuple[float, float]] = deque()  # (written, came through)

    def start(self) -> bool:
        """Open the pty and start the canary; False (logged) where no pty opens."""
        if self._task is not None:
            return True
        try:
            import pty
            import tty

            master, slave = pty.openpty()
            tty.setraw(slave)  # every byte through at once, no echo, no line editing
            os.set_blocking(master, False)
            os.set_blocking(slave, False)
        except (ImportError, OSError) as exc:
            logger.warning("no tty canary (%s): host tty stalls are not told apart", exc)
            return False
        self._fds = (master, slave)
        loop = asyncio.get_running_loop()
        loop.add_reader(slave, self._on_readable)
        self._task = loop.create_task(self._run(), name="tty canary")
        return True

    async def close(self) -> None:
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        fds, self._fds = self._fds, None
        if fds is not None:
            asyncio.get_running_loop().remove_reader(fds[1])
            for fd in fds:
                os.close(fd)
        self._sent_at = None

    @property
    def canaries(self) -> int:
        """Canary bytes that came through since the start (of those kept)."""
        return len(self._flights)

    def held_s(self, window_s: float) -> float:
        """The longest the tty layer held a canary byte among those in flight at any
        time during the last ``window_s`` (the one in flight: until now)."""
        now = self._clock()
        since = now - window_s
        worst = 0.0 if self._sent_at is None else now - self._sent_at
        for written, came in reversed(self._flights):
            if came < since:
                break
            worst = max(worst, came - written)
        return worst

    def _on_readable(self) -> None:
        if self._fds is None:
            return
        with contextlib.suppress(BlockingIOError, InterruptedError):
            os.read(self._fds[1], 64)
        if self._sent_at is not None:
            came = self._clock()
            self._flights.append((self._sent_at, came))
            self._sent_at = None
            while self._flights and came - self._flights[0][1] > KEEP_S:
                self._flights.popleft()
        self._arrived.set()

    async def _run(self) -> None:
        while self._fds is not None:
            self._arrived.clear()
            self._sent_at = self._clock()
            try:
                os.write(self._fds[0], b"\0")
            except OSError as exc:
                logger.warning("tty canary stopped: %s", exc)
                self._sent_at = None
                return
            await self._arrived.wait()
            await asyncio.sleep(self._period_s)
