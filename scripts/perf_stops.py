"""Stopping distance and time on every demo plant: STOP against the power-off alone.

    .venv/bin/python scripts/perf_stops.py [--only slap2|z1100|ep7047] [--rounds N]

Starts each simulated device with its real driver and a real hub (one fresh rig per
run, see ``servotune.perf.stops``), brings one axis to top speed or into a limit cycle,
presses STOP (or the explicit power-off: SLAP2 st, Z1100 Job 0, EP7047 Enable off)
and records the shaft as the simulator sees it until it is at rest. Prints a markdown
table (the one in docs/control.md) and the events each STOP logged. The figures
depend on the host only through its latency; compare the ratio column.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys

from servotune.perf import stops as stopbench


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", choices=["slap2", "z1100", "ep7047"], default=None)
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument("--events", action="store_true", help="print every STOP's events")
    args = parser.parse_args()
    cases = [c for c in stopbench.CASES if args.only in (None, c.device)]
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
