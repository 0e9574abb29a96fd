"""A device on the master side of a pty, in a thread: each byte the host sends is
handed to ``handle``, and what it returns is written back (the tests' stand-in for
a module when the simulator's wire timing is not the subject); ``pty_channel`` opens
the host's end as a ``SerialChannel``."""

from __future__ import annotations

import contextlib
import os
import select
import threading
import tty
from collections.abc import AsyncIterator

from servotune.transports.serial import SerialChannel, SerialConnector


@contextlib.asynccontextmanager
async def pty_channel(baud: int = 38400) -> AsyncIterator[tuple[int, SerialChannel]]:
    """A raw pty: its master fd (the device's end) and a channel open on its slave."""
    master, slave = os.openpty()
    tty.setraw(master)
    channel = await SerialConnector(os.ttyname(slave), baud).open()
    try:
        yield master, channel
    finally:
        await channel.close()
        os.close(master)
        os.close(slave)


class PtyPeer:
    def __init__(self, master: int) -> None:
        self.master = master
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def handle(self, byte: int) -> bytes:
        """What the device sends back for ``byte`` (called in the peer's thread)."""
        raise NotImplementedError

    def _run(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.02)
            if not ready:
                continue
            try:
                data = os.read(self.master, 64)
            except OSError:
                return
            for byte in data:
                if out := self.handle(byte):
                    os.write(self.master, out)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
