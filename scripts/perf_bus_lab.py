#!/usr/bin/env python3
"""Load test of the lab bus (docs/lab.md): a simulated lab of R rigs x A axes at 30
telemetry batches/s per axis, through nats-server and ``servotune hub`` to websocket
viewers. Reports latency sample -> viewer (p50/p99), gaps at the viewers, the hub's CPU
and the bus throughput.

* nats-server: started as in the tests (tests/support/nats.py: free ports, the accounts
  of ``servotune bus-accounts``).
* the hub: ``servotune hub`` in a process of its own (port ``--port``), so its CPU is
  its own (``/proc/<pid>/stat``: user + system time over the measuring window).
* the rigs: fake rigs (tests/support/fake_rig.py), in-process clients of the bus with each
  rig's own credentials, speaking the rig agent's protocol (manifest, presence every
  0.5 s with the rig's clock, clock answers, telemetry batches, snapshot and command
  answers). NOT whole servotune apps: 20 of those on simulated lines would not fit on
  this machine; the hub cannot tell them apart.
  Each batch carries ``--samples`` samples; a sample's ``position`` channel is the wall
  clock when it was made and its ``velocity`` channel a per-axis sequence number, so a
  viewer measures latency (same machine, one clock) and counts missing samples.
* viewers: ``--viewers`` websocket clients of the hub that read everything (healthy),
  each in a process of its own, measuring over the same wall-clock window.

    PYTHONPATH=server .venv/bin/python scripts/perf_bus_lab.py --rigs 20 --axes 6 --seconds 20
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import multiprocessing
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from tests.support.bus_lab import create_bus_state  # noqa: E402
from tests.support.fake_rig import FakeRig  # noqa: E402
from tests.support.nats import free_port, hub_command, nats_lab  # noqa: E402

BATCH_PERIOD_S = 1 / 30
CLOCK_TICKS = os.sysconf("SC_CLK_TCK")


def percentiles(values: list[float]) -> str:
    if not values:
        return "no samples"
    array = np.asarray(values) * 1000.0
    p50, p99 = np.percentile(array, [50, 99])
    return f"p50 {p50:6.1f} ms  p99 {p99:6.1f} ms  max {array.max():6.1f} ms  (n={array.size})"


def cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLOCK_TICKS  # utime + stime


class Viewer:
    """A healthy websocket client of the hub: reads everything, measures."""

    def __init__(self, window: Any, ready: Any) -> None:
        self.latency: list[float] = []
        self.samples = 0
        self.gaps = 0
        self.dropped = 0
        self._last: dict[str, float] = {}
        # Shared with the parent: (from, until) wall clock, 0 until the parent sets it.
        self.window = window
        self.ready = ready

    async def run(self, port: int) -> None:
        import websockets
        from websockets.typing import Origin

        async with websockets.connect(
            f"ws://127.0.0.1:{port}/ws", max_size=None, origin=Origin(f"http://127.0.0.1:{port}")
        ) as socket:

            async def beat() -> None:
                while True:
                    await socket.send('{"type": "ping"}')
                    await asyncio.sleep(1.0)

            task = asyncio.create_task(beat())
            self.ready.set()
            try:
                async for text in socket:
                    arrived = time.time()
                    from_wall, until_wall = self.window[0], self.window[1]
                    if from_wall and arrived > until_wall:
                        return
                    measuring = bool(from_wall) and arrived >= from_wall
                    message = json.loads(text)
                    kind = message.get("type")
                    if kind == "client_stats":
                        self.dropped = int(message.get("dropped", 0))
                    if kind != "telemetry":
                        continue
                    axis = message["axis"]
                    positions = message["channels"].get("position") or []
                    seqs = message["channels"].get("velocity") or []
                    for position, seq in zip(positions, seqs, strict=False):
                        if position is None or seq is None:
                            continue
                        last = self._last.get(axis)
                        if measuring:
                            self.latency.append(arrived - position)
                            self.samples += 1
                            if last is not None and seq > last + 1:
                                self.gaps += int(seq - last - 1)
                        self._last[axis] = seq
            finally:
                task.cancel()


def viewer_process(port: int, window: Any, ready: Any, results: Any) -> None:
    """A viewer in a process of its own (the benchmark's rigs must not slow it down)."""
    viewer = Viewer(window, ready)
    try:
        asyncio.run(viewer.run(port))
    except Exception as exc:  # reported, the others' results still count
        print(f"viewer: {type(exc).__name__}: {exc}", file=sys.stderr)
    results.put(
        {
            "latency": viewer.latency,
            "samples": viewer.samples,
            "gaps": viewer.gaps,
            "dropped": viewer.dropped,
        }
    )


async def run(args: argparse.Namespace) -> None:
    names = [f"rig-{i:02d}" for i in range(1, args.rigs + 1)]
    with tempfile.TemporaryDirectory(prefix="perf-bus-lab-") as tmp_name:
        tmp = Path(tmp_name)
        async with nats_lab(tmp / "nats", names) as lab:
            await create_bus_state(lab)
            rigs = [
                FakeRig(
                    name,
                    args.axes,
                    url=lab.url,
                    user=lab.users[name].name,
                    password=lab.users[name].password,
                    samples_per_s=args.samples / BATCH_PERIOD_S,
                    batch=args.samples,
                )
                for name in names
            ]
            for rig in rigs:
                await rig.start()
            env = dict(os.environ, PYTHONPATH=str(ROOT / "server"))
            hub = subprocess.Popen(  # noqa: ASYNC220 (once, before measuring)
                hub_command(lab, args.port, tmp / "hub"),
                env=env,
                stdout=subprocess.DEVNULL,
                stderr=open(tmp / "hub.log", "wb"),  # noqa: SIM115, ASYNC230
            )
            tasks: list[asyncio.Task[None]] = []
            try:
                async with httpx.AsyncClient(base_url=f"http://127.0.0.1:{args.port}") as http:
                    axes: list[Any] = []
                    for _ in range(1200):  # a loaded machine: up to 2 minutes
                        with contextlib.suppress(httpx.HTTPError):
                            axes = (await http.get("/api/axes")).json()
                            if len(axes) == args.rigs * args.axes:
                                break
                        await asyncio.sleep(0.1)
                    else:
                        print(f"the hub lists {len(axes)} axes")
                        log = (tmp / "hub.log").read_text()[-2000:]
                        raise SystemExit(f"the hub did not list every axis: {log}")
                print(f"the hub lists every axis at {time.strftime('%H:%M:%S')}")
                for rig in rigs:
                    tasks.append(asyncio.create_task(rig.presence()))
                    tasks.append(asyncio.create_task(rig.telemetry()))
                context = multiprocessing.get_context("spawn")
                results = context.Queue()
                window = context.Array("d", 2)
                readies = [context.Event() for _ in range(args.viewers)]
                viewers = [
                    context.Process(target=viewer_process, args=(args.port, window, ready, results))
                    for ready in readies
                ]
                for viewer in viewers:
                    viewer.start()
                for ready in readies:
                    if not await asyncio.to_thread(ready.wait, 120):
                        raise SystemExit("a viewer did not connect in 2 minutes")
                await asyncio.sleep(3.0)  # settle: every rig online, the viewers caught up
                window[0], window[1] = time.time(), time.time() + args.seconds
                print(f"measuring from {time.strftime('%H:%M:%S')} for {args.seconds:g} s")
                published0 = sum(r.published for r in rigs)
                bytes0 = sum(r.bytes for r in rigs)
                nats_pid = lab.server.pid
                cpu0, wall0 = cpu_s(hub.pid), time.monotonic()
                nats0, rigs0 = cpu_s(nats_pid), cpu_s(os.getpid())
                load0 = os.getloadavg()[0]
                await asyncio.sleep(args.seconds)
                cpu1, wall1 = cpu_s(hub.pid), time.monotonic()
                nats1, rigs1 = cpu_s(nats_pid), cpu_s(os.getpid())
                counters: dict[str, int] = {}
                async with httpx.AsyncClient(base_url=f"http://127.0.0.1:{args.port}") as http:
                    for name in names:
                        status = (await http.get(f"/api/links/{name}.line/status")).json()
                        for key, value in status.get("counters", {}).items():
                            counters[key] = counters.get(key, 0) + int(value)
                published = sum(r.published for r in rigs) - published0
                sent_bytes = sum(r.bytes for r in rigs) - bytes0
                got = [await asyncio.to_thread(results.get, True, 120) for _ in viewers]
                elapsed = wall1 - wall0
                expected = args.rigs * args.axes * args.samples * elapsed / BATCH_PERIOD_S
                print(
                    f"lab: {args.rigs} rigs x {args.axes} axes, {args.samples} samples/batch, "
                    f"30 batches/s per axis; {args.viewers} viewers; {elapsed:.1f} s; "
                    f"load average {load0:.1f} -> {os.getloadavg()[0]:.1f} "
                    f"({os.cpu_count()} cores)"
                )
                print(
                    f"bus: {published / elapsed:.0f} telemetry messages/s, "
                    f"{sent_bytes / elapsed / 1e6:.2f} MB/s from the rigs "
                    f"(expected {args.rigs * args.axes * 30} messages/s)"
                )
                print(
                    f"CPU (% of one core, user + system): hub {100 * (cpu1 - cpu0) / elapsed:.0f}, "
                    f"nats-server {100 * (nats1 - nats0) / elapsed:.0f}, "
                    f"the fake rigs (one process) {100 * (rigs1 - rigs0) / elapsed:.0f}"
                )
                print(f"the hub, summed over the rigs' links: {counters}")
                for index, result in enumerate(got):
                    print(
                        f"viewer {index}: {result['samples']} samples (~{expected:.0f} made), "
                        f"{result['gaps']} missing, hub dropped {result['dropped']} for it"
                    )
                    print(f"  sample -> viewer: {percentiles(result['latency'])}")
                for viewer in viewers:
                    viewer.join(10)
            finally:
                for task in tasks:
                    task.cancel()
                hub.terminate()
                hub.wait(30)
                for line in (tmp / "hub.log").read_text().splitlines():
                    if any(k in line for k in ("keep-alive", "withheld", "safety lane")):
                        print("hub log:", line)
                for rig in rigs:
                    with contextlib.suppress(Exception):
                        await rig.nc.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rigs", type=int, default=20)
    parser.add_argument("--axes", type=int, default=6)
    parser.add_argument("--samples", type=int, default=4, help="samples per batch")
    parser.add_argument("--viewers", type=int, default=2)
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--port", type=int, default=free_port())
    args = parser.parse_args()
    asyncio.run(run(args))
    return 0


if __name__ == "__main__":
    sys.exit(main())
