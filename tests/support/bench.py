"""Bench runs through the API: start one, wait for it to finish."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from tests.support.servers import LiveServer


async def finished_run(server: LiveServer, axis_id: str, run_id: str) -> dict[str, Any]:
    for _ in range(400):
        runs = (await server.client.get(f"/api/axes/{axis_id}/bench/runs")).json()
        run = next(r for r in runs if r["id"] == run_id)
        if run["status"] != "recording":
            full: dict[str, Any] = (await server.client.get(f"/api/bench/runs/{run_id}")).json()
            return full
        await asyncio.sleep(0.05)
    pytest.fail(f"run {run_id} never finished")


async def start(server: LiveServer, axis_id: str, **test: Any) -> str:
    response = await server.client.post(f"/api/axes/{axis_id}/bench/runs", json=test)
    assert response.status_code == 202, response.text
    run_id: str = response.json()["id"]
    return run_id
