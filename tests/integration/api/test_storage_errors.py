"""An unwritable database is told, never silent: clear JSON errors
(507), an event and a ``storage_status`` message, the server starts without a
traceback, and settings applied meanwhile are saved once the database works again."""

from __future__ import annotations

import asyncio
import json
import logging
import sqlite3
from pathlib import Path
from typing import Any

import pytest
import websockets
from websockets.typing import Origin

from servotune.config import LinkSpec
from servotune.storage import Storage
from tests.support.servers import serve
from tests.support.sim_lines import running_simulator


def _break(storage: Storage) -> sqlite3.Connection:
    """Make every later write fail the way a read-only database does."""
    writable = storage._db
    storage._db = sqlite3.connect(
        f"file:{storage.path}?mode=ro", uri=True, check_same_thread=False, isolation_level=None
    )
    return writable


async def test_an_unwritable_database_at_start_is_told_and_every_write_answers_507(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    blocker = tmp_path / "not-a-directory"
    blocker.write_text("a file where the data directory should be")
    with running_simulator([0, 1], tmp_path, link_path=str(tmp_path / "tty")) as (sim, _):
        spec = LinkSpec("slap2", sim.path, "line", sim.baud, [0, 1], 512)
        with caplog.at_level(logging.WARNING):
            async with serve(spec, blocker / "data") as (_, client, ws_url):
                status = (await client.get("/api/storage")).json()
                assert status["writable"] is False and "cannot be written" in status["message"]
                async with websockets.connect(
                    ws_url, origin=Origin(ws_url.replace("ws://", "http://").removesuffix("/ws"))
                ) as ws:
                    messages = [json.loads(await ws.recv()) for _ in range(12)]
                assert any(
                    m["type"] == "event" and "settings are not being saved" in m["message"]
                    for m in messages
                )
                limits = {"max_distance_counts": 1000, "max_velocity": 5000, "max_pwm": 40}
                response = await client.put("/api/axes/line-0/bench/limits", json=limits)
                assert response.status_code == 507, response.text
                assert "cannot be written" in response.json()["detail"]
                response = await client.post(
                    "/api/axes/line-0/bench/runs", json={"kind": "move", "distance": 500}
                )
                assert response.status_code == 507, response.text
                response = await client.post(
                    "/api/axes/line-0/param-sets", json={"name": "before", "note": ""}
                )
                assert response.status_code == 507, response.text
                # A PATCH still reaches the device, and says it was not saved.
                response = await client.patch("/api/axes/line-0/params", json={"kp": 55})
                assert response.status_code == 200 and response.json()["kp"] == 55
    assert not [r for r in caplog.records if r.exc_info], "a traceback was logged"


async def test_settings_not_saved_are_reported_kept_and_saved_when_it_works_again(
    tmp_path: Path,
) -> None:
    with running_simulator([0, 1], tmp_path, link_path=str(tmp_path / "tty")) as (sim, _):
        spec = LinkSpec("slap2", sim.path, "line", sim.baud, [0, 1], 512)
        async with serve(spec, tmp_path / "data") as (app, client, ws_url):
            storage: Storage = app.state.storage
            async with websockets.connect(
                ws_url, origin=Origin(ws_url.replace("ws://", "http://").removesuffix("/ws"))
            ) as ws:
                writable = _break(storage)
                response = await client.patch("/api/axes/line-0/params", json={"kp": 61})
                assert response.status_code == 200
                seen: list[dict[str, Any]] = []
                while not any(m["type"] == "storage_status" for m in seen):
                    seen.append(json.loads(await asyncio.wait_for(ws.recv(), 5)))
                status = next(m for m in seen if m["type"] == "storage_status")
                assert status["writable"] is False and "cannot be written" in status["message"]
                assert any(
                    m["type"] == "event"
                    and m["level"] == "error"
                    and "settings are not being saved" in m["message"]
                    and "kp" in m["message"]
                    for m in seen
                )
                assert (await client.get("/api/storage")).json()["writable"] is False
                response = await client.post(
                    "/api/axes/line-0/bench/runs", json={"kind": "move", "distance": 500}
                )
                assert response.status_code == 507
                # The database works again: the next save carries what was missed.
                storage._db.close()
                storage._db = writable
                response = await client.patch("/api/axes/line-0/params", json={"kd": 90})
                assert response.status_code == 200
                seen = []
                while not any(m["type"] == "storage_status" for m in seen):
                    seen.append(json.loads(await asyncio.wait_for(ws.recv(), 5)))
                assert next(m for m in seen if m["type"] == "storage_status")["writable"]
            key = "slap2/line/0"
            saved = await asyncio.to_thread(storage.last_params, key)
            assert saved["kp"] == 61 and saved["kd"] == 90
            assert storage.unsaved == {}
