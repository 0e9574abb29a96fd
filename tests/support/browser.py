"""Headless Chromium for the browser tests (fixtures registered by tests/conftest.py)."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from playwright.async_api import Browser, Page, async_playwright

from servotune.api.app import WEB_DIST
from servotune.config import LinkSpec
from servotune.devices.slap2.sim.line import Slap2Line
from servotune.devices.slap2.sim.module import Slap2Module
from servotune.sim.pty import PtySimulator
from tests.support.servers import LiveServer, live_server
from tests.support.sim_lines import running_simulator

CHROMIUM = "/usr/bin/chromium"


CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]


@pytest.fixture
async def browser() -> AsyncIterator[Browser]:
    assert Path(CHROMIUM).exists(), "install Debian's chromium (scripts/test.sh does)"
    assert (WEB_DIST / "index.html").exists(), "build the web bundle (scripts/test.sh does)"
    async with async_playwright() as playwright:
        browser = await playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            yield browser
        finally:
            await browser.close()


@pytest.fixture
async def dashboard(tmp_path: Path, browser: Browser) -> AsyncIterator[tuple[Page, LiveServer]]:
    with running_simulator([0, 1], tmp_path, link_path=str(tmp_path / "tty")) as (sim, bus):
        async with live_server(sim, bus, tmp_path / "data", web_dir=WEB_DIST) as server:
            page = await browser.new_page(viewport={"width": 1400, "height": 900})
            errors: list[str] = []
            page.on("pageerror", lambda exc: errors.append(str(exc)))
            await page.goto(server.base_url)
            yield page, server
            assert not errors, f"JavaScript errors: {errors}"
            await page.close()


@pytest.fixture
async def slap2(tmp_path: Path) -> AsyncIterator[LiveServer]:
    with running_simulator([0, 1], tmp_path, link_path=str(tmp_path / "tty")) as (sim, bus):
        async with live_server(sim, bus, tmp_path / "data", web_dir=WEB_DIST) as server:
            yield server


async def open_page(
    browser: Browser, server: LiveServer, width: int, height: int, scheme: Any = "dark"
) -> tuple[Page, list[str]]:
    context = await browser.new_context(
        viewport={"width": width, "height": height}, color_scheme=scheme
    )
    page = await context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    await page.goto(server.base_url)
    return page, errors


@contextlib.asynccontextmanager
async def one_module_page(
    tmp_path: Path,
    browser: Browser,
    module: Slap2Module,
    viewport: dict[str, int],
) -> AsyncIterator[tuple[Page, LiveServer]]:
    """One SLAP2 module on a pty behind a live server (once it reports a position), and
    a page (no JavaScript errors at the end)."""
    bus = Slap2Line([module])
    simulator = PtySimulator(bus, baud=19200, link_path=str(tmp_path / "tty"))
    simulator.start()
    try:
        spec = LinkSpec("slap2", simulator.path, "line", simulator.baud, [0], 512)
        async with live_server(
            simulator, bus, tmp_path / "data", web_dir=WEB_DIST, spec=spec
        ) as server:
            for _ in range(200):  # the module polled once: it has a position
                if (await server.state("line-0")).get("position") is not None:
                    break
                await asyncio.sleep(0.05)
            page = await browser.new_page(viewport=viewport)
            errors: list[str] = []
            page.on("pageerror", lambda exc: errors.append(str(exc)))
            yield page, server
            assert not errors, f"JavaScript errors: {errors}"
            await page.close()
    finally:
        simulator.stop()
