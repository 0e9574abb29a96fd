"""Export and import of bench runs: complete validation (422 naming the field), finite
numbers everywhere, body limits (413), multipart for big runs, stored garbage readable
(nothing holds a STOP back, errors are told)."""

from __future__ import annotations

import asyncio
import functools
import json
import os
import sqlite3
from pathlib import Path
from typing import Any

import pytest

from servotune.bench.files import (
    MAX_IMPORT_BYTES,
    MAX_IMPORT_JSON_BYTES,
    needs_rejudging,
    rejudge_in_process,
)
from servotune.bench.quality import SAMPLING_RULE
from servotune.storage import Storage, StorageError
from tests.support.bench import finished_run, start
from tests.support.servers import LiveServer, live_server
from tests.support.sim_lines import running_simulator


async def _exported(api: LiveServer) -> tuple[dict[str, Any], dict[str, Any], str]:
    run = await finished_run(api, "line-0", await start(api, "line-0", kind="move", distance=800))
    meta = (await api.client.get(f"/api/bench/runs/{run['id']}/run.json")).json()
    csv_text = (await api.client.get(f"/api/bench/runs/{run['id']}/samples.csv")).text
    return run, meta, csv_text


async def _import(api: LiveServer, meta: Any, csv_text: str, axis: str = "line-1") -> Any:
    return await api.client.post(
        f"/api/axes/{axis}/bench/runs/import", json={"meta": meta, "csv": csv_text}
    )


async def test_bad_imports_answer_422_naming_the_field_and_store_nothing(
    api: LiveServer,
) -> None:
    run, meta, csv_text = await _exported(api)
    assert run["quality"]["status"] in ("good", "doubtful", "bad")
    cases: list[tuple[dict[str, Any], str]] = [
        ({"created_s": "abc"}, "meta.created_s"),
        ({"created_s": {}}, "meta.created_s"),
        ({"created_s": [1]}, "meta.created_s"),
        ({"created_s": "nan"}, "meta.created_s"),
        ({"status": "recording"}, "meta.status"),
        ({"device": "z1100"}, "meta.device"),
        ({"params": {"kp": "40"}}, "meta.params.kp"),
        ({"plan": {**meta["plan"], "y0": "1"}}, "meta.plan.y0"),
        ({"columns": ["position", "t_s"]}, "meta.columns"),
        ({"surprise": 1}, "meta.surprise"),
    ]
    for change, field in cases:
        response = await _import(api, {**meta, **change}, csv_text)
        assert response.status_code == 422, (change, response.text)
        assert response.json()["field"] == field, (change, response.json())
        assert field in response.json()["detail"]
    # Non-finite numbers in the JSON text itself (Python's json accepts these tokens).
    for token in ("NaN", "Infinity", "1e400"):
        text = json.dumps({"meta": meta, "csv": csv_text}).replace(
            f'"created_s": {json.dumps(meta["created_s"])}', f'"created_s": {token}'
        )
        response = await api.client.post(
            "/api/axes/line-1/bench/runs/import",
            content=text,
            headers={"content-type": "application/json"},
        )
        assert response.status_code == 422, (token, response.text)
        assert response.json()["field"] == "meta.created_s"
    lines = csv_text.splitlines()
    t_s, _, *rest = lines[2].split(",")
    for bad_line, what in (
        # The second column replaced by field, not by text: its value may also occur
        # inside the t_s column.
        (",".join([t_s, "abc", *rest]), "not a number"),
        (",".join([t_s, "inf", *rest]), "not finite"),
        (lines[2] + ",1", "fields"),
    ):
        bad_csv = "\n".join([*lines[:2], bad_line, *lines[3:]]) + "\n"
        response = await _import(api, meta, bad_csv)
        assert response.status_code == 422, (what, response.text)
        assert response.json()["field"] == "csv" and "line 3" in response.json()["detail"]
        assert what in response.json()["detail"]
    swapped = "\n".join([lines[0], lines[2], lines[1], *lines[3:]]) + "\n"
    response = await _import(api, meta, swapped)
    assert response.status_code == 422 and "before the line above" in response.json()["detail"]
    assert (await api.client.get("/api/axes/line-1/bench/runs")).json() == []


async def test_each_import_runs_in_a_fresh_process_forked_with_the_import_code_loaded(
    api: LiveServer,
) -> None:
    """The isolation of an import (``bench.files``): a process of its own, a new one
    per import, whose memory goes with it. That process is a fork of a fork server
    that has ``bench.files`` imported, so a refused file costs a fork, not an
    interpreter start with its imports (docs/bench.md). A process that dies under an
    import is a 507, and the next import gets a new process."""
    bench = api.app.state.bench
    # A builtin as the call: unpickling it imports nothing into the process.
    probe = functools.partial(
        eval,
        "(__import__('os').getpid(), 'servotune.bench.files' in __import__('sys').modules)",
    )
    first_pid, first_loaded = await bench._in_import_process(probe)
    second_pid, second_loaded = await bench._in_import_process(probe)
    assert first_pid != os.getpid() and second_pid not in (os.getpid(), first_pid)
    assert first_loaded and second_loaded
    with pytest.raises(StorageError, match="ended before it answered"):
        await bench._in_import_process(functools.partial(os._exit, 1))
    third_pid, _ = await bench._in_import_process(probe)
    assert third_pid not in (os.getpid(), first_pid, second_pid)


async def test_an_import_whose_process_died_midway_leaves_no_run(
    api: LiveServer, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The import process chose no id of its own: the server gives it one, so that
    when the process dies after it stored part of the run (the test above: a 507),
    the server deletes that part. The death is played here by a stand-in that stores
    the run's start, as the import process does first, and then fails as a dead
    process does."""
    _, meta, csv_text = await _exported(api)
    bench = api.app.state.bench
    storage: Storage = bench._storage
    axis_key = api.app.state.hub.entry("line-1").storage_key

    async def dies_after_the_first_write(call: functools.partial[Any]) -> Any:
        run_id = call.args[-1]
        storage.create_run(run_id, axis_key, "line-1", 1.0, {"test": {}})
        assert [r["id"] for r in storage.list_runs(axis_key)] == [run_id]
        raise StorageError("not saved: the import process ended before it answered")

    monkeypatch.setattr(bench, "_in_import_process", dies_after_the_first_write)
    response = await _import(api, meta, csv_text)
    assert response.status_code == 507, response.text
    assert "ended before it answered" in response.json()["detail"]
    assert (await api.client.get("/api/axes/line-1/bench/runs")).json() == []


async def test_multipart_import_round_trip_and_streamed_exports(api: LiveServer) -> None:
    run, meta, csv_text = await _exported(api)
    response = await api.client.post(
        "/api/axes/line-1/bench/runs/import",
        files={
            "meta": ("run.json", json.dumps(meta), "application/json"),
            "csv": ("samples.csv", csv_text, "text/csv"),
        },
    )
    assert response.status_code == 201, response.text
    imported = (await api.client.get(f"/api/bench/runs/{response.json()['id']}")).json()
    assert imported["samples"] == run["samples"]
    for key in ("metrics", "quality", "plan", "t0_s", "return"):
        assert imported[key] == run[key], key
    assert imported["status"] == run["status"] and imported["imported_from"] == run["id"]
    again = (await api.client.get(f"/api/bench/runs/{imported['id']}/samples.csv")).text
    assert again == csv_text


async def test_bodies_beyond_the_limits_answer_413(api: LiveServer) -> None:
    response = await api.client.post(
        "/api/axes/line-1/bench/runs/import",
        content=b"x" * (MAX_IMPORT_JSON_BYTES + 1),
        headers={"content-type": "application/json"},
    )
    assert response.status_code == 413
    assert "multipart" in response.json()["detail"]

    async def chunks() -> Any:  # no Content-Length: the stream itself is cut off
        for _ in range(MAX_IMPORT_JSON_BYTES // (1 << 20) + 1):
            yield b" " * (1 << 20)

    response = await api.client.post(
        "/api/axes/line-1/bench/runs/import",
        content=chunks(),
        headers={"content-type": "application/json"},
    )
    assert response.status_code == 413
    # A declared length beyond the multipart limit is refused before the body is read
    # (raw socket: an HTTP client will not send a length it does not deliver).
    host, port = api.base_url.removeprefix("http://").split(":")
    reader, writer = await asyncio.open_connection(host, int(port))
    writer.write(
        (
            "POST /api/axes/line-1/bench/runs/import HTTP/1.1\r\n"
            f"Host: {host}\r\nContent-Type: multipart/form-data; boundary=x\r\n"
            f"X-CSRF-Token: {api.client.headers['X-CSRF-Token']}\r\n"
            f"Content-Length: {MAX_IMPORT_BYTES + 1}\r\n\r\n"
        ).encode()
    )
    await writer.drain()
    status_line = await asyncio.wait_for(reader.readline(), 10)
    writer.close()
    assert b" 413 " in status_line, status_line
    spec = (await api.client.get("/openapi.json")).json()
    operation = spec["paths"]["/api/axes/{axis_id}/bench/runs/import"]["post"]
    assert "64 MiB" in operation["requestBody"]["description"]
    assert "413" in operation["responses"]
    assert set(operation["requestBody"]["content"]) == {"application/json", "multipart/form-data"}


async def test_non_finite_numbers_stored_earlier_never_make_a_run_unreadable(
    tmp_path: Path,
) -> None:
    data = tmp_path / "data"
    storage = Storage(data / "servotune.db")
    storage.create_run("legacy", "slap2/line/0", "line-0", 1.0, {"test": {}, "metrics": None})
    storage.close()
    # What an older version could write: NaN and 1e400 in the JSON text, inf in REAL.
    db = sqlite3.connect(data / "servotune.db")
    db.execute(
        "UPDATE runs SET created_s = ?, status = 'complete', meta = ? WHERE id = 'legacy'",
        (
            float("inf"),
            '{"test": {}, "columns": ["t_s", "position"], "flags": ["inpos"], '
            '"metrics": {"overshoot_pct": NaN, "step": 1e400}}',
        ),
    )
    db.execute(
        "INSERT INTO run_chunks(run_id, seq, samples) VALUES ('legacy', 0, ?)",
        ("[[0.0, NaN, [0]], [0.1, 1e400, [1]], [0.2, 3.5, [0]]]",),
    )
    db.commit()
    db.close()
    with running_simulator([0, 1], tmp_path, link_path=str(tmp_path / "tty")) as (sim, bus):
        async with live_server(sim, bus, data) as server:
            response = await server.client.get("/api/bench/runs/legacy/run.json")
            assert response.status_code == 200, response.text
            assert response.json()["metrics"] == {"overshoot_pct": None, "step": None}
            assert response.json()["created_s"] is None
            response = await server.client.get("/api/bench/runs/legacy")
            assert response.status_code == 200
            assert response.json()["samples"] == [
                [0.0, None, [0]],
                [0.1, None, [1]],
                [0.2, 3.5, [0]],
            ]
            csv_text = (await server.client.get("/api/bench/runs/legacy/samples.csv")).text
            assert csv_text.splitlines()[1:] == ["0.0,,0", "0.1,,1", "0.2,3.5,0"]


def test_the_text_path_of_the_csv_export_writes_what_the_csv_writer_writes() -> None:
    import json
    import random

    from servotune.bench.files import csv_rows, plain_chunk_csv
    from servotune.storage import dumps_strict

    rng = random.Random(3)

    def value() -> float | int | None:
        r = rng.random()
        if r < 0.1:
            return None
        if r < 0.3:
            return rng.randint(-(10**6), 10**6)
        if r < 0.5:
            return rng.choice([0.0, -0.0, 1e-5, 1e16, 123.456, -2.5e-300, 1.7976931348623157e308])
        return rng.uniform(-1e6, 1e6)

    taken = 0
    for _ in range(2000):
        columns, flags = rng.randint(1, 6), rng.randint(0, 4)
        rows = [
            [*(value() for _ in range(columns)), [rng.randint(0, 1) for _ in range(flags)]]
            for _ in range(rng.randint(1, 20))
        ]
        text = dumps_strict(rows)
        fast = plain_chunk_csv(text)
        if fast is not None:
            taken += 1
            assert fast == csv_rows(json.loads(text)), text
    assert taken > 1000
    # anything but numbers, nulls and flag lists takes the general path
    assert plain_chunk_csv('[[1.0,"a",[0]]]') is None
    assert plain_chunk_csv("[[1.0,true,[0]]]") is None
    assert plain_chunk_csv("[[1.0,[2.0,[0]]]]") is None
    assert plain_chunk_csv("[]") is None


async def test_a_run_judged_by_an_older_rule_is_judged_again_when_imported_or_stored(
    api: LiveServer, tmp_path: Path
) -> None:
    """One rule for every run on the page, wherever it was recorded. A run
    exported (or stored) by an older version keeps the metrics it was judged with: a
    peak time of 1 ms "trusted" that no 3 samples resolve. Imported, and at a server's
    start-up for the runs in its database (bench.files.rejudge_in_process), it is judged by
    today's sampling rule; a run judged by it already is left as it is."""
    run, meta, csv_text = await _exported(api)
    assert meta["quality"]["sampling_rule"] == SAMPLING_RULE
    old = json.loads(json.dumps(meta))
    del old["quality"]["sampling_rule"]
    old["metrics"]["peak_time_s"] = 0.001
    old["quality"]["untrusted"].pop("peak_time_s", None)
    response = await _import(api, old, csv_text)
    assert response.status_code == 201, response.text
    imported = (await api.client.get(f"/api/bench/runs/{response.json()['id']}")).json()
    assert imported["metrics"]["peak_time_s"] is None
    assert "needs 3" in imported["quality"]["untrusted"]["peak_time_s"]
    assert imported["quality"]["sampling_rule"] == SAMPLING_RULE
    assert imported["metrics"]["overshoot_pct"] == run["metrics"]["overshoot_pct"]

    # Stored by an older version: judged again by the start-up pass.
    storage = Storage(tmp_path / "old.db")
    rows = run["samples"]
    stored = {k: v for k, v in old.items() if k not in ("id", "axis_id", "status", "baseline")}
    storage.create_run("old", "slap2/x/0", "x-0", 1.0, stored)
    storage.append_samples("old", 0, rows)
    storage.finish_run("old", "complete", stored)
    current = json.loads(json.dumps(stored))
    current["quality"]["sampling_rule"] = SAMPLING_RULE
    storage.create_run("current", "slap2/x/0", "x-0", 2.0, current)
    storage.append_samples("current", 0, rows)
    storage.finish_run("current", "complete", current)
    storage.close()
    assert needs_rejudging({**stored, "status": "complete"})
    assert await asyncio.to_thread(rejudge_in_process, str(tmp_path / "old.db")) == 1
    storage = Storage(tmp_path / "old.db")
    try:
        judged = storage.get_run_meta("old")
        assert judged is not None and judged["metrics"]["peak_time_s"] is None
        assert judged["quality"]["sampling_rule"] == SAMPLING_RULE
        untouched = storage.get_run_meta("current")
        assert untouched is not None and untouched["metrics"]["peak_time_s"] == 0.001
    finally:
        storage.close()


async def test_a_run_the_after_check_marked_keeps_its_finding_through_export_and_import(
    api: LiveServer,
) -> None:
    """A run after which the axis was found oscillating (or its loop could not be
    verified) is exported with that finding; importing the export keeps it, and
    the quality reason that names it, instead of refusing the file."""
    _, meta, csv_text = await _exported(api)
    for key, code in (
        ("left_oscillating", "left_oscillating"),
        ("loop_unverified", "loop_unverified"),
    ):
        marked = json.loads(json.dumps(meta))
        finding = {
            "reason": "oscillation",
            "message": f"{code}: test",
            "restored": True,
            "holds": True,
        }
        marked[key] = finding
        marked["quality"]["reasons"].insert(0, {"code": code, "message": finding["message"]})
        response = await _import(api, marked, csv_text)
        assert response.status_code == 201, response.text
        imported = (await api.client.get(f"/api/bench/runs/{response.json()['id']}")).json()
        assert imported[key] == finding
        assert imported["quality"]["reasons"][0]["code"] == code
