"""One rig cannot disturb another.

A rig publishing 5,000 telemetry samples a second on its own subjects (one sample per
message, the hardest case for the hub) delayed the hub's keep-alives to another rig to
509 ms (lease 350 ms), and that rig's dead-man stopped a move the hub had started. Here:
the hub in a process of its own (``servotune hub``), the flooding rig in another
(tests/support/fake_rig.py, with rig-b's credentials), rig-a an in-process app on a simulated
SLAP2 line whose axis the hub set moving. Through the flood, rig-a's keep-alives keep
coming within its lease, its dead-man does not fire, it stays online at the hub, and
the hub sheds the flooding rig's oldest telemetry (its per-rig limit) while still
showing it.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import re
import sys
import threading
import time
from pathlib import Path

import httpx
import nats
import pytest

from servotune.api.app import AppConfig
from servotune.bus.connection import BusSettings
from servotune.bus.lane import cpu_wait_s
from servotune.bus.subjects import presence, rig_cmd
from servotune.config import LinkSpec
from servotune.hub.control_client import ControlSettings
from tests.support.bus_lab import VM, create_bus_state, start_app, stop_app, wait_for_manifest
from tests.support.control import recorded_line
from tests.support.nats import Lab, child_process, free_port, hub_command, nats_lab
from tests.support.paths import REPO as ROOT
from tests.support.servers import use_csrf_token

FLOOD_SAMPLES_PER_S = 5000.0
FLOOD_S = 10.0


def _gaps(times: list[float], start: float, end: float) -> list[float]:
    window = [t for t in times if start <= t <= end]
    return [b - a for a, b in itertools.pairwise(window)]


class KeepAliveWatch:
    """rig-a's keep-alives as they arrive at a client of its own (rig-a's credentials),
    and rig-a's presence (the hub's STOP user may hear it), in a thread and loop of its
    own: when they came, whatever the test's loop does."""

    def __init__(self, lab: Lab) -> None:
        self._lab = lab
        self.times: list[float] = []
        # This thread's time waiting for a CPU at each arrival (the kernel's account).
        self.cpu_waits: list[float] = []
        self.presences: list[float] = []
        self._ready = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=lambda: asyncio.run(self._run()), daemon=True)

    async def _run(self) -> None:
        user = self._lab.users["rig-a"]
        nc = await nats.connect(
            self._lab.url, user=user.name, password=user.password, inbox_prefix="_INBOX_rig-a"
        )

        async def heard(_: object) -> None:
            self.times.append(time.monotonic())
            self.cpu_waits.append(cpu_wait_s() or 0.0)

        await nc.subscribe(rig_cmd("rig-a", "keepalive"), cb=heard)
        await nc.flush()
        hub_stop = self._lab.users["hub-stop"]
        presence_nc = await nats.connect(
            self._lab.url, user=hub_stop.name, password=hub_stop.password
        )

        async def present(_: object) -> None:
            self.presences.append(time.monotonic())

        await presence_nc.subscribe(presence("rig-a"), cb=present)
        await presence_nc.flush()
        self._ready.set()
        await asyncio.to_thread(self._stop.wait)
        await nc.close()
        await presence_nc.close()

    def __enter__(self) -> KeepAliveWatch:
        self._thread.start()
        assert self._ready.wait(10), "the keep-alive watch did not connect"
        return self

    def __exit__(self, *_: object) -> None:
        self._stop.set()
        self._thread.join(10)


@pytest.mark.slow
async def test_a_rigs_telemetry_flood_does_not_disturb_another_rig(tmp_path: Path) -> None:
    (tmp_path / "rig-a").mkdir()
    async with nats_lab(tmp_path / "nats", ["rig-a", "rig-b"]) as lab:
        await create_bus_state(lab)
        with recorded_line(tmp_path / "rig-a", [0, 1]) as (simulator, wire):
            rig = await start_app(
                AppConfig(
                    links=[LinkSpec("slap2", simulator.path, "line", 19200, [0, 1], 512)],
                    data_dir=tmp_path / "rig-a" / "data",
                    web_dir=tmp_path / "no-web",
                    twin=False,
                    control=ControlSettings(),
                    bus=BusSettings(
                        url=lab.rig_url("rig-a"),
                        rig="rig-a",
                        credentials=lab.users["rig-a"].credentials,
                    ),
                )
            )
            try:
                await wait_for_manifest(lab, "rig-a")
                await _flood(lab, tmp_path, rig, wire)
            finally:
                await stop_app(rig)


async def _flood(lab: Lab, tmp_path: Path, rig: object, wire: object) -> None:
    port = free_port()
    hub_args = hub_command(lab, port, tmp_path / "hub-data")
    flood_args = [
        sys.executable,
        "-m",
        "tests.support.fake_rig",
        "--url",
        lab.url,
        "--credentials",
        str(lab.users["rig-b"].credentials),
        "--rig",
        "rig-b",
        "--samples-per-s",
        str(FLOOD_SAMPLES_PER_S),
        "--batch",
        "1",
        "--quiet-s",
        "4",
        "--seconds",
        str(FLOOD_S),
    ]
    lease_s = rig.app.state.control.settings.lease_s  # type: ignore[attr-defined]
    with child_process(hub_args, tmp_path / "hub.log", ROOT) as hub_process:
        async with httpx.AsyncClient(base_url=f"http://127.0.0.1:{port}", timeout=60) as hub:
            for _ in range(600):
                with contextlib.suppress(httpx.HTTPError):
                    state = await hub.get("/api/axes/rig-a.line-0/state")
                    if state.status_code == 200 and state.json()["health"] != "offline":
                        break
                await asyncio.sleep(0.1)
            else:
                raise AssertionError((tmp_path / "hub.log").read_text()[-3000:])
            await use_csrf_token(hub)
            # The hub sets rig-a's axis moving: the hub session is its mover, the
            # rig's dead-man stops it if the keep-alives stop for the lease.
            response = await hub.post(
                "/api/axes/rig-a.line-0/commands", json={"command": "velocity_mode"}
            )
            assert response.status_code == 200, response.text
            moved = time.monotonic()
            assert wire.bus.module(0).rss & VM  # type: ignore[attr-defined]
            with (
                KeepAliveWatch(lab) as watch,
                child_process(flood_args, tmp_path / "flood.log", ROOT) as flooder,
            ):
                flood_from = time.monotonic() + 4.0  # after --quiet-s
                test_waited = cpu_wait_s() or 0.0
                offline_seen = []
                while flooder.poll() is None:
                    # Shown offline by the hub (silence), not by rig-a's own link. A
                    # poll the starved hub does not answer in time tells nothing.
                    with contextlib.suppress(httpx.TimeoutException):
                        status = (await hub.get("/api/links/rig-a.line/status")).json()
                        if status["state"] == "disconnected":
                            offline_seen.append((time.monotonic(), status["message"]))
                    await asyncio.sleep(0.2)
                flood_to = time.monotonic()
                test_waited = (cpu_wait_s() or 0.0) - test_waited
            lines = (tmp_path / "flood.log").read_text().splitlines()
            report = json.loads(next(line for line in lines if line.startswith("{")))
            counters = (await hub.get("/api/links/rig-b.line/status")).json()["counters"]
        # Stopped as an operator would: it logs its account of its keep-alive rounds.
        hub_process.terminate()
        hub_process.wait(30)
    summary = next(
        line
        for line in (tmp_path / "hub.log").read_text().splitlines()
        if "keep-alive rounds" in line
    )
    print(f"hub: {summary}")
    print(f"rig-b at the hub: {counters}")
    # The flood happened as intended (a precondition, not the product).
    assert report["samples_per_s"] >= 0.8 * FLOOD_SAMPLES_PER_S, report
    # What the hub could have caused (its gaps less its safety thread's waits for a CPU,
    # the kernel's account) stays within the lease: the flood does not delay them.
    not_cpu_ms = _ms(r"not spent waiting for a CPU (\d+) ms", summary)
    hub_cpu_ms = _ms(r"longest wait for a CPU (\d+) ms", summary)
    assert not_cpu_ms < 1000 * lease_s, summary
    # And so they arrive at rig-a: every gap within the lease but for the waits for a
    # CPU of the hub's safety thread and of this observer. This machine is shared
    # (load averages of 15-25 on its 2 cores were seen while this was written): there
    # any process may wait 100s of ms, which is not what this test is about.
    arrivals = [
        (t, w)
        for t, w in zip(watch.times, watch.cpu_waits, strict=True)
        if flood_from <= t <= flood_to
    ]
    gaps = [(b[0] - a[0], b[1] - a[1]) for a, b in itertools.pairwise(arrivals)]
    assert len(gaps) > 5 * FLOOD_S, f"{len(gaps)} keep-alives in the flood"
    worst, observer_wait = max(gaps)
    print(
        f"flood {report['samples_per_s']:.0f} samples/s; rig-a's keep-alives: {len(gaps)} "
        f"gaps, max {1000 * worst:.0f} ms ({1000 * observer_wait:.0f} ms of it the observer "
        f"waiting for a CPU); lease {1000 * lease_s:.0f} ms; this test's loop waited "
        f"{1000 * test_waited:.0f} ms for a CPU during the flood"
    )
    for gap, waited in gaps:
        assert gap - waited - hub_cpu_ms / 1000 < lease_s, (gap, waited, summary)
    # The move the hub started was not stopped by rig-a's dead-man (unless rig-a itself,
    # in this test's process, was starved of the CPU: the kernel's account again).
    # A STOP of a moving SLAP2 axis sends pm (a hold), or st and the spwm 0 brake when
    # its loop could not be judged: any of them means it was stopped.
    stops = [
        at
        for at, sent in wire.since(moved, 0)  # type: ignore[attr-defined]
        if sent in ("st", "pm") or sent.replace(" ", "") == "spwm0"
    ]
    if stops:
        assert test_waited > lease_s, f"STOP on rig-a; this process waited {test_waited:.2f} s"
    else:
        assert wire.bus.module(0).rss & VM  # type: ignore[attr-defined]
    # rig-a was shown offline only if it fell silent (this process, where rig-a runs,
    # starved of the CPU for longer than offline_after_s: seen at load averages of 17).
    silences = [b - a for a, b in itertools.pairwise(watch.presences) if a >= flood_from - 1.0]
    if offline_seen:
        assert max(silences) > 1.0, (
            f"shown offline, its presence at most {max(silences):.2f} s apart"
        )
    # The flooding rig was shown, within its limit: its oldest shed.
    assert counters.get("batches_shed", 0) > 0, counters


def _ms(pattern: str, text: str) -> int:
    found = re.search(pattern, text)
    assert found is not None, text
    return int(found[1])
