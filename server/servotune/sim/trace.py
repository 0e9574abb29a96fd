"""A simulated serial device's shaft, recorded where the device runs, for measurements
that watch the device itself rather than what its driver reports (``perf.stops``).

``TracedDevice`` wraps a ``SimDevice`` and records one axis (host monotonic time, shaft
position in counts, shaft speed in counts/s) every time the device is advanced; it runs
in the simulator's process (``traced_serial_process``). ``RemoteTrace`` is the
measuring side: it fetches the points so far incrementally over the process's pipe
(``SimProcess.request("device", ...)``). The monotonic clock is the host's, the same
in every process.
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


class TracedDevice:
    """``device`` on the line, recording ``read()`` (position, speed) after every
    advance; ``powered()`` says whether the traced motor is under power."""

    def __init__(
        self,
        device: SimDevice,
        read: Callable[[], tuple[float, float]],
        powered: Callable[[], bool],
    ) -> None:
        self.device = device
        self._read = read
        self._powered = powered
        self.points: list[ShaftPoint] = []

    def points_since(self, start: int) -> list[ShaftPoint]:
        return self.points[start:]

    def powered(self) -> bool:
        return self._powered()

    def advance_to(self, t_s: float) -> bytes:
        out = self.device.advance_to(t_s)
        position, speed = self._read()
        self.points.append((time.monotonic(), position, speed))
        return out

    def receive(self, byte: int) -> bytes:
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
