"""Nothing holds a STOP back: a large import, its exports and an
auto-tune identification with its fit run while STOPs are sent and telemetry flows.

Before the fix a 6.66 MB import held a STOP for 2.5-3.3 s and a 39.8 MB one for 14 s:
the body was parsed, validated and stored on the event loop, so a STOP waited for the
whole import. The bounds asserted are what the design guarantees on any host, however
loaded (the import runs in its own process, exports in small pieces): in each phase
STOPs keep being answered (at least three, each in less than half the phase), and the
other line's telemetry never pauses for half the import. The measured figures per
phase are printed (targets on a quiet machine: STOP 50 ms, telemetry gap 100 ms).
"""

from __future__ import annotations

import asyncio
import itertools
import json
import os
import statistics
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
import websockets

from servotune.config import LinkSpec
from tests.support.bench import finished_run, start
from tests.support.servers import origin, serve, sim_process

IMPORT_ROWS = 250_000  # about 16 MB of CSV
EXPORTS_MIN_S = 1.5  # the exports phase lasts at least this (see the test)

# The product's own loop lag and STOP time on this host: run alone (scripts/test.sh).
pytestmark = pytest.mark.host_timing


def _big_csv(meta: dict[str, Any]) -> bytes:
    columns, flags = meta["columns"], meta["flags"]
    header = ",".join([*columns, *flags]) + "\n"
    values = ",".join(f"{1000.0 + i:.1f}" for i in range(len(columns) - 1))
    flag_text = ",".join("0" for _ in flags)
    lines = [f"{i * 0.02:.6f},{values},{flag_text}\n" for i in range(IMPORT_ROWS)]
    return (header + "".join(lines)).encode()


async def test_stop_and_telemetry_are_not_held_back_by_import_export_and_fit(
    tmp_path: Path,
) -> None:
    # The simulator in its own process, like a real device: in this process it would
    # compete with the server for the interpreter and measure itself, not the server.
    # Two lines: STOPs go to one, the identification runs on the other.
    with sim_process(tmp_path / "a") as path_a, sim_process(tmp_path / "b") as path_b:
        specs = [
            LinkSpec("slap2", path_a, "line", 19200, [0], 512),
            LinkSpec("slap2", path_b, "tune", 19200, [0], 512),
        ]
        async with serve(specs, tmp_path / "data") as (_, client, ws_url):
            server = SimpleNamespace(client=client)
            run = await finished_run(
                server, "line-0", await start(server, "line-0", kind="move", distance=500)
            )
            meta = (await client.get(f"/api/bench/runs/{run['id']}/run.json")).json()
            body = await asyncio.to_thread(_big_csv, meta)
            print(f"\nimport: {len(body) / 1e6:.1f} MB of CSV, {IMPORT_ROWS} rows")

            telemetry: list[float] = []
            lags: list[tuple[float, float]] = []
            stops: list[tuple[float, float]] = []  # (sent, latency)
            done = asyncio.Event()

            async def watch_telemetry() -> None:
                async with websockets.connect(ws_url, max_size=None, origin=origin(ws_url)) as ws:
                    while not done.is_set():
                        try:
                            text = await asyncio.wait_for(ws.recv(), 0.5)
                        except TimeoutError:
                            continue
                        # The other line: its telemetry does not depend on the STOPs.
                        if '"telemetry"' in text[:40] and '"tune-0"' in text[:80]:
                            telemetry.append(time.perf_counter())

            async def watch_loop() -> None:
                while not done.is_set():
                    before = time.perf_counter()
                    await asyncio.sleep(0.01)
                    now = time.perf_counter()
                    lags.append((now, now - before - 0.01))

            statuses: list[int] = []

            async def send_stops() -> None:
                while not done.is_set():
                    sent = time.perf_counter()
                    response = await client.post(
                        "/api/axes/line-0/commands", json={"command": "stop"}
                    )
                    stops.append((sent, time.perf_counter() - sent))
                    statuses.append(response.status_code)
                    response.json()  # always a JSON answer
                    await asyncio.sleep(0.2)

            watchers = [
                asyncio.create_task(watch_telemetry()),
                asyncio.create_task(watch_loop()),
            ]
            await asyncio.sleep(1.0)  # telemetry flowing
            stopper = asyncio.create_task(send_stops())
            phases: list[tuple[str, float, float]] = []
            began = time.perf_counter()
            response = await client.post(
                "/api/axes/line-0/bench/runs/import",
                files={
                    "meta": ("run.json", json.dumps(meta), "application/json"),
                    "csv": ("samples.csv", body, "text/csv"),
                },
                timeout=300,
            )
            imported_at = time.perf_counter()
            phases.append(("import", began, imported_at))
            assert response.status_code == 201, response.text
            run_id = response.json()["id"]
            # Exported again until the phase lasts EXPORTS_MIN_S: on a fast host one
            # pair of exports takes 0.5 s, too short for the STOPs this test counts.
            exports = 0
            while exports == 0 or time.perf_counter() - imported_at < EXPORTS_MIN_S:
                size = 0
                async with client.stream("GET", f"/api/bench/runs/{run_id}", timeout=300) as r:
                    async for chunk in r.aiter_bytes():
                        size += len(chunk)
                lines = 0
                async with client.stream(
                    "GET", f"/api/bench/runs/{run_id}/samples.csv", timeout=300
                ) as r:
                    async for chunk in r.aiter_bytes():
                        lines += chunk.count(b"\n")
                assert lines == IMPORT_ROWS + 1 and size > 20 * IMPORT_ROWS
                exports += 1
            phases.append((f"exports (x{exports})", imported_at, time.perf_counter()))
            fit_began = time.perf_counter()
            proposal = await client.post(
                "/api/axes/tune-0/autotune/identify",
                json={"max_pwm": 60, "max_distance_counts": 4000},
                timeout=120,
            )
            phases.append(("auto-tune identify + fit", fit_began, time.perf_counter()))
            done.set()
            await stopper
            for task in watchers:
                await task

            gaps = [(b, b - a) for a, b in itertools.pairwise(telemetry) if b >= began]
            for name, t_from, t_to in phases:
                in_phase = [lat for sent, lat in stops if t_from <= sent < t_to] or [0.0]
                phase_gaps = [g for t, g in gaps if t_from <= t < t_to] or [0.0]
                phase_lags = [lag for t, lag in lags if t_from <= t < t_to] or [0.0]
                print(
                    f"{name}: {t_to - t_from:.1f} s, {len(in_phase)} STOPs median "
                    f"{statistics.median(in_phase) * 1000:.0f} ms max {max(in_phase) * 1000:.0f}"
                    f" ms; telemetry gap max {max(phase_gaps) * 1000:.0f} ms; event-loop lag "
                    f"max {max(phase_lags) * 1000:.0f} ms"
                )
            print(f"STOP answers {sorted(set(statuses))}; load {os.getloadavg()[0]:.1f}")
            # The staircase, the fit and the gain search ran (on a heavily loaded host
            # the fitted tau can be too blurred for any gains to qualify: a 409 that
            # says so, after the whole search).
            assert proposal.status_code == 200 or (
                proposal.status_code == 409 and "no gains meet the rule" in proposal.text
            ), proposal.text
            # What the design guarantees on any host, loaded or not: the heavy work does
            # not hold the loop for its duration (before, a STOP sent during an import
            # was answered only after the whole body was parsed and stored).
            for name, t_from, t_to in phases:
                answered = [
                    (sent, lat) for sent, lat in stops if t_from <= sent and sent + lat < t_to
                ]
                # A STOP leaves every 0.2 s plus its latency: three fit in a phase of
                # 1.2 s; a shorter phase (a fast host) must still answer one before it
                # ends, which a loop held for the phase's duration cannot.
                wanted = max(1, min(3, int((t_to - t_from) / 0.4)))
                assert len(answered) >= wanted, f"{name}: only {len(answered)} STOPs answered"
                assert max(lat for _, lat in answered) < 0.5 * (t_to - t_from), name
            import_s = imported_at - began
            assert max(g for t, g in gaps if t < imported_at) < 0.5 * import_s
