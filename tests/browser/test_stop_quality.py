"""In headless Chromium: STOP says what it does and bad bench runs are
not shown as good (item 5).

* On the axis page of each device family (SLAP2, Z1100, EP7047) the stop effect the
  descriptor names (``descriptor.stop.summary``) is shown next to the axis's STOP and at
  the top bar's STOP.
* Esc while one of the app's dialogs is open closes that dialog and sends no STOP (no
  ``STOP`` event from the hub, the simulated module keeps running); Esc without a dialog
  stops every axis.
* A bench run the server judges bad (a PWM too small to overcome the simulated motor's
  friction: ``did_not_move``) has no ✓, shows the server's reasons, and none of its
  metric cells is coloured better or worse than the baseline.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import pytest
import websockets
from playwright.async_api import Browser, Page, expect

from servotune.api.app import WEB_DIST
from servotune.config import LinkSpec
from tests.support.bench import finished_run, start
from tests.support.paths import ARTIFACTS
from tests.support.servers import LiveServer, live_server
from tests.support.sim_lines import running_simulator

pytestmark = pytest.mark.browser

VM = 0b0100  # the SLAP2's rss bit of velocity mode
PM = 0b1000  # the SLAP2's rss bit of position mode


# --- item 10: the stop effect at the button -------------------------------------------


@contextlib.asynccontextmanager
async def _slap2_server(tmp_path: Path) -> AsyncIterator[tuple[LiveServer, str]]:
    with running_simulator([0], tmp_path, link_path=str(tmp_path / "tty")) as (sim, bus):
        spec = LinkSpec("slap2", sim.path, "line", sim.baud, [0], 512)
        async with live_server(sim, bus, tmp_path / "data", web_dir=WEB_DIST, spec=spec) as s:
            yield s, "line-0"


@contextlib.asynccontextmanager
async def _z1100_server(tmp_path: Path) -> AsyncIterator[tuple[LiveServer, str]]:
    from tests.support.sim_lines import z1100_chip_process

    with z1100_chip_process(tmp_path) as (sim, chip):
        spec = LinkSpec("z1100", sim.path, "chip", 38400, [0, 1, 2])
        async with live_server(sim, chip, tmp_path / "data", web_dir=WEB_DIST, spec=spec) as s:
            yield s, "chip-y"


@contextlib.asynccontextmanager
async def _ep7047_server(tmp_path: Path) -> AsyncIterator[tuple[LiveServer, str]]:
    spec = LinkSpec("ep7047", "sim", "ep", 0, [1])
    async with live_server(None, None, tmp_path / "data", web_dir=WEB_DIST, spec=spec) as s:
        yield s, "ep-1"


SERVERS: dict[str, Callable[[Path], contextlib.AbstractAsyncContextManager[Any]]] = {
    "slap2": _slap2_server,
    "z1100": _z1100_server,
    "ep7047": _ep7047_server,
}


@pytest.mark.parametrize("device", list(SERVERS))
async def test_each_axis_page_shows_what_its_stop_does_next_to_stop(
    tmp_path: Path,
    browser: Browser,
    device: str,
) -> None:
    async with SERVERS[device](tmp_path) as (server, axis_id):
        descriptor = (await server.client.get(f"/api/axes/{axis_id}/descriptor")).json()
        assert descriptor["device"] == device
        summary: str = descriptor["stop"]["summary"]
        labels = {c["name"]: c["label"] for c in descriptor["commands"]}
        gentler_labels = [labels[name] for name in descriptor["stop"]["gentler"]]
        page = await browser.new_page(viewport={"width": 1400, "height": 900})
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        await page.goto(f"{server.base_url}/#/axis/{axis_id}")
        await expect(page.get_by_test_id("plot-position")).to_be_visible()

        # At the axis's own STOP: in the same "stop" group as the device's stop command,
        # with the gentler stops the descriptor offers.
        group = page.locator('.cmd-group[data-group="stop"]')
        effect = group.get_by_test_id("stop-effect")
        await expect(effect).to_contain_text(summary)
        for label in gentler_labels:
            await expect(effect).to_contain_text(label)
        await expect(group.get_by_test_id("cmd-stop")).to_be_visible()
        await expect(effect).to_be_visible()

        # At the top bar's STOP (every axis): the effect of each device family present,
        # shown on a laptop-wide screen and in the button's tooltip.
        await expect(page.get_by_test_id("stop-effect-all")).to_contain_text(summary)
        await expect(page.get_by_test_id("stop-effect-all")).to_be_visible()
        title = await page.get_by_test_id("stop-all").get_attribute("title")
        assert title is not None and summary in title

        if device == "slap2":
            # On a phone the top bar has no room for the text (it hides below 1100 px):
            # the axis's STOP and its effect are on the first screen of the axis page.
            phone = await browser.new_page(viewport={"width": 390, "height": 844})
            phone.on("pageerror", lambda exc: errors.append(str(exc)))
            await phone.goto(f"{server.base_url}/#/axis/{axis_id}")
            group = phone.locator('.cmd-group[data-group="stop"]')
            await expect(group.get_by_test_id("stop-effect")).to_contain_text(summary)
            await expect(phone.get_by_test_id("stop-all")).to_be_in_viewport()
            await expect(group.get_by_test_id("cmd-stop")).to_be_in_viewport()
            await expect(group.get_by_test_id("stop-effect")).to_be_in_viewport()
            ARTIFACTS.mkdir(parents=True, exist_ok=True)
            await phone.screenshot(path=str(ARTIFACTS / "stop-effect-phone.png"))
            await phone.close()
        assert not errors, f"JavaScript errors: {errors}"
        await page.close()


# --- item 10: Esc in a dialog closes the dialog only ----------------------------------


class StopEvents:
    """The hub's ``STOP`` events (one per axis a STOP reached), as a websocket sees them."""

    def __init__(self) -> None:
        self.axes: list[str] = []
        self.changed = asyncio.Event()

    async def follow(self, server: LiveServer, ready: asyncio.Event) -> None:
        async with websockets.connect(server.ws_url, origin=server.base_url) as ws:
            hello = json.loads(await ws.recv())
            assert hello["type"] == "hello"
            ready.set()
            async for raw in ws:
                message = json.loads(raw)
                # The STOP button's event per axis: "STOP" or "STOP: <sent>: <outcome>"
                # (not "STOP (server start-up)", "STOP sent", "STOP not delivered").
                text = message.get("message", "")
                if message.get("type") == "event" and (text == "STOP" or text.startswith("STOP: ")):
                    self.axes.append(message["axis"])
                    self.changed.set()

    async def wait_for(self, count: int, timeout_s: float = 10) -> None:
        async with asyncio.timeout(timeout_s):
            while len(self.axes) < count:
                self.changed.clear()
                await self.changed.wait()


async def test_escape_in_a_dialog_closes_it_and_sends_no_stop(
    dashboard: tuple[Page, LiveServer],
) -> None:
    page, server = dashboard
    stops = StopEvents()
    ready = asyncio.Event()
    follower = asyncio.create_task(stops.follow(server, ready))
    try:
        await asyncio.wait_for(ready.wait(), 10)
        # Events from before the websocket connected arrive in its snapshot: none is a STOP.
        assert stops.axes == []

        await page.get_by_test_id("axis-link-line-1").click()
        await page.get_by_test_id("cmd-velocity_mode").click()
        for _ in range(250):
            if server.bus.module(1).rss & VM:
                break
            await asyncio.sleep(0.02)
        assert server.bus.module(1).rss & VM, "velocity mode did not start"

        # A confirmation dialog of the app (Save to EEPROM asks first).
        await page.get_by_test_id("cmd-save_eeprom").click()
        dialog = page.get_by_test_id("confirm-dialog")
        await expect(dialog).to_be_visible()
        await page.keyboard.press("Escape")
        await expect(dialog).to_have_count(0)
        await expect(page.get_by_test_id("stop-note")).to_have_text("")

        # Esc with no dialog open: the global STOP, one STOP event per axis.
        await page.keyboard.press("Escape")
        await expect(page.get_by_test_id("stop-note")).to_have_text("STOPPED (Esc)")
        await stops.wait_for(2)
        # STOP from velocity mode holds the shaft in pm where it is.
        for _ in range(250):
            if server.bus.module(1).rss & 0b1100 == PM:
                break
            await asyncio.sleep(0.02)
        assert server.bus.module(1).rss & 0b1100 == PM, "Esc did not stop and hold the axis"
        # Had the Esc in the dialog sent a STOP, its request (sent first) would have
        # given two more events by the time the second one was answered.
        assert sorted(stops.axes) == ["line-0", "line-1"], stops.axes
    finally:
        follower.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await follower


# --- item 5: a bad run is not shown as good --------------------------------------------


async def test_a_run_the_server_judges_bad_has_no_check_mark_and_shows_why(
    dashboard: tuple[Page, LiveServer],
) -> None:
    page, server = dashboard
    # PWM 1 does not overcome the simulated motor's friction: the server says bad. First,
    # while the axis rests at 0, far from its switches.
    bad = await finished_run(
        server, "line-1", await start(server, "line-1", kind="pwm_step", pwm=1, duration_s=0.6)
    )
    assert bad["status"] == "complete", bad
    quality = bad["quality"]
    assert quality["status"] == "bad", quality
    assert quality["reasons"][0]["code"] == "did_not_move", quality
    # The reference: a short PWM step that turns the motor, made the baseline.
    good = await finished_run(
        server, "line-1", await start(server, "line-1", kind="pwm_step", pwm=30, duration_s=0.3)
    )
    assert good["status"] == "complete", good
    # A baseline that is not bad itself: the colouring is on, only the bad run is spared.
    assert good["quality"]["status"] != "bad", good["quality"]
    response = await server.client.post(f"/api/bench/runs/{good['id']}/baseline")
    assert response.is_success, response.text

    await page.get_by_test_id("axis-link-line-1").click()
    await page.get_by_test_id("bench-toggle").click()
    status = page.get_by_test_id(f"bench-run-status-{bad['id']}")
    await expect(status).to_have_attribute("data-quality", "bad")
    await expect(status).not_to_have_text("✓")
    await expect(status).not_to_have_class("run-status ok")
    reasons = page.get_by_test_id(f"bench-run-reasons-{bad['id']}")
    for reason in quality["reasons"]:
        await expect(reasons).to_contain_text(reason["message"])

    # The good run next to it keeps its own verdict (✓ only if the server said good).
    good_status = page.get_by_test_id(f"bench-run-status-{good['id']}")
    await expect(good_status).to_have_attribute("data-quality", good["quality"]["status"])

    # Not coloured better or worse than the baseline; untrusted metrics say why.
    row = page.get_by_test_id(f"bench-run-row-{bad['id']}")
    await expect(row.locator("td.c-metric")).not_to_have_count(0)
    assert await row.locator("td.better, td.worse").count() == 0
    for cell in await row.locator("td.untrusted").all():
        why = await cell.get_attribute("data-untrusted")
        assert why in quality["untrusted"].values(), (why, quality["untrusted"])


async def test_an_imported_bad_run_is_not_coloured_against_the_baseline(
    dashboard: tuple[Page, LiveServer],
) -> None:
    """A run exported by a server that judged it bad keeps that verdict on import, and
    its metrics are not coloured against the baseline; the same metrics in a run judged
    good are (the control: the colouring is there to be seen)."""
    page, server = dashboard
    run = await finished_run(
        server, "line-1", await start(server, "line-1", kind="move", distance=800)
    )
    assert run["status"] == "complete", run
    response = await server.client.post(f"/api/bench/runs/{run['id']}/baseline")
    assert response.is_success, response.text
    meta = (await server.client.get(f"/api/bench/runs/{run['id']}/run.json")).json()
    csv_text = (await server.client.get(f"/api/bench/runs/{run['id']}/samples.csv")).text
    assert meta["metrics"]["peak_following_error"] is not None, meta["metrics"]
    # Far off the baseline's following error, whatever it measured. A whole number,
    # because the page writes a number as JavaScript prints it (228.0 -> "228").
    worse = {
        **meta["metrics"],
        "peak_following_error": int(10 * abs(meta["metrics"]["peak_following_error"])) + 100,
    }
    reason = {"code": "did_not_move", "message": "the axis moved 0 of 800 counts"}
    imported: dict[str, str] = {}
    for verdict, quality in (
        ("bad", {"status": "bad", "reasons": [reason], "untrusted": {}}),
        ("good", {"status": "good", "reasons": [], "untrusted": {}}),
    ):
        response = await server.client.post(
            "/api/axes/line-1/bench/runs/import",
            json={
                "meta": {**meta, "baseline": False, "metrics": worse, "quality": quality},
                "csv": csv_text,
            },
        )
        assert response.is_success, response.text
        imported[verdict] = response.json()["id"]
        stored = (await server.client.get(f"/api/bench/runs/{imported[verdict]}")).json()
        assert stored["quality"]["status"] == verdict, stored["quality"]

    await page.get_by_test_id("axis-link-line-1").click()
    await page.get_by_test_id("bench-toggle").click()
    bad_id, good_id = imported["bad"], imported["good"]
    await expect(page.get_by_test_id(f"bench-run-status-{bad_id}")).to_have_attribute(
        "data-quality", "bad"
    )
    await expect(page.get_by_test_id(f"bench-run-status-{bad_id}")).not_to_have_text("✓")
    await expect(page.get_by_test_id(f"bench-run-reasons-{bad_id}")).to_contain_text(
        reason["message"]
    )
    await expect(page.get_by_test_id(f"bench-run-status-{good_id}")).to_have_text("✓")
    # The control: judged good, the same number is coloured worse than the baseline.
    await expect(page.get_by_test_id(f"bench-metric-{good_id}-peak_following_error")).to_have_class(
        "c-metric num worse"
    )
    bad_cell = page.get_by_test_id(f"bench-metric-{bad_id}-peak_following_error")
    await expect(bad_cell).to_have_attribute("data-value", str(worse["peak_following_error"]))
    await expect(bad_cell).to_have_class("c-metric num")
