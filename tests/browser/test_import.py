"""Importing a run from the bench page (its .json and .csv picked in the browser).

The page sends the run as multipart, outside the JSON ``request`` helper: it must carry
the CSRF token like every other state-changing call (without it the server answers 403
and nothing is imported).
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest
from playwright.async_api import Page, expect

from servotune.bench.metrics import DEFINITIONS
from tests.support.servers import LiveServer

pytestmark = pytest.mark.browser


async def _finished_run(server: LiveServer, axis_id: str) -> str:
    response = await server.client.post(
        f"/api/axes/{axis_id}/bench/runs",
        json={"kind": "move", "distance": 800, "duration_s": 1.0, "note": "to export"},
    )
    assert response.status_code == 202, response.text
    run_id: str = response.json()["id"]
    for _ in range(300):
        run = (await server.client.get(f"/api/bench/runs/{run_id}")).json()
        if run["status"] != "recording":
            return run_id
        await asyncio.sleep(0.1)
    raise AssertionError(f"run {run_id} still recording")


async def test_a_run_exported_and_imported_from_the_page_is_listed(
    dashboard: tuple[Page, LiveServer],
    tmp_path: Path,
) -> None:
    page, server = dashboard
    run_id = await _finished_run(server, "line-0")
    json_path, csv_path = tmp_path / f"run-{run_id}.json", tmp_path / f"run-{run_id}.csv"
    json_path.write_bytes((await server.client.get(f"/api/bench/runs/{run_id}/run.json")).content)
    csv_path.write_bytes((await server.client.get(f"/api/bench/runs/{run_id}/samples.csv")).content)

    await page.get_by_test_id("axis-link-line-0").click()
    await page.get_by_test_id("bench-toggle").click()
    await expect(page.get_by_test_id(f"bench-run-row-{run_id}")).to_be_visible(timeout=15_000)
    rows = page.locator("tr.run-row")
    before = await rows.count()
    # a metric's header explains it in the server's words (bench.metrics.DEFINITIONS,
    # served with the bench info), not a copy kept in the web client
    settle = page.locator('th[data-metric="settling_time_s"]').first
    sentence = DEFINITIONS["settling_time_s"].replace("None", "—")
    assert sentence in (await settle.get_attribute("title") or "")
    # one file after the other, as a user picks them
    await page.get_by_test_id("bench-import-file").set_input_files(str(json_path))
    await expect(page.get_by_test_id("bench-import-status")).to_contain_text("now pick")
    await page.get_by_test_id("bench-import-file").set_input_files(str(csv_path))
    status = page.get_by_test_id("bench-import-status")
    await expect(status).to_contain_text("✓ imported as", timeout=15_000)
    await expect(rows).to_have_count(before + 1, timeout=15_000)
    imported = [
        r
        for r in (await server.client.get("/api/axes/line-0/bench/runs")).json()
        if r["id"] != run_id
    ]
    assert [r.get("imported_from") for r in imported] == [run_id]
    # the imported run is selected for the overlay, like a run that just finished
    await expect(page.get_by_test_id(f"bench-run-select-{imported[0]['id']}")).to_be_checked()
