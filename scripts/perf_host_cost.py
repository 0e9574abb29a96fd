"""Host CPU per telemetry sample of each driver against its demo simulator process.

What the server pays per sample, independent of the autopilot, the hub and the web
side: the SLAP2 and Z1100 links (the event loop's CPU time, ``time.thread_time``,
over the samples delivered) and the EP7047 link (its cycle thread's CPU time from
``/proc``, over the cycles). The simulators run in their own processes, as in the
demo (``servotune.demo``). Per-sample CPU is far less sensitive to other work on the
machine than a rate, so it is the figure to compare between two versions (alternate
them, ``PYTHONPATH=<the other tree>/server``); a loaded host still inflates it.

Run: ``PYTHONPATH=server python scripts/perf_host_cost.py [--seconds 10]``. Linux
only (``/proc``).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

from servotune.config import LinkSpec
from servotune.devices import default_registry
from servotune.devices.ep7047.entry import demo_slave as ep7047_demo_slave
from servotune.devices.slap2.entry import demo_line as slap2_demo_line
from servotune.devices.z1100.entry import demo_line as z1100_demo_line
from servotune.perf.link_rate import _CountingSink


def _thread_cpu_s(native_id: int) -> float:
    fields = Path(f"/proc/self/task/{native_id}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _samples(sink: _CountingSink) -> int:
    return sum(len(times) for times in sink.samples.values())


async def _measure(spec: LinkSpec, seconds: float) -> str:
    sink = _CountingSink()
    link = default_registry().build_link(spec, sink)
    task = asyncio.create_task(link.run())
    try:
        deadline = time.monotonic() + 60
        while link.state != "connected":
            if time.monotonic() > deadline:
                return f"{spec.device}: did not connect"
            await asyncio.sleep(0.05)
        await asyncio.sleep(1.0)
        cycle = [t for t in threading.enumerate() if t.name.startswith("ep7047-cycle")]

        def cpu_s() -> float:
            native_id = cycle[0].native_id if cycle else None
            return _thread_cpu_s(native_id) if native_id is not None else time.thread_time()

        n0, c0, t0 = _samples(sink), cpu_s(), time.monotonic()
        await asyncio.sleep(seconds)
        n1, c1, t1 = _samples(sink), cpu_s(), time.monotonic()
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    samples = n1 - n0
    if samples <= 0:
        return f"{spec.device}: no samples"
    rate_hz = samples / (t1 - t0) / len(spec.addresses)
    wire = link.wire_limit_hz()
    where = "cycle thread" if cycle else "event loop"
    share = f" = {rate_hz / wire:.0%} of the wire" if wire else ""
    return (
        f"{spec.device:<7} {(c1 - c0) / samples * 1e6:6.0f} us CPU per sample ({where}), "
        f"{(c1 - c0) / (t1 - t0):.3f} core, {rate_hz:6.1f} Hz per axis{share}"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    args = parser.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f} (1 min), {os.cpu_count()} cores")
    with tempfile.TemporaryDirectory(prefix="st-cost-") as scratch:
        for line in (slap2_demo_line, z1100_demo_line, ep7047_demo_slave):
            with line(Path(scratch)) as specs:
                print("  " + asyncio.run(_measure(specs[0], args.seconds)), flush=True)
    print(f"load average {os.getloadavg()[0]:.2f} (1 min) at the end")
    return 0


if __name__ == "__main__":
    sys.exit(main())
