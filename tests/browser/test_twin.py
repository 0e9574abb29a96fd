"""The 3D twin in headless Chromium: the demo's axis page with the 3D panel, the rig.

Software WebGL (SwiftShader) is slow to its first frame on a loaded machine: the
waits below are for the canvas and viser's labels (DOM elements drawn once the scene
arrived), with generous timeouts; nothing asserts a frame rate.
"""

from __future__ import annotations

import asyncio
import io
import time
from pathlib import Path

import pytest
from PIL import Image
from playwright.async_api import Browser, Page, expect

from servotune.api.app import WEB_DIST
from tests.support.paths import ARTIFACTS
from tests.support.servers import demo_server

pytestmark = [pytest.mark.browser, pytest.mark.slow]

FIRST_FRAME_TIMEOUT_MS = 180_000
MIN_COLOURS = 50


def distinct_colours(png: bytes) -> int:
    """Colours in the middle of the view, where the scene is (viser's notification and
    panel sit in the top corners and would count as drawn)."""
    image = Image.open(io.BytesIO(png)).convert("RGB")
    width, height = image.size
    middle = image.crop((width // 5, height * 3 // 10, width * 4 // 5, height * 17 // 20))
    colours = middle.reduce(4).getcolors(maxcolors=1 << 16)
    return len(colours) if colours is not None else 1 << 16


async def scene_drawn(page: Page, iframe: str) -> bytes:
    """Wait until viser's client in ``iframe`` is connected (through the proxy) and its
    canvas shows the scene; return that screenshot. viser draws its labels in WebGL
    too, so the only evidence of a drawn scene is in the pixels: discs, rails, a floor
    grid and text give many colours, a blank canvas a handful."""
    frame = page.frame_locator(iframe)
    await expect(frame.locator("canvas").first).to_be_visible(timeout=FIRST_FRAME_TIMEOUT_MS)
    await expect(frame.get_by_text("Connected", exact=True)).to_be_visible(
        timeout=FIRST_FRAME_TIMEOUT_MS
    )
    element = page.locator(iframe)
    deadline = time.monotonic() + FIRST_FRAME_TIMEOUT_MS / 1000
    while True:
        png = await element.screenshot(timeout=FIRST_FRAME_TIMEOUT_MS)
        if distinct_colours(png) > MIN_COLOURS:
            return png
        if time.monotonic() > deadline:
            pytest.fail(f"the 3D scene in {iframe} was not drawn within the timeout")
        await asyncio.sleep(1.0)


async def test_axis_page_3d_beside_the_plots_and_the_rig(
    tmp_path: Path,
    browser: Browser,
) -> None:
    async with demo_server(tmp_path, web_dir=WEB_DIST) as demo:
        page = await browser.new_page(viewport={"width": 1400, "height": 900})
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        await page.goto(f"{demo.base_url}/#/axis/demo-slap2-0")
        await page.get_by_test_id("twin-beside").click(timeout=60_000)
        await scene_drawn(page, "[data-testid=twin-panel] iframe")
        await expect(page.get_by_test_id("plot-position")).to_be_visible(timeout=60_000)

        # The choice is remembered: after a reload the panel is back beside the plots.
        await page.reload()
        # (Generous timeouts: the descriptor and the page load slowly on a loaded machine.)
        await expect(page.get_by_test_id("twin-beside")).to_have_class("seg-btn on", timeout=60_000)
        await expect(page.locator("[data-testid=twin-panel] iframe")).to_have_count(1)

        await page.goto(f"{demo.base_url}/#/rig")
        png = await scene_drawn(page, "[data-testid=twin-rig] iframe")
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        (ARTIFACTS / "twin-rig.png").write_bytes(png)
        assert not errors, f"JavaScript errors: {errors}"
        await page.close()
