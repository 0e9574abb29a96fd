"""Audit of commands and parameter writes, the audit API, and the hook to the control lock.

Against simulated SLAP2 modules on a real pty, in local mode (the same code paths as
exposed mode, with the local principal) and exposed mode for the per-user view.
"""

from __future__ import annotations

import asyncio
import csv
import io
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi import FastAPI, HTTPException

from servotune.api.app import AppConfig, create_app
from servotune.auth.audit import AuditLog, AuditQuery, scrub
from servotune.auth.principal import Principal
from servotune.config import LinkSpec
from tests.support.auth import client, exposed_config, login, make_accounts, running
from tests.support.servers import use_csrf_token
from tests.support.sim_lines import running_simulator
from tests.support.waiting import wait_for


@dataclass
class Rig:
    app: FastAPI
    http: httpx.AsyncClient
    bus: Any


@pytest.fixture
async def rig(tmp_path: Path) -> AsyncIterator[Rig]:
    with running_simulator([0, 1], tmp_path) as (sim, bus):
        spec = LinkSpec("slap2", sim.path, "line", sim.baud, [0, 1], 512)
        app = create_app(
            AppConfig(links=[spec], data_dir=tmp_path / "data", web_dir=tmp_path / "no-web")
        )
        async with running(app), client(app, base="http://localhost") as http:
            hub = app.state.hub
            await wait_for(lambda: hub.axis_state("line-0") is not None, 10, "telemetry")
            await use_csrf_token(http)
            yield Rig(app, http, bus)


def entries(app: FastAPI, **filters: Any) -> list[dict[str, Any]]:
    audit: AuditLog = app.state.audit
    audit.flush()
    return audit.query(AuditQuery(**filters))


async def test_parameter_write_is_audited_with_before_and_after(rig: Rig) -> None:
    response = await rig.http.patch("/api/axes/line-0/params", json={"kp": 55})
    assert response.status_code == 200, response.text
    row = entries(rig.app, action="/params")[0]
    assert (row["who"], row["axis"], row["result"]) == ("local", "line-0", "ok")
    assert row["before"] == '{"kp": 40}'
    assert '"kp": 55' in row["after"]
    assert row["address"] == "127.0.0.1"
    # A refused write is audited with its answer, and nothing reached the module.
    response = await rig.http.patch("/api/axes/line-0/params", json={"kp": 99999})
    assert response.status_code == 422
    row = entries(rig.app, action="/params")[0]
    assert row["result"].startswith("http 422") and "kp" in row["result"]
    assert row["after"] is None
    assert rig.bus.module(0).settings["kp"] == 55


async def test_commands_are_audited_with_their_result(rig: Rig) -> None:
    response = await rig.http.post("/api/axes/line-0/commands", json={"command": "position_mode"})
    assert response.status_code == 200, response.text
    response = await rig.http.post("/api/axes/line-0/commands", json={"command": "stop"})
    assert response.status_code == 200
    rows = entries(rig.app, action="/commands")
    assert [r["detail"] for r in rows[:2]] == ["stop", "position_mode"]
    assert all(r["result"] == "ok" and r["axis"] == "line-0" for r in rows[:2])
    assert '"sent"' in rows[0]["after"]
    assert (await rig.http.post("/api/stop")).status_code == 200
    assert entries(rig.app, action="POST /api/stop")[0]["result"] == "ok"


class FakeControl:
    """Stands in for the control module's lock: records the calls, refuses axis 1."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, str | None, str]] = []

    async def require(self, axis_id: str, client_id: str | None, principal: Principal) -> None:
        self.calls.append((axis_id, client_id, principal.user))
        if axis_id == "line-1":
            raise HTTPException(423, "line-1 is controlled by olga")


async def test_lock_is_asked_for_changes_never_for_stop(rig: Rig) -> None:
    control = FakeControl()
    rig.app.state.control = control
    headers = {"X-Servotune-Client": "tab-7"}
    http = rig.http
    ok = await http.patch("/api/axes/line-0/params", json={"kd": 81}, headers=headers)
    assert ok.status_code == 200
    assert control.calls == [("line-0", "tab-7", "local")]
    before = rig.bus.module(1).settings["kd"]
    locked = await http.patch("/api/axes/line-1/params", json={"kd": 81}, headers=headers)
    assert locked.status_code == 423 and "olga" in locked.json()["detail"]
    await asyncio.sleep(0.2)
    assert rig.bus.module(1).settings["kd"] == before  # nothing was sent
    control.calls.clear()
    # STOP (global and per axis) and reads never ask the lock.
    assert (await http.post("/api/stop", headers=headers)).status_code == 200
    stop = await http.post("/api/axes/line-1/commands", json={"command": "stop"}, headers=headers)
    assert stop.status_code == 200
    assert (await http.get("/api/axes/line-1/params")).status_code == 200
    # Saving a parameter set does not change the axis; restoring one does.
    saved = await http.post("/api/axes/line-1/param-sets", json={"name": "a"}, headers=headers)
    assert saved.status_code == 201
    assert control.calls == []
    move = await http.post(
        "/api/axes/line-1/commands", json={"command": "position_mode"}, headers=headers
    )
    assert move.status_code == 423
    restore = await http.post("/api/axes/line-1/param-sets/a/restore", headers=headers)
    assert restore.status_code == 423
    assert [c[0] for c in control.calls] == ["line-1", "line-1"]
    locked_rows = entries(rig.app, result="http 423")
    assert locked_rows[0]["result"] == "http 423: line-1 is controlled by olga"
    assert locked_rows[1]["detail"] == "position_mode"


async def test_audit_page_api_filters_and_csv(tmp_path: Path) -> None:
    make_accounts(tmp_path)
    app = create_app(exposed_config(tmp_path))
    async with running(app), client(app) as admin, client(app) as victor:
        await login(admin, "alice")
        await login(victor, "victor")
        assert (await victor.post("/api/stop")).status_code == 200
        assert (await victor.patch("/api/axes/x-0/params", json={"kp": 1})).status_code == 403
        mine = (await victor.get("/api/audit")).json()
        assert mine and {r["who"] for r in mine} == {"victor"}
        # A viewer asking for someone else's entries still gets only their own.
        assert {r["who"] for r in (await victor.get("/api/audit?who=alice")).json()} <= {"victor"}
        everyone = (await admin.get("/api/audit")).json()
        assert {"alice", "victor"} <= {r["who"] for r in everyone}
        refused = (await admin.get("/api/audit?result=refused&who=victor")).json()
        assert refused and all(r["result"] == "refused" for r in refused)
        response = await admin.get("/api/audit.csv?who=victor")
        assert response.headers["content-type"].startswith("text/csv")
        assert "attachment" in response.headers["content-disposition"]
        rows = list(csv.DictReader(io.StringIO(response.text)))
        assert rows and {r["who"] for r in rows} == {"victor"}
        assert rows[0]["time_utc"].endswith("Z")
        # The limit names its range; one entry is what limit=1 gives.
        assert len((await admin.get("/api/audit?limit=1")).json()) == 1
        for bad in ("0", "10001"):
            response = await admin.get(f"/api/audit.csv?limit={bad}")
            assert response.status_code == 422 and "limit" in response.text


def test_scrub_and_csv_formula_cells(tmp_path: Path) -> None:
    assert scrub({"password": "p", "nested": [{"api_token": "t", "kp": 1}]}) == {
        "password": "<redacted>",
        "nested": [{"api_token": "<redacted>", "kp": 1}],
    }
    audit = AuditLog(tmp_path / "a.db")
    try:
        audit.record(who="x", action="console", detail='=HYPERLINK("http://evil")')
        audit.flush()
        text = audit.csv(AuditQuery())
    finally:
        audit.close()
    row = next(csv.DictReader(io.StringIO(text)))
    assert row["detail"].startswith("'=")  # a spreadsheet shows it, never runs it


# --- anonymous refusals: aggregated, with a retention ---------------------------------


async def test_refused_anonymous_requests_are_aggregated(tmp_path: Path) -> None:
    """Finding 7: 400 refused requests wrote 400 rows. Per address and result, one row
    and one summary of the rest per window now."""
    make_accounts(tmp_path)
    app = create_app(exposed_config(tmp_path))
    async with running(app), client(app) as http:
        for i in range(200):
            await http.post("/api/stop", headers={"X-Forwarded-For": "203.0.113.7"})
            await http.get(f"/api/axes?n={i}", headers={"Host": "evil.example"})
        await http.post("/api/stop", headers={"X-Forwarded-For": "203.0.113.8"})
        app.state.audit.flush()
        rows = app.state.audit.query(AuditQuery(who="?"))
        # 2 results x 2 addresses at most, no summary before the window has passed.
        assert 2 <= len(rows) <= 4, rows
    # Closing writes the pending summaries: nothing is lost, it is counted.
    audit = AuditLog(tmp_path / "auth.db")
    rows = audit.query(AuditQuery(who="?"))
    audit.close()
    summaries = [r for r in rows if r["action"] == "refusals summarised"]
    counted = sum(int(r["detail"].split()[0]) for r in summaries)
    assert counted + len(rows) - len(summaries) == 401, rows


def test_anonymous_windows_and_retention(tmp_path: Path) -> None:
    import sqlite3
    import time

    now = [0.0]
    path = tmp_path / "auth.db"
    audit = AuditLog(path, anonymous_window_s=60.0, clock=lambda: now[0])
    for _ in range(5):
        audit.record(who="?", action="POST /api/stop", address="a", result="refused")
    now[0] = 61.0  # the window passed: the next one writes the summary first
    audit.record(who="?", action="POST /api/stop", address="a", result="refused")
    audit.record(who="olga", action="POST /api/stop", address="a", result="refused")
    audit.flush()
    rows = audit.query(AuditQuery())
    assert [r["action"] for r in reversed(rows)] == [
        "POST /api/stop",
        "refusals summarised",
        "POST /api/stop",
        "POST /api/stop",
    ]
    assert rows[2]["detail"].startswith("4 more like this from a")
    audit.close()
    # Rows of anonymous callers older than the retention go; everyone else's stay.
    db = sqlite3.connect(path)
    with db:
        db.execute("UPDATE audit SET t_s = ?", (time.time() - 31 * 86400,))
    db.close()
    audit = AuditLog(path, anonymous_retention_days=30)
    audit.flush()
    rows = audit.query(AuditQuery())
    audit.close()
    assert [r["who"] for r in rows] == ["olga"]
