"""Soak: a held, idle page in headless Chromium under a CPU hog on every core must keep
its axis (no false dead-man stops under load).

``python -m servotune demo`` runs as a subprocess (autopilot on for the other axes:
their plots keep the page drawing), a page holds one SLAP2 axis (Take control) and
stays idle for ``SERVOTUNE_DEADMAN_SOAK_S`` seconds (run only when it is set; the issue's
soak is ``SERVOTUNE_DEADMAN_SOAK_S=1800``) while one busy
process per core runs. Asserted: no dead-man stop of that axis and the page still holds
it at the end. Printed (``-s``): the load, how often and how long the page's own thread
was held off (a 100 ms interval timer in the page: gaps over the lease are where the
page's own heartbeats would have tripped the dead-man), and the events.
"""

from __future__ import annotations

import asyncio
import os
import re
import time
from pathlib import Path

import pytest
from playwright.async_api import async_playwright, expect

from servotune.perf.demo import StreamWatcher, cpu_hog, demo_server, load_average
from tests.support.browser import CHROMIUM, CHROMIUM_ARGS

# A soak, run on purpose (SERVOTUNE_DEADMAN_SOAK_S=1800, the 30 minutes): a CPU
# hog on every core for that long is no part of the suite. In the suite a 60 s run had one
# false stop (2.0 s without a worker heartbeat, the connection not checkable): known,
# docs/notes/issue-24-stops.md.
pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        "SERVOTUNE_DEADMAN_SOAK_S" not in os.environ,
        reason="a soak: set SERVOTUNE_DEADMAN_SOAK_S (seconds) to run it",
    ),
]

SOAK_S = float(os.environ.get("SERVOTUNE_DEADMAN_SOAK_S", "1800"))
AXIS = "demo-slap2-1"
LEASE_MS = 350

# A 100 ms interval timer in the page: how late its ticks come is how long the page's
# own thread was held off (what used to delay its heartbeats).
GAP_METER = """() => {
  const w = window;
  w.__gaps = { n: 0, over: 0, max: 0, last: performance.now() };
  setInterval(() => {
    const now = performance.now(), gap = now - w.__gaps.last;
    w.__gaps.last = now; w.__gaps.n += 1;
    if (gap > w.__gaps.max) w.__gaps.max = gap;
    if (gap > OVER) w.__gaps.over += 1;
  }, 100);
}""".replace("OVER", str(100 + LEASE_MS))


async def test_a_held_idle_page_keeps_its_axis_under_a_cpu_hog(tmp_path: Path) -> None:
    assert Path(CHROMIUM).exists(), "install Debian's chromium (scripts/test.sh does)"
    log = tmp_path / "server.log"
    with (
        demo_server(data_dir=tmp_path / "data", log_path=log, connect_timeout_s=120) as server,
        StreamWatcher(server.base_url) as stream,
    ):
        async with async_playwright() as playwright:
            browser = await playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            try:
                page = await browser.new_page(viewport={"width": 1440, "height": 900})
                await page.goto(f"{server.base_url}/#/axis/{AXIS}")
                await page.get_by_test_id("control-take").click(timeout=30_000)
                await expect(page.get_by_test_id("control-badge")).to_have_text(
                    "yours", timeout=30_000
                )
                await page.evaluate(GAP_METER)
                load = [load_average()[0]]
                lost_at: float | None = None
                start = time.monotonic()
                with cpu_hog():
                    while time.monotonic() - start < SOAK_S:
                        await asyncio.sleep(5)
                        load.append(load_average()[0])
                        badge = await page.get_by_test_id("control-badge").inner_text()
                        if badge != "yours" and lost_at is None:
                            lost_at = time.monotonic() - start
                gaps = await page.evaluate("() => window.__gaps")
                badge = await page.get_by_test_id("control-badge").inner_text()
                await asyncio.sleep(1)  # the last events reach the watcher
                with stream.lock:  # before the page closes (its axis then lapses, rightly)
                    events = list(stream.counts.event_texts)
            finally:
                await browser.close()
    mine = [e for e in events if "dead-man" in e]
    # The server's own view: the longest it went without a heartbeat from the page's
    # tab while it held the axis (logged by the control service when it grows).
    gaps_ms = [
        float(m.group(1))
        for m in re.finditer(r"dead-man: \S+ heard after (\d+) ms", log.read_text(errors="replace"))
    ]
    print(
        f"\ndead-man soak: {SOAK_S:.0f} s, a CPU hog on each of {os.cpu_count()} cores, "
        f"load average (1 min) min {min(load):.1f} / max {max(load):.1f}; page timer: "
        f"{gaps['n']} ticks, worst gap {gaps['max']:.0f} ms, {gaps['over']} gaps over "
        f"{100 + LEASE_MS} ms (where the page's own heartbeats would have tripped); "
        f"dead-man events: {len(mine)}; badge at the end: {badge!r}; server: worst heartbeat "
        f"gap {max(gaps_ms, default=0):.0f} ms ({len(gaps_ms)} new worsts over {LEASE_MS // 2} ms)"
    )
    for event in mine[:10]:
        print("  ", event)
    assert not mine, f"false dead-man stops: {mine}"
    assert lost_at is None and badge == "yours", f"the page lost its axis after {lost_at} s"
