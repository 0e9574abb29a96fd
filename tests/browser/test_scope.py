"""In headless Chromium: every screen, an honest scope, coupled Z1100 gains.

Phone STOP, laptop command strips, contrast in both themes, markers on sparse data,
a trigger on ``move``, Δ cursors on a known data set, the KABH+KABD write group.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest
from playwright.async_api import Browser, Page, expect

from servotune.api.app import WEB_DIST
from tests.support.browser import open_page
from tests.support.paths import SUPPORT
from tests.support.servers import LiveServer, live_server

pytestmark = pytest.mark.browser

CONTRAST_JS = (SUPPORT / "contrast.js").read_text()

# Every command button of the axis page inside the viewport, and no horizontal scroll.
OFFSCREEN_JS = """() => {
  const vw = document.documentElement.clientWidth;
  const bad = [];
  for (const b of document.querySelectorAll('.controls button, .stop-all')) {
    const r = b.getBoundingClientRect();
    if (!r.width) continue;
    if (r.left < 0 || r.right > vw + 0.5) bad.push(b.textContent.trim());
  }
  return { bad, count: document.querySelectorAll('.controls button').length,
           scroll: document.documentElement.scrollWidth - vw };
}"""


async def in_viewport(page: Page, testid: str) -> bool:
    box = await page.get_by_test_id(testid).bounding_box()
    size = page.viewport_size
    assert box is not None and size is not None
    return (
        box["x"] >= 0
        and box["y"] >= 0
        and box["x"] + box["width"] <= size["width"]
        and box["y"] + box["height"] <= size["height"]
    )


async def test_phone_stop_is_on_screen_and_stops(browser: Browser, slap2: LiveServer) -> None:
    page, errors = await open_page(browser, slap2, 390, 844)
    await page.goto(f"{slap2.base_url}/#/axis/line-1")
    await expect(page.get_by_test_id("axis-name")).to_be_visible()
    assert await page.evaluate("document.documentElement.scrollWidth") <= 390
    await page.get_by_test_id("cmd-velocity_mode").click()
    for _ in range(100):
        if slap2.bus.module(1).rss & 0b0100:
            break
        await asyncio.sleep(0.02)
    assert slap2.bus.module(1).rss & 0b0100, "velocity mode did not start"
    # Scrolled to the bottom of the page, the STOP is still on screen (sticky bar).
    await page.evaluate("window.scrollTo(0, document.body.scrollHeight)")
    assert await in_viewport(page, "stop-all")
    await page.get_by_test_id("stop-all").click()
    for _ in range(100):  # STOP from vm holds in pm
        if slap2.bus.module(1).rss & 0b1100 == 0b1000:
            break
        await asyncio.sleep(0.02)
    assert slap2.bus.module(1).rss & 0b1100 == 0b1000, "STOP did not stop and hold the axis"
    # The axis list is a drawer on a phone.
    assert not await in_viewport(page, "axis-link-line-0")
    await page.get_by_test_id("nav-toggle").click()
    await expect(page.get_by_test_id("axis-link-line-0")).to_be_in_viewport()
    await page.get_by_test_id("axis-link-line-0").click()
    await page.wait_for_function("window.__servotune.currentAxis() === 'line-0'")
    # One plot at a time, chosen with the tabs.
    await expect(page.get_by_test_id("plot-position")).to_be_visible()
    await expect(page.get_by_test_id("plot-velocity")).to_be_hidden()
    await page.get_by_test_id("plot-tab-velocity").click()
    await expect(page.get_by_test_id("plot-velocity")).to_be_visible()
    await expect(page.get_by_test_id("plot-position")).to_be_hidden()
    assert not errors


async def laptop_check(browser: Browser, server: LiveServer, axis: str) -> None:
    page, errors = await open_page(browser, server, 1280, 800)
    await page.goto(f"{server.base_url}/#/axis/{axis}")
    await expect(page.get_by_test_id("plot-position")).to_be_visible()
    result = await page.evaluate(OFFSCREEN_JS)
    assert result["count"] > 3, result
    assert result["bad"] == [], result
    assert result["scroll"] <= 0, result
    assert not errors
    await page.context.close()


async def test_laptop_shows_every_command_of_every_device(
    tmp_path: Path, browser: Browser, slap2: LiveServer
) -> None:
    from servotune.config import LinkSpec
    from tests.support.sim_lines import z1100_chip_process

    await laptop_check(browser, slap2, "line-0")
    spec = LinkSpec("ep7047", "sim", "ep", 0, [1])
    async with live_server(None, None, tmp_path / "ep", web_dir=WEB_DIST, spec=spec) as server:
        await laptop_check(browser, server, "ep-1")
    with z1100_chip_process(tmp_path) as (sim, chip):
        spec = LinkSpec("z1100", sim.path, "chip", 38400, [0, 1, 2])
        async with live_server(sim, chip, tmp_path / "z", web_dir=WEB_DIST, spec=spec) as server:
            await laptop_check(browser, server, "chip-x")


@pytest.mark.parametrize("scheme", ["dark", "light"])
async def test_text_contrast_meets_wcag_aa(
    browser: Browser, slap2: LiveServer, scheme: str
) -> None:
    page, errors = await open_page(browser, slap2, 1280, 800, scheme)
    await expect(page.get_by_test_id("plot-position")).to_be_visible()
    # The OS preference is the default theme.
    assert await page.evaluate("document.documentElement.dataset.theme") == scheme
    await page.get_by_test_id("events-toggle").click()
    await page.get_by_test_id("cursors-toggle").click()
    await page.get_by_test_id("trigger-toggle").click()
    result = await page.evaluate(CONTRAST_JS)
    assert result["checked"] > 100
    assert result["fails"] == [], result["fails"][:10]
    await page.goto(f"{slap2.base_url}/#/overview")
    await expect(page.get_by_test_id("tile-line-0")).to_be_visible()
    result = await page.evaluate(CONTRAST_JS)
    assert result["fails"] == [], result["fails"][:10]
    assert not errors


async def test_markers_only_on_sparse_data(browser: Browser, slap2: LiveServer) -> None:
    page, errors = await open_page(browser, slap2, 1280, 800)
    # 40 samples over 10 s: ~25 px apart on a 1000 px plot: markers.
    await page.evaluate("window.__lab = window.__servotune.lab({samples: 40, periodS: 0.25})")
    status = page.get_by_test_id("scope-lab").get_by_test_id("scope-status")
    await expect(status).to_contain_text("40 samples")
    await expect(status).to_contain_text("markers")
    await page.evaluate("window.__lab.destroy()")
    # 20000 samples over 10 s: decimated, no markers.
    await page.evaluate("window.__lab = window.__servotune.lab({samples: 20000, periodS: 0.0005})")
    status = page.get_by_test_id("scope-lab").get_by_test_id("scope-status")
    await expect(status).to_contain_text("samples")
    assert "markers" not in (await status.text_content() or "")
    assert not errors


async def test_delta_cursors_read_known_times(browser: Browser, slap2: LiveServer) -> None:
    page, errors = await open_page(browser, slap2, 1280, 800)
    # Samples every 0.1 s; ch0 = round(1000 sin(pi t)).
    await page.evaluate("window.__lab = window.__servotune.lab({samples: 100, periodS: 0.1})")
    lab = page.get_by_test_id("scope-lab")
    await lab.get_by_test_id("cursors-toggle").click()
    over = lab.get_by_test_id("plot-ch0").locator(".u-over")
    box = await over.bounding_box()
    assert box is not None
    # The x scale runs 0..10 s over the plot area: clicks at 25 % and 70 %.
    await over.click(position={"x": box["width"] * 0.25, "y": box["height"] / 2})
    await over.click(position={"x": box["width"] * 0.70, "y": box["height"] / 2})
    readout = lab.get_by_test_id("cursor-readout")
    await expect(readout.get_by_test_id("cursor-dt")).to_be_visible()
    a, b = await page.evaluate("[window.__lab.stack.cursors.a, window.__lab.stack.cursors.b]")
    # Snapped to samples (multiples of 0.1 s), where the clicks were.
    for t, want in ((a, 2.5), (b, 7.0)):
        assert abs(t * 10 - round(t * 10)) < 1e-6
        assert abs(t - want) <= 0.15
    dt = b - a
    assert await readout.get_by_test_id("cursor-dt").text_content() == f"Δt {dt:.4f} s"
    assert await readout.get_by_test_id("cursor-freq").text_content() == f"1/Δt {1 / dt:.3f} Hz"
    import math

    dy = round(1000 * math.sin(math.pi * b)) - round(1000 * math.sin(math.pi * a))
    assert await readout.get_by_test_id("cursor-dy-ch0").text_content() == f"Δch0 {dy} counts"
    assert not errors


async def test_trigger_on_move_captures_the_move(browser: Browser, slap2: LiveServer) -> None:
    page, errors = await open_page(browser, slap2, 1400, 900)
    await page.goto(f"{slap2.base_url}/#/axis/line-0")
    await expect(page.get_by_test_id("plot-position")).to_be_visible()
    await page.get_by_test_id("scope-window-5").click()
    await page.get_by_test_id("trigger-toggle").click()
    await page.get_by_test_id("trigger-mode").select_option("single")
    await page.get_by_test_id("trigger-source").select_option("flag:move:rising")
    await expect(page.get_by_test_id("trigger-state")).to_have_attribute("data-state", "armed")
    response = await slap2.client.post(
        "/api/axes/line-0/commands", json={"command": "position_mode"}
    )
    assert response.status_code == 200, response.text
    await asyncio.sleep(0.5)
    response = await slap2.client.post(
        "/api/axes/line-0/commands", json={"command": "move_relative", "distance": 4000}
    )
    assert response.status_code == 200, response.text
    await expect(page.get_by_test_id("trigger-state")).to_have_attribute(
        "data-state", "captured", timeout=15_000
    )
    # The frozen window holds the edge: move off before the trigger point, on at it.
    edge = await page.evaluate(
        """() => {
      const s = window.__servotune.scope();
      const b = s.buffer, t = s.trigger.capturedT;
      const i = b.indexAt(t);
      return { on: b.flags.get('move')[i], before: b.flags.get('move')[i - 1],
               shown: s.shown, t };
    }"""
    )
    assert edge["on"] == 1 and edge["before"] == 0, edge
    lo, hi = edge["shown"]
    assert lo < edge["t"] < hi
    assert abs((edge["t"] - lo) / (hi - lo) - 0.2) < 0.02  # 20 % pre-trigger
    # Single: the display stays frozen on that capture.
    await asyncio.sleep(0.5)
    assert await page.evaluate("window.__servotune.scope().shown[0]") == lo
    # The capture is kept until re-armed or cleared, whatever the live ring
    # drops (it keeps 60 s: after that the plot went blank, the CSV had only its
    # header, and the state still said "captured"). Empty the ring as those 60 s would.
    kept = await page.evaluate(
        """() => {
      const s = window.__servotune.scope();
      s.buffer.clear();
      s.redraw();
      const lines = s.tools.exportCsv().trim().split(String.fromCharCode(10));
      const csv = lines.filter((l) => !l.startsWith('#'));
      const b = s.view, i = b.indexAt(s.trigger.capturedT);
      return { rows: csv.length - 1, live: s.buffer.length, on: b.flags.get('move')[i],
               status: document.querySelector('[data-testid=trigger-state]').dataset.state };
    }"""
    )
    assert kept["live"] == 0 and kept["status"] == "captured", kept
    assert kept["rows"] > 20 and kept["on"] == 1, kept
    # Re-armed: the live trace again, the capture gone.
    await page.get_by_test_id("trigger-source").select_option("flag:move:falling")
    await expect(page.get_by_test_id("trigger-state")).to_have_attribute("data-state", "armed")
    assert await page.evaluate(
        "window.__servotune.scope().view === window.__servotune.scope().buffer"
    )
    assert not errors


async def test_z1100_gains_written_as_one_group(tmp_path: Path, browser: Browser) -> None:
    from servotune.config import LinkSpec
    from tests.support.sim_lines import z1100_chip_process

    with z1100_chip_process(tmp_path) as (sim, chip):
        spec = LinkSpec("z1100", sim.path, "chip", 38400, [0, 1, 2])
        async with live_server(sim, chip, tmp_path / "data", web_dir=WEB_DIST, spec=spec) as server:
            page, errors = await open_page(browser, server, 1400, 900)
            await page.goto(f"{server.base_url}/#/axis/chip-y")
            await expect(page.get_by_test_id("write-group-bar-0")).to_be_visible()
            await expect(page.get_by_test_id("param-kabd_k-device")).not_to_have_text("—")
            kabd_a = chip.parameters(1).kabd.a
            # Edits are staged: nothing is written yet.
            await page.get_by_test_id("param-kabh_k-input").fill("100")
            await page.get_by_test_id("param-kabh_k-input").press("Enter")
            await page.get_by_test_id("param-kabd_k-input").fill("7")
            await page.get_by_test_id("param-kabd_k-input").press("Enter")
            await expect(page.get_by_test_id("write-group-0-pending")).to_contain_text("2 edited")
            assert chip.parameters(1).kabh.k != 100
            await page.get_by_test_id("write-group-0").click()
            await expect(page.get_by_test_id("write-group-0-status")).to_contain_text(
                "✓", timeout=8000
            )
            # KABH first, then KABD: the chip keeps the user's standstill gains.
            assert chip.parameters(1).kabh.k == 100
            assert chip.parameters(1).kabd.k == 7
            assert chip.parameters(1).kabd.a == kabd_a
            await expect(page.get_by_test_id("param-kabd_k-device")).to_have_text("7")
            # No stacked "write KABD again" offers; at most one restore.
            assert await page.locator(".overwrite-offer").count() == 0
            assert await page.get_by_test_id("write-group-restore").count() <= 1
            assert not errors


async def test_overview_tiles_show_the_control_holder(browser: Browser, slap2: LiveServer) -> None:
    page, errors = await open_page(browser, slap2, 1280, 800)
    await page.goto(f"{slap2.base_url}/#/overview")
    holder = page.get_by_test_id("tile-control-line-0")
    await expect(holder).to_have_text("control: free")
    await page.goto(f"{slap2.base_url}/#/axis/line-0")
    await page.get_by_test_id("control-take").click()
    await expect(page.get_by_test_id("control-badge")).to_have_text("yours")
    await page.goto(f"{slap2.base_url}/#/overview")
    await expect(holder).to_have_text("control: this tab")
    await expect(page.get_by_test_id("tile-control-line-1")).to_have_text("control: free")
    # Another tab sees who holds it.
    other, other_errors = await open_page(browser, slap2, 1280, 800)
    await other.goto(f"{slap2.base_url}/#/overview")
    await expect(other.get_by_test_id("tile-control-line-0")).to_contain_text("(another tab)")
    assert not errors and not other_errors
