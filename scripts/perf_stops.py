"""Stopping distance and time on every demo plant: STOP against the power-off alone.

    .venv/bin/python scripts/perf_stops.py [--only DEVICE] [--case NAME] [--rounds N]

Starts each simulated device with its real driver and a real hub (one fresh rig per
run, see ``servotune.perf.stops``), brings one axis to top speed or into a limit cycle
(the cases of each device's registry entry), presses STOP (or the explicit power-off:
SLAP2 st, Z1100 Job 0, EP7047 Enable off) and records the shaft as the simulator sees
it until it is at rest; the simulator also runs a copy of the device, taken as the
STOP arrived, forward with the power off alone. Prints a markdown table (the one in
docs/control.md) and the events each STOP logged. The figures from the arrival do not
depend on the host's latency; compare the ratio column.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys

from servotune.perf import stops as stopbench


def main() -> None:
    every = stopbench.cases()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", choices=sorted({c.device for c in every}), default=None)
    parser.add_argument(
        "--case", choices=sorted({c.name for c in every}), default=None, help="one case"
    )
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument("--events", action="store_true", help="print every STOP's events")
    args = parser.parse_args()
    cases = [c for c in every if args.only in (None, c.device) and args.case in (None, c.name)]
    results = []
    for _ in range(args.rounds):
        results += asyncio.run(stopbench.measure_all(cases))
    print(f"# load average before/after: {os.getloadavg()[0]:.1f}", file=sys.stderr)
    print(stopbench.table(results))
    if args.events:
        for result in results:
            for event in result.events:
                print(f"{result.case.label} / {result.case.state} / {result.method}: {event}")


if __name__ == "__main__":
    main()
