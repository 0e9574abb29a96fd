"""A simulated serial device's shaft, recorded where the device runs, for measurements
that watch the device itself rather than what its driver reports (``perf.stops``).

``TracedDevice`` wraps a ``SimDevice`` and records one axis (host monotonic time, shaft
position in counts, shaft speed in counts/s) every time the device is advanced, and,
given a ``decode`` of the host's bytes into the driver's own text of each completed
command, when each command reached the device and the shaft there. It runs in the
simulator's process (``traced_serial_process``). ``RemoteTrace`` is the measuring side:
it asks over the process's pipe (``SimProcess.request("device", ...)``), fetching the
points incrementally. The monotonic clock is the host's, the same in every process.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator, Callable
from typing import TypeAlias

from servotune.sim.base import SimDevice
from servotune.sim.process import SerialSimSpec, SimProcess, serve_serial

# (host monotonic time in s, shaft position in counts, shaft speed in counts/s)
ShaftPoint: TypeAlias = tuple[float, float, float]


def _wire_text(text: str) -> str:
    """A command as the trace compares it: no spaces, lower case."""
    return text.replace(" ", "").lower()


class TracedDevice:
    """``device`` on the line, recording ``read()`` (position, speed) after every
    advance; ``powered()`` says whether the traced motor is under power; ``decode``
    (one host byte -> the commands it completes; None: commands are not traced)."""

    def __init__(
        self,
        device: SimDevice,
        read: Callable[[], tuple[float, float]],
        powered: Callable[[], bool],
        decode: Callable[[int], list[str]] | None = None,
    ) -> None:
        self.device = device
        self._read = read
        self._powered = powered
        self._decode = decode
        self.points: list[ShaftPoint] = []
        self.commands: list[tuple[float, str, float, float]] = []

    def points_since(self, start: int) -> list[ShaftPoint]:
        return self.points[start:]

    def arrival(self, texts: list[str], since: float) -> ShaftPoint | None:
        """(time, position, speed) when the first of ``texts`` reached the device at or
        after ``since``; None if none did."""
        wanted = {_wire_text(text) for text in texts}
        for t, text, position, speed in self.commands:
            if t >= since and text in wanted:
                return t, position, speed
        return None

    def powered(self) -> bool:
        return self._powered()

    def advance_to(self, t_s: float) -> bytes:
        out = self.device.advance_to(t_s)
        position, speed = self._read()
        self.points.append((time.monotonic(), position, speed))
        return out

    def receive(self, byte: int) -> bytes:
        texts = self._decode(byte) if self._decode is not None else []
        if texts:
            # The device has been advanced to this byte's arrival: the shaft as the
            # command finds it, before the device acts on it.
            position, speed = self._read()
            t = time.monotonic()
            self.commands.extend((t, _wire_text(text), position, speed) for text in texts)
        return self.device.receive(byte)


class RemoteTrace:
    """The measuring side of a ``TracedDevice`` in a simulator's process."""

    def __init__(self, process: SimProcess) -> None:
        self._process = process
        self.points: list[ShaftPoint] = []

    async def trace(self) -> list[ShaftPoint]:
        """Every point so far (the new ones fetched from the process)."""
        new = await asyncio.to_thread(
            self._process.request, "device", method="points_since", start=len(self.points)
        )
        self.points.extend(tuple(p) for p in new)
        return list(self.points)

    async def powered(self) -> bool:
        return bool(await asyncio.to_thread(self._process.request, "device", method="powered"))

    async def reached(self, method: str, since: float, sent: list[str]) -> ShaftPoint | None:
        """The shaft when the first of the commands ``sent`` (the stop ``method`` asked
        for at ``since``) reached the device; None if the device saw none of them."""
        found = await asyncio.to_thread(
            self._process.request, "device", method="arrival", texts=sent, since=since
        )
        return None if found is None else (found[0], found[1], found[2])


@contextlib.asynccontextmanager
async def traced_serial_process(
    name: str, build: Callable[[], TracedDevice], baud: int
) -> AsyncIterator[tuple[str, RemoteTrace]]:
    """``build()`` (picklable: a module-level function or a ``functools.partial`` of
    one) on a pty at ``baud`` in a process of its own, as the demo runs it; yields the
    pty's path and the trace. The process is stopped on leaving."""
    process = SimProcess(name, serve_serial, SerialSimSpec(name, build, baud))
    await asyncio.to_thread(process.start)
    try:
        yield process.ready["path"], RemoteTrace(process)
    finally:
        await asyncio.to_thread(process.stop)
