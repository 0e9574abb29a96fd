"""The frequency response and the what-if view in headless Chromium.

A SLAP2 on the pty simulator: identify the plant (auto-tune), run a frequency response
from the bench page and see its Bode plot, Nyquist plot and margins; the what-if view's
margins (computed in the browser) agree with the server's (python-control); "Apply and
verify" runs the verification step and the prediction is compared with it.
"""

from __future__ import annotations

import asyncio
import json
import statistics
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from playwright.async_api import Browser, Page, expect

from servotune.devices.slap2.sim.module import Slap2Module
from tests.support.browser import one_module_page
from tests.support.paths import ARTIFACTS
from tests.support.servers import LiveServer

pytestmark = pytest.mark.browser

# What-if prediction against the measured verification step: RMS over the record of
# measured - predicted, as a fraction of the step. The prediction is linear (no
# friction) and today's samples carry the time they were parsed, not latched (tens of
# ms late during the rise): 10 % of the step is what both allow.
RMS_TOLERANCE = 0.10


@pytest.fixture
async def page_and_server(
    tmp_path: Path,
    browser: Browser,
) -> AsyncIterator[tuple[Page, LiveServer]]:
    module = Slap2Module(0, eeprom_path=tmp_path / "eeprom_0.json")
    async with one_module_page(
        tmp_path, browser, module, {"width": 1400, "height": 1200}
    ) as page_server:
        yield page_server


async def slide(page: Page, testid: str, value: int) -> None:
    """Move a range slider as a user's drag does: value, then an input event."""
    await page.get_by_test_id(testid).evaluate(
        "(el, v) => { el.value = String(v); el.dispatchEvent(new Event('input')); }", value
    )


async def test_frequency_response_bode_margins_and_what_if(
    page_and_server: tuple[Page, LiveServer],
) -> None:
    page, server = page_and_server
    # The bench page open before the identification: the what-if view has no model yet
    # and gets it live when the identification's run ends (no reload).
    await page.goto(server.base_url)
    await page.get_by_test_id("axis-link-line-0").click()
    await page.get_by_test_id("bench-toggle").click()
    await expect(page.get_by_test_id("whatif-status")).to_contain_text(
        "no identified plant model", timeout=10_000
    )
    # The identification is this test's precondition, not its subject (test_autotune.py
    # has that): a second attempt when a starved host lost the line during the first.
    for _attempt in range(2):
        response = await server.client.post(
            "/api/axes/line-0/autotune/identify",
            json={"max_pwm": 60, "max_distance_counts": 4000, "response": "no_overshoot"},
            timeout=60,
        )
        if response.status_code == 200:
            break
        await asyncio.sleep(1.0)
    assert response.status_code == 200, response.text
    proposal = response.json()["gains"]
    await expect(page.get_by_test_id("whatif-pm")).to_contain_text("°", timeout=15_000)
    await expect(page.get_by_test_id("whatif-proposal")).to_be_visible()
    panel = page.get_by_test_id("frf-panel")
    await expect(panel).to_be_visible(timeout=10_000)
    await page.get_by_test_id("frf-low_hz").fill("1")
    await page.get_by_test_id("frf-high_hz").fill("40")
    await page.get_by_test_id("frf-duration_s").fill("5")
    await expect(page.get_by_test_id("frf-inject")).to_have_value("closed")
    await expect(page.get_by_test_id("frf-pwm")).to_be_hidden()  # open loop only
    # Open loop asks first; dismissed, nothing is started.
    await page.get_by_test_id("frf-inject").select_option("open")
    await expect(page.get_by_test_id("frf-pwm")).to_be_visible()
    await expect(page.get_by_test_id("frf-amplitude")).to_be_hidden()
    dialogs: list[str] = []
    before = len((await server.client.get("/api/axes/line-0/bench/runs")).json())

    async def dismiss(dialog: Any) -> None:
        dialogs.append(dialog.message)
        await dialog.dismiss()

    page.once("dialog", dismiss)
    await page.get_by_test_id("frf-run").click()
    for _ in range(100):
        if dialogs:
            break
        await asyncio.sleep(0.05)
    assert dialogs and "position controller is OFF" in dialogs[0], dialogs
    await asyncio.sleep(0.3)
    assert len((await server.client.get("/api/axes/line-0/bench/runs")).json()) == before
    await page.get_by_test_id("frf-inject").select_option("closed")
    # A host starved by other work polls far below the wire's rate; the server then says
    # the capture is too sparse to measure (the product's honest answer, checked here),
    # and the user runs it again: so does this test, at most twice.
    retakes: list[str] = []
    for _attempt in range(3):
        clicked = time.monotonic()
        await page.get_by_test_id("frf-run").click()
        for _ in range(600):
            runs = (await server.client.get("/api/axes/line-0/bench/runs")).json()
            # (the click's run may not exist yet: the previous run is the last then)
            if len(runs) > before and runs[-1]["status"] != "recording":
                break
            await asyncio.sleep(0.05)
        before = len(runs)
        assert runs[-1]["test"]["kind"] == "frequency_response"
        assert runs[-1]["status"] == "complete", runs[-1]["message"]
        frf_run_s = time.monotonic() - clicked
        first = (await server.client.get(f"/api/bench/runs/{runs[-1]['id']}/frf")).json()
        problem = first["measured_problem"] or ""
        if first["measured"] is not None or "too sparse to measure" not in problem:
            break
        retakes.append(problem)
        await expect(page.get_by_test_id("frf-panel")).to_contain_text("too sparse")
        await page.get_by_test_id(f"bench-run-select-{runs[-1]['id']}").uncheck()
    if retakes:
        print(f"frequency response retaken {len(retakes)}x: {retakes}")
    assert first["measured"] is not None, first["measured_problem"]
    readouts = page.get_by_test_id("frf-readouts")
    await expect(readouts.locator("tr[data-source='measured']")).to_have_count(1, timeout=30_000)
    await expect(readouts.locator("tr[data-source='model']")).to_have_count(1)
    # The Bode plot is drawn (uPlot canvases) and the Nyquist plot has one run.
    await expect(page.get_by_test_id("bode-magnitude").locator("canvas")).to_have_count(1)
    await expect(page.get_by_test_id("bode-phase").locator("canvas")).to_have_count(1)
    await expect(page.get_by_test_id("nyquist")).to_have_attribute("data-curves", "1")
    # 1-40 Hz asked at 19200 baud: the tones above what the wire resolves are listed
    left_out = first["measured"]["not_measured_hz"]
    assert left_out and left_out[0] == 21.0 and left_out[-1] == 40.0
    await expect(page.get_by_test_id("frf-note")).to_contain_text("not measured: above what")
    model_pm = readouts.locator("tr[data-source='model'] [data-testid='frf-pm']")
    await expect(model_pm).to_contain_text("°")
    runs = (await server.client.get("/api/axes/line-0/bench/runs")).json()
    run_id = first["run_id"]
    frf = (await server.client.get(f"/api/bench/runs/{run_id}/frf")).json()
    server_pm = frf["model"]["margins"]["phase_margin_deg"]
    assert f"{server_pm:.1f}" in await model_pm.inner_text()
    # A measured margin is a number or "not measurable" with the API's reason.
    measured = frf["measured"]["margins"]
    gm_cell = readouts.locator("tr[data-source='measured'] [data-testid='frf-gm']")
    if measured["gain_margin_db"] is None:
        await expect(gm_cell).to_have_text("not measurable")
        assert await gm_cell.get_attribute("title") == measured["gain_margin_problem"]
        reasons = page.get_by_test_id("frf-margin-reason")
        await expect(reasons.first).to_contain_text("not measurable from this run")
    else:
        await expect(gm_cell).to_contain_text(f"{measured['gain_margin_db']:.1f}")
    await page.get_by_test_id("frf-loop").select_option("open")
    await expect(page.get_by_test_id("bode-magnitude").locator("canvas")).to_have_count(1)
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    await panel.scroll_into_view_if_needed()
    await panel.screenshot(path=str(ARTIFACTS / "bode-open-loop-laptop.png"))
    await page.set_viewport_size({"width": 390, "height": 844})
    await page.wait_for_timeout(300)  # the plots rebuild on resize (ResizeObserver)
    await panel.screenshot(path=str(ARTIFACTS / "bode-open-loop-phone.png"))
    await page.set_viewport_size({"width": 1400, "height": 1200})
    await page.get_by_test_id("frf-loop").select_option("closed")

    # What-if: the browser's margins agree with python-control's for the same gains.
    whatif = page.get_by_test_id("whatif-panel")
    await expect(page.get_by_test_id("whatif-pm")).to_contain_text("°")
    text = await page.get_by_test_id("whatif-pm").inner_text()
    browser_pm = float(text.split("margin")[1].split("°")[0])
    assert browser_pm == pytest.approx(server_pm, abs=0.5)

    # Update time: 30 slider moves, each redraws prediction, margins and plot.
    times: list[float] = []
    for kp in range(41, 71):
        await slide(page, "whatif-kp", kp)
        times.append(float(await whatif.get_attribute("data-update-ms") or "nan"))
    compute = float(await whatif.get_attribute("data-compute-ms") or "nan")
    await slide(page, "whatif-kp", 40)

    # The proposal is previewable from the gains in use: a number field takes any gain
    # the device does (the slider follows), and "proposal" loads the auto-tune's gains;
    # margins are read against the target, with a warning below it.
    kp_field = page.get_by_test_id("whatif-kp-value")
    await kp_field.fill("1676")
    await expect(page.get_by_test_id("whatif-kp")).to_have_value("1676")
    assert int(await page.get_by_test_id("whatif-kp").get_attribute("max") or 0) >= 1676
    await page.get_by_test_id("whatif-proposal").click()
    for name, value in proposal.items():
        await expect(page.get_by_test_id(f"whatif-{name}-value")).to_have_value(str(value))
    await expect(whatif).to_have_attribute("data-stable", "1")
    await expect(page.get_by_test_id("whatif-warning")).to_be_hidden()
    await kp_field.fill("4000")  # past the margins: the warning says what and against what
    await expect(page.get_by_test_id("whatif-warning")).to_contain_text("target medium")
    await page.get_by_test_id("whatif-in-use").click()
    await expect(kp_field).to_have_value("40")

    # Apply (the gains in use) and verify: a position step of 2000 counts; the status
    # says the verification runs, then that it is done (not "running" after it ended).
    await page.get_by_test_id("whatif-distance").fill("2000")
    await page.get_by_test_id("whatif-apply").click()
    await expect(page.get_by_test_id("whatif-status")).to_contain_text("verification")
    await expect(whatif).not_to_have_attribute("data-rms-vs-measured", "", timeout=30_000)
    rms = float(await whatif.get_attribute("data-rms-vs-measured") or "nan")
    await expect(page.get_by_test_id("whatif-status")).not_to_contain_text(
        "running", timeout=30_000
    )
    # The step predicted is the compared run's: a 900-count step run selected alone.
    other = (
        await server.client.post(
            "/api/axes/line-0/bench/runs", json={"kind": "position_step", "distance": 900}
        )
    ).json()["id"]
    await expect(page.get_by_test_id("whatif-distance")).to_have_value("900", timeout=30_000)
    assert other
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    await panel.scroll_into_view_if_needed()
    await page.screenshot(path=str(ARTIFACTS / "bench-frequency-response.png"), full_page=True)
    await whatif.screenshot(path=str(ARTIFACTS / "bench-whatif.png"))
    assert rms <= RMS_TOLERANCE * 2000, rms
    (ARTIFACTS / "frf-whatif-timing.json").write_text(
        json.dumps(
            {
                "frf_1_to_40_hz_run_s": frf_run_s,
                "frf_duration_s": 5.0,
                "whatif_update_ms_median": statistics.median(times),
                "whatif_update_ms_max": max(times),
                "whatif_compute_ms_last": compute,
                "rms_vs_measured_counts": rms,
                "server_pm_deg": server_pm,
                "browser_pm_deg": browser_pm,
            }
        )
    )
