"""A simulated serial device's shaft, recorded where the device runs, for measurements
that watch the device itself rather than what its driver reports (``perf.stops``).

``TracedDevice`` wraps a ``SimDevice`` and records one axis (host monotonic time, shaft
position in counts, shaft speed in counts/s) every time the device is advanced, and,
given a ``decode`` of the host's bytes into the driver's own text of each completed
command, when each command reached the device and the shaft there. Armed, it also keeps
a copy of the device as each command found it, so that ``unpowered`` can run the
device's power-off alone forward from the state a stop arrived in: the same position,
speed, currents and loop state, whatever the host's latency made of the phase. It runs
in the simulator's process (``traced_serial_process``). ``RemoteTrace`` is the measuring
side: it asks over the process's pipe (``SimProcess.request("device", ...)``), fetching
the points incrementally. The monotonic clock is the host's, the same in every process.
"""

from __future__ import annotations

import asyncio
import contextlib
import copy
import time
from collections.abc import AsyncIterator, Callable
from typing import Final, Generic, TypeAlias, TypeVar

from servotune.sim.base import SimDevice
from servotune.sim.process import SerialSimSpec, SimProcess, serve_serial

# (host monotonic time in s, shaft position in counts, shaft speed in counts/s)
ShaftPoint: TypeAlias = tuple[float, float, float]

D = TypeVar("D", bound=SimDevice)

# The latest copies kept while armed (each a few kB, ~2 ms to take): a stop's first
# command is among the last ones when the measurement disarms.
MAX_COPIES: Final = 256
# The step of an unpowered copy's run (s): finer than any demo plant's loop tick.
UNPOWERED_STEP_S: Final = 0.0005


def _wire_text(text: str) -> str:
    """A command as the trace compares it: no spaces, lower case."""
    return text.replace(" ", "").lower()


def unpowered_points(
    advance: Callable[[float], object],
    read: Callable[[], tuple[float, float]],
    at: float,
    rest_counts_s: float,
    rest_for_s: float,
    max_s: float,
) -> list[ShaftPoint]:
    """A copy of a device, already powered off, run forward in ``UNPOWERED_STEP_S``
    steps (``advance(elapsed_s)`` to that long after the copy was taken; ``read()``
    its shaft) until its speed stayed below ``rest_counts_s`` for ``rest_for_s`` or
    ``max_s`` passed: points on the host's clock from ``at``, when it was taken."""
    points = [(at, *read())]
    rest_since: float | None = None
    elapsed_s = 0.0
    while elapsed_s < max_s:
        elapsed_s += UNPOWERED_STEP_S
        advance(elapsed_s)
        position, speed = read()
        points.append((at + elapsed_s, position, speed))
        if abs(speed) >= rest_counts_s:
            rest_since = None
        elif rest_since is None:
            rest_since = elapsed_s
        elif elapsed_s - rest_since >= rest_for_s + UNPOWERED_STEP_S:
            break  # a step past it: the points' host times round differently
    return points


class TracedDevice(Generic[D]):
    """``device`` on the line, recording ``read(device)`` (position, speed) after every
    advance; ``powered()`` says whether the traced motor is under power; ``decode``
    (one host byte -> the commands it completes; None: commands are not traced);
    ``power_off(device)`` does to a device what its power-off command alone does to the
    traced motor (None: ``unpowered`` is not offered)."""

    def __init__(
        self,
        device: D,
        read: Callable[[D], tuple[float, float]],
        powered: Callable[[], bool],
        decode: Callable[[int], list[str]] | None = None,
        power_off: Callable[[D], None] | None = None,
    ) -> None:
        self.device = device
        self._read = read
        self._powered = powered
        self._decode = decode
        self._power_off = power_off
        self._device_time_s = 0.0
        self.points: list[ShaftPoint] = []
        self.commands: list[tuple[float, str, float, float]] = []
        self._armed = False
        # (host time, device time, the device as the command found it) per arrival
        self._copies: dict[float, tuple[float, D]] = {}

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

    def arm(self) -> None:
        """From now until ``disarm``, keep a copy of the device as each command finds
        it (the latest ``MAX_COPIES``; earlier ones are dropped)."""
        self._copies.clear()
        self._armed = self._power_off is not None

    def disarm(self) -> None:
        """No more copies; those taken are kept for ``unpowered``."""
        self._armed = False

    def unpowered(
        self, at: float, rest_counts_s: float, rest_for_s: float, max_s: float
    ) -> list[ShaftPoint] | None:
        """The traced shaft of the copy taken when a command arrived at host time
        ``at`` (an ``arrival``'s time), powered off as the device's power-off command
        alone does and run forward on its own, until its speed stayed below
        ``rest_counts_s`` for ``rest_for_s`` or ``max_s`` passed: points on the host's
        clock from ``at``. None: no copy was taken then. Holds the simulated device for
        as long as it runs (ask after the measurement)."""
        kept = self._copies.pop(at, None)
        if kept is None or self._power_off is None:
            return None
        device_time_s, device = kept
        self._power_off(device)
        return unpowered_points(
            lambda elapsed_s: device.advance_to(device_time_s + elapsed_s),
            lambda: self._read(device),
            at,
            rest_counts_s,
            rest_for_s,
            max_s,
        )

    def powered(self) -> bool:
        return self._powered()

    def advance_to(self, t_s: float) -> bytes:
        out = self.device.advance_to(t_s)
        self._device_time_s = max(self._device_time_s, t_s)
        position, speed = self._read(self.device)
        self.points.append((time.monotonic(), position, speed))
        return out

    def receive(self, byte: int) -> bytes:
        texts = self._decode(byte) if self._decode is not None else []
        if texts:
            # The device has been advanced to this byte's arrival: the shaft as the
            # command finds it, before the device acts on it.
            position, speed = self._read(self.device)
            t = time.monotonic()
            self.commands.extend((t, _wire_text(text), position, speed) for text in texts)
            if self._armed:
                self._copies[t] = (self._device_time_s, copy.deepcopy(self.device))
                if len(self._copies) > MAX_COPIES:
                    del self._copies[next(iter(self._copies))]
        return self.device.receive(byte)


class LineCommands:
    """A ``decode`` for a line protocol: the host's lines as a device reads them (``end``
    completes a line, ``cancel`` discards the line typed so far, control characters
    are not part of it)."""

    def __init__(self, end: int = 0x0D, cancel: int | None = None) -> None:
        self._end = end
        self._cancel = cancel
        self._buffer = bytearray()

    def __call__(self, byte: int) -> list[str]:
        if byte == self._end:
            line = self._buffer.decode("latin-1")
            self._buffer.clear()
            return [line]
        if byte == self._cancel:
            self._buffer.clear()
        elif byte >= 0x20:
            self._buffer.append(byte)
        return []


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

    async def arm(self) -> None:
        """See ``TracedDevice.arm``."""
        await asyncio.to_thread(self._process.request, "device", method="arm")

    async def disarm(self) -> None:
        """See ``TracedDevice.disarm``."""
        await asyncio.to_thread(self._process.request, "device", method="disarm")

    async def unpowered(
        self, at: float, rest_counts_s: float, rest_for_s: float, max_s: float
    ) -> list[ShaftPoint] | None:
        """See ``TracedDevice.unpowered``."""
        found = await asyncio.to_thread(
            self._process.request,
            "device",
            method="unpowered",
            at=at,
            rest_counts_s=rest_counts_s,
            rest_for_s=rest_for_s,
            max_s=max_s,
        )
        return None if found is None else [(p[0], p[1], p[2]) for p in found]


@contextlib.asynccontextmanager
async def traced_serial_process(
    name: str, build: Callable[[], TracedDevice[D]], baud: int
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
