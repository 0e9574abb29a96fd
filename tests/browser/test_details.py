"""Details a user meets on a SLAP2 line, in headless Chromium: the console's
answer to a command without a reply and to one the device refused (7), a gain slider
moved by arrow keys writes once when the keys rest, not once per step (6), and a
tile of the rig overview opens its axis (5), and an edit made while the tuning panel
reads the device is kept.
"""

from __future__ import annotations

import asyncio

import pytest
from playwright.async_api import Browser, Page, Request, Route, WebSocketRoute, expect

from tests.support.paths import ARTIFACTS
from tests.support.servers import LiveServer
from tests.support.waiting import wait_for

pytestmark = pytest.mark.browser


async def test_console_says_no_reply_and_shows_the_refusal(
    dashboard: tuple[Page, LiveServer],
) -> None:
    page, _ = dashboard
    await page.get_by_test_id("axis-link-line-0").click()
    console = page.get_by_test_id("console-input")
    output = page.get_by_test_id("console-output")
    await console.fill("sv 2000")  # a set command: the SLAP2 answers a bare CR
    await console.press("Enter")
    await expect(output.get_by_test_id("console-no-reply")).to_have_count(1, timeout=5000)
    await expect(output.get_by_test_id("console-refusal")).to_have_count(0)
    await console.fill("cal 9")  # calibration modes are 0..5: the module sets uc
    await console.press("Enter")
    last = output.locator(".con-entry").last
    await expect(last).to_contain_text("refused", timeout=5000)
    await expect(last).to_contain_text("uc")
    await expect(last).to_have_class("con-entry error")
    await console.fill("zz")  # no such command: the console does not send it at all
    await console.press("Enter")
    last = output.locator(".con-entry").last
    await expect(last).to_contain_text("not sent", timeout=5000)
    await expect(last).to_have_class("con-entry error")


async def test_arrow_keys_on_a_gain_slider_write_once_when_they_rest(
    dashboard: tuple[Page, LiveServer],
) -> None:
    page, server = dashboard
    await page.get_by_test_id("axis-link-line-0").click()
    slider = page.get_by_test_id("param-kp-slider")
    await expect(slider).to_be_visible(timeout=10_000)
    await expect(page.get_by_test_id("param-kp-device")).to_have_text("40", timeout=10_000)
    writes: list[str] = []

    def on_request(request: Request) -> None:
        if request.method == "PATCH" and request.url.endswith("/api/axes/line-0/params"):
            writes.append(request.post_data or "")

    page.on("request", on_request)
    await slider.focus()
    for _ in range(5):
        await page.keyboard.press("ArrowRight")
    assert writes == [], "a key step wrote to the motor"
    await expect(page.get_by_test_id("param-kp-device")).to_have_text("45", timeout=5000)
    await asyncio.sleep(1.0)  # longer than the rest that writes: nothing more comes
    assert len(writes) == 1 and '"kp":45' in writes[0].replace(" ", ""), writes
    assert server.bus.module(0).settings["kp"] == 45


async def test_an_overview_tile_opens_its_axis(
    dashboard: tuple[Page, LiveServer],
) -> None:
    page, _ = dashboard
    await page.get_by_test_id("nav-overview").click()
    tile = page.get_by_test_id("tile-line-1")
    await expect(tile).to_be_visible(timeout=10_000)
    await expect(page.get_by_test_id("tile-position-line-1")).not_to_have_text("—")
    # What STOP does is on each tile, at any width (the top bar shows it only when wide).
    await page.set_viewport_size({"width": 390, "height": 844})
    stop = page.get_by_test_id("tile-stop-line-1")
    await expect(stop).to_contain_text("STOP: SLAP2: brakes at full power in pm and holds")
    await expect(stop).to_be_in_viewport()
    await page.wait_for_timeout(600)  # the rail slides into its drawer
    await page.screenshot(path=str(ARTIFACTS / "overview-phone.png"))
    await page.set_viewport_size({"width": 1400, "height": 900})
    await tile.click()
    await expect(page).to_have_url(f"{page.url.split('#')[0]}#/axis/line-1")
    await expect(page.get_by_test_id("axis-health")).to_be_visible()
    await expect(page.get_by_test_id("console-input")).to_be_visible()


async def test_the_live_plot_of_a_captured_axis_gets_every_captured_sample(
    dashboard: tuple[Page, LiveServer],
) -> None:
    """The live plots of a captured axis show the dense data. A bench step
    captures the axis (the line devoted to it); the page open on that axis receives at
    least every sample the run recorded: the fan-out thins nothing. (A count, not a
    rate: what the host manages to poll does not matter.)"""
    from tests.support.bench import finished_run, start

    page, server = dashboard
    await page.get_by_test_id("axis-link-line-0").click()
    await expect(page.get_by_test_id("plot-position")).to_be_visible(timeout=10_000)
    before = await page.evaluate("window.__servotune.samplesReceived('line-0')")
    run = await finished_run(
        server, "line-0", await start(server, "line-0", kind="position_step", distance=2000)
    )
    assert run["status"] == "complete", run["message"]
    await asyncio.sleep(0.5)  # the last samples' websocket batch
    received = await page.evaluate("window.__servotune.samplesReceived('line-0')") - before
    recorded = len(run["samples"])
    assert recorded > 20, recorded
    assert received >= recorded, f"the page got {received} samples of the run's {recorded}"


async def test_an_edit_made_while_the_panel_reads_the_device_is_kept(
    slap2: LiveServer, browser: Browser
) -> None:
    """The tuning panel reads the device when it opens; the websocket may bring the
    device's values first, and the user may edit a field before the read answers. That
    read must fill in the device values, not throw the user's edit away.

    Both orders are forced: the websocket's ``params`` messages and the panel's
    ``GET …/params`` are held by Playwright routes and let go one after the other."""
    held_messages: list[str] = []
    hold_params = True
    pages: list[WebSocketRoute] = []

    async def socket(ws: WebSocketRoute) -> None:
        server = ws.connect_to_server()
        pages.append(ws)

        def to_page(message: str | bytes) -> None:
            if (
                hold_params
                and isinstance(message, str)
                and '"type":"params"' in message.replace(" ", "")
            ):
                held_messages.append(message)
            else:
                ws.send(message)

        server.on_message(to_page)

    held_reads: list[Route] = []

    async def params(route: Route) -> None:
        if route.request.method == "GET":
            held_reads.append(route)
        else:
            await route.continue_()

    page = await browser.new_page(viewport={"width": 1400, "height": 900})
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    await page.route_web_socket("**/ws", socket)
    await page.route("**/api/axes/line-0/params", params)
    await page.goto(f"{slap2.base_url}/#/axis/line-0")
    device = page.get_by_test_id("param-kp-device")
    await expect(device).to_have_text("—", timeout=10_000)
    await wait_for(lambda: bool(held_reads and held_messages), timeout_s=10)
    hold_params = False
    for message in held_messages:
        pages[0].send(message)
    await expect(device).to_have_text("40", timeout=5000)
    field = page.get_by_test_id("param-kp-input")
    await field.fill("55")  # staged in the field, not written (no Enter)
    row = page.locator("[data-param='kp']")
    await expect(row).to_have_attribute("data-differs", "1")
    await held_reads[0].continue_()
    await expect(page.get_by_test_id("tuning-status")).to_contain_text("✓ Read", timeout=5000)
    await expect(row).to_have_attribute("data-differs", "1")
    await page.get_by_test_id("tuning-status").click()  # the field loses focus
    await expect(field).to_have_value("55")
    assert slap2.bus.module(0).settings["kp"] == 40
    assert not errors, errors
    await page.close()
