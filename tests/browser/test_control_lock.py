"""Two browser tabs hand an axis over in headless Chromium (the control lock's UI)."""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from playwright.async_api import Browser, Page, expect

from servotune.api.app import WEB_DIST
from servotune.hub.control_client import ControlSettings
from tests.support.control import Server, control_server
from tests.support.paths import ARTIFACTS

pytestmark = pytest.mark.browser

VM = 1 << 2
PM = 1 << 3


@pytest.fixture
async def two_tabs(
    tmp_path: Path,
    browser: Browser,
) -> AsyncIterator[tuple[Page, Page, Server]]:
    # This test checks the hand-over in the UI, not the dead-man's timing (test_control
    # does, with a client whose timing the test controls): a browser starved of CPU on a
    # loaded machine was seen to send heartbeats seconds apart, so the lease is long here.
    # Closing a tab is a closed socket: that lapses at once, whatever the lease.
    settings = ControlSettings(request_timeout_s=20.0, lease_s=10.0)
    async with control_server(tmp_path, settings, web_dir=WEB_DIST) as server:
        pages = []
        errors: list[str] = []
        for _ in range(2):
            context = await browser.new_context(viewport={"width": 1400, "height": 900})
            page = await context.new_page()
            page.on("pageerror", lambda exc: errors.append(str(exc)))
            await page.goto(f"{server.base_url}/#/axis/line-0")
            pages.append(page)
        yield pages[0], pages[1], server
        assert not errors, f"JavaScript errors: {errors}"
        for page in pages:
            await page.context.close()


async def test_two_tabs_hand_an_axis_over(two_tabs: tuple[Page, Page, Server]) -> None:
    alice, bob, server = two_tabs
    await expect(alice.get_by_test_id("control-badge")).to_have_text("free", timeout=10000)
    await alice.get_by_test_id("control-take").click()
    await expect(alice.get_by_test_id("control-badge")).to_have_text("yours")
    await expect(bob.get_by_test_id("control-badge")).to_contain_text("held by local")
    await expect(bob.locator(".axis-view.control-locked")).to_have_count(1)
    await expect(bob.get_by_test_id("control-take")).to_be_hidden()

    # Alice runs velocity mode; Bob's click is refused by the server (read-only here).
    await alice.get_by_test_id("cmd-velocity_mode").click()
    deadline = time.monotonic() + 5
    while not server.bus.module(0).rss & VM:
        assert time.monotonic() < deadline, "velocity mode did not start"
        await asyncio.sleep(0.02)
    # (with the CSRF token, as the page's own client sends it: the lock must refuse it)
    refused = await bob.evaluate(
        """async () => {
            const session = await (await fetch('/api/auth/session')).json();
            return (await fetch('/api/axes/line-0/params', {method: 'PATCH',
                headers: {'Content-Type': 'application/json',
                          'X-CSRF-Token': session.csrf_token},
                body: '{"kp": 70}'})).status;
        }"""
    )
    assert refused == 423
    assert server.bus.module(0).settings["kp"] == 40

    # Bob asks; Alice allows; the axis stops before it changes hands.
    await bob.get_by_test_id("control-request").click()
    await expect(bob.get_by_test_id("control-pending")).to_contain_text("asked for control")
    await expect(alice.get_by_test_id("control-prompt-line-0")).to_be_visible()
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    await alice.screenshot(path=str(ARTIFACTS / "control-prompt.png"))
    await alice.get_by_test_id("control-allow").click()
    await expect(bob.get_by_test_id("control-badge")).to_have_text("yours")
    await expect(alice.get_by_test_id("control-badge")).to_contain_text("held by local")
    assert not server.bus.module(0).rss & VM, "handed over while moving"
    await expect(alice.locator(".axis-view.control-locked")).to_have_count(1)
    await bob.screenshot(path=str(ARTIFACTS / "control-handed-over.png"))
    await alice.screenshot(path=str(ARTIFACTS / "control-read-only.png"))

    # Hold-to-run jog, both ways: pressed runs (pm + ma towards the end), released
    # decelerates and holds (ma to where the profile stops).
    module = server.bus.module(0)
    for side, sign in (("minus", -1), ("plus", 1)):
        start = module.position
        await bob.get_by_test_id(f"jog-{side}").hover()
        await bob.mouse.down()
        deadline = time.monotonic() + 5
        while (module.position - start) * sign < 500:
            assert time.monotonic() < deadline, f"jog {side} did not start"
            await asyncio.sleep(0.02)
        await bob.mouse.up()
        deadline = time.monotonic() + 5
        while module.moving or abs(module.motor.speed_rad_s) > 0.5:
            assert time.monotonic() < deadline, f"jog {side} release did not stop"
            await asyncio.sleep(0.02)
        assert module.rss & PM, "the jog release left the motor unpowered"

    # Bob's tab closes while the axis runs: the dead-man stops it.
    await bob.get_by_test_id("cmd-velocity_mode").click()
    deadline = time.monotonic() + 5
    while not server.bus.module(0).rss & VM:
        assert time.monotonic() < deadline, "velocity mode did not start"
        await asyncio.sleep(0.02)
    closed = time.monotonic()
    await bob.context.close()
    while server.bus.module(0).rss & VM:
        assert time.monotonic() - closed < 2, "closing the tab did not stop the axis"
        await asyncio.sleep(0.01)
    await expect(alice.get_by_test_id("control-badge")).to_have_text("free")
