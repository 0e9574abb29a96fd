"""Benchmark: telemetry samples per second per axis against the wire limit.

Runs ``servotune sim <device>`` as a separate process on a pseudo-terminal (the real
serial path: pty, pyserial-asyncio-fast, the simulator's wire timing at the chosen
baud) and the real driver against it, then prints what it achieved next to what the
wire allows for the same poll set. Not a test: the figures depend on the machine.

The wire limit assumes the host and the device turn around in no time. They cannot:
the SLAP2's host algorithm (the manual's "sstring") waits for each character's echo
before it sends the next, and the Z1100 host sends a request when the previous reply
is in, so every such turn costs a pty hop each way, two processes' wake-ups and the
simulator's timer on top of the wire time. The benchmark prints that cost per turn
(``registry.PollSet.turns_per_sample``, from the device's entry), so a figure below the
target can be told apart from characters lost or wasted on the wire.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import subprocess
import sys
import time
from collections import defaultdict
from collections.abc import Callable, Coroutine, Mapping
from typing import Any

from servotune.config import LinkSpec
from servotune.devices import default_registry
from servotune.link.base import Sample, WireStats
from servotune.registry import PollSet, Registry
from servotune.schema import AxisHealth, EventLevel, LinkState


class _CountingSink:
    def __init__(self) -> None:
        self.samples: dict[str, list[float]] = defaultdict(list)
        self.state: LinkState = "connecting"
        self.wire_limit_hz = 0.0
        self.errors = 0

    def on_sample(self, axis_id: str, sample: Sample) -> None:
        self.samples[axis_id].append(sample.t)

    def on_link_status(
        self,
        link_id: str,
        state: LinkState,
        message: str,
        rate_hz: float,
        wire_limit_hz: float,
        errors: int,
    ) -> None:
        self.state, self.wire_limit_hz, self.errors = state, wire_limit_hz, errors

    def on_axis_health(self, axis_id: str, health: AxisHealth, message: str) -> None:
        pass

    def on_params(self, axis_id: str, values: Mapping[str, int], source: str) -> None:
        pass

    def on_event(self, level: EventLevel, axis_id: str | None, message: str) -> None:
        pass


async def _measure(
    devices: Registry, device: str, path: str, baud: int, addresses: list[int], duration_s: float
) -> int:
    sink = _CountingSink()
    link = devices.build_link(LinkSpec(device, path, "bench", baud, addresses), sink)
    assert isinstance(link, WireStats)
    task = asyncio.create_task(link.run())
    try:
        deadline = time.monotonic() + 10
        while link.state != "connected":
            if time.monotonic() > deadline:
                print("bench: the link did not connect", file=sys.stderr)
                return 1
            await asyncio.sleep(0.05)
        await asyncio.sleep(0.5)  # settle: learn reply lengths
        for samples in sink.samples.values():
            samples.clear()
        await asyncio.sleep(duration_s)
        wire_limit_hz = link.wire_limit_hz()
        simulator = devices.get(device).simulator
        describe = simulator.poll_set if simulator is not None else None
        poll_set = describe(link) if describe is not None else PollSet("", 0.0)
        if poll_set.description:
            print(poll_set.description)
        print(f"wire limit for this poll set: {wire_limit_hz:.1f} samples/s per axis")
        ratios = []
        for axis_id, times in sorted(sink.samples.items()):
            if len(times) < 2:
                print(f"  {axis_id}: no samples")
                ratios.append(0.0)
                continue
            rate_hz = (len(times) - 1) / (times[-1] - times[0])
            ratio = rate_hz / wire_limit_hz
            ratios.append(ratio)
            print(f"  {axis_id}: {rate_hz:6.1f} samples/s = {ratio:6.1%} of the wire limit")
        if ratios and min(ratios) > 0 and poll_set.turns_per_sample > 0:
            turns = poll_set.turns_per_sample
            lost_s = 1 / (min(ratios) * wire_limit_hz) - 1 / wire_limit_hz
            print(
                f"time per sample beyond the wire (worst axis): {lost_s * 1e3:.2f} ms = "
                f"{lost_s / turns * 1e6:.0f} us per host/device turn ({turns:.1f} turns)"
            )
        print(f"link errors during the run: {link.errors}")
        print(f"worst axis: {min(ratios):.1%} of the wire limit (target >= 90 %)")
        return 0
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


def run_bench(*, device: str, baud: int | None, addresses: list[int], duration_s: float) -> int:
    """Start the simulator process, measure, print, clean up. Returns an exit code."""
    devices = default_registry()
    rules = devices.link_rules(device)
    baud = baud or rules.default_baud or 0
    if rules.addressing == "fixed":
        addresses = list(rules.fixed_addresses)
    command = [
        sys.executable,
        "-m",
        "servotune.cli",
        "sim",
        device,
        "--baud",
        str(baud),
        "--addresses",
        ",".join(map(str, addresses)),
    ]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, text=True, env=os.environ.copy())
    try:
        assert process.stdout is not None
        path = process.stdout.readline().strip()
        if not path:
            print("bench: the simulator printed no path", file=sys.stderr)
            return 1
        # The server runs on uvloop when it is installed (uvicorn's default), so
        # measure on the same loop.
        try:
            import uvloop

            runner: Callable[[Coroutine[Any, Any, int]], int] = uvloop.run
            loop_name = "uvloop"
        except ImportError:
            runner, loop_name = asyncio.run, "asyncio"
        print(f"event loop: {loop_name}")
        return runner(_measure(devices, device, path, baud, addresses, duration_s))
    finally:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=5)
        except subprocess.TimeoutExpired:
            process.kill()
