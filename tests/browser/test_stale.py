"""Without the server, the page claims no state (stale data after a
disconnect is dimmed and the status says so; a state is never shown that
nobody knows).

The websocket is cut between the page and a live server (Playwright's websocket route:
the page's socket is closed and every reconnection refused), so the server and its
devices run on while the page cannot hear them, as when a laptop loses the network.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from playwright.async_api import Browser, WebSocketRoute, expect

from servotune.api.app import WEB_DIST
from tests.support.paths import ARTIFACTS
from tests.support.servers import live_server
from tests.support.sim_lines import running_simulator

pytestmark = pytest.mark.browser


async def test_a_cut_connection_shows_no_axis_as_ok(
    tmp_path: Path,
    browser: Browser,
) -> None:
    routes: list[WebSocketRoute] = []
    cut = False

    async def handler(ws: WebSocketRoute) -> None:
        if cut:
            await ws.close(code=1011, reason="cut by the test")
            return
        ws.connect_to_server()
        routes.append(ws)

    with running_simulator([0, 1], tmp_path, link_path=str(tmp_path / "tty")) as (sim, bus):
        async with live_server(sim, bus, tmp_path / "data", web_dir=WEB_DIST) as server:
            page = await browser.new_page(viewport={"width": 1280, "height": 800})
            await page.route_web_socket("**/ws", handler)
            await page.goto(server.base_url)
            await page.get_by_test_id("axis-link-line-0").click()
            badge = page.get_by_test_id("axis-health")
            await expect(badge).to_have_attribute("data-health", "ok", timeout=10_000)
            styles = "el => [getComputedStyle(el).color, getComputedStyle(el).textDecorationLine]"
            live: Any = await badge.evaluate(styles)
            lamp = page.locator("[data-testid='axis-link-line-0'] .axis-lamp")
            live_lamp = await lamp.evaluate("el => getComputedStyle(el).backgroundColor")
            assert live[1] == "none"

            cut = True
            for route in routes:
                await route.close(code=1011, reason="cut by the test")
            await expect(page.locator("body")).not_to_have_attribute("data-ws", "open")
            await expect(page.get_by_text("Live values below are stale").first).to_be_visible()
            stale: Any = await badge.evaluate(styles)
            assert stale[0] != live[0], "the health badge kept its live colour"
            assert stale[1] == "line-through", stale
            stale_lamp = await lamp.evaluate("el => getComputedStyle(el).backgroundColor")
            assert stale_lamp != live_lamp, "the rail's axis lamp kept its live colour"
            ARTIFACTS.mkdir(parents=True, exist_ok=True)
            await page.screenshot(path=str(ARTIFACTS / "disconnected-laptop.png"))
            await page.set_viewport_size({"width": 390, "height": 844})
            await page.wait_for_timeout(500)  # the rail slides away into its drawer
            stop = page.get_by_test_id("stop-all")
            box = await stop.bounding_box()
            assert box is not None and box["x"] + box["width"] <= 390, box
            await page.screenshot(path=str(ARTIFACTS / "disconnected-phone.png"))
            await page.close()
