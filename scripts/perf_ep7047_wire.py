"""The EP7047 driver on a real EtherCAT wire: cycle period and jitter, lost cycles,
watchdog trips and CPU per process, quiet and under a CPU hog.

Makes a network namespace and a veth pair (root), starts the simulated EP7047-1032 in
the namespace (``servotune sim ep7047 --ifname``, real-time priority), runs the driver
(pysoem) on the other end with the axis enabled and moving back and forth (ABSOLUTE
moves of +/- one turn, as the demo autopilot does), and reports per cycle time:

* the period the WIRE sees (the slave stamps every process-data frame in OP): mean,
  p50/p99/max, gaps over 10 ms;
* lost cycles (the driver's count: no frame back, or a wrong working counter) and
  their rate per hour, watchdog trips at the slave;
* CPU (user + system from /proc, per second) of this process (the server side: event
  loop and the driver's thread), the cycle process and the slave;
* bring-up time (open to OP) and SDO latency (upload of 0x8020:02 from the event loop,
  p50/max over 50).

``--hog`` adds one busy process per core (normal priority) for the run. ``--thread``
runs the cycle in the driver's thread instead of the cycle process (the old way), for
comparison. ``--soak S`` runs one cycle time for S seconds and prints the same.

Run as root: ``.venv/bin/python scripts/perf_ep7047_wire.py [--cycles 1,2,4]
[--seconds 20] [--hog] [--thread] [--soak 1800]``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from servotune.devices.ep7047.codec import VELOCITY_MAX, StartType
from servotune.devices.ep7047.link import PysoemMaster, build_ep7047_link
from servotune.devices.ep7047.sim.netns import netns_problem, slave_process, veth_pair
from servotune.devices.ep7047.sim.slave import DEMO_COUNTS_PER_REV, DEMO_SPEED_RANGE_STEPS_S
from servotune.link.base import Sample
from servotune.transports.ethercat_cycle import CycleProcessMaster

CLOCK_TICKS = os.sysconf("SC_CLK_TCK")


class Sink:
    def __init__(self) -> None:
        self.samples = 0
        self.latest: Sample | None = None
        self.events: list[str] = []
        self.state = ""

    def on_sample(self, axis_id: str, sample: Sample) -> None:
        self.samples += 1
        self.latest = sample

    def on_link_status(self, link_id: str, state: str, message: str, *rest: Any) -> None:
        self.state = state

    def on_axis_health(self, *args: Any) -> None:
        pass

    def on_params(self, *args: Any) -> None:
        pass

    def on_event(self, level: str, axis_id: str | None, message: str) -> None:
        # Wall-clock time: to match the slave's log and the cycle process's (stderr).
        stamp = time.strftime("%H:%M:%S", time.gmtime()) + f".{int(time.time() * 1000) % 1000:03d}"
        self.events.append(f"{stamp} {level}: {message}")


def cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLOCK_TICKS


@contextlib.contextmanager
def hog(enabled: bool) -> Iterator[None]:
    processes = []
    if enabled:
        for _ in range(os.cpu_count() or 2):
            processes.append(subprocess.Popen([sys.executable, "-c", "while True: pass"]))
    try:
        yield
    finally:
        for process in processes:
            process.kill()
            process.wait()


def swing_move(target: int) -> dict[str, int]:
    """The arguments of the benchmarks' back-and-forth move: absolute to ``target``
    at 3000 with 400 ms ramps (the axis swings one turn either way)."""
    return {
        "start_type": int(StartType.ABSOLUTE),
        "target": target,
        "velocity": 3000,
        "acceleration_ms": 400,
        "deceleration_ms": 400,
    }


async def run_one(
    cycle_s: float, seconds: float, use_thread: bool, pair: Any, slave: Any
) -> dict[str, Any]:
    sink = Sink()
    master = None if use_thread else CycleProcessMaster(PysoemMaster, cycle_s=cycle_s)
    link = build_ep7047_link(
        "bench",
        pair.master_if,
        1,
        sink,  # type: ignore[arg-type]
        master=master,
        cycle_s=cycle_s,
        speed_range_steps_s=DEMO_SPEED_RANGE_STEPS_S,
        counts_per_rev=DEMO_COUNTS_PER_REV,
        cycle_process=not use_thread,
    )
    started = time.monotonic()
    task = asyncio.create_task(link.run())
    try:
        while link.state != "connected":
            await asyncio.sleep(0.005)
            if time.monotonic() - started > 60:
                raise RuntimeError(f"no OP: {sink.events[-3:]}")
        bring_up_s = time.monotonic() - started
        axis = link.axes[0]
        sdo_ms = []
        for _ in range(50):
            t = time.perf_counter()
            await link.sdo_read(VELOCITY_MAX)
            sdo_ms.append((time.perf_counter() - t) * 1000)
        await axis.command("enable", {})
        slave.control("gaps")
        trips_before = slave.record()["watchdog_trips"]
        lost_before = link.counters["lost_frames"]
        pids = {"server": os.getpid(), "slave": slave.pid}
        if master is not None and master.pid is not None:
            pids["cycle"] = master.pid
        cpu_before = {name: cpu_s(pid) for name, pid in pids.items()}
        t0 = time.monotonic()
        target = DEMO_COUNTS_PER_REV
        while time.monotonic() - t0 < seconds:
            with contextlib.suppress(Exception):
                await axis.command("execute_move", swing_move(target))
            target = -target
            await asyncio.sleep(max(0.0, min(1.5, seconds - (time.monotonic() - t0))))
            latest = sink.latest
            if (
                link.state == "connected"
                and latest is not None
                and not latest.flags.get("enable_out")
            ):
                with contextlib.suppress(Exception):  # after a trip: Enable again
                    await axis.command("enable", {})
        elapsed = time.monotonic() - t0
        cpu = {name: (cpu_s(pid) - cpu_before[name]) / elapsed for name, pid in pids.items()}
        gaps = slave.control("gaps")["ok"]
        lost = link.counters["lost_frames"] - lost_before
        return {
            "cycle_ms": cycle_s * 1000,
            "mode": "thread" if use_thread else "process",
            "bring_up_ms": bring_up_s * 1000,
            "sdo_p50_ms": statistics.median(sdo_ms),
            "sdo_max_ms": max(sdo_ms),
            "seconds": elapsed,
            "gaps": gaps,
            "lost": lost,
            "lost_per_hour": lost / elapsed * 3600,
            "watchdog_trips": slave.record()["watchdog_trips"] - trips_before,
            "cpu": cpu,
            "priority": getattr(master, "priority_text", ""),
            "events": [e for e in sink.events if " info: " not in e],
        }
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


def show(result: dict[str, Any], load: str) -> None:
    gaps = result["gaps"]
    cpu = " ".join(f"{name} {value:.3f}" for name, value in result["cpu"].items())
    print(
        f"| {result['cycle_ms']:g} ms | {result['mode']} | {load} | "
        f"{gaps.get('mean_ms', 0):.3f} | {gaps.get('p50_ms', 0):.3f} | "
        f"{gaps.get('p99_ms', 0):.3f} | {gaps.get('max_ms', 0):.1f} | "
        f"{gaps.get('over_10ms', 0)} | {result['lost']} ({result['lost_per_hour']:.0f}/h) | "
        f"{result['watchdog_trips']} | {cpu} | {result['bring_up_ms']:.0f} | "
        f"{result['sdo_p50_ms']:.2f}/{result['sdo_max_ms']:.2f} |",
        flush=True,
    )


async def main(args: argparse.Namespace) -> int:
    problem = netns_problem()
    if problem is not None:
        print(f"cannot run: {problem}", file=sys.stderr)
        return 2
    cycles = [float(c) / 1000 for c in args.cycles.split(",")]
    seconds = args.soak or args.seconds
    print(
        "| cycle | cycle in | load | wire period mean ms | p50 | p99 | max | gaps > 10 ms | "
        "lost cycles | watchdog trips | CPU (core) | bring-up ms | SDO p50/max ms |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    loads = [False, True] if args.hog == "both" else [args.hog == "on"]
    with (
        tempfile.TemporaryDirectory() as tmp,
        veth_pair() as pair,
        slave_process(pair, Path(tmp)) as slave,
    ):
        for cycle_s in cycles:
            for loaded in loads:
                with hog(loaded):
                    result = await run_one(cycle_s, seconds, args.thread, pair, slave)
                show(result, "hog" if loaded else "quiet")
                for event in result["events"]:  # why a drop-out or a trip happened
                    print(f"  {event}", flush=True)
        if result.get("priority"):
            print(f"\n{result['priority']}")
        # The slave's own account of every trip and state change (its log, timestamped).
        log = Path(tmp) / "slave.log"
        for line in log.read_text().splitlines() if log.exists() else []:
            if "WARNING" in line or "ERROR" in line:
                print(f"  slave: {line}", flush=True)
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cycles", default="1,2,4", help="cycle times in ms")
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--hog", choices=["off", "on", "both"], default="both")
    parser.add_argument("--thread", action="store_true", help="the cycle in the driver thread")
    parser.add_argument("--soak", type=float, default=0.0, help="seconds, one run per cycle")
    sys.exit(asyncio.run(main(parser.parse_args())))
