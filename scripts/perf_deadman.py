"""Benchmark of the dead-man and of the telemetry fan-out.

    PYTHONPATH=server python scripts/perf_deadman.py [--trials 20] [--viewers 20]
    PYTHONPATH=server python scripts/perf_deadman.py --fanout-only \
        --server-pythonpath /tmp/old/server        # "before": a server without the lock

The server runs as its own process (``python -m servotune serve``) on a simulated SLAP2
line that this process serves on a pty through ``WireRecorder``, so the stop is timed on
the simulated device's own record of its wire, not on anything the server says.

Dead-man: a raw websocket client takes the axis, heartbeats, starts velocity mode, then
vanishes — (a) RST without a close frame (SO_LINGER 0), (b) a network cut: an iptables
rule drops every packet of the client on the loopback, its acknowledgements included
(laptop asleep, cable cut; root only), (c) silent while its machine still acknowledges
(a frozen browser: given ``alive_grace_s`` first). Time from the vanishing to the
dead-man's controlled stop (``pm``, from velocity mode) reaching the simulated module;
median and worst of ``--trials``.

Fan-out: ``--viewers`` websocket clients read telemetry for ``--seconds``; reported are
the server process' CPU share, the samples each viewer received per second, and the
99th percentile gap between telemetry messages. With the control lock, one holder
heartbeats meanwhile (the checks on the path are exercised).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import websockets

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from tests.support.control import (
    RawWebsocket,
    can_cut_the_network,
    cut_network,
    free_port,
    recorded_line,
    take_with_raw_client,
)
from tests.support.servers import use_csrf_token

TICKS_PER_S = os.sysconf("SC_CLK_TCK")


def cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS_PER_S


@contextlib.asynccontextmanager
async def server_process(tmp: Path, tty: str, port: int, pythonpath: str | None):  # type: ignore[no-untyped-def]
    link = f"slap2:{tty}?addresses=0,1&baud=19200&lines=512"
    args = ["-m", "servotune.cli", "serve", "--link", link, "--port", str(port)]
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        *args,
        *("--data-dir", str(tmp / "data")),
        stdout=subprocess.DEVNULL,
        stderr=open(os.environ.get("BENCH_SERVER_LOG", os.devnull), "ab"),  # noqa: SIM115, ASYNC230
        env={**os.environ, "PYTHONPATH": pythonpath or os.environ.get("PYTHONPATH", "")},
    )
    try:
        async with httpx.AsyncClient(base_url=f"http://127.0.0.1:{port}", timeout=10) as client:
            for _ in range(500):
                with contextlib.suppress(httpx.HTTPError):
                    axes = (await client.get("/api/axes")).json()
                    if (await client.get(f"/api/axes/{axes[0]['id']}/state")).status_code == 200:
                        break
                await asyncio.sleep(0.05)
            await asyncio.sleep(1.0)  # start-up stop out, link settled
            await use_csrf_token(client)  # local mode still wants the token on writes
            yield process, client
    finally:
        process.terminate()
        await asyncio.wait_for(process.wait(), 10)


async def deadman(trials: int, port: int, client: httpx.AsyncClient, wire) -> None:  # type: ignore[no-untyped-def]
    axis = (await client.get("/api/axes")).json()[0]["id"]

    class _Server:  # what take_with_raw_client needs
        pass

    target = _Server()
    target.port = port  # type: ignore[attr-defined]
    modes = ["RST, no close frame", "network cut", "silent, machine alive"]
    if can_cut_the_network():
        modes.remove("network cut")
    for mode in modes:
        delays: list[float] = []
        for _ in range(trials):
            raw, client_id, beat = await take_with_raw_client(target, axis)  # type: ignore[arg-type]
            response = await client.post(
                f"/api/axes/{axis}/commands",
                json={"command": "velocity_mode"},
                headers={"X-Servotune-Client": client_id},
            )
            assert response.status_code == 200, response.text
            await asyncio.sleep(0.4)
            with contextlib.ExitStack() as vanish:
                if mode == "network cut":
                    vanish.enter_context(cut_network(raw.port))
                beat.cancel()
                gone = time.monotonic()
                if mode.startswith("RST"):
                    raw.drop()
                stopped = None
                while stopped is None and time.monotonic() - gone < 5:
                    stopped = wire.first("pm", 0, gone)
                    await asyncio.sleep(0.002)
            await raw.close_quietly()
            if stopped is None:
                lines = [line for _, line in wire.since(gone, 0)][:30]
                print(f"  {mode}: NO STOP within 5 s; module 0 got {lines}")
                continue
            delays.append(stopped - gone)
            if stopped - gone > 0.5 and mode != "silent, machine alive":
                lines = [line for _, line in wire.since(gone, 0)][:30]
                print(f"  {mode}: {1000 * (stopped - gone):.0f} ms; module 0 got {lines}")
            await asyncio.sleep(0.3)
        ms = sorted(1000 * d for d in delays)
        print(
            f"dead-man, {mode}: {len(ms)}/{trials} trials, median {statistics.median(ms):.0f} ms,"
            f" worst {ms[-1]:.0f} ms, best {ms[0]:.0f} ms"
        )


async def fanout(viewers: int, seconds: float, port: int, pid: int, with_holder: bool) -> None:
    async with httpx.AsyncClient(base_url=f"http://127.0.0.1:{port}") as client:
        axes = [a["id"] for a in (await client.get("/api/axes")).json()]
    url = f"ws://127.0.0.1:{port}/ws"
    stop = asyncio.Event()
    samples = [0] * viewers
    gaps: list[float] = []

    async def viewer(index: int) -> None:
        async with websockets.connect(url, max_size=None) as ws:
            last = None
            while not stop.is_set():
                try:
                    raw = await asyncio.wait_for(ws.recv(), 1)
                except TimeoutError:
                    continue
                message = json.loads(raw)
                if message["type"] == "telemetry":
                    now = time.monotonic()
                    if last is not None:
                        gaps.append(now - last)
                    last = now
                    samples[index] += len(message["t"])

    holder: RawWebsocket | None = None
    beat: asyncio.Task[None] | None = None
    if with_holder:

        class _Server:
            pass

        target = _Server()
        target.port = port  # type: ignore[attr-defined]
        holder, _, beat = await take_with_raw_client(target, axes[-1])  # type: ignore[arg-type]
    tasks = [asyncio.create_task(viewer(i)) for i in range(viewers)]
    await asyncio.sleep(1.0)
    start_samples = list(samples)
    cpu0, t0 = cpu_s(pid), time.monotonic()
    gaps.clear()
    await asyncio.sleep(seconds)
    cpu1, t1 = cpu_s(pid), time.monotonic()
    end_samples = list(samples)
    async with httpx.AsyncClient(base_url=f"http://127.0.0.1:{port}") as client:
        links = (await client.get("/api/links")).json()
        produced = 0.0
        for link in links:
            status = (await client.get(f"/api/links/{link['id']}/status")).json()
            produced += status["rate_hz"] * len(axes)
    stop.set()
    await asyncio.gather(*tasks, return_exceptions=True)
    if beat is not None:
        beat.cancel()
    if holder is not None:
        await holder.close_quietly()
    rates = [(e - s) / (t1 - t0) for s, e in zip(start_samples, end_samples, strict=True)]
    gaps.sort()
    p99 = gaps[int(0.99 * (len(gaps) - 1))] * 1000 if gaps else float("nan")
    print(
        f"fan-out, {viewers} viewers{' + 1 heartbeating holder' if with_holder else ''}: "
        f"server CPU {100 * (cpu1 - cpu0) / (t1 - t0):.1f} % of a core, samples/s per viewer "
        f"min {min(rates):.0f} median {statistics.median(rates):.0f} (link produces "
        f"{produced:.0f}: {100 * min(rates) / produced:.0f} % delivered to the slowest), "
        f"telemetry gap p99 {p99:.0f} ms"
    )


async def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--trials", type=int, default=20)
    parser.add_argument("--viewers", type=int, default=20)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--fanout-only", action="store_true", help="for a server without the lock")
    parser.add_argument("--server-pythonpath", default=None, help="run another servotune copy")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        with recorded_line(tmp, [0, 1]) as (simulator, wire):
            port = free_port()
            async with server_process(tmp, simulator.path, port, args.server_pythonpath) as (
                process,
                client,
            ):
                if not args.fanout_only and args.trials:
                    await deadman(args.trials, port, client, wire)
                await fanout(args.viewers, args.seconds, port, process.pid, not args.fanout_only)


if __name__ == "__main__":
    asyncio.run(main())
