"""The demo's EP7047 as ``perf.stops`` measures a stop on it: the simulated drive
in-process behind a master that records the shaft after every exchange, the exchange
that carried a stop to the drive, and (armed) a copy of the drive's engine as each
exchange found it, to run forward with Enable off from a stop's arrival."""

from __future__ import annotations

import copy
import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from typing import Final

from servotune.devices.ep7047.codec import CYCLE_S, PosControl, StmControl, StmStatus
from servotune.devices.ep7047.sim.engine import Ep7047Engine
from servotune.devices.ep7047.sim.slave import (
    SimulatedEp7047Slave,
    SimulatedEthercatMaster,
    demo_slave,
)
from servotune.sim.trace import MAX_COPIES, ShaftPoint, unpowered_points

# The drive's and its driver's process-data watchdog on this rig: the host is what
# stalls here, not the drive (the measuring host's own thread cycles the in-process
# drive, and on a loaded host it can be held past the device's 100 ms; a trip
# mid-measurement is a coast, not the stop being measured). At 1 s a stall is latency,
# as it is for the serial devices.
STOP_PLANT_WATCHDOG_S: Final = 1.0


class TracedMaster(SimulatedEthercatMaster):
    """The simulated master, recording the shaft (host monotonic time, counts, counts/s)
    after every exchange, as ``sim.trace.TracedDevice`` does for a serial device."""

    def __init__(
        self,
        slaves: Sequence[SimulatedEp7047Slave],
        read: Callable[[], tuple[float, float]],
        exchanged: Callable[[], None] = lambda: None,
    ) -> None:
        super().__init__(slaves)
        self._read = read
        self._exchanged = exchanged
        self.points: list[ShaftPoint] = []

    def receive_processdata(self, timeout: int = 2000) -> int:
        wkc = super().receive_processdata(timeout)
        position, speed = self._read()
        self.points.append((time.monotonic(), position, speed))
        self._exchanged()
        return wkc


class StopPlant:
    """The demo's drive (``demo_slave``) with ``STOP_PLANT_WATCHDOG_S``, behind a
    ``TracedMaster``."""

    def __init__(self) -> None:
        self.drive = demo_slave()
        self.drive.watchdog_s = STOP_PLANT_WATCHDOG_S
        plant = self.drive.engine.plant
        self.master = TracedMaster(
            [self.drive], lambda: (plant.shaft_counts, plant.speed_counts_s), self._exchanged
        )
        self._armed = False
        # exchange time -> the drive's engine as that exchange found it (armed only)
        self._copies: dict[float, Ep7047Engine] = {}

    def _exchanged(self) -> None:
        history = self.drive.history
        if self._armed and history and history[-1].t not in self._copies:
            # The engine has run up to this exchange with the outputs before it: the
            # drive as the exchange's new outputs find it.
            self._copies[history[-1].t] = copy.deepcopy(self.drive.engine)
            if len(self._copies) > MAX_COPIES:
                del self._copies[next(iter(self._copies))]

    async def arm(self) -> None:
        """From now until ``disarm``, keep a copy of the engine at each exchange."""
        self._copies.clear()
        self._armed = True

    async def disarm(self) -> None:
        self._armed = False

    async def unpowered(
        self, at: float, rest_counts_s: float, rest_for_s: float, max_s: float
    ) -> list[ShaftPoint] | None:
        """The engine copied at the exchange at ``at`` (a ``reached`` time), run on with
        the outputs of the exchange before it with Enable off (what the power-off alone
        sends), as ``sim.trace.TracedDevice.unpowered`` does for a serial device."""
        engine = self._copies.pop(at, None)
        before = [e for e in list(self.drive.history) if e.t < at]
        if engine is None or not before:
            return None
        outputs = before[-1].outputs
        off = dataclasses.replace(outputs, stm_control=outputs.stm_control & ~StmControl.ENABLE)
        plant = engine.plant
        ran = 0

        def advance(elapsed_s: float) -> None:
            nonlocal ran
            due = math.floor(elapsed_s / CYCLE_S + 1e-9)  # the drive's 250 us cycles
            if due > ran:
                engine.run(off, due - ran)
                ran = due

        def read() -> tuple[float, float]:
            return plant.shaft_counts, plant.speed_counts_s

        return unpowered_points(advance, read, at, rest_counts_s, rest_for_s, max_s)

    def powered(self) -> bool:
        """The drive reports its output stage ready (enabled, powered) in its last
        exchange."""
        history = self.drive.history
        return bool(history and history[-1].inputs.stm_status & StmStatus.READY)

    async def reached(self, method: str, since: float, sent: list[str]) -> ShaftPoint | None:
        """The shaft when the first exchange at or after ``since`` carried ``method`` to
        the drive (STOP: the emergency stop bit; "power off": Enable off), with the
        position and speed of the first point after it (the drive acts on new outputs
        from that exchange on)."""
        for exchange in list(self.drive.history):
            if exchange.t < since:
                continue
            outputs = exchange.outputs
            if (method == "STOP" and outputs.pos_control & PosControl.EMERGENCY_STOP) or (
                method == "power off" and not outputs.stm_control & StmControl.ENABLE
            ):
                after = [p for p in self.master.points if p[0] >= exchange.t]
                return (exchange.t, after[0][1], after[0][2]) if after else None
        return None
