#!/usr/bin/env python3
"""Benchmark of the lab bus (docs/lab.md): telemetry latency rig -> bus -> hub, and the
command round trip hub -> rig -> device read-back.

Starts nats-server (tests/support/nats.py: free ports, a temporary account), N rigs
in-process (each a whole servotune app on its own simulated SLAP2 line on a pty, as in
the tests) and a hub, all in this process. Then, for ``--seconds``:

* telemetry: a bus client with the hub's credentials receives every rig's telemetry
  batches. For each batch: time in the rig = the rig clock at publish (header
  ``St-Rig-Now``) minus the newest sample's receive time (the rig's batching, up to
  33 ms) ; time on the bus = wall clock at arrival minus the wall clock at publish
  (header ``St-Wall``; one machine, one clock). device -> hub = their sum, for the
  newest and for the oldest sample of the batch. The hub's own fan-out to a websocket
  adds its batch period (33 ms at most) on top: not measured here.
* commands: ``--writes`` parameter writes (``kp``) through the hub's REST API, each
  answered after the rig wrote the device and read it back.

    PYTHONPATH=server .venv/bin/python scripts/perf_bus.py --rigs 2 --seconds 10
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from tests.support.bus_lab import (  # noqa: E402  (the tests' own fixtures, as a script)
    RIGS,
    LabRun,
    add_rig_lines,
    create_bus_state,
    start_hub,
    start_rig,
    stop_app,
    wait_for_manifest,
)
from tests.support.nats import nats_lab  # noqa: E402


def percentiles(values: list[float]) -> str:
    if not values:
        return "no samples"
    array = np.asarray(values) * 1000.0
    p50, p99 = np.percentile(array, [50, 99])
    return f"p50 {p50:6.1f} ms  p99 {p99:6.1f} ms  max {array.max():6.1f} ms  (n={array.size})"


async def run(rigs: int, seconds: float, writes: int) -> None:
    import nats

    names = [f"rig-{i}" for i in range(1, rigs + 1)] if rigs != 2 else list(RIGS)
    with tempfile.TemporaryDirectory(prefix="perf-bus-") as tmp_name:
        tmp = Path(tmp_name)
        async with nats_lab(tmp / "nats", names) as lab:
            run_ = LabRun(lab, tmp)
            with contextlib.ExitStack() as lines:
                add_rig_lines(run_, names, lines)
                try:
                    await create_bus_state(lab)
                    for rig in run_.rigs.values():
                        await start_rig(run_, rig)
                    for name in names:
                        await wait_for_manifest(lab, name)
                    await start_hub(run_)
                    await asyncio.sleep(2.0)
                    await measure(run_, lab, nats, seconds, writes)
                finally:
                    await stop_app(run_.hub)
                    for rig in run_.rigs.values():
                        await stop_app(rig.app)


async def measure(run_: LabRun, lab: object, nats: object, seconds: float, writes: int) -> None:
    from servotune.bus.subjects import PREFIX

    user = run_.lab.users["hub"]
    nc = await nats.connect(run_.lab.url, user=user.name, password=user.password)  # type: ignore[attr-defined]
    in_rig_newest: list[float] = []
    in_rig_oldest: list[float] = []
    on_bus: list[float] = []
    total_newest: list[float] = []
    total_oldest: list[float] = []
    samples = 0

    async def on_batch(msg: object) -> None:
        nonlocal samples
        arrived = time.time()
        headers = msg.headers or {}  # type: ignore[attr-defined]
        body = json.loads(msg.data)  # type: ignore[attr-defined]
        if "St-Rig-Now" not in headers or not body["t"]:
            return
        rig_now = float(headers["St-Rig-Now"])
        bus = arrived - float(headers["St-Wall"])
        newest, oldest = rig_now - body["t"][-1], rig_now - body["t"][0]
        samples += len(body["t"])
        in_rig_newest.append(newest)
        in_rig_oldest.append(oldest)
        on_bus.append(bus)
        total_newest.append(newest + bus)
        total_oldest.append(oldest + bus)

    await nc.subscribe(f"{PREFIX}.*.*.*.telemetry", cb=on_batch)  # type: ignore[attr-defined]
    started = time.monotonic()
    await asyncio.sleep(seconds)
    elapsed = time.monotonic() - started
    await nc.close()  # type: ignore[attr-defined]
    print(f"telemetry over {elapsed:.1f} s: {len(on_bus)} batches, {samples} samples")
    print(f"  in the rig (newest sample):  {percentiles(in_rig_newest)}")
    print(f"  in the rig (oldest sample):  {percentiles(in_rig_oldest)}")
    print(f"  on the bus:                  {percentiles(on_bus)}")
    print(f"  device -> hub, newest:       {percentiles(total_newest)}")
    print(f"  device -> hub, oldest:       {percentiles(total_oldest)}")

    client = run_.hub_client
    axis = f"{next(iter(run_.rigs))}.line-0"
    round_trips = []
    for index in range(writes):
        began = time.perf_counter()
        response = await client.patch(f"/api/axes/{axis}/params", json={"kp": 40 + index % 2})
        round_trips.append(time.perf_counter() - began)
        if response.status_code != 200:
            print(f"  write {index}: {response.status_code} {response.text}")
    print(f"command round trip (hub REST -> rig -> device write + read-back, {axis}):")
    print(f"  {percentiles(round_trips)}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rigs", type=int, default=2)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--writes", type=int, default=50)
    args = parser.parse_args()
    asyncio.run(run(args.rigs, args.seconds, args.writes))
    return 0


if __name__ == "__main__":
    sys.exit(main())
