"""The dashboard in headless Chromium, against a live server and simulated modules."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest
from playwright.async_api import Browser, Page, expect

from servotune.api.app import WEB_DIST
from tests.support.paths import ARTIFACTS
from tests.support.servers import LiveServer, live_server

pytestmark = pytest.mark.browser


async def samples_received(page: Page, axis_id: str) -> int:
    count: int = await page.evaluate(f"window.__servotune.samplesReceived({axis_id!r})")
    return count


async def test_tune_kp_and_stop_in_the_browser(dashboard: tuple[Page, LiveServer]) -> None:
    page, server = dashboard
    await page.get_by_test_id("axis-link-line-0").click()
    await expect(page.get_by_test_id("plot-position")).to_be_visible()

    # Live plots: samples keep arriving (how fast depends on the machine's load: wait
    # for ten more, up to 20 s, rather than counting those of one second).
    first = await samples_received(page, "line-0")
    for _ in range(200):
        if await samples_received(page, "line-0") > first + 10:
            break
        await asyncio.sleep(0.1)
    assert await samples_received(page, "line-0") > first + 10

    # Move the kp slider: applied on release, read back from the simulated module.
    await page.get_by_test_id("param-kp-slider").fill("65")
    await expect(page.get_by_test_id("param-kp-device")).to_contain_text("65", timeout=5000)
    assert server.bus.module(0).settings["kp"] == 65
    await expect(page.get_by_test_id("param-kp-input")).to_have_value("65")

    # Out-of-range typed value: a clear error, nothing sent.
    await page.get_by_test_id("param-kd-input").fill("40000")
    await page.get_by_test_id("param-kd-input").press("Enter")
    await expect(page.get_by_test_id("error-message")).to_contain_text("32767")
    assert server.bus.module(0).settings["kd"] == 80

    # Position mode and a move, then STOP.
    await page.get_by_test_id("cmd-position_mode").click()
    await page.get_by_test_id("cmd-move_absolute-position").fill("3000")
    await page.get_by_test_id("cmd-move_absolute").click()
    for _ in range(100):
        if server.bus.module(0).moving:
            break
        await asyncio.sleep(0.02)
    await page.get_by_test_id("stop-all").click()
    # STOP holds the shaft in pm where it is (docs/control.md): pm on, vm off, no move running.
    module = server.bus.module(0)
    for _ in range(100):
        if module.rss & 0b1100 == 0b1000 and not module.moving:
            break
        await asyncio.sleep(0.02)
    assert module.rss & 0b1100 == 0b1000 and not module.moving, "STOP did not stop and hold"

    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    await page.screenshot(path=str(ARTIFACTS / "dashboard-slap2.png"), full_page=True)


async def test_escape_key_stops_every_axis(dashboard: tuple[Page, LiveServer]) -> None:
    page, server = dashboard
    await page.get_by_test_id("axis-link-line-1").click()
    await page.get_by_test_id("cmd-velocity_mode").click()
    for _ in range(100):
        if server.bus.module(1).rss & 0b0100:
            break
        await asyncio.sleep(0.02)
    assert server.bus.module(1).rss & 0b0100, "velocity mode did not start"
    await page.get_by_test_id("console-input").focus()
    await page.keyboard.press("Escape")
    for _ in range(100):  # STOP from vm holds in pm
        if server.bus.module(1).rss & 0b1100 == 0b1000:
            break
        await asyncio.sleep(0.02)
    assert server.bus.module(1).rss & 0b1100 == 0b1000, "Esc did not stop and hold the axis"


async def test_console_shows_multiline_reply(dashboard: tuple[Page, LiveServer]) -> None:
    page, _ = dashboard
    await page.get_by_test_id("axis-link-line-0").click()
    console = page.get_by_test_id("console-input")
    await console.fill("rrss")
    await console.press("Enter")
    output = page.get_by_test_id("console-output")
    await expect(output).to_contain_text("rrss")
    await expect(output).to_contain_text("inpos", timeout=5000)


async def test_z1100_axis_renders_and_k_reads_back(tmp_path: Path, browser: Browser) -> None:
    from servotune.config import LinkSpec
    from tests.support.sim_lines import z1100_chip_process

    with z1100_chip_process(tmp_path) as (sim, chip):
        spec = LinkSpec("z1100", sim.path, "chip", 38400, [0, 1, 2])
        async with live_server(sim, chip, tmp_path / "data", web_dir=WEB_DIST, spec=spec) as server:
            page = await browser.new_page(viewport={"width": 1400, "height": 900})
            await page.goto(server.base_url)
            await page.get_by_test_id("axis-link-chip-y").click()
            await expect(page.get_by_test_id("plot-position")).to_be_visible()
            await expect(page.get_by_test_id("param-kabd_k-device")).not_to_have_text("—")
            kabd_k = chip.parameters(1).kabd.k
            field = page.get_by_test_id("param-kabh_k-input")
            await field.fill("100")
            await field.press("Enter")
            # KABH and KABD are one write group (KABH overwrites KABD on the chip).
            await page.get_by_test_id("write-group-0").click()
            await expect(page.get_by_test_id("param-kabh_k-device")).to_have_text(
                "100", timeout=5000
            )
            assert chip.parameters(1).kabh.k == 100
            # KABD was written after KABH with the user's values: not lost.
            await expect(page.get_by_test_id("param-kabd_k-device")).to_have_text(str(kabd_k))
            ARTIFACTS.mkdir(parents=True, exist_ok=True)
            await page.screenshot(path=str(ARTIFACTS / "dashboard-z1100.png"))
            await page.close()


async def test_ep7047_modulo_plus_move_ends_in_target(tmp_path: Path, browser: Browser) -> None:
    from servotune.config import LinkSpec

    spec = LinkSpec("ep7047", "sim", "ep", 0, [1])
    async with live_server(None, None, tmp_path / "data", web_dir=WEB_DIST, spec=spec) as server:
        page = await browser.new_page(viewport={"width": 1400, "height": 900})
        await page.goto(server.base_url)
        await page.get_by_test_id("axis-link-ep-1").click()
        await page.get_by_test_id("cmd-execute_move-start_type").select_option(
            label="MODULO_PLUS (0x0205)"
        )
        await page.get_by_test_id("cmd-execute_move-target").fill("1024")

        async def watchdog_trips() -> int:
            status = (await server.client.get("/api/links/ep/status")).json()
            return int(status["counters"].get("watchdog_trips", 0))

        # The simulated drive and its master run in the link's cycle process, paced like
        # a real NIC's: a stall of this process does not starve its 100 ms watchdog, so
        # the move is made once and no watchdog trip is accepted.
        trips = await watchdog_trips()
        await page.get_by_test_id("cmd-enable").click()
        await expect(page.get_by_test_id("flag-stm_ready")).to_have_attribute("data-on", "1")
        await page.get_by_test_id("cmd-execute_move").click()
        # Modulo factor of the demo axis: one turn of 4096 counts; target 1024 in it. The
        # move is short: on a loaded host the page may never render a frame while "busy"
        # is on, so the move is seen in the position, then the page must agree.
        for _ in range(200):
            state = (await server.client.get("/api/axes/ep-1/state")).json()
            if state["position"] is not None and round(state["position"]) % 4096 == 1024:
                break
            await asyncio.sleep(0.05)
        assert await watchdog_trips() == trips, "the drive's watchdog tripped"
        assert round(state["position"]) % 4096 == 1024, state
        await expect(page.get_by_test_id("flag-in_target")).to_have_attribute(
            "data-on", "1", timeout=10_000
        )
        await expect(page.get_by_test_id("flag-busy")).to_have_attribute("data-on", "0")
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        await page.screenshot(path=str(ARTIFACTS / "dashboard-ep7047.png"))
        await page.close()


async def test_bench_overlays_two_runs_with_different_kp(
    dashboard: tuple[Page, LiveServer],
) -> None:
    page, server = dashboard
    await page.get_by_test_id("axis-link-line-0").click()
    await page.get_by_test_id("bench-toggle").click()
    await page.get_by_test_id("bench-kind").select_option("move")
    await page.get_by_test_id("bench-distance").fill("2000")
    run_ids: list[str] = []
    for kp in (40, 120):
        response = await server.client.patch("/api/axes/line-0/params", json={"kp": kp})
        assert response.status_code == 200
        await expect(page.get_by_test_id("bench-run")).to_be_enabled(timeout=10_000)
        await page.get_by_test_id("bench-run").click()
        await expect(page.get_by_test_id("bench-progress")).to_have_attribute(
            "data-status", "complete", timeout=15_000
        )
        runs = (await server.client.get("/api/axes/line-0/bench/runs")).json()
        run_ids = [r["id"] for r in runs]
    assert len(run_ids) == 2
    for run_id in run_ids:
        checkbox = page.get_by_test_id(f"bench-run-select-{run_id}")
        if not await checkbox.is_checked():
            await checkbox.check()
        # A metric row per run, with a value from the server (not the rise time: at
        # the SLAP2's polling rate a 2000-count move has too few samples in its rise,
        # and the server nulls it with the reason).
        cell = page.get_by_test_id(f"bench-metric-{run_id}-steady_state_error")
        await expect(cell).not_to_have_attribute("data-value", "")
    await expect(page.get_by_test_id("bench-overlay")).to_have_attribute("data-series", "2")
    await expect(page.get_by_test_id("bench-param-diff")).to_contain_text("kp")
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    await page.screenshot(path=str(ARTIFACTS / "bench-overlay.png"), full_page=True)


async def test_saving_limits_on_the_page_keeps_the_travel_window(
    dashboard: tuple[Page, LiveServer],
) -> None:
    """The page has no travel-window fields: saving the other limits sends the window
    back as the server holds it instead of clearing it."""
    page, server = dashboard
    window = {"min_position_counts": -50_000, "max_position_counts": 50_000}
    limits = {"max_distance_counts": 20_000, "max_velocity": 20_000, "max_pwm": 80}
    response = await server.client.put(
        "/api/axes/line-0/bench/limits", json={**limits, "max_duration_s": 10, **window}
    )
    assert response.status_code == 200
    await page.get_by_test_id("axis-link-line-0").click()
    await page.get_by_test_id("bench-toggle").click()
    await page.get_by_test_id("bench-limit-max_pwm").fill("70")
    await page.get_by_test_id("bench-limits-save").click()
    await expect(page.locator(".bench-limits-status")).to_contain_text("saved")
    saved = (await server.client.get("/api/axes/line-0/bench")).json()["limits"]
    assert saved["max_pwm"] == 70
    assert {k: saved[k] for k in window} == window
