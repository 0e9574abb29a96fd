"""Server-side CPU of one EP7047 link per sample, the simulator in its own process.

Starts the simulated EP7047-1032 as ``servotune sim`` does (its own process, behind the
master seam), runs the driver's link in this process for ``--seconds`` with the axis
enabled and an endless move running (so the inputs change every cycle; ``--moves
demo``: the demo autopilot's moves of +/- one turn instead), and prints this process's
CPU time (user + system, ``os.times``; the simulator's is not counted) per second and
per sample delivered to the event loop. The figure covers the cycle thread
(exchange, handshakes, sample) and the delivery to the loop; a
counting sink stands in for the hub.

It also prints the cycle thread's share and the simulator process's CPU (``/proc``,
Linux), per second and per sample: the simulator pays for every exchange too.

Run: ``PYTHONPATH=server python scripts/perf_ep7047_link.py [--seconds 10] [--moves
demo]``. Compare two versions on the same machine state (alternate them; a loaded host
lowers the rate but the CPU per sample much less).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import sys
import tempfile
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from servotune.devices.ep7047.link import build_ep7047_link
from servotune.devices.ep7047.sim.process import ProcessMaster, ep7047_sim_process
from servotune.devices.ep7047.sim.slave import DEMO_COUNTS_PER_REV, DEMO_SPEED_RANGE_STEPS_S
from servotune.link.base import Sample


class CountingSink:
    """A DriverSink that only counts samples."""

    def __init__(self) -> None:
        self.samples = 0
        self.state = ""
        self.latest: Sample | None = None

    def on_sample(self, axis_id: str, sample: Sample) -> None:
        self.samples += 1
        self.latest = sample

    def on_link_status(self, link_id: str, state: str, message: str, *_: object) -> None:
        self.state = state

    def on_axis_health(self, axis_id: str, health: str, message: str) -> None:
        pass

    def on_params(self, axis_id: str, values: Mapping[str, int], source: str) -> None:
        pass

    def on_event(self, level: str, axis_id: str | None, message: str) -> None:
        pass


async def demo_moves(axis: Any, sink: CountingSink) -> None:
    """What the demo's autopilot does: ABSOLUTE moves to +/- one turn at 3000 bp with
    400 ms ramps, each after the last has ended, 0.5 s apart."""
    target = DEMO_COUNTS_PER_REV
    move = {"start_type": 0x0001, "velocity": 3000, "acceleration_ms": 400}
    for _ in range(500):  # a start before STM Ready is refused
        if sink.latest is not None and sink.latest.flags["stm_ready"]:
            break
        await asyncio.sleep(0.01)
    while True:
        await axis.command("execute_move", {**move, "deceleration_ms": 400, "target": target})
        while True:
            await asyncio.sleep(0.05)
            latest = sink.latest
            if latest is not None and not latest.flags["busy"] and not latest.flags["execute_out"]:
                break
        await asyncio.sleep(0.5)
        target = -target


async def measure(seconds: float, moves: str) -> None:
    with tempfile.TemporaryDirectory(prefix="perf-ep7047-") as scratch:
        simulator = ep7047_sim_process(Path(scratch) / "record.json")
        await asyncio.to_thread(simulator.start)
        try:
            sink = CountingSink()
            link = build_ep7047_link(
                "ec",
                simulator.ready["path"],
                1,
                sink,  # type: ignore[arg-type]
                master=ProcessMaster(simulator.ready["path"].removeprefix("sim:")),
                speed_range_steps_s=DEMO_SPEED_RANGE_STEPS_S,
                counts_per_rev=DEMO_COUNTS_PER_REV,
            )
            task = asyncio.create_task(link.run())
            for _ in range(300):
                if link.state == "connected":
                    break
                await asyncio.sleep(0.05)
            axis = link.axes[0]
            await axis.command("enable", {})
            mover: asyncio.Task[None] | None = None
            if moves == "demo":
                mover = asyncio.create_task(demo_moves(axis, sink))
            else:
                await axis.command(
                    "execute_move",
                    {"start_type": 0x0003, "target": 0, "velocity": 1000},  # ENDLESS_PLUS
                )
            await asyncio.sleep(0.5)
            sim_pid = int(simulator.ready["pid"])
            cycle = [t for t in threading.enumerate() if t.name.startswith("ep7047-cycle")]
            cycle_id = cycle[0].native_id if cycle else None
            before, samples_before, t0 = os.times(), sink.samples, time.monotonic()
            sim0 = _cpu_s(f"/proc/{sim_pid}/stat")
            thread0 = _cpu_s(f"/proc/self/task/{cycle_id}/stat") if cycle_id else 0.0
            await asyncio.sleep(seconds)
            after, samples, wall = os.times(), sink.samples - samples_before, time.monotonic() - t0
            sim1 = _cpu_s(f"/proc/{sim_pid}/stat")
            thread1 = _cpu_s(f"/proc/self/task/{cycle_id}/stat") if cycle_id else 0.0
            for running in (mover, task):
                if running is not None:
                    running.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await running
        finally:
            await asyncio.to_thread(simulator.stop)
    cpu = (after.user - before.user) + (after.system - before.system)
    print(
        f"{wall:.1f} s: {samples / wall:.0f} samples/s; this process {cpu / wall:.3f} CPU s/s "
        f"(cycle thread {(thread1 - thread0) / wall:.3f}), "
        f"{cpu / max(samples, 1) * 1e6:.0f} us CPU per sample; simulator process "
        f"{(sim1 - sim0) / wall:.3f} CPU s/s, {(sim1 - sim0) / max(samples, 1) * 1e6:.0f} us per "
        f"sample; load {os.getloadavg()[0]:.2f}"
    )


def _cpu_s(stat_path: str) -> float:
    """utime + stime of a process or thread from its ``/proc/.../stat``."""
    fields = Path(stat_path).read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument(
        "--moves",
        choices=["endless", "demo"],
        default="endless",
        help="an ENDLESS move throughout (inputs change every cycle), or the demo "
        "autopilot's moves of +/- one turn",
    )
    args = parser.parse_args()
    asyncio.run(measure(args.seconds, args.moves))
    return 0


if __name__ == "__main__":
    sys.exit(main())
