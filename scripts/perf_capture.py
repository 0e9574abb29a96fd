"""Capture rate per device: samples/s of the axis under test and the ratio to the wire limit.

Usage: PYTHONPATH=server python scripts/perf_capture.py [seconds]

For the SLAP2 (19200 baud, two modules on one line, as in the demo) and the Z1100
(38400 baud, three motors), each simulator in a process of its own (as the demo runs
them), the driver in this process:

* normal polling: samples/s per axis and the link's own wire limit for its poll set;
* capture of one axis (``async with axis.capture(...)``) while it makes a move:
  samples/s of that axis, and the ratio to the *focused* poll set's wire limit,
  computed from the characters the capture's transactions took on the wire
  (``CaptureStats.wire_chars``: every character sent, echoed and replied, at 10 bit
  times each) - i.e. the share of the time the wire was busy with the capture.

Targets: SLAP2 >= 120 samples/s and >= 90 % of the focused wire limit,
Z1100 >= 200 samples/s; normal polling >= 90 % of the wire limit quietly.
Machine-dependent by nature (a benchmark, not a test): the load average is printed.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import os
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Mapping
from pathlib import Path

from servotune.devices.slap2.link import Slap2Axis, Slap2Link, Slap2LinkConfig
from servotune.devices.slap2.sim.demo import build_slap2_line
from servotune.devices.z1100.link import Z1100Axis, Z1100Link, Z1100LinkConfig
from servotune.devices.z1100.sim.chip import Z1100Chip
from servotune.devices.z1100.sim.demo import Z1100_LOADS_KG_M2, write_demo_flash
from servotune.link.base import Sample
from servotune.schema import AxisHealth, EventLevel, LinkState
from servotune.sim.process import SerialSimSpec, serial_sim_process
from servotune.transports.serial import SerialConnector

Z1100_BAUD = 38400


def build_z1100_38400(state_dir: Path) -> Z1100Chip:
    state_dir.mkdir(parents=True, exist_ok=True)
    flash = state_dir / "z1100_flash.json"
    write_demo_flash(flash)
    return Z1100Chip.with_loads(Z1100_LOADS_KG_M2, flash_path=flash, jumper_baud=Z1100_BAUD)


class Sink:
    def __init__(self) -> None:
        self.samples: dict[str, list[float]] = defaultdict(list)
        self.health: dict[str, tuple[str, str]] = {}
        self.status: tuple[float, float] = (0.0, 0.0)

    def on_sample(self, axis_id: str, sample: Sample) -> None:
        self.samples[axis_id].append(sample.t)

    def on_link_status(
        self, link_id: str, state: LinkState, message: str, rate: float, limit: float, errors: int
    ) -> None:
        self.status = (rate, limit)

    def on_axis_health(self, axis_id: str, health: AxisHealth, message: str) -> None:
        self.health[axis_id] = (health, message)

    def on_params(self, axis_id: str, values: Mapping[str, int], source: str) -> None:
        pass

    def on_event(self, level: EventLevel, axis_id: str | None, message: str) -> None:
        pass


def rate(times: list[float], t_from: float, t_to: float) -> float:
    n = sum(1 for t in times if t_from <= t <= t_to)
    return n / (t_to - t_from)


async def run(link: Slap2Link | Z1100Link, sink: Sink, seconds: float) -> None:
    await wait(lambda: link.state == "connected", 60)
    await asyncio.sleep(1.0)
    t = time.monotonic()
    await asyncio.sleep(seconds)
    now = time.monotonic()
    per_axis = [rate(sink.samples[a.id], t, now) for a in link.axes]
    limit = link.wire_limit_hz()
    mean = sum(per_axis) / len(per_axis)
    print(
        f"{link.device} normal polling: {', '.join(f'{r:.1f}' for r in per_axis)} samples/s "
        f"per axis; wire limit {limit:.1f}/s: {mean / limit:.0%}"
    )


async def wait(condition: object, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():  # type: ignore[operator]
        if time.monotonic() > deadline:
            raise TimeoutError("timed out")
        await asyncio.sleep(0.05)


async def measure_slap2(state: Path, seconds: float) -> None:
    spec = SerialSimSpec("slap2", functools.partial(build_slap2_line, state / "slap2"), 19200)
    with serial_sim_process(spec) as simulator:
        path = simulator.ready["path"]
        sink = Sink()
        config = Slap2LinkConfig(link_id="slap2", path=path, addresses=[0, 1])
        link = Slap2Link(config, SerialConnector(path, 19200), sink)
        task = asyncio.create_task(link.run())
        try:
            await run(link, sink, seconds)
            axis = next(a for a in link.axes if a.address == 0)
            assert isinstance(axis, Slap2Axis)
            await axis.command("position_mode", {})
            await asyncio.sleep(0.3)
            async with axis.capture("benchmark"):
                t = time.monotonic()
                direction = 1
                while time.monotonic() - t < seconds:
                    await axis.command("move_relative", {"distance": 3000 * direction})
                    direction = -direction
                    await asyncio.sleep(0.7)
                now = time.monotonic()
                stats = link.capture_stats(0)
                paused = sink.health.get(link.axis_id(1))
            assert stats is not None
            achieved = rate(sink.samples[axis.id], t, now)
            char_s = 10 / 19200
            limit = stats.samples / (stats.wire_chars * char_s)
            print(
                f"slap2 capture of #0 (two modules on the line, #1 {paused}): "
                f"{achieved:.1f} samples/s; focused wire limit {limit:.1f}/s: "
                f"{achieved / limit:.0%}; setpoint checks {stats.setpoint_checks}, "
                f"{stats.setpoint_mismatches} off, max residual "
                f"{stats.max_setpoint_residual:.1f} counts"
            )
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task


async def measure_z1100(state: Path, seconds: float) -> None:
    spec = SerialSimSpec("z1100", functools.partial(build_z1100_38400, state / "z1100"), Z1100_BAUD)
    with serial_sim_process(spec) as simulator:
        path = simulator.ready["path"]
        sink = Sink()
        config = Z1100LinkConfig(link_id="z1100", path=path, baud=Z1100_BAUD)
        link = Z1100Link(config, SerialConnector(path, Z1100_BAUD), sink)
        task = asyncio.create_task(link.run())
        try:
            await run(link, sink, seconds)
            axis = link.axes[1]
            assert isinstance(axis, Z1100Axis)
            async with axis.capture("benchmark"):
                t = time.monotonic()
                await asyncio.sleep(seconds)
                now = time.monotonic()
                stats = link.capture_stats(1)
            assert stats is not None
            achieved = rate(sink.samples[axis.id], t, now)
            limit = stats.samples / (stats.wire_chars * 10 / Z1100_BAUD)
            print(
                f"z1100 capture of motor 2 at {Z1100_BAUD} baud: {achieved:.1f} samples/s; "
                f"focused wire limit {limit:.1f}/s: {achieved / limit:.0%}"
            )
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task


async def main(seconds: float) -> None:
    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    with tempfile.TemporaryDirectory() as directory:
        await measure_slap2(Path(directory), seconds)
        await measure_z1100(Path(directory), seconds)
    print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    asyncio.run(main(float(sys.argv[1]) if len(sys.argv) > 1 else 5.0))
